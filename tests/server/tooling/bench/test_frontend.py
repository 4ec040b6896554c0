"""Fleet estimator cost bench: runs small, reports every case, writes its JSON."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from server.tooling.bench.frontend import run


def test_small_run_prints_and_writes_every_case(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "fe.json"
    result = run(path, sizes=(3,), intervals_ms=(100, 200), seconds=4.0, source_runs=2)
    cases = result["cases"]
    assert [(c["vehicles"], c["interval_ms"]) for c in cases] == [(3, 100), (3, 200)]
    for c in cases:
        assert c["rows"] > 0
        assert c["push_ms"] > 0 and c["advance_ms"] > 0
        assert 0 <= c["wheel_fit_ms"] + c["engine_ms"] <= c["advance_ms"]
    assert json.loads(path.read_text()) == result
    assert "advance ms" in capsys.readouterr().out
