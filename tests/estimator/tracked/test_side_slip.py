"""The side-slip gain learnt beside GNSS on the crawler simulator (a ground sliding more than
configured must not be read as a gyro scale error)."""

from __future__ import annotations

import numpy as np

from estimator.sim.tracked import simulate_tracked
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet
from estimator.tracked import TrackedState as S


def test_a_slippery_grounds_side_slip_is_learnt_not_put_on_the_gyro() -> None:
    run = simulate_tracked("random", 1038)  # lateral resistance 0.39 against 0.6 configured
    fleet = TrackedFleet(TrackedEstimatorConfig())
    fleet.add_vehicle("v", run.config)
    loss_ns = run.outages_ns[0][0]
    for key_ns, m in run.measurements:
        if key_ns > loss_ns:
            break
        fleet.push("v", m)
    fleet.advance({"v": loss_ns})
    x, P = fleet.filter_state("v")
    expected = run.config.motion.lateral_resistance / run.route.ground.lateral_resistance
    assert abs(x[S.SIDE_SLIP] - expected) < 0.15 * expected
    scale_err = x[S.GYRO_SCALE] - run.errors.gyro_scale
    assert abs(scale_err) < 3.0 * np.sqrt(P[S.GYRO_SCALE, S.GYRO_SCALE])
