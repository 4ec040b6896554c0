"""The history benchmark runs end to end on a small series (numbers are not checked here)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimator.types import EstimateFlag
from server.tooling.bench.series import run, vehicle_hour


def test_vehicle_hour_shape() -> None:
    rows = vehicle_hour(6000)
    assert rows.shape == (6000,)
    assert np.all(np.diff(rows["stamp_ns"]) == 100_000_000)
    standstill = (rows["flags"] & int(EstimateFlag.STANDSTILL)) != 0
    assert np.isnan(rows["slip_left_pct"][standstill]).all()
    assert np.isfinite(rows["slip_left_pct"][~standstill]).all()


def test_run_small(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bench.json"
    result = run(out, rows=3000, repeats=1)
    assert json.loads(out.read_text()) == result
    cases = result["cases"]
    assert "target_ms" in cases["series json max_points=2000"]
    assert "target_ms" in cases["report"]
    assert all(c["median_ms"] > 0 for c in cases.values())
    assert cases["series json max_points=2000"]["bytes"] < cases["series json full rate"]["bytes"]
    assert "series json max_points=2000" in capsys.readouterr().out
