"""A count or a duration out of range on the ``slipfleet`` command line is refused by the parser
in one line naming the option, before anything is simulated, bound or published (no traceback
from deep inside the demo, no empty recording, no demo running forever on a negative time)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.server.cli_support import run_cli

CASES = [
    (["demo", "--vehicles", "0"], "--vehicles", "1 or more"),
    (["demo", "--vehicles", "-1"], "--vehicles", "1 or more"),
    (["demo", "--vehicles", "two"], "--vehicles", "not a whole number"),
    (["demo", "--duration", "-3"], "--duration", "0 (until Ctrl-C)"),
    (["simulate", "--vehicles", "0"], "--vehicles", "1 or more"),
    (["simulate", "--duration", "-1"], "--duration", "> 0"),
    (["record", "RECORDING", "--vehicles", "0"], "--vehicles", "1 or more"),
    (["loadtest", "--vehicles", "0", "--duration", "5"], "--vehicles", "1 or more"),
    (["loadtest", "--vehicles", "3", "--duration", "-1"], "--duration", "> 0"),
    (
        ["loadtest", "--vehicles", "3", "--duration", "5", "--publishers", "0"],
        "--publishers",
        "1 or more",
    ),
]


@pytest.mark.parametrize(("args", "option", "says"), CASES, ids=lambda v: str(v))
def test_an_out_of_range_count_or_duration_is_one_line(
    args: list[str], option: str, says: str, tmp_path: Path
) -> None:
    recording = tmp_path / "x.sfrec"
    args = [str(recording) if a == "RECORDING" else a for a in args]
    result = run_cli(args, cwd=tmp_path, timeout_s=60.0)
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert f"argument {option}:" in lines[0] and says in lines[0], lines[0]
    assert not recording.exists()
    assert not (tmp_path / "data").exists(), "the demo opened a store"


def test_demo_duration_zero_still_means_until_ctrl_c() -> None:
    from server.cli import _parser

    args = _parser().parse_args(["demo", "--duration", "0", "--vehicles", "2"])
    assert args.duration == 0.0 and args.vehicles == 2
