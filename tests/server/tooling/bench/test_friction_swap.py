"""The damaged-tyre swap replay: transparent when nothing is swapped, and a swap reaches the
filter."""

from __future__ import annotations

import numpy as np

from estimator.friction import FrictionMode
from estimator.friction import fleet as fleet_mod
from estimator.sim.four_wheel import NAMED, simulate_four_wheel
from server.tooling.bench.friction import sensor_series
from server.tooling.bench.friction_swap import _truth_params, replay

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
