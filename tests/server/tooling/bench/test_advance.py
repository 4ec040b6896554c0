"""Batched fleet step bench: runs small, side by side with a git revision (in child processes
or interleaved in this one), same rows."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from server.tooling.bench.advance import _interleaved_of, measure, run

_REPO = Path(__file__).resolve().parents[4]


def test_measure_counts_calls_and_ticks() -> None:
    result = measure((2, 4), seconds=3.0, source_runs=2)
    cases = result["cases"]
    assert [c["vehicles"] for c in cases] == [2, 4]
    for c in cases:
        assert c["calls"] == 20  # (3 s − 2 s warm-up) / 50 ms
        # phases spread over the tick: about half the fleet is due at each call
        assert c["ticks"] == c["vehicles"] * 10 and c["advance_s"] > 0
    assert len(result["digest"]) == 64


def test_side_by_side_with_a_revision_prints_and_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    git = subprocess.run(["git", "-C", str(_REPO), "rev-parse", "HEAD"], capture_output=True)
    if git.returncode != 0:
        pytest.skip("not a git checkout")
    path = tmp_path / "advance.json"
    result = run(
        path,
        sizes=(2, 3),
        estimators=("mdsf",),
        baseline="HEAD",
        repeats=1,
        seconds=3.0,
        source_runs=2,
    )
    mdsf = result["estimators"]["mdsf"]
    assert [c["vehicles"] for c in mdsf["after"]["cases"]] == [2, 3]
    assert [c["vehicles"] for c in mdsf["before"]["cases"]] == [2, 3]
    assert isinstance(mdsf["rows_identical"], bool)  # the working tree's rows against HEAD's
    assert json.loads(path.read_text()) == result
    out = capsys.readouterr().out
    assert "after/before" in out and "rows identical:" in out


@pytest.mark.parametrize(("estimator", "ticks_per_vehicle"), [("tracked", 10), ("friction", 50)])
def test_measure_knows_the_tracked_and_friction_fleets(
    estimator: str, ticks_per_vehicle: int
) -> None:
    result = measure((2, 3), seconds=3.0, source_runs=2, estimator=estimator)
    for c in result["cases"]:
        assert c["calls"] == 20
        # 1 s measured: 10 ticks of 0.1 s (tracked), 50 of 0.02 s (friction) per vehicle
        assert c["ticks"] == c["vehicles"] * ticks_per_vehicle and c["advance_s"] > 0


def test_every_estimator_printed_side_by_side(capsys: pytest.CaptureFixture[str]) -> None:
    result = run(sizes=(2,), repeats=1, seconds=3.0, source_runs=1)
    assert list(result["estimators"]) == ["mdsf", "tracked", "friction"]
    out = capsys.readouterr().out
    for name in ("mdsf", "tracked", "friction"):
        assert f"\n{name}\n" in out
    with pytest.raises(ValueError, match="unknown estimators"):
        run(sizes=(2,), estimators=("nope",), repeats=1, seconds=3.0)


def _estimator_as_committed() -> bool:
    """Whether this tree's ``estimator/`` is HEAD's (the interleaved run's rows then agree)."""
    diff = ["git", "-C", str(_REPO), "status", "--porcelain", "--", "estimator"]
    return subprocess.run(diff, capture_output=True, text=True, check=True).stdout == ""


def test_interleaved_head_against_this_tree_fills_both_columns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "advance.json"
    result = run(
        path,
        sizes=(2, 3),
        estimators=("mdsf",),
        baseline="HEAD",
        interleave=True,
        repeats=2,
        seconds=3.0,
        source_runs=2,
    )
    mdsf = result["estimators"]["mdsf"]
    for version in ("before", "after"):
        cases = mdsf[version]["cases"]
        assert [c["vehicles"] for c in cases] == [2, 3]
        assert all(c["call_ms"] > 0 and c["tick_us"] > 0 for c in cases)
    # the same fleet in both: as many rows per call, and the same bytes while estimator/ is HEAD's
    assert [c["ticks_per_call"] for c in mdsf["before"]["cases"]] == [1.0, 1.5]
    assert [c["ticks_per_call"] for c in mdsf["after"]["cases"]] == [1.0, 1.5]
    assert mdsf["rows_identical"] is _estimator_as_committed()
    assert json.loads(path.read_text()) == result
    out = capsys.readouterr().out
    assert "calls alternating" in out and "after/before" in out
    assert f"rows identical: {'yes' if mdsf['rows_identical'] else 'NO'}" in out


def test_interleave_without_a_baseline_is_one_line_on_stderr() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "server.tooling.bench.advance", "--interleave", "--sizes", "2"],
        cwd=_REPO,
        capture_output=True,
        text=True,
    )
    assert done.returncode != 0 and done.stdout == ""
    assert done.stderr.splitlines() == [
        "slipfleet bench advance: --interleave needs --baseline REV (the revision whose "
        "estimators run beside this tree's)"
    ]
    with pytest.raises(ValueError, match="needs --baseline"):
        run(sizes=(2,), estimators=("mdsf",), interleave=True, repeats=1, seconds=3.0)


@pytest.mark.parametrize("bench", ["advance", "pipeline", "writes"])
def test_a_baseline_that_is_no_revision_is_one_line_on_stderr(bench: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", f"server.tooling.bench.{bench}", "--baseline", "no-such-rev"],
        cwd=_REPO,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and done.stdout == ""
    last = done.stderr.splitlines()[-1]
    assert last.endswith("argument --baseline: 'no-such-rev' is not a revision of this repository")
    assert "Traceback" not in done.stderr


def test_interleaved_skips_an_estimator_the_baseline_lacks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    old = tmp_path / "old_estimator"
    old.mkdir()
    (old / "__init__.py").write_text("")
    (old / "friction.py").write_text("import a_module_nobody_has\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert _interleaved_of("tracked", "old_estimator", (2,), 3.0, 1, 1) is None
    # a module the baseline's estimator itself fails to import is an error, not a skip
    with pytest.raises(ModuleNotFoundError, match="a_module_nobody_has"):
        _interleaved_of("friction", "old_estimator", (2,), 3.0, 1, 1)
