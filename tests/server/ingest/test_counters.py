"""Ingest counters add up."""

from __future__ import annotations

import threading

from server.ingest.counters import NO_VEHICLE, IngestCounters


def _check(c: dict[str, int]) -> None:
    assert c["received"] == c["accepted"] + c["late"] + c["duplicate"] + c["rejected"]
    assert c["rejected"] == sum(v for k, v in c.items() if k.startswith("rejected_"))


def test_counters_add_up() -> None:
    c = IngestCounters()
    c.accepted("a")
    c.accepted("a", lost_delta=3)
    c.late("a", lost_delta=-1)
    c.duplicate("a")
    c.rejected("a", "non_finite")
    c.rejected("a", "non_finite")
    c.rejected("a", "unknown_vehicle")
    c.rejected(None, "bad_key")
    c.seq_restart("a")
    c.wheel_gap("a")
    c.estimator_error("a")
    c.estimator_error("a")
    c.config_refused("a")
    c.config_refused(None)
    snap = c.snapshot()
    a = snap["a"]
    assert a == {
        "received": 7,
        "accepted": 2,
        "late": 1,
        "duplicate": 1,
        "rejected": 3,
        "lost_by_seq_gap": 2,
        "seq_restarts": 1,
        "clock_reanchors": 0,
        "wheel_gaps": 1,
        "estimator_errors": 2,
        "configs_refused": 1,
        "rejected_non_finite": 2,
        "rejected_unknown_vehicle": 1,
    }
    _check(a)
    _check(snap[NO_VEHICLE])
    assert c.totals()["received"] == 8
    c.forget("a")
    assert "a" not in c.snapshot()


def test_snapshot_is_consistent_under_concurrent_writes() -> None:
    c = IngestCounters()
    stop = threading.Event()

    def writer() -> None:
        i = 0
        while not stop.is_set():
            [c.accepted, c.late, c.duplicate][i % 3]("v")
            c.rejected("v", "wrong_type")
            i += 1

    t = threading.Thread(target=writer)
    t.start()
    try:
        for _ in range(200):
            snap = c.snapshot()
            if "v" in snap:
                _check(snap["v"])
    finally:
        stop.set()
        t.join()


def test_restore_carries_on_from_stored_totals() -> None:
    before = IngestCounters()
    before.accepted("a", lost_delta=2)
    before.late("a")
    before.rejected("a", "clock_jump")
    before.estimator_error("a")
    stored = before.snapshot()["a"]
    after = IngestCounters()  # a restarted server
    after.restore("a", stored)
    after.accepted("a")
    after.estimator_error("a")
    c = after.snapshot()["a"]
    assert (c["received"], c["accepted"], c["late"], c["rejected_clock_jump"]) == (4, 2, 1, 1)
    assert c["lost_by_seq_gap"] == 2 and c["estimator_errors"] == 2
    assert c["received"] == c["accepted"] + c["late"] + c["duplicate"] + c["rejected"]
