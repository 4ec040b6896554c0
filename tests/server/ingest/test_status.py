"""The vehicle status: refusal counts over the last minute, when they are published, and the
rate-limited log lines (the clock is the test's; real Zenoh is in ``test_zenoh_auth``)."""

from __future__ import annotations

import json
import logging

import pytest

from server.ingest.counters import NO_VEHICLE, IngestCounters
from server.ingest.status import (
    LOG_EVERY_NS,
    PUBLISH_EVERY_NS,
    WINDOW_NS,
    RefusalWindow,
    refused_of,
    status_payload,
)

S = 10**9


def _refuse(counters: IngestCounters, vid: str | None, reason: str, n: int) -> None:
    for _ in range(n):
        counters.rejected(vid, reason)


def test_refused_of_takes_the_rejected_counters_only() -> None:
    c = IngestCounters()
    c.accepted("v1")
    _refuse(c, "v1", "wrong_type", 3)
    _refuse(c, "v1", "clock_skew", 1)
    assert refused_of(c.snapshot()["v1"]) == {"wrong_type": 3, "clock_skew": 1}


def test_counts_are_those_of_the_last_minute() -> None:
    c, w = IngestCounters(), RefusalWindow()
    w.prime(c.snapshot(), 0)
    _refuse(c, "v1", "wrong_type", 5)
    assert w.update(c.snapshot(), 1 * S) == [("v1", {"wrong_type": 5})]
    _refuse(c, "v1", "wrong_type", 2)
    _refuse(c, "v1", "non_finite", 1)
    assert w.update(c.snapshot(), 30 * S) == [("v1", {"wrong_type": 7, "non_finite": 1})]
    # at 61 s the first five are older than a minute
    assert w.update(c.snapshot(), 61 * S) == [("v1", {"wrong_type": 2, "non_finite": 1})]


def test_published_every_few_seconds_while_refused_and_once_when_it_stops() -> None:
    c, w = IngestCounters(), RefusalWindow()
    w.prime(c.snapshot(), 0)
    c.accepted("ok")  # a vehicle without refusals is never told
    sent: list[int] = []
    for t_s in range(1, 130):
        if t_s <= 20:
            _refuse(c, "v1", "wrong_type", 1)
        for vid, refused in w.update(c.snapshot(), t_s * S):
            assert vid == "v1"
            sent.append(t_s)
            last = refused
    every_s = PUBLISH_EVERY_NS // S
    window_s = WINDOW_NS // S
    # every few seconds from the first refusal until the last one leaves the window ...
    assert sent[:-1] == list(range(1, 20 + window_s, every_s))
    # ... and once more, empty, when none is left
    assert sent[-1] == 20 + window_s and last == {}


def test_restored_totals_are_not_in_the_window_and_a_vehicle_without_key_is_not_told() -> None:
    c = IngestCounters()
    c.restore("v1", {"received": 9, "rejected": 9, "rejected_wrong_type": 9})
    w = RefusalWindow()
    w.prime(c.snapshot(), 100 * S)
    _refuse(c, None, "bad_key", 4)  # counted under NO_VEHICLE
    assert NO_VEHICLE in c.snapshot()
    assert w.update(c.snapshot(), 101 * S) == []
    _refuse(c, "v1", "wrong_type", 1)
    assert w.update(c.snapshot(), 102 * S) == [("v1", {"wrong_type": 1})]


def test_log_line_on_the_first_refusal_then_one_a_minute_with_the_count(
    caplog: pytest.LogCaptureFixture,
) -> None:
    c, w = IngestCounters(), RefusalWindow()
    w.prime(c.snapshot(), 0)
    caplog.set_level(logging.WARNING, logger="server.ingest.status")
    for t_s in range(1, 200):
        _refuse(c, "v1", "wrong_type", 10)
        if t_s == 50:
            _refuse(c, "v1", "non_finite", 1)
        w.update(c.snapshot(), t_s * S)
    lines = [r.getMessage() for r in caplog.records]
    type_lines = [m for m in lines if "wrong_type" in m]
    assert type_lines[0] == "vehicle v1: packets refused (wrong_type): 10"
    # then at most one a minute, with the count since the previous line
    every_s = LOG_EVERY_NS // S
    assert len(type_lines) == 1 + (199 - 1) // every_s
    assert (
        type_lines[1]
        == f"vehicle v1: {10 * every_s} more packets refused (wrong_type) since the last line"
    )
    assert [m for m in lines if "non_finite" in m] == [
        "vehicle v1: packets refused (non_finite): 1"
    ]


def test_payload_is_json_with_the_window_and_total() -> None:
    body = json.loads(status_payload("v1", {"wrong_type": 3, "bad_key": 1}, 1_700_000_000 * S))
    assert body == {
        "vehicle_id": "v1",
        "stamp_ns": 1_700_000_000 * S,
        "window_s": 60,
        "refused": {"bad_key": 1, "wrong_type": 3},
        "refused_total": 4,
    }
