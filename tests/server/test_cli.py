"""The ``slipfleet`` command: every benchmark is reachable, record writes a replayable file."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.cli import BENCHES, main
from server.protocol import decode
from server.protocol.recording import read_recording


@pytest.mark.parametrize("which", BENCHES)
def test_every_bench_has_help(which: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["bench", which, "--help"])
    assert exc.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_bench_options_reach_the_benchmark(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "viewer", "--vehicles", "20", "--frames", "2"]) == 0
    out = capsys.readouterr().out
    assert "20 vehicles, 2 frames" in out and "per-vehicle / batched" in out


def test_record_writes_a_replayable_recording(tmp_path: Path) -> None:
    path = tmp_path / "drive.sfrec"
    assert (
        main(
            ["record", str(path), "--vehicles", "2", "--scenario", "field_work", "--duration", "5"]
        )
        == 0
    )
    records = list(read_recording(path))
    assert len(records) > 2 * 5 * 25  # ~30 packets per vehicle-second
    assert [r.stamp_ns for r in records] == sorted(r.stamp_ns for r in records)
    vehicles = {decode(r.key, r.payload).vehicle_id for r in records}
    assert vehicles == {"sim-0001", "sim-0002"}
