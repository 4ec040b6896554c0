"""The friction front end's small filters on hand-made sensor streams: the tilt gradients from
the receiver's attitude, the yaw gyro's bias from its heading, and the forward accelerometer's
bias kept apart from the body's pitch."""

from __future__ import annotations

import math

import numpy as np

from estimator.config import ChassisConfig, DrivenAxle, Wheeled4wdSteeredConfig
from estimator.friction.frontend import FrontEnd, FrontEndConfig, FrontEndTick, _TiltGradient
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
