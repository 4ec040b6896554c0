"""The damaged-tyre swap replay: transparent when nothing is swapped, and a swap reaches the
filter; the wheel readings' rounding on the straight."""

from __future__ import annotations

import numpy as np

from estimator.friction import FrictionMode
from estimator.friction import fleet as fleet_mod
from estimator.sim.four_wheel import NAMED, WheelSpeedSensor, simulate_four_wheel
from server.tooling.bench.friction import sensor_series
from server.tooling.bench.friction_swap import _truth_params, replay, rounding_rows

SEED = 1


def test_the_replay_redraws_the_runs_truth_and_changes_nothing_unswapped() -> None:
    runs = simulate_four_wheel([NAMED["damaged_tyre"]], [SEED])
    p = _truth_params(runs[0], SEED)
    np.testing.assert_array_equal(p.kz_npm[0], runs[0].tyre_kz_npm)
    np.testing.assert_array_equal(p.c_px_npm2[0], runs[0].tyre_c_px_npm2)
    bench = sensor_series(runs, FrictionMode.PRODUCT)[0]
    ((t, mu),) = replay(runs, [SEED], "none")
    np.testing.assert_array_equal(t, bench.t_s)
    np.testing.assert_array_equal(mu, bench.mu_filter)
    ((_, mu_kappa),) = replay(runs, [SEED], "kappa+nobal")
    assert np.abs(mu_kappa - mu).max() > 1e-3
    assert fleet_mod.balance_std_n.__name__ == "balance_std_n"  # restored after the replay


def test_a_held_speed_keeps_its_rounding_in_the_readings_mean() -> None:
    """On the straight before the manoeuvre the undriven wheels turn steadily: their readings'
    mean error over the GNSS epochs is the truth's speed rounded to the CAN quantum (within
    0.2e-4 of the speed), up to half a quantum and not averaged away; the driven wheels ring
    on their tyres far faster than the epochs (above 20 Hz)."""
    runs = simulate_four_wheel([NAMED["damaged_tyre"]], [SEED])
    sensor = WheelSpeedSensor()
    r = rounding_rows(runs[0], sensor)
    np.testing.assert_allclose(r["reading"][:2], r["rounding"][:2], atol=2e-5)
    assert np.all(np.abs(r["rounding"]) <= 0.5 * sensor.quantum_radps / r["omega"] + 1e-9)
    assert np.abs(r["rounding"][:2]).max() > 1e-4  # seed 1's front wheels: +4.1e-4
    assert np.all(r["ring_straight"][2:, 0] > 20.0)
