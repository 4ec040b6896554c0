"""Simulator conditions beyond the named scenarios: body sway, slip steps, GNSS epoch phase and
jitter, stream clock offsets, IMU misalignment, the random drive."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from estimator.config import VehicleGeometry, WheeledRearDriveConfig
from estimator.sim import GRAVITY_MPS2, simulate, truth_at
from estimator.sim.kinematics import rotation_body_to_enu
from estimator.sim.sensors import imu_mounting
from estimator.types import GnssFix, GnssSample, ImuBatch, Wheel, WheelEdges

START_NS = 1_700_000_000_000_000_000


def _gnss(run) -> list[GnssSample]:  # type: ignore[no-untyped-def]
    return [m for m in run.measurements if isinstance(m, GnssSample) and m.fix != GnssFix.NONE]


def _imu(run) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    batches = [m for m in run.measurements if isinstance(m, ImuBatch)]
    return (
        np.concatenate([b.stamp_ns for b in batches]),
        np.concatenate([b.accel_mps2 for b in batches]),
        np.concatenate([b.gyro_radps for b in batches]),
    )


def _edges(run, wheel: Wheel) -> np.ndarray:  # type: ignore[no-untyped-def]
    parts = [m.stamp_ns for m in run.measurements if isinstance(m, WheelEdges) and m.wheel == wheel]
    return np.concatenate(parts)


def _quiet() -> dict[str, Any]:
    """Sensors without noise or bias, so a test sees only the condition it sets."""
    return {
        "gnss_vel_std_mps": 0.0,
        "gnss_outlier_prob": 0.0,
        "accel_std_mps2": 0.0,
        "gyro_std_radps": 0.0,
        "accel_bias_std_mps2": 0.0,
        "gyro_bias_std_radps": 0.0,
        "accel_bias_walk_mps2": 0.0,
        "gyro_bias_walk_radps": 0.0,
        "tooth_error_rel": 0.0,
    }


def test_body_sway_moves_pitch_roll_and_the_mast_top() -> None:
    cfg = WheeledRearDriveConfig(geometry=VehicleGeometry(h0_m=1.2, h1_m=3.0))
    run = simulate(
        "slope_wet_patch",
        seed=3,
        start_ns=START_NS,
        config=cfg,
        sway_hz=1.5,
        sway_pitch_deg=4.0,
        sway_roll_deg=3.0,
        slope_deg=0.0,
        cross_slope_deg=0.0,
    )
    tr = run.truth
    cruise = (tr["v0_mps"] > 1.5) & (tr["v0_mps"] < 2.5)
    assert math.degrees(np.max(np.abs(tr["pitch_rad"][cruise]))) == pytest.approx(4.0, abs=0.3)
    assert math.degrees(np.max(np.abs(tr["roll_rad"][cruise]))) == pytest.approx(3.0, abs=0.3)
    # ωx ≈ 2π·f·A_θ; the antenna 4.2 m up moves forward at V0 − ωx·(h0 + h1)
    wx = tr["pitch_rate_radps"][cruise]
    assert np.max(np.abs(wx)) == pytest.approx(2 * math.pi * 1.5 * math.radians(4.0), rel=0.1)
    np.testing.assert_allclose(tr["vg_mps"][cruise], tr["v0_mps"][cruise] - wx * 4.2, atol=1e-9)
    # no sway at standstill
    assert np.all(np.abs(tr["pitch_rate_radps"][tr["v0_mps"] == 0.0]) < 0.03)


def test_body_sway_leaves_the_slip_to_the_grade_under_the_axle() -> None:
    """The cab swings about the axle; the ground under the wheels does not: the truth's slip
    is the same with and without a 4° pitch sway (it read the sway as a grade: ±~2 pp)."""
    kw = {"slope_deg": 0.0, "cross_slope_deg": 0.0, "sway_hz": 1.5, "sway_roll_deg": 0.0}
    still = simulate("slope_wet_patch", seed=3, start_ns=START_NS, sway_pitch_deg=0.0, **kw)
    sway = simulate("slope_wet_patch", seed=3, start_ns=START_NS, sway_pitch_deg=4.0, **kw)
    cruise = sway.truth["v0_mps"] > 1.5
    assert math.degrees(np.max(np.abs(sway.truth["pitch_rad"][cruise]))) > 3.5
    for side in ("left", "right"):
        d = sway.truth[f"slip_{side}_pct"] - still.truth[f"slip_{side}_pct"]
        assert np.nanmax(np.abs(d)) < 1e-9


def test_slip_steps_add_to_both_wheels_at_constant_speed() -> None:
    kw = {"slope_deg": 0.0, "cross_slope_deg": 0.0, "mu_wet": 0.6, "slip_texture": 0.0}
    base = simulate("slope_wet_patch", seed=4, start_ns=START_NS, **kw)
    run = simulate(
        "slope_wet_patch",
        seed=4,
        start_ns=START_NS,
        slip_steps=((20.0, 11.0, 0.0), (40.0, -11.0, 1.5)),
        **kw,
    )
    d = run.truth["slip_left_pct"] - base.truth["slip_left_pct"]
    t = (run.truth["stamp_ns"] - START_NS) * 1e-9
    np.testing.assert_allclose(d[(t > 20.0) & (t < 40.0)], 11.0, atol=0.2)
    assert np.all(np.abs(d[(t > 10.0) & (t < 19.9)]) < 1e-9)
    assert np.all(np.abs(d[(t > 41.6) & (t < 50.0)]) < 0.2)
    mid = (t > 40.6) & (t < 41.0)
    assert np.all((d[mid] > 1.0) & (d[mid] < 10.0))  # a ramp, not a jump
    assert np.array_equal(run.truth["v0_mps"], base.truth["v0_mps"])


def test_gnss_epochs_phase_and_jitter_describe_their_own_instant() -> None:
    run = simulate("figure_eight", seed=5, start_ns=START_NS, gnss_epoch_phase_ms=40.0, **_quiet())
    stamps = np.array([g.stamp_ns for g in _gnss(run)]) - START_NS
    assert np.all(stamps % 100_000_000 == 40_000_000)
    jit = simulate("figure_eight", seed=5, start_ns=START_NS, gnss_epoch_jitter_ms=20.0, **_quiet())
    gs = _gnss(jit)
    off = (np.array([g.stamp_ns for g in gs]) - START_NS) % 100_000_000
    off = np.where(off > 50_000_000, off - 100_000_000, off) * 1e-6
    assert np.max(np.abs(off)) <= 20.0 and np.std(off) > 5.0
    # the velocity is the antenna's at the stamp (to the 2 ms fine grid)
    stamp = np.array([g.stamp_ns for g in gs])
    speed = np.array([math.hypot(g.vel_enu_mps[0], g.vel_enu_mps[1]) for g in gs])
    true = truth_at(jit.truth, stamp, "vg_mps")
    moving = true > 1.0
    assert np.max(np.abs(speed[moving] - true[moving])) < 0.02


def test_clock_offsets_shift_each_stream_against_the_truth() -> None:
    quiet = _quiet()
    base = simulate("hard_braking", seed=6, start_ns=START_NS, **quiet)
    run = simulate(
        "hard_braking", seed=6, start_ns=START_NS, clock_offset_ms=(-80.0, 40.0, 60.0), **quiet
    )
    # GNSS 80 ms early: the epoch stamped t carries the velocity of t + 80 ms
    g0, g1 = _gnss(base), _gnss(run)
    v0 = np.array([g.vel_enu_mps[1] for g in g0])
    v1 = np.array([g.vel_enu_mps[1] for g in g1])
    assert np.allclose(
        v1[:-1],
        np.interp(
            np.array([g.stamp_ns for g in g1[:-1]]) + 80_000_000,
            np.array([g.stamp_ns for g in g0]),
            v0,
        ),
        atol=0.05,
    )
    # the IMU 40 ms ahead: its sample stamped t is the truth at t − 40 ms
    t0, a0, _ = _imu(base)
    t1, a1, _ = _imu(run)
    assert np.array_equal(t0, t1)
    np.testing.assert_array_equal(a1[100:, 1], a0[96:-4, 1])
    # wheel edges 60 ms late
    e0, e1 = _edges(base, Wheel.LEFT), _edges(run, Wheel.LEFT)
    assert e1.size <= e0.size
    np.testing.assert_array_equal(e1, e0[: e1.size] + 60_000_000)


def test_imu_misalignment_turns_what_the_imu_reads() -> None:
    run = simulate(
        "hard_braking",
        seed=7,
        start_ns=START_NS,
        imu_misalign_deg=(3.0, 2.0),
        **_quiet(),
    )
    stamps, accel, gyro = _imu(run)
    rest = (truth_at(run.truth, stamps - 20_000_000, "v0_mps") == 0.0) & (
        truth_at(run.truth, stamps + 20_000_000, "v0_mps") == 0.0
    )
    # standing on level ground: the forward axis reads g·sin(2°), like a 2° slope
    np.testing.assert_allclose(
        accel[rest, 1], GRAVITY_MPS2 * math.sin(math.radians(2.0)), atol=1e-6
    )
    # the turn is the rotation of the IMU's axes in the body frame
    r = imu_mounting((3.0, 2.0))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    ref = rotation_body_to_enu(
        np.array([-math.radians(3.0)]), np.array([math.radians(2.0)]), np.array([0.0])
    )[0]
    np.testing.assert_allclose(r, ref, atol=1e-12)
    # hard braking along the body's forward axis leaks sin(3°) of it into the lateral reading
    moving = np.abs(truth_at(run.truth, stamps, "a0_mps2")) > 2.0
    a_fwd = truth_at(run.truth, stamps[moving], "a0_mps2")
    lateral = accel[moving, 0]
    ratio = np.median(lateral / a_fwd)
    assert ratio == pytest.approx(math.sin(math.radians(3.0)), abs=0.01)
    assert not np.allclose(gyro, 0.0)


@pytest.mark.parametrize("seed", range(6))
def test_random_drive_starts_and_ends_at_rest_within_its_speeds(seed: int) -> None:
    run = simulate(
        "random_drive", seed=seed, start_ns=START_NS, speed_min_mps=0.2, speed_max_mps=0.8
    )
    v = run.truth["v0_mps"]
    assert v[0] == 0.0 and v[-1] == 0.0
    assert v.max() <= 0.8 + 0.06
    assert np.all(run.truth["vl_mps"] >= 0) and np.all(run.truth["vr_mps"] >= 0)
    assert run.duration_s >= 150.0
    fast = simulate("random_drive", seed=seed, start_ns=START_NS)
    assert 1.0 < np.percentile(fast.truth["v0_mps"], 90) <= 4.06
    assert np.max(np.abs(fast.truth["yaw_rate_radps"])) > 0.02
