"""The accelerometers' biases as states of the tracked filter: where they enter (the speed's
prediction, the roll's measurement) and what they do to the attitude's 1-sigma on a unit whose
biases are as large as the config says."""

from __future__ import annotations

import dataclasses
import math
from functools import cache

import numpy as np

from estimator.config import TrackedConfig
from estimator.sim.tracked import TrackedRun, simulate_tracked
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet
from estimator.tracked.filter import GRAVITY_MPS2, predict
from estimator.tracked.model import N_STATES
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import _fuse_lateral_force, _initial_p, _q_diag, initial_filter
from estimator.types import GnssSample, ImuBatch
from tests.estimator.tracked._ticks import quiet_tick, rows_over

DT = 0.1
NEES_BAND = (0.3, 1.6)
"""Mean (error/σ)² of the rows' pitch and roll: 1 if honest (main: 2.2 and 2.6 on this run)."""
INSIDE_MIN = 0.88
UP_BIAS_TOL_MPS2 = 0.01
"""Share of rows within 2σ: 0.954 if honest (main: 0.84 pitch, 0.73 roll on this run)."""


def test_the_forward_bias_is_taken_out_of_the_speeds_prediction() -> None:
    x = np.zeros((1, N_STATES))
    x[0, S.SPEED], x[0, S.ACCEL_BIAS_Y] = 5.0, 0.04
    P = np.eye(N_STATES)[None] * 1e-4
    zero = np.zeros(1)
    out, P1 = predict(x, P, zero, np.array([0.5]), zero, DT, np.zeros((1, N_STATES)))
    assert math.isclose(out[0, S.SPEED], 5.0 + DT * (0.5 - 0.04), rel_tol=1e-12)
    # F[V, b_y] = −Δ: the bias's variance reaches the speed's, and their covariance is −Δ·P_bb
    assert math.isclose(P1[0, S.SPEED, S.ACCEL_BIAS_Y], -DT * 1e-4, rel_tol=1e-12)
    assert math.isclose(P1[0, S.SPEED, S.SPEED], 1e-4 * (1.0 + DT**2) + 1e-4 * (DT * 9.80665) ** 2)


def test_the_lateral_bias_enters_the_rolls_measurement() -> None:
    cfg = TrackedEstimatorConfig()
    p = VehicleParams.of(TrackedConfig())
    f = initial_filter(cfg)
    f.x[0, S.ACCEL_BIAS_X] = 0.02
    f.P = np.diag(np.full(N_STATES, 1e-4))[None]
    inp = quiet_tick(1, int(DT * 1e9), lateral_accel_mps2=np.array([0.02]))
    before = f.x.copy()
    _fuse_lateral_force(f, inp, p, cfg, np.zeros(1))
    # level and still, the reading is the bias the state holds: nothing to correct
    assert np.allclose(f.x, before, atol=1e-15)
    f.x[0, S.ACCEL_BIAS_X] = 0.0
    _fuse_lateral_force(f, inp, p, cfg, np.zeros(1))
    # without it, 0.02 m/s² is shared between the bias and a roll to the left (−): 1/g per m/s²
    gain_b, gain_roll = f.x[0, S.ACCEL_BIAS_X], f.x[0, S.ROLL]
    assert gain_b > 0.0 and gain_roll < 0.0
    assert math.isclose(gain_b / -gain_roll, 1.0 / GRAVITY_MPS2, rel_tol=1e-9)


def test_the_biases_prior_and_walk_are_the_configs_in_the_product_only() -> None:
    cfg = TrackedEstimatorConfig(accel_bias_std_mps2=0.05, accel_bias_walk_mps2_rt_s=2e-4)
    p = VehicleParams.of(TrackedConfig())
    P0 = _initial_p(cfg)
    q = _q_diag(cfg, p, np.zeros(1), np.ones(1), np.full(1, 10))
    for b in (S.ACCEL_BIAS_X, S.ACCEL_BIAS_Y):
        assert math.isclose(P0[b, b], 0.05**2) and math.isclose(q[0, b], 2e-4**2 * cfg.tick_s)
    paper = dataclasses.replace(cfg, mode="paper")
    assert _initial_p(paper)[S.ACCEL_BIAS_Y, S.ACCEL_BIAS_Y] == 0.0


def _biased(run: TrackedRun, bias_xy_mps2: tuple[float, float]) -> TrackedRun:
    """``run`` with its accelerometers' biases replaced by ``bias_xy_mps2`` (right, forward)."""
    drawn = run.errors.accel_bias_mps2
    shift = np.array([bias_xy_mps2[0] - drawn[0], bias_xy_mps2[1] - drawn[1], 0.0])
    meas = [
        (k, dataclasses.replace(m, accel_mps2=m.accel_mps2 + shift))
        if isinstance(m, ImuBatch)
        else (k, m)
        for k, m in run.measurements
    ]
    return dataclasses.replace(run, measurements=meas)


@cache
def _hill_with_bias(bias_mps2: float) -> tuple[TrackedRun, np.ndarray]:
    """``route_firm_hill`` seed 3 for 300 s (its ramps, side slopes and the start of its
    outage at 150 s), the unit's biases ``bias_mps2`` on both axes."""
    run = _biased(simulate_tracked("route_firm_hill", 3), (bias_mps2, bias_mps2))
    return run, rows_over(run, TrackedEstimatorConfig(), 300.0)


def test_a_unit_biased_as_the_config_says_gets_an_honest_attitude_sigma() -> None:
    cfg = TrackedEstimatorConfig()
    run, rows = _hill_with_bias(cfg.accel_bias_std_mps2)
    k = run.index_at(rows["stamp_ns"])
    given = np.isfinite(rows["pitch_rad"]) & np.isfinite(rows["roll_rad"])
    for name in ("pitch", "roll"):
        err = (rows[f"{name}_rad"] - getattr(run.truth, f"{name}_rad")[k])[given]
        z = err / rows[f"{name}_std_rad"][given]
        nees, inside = float(np.mean(z**2)), float(np.mean(np.abs(z) < 2.0))
        assert NEES_BAND[0] < nees < NEES_BAND[1], (name, nees)
        assert inside > INSIDE_MIN, (name, inside)


def _without_up_velocity(run: TrackedRun) -> TrackedRun:
    """``run`` with its receiver giving no up velocity (NaN)."""
    meas = [
        (k, dataclasses.replace(m, vel_enu_mps=(*m.vel_enu_mps[:2], math.nan)))
        if isinstance(m, GnssSample)
        else (k, m)
        for k, m in run.measurements
    ]
    return dataclasses.replace(run, measurements=meas)


def _state_before_outage(run: TrackedRun) -> tuple[np.ndarray, np.ndarray]:
    fleet = TrackedFleet(TrackedEstimatorConfig())
    fleet.add_vehicle("v", run.config)
    until = run.outages_ns[0][0]
    for stamp, m in run.measurements:
        if stamp <= until:
            fleet.push("v", m)
    list(fleet.advance({"v": until}))
    return fleet.filter_state("v")


def test_the_up_velocity_pins_the_pitch_and_the_forward_bias_is_learnt() -> None:
    run = _biased(simulate_tracked("route_firm_hill", 3), (0.0, 0.04))
    k = run.index_at(np.array([run.outages_ns[0][0]]))[0]
    x, P = _state_before_outage(run)
    # 150 s over ramps and turns beside GNSS: the bias recovered, its 1-sigma under the prior
    assert abs(x[S.ACCEL_BIAS_Y] - 0.04) < UP_BIAS_TOL_MPS2
    assert math.sqrt(P[S.ACCEL_BIAS_Y, S.ACCEL_BIAS_Y]) < 0.5 * 0.03
    # the up velocity sees the pitch itself: within 1 mrad, its 1-sigma under 0.6 mrad
    assert abs(x[S.PITCH] - run.truth.pitch_rad[k]) < 1e-3
    assert math.sqrt(P[S.PITCH, S.PITCH]) < 6e-4
    _, P_blind = _state_before_outage(_without_up_velocity(run))
    # without it only θ + b_y/g is seen, turns parting them slowly: a wider pitch
    assert math.sqrt(P_blind[S.PITCH, S.PITCH]) > 2.0 * math.sqrt(P[S.PITCH, S.PITCH])
