"""The storage benchmark runs end to end (tiny sizes) and reports what it measured."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from server.tooling.bench.storage import run


def _check(backend: dict[str, object]) -> None:
    assert backend["rows"] == 300
    assert isinstance(backend["insert_speedup"], float) and backend["insert_speedup"] > 0
    for case in ("insert_batched", "insert_batched_fleet"):
        assert backend[f"{case}_us_per_row"] == pytest.approx(1e6 / backend[f"{case}_rows_per_s"])
        assert 0 < backend[f"{case}_best_us_per_row"] <= backend[f"{case}_us_per_row"]
    for key in ("query_all_fields", "query_few_fields"):
        q = backend[key]
        assert isinstance(q, dict) and q["median_ms"] > 0 and q["best_ms"] <= q["median_ms"]
        busy = q["busy_thread"]
        assert busy["median_ms"] > 0 and busy["best_ms"] <= busy["median_ms"]
        assert q["busy_slowdown"] == busy["median_ms"] / q["median_ms"]
        assert q["meets_target"] == (q["median_ms"] < 100.0)
        assert busy["meets_target"] == (busy["median_ms"] < 100.0)


def test_sqlite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bench.json"
    results = run(out, rows=300, baseline_rows=20, repeats=2)
    assert set(results["backends"]) == {"sqlite"}
    sqlite = results["backends"]["sqlite"]
    _check(sqlite)
    assert sqlite["fleet_vehicles"] == 30  # capped: one packet per vehicle at least
    old = sqlite["column_layout"]  # the baseline: SQLite's schema before version 6
    for case in ("insert_batched", "insert_batched_fleet"):
        assert old[f"{case}_cost_ratio"] == pytest.approx(
            old[f"{case}_us_per_row"] / sqlite[f"{case}_us_per_row"]
        )
    assert sqlite["query_all_fields_column_read"]["median_ms"] > 0
    assert json.loads(out.read_text()) == results
    out = capsys.readouterr().out
    assert "one commit per row" in out and "column layout" in out and "30 vehicles" in out
    assert "busy thread" in out and "busy/quiet" in out
    # no thread left spinning after the run
    assert not [t for t in threading.enumerate() if t.name == "bench-busy-python"]


@pytest.mark.postgres
def test_postgres(pg_url: str) -> None:
    results = run(postgres_url=pg_url, rows=300, baseline_rows=20, repeats=2)
    _check(results["backends"]["postgresql"])
    assert results["backends"]["postgresql"]["column_layout"] is None
