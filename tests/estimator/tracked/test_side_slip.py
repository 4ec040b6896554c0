"""The side-slip gain learnt beside GNSS on the crawler simulator (a ground sliding more than
configured must not be read as a gyro scale error)."""

from __future__ import annotations

import numpy as np

from estimator.sim.tracked import CrawlerSensors, simulate_tracked
from estimator.tracked import TrackedState as S

from ._ticks import run_to_first_outage


def test_a_slippery_grounds_side_slip_is_learnt_not_put_on_the_gyro() -> None:
    # lateral resistance 0.39 against 0.6 configured; the gyro the data sheet's (grade 1)
    run = simulate_tracked("random", 1038, sensors=CrawlerSensors())
    fleet, _ = run_to_first_outage(run)
    x, P = fleet.filter_state("v")
    expected = run.config.motion.lateral_resistance / run.route.ground.lateral_resistance
    assert abs(x[S.SIDE_SLIP] - expected) < 0.15 * expected
    scale_err = x[S.GYRO_SCALE] - run.errors.gyro_scale
    assert abs(scale_err) < 3.0 * np.sqrt(P[S.GYRO_SCALE, S.GYRO_SCALE])
