"""The friction front end's small filters on hand-made sensor streams: the tilt gradients from
the receiver's attitude, the yaw gyro's bias from its heading, and the forward accelerometer's
bias kept apart from the body's pitch."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimator.config import ChassisConfig, DrivenAxle, Wheeled4wdSteeredConfig
from estimator.friction import FilterConfig
from estimator.friction.brush import load_adaptive_stiffness_n
from estimator.friction.frontend import (
    FrontEnd,
    FrontEndConfig,
    FrontEndTick,
    _TiltGradient,
    antenna_arm_m,
    antenna_velocity_at_cg,
    body_rates_radps,
    calibration_scale_var,
    consider_step,
    rim_persistent_std_mps,
    ringing_slip_std,
    spin_up_slip,
    tilted_arm_m,
)
from estimator.friction.model import GRAVITY_MPS2
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

CONFIG = Wheeled4wdSteeredConfig(
    chassis=ChassisConfig(
        driven_axle=DrivenAxle.REAR,
        drag_area_m2=0.0,
        rolling_resistance=0.0,
        pitch_gradient_deg_per_g=2.0,
    )
)
HEADING_RAD = 1.0


def test_tilt_gradient_from_changes_not_from_the_bank() -> None:
    """Fixes ``θ = s·a/g + bank`` with the reading stepping between 0 and 0.4 g: the slope
    comes out as ``s`` (prior 0.03, truth 0.05) within 2 %, the 0.05 rad bank left out."""
    fit = _TiltGradient(0.031, prior_weight=0.2, highpass_s=3.0)
    assert abs(fit.slope - 0.031 / 1.031) < 1e-12
    t_ns = 0
    for k in range(300):
        reading_g = 0.4 if (k // 30) % 2 else 0.0
        fit.fix(0.05 * reading_g + 0.05, reading_g, t_ns)
        t_ns += 100_000_000
    assert abs(fit.slope / 0.05 - 1.0) < 0.02
    fit.fix(math.nan, 0.1, t_ns)  # a receiver without attitude changes nothing
    assert abs(fit.slope / 0.05 - 1.0) < 0.02


def _drive(
    seconds: float, accel_mps2: float, accel_bias_mps2: float, gyro_bias_radps: float
) -> tuple[FrontEnd, list[FrontEndTick]]:
    """Straight ahead from 10 m/s at ``accel_mps2``; the body pitches by the config's gradient
    ×1.3, the forward accelerometer reads that leak and its bias, the yaw gyro its bias; GNSS
    (10 Hz) gives the true velocity, heading and pitch."""
    fe = FrontEnd(CONFIG, FrontEndConfig(), 0.02)
    pitch_rad = 1.3 * math.radians(CONFIG.chassis.pitch_gradient_deg_per_g) * accel_mps2
    pitch_rad /= GRAVITY_MPS2
    t_imu = np.arange(1, round(seconds * 100) + 1) * 10_000_000
    v = 10.0 + accel_mps2 * t_imu / 1e9
    accel = np.zeros((t_imu.size, 3))
    accel[:, 1] = accel_mps2 + GRAVITY_MPS2 * math.sin(pitch_rad) + accel_bias_mps2
    accel[:, 2] = GRAVITY_MPS2
    gyro = np.zeros((t_imu.size, 3))
    gyro[:, 2] = gyro_bias_radps
    fe.push_imu(ImuBatch(t_imu, accel, gyro))
    radius = CONFIG.tyre.unloaded_radius_m
    fe.push_wheels(WheelSpeeds4(t_imu[1::2], np.repeat(v[1::2, None] / radius, 4, axis=1)))
    fe.push_steering(SteeringAngles(t_imu[1::2], np.zeros(t_imu.size // 2)))
    for k in range(9, t_imu.size, 10):
        fe.push_gnss(
            GnssSample(
                stamp_ns=int(t_imu[k]),
                vel_enu_mps=(v[k] * math.sin(HEADING_RAD), v[k] * math.cos(HEADING_RAD), 0.0),
                heading_rad=HEADING_RAD,
                pitch_rad=pitch_rad if t_imu[k] > 1e9 else 0.0,
                roll_rad=0.0,
                lat_deg=48.0,
                lon_deg=11.0,
                height_m=500.0,
            )
        )
    ticks = [fe.tick(int(t)) for t in range(20_000_000, int(t_imu[-1]) + 1, 20_000_000)]
    return fe, [t for t in ticks if t is not None]


def test_yaw_gyro_bias_learnt_from_the_heading() -> None:
    """A yaw gyro reading 0.003 rad/s on a straight (the receiver's heading constant): within
    10 s the front end's yaw rate is within 3e-4 rad/s of 0 (at 15 m/s, 4.5e-3 m/s² of lateral
    acceleration where the side-slip filter's bias would otherwise take 0.045)."""
    fe, ticks = _drive(10.0, 0.0, 0.0, 0.003)
    assert abs(fe.yaw.bias - 0.003) < 3e-4
    assert abs(ticks[-1].yaw_rate_radps) < 3e-4


def test_forward_bias_is_the_sensors_not_the_pitch() -> None:
    """Accelerating at 1.5 m/s² with an accelerometer bias of 0.04 m/s² and a body that pitches
    1.3 times the config's gradient: the speed filter's bias state holds the 0.04 (not the
    pitch's leak of 0.07) and the measured ``a_x`` is 1.5 m/s² within 0.015 once the pitch
    gradient is learnt (after 4 s)."""
    fe, ticks = _drive(8.0, 1.5, 0.04, 0.0)
    assert abs(fe.vx.bias - 0.04) < 0.01
    late = [t.z[0] for t in ticks[-100:]]
    assert abs(float(np.mean(late)) - 1.5) < 0.015


def test_the_leak_of_the_lagged_reading_is_taken_out() -> None:
    """A 0.3 s ramp of the lateral acceleration to 4 m/s²: the body rolls behind it (the
    config's roll gradient through its load-transfer lag), so the accelerometer reads
    ``a + g sin(k ā/g)``. The front end's ``a_y`` stays within 0.01 m/s² of ``a`` through the
    ramp; taking ``s`` of the instantaneous reading instead would be 0.07 m/s² low there,
    which integrated into ``v_y`` stays as a side-slip error."""
    fe = FrontEnd(CONFIG, FrontEndConfig(), 0.02)
    k = math.radians(CONFIG.chassis.roll_gradient_deg_per_g)
    gain = 1.0 - math.exp(-0.02 / CONFIG.chassis.load_transfer_lag_s)
    lagged = 0.0
    errors, instantaneous = [], []
    for n in range(100):
        a = 4.0 * min(n * 0.02 / 0.3, 1.0)
        lagged += (a - lagged) * gain
        reading = a + GRAVITY_MPS2 * math.sin(k * lagged / GRAVITY_MPS2)
        fe._learn_tilt(0.0, reading, fresh=False)
        errors.append(fe._detilt(0.0, reading)[1] - a)
        instantaneous.append(reading * (1.0 - fe.roll.slope) - a)
    assert max(abs(e) for e in errors) < 0.01
    assert min(instantaneous) < -0.06


def test_the_accelerations_are_carried_to_the_tick() -> None:
    """100 Hz IMU samples in 20 ms ticks: their mean lies 5 ms before the tick. On a ramp of
    14 m/s³ (a 0.3 s steering ramp to 4.2 m/s²) that mean is 0.07 m/s² behind; carried along
    its change since the last tick it is the value at the tick (the first tick: as read)."""
    fe = FrontEnd(CONFIG, FrontEndConfig(), 0.02)
    t_ns = np.arange(1, 11) * 10_000_000
    fe.push_imu(ImuBatch(t_ns, np.zeros((10, 3)), np.zeros((10, 3))))
    window = fe._imu_window(20_000_000)
    assert window is not None and abs(window[2] - 0.005) < 1e-15
    for n in range(6):
        t_s = 0.02 * n
        mean = 14.0 * (t_s - 0.005)
        ax, ay = fe._at_tick(0.5 * mean, mean, 0.005)
        want = mean if n == 0 else 14.0 * t_s
        assert abs(ay - want) < 1e-12 and abs(ax - 0.5 * want) < 1e-12


def _ringing_wheel(amplitude: float) -> list[FrontEndTick]:
    """Straight at 12 m/s for 6 s; from 3 s the rear-left wheel rings on its tyre at 105 Hz,
    ``ω = v/r (1 + A sin(2π 105 t) e^{−(t−3)/0.3})`` (a stiff tyre's wheel mode after a torque
    step), its CAN readings (50 Hz, rounded to 0.025 rad/s) aliasing the ring into a 5 Hz
    swing; GNSS (10 Hz) gives the true velocity."""
    fe = FrontEnd(CONFIG, FrontEndConfig(), 0.02)
    t_imu = np.arange(1, 601) * 10_000_000
    accel = np.zeros((t_imu.size, 3))
    accel[:, 2] = GRAVITY_MPS2
    fe.push_imu(ImuBatch(t_imu, accel, np.zeros((t_imu.size, 3))))
    t_s = t_imu[1::2] / 1e9
    omega = np.full((t_s.size, 4), 12.0 / CONFIG.tyre.unloaded_radius_m)
    late = np.maximum(t_s - 3.0, 0.0)
    ring = amplitude * np.sin(2 * math.pi * 105.0 * t_s) * np.exp(-late / 0.3)
    omega[:, 2] *= 1.0 + np.where(t_s >= 3.0, ring, 0.0)
    fe.push_wheels(WheelSpeeds4(t_imu[1::2], np.round(omega / 0.025) * 0.025))
    fe.push_steering(SteeringAngles(t_imu[1::2], np.zeros(t_s.size)))
    for k in range(9, t_imu.size, 10):
        fe.push_gnss(
            GnssSample(
                stamp_ns=int(t_imu[k]),
                vel_enu_mps=(12.0 * math.sin(HEADING_RAD), 12.0 * math.cos(HEADING_RAD), 0.0),
                heading_rad=HEADING_RAD,
                pitch_rad=0.0,
                roll_rad=0.0,
                lat_deg=48.0,
                lon_deg=11.0,
                height_m=500.0,
            )
        )
    ticks = [fe.tick(int(t)) for t in range(20_000_000, int(t_imu[-1]) + 1, 20_000_000)]
    return [t for t in ticks if t is not None]


def test_a_ringing_wheel_keeps_its_slip_uncertain() -> None:
    """The ringing rear-left wheel of :func:`_ringing_wheel` (a 2 % swing of its speed):
    wherever its relaxed κ has been swung away from its partner's by more than twice the μ
    gate's ``learn_mu_max_kappa_std`` (3e-3), κ's 1-σ is above the gate, so μ does not learn
    from it (the relaxation term alone falls to 0.9e-3 there, as the relaxed slip catches up
    with the slow alias). Before the ring, and once it has died out, the 1-σ is the still
    wheels'."""
    gate = FilterConfig().learn_mu_max_kappa_std
    ticks = _ringing_wheel(0.02)
    t_s = 0.02 * np.arange(1, len(ticks) + 1)
    kappa = np.array([t.kappa for t in ticks])
    k_std = np.array([t.kappa_std for t in ticks])
    swung = np.abs(kappa[:, 2] - kappa[:, 3])
    assert swung.max() > 3 * gate  # the alias does swing the relaxed slip
    far = swung > 2 * gate
    assert far.sum() >= 3 and np.all(k_std[far, 2] > gate)
    for quiet in (t_s < 2.9, t_s > 5.5):
        assert np.all(np.abs(k_std[quiet, 2] - k_std[quiet, 3]) < 2e-4)
    still = _ringing_wheel(0.0)
    assert np.allclose([t.kappa_std for t in still][-50:], k_std[-50:], atol=2e-4)


def test_ringing_slip_std_by_hand() -> None:
    """``ring ← ring + g (max(|κ − κ_prev| − rounding, 0) − ring)``: a change of 5e-3 with
    1e-3 of rounding at ``g`` 0.5 from 2e-3 gives 3e-3; a change within the rounding lets it
    fall by ``g``; no previous reading counts as no change; per wheel ``(B, 4)``."""
    kappa = np.array([[5e-3, 5e-4, 0.0, -5e-3]])
    prev = np.array([[0.0, 0.0, math.nan, 0.0]])
    ring = np.full((1, 4), 2e-3)
    out = ringing_slip_std(kappa, prev, ring, 0.5, np.full((1, 4), 1e-3))
    assert np.allclose(out, [[3e-3, 1e-3, 1e-3, 3e-3]], rtol=1e-12)


def _accelerating_after_calibration(scale_err: float) -> tuple[np.ndarray, list[FrontEndTick]]:
    """6 s at 10 m/s with GNSS reading ``1 − scale_err`` of the speed (the radii learnt that
    much small), then 2 m/s² for 6 s without GNSS on the rims alone; the wheel speeds are the
    tone rings' means over the 0.02 s window before each reading, on radii that fall with the
    load as ``ρ = 1/3``. Returns the true speeds at the ticks and the ticks."""
    fe = FrontEnd(CONFIG, FrontEndConfig(), 0.02)
    ch, ty = CONFIG.chassis, CONFIG.tyre
    t_imu = np.arange(1, 1201) * 10_000_000
    t_s = t_imu / 1e9
    accel_mps2 = np.where(t_s > 6.0, 2.0, 0.0)

    def distance_m(t: np.ndarray) -> np.ndarray:
        after = np.maximum(t - 6.0, 0.0)
        return 10.0 * t + after * after

    accel = np.zeros((t_s.size, 3))
    accel[:, 1], accel[:, 2] = accel_mps2, GRAVITY_MPS2
    fe.push_imu(ImuBatch(t_imu, accel, np.zeros((t_s.size, 3))))
    wheelbase = ch.cg_to_front_axle_m + ch.cg_to_rear_axle_m
    static_n = ch.mass_kg * GRAVITY_MPS2 / (2 * wheelbase)
    static_n *= np.array([ch.cg_to_rear_axle_m] * 2 + [ch.cg_to_front_axle_m] * 2)
    t_w = t_s[1::2]
    a_w = np.where(t_w > 6.0, 2.0, 0.0)[:, None]
    # the body's load moves back with the acceleration (after the chassis's lag), the rims
    # roll on radii that follow it, and the undriven front wheels slip as they spin up
    settled = 1.0 - np.exp(-np.maximum(t_w - 6.0, 0.0) / ch.load_transfer_lag_s)[:, None]
    moved_n = ch.mass_kg * ch.cg_height_m * a_w * settled / (2 * wheelbase)
    fz_n = static_n + moved_n * np.array([-1.0, -1.0, 1.0, 1.0])
    radius_m = ty.unloaded_radius_m - fz_n / (3.0 * ty.kz_npm)
    c_x = load_adaptive_stiffness_n(fz_n, ty.kz_npm, ty.unloaded_radius_m, ty.c_px_npm2)
    slip = spin_up_slip(a_w, radius_m, c_x, FrontEndConfig().wheel_inertia_kgm2)
    slip[:, 2:] = 0.0  # the driven rear wheels: no reading of the speed
    window_mps = (distance_m(t_w) - distance_m(t_w - 0.02)) / 0.02
    fe.push_wheels(WheelSpeeds4(t_imu[1::2], window_mps[:, None] * (1.0 + slip) / radius_m))
    fe.push_steering(SteeringAngles(t_imu[1::2], np.zeros(t_w.size)))
    for k in range(9, 600, 10):
        v = (1.0 - scale_err) * 10.0
        fe.push_gnss(
            GnssSample(
                stamp_ns=int(t_imu[k]),
                vel_enu_mps=(v * math.sin(HEADING_RAD), v * math.cos(HEADING_RAD), 0.0),
                heading_rad=HEADING_RAD,
                pitch_rad=0.0,
                roll_rad=0.0,
                lat_deg=48.0,
                lon_deg=11.0,
                height_m=500.0,
            )
        )
    stamps = range(20_000_000, int(t_imu[-1]) + 1, 20_000_000)
    ticks = [(t / 1e9, fe.tick(t)) for t in stamps]
    kept = [(t, k) for t, k in ticks if k is not None and t > 6.5]
    true_mps = np.array([10.0 + 2.0 * (t - 6.0) for t, _ in kept])
    return true_mps, [k for _, k in kept]


def test_the_stated_speed_std_covers_the_window_lag_and_the_radius_scale() -> None:
    """Accelerating at 2 m/s² on radii learnt 8e-4 small (about twice the calibration's stated
    scale 1-σ at 10 m/s): the speed reads ``ε v + a T/2`` low (0.026-0.036 m/s), persistently.
    The speed filter's own 1-σ (``kappa_common_std`` × v) covers it on few ticks; the stated
    ``vx_std_mps`` on nearly every tick, and it is not blown up (median under 2 × the RMS
    error)."""
    true_mps, ticks = _accelerating_after_calibration(8e-4)
    assert len(ticks) > 250
    err = np.array([k.vx_mps for k in ticks]) - true_mps
    assert np.median(err) < -0.02  # the persistent error is there
    own = np.array([k.kappa_common_std * max(abs(k.vx_mps), 1.0) for k in ticks])
    stated = np.array([k.vx_std_mps for k in ticks])
    assert np.mean(np.abs(err) < 2 * own) < 0.5
    assert np.mean(np.abs(err) < 2 * stated) > 0.95
    assert np.median(stated) < 2.0 * math.sqrt(float(np.mean(err * err)))


def test_speed_std_helpers_by_hand() -> None:
    """The considered parts, hand-computed: the window's lag and the scale; the calibration's
    scale variance through two epochs; a reading's and a GNSS fix's step of the persistent
    error."""
    got = rim_persistent_std_mps(-2.0, 20.0, 5e-4, 0.003, 0.02)
    assert abs(got - math.sqrt(0.02**2 + 0.01**2 + 0.003**2)) < 1e-15
    var = calibration_scale_var(1e-4, 1.0, 10.0)  # the first epoch forgets the prior
    assert abs(var - (0.03 / 10.0) ** 2) < 1e-18
    var2 = calibration_scale_var(var, 0.5, 10.0)  # the second halves it
    assert abs(var2 - 0.25 * var - 0.25 * (0.03 / 10.0) ** 2) < 1e-18
    assert abs(consider_step(0.01, 0.25, 0.03) - (0.75 * 0.01 + 0.25 * 0.03)) < 1e-15
    assert abs(consider_step(0.01, 0.25, 0.0) - 0.0075) < 1e-15


def _body_fix(
    stamp_ns: int,
    ahead_mps: float,
    left_mps: float,
    heading_rad: float,
    pitch_rad: float = math.nan,
    roll_rad: float = math.nan,
) -> GnssSample:
    """A fix whose velocity is ``ahead_mps`` along and ``left_mps`` across the compass
    heading ``heading_rad``, turned into east and north."""
    h = heading_rad
    return GnssSample(
        stamp_ns=stamp_ns,
        vel_enu_mps=(
            ahead_mps * math.sin(h) - left_mps * math.cos(h),
            ahead_mps * math.cos(h) + left_mps * math.sin(h),
            0.0,
        ),
        heading_rad=h,
        pitch_rad=pitch_rad,
        roll_rad=roll_rad,
        lat_deg=48.0,
        lon_deg=11.0,
        height_m=500.0,
    )


def test_the_gnss_lateral_speed_is_the_cgs_with_the_antenna_off_the_cg() -> None:
    """A steady left turn, 15 m/s at 0.25 rad/s, the CG drifting 0.1 m/s to the right, the
    antenna 2.0 m ahead of the CG and 0.3 m right of it: the receiver reads ``v_y + r·2.0``
    (+0.4 m/s) across its heading and ``v_x + r·0.3`` along it. The front end's GNSS lateral
    speed is the CG's −0.1 m/s within 0.01 m/s on every epoch after the first second (the
    antenna's would be 0.5 m/s off), and its speed the CG's 15 m/s within 0.02 (the
    antenna's: 0.075 off)."""
    chassis = dataclasses.replace(CONFIG.chassis, antenna_lever_arm_m=(0.3, 2.0, 1.8))
    fe = FrontEnd(dataclasses.replace(CONFIG, chassis=chassis), FrontEndConfig(), 0.02)
    speed_mps, rate_radps, vy_mps = 15.0, 0.25, -0.1
    t_imu = np.arange(1, 601) * 10_000_000
    accel = np.zeros((t_imu.size, 3))
    accel[:, 0] = -rate_radps * speed_mps  # the IMU's X is right: a left turn reads negative
    accel[:, 2] = GRAVITY_MPS2
    gyro = np.zeros((t_imu.size, 3))
    gyro[:, 2] = rate_radps
    fe.push_imu(ImuBatch(t_imu, accel, gyro))
    omega = np.full((t_imu.size // 2, 4), speed_mps / CONFIG.tyre.unloaded_radius_m)
    fe.push_wheels(WheelSpeeds4(t_imu[1::2], omega))
    fe.push_steering(SteeringAngles(t_imu[1::2], np.full(t_imu.size // 2, 0.75)))
    ahead = speed_mps + rate_radps * 0.3
    left = vy_mps + rate_radps * 2.0
    for k in range(9, t_imu.size, 10):
        h = HEADING_RAD - rate_radps * t_imu[k] / 1e9  # compass: a left turn lowers it
        fe.push_gnss(_body_fix(int(t_imu[k]), ahead, left, h))
    ticks = [fe.tick(int(t)) for t in range(20_000_000, int(t_imu[-1]) + 1, 20_000_000)]
    late = [t for t in ticks[50:] if t is not None and t.gnss]
    assert len(late) >= 40
    assert max(abs(t.vy_gnss_mps - vy_mps) for t in late) < 0.01
    assert abs(late[-1].vx_mps - speed_mps) < 0.02


def test_the_rigid_body_transfer_by_hand_on_a_rolling_body() -> None:
    """``v_cg = v_ant − ω × d``: the gyro's (X right, Y forward, Z up) ``(0.05, 0.2, ·)`` is a
    roll rate ``p`` 0.2 rad/s (right side going down) and a pitch rate ``q`` −0.05 (nose going
    up) about x forward, y left; yaw 0.1. The arm 1.0 m ahead, 0.4 m left, 2.0 m above the
    tilt axis: ``v_x = 15 + 0.1·0.4 − (−0.05)·2.0 = 15.14``, ``v_y = 0.3 − 0.1·1.0 + 0.2·2.0 =
    0.6``; the negated arm takes it back. Rolled 0.1 rad (no pitch) the arm turns about x:
    ``(1.0, 0.4 cos 0.1 − 2.0 sin 0.1, 0.4 sin 0.1 + 2.0 cos 0.1)``. The config's arm is from
    the ground (x right, y forward) and the axis height comes off its height."""
    rates = body_rates_radps(np.array([0.05, 0.2, 9.9]), 0.1)
    assert np.allclose(rates, [0.2, -0.05, 0.1], rtol=0, atol=1e-15)
    arm = np.array([1.0, 0.4, 2.0])
    cg = antenna_velocity_at_cg(np.array([15.0, 0.3]), rates, arm)
    assert np.allclose(cg, [15.14, 0.6], rtol=0, atol=1e-12)
    back = antenna_velocity_at_cg(cg, rates, -arm)
    assert np.allclose(back, [15.0, 0.3], rtol=0, atol=1e-12)
    rolled = tilted_arm_m(arm, 0.1, 0.0)
    want = [
        1.0,
        0.4 * math.cos(0.1) - 2.0 * math.sin(0.1),
        0.4 * math.sin(0.1) + 2.0 * math.cos(0.1),
    ]
    assert np.allclose(rolled, want, rtol=0, atol=1e-15)
    pitched = tilted_arm_m(arm, 0.0, 0.1)  # nose up: a raised antenna moves back
    assert pitched[0] == pytest.approx(1.0 * math.cos(0.1) - 2.0 * math.sin(0.1), abs=1e-15)
    chassis = dataclasses.replace(
        CONFIG.chassis, antenna_lever_arm_m=(-0.4, 1.0, 2.3), tilt_axis_height_m=0.3
    )
    assert antenna_arm_m(chassis) == pytest.approx((1.0, 0.4, 2.0), abs=1e-15)


def _swaying_mast(roll_gyro_bias_radps: float) -> tuple[list[FrontEndTick], float]:
    """Straight at 15 m/s for 6 s, the body swaying in roll about its axis 0.3 m above the
    ground (``φ = 0.03 sin(2π·0.5 t)``, a roll rate up to 0.094 rad/s), the antenna 2.5 m up,
    the receiver giving its roll: the ticks with a fresh epoch after the first second, and
    the largest lateral speed the receiver reads after it."""
    chassis = dataclasses.replace(
        CONFIG.chassis, antenna_lever_arm_m=(0.0, 0.5, 2.5), tilt_axis_height_m=0.3
    )
    fe = FrontEnd(dataclasses.replace(CONFIG, chassis=chassis), FrontEndConfig(), 0.02)
    speed_mps, height_m, w = 15.0, 2.2, 2 * math.pi * 0.5
    t_imu = np.arange(1, 601) * 10_000_000
    t_s = t_imu / 1e9
    roll, roll_rate = 0.03 * np.sin(w * t_s), 0.03 * w * np.cos(w * t_s)
    accel = np.zeros((t_imu.size, 3))
    accel[:, 0] = -GRAVITY_MPS2 * np.sin(roll)  # the IMU's X is right: it leans with the body
    accel[:, 2] = GRAVITY_MPS2 * np.cos(roll)
    gyro = np.zeros((t_imu.size, 3))
    gyro[:, 1] = roll_rate + roll_gyro_bias_radps  # about Y forward: right side down
    fe.push_imu(ImuBatch(t_imu, accel, gyro))
    omega = np.full((t_imu.size // 2, 4), speed_mps / CONFIG.tyre.unloaded_radius_m)
    fe.push_wheels(WheelSpeeds4(t_imu[1::2], omega))
    fe.push_steering(SteeringAngles(t_imu[1::2], np.zeros(t_imu.size // 2)))
    left = -height_m * roll_rate * np.cos(roll)
    h = HEADING_RAD
    for k in range(9, t_imu.size, 10):
        fe.push_gnss(_body_fix(int(t_imu[k]), speed_mps, left[k], h, 0.0, float(roll[k])))
    ticks = [fe.tick(int(t)) for t in range(20_000_000, int(t_imu[-1]) + 1, 20_000_000)]
    late = [t for t in ticks[50:] if t is not None and t.gnss]
    assert len(late) >= 40
    return late, float(np.max(np.abs(left[100:])))


def test_the_gnss_lateral_speed_is_the_cgs_under_a_swaying_mast() -> None:
    """The receiver reads ``−2.2 φ̇ cos φ`` across its heading (up to 0.21 m/s) while the CG
    does not move sideways (:func:`_swaying_mast`): the front end's GNSS lateral speed is
    the CG's 0 within 0.01 m/s on every epoch after the first second (left with the yaw's
    arm alone it is the antenna's)."""
    late, sway_mps = _swaying_mast(0.0)
    assert sway_mps > 0.2
    assert max(abs(t.vy_gnss_mps) for t in late) < 0.01


def test_the_roll_gyros_bias_is_learnt_from_the_receivers_roll() -> None:
    """The same sway with the roll gyro 0.01 rad/s off (times the 2.2 m mast: 0.022 m/s
    across): the receiver's roll corrects the bias as its heading does the yaw gyro's, and
    from the third second on the GNSS lateral speed is the CG's within 0.005 m/s."""
    late, _ = _swaying_mast(0.01)
    after = late[-30:]
    assert len(after) == 30
    assert max(abs(t.vy_gnss_mps) for t in after) < 0.005
