"""Store write bench: a small fleet's rows written a few per commit, maintain after each."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from server.tooling.bench.writes import measure, run


def test_measure_counts_every_row_after_the_warmup_and_times_both_parts() -> None:
    got = measure(12, rows_per_commit=5, seconds=4.0)
    assert got["rows"] == 12 * 40  # 40 ticks of 100 ms, a row per vehicle each
    assert got["write_s"] > 0 and got["maintain_s"] > 0  # move rounds ran (span > 3 s)
    assert got["longest_maintain_s"] > 0


def test_side_by_side_with_a_revision_prints_and_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "writes.json"
    result = run(10, [4], 1.0, baseline="HEAD", repeats=1, json_path=path)
    (case,) = result["cases"]
    assert case["rows_per_commit"] == 4
    for version in ("before", "after"):
        assert case[version]["total"] == pytest.approx(
            case[version]["write"] + case[version]["maintain"]
        )
    assert case["after_over_before"] == pytest.approx(
        case["after"]["total"] / case["before"]["total"]
    )
    assert json.loads(path.read_text()) == result
    out = capsys.readouterr().out
    assert "after/before" in out and "working tree" in out
