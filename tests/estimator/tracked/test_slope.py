"""The tracked estimator on ground that is not flat: the pitch and roll it carries, the
horizontal dead reckoning of an along-ground distance, gravity out of every accelerometer use."""

from __future__ import annotations

import dataclasses
import math
from functools import cache

import numpy as np

from estimator.config import TrackedConfig
from estimator.sim.tracked import TrackedRun, simulate_tracked
from estimator.tracked import TrackedEstimatorConfig, TrackedFleet
from estimator.tracked.filter import GRAVITY_MPS2, predict
from estimator.tracked.model import N_STATES, MotionState
from estimator.tracked.model import TrackedState as S
from estimator.tracked.odometer import odometer_measurement
from estimator.tracked.params import VehicleParams
from estimator.tracked.step import _antenna_ahead_m, _antenna_right_m, accel_steady, initial_filter

SECOND = 1_000_000_000
G = GRAVITY_MPS2
DT = 0.1


def _x(**values: float) -> np.ndarray:
    x = np.zeros((1, N_STATES))
    x[0, S.F_STRAIGHT] = 1.0
    for name, v in values.items():
        x[0, S[name]] = v
    return x


def _predict(
    x: np.ndarray,
    *,
    accel: float = 0.0,
    gyro_z: float = 0.0,
    tilt: tuple[float, float] = (0.0, 0.0),
    P: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    P0 = np.eye(N_STATES)[None] * 1e-6 if P is None else P
    return predict(
        x,
        P0,
        np.array([gyro_z]),
        np.array([accel]),
        np.zeros(1),
        DT,
        np.zeros((1, N_STATES)),
        None,
        (np.array([tilt[0]]), np.array([tilt[1]])),
    )


def test_the_hull_moves_its_along_ground_speed_times_cos_pitch_horizontally() -> None:
    theta = math.atan(0.10)
    x, _ = _predict(_x(SPEED=10.0, PITCH=theta), accel=G * math.sin(theta))
    assert math.isclose(x[0, S.NORTH], DT * 10.0 * math.cos(theta), rel_tol=1e-12)
    assert abs(x[0, S.EAST]) < 1e-15
    # 0.5 % of the distance on a 10 % grade: what a level model would count too far
    assert 10.0 * DT - x[0, S.NORTH] > 0.004 * 10.0 * DT


def test_gravity_is_taken_out_of_the_speed_prediction() -> None:
    theta = math.atan(0.10)
    # climbing at a steady speed: the accelerometer reads g·sin θ, the hull does not speed up
    x, _ = _predict(_x(SPEED=5.0, PITCH=theta), accel=G * math.sin(theta))
    assert math.isclose(x[0, S.SPEED], 5.0, abs_tol=1e-12)
    x, _ = _predict(_x(SPEED=5.0, PITCH=theta), accel=G * math.sin(theta) + 0.5)
    assert math.isclose(x[0, S.SPEED], 5.0 + 0.5 * DT, abs_tol=1e-12)


def test_the_pitch_follows_its_gyro_less_its_bias() -> None:
    x, _ = _predict(_x(PITCH=0.02, PITCH_GYRO_BIAS=0.001), tilt=(0.011, 0.0))
    assert math.isclose(x[0, S.PITCH], 0.02 + DT * 0.010, abs_tol=1e-15)


def test_a_turn_on_a_side_slope_pitches_the_hull_and_slows_the_heading() -> None:
    phi, w = 0.1, 0.5
    x, _ = _predict(_x(ROLL=phi), gyro_z=w)
    # θ̇ = ω_x·cos φ + ω·sin φ; ψ̇ = −(ω·cos φ − ω_x·sin φ)/cos θ; φ̇ = ω_y − tan θ·(…) = 0
    assert math.isclose(x[0, S.PITCH], DT * w * math.sin(phi), rel_tol=1e-12)
    assert math.isclose(x[0, S.HEADING], -DT * w * math.cos(phi), rel_tol=1e-12)
    assert math.isclose(x[0, S.ROLL], phi, rel_tol=1e-12)


def test_the_position_covariance_carries_the_pitchs() -> None:
    theta, v, var = math.atan(0.1), 10.0, 0.02**2
    P = np.zeros((1, N_STATES, N_STATES))
    P[0, S.PITCH, S.PITCH] = var
    _, P1 = _predict(_x(SPEED=v, PITCH=theta), accel=G * math.sin(theta), P=P)
    # north = V·cos θ·Δt: its variance (Δt·V·sin θ)²·σ_θ² from the pitch alone
    want = (DT * v * math.sin(theta)) ** 2 * var
    assert math.isclose(P1[0, S.NORTH, S.NORTH], want, rel_tol=1e-9)
    assert math.isclose(
        P1[0, S.SPEED, S.SPEED], (DT * G * math.cos(theta)) ** 2 * var, rel_tol=1e-9
    )


def _steady_inputs(accel: float, steady_s: float) -> object:
    from estimator.tracked.vehicle import TickInputs

    names = [f.name for f in dataclasses.fields(TickInputs)]
    values = {n: np.zeros(1) for n in names}
    values["accel_mps2"] = np.array([accel])
    values["steady_s"] = np.array([steady_s])
    return TickInputs(**values)  # type: ignore[arg-type]


def test_climbing_a_steady_grade_is_steady_and_speeding_up_on_the_level_is_not() -> None:
    cfg = TrackedEstimatorConfig()
    theta = math.atan(0.10)
    f = initial_filter(cfg)
    f.x[0, S.PITCH] = theta
    for _ in range(20):
        inp = accel_steady(f, _steady_inputs(G * math.sin(theta), 10.0), cfg)  # type: ignore[arg-type]
    assert math.isclose(float(inp.steady_s[0]), 2.0, abs_tol=1e-9)  # the hull's own: none
    assert abs(float(inp.accel_mps2[0])) < 1e-12
    assert float(inp.steady_s[0]) >= cfg.learn_steady_s  # the odometer factors learn there
    level = initial_filter(cfg)
    inp = accel_steady(level, _steady_inputs(0.5, 10.0), cfg)  # type: ignore[arg-type]
    assert float(inp.steady_s[0]) == 0.0 and float(inp.accel_mps2[0]) == 0.5


def test_the_traction_slip_reads_the_drawbar_pull_and_the_lag_the_hulls_acceleration() -> None:
    cfg = TrackedEstimatorConfig()
    p = VehicleParams.of(TrackedConfig())
    x = _x(SPEED=5.0, ACCEL_LAG=0.4, ACCEL_SLIP=0.05)
    state = np.array([int(MotionState.STRAIGHT)])

    def corrected(accel: float, pull: float) -> float:
        out = odometer_measurement(
            cfg,
            p,
            x,
            state,
            np.array([5.0]),
            np.zeros(1),
            np.array([accel]),
            np.zeros(1),
            np.ones(1, dtype=bool),
            None,
            np.array([pull]),
        )
        return float(out[4][0])

    pull = G * math.sin(math.atan(0.1))
    # climbing steadily: no lag, the traction slip of the pull (1 − κ·pull)
    assert math.isclose(corrected(0.0, pull), 5.0 * (1.0 - 0.05 * pull), rel_tol=1e-12)
    # speeding up on the level: both
    assert math.isclose(corrected(0.5, 0.5), 5.0 * (1.0 - 0.05 * 0.5) - 0.4 * 0.5, rel_tol=1e-12)


def test_the_antennas_lever_arm_is_pitched_and_rolled() -> None:
    p = VehicleParams.of(TrackedConfig())
    y, z = float(p.antenna_xy_m[0, 1]), float(p.antenna_up_m[0])
    theta = 0.1
    got = float(_antenna_ahead_m(_x(PITCH=theta), p)[0])
    assert math.isclose(got, y * math.cos(theta) - z * math.sin(theta), rel_tol=1e-12)
    assert z > 1.0 and got < -0.1  # a tall mast leans back 0.18 m on a 10 % grade
    x = float(p.antenna_xy_m[0, 0])
    phi = 0.05
    right = float(_antenna_right_m(_x(ROLL=phi), p)[0])
    assert math.isclose(right, x * math.cos(phi) + z * math.sin(phi), rel_tol=1e-12)
    assert right > 0.08  # and 9 cm to the low side on a 5 % side slope


@cache
def _hill_states() -> tuple[TrackedRun, np.ndarray, np.ndarray]:
    """``route_firm_hill`` seed 3 for 140 s (before its outage): the filter's state at
    every second and the stamps."""
    run = simulate_tracked("route_firm_hill", 3)
    fleet = TrackedFleet()
    fleet.add_vehicle("v", run.config)
    states, stamps = [], []
    t, i, ms = run.start_ns, 0, run.measurements
    while t < run.start_ns + 140 * SECOND:
        t += SECOND
        while i < len(ms) and ms[i][0] <= t:
            fleet.push("v", ms[i][1])
            i += 1
        list(fleet.advance({"v": t}))
        states.append(fleet.filter_state("v")[0])
        stamps.append(t)
    return run, np.array(states), np.array(stamps)


def test_pitch_and_roll_are_estimated_causally_on_a_hill() -> None:
    run, x, stamps = _hill_states()
    k = run.index_at(stamps - 100_000_000)  # the state is the last tick's, ≤ 0.1 s before
    late = slice(20, None)  # after the start
    pitch_err = x[late, S.PITCH] - run.truth.pitch_rad[k][late]
    roll_err = x[late, S.ROLL] - run.truth.roll_rad[k][late]
    assert np.abs(run.truth.pitch_rad[k][late]).max() > 0.09  # it drove over the hills
    # within the accelerometer's bias (0.03 m/s² ~ 3 mrad) and the ramps' few mrad of lag
    assert np.sqrt(np.mean(pitch_err**2)) < 0.006
    assert np.sqrt(np.mean(roll_err**2)) < 0.01
    # and the speed, whose prediction reads g·sin θ, stays on the truth
    speed_err = x[late, S.SPEED] - run.truth.speed_mps[k][late]
    assert np.sqrt(np.mean(speed_err**2)) < 0.1
