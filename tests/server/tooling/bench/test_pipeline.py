"""Server pipeline bench: a small fleet through decode, reorder, estimator and sinks."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from server.tooling.bench.pipeline import STAGES, TICK_PHASES, WARMUP_S, measure, run


def test_measure_times_every_stage_and_emits_a_row_per_tick() -> None:
    got = measure(6, seconds=WARMUP_S + 2.0, paced=False)
    assert got["vehicles"] == 6 and got["seconds"] == pytest.approx(2.0)
    # every vehicle's 100 ms tick is computed within the window (± one tick at either end)
    assert abs(got["rows"] - 6 * 2.0 * 10) <= 2 * 6
    for stage in STAGES:
        assert got[f"{stage}_s"] > 0, stage
    assert got["total_s"] >= sum(got[f"{s}_s"] for s in STAGES) - 1e-6
    # the tick's phases, as the pipeline counts them, are parts of the tick
    for phase in TICK_PHASES:
        assert got[f"{phase}_s"] > 0, phase
    assert sum(got[f"{p}_s"] for p in TICK_PHASES) <= got["tick_s"] + 1e-3


def test_side_by_side_with_a_revision_prints_and_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "pipeline.json"
    result = run([4], WARMUP_S + 1.0, baseline="HEAD", repeats=1, json_path=path)
    (case,) = result["cases"]
    assert case["vehicles"] == 4
    assert case["before"]["rows"] > 0 and case["after"]["rows"] > 0
    assert case["after_over_before"] == pytest.approx(
        case["after"]["total"] / case["before"]["total"]
    )
    assert json.loads(path.read_text()) == result
    out = capsys.readouterr().out
    assert "after/before" in out and "working tree" in out
