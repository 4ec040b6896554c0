"""The hull's pitch and roll in the tracked rows: the filter's own attitude and its 1-sigma,
NaN until the filter has measured it, true to the simulator on a hilly route."""

from __future__ import annotations

from functools import cache

import numpy as np

from estimator.sim.tracked import TrackedRun, simulate_tracked
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet
from estimator.tracked.model import TrackedState as S
from tests.estimator.tracked._ticks import rows_over

SECOND = 1_000_000_000


@cache
def _hill() -> tuple[TrackedRun, np.ndarray]:
    """``route_firm_hill`` seed 2 for 300 s: its ramps and side slopes and the start of its
    4-minute GNSS outage (at 150 s)."""
    run = simulate_tracked("route_firm_hill", 2)
    return run, rows_over(run, TrackedEstimatorConfig(), 300.0)


def test_pitch_and_roll_rows_follow_the_simulated_hill() -> None:
    run, rows = _hill()
    k = run.index_at(rows["stamp_ns"])
    assert np.abs(run.truth.pitch_rad[k]).max() > 0.09  # 10 % ramps
    assert np.abs(run.truth.roll_rad[k]).max() > 0.045  # 5 % cross grades
    given = np.isfinite(rows["pitch_rad"]) & np.isfinite(rows["roll_rad"])
    assert given[10:].all()  # after the first second every row has the attitude
    pitch_err = (rows["pitch_rad"] - run.truth.pitch_rad[k])[given]
    roll_err = (rows["roll_rad"] - run.truth.roll_rad[k])[given]
    # within the accelerometer's bias (0.03 m/s² ~ 3 mrad) and the ramps' few mrad of lag
    assert np.sqrt(np.mean(pitch_err**2)) < 0.005
    assert np.sqrt(np.mean(roll_err**2)) < 0.007
    assert np.abs(pitch_err).max() < 0.02 and np.abs(roll_err).max() < 0.02
    # the rows' 1-sigma is the filter's: positive, below the reporting bound, shrinking
    for name in ("pitch_std_rad", "roll_std_rad"):
        std = rows[name][given]
        assert (std > 0).all() and (std <= TrackedEstimatorConfig().tilt_reported_std_rad).all()
        assert std[-1] < std[0]


def test_the_attitude_is_nan_until_the_filter_has_measured_it() -> None:
    run, rows = _hill()
    # the first row is given before the accelerometer has pinned the pitch (prior 0.2 rad)
    assert np.isnan(rows["pitch_rad"][0]) and np.isnan(rows["pitch_std_rad"][0])
    strict = rows_over(run, TrackedEstimatorConfig(tilt_reported_std_rad=1e-4), 5.0)
    assert strict.size > 40
    for name in ("pitch_rad", "pitch_std_rad", "roll_rad", "roll_std_rad"):
        assert np.isnan(strict[name]).all(), name


def test_the_rows_attitude_is_the_filters_state() -> None:
    run = simulate_tracked("route_firm_hill", 2)
    fleet = TrackedFleet()
    fleet.add_vehicle("v", run.config)
    until = run.start_ns + 200 * SECOND  # on the first ramps
    for stamp, m in run.measurements:
        if stamp <= until:
            fleet.push("v", m)
    list(fleet.advance({"v": until}))
    rows = fleet.flush("v")  # the held rows, the newest being the filter's last tick
    x, P = fleet.filter_state("v")
    last = rows[-1]
    assert last["pitch_rad"] == x[S.PITCH] and last["roll_rad"] == x[S.ROLL]
    assert last["pitch_std_rad"] == np.sqrt(P[S.PITCH, S.PITCH])
    assert last["roll_std_rad"] == np.sqrt(P[S.ROLL, S.ROLL])
    assert abs(x[S.PITCH]) > 0.01  # on a ramp
