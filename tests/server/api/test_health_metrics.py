"""/health readiness and /metrics Prometheus text."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from server.metrics.prometheus import MetricFamily, Sample, render
from server.storage.base import Store

from .conftest import ApiClient, FakeRuntime

# Prometheus text exposition format 0.0.4, line by line.
_NAME = r"[a-zA-Z_:][a-zA-Z0-9_:]*"
_LABELS = r'\{(?:[a-zA-Z_][a-zA-Z0-9_]*="(?:[^"\\\n]|\\[\\"n])*"(?:,|(?=\})))*\}'
_VALUE = r"(?:[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?|NaN|[+-]Inf)"
_SAMPLE = re.compile(rf"({_NAME})({_LABELS})? ({_VALUE})(?: -?\d+)?")
_HELP = re.compile(rf"# HELP ({_NAME}) .*")
_TYPE = re.compile(rf"# TYPE ({_NAME}) (counter|gauge|histogram|summary|untyped)")


def parse_exposition(text: str) -> dict[str, list[tuple[str, str, float]]]:
    """Check every line against the text format; return family → [(name, labels, value)]."""
    assert text.endswith("\n")
    families: dict[str, list[tuple[str, str, float]]] = {}
    typed: dict[str, str] = {}
    for line in text.splitlines():
        if m := _HELP.fullmatch(line):
            continue
        if m := _TYPE.fullmatch(line):
            assert m.group(1) not in typed, f"TYPE given twice: {line}"
            typed[m.group(1)] = m.group(2)
            families[m.group(1)] = []
            continue
        m = _SAMPLE.fullmatch(line)
        assert m, f"not a valid exposition line: {line!r}"
        name = m.group(1)
        family = next(f for f in typed if name == f or name.startswith(f + "_"))
        families[family].append((name, m.group(2) or "", float(m.group(3).replace("Inf", "inf"))))
    return families


def test_health_ok(client: ApiClient) -> None:
    r = client.get("/api/v1/health")
    assert r.status_code == 200
    assert r.json() == {"status": "ok", "checks": {"zenoh": True, "storage": True}}


def test_health_names_the_part_that_is_down(client: ApiClient, runtime: FakeRuntime) -> None:
    runtime.zenoh_up = False
    r = client.get("/api/v1/health")
    assert r.status_code == 503
    assert r.json() == {
        "error": "unavailable",
        "reason": "down: zenoh",
        "checks": {"zenoh": False, "storage": True},
    }


def test_health_check_that_raises_is_down(client: ApiClient, runtime: FakeRuntime) -> None:
    def broken() -> dict[str, bool]:
        raise RuntimeError("boom")

    runtime.health = broken  # type: ignore[method-assign]
    r = client.get("/api/v1/health")
    assert r.status_code == 503
    assert r.json()["checks"] == {"runtime": False}


def test_metrics_parse_as_exposition(client: ApiClient, store: Store, runtime: FakeRuntime) -> None:
    client.put("/api/v1/vehicles/t1", json={})
    client.put('/api/v1/vehicles/t"2', json={})  # refused id: never reaches the metrics
    store.write_counters({"t1": {"accepted": 7, "rejected_bad_payload": 2}}, 0)
    runtime.zenoh_up = False
    r = client.get("/api/v1/metrics")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain; version=0.0.4")
    fams = parse_exposition(r.text)
    assert ("slipfleet_up", '{component="storage"}', 1.0) in fams["slipfleet_up"]
    assert ("slipfleet_up", '{component="zenoh"}', 0.0) in fams["slipfleet_up"]
    packets = fams["slipfleet_ingest_packets"]
    assert (
        "slipfleet_ingest_packets_total",
        '{vehicle="t1",reason="rejected_bad_payload"}',
        2.0,
    ) in packets
    assert fams["slipfleet_writer_backlog_rows"] == [("slipfleet_writer_backlog_rows", "", 0.0)]


def test_metrics_by_vehicle_flag_reaches_the_runtime(
    client: ApiClient, runtime: FakeRuntime
) -> None:
    assert client.get("/api/v1/metrics").status_code == 200
    assert client.get("/api/v1/metrics?by_vehicle=false").status_code == 200
    assert client.get("/api/v1/metrics?by_vehicle=maybe").status_code == 422
    assert runtime.metrics_by_vehicle == [True, False]


def test_the_readme_names_metrics_paths_that_answer(client: ApiClient) -> None:
    readme = (Path(__file__).parents[3] / "README.md").read_text(encoding="utf-8")
    named = set(re.findall(r"(?<![\w/])(/[\w/]*metrics)(?:\?by_vehicle=(\w+))?", readme))
    assert ("/api/v1/metrics", "false") in named
    for path, by_vehicle in sorted(named):
        query = f"?by_vehicle={by_vehicle}" if by_vehicle else ""
        assert client.get(path + query).status_code == 200, f"README names {path}{query}"


def test_fleet_totals_sum_the_vehicles_and_drop_their_label() -> None:
    from server.runtime import _estimator_family, _ingest_families

    counters = {
        "v1": {"received": 10, "accepted": 8, "late": 2, "rejected_non_finite": 1},
        "v2": {"received": 5, "accepted": 5, "rejected_non_finite": 2, "rejected_bad_key": 1},
    }
    text = render(_ingest_families(counters, by_vehicle=False))
    assert 'vehicle="' not in text
    assert "slipfleet_packets_received_total 15" in text
    assert "slipfleet_packets_late_total 2" in text
    assert 'slipfleet_packets_rejected_total{reason="non_finite"} 3' in text
    assert 'slipfleet_packets_rejected_total{reason="bad_key"} 1' in text
    per_vehicle = render(_ingest_families(counters))
    assert 'slipfleet_packets_received_total{vehicle="v2"} 5' in per_vehicle
    events = {"mdsf": {"v1": {"resets": 1, "gnss_gated": 4}, "v2": {"gnss_gated": 3}}}
    fleet = render([_estimator_family(events, by_vehicle=False)])
    assert 'slipfleet_estimator_events_total{estimator="mdsf",event="gnss_gated"} 7' in fleet
    assert 'vehicle="' not in fleet


def test_render_escapes_and_special_values() -> None:
    text = render(
        [
            MetricFamily(
                "x_seconds",
                "gauge",
                "Help with \\ and\nnewline.",
                [
                    Sample(math.nan, {"v": 'a"b\\c\nd'}),
                    Sample(math.inf),
                    Sample(-math.inf, {"v": "e"}),
                    Sample(0.25, {"v": "f"}),
                    Sample(3.0, {"v": "g"}),
                ],
            )
        ]
    )
    assert text.splitlines() == [
        "# HELP x_seconds Help with \\\\ and\\nnewline.",
        "# TYPE x_seconds gauge",
        'x_seconds{v="a\\"b\\\\c\\nd"} NaN',
        "x_seconds +Inf",
        'x_seconds{v="e"} -Inf',
        'x_seconds{v="f"} 0.25',
        'x_seconds{v="g"} 3',
    ]
    values = [v for _, _, v in parse_exposition(text)["x_seconds"]]
    assert math.isnan(values[0]) and values[1:] == [math.inf, -math.inf, 0.25, 3.0]


def test_invalid_metric_names_are_refused() -> None:
    with pytest.raises(ValueError):
        MetricFamily("bad-name", "gauge", "h")
    with pytest.raises(ValueError):
        MetricFamily("ok", "gauge", "h", [Sample(1, {"bad-label": "x"})])
    with pytest.raises(ValueError):
        render([MetricFamily("a", "gauge", "h"), MetricFamily("a", "gauge", "h")])
