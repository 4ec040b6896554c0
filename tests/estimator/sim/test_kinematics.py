"""Truth self-consistency: eq. (2)-(5), eq. (8)(9) inversion, gravity in the specific force."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.config import VehicleGeometry, WheeledRearDriveConfig
from estimator.sim import GRAVITY_MPS2, rim_speed_from_slip, simulate, slip_from_speeds
from estimator.sim.kinematics import MotionPlan, integrate_plan, rotation_body_to_enu

START_NS = 1_700_000_000_000_000_000


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@given(st.floats(-math.pi, math.pi), st.floats(-0.5, 0.5), st.floats(-0.5, 0.5))
def test_rotation_is_yaw_pitch_roll_product(psi: float, theta: float, phi: float) -> None:
    r = rotation_body_to_enu(np.array([psi]), np.array([theta]), np.array([phi]))[0]
    np.testing.assert_allclose(r, _rz(-psi) @ _rx(theta) @ _ry(phi), atol=1e-12)
    # forward axis is the direction eq. (1) projects on
    fwd = [math.sin(psi) * math.cos(theta), math.cos(psi) * math.cos(theta), math.sin(theta)]
    np.testing.assert_allclose(r[:, 1], fwd, atol=1e-12)


@given(st.floats(0.01, 10.0), st.floats(-0.6, 0.6))
def test_slip_inversion_round_trip(ground_mps: float, slip: float) -> None:
    rim = rim_speed_from_slip(np.array([ground_mps]), np.array([slip]))
    back = slip_from_speeds(rim, np.array([ground_mps]))
    np.testing.assert_allclose(back, [slip], atol=1e-12)


def test_slip_definition_hand_cases() -> None:
    # driving: rW = 1.25, V = 1 -> S = 0.25/1.25 = 20 %
    assert slip_from_speeds(np.array([1.25]), np.array([1.0]))[0] == 0.2
    # braking: rW = 0.8, V = 1 -> S = -0.2/1 = -20 %
    np.testing.assert_allclose(slip_from_speeds(np.array([0.8]), np.array([1.0])), [-0.2])
    assert math.isnan(slip_from_speeds(np.array([0.0]), np.array([0.0]))[0])


def test_truth_satisfies_structural_relations() -> None:
    geo = VehicleGeometry(h0_m=1.1, h1_m=1.5, track_width_m=1.6)
    run = simulate(
        "figure_eight", seed=3, start_ns=START_NS, config=WheeledRearDriveConfig(geometry=geo)
    )
    tr = run.truth
    wx, wz = tr["pitch_rate_radps"], tr["yaw_rate_radps"]
    # eq. (2)(3): V1 = Vg + ωx·h1, V0 = V1 + ωx·h0
    np.testing.assert_allclose(tr["v1_mps"], tr["vg_mps"] + wx * geo.h1_m, atol=1e-12)
    np.testing.assert_allclose(tr["v0_mps"], tr["v1_mps"] + wx * geo.h0_m, atol=1e-12)
    # eq. (4)(5)
    np.testing.assert_allclose(tr["vl_mps"], tr["v0_mps"] - wz * geo.track_width_m / 2, atol=1e-12)
    np.testing.assert_allclose(tr["vr_mps"], tr["v0_mps"] + wz * geo.track_width_m / 2, atol=1e-12)
    # rim = r·W and slip from eq. (8)(9) on the truth speeds
    np.testing.assert_allclose(tr["rim_left_mps"], tr["omega_left_radps"] * geo.wheel_radius_left_m)
    for side, v in (("left", "vl_mps"), ("right", "vr_mps")):
        moving = tr[v] > 1e-3
        s = slip_from_speeds(tr[f"rim_{side}_mps"][moving], tr[v][moving])
        np.testing.assert_allclose(100 * s, tr[f"slip_{side}_pct"][moving], atol=1e-9)


def test_lever_arm_offsets_add_yaw_terms() -> None:
    geo = VehicleGeometry(antenna_offset_m=(0.3, 0.8), imu_offset_m=(-0.2, 0.5))
    run = simulate(
        "paper_circle", seed=4, start_ns=START_NS, config=WheeledRearDriveConfig(geometry=geo)
    )
    tr = run.truth
    wx, wz = tr["pitch_rate_radps"], tr["yaw_rate_radps"]
    np.testing.assert_allclose(
        tr["vg_mps"], tr["v0_mps"] + wz * 0.3 - wx * (geo.h0_m + geo.h1_m), atol=1e-12
    )
    np.testing.assert_allclose(tr["v1_mps"], tr["v0_mps"] - wz * 0.2 - wx * geo.h0_m, atol=1e-12)


def test_specific_force_at_rest_on_a_slope_is_gravity() -> None:
    theta, phi = math.radians(8.0), math.radians(-3.0)

    def still(t: np.ndarray) -> np.ndarray:
        return np.zeros_like(t)

    def slope(d: np.ndarray) -> np.ndarray:
        return np.full_like(d, theta)

    def bank(d: np.ndarray) -> np.ndarray:
        return np.full_like(d, phi)

    plan = MotionPlan(
        duration_s=2.0, speed_mps=still, terrain_pitch_rad=slope, terrain_roll_rad=bank
    )
    fine = integrate_plan(
        plan,
        fine_rate_hz=500.0,
        track_width_m=1.8,
        wheel_radius_m=(0.8, 0.8),
        rng=np.random.default_rng(0),
    )
    f = fine.specific_force_body(np.array([0.1, 0.2, 1.0]))
    g = GRAVITY_MPS2
    expected = [
        -g * math.sin(phi) * math.cos(theta),
        g * math.sin(theta),
        g * math.cos(phi) * math.cos(theta),
    ]
    np.testing.assert_allclose(f, np.tile(expected, (f.shape[0], 1)), atol=1e-12)
    assert np.all(fine.wheel_radps == 0.0)


def test_specific_force_when_moving_matches_kinematics() -> None:
    run = simulate(
        "slope_wet_patch",
        seed=5,
        start_ns=START_NS,
        accel_std_mps2=0.0,
        accel_bias_std_mps2=0.0,
        accel_bias_walk_mps2=0.0,
        gyro_std_radps=0.0,
        gyro_bias_std_radps=0.0,
        gyro_bias_walk_radps=0.0,
    )
    from estimator.sim import truth_at
    from estimator.types import ImuBatch

    imu = [m for m in run.measurements if isinstance(m, ImuBatch)]
    stamps = np.concatenate([m.stamp_ns for m in imu])
    accel = np.concatenate([m.accel_mps2 for m in imu])
    gyro = np.concatenate([m.gyro_radps for m in imu])
    pitch = truth_at(run.truth, stamps, "pitch_rad")
    a1 = truth_at(run.truth, stamps, "a1_mps2")
    # forward axis reads dv/dt + g·sinθ
    np.testing.assert_allclose(accel[:, 1], a1 + GRAVITY_MPS2 * np.sin(pitch), atol=1e-9)
    np.testing.assert_allclose(
        gyro[:, 2], truth_at(run.truth, stamps, "yaw_rate_radps"), atol=1e-12
    )
    # the climb reads about g·sin 8° ≈ 1.36 m/s² on the slope
    on_slope = pitch > math.radians(7.9)
    assert on_slope.any()
    # (body pitching adds lever-arm terms at the IMU height, hence the spread)
    assert abs(float(np.median(accel[on_slope, 1])) - 1.365) < 0.05
    assert np.all(np.abs(accel[on_slope, 1] - 1.365) < 0.4)


def test_heading_follows_yaw_rate_ccw() -> None:
    run = simulate("paper_circle", seed=6, start_ns=START_NS, heading0_deg=90.0)
    tr = run.truth
    heading = np.unwrap(tr["heading_rad"])
    moving = tr["v0_mps"][1:] > 0.5
    # counter-clockwise: heading (clockwise from north) decreases
    assert np.all(np.diff(heading)[moving] < 0)
    # circling at 0.4 rad/s after the lead-in: one lap ≈ 15.7 s
    circling = tr["stamp_ns"] >= START_NS + 6 * 10**9
    t = (tr["stamp_ns"][circling] - START_NS) * 1e-9
    rate = -(heading[circling][-1] - heading[circling][0]) / (t[-1] - t[0])
    assert abs(rate - 0.4) < 0.01
    # starting eastbound, turning left: goes north
    assert tr["north_m"][circling][0] > 0.5
    # the speed stays within 3.0 ± 0.03 m/s while circling
    assert np.all(np.abs(tr["v0_mps"][circling] - 3.0) <= 0.0301)


@settings(max_examples=12, deadline=None)
@given(
    st.floats(0.5, 2.0),
    st.floats(0.0, 3.0),
    st.floats(1.0, 2.5),
    st.tuples(st.floats(-0.5, 0.5), st.floats(-1.0, 1.0)),
    st.integers(0, 2**31),
)
def test_structural_relations_hold_for_any_geometry(
    h0: float, h1: float, b: float, antenna: tuple[float, float], seed: int
) -> None:
    geo = VehicleGeometry(h0_m=h0, h1_m=h1, track_width_m=b, antenna_offset_m=antenna)
    run = simulate(
        "hard_braking",
        seed=seed,
        start_ns=START_NS,
        config=WheeledRearDriveConfig(geometry=geo),
        cycles=1,
    )
    tr = run.truth
    wx, wz = tr["pitch_rate_radps"], tr["yaw_rate_radps"]
    np.testing.assert_allclose(
        tr["vg_mps"], tr["v0_mps"] + wz * antenna[0] - wx * (h0 + h1), atol=1e-12
    )
    np.testing.assert_allclose(tr["v1_mps"], tr["v0_mps"] - wx * h0, atol=1e-12)
    np.testing.assert_allclose(tr["vr_mps"] - tr["vl_mps"], wz * b, atol=1e-12)
    assert np.all(tr["vl_mps"] >= 0) and np.all(tr["vr_mps"] >= 0)
