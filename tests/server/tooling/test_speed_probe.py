"""The machine speed probe: a fixed loop's least time, which more work takes longer."""

from __future__ import annotations

from server.tooling.speed_probe import probe_s


def test_probe_times_its_loop_and_a_longer_loop_takes_longer() -> None:
    short = probe_s(steps=200_000, repeats=3)
    long = probe_s(steps=2_000_000, repeats=3)
    assert 0 < short < long
    assert long > 3 * short  # ten times the steps: far more than noise
