"""The friction front end's small filters on hand-made sensor streams: the tilt gradients from
the receiver's attitude, the yaw gyro's bias from its heading, and the forward accelerometer's
bias kept apart from the body's pitch."""

from __future__ import annotations

import math

import numpy as np

from estimator.config import ChassisConfig, DrivenAxle, Wheeled4wdSteeredConfig
from estimator.friction.frontend import (
    FrontEnd,
    FrontEndConfig,
    FrontEndTick,
    _TiltGradient,
    can_wheel_timing,
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


def test_a_can_wheel_speed_belongs_half_a_period_back() -> None:
    """A tooth-timed mean over the 20 ms before its stamp belongs 10 ms back (plus the
    reading's age); at a crawl, one tooth longer than the period (τ = 2π/(48 ω)), the last
    full tooth's centre, ``τ`` back (all of it taken: ``can_lag_share`` 1; half of it with
    0.5; the default takes none, not knowing whether the ECU averages, so the reading's age
    alone); an instantaneous sample at its stamp."""
    fe = FrontEndConfig(can_lag_share=1.0)
    half = FrontEndConfig(can_lag_share=0.5)
    lag, _ = can_wheel_timing(np.full(4, 40.0), np.zeros(4), np.zeros(4), half)
    np.testing.assert_allclose(lag, 0.005, rtol=1e-12)
    omega = np.array([40.0, 40.0, 2.0 * math.pi / (48 * 0.05), 40.0])
    lag, _ = can_wheel_timing(omega, np.zeros(4), np.array([0.0, 0.004, 0.0, 0.0]), fe)
    np.testing.assert_allclose(lag, [0.010, 0.014, 0.05, 0.010], rtol=1e-12)
    instant = FrontEndConfig(can_tooth_mean=False)
    lag, _ = can_wheel_timing(omega, np.zeros(4), np.full(4, 0.004), instant)
    np.testing.assert_allclose(lag, 0.004, rtol=1e-12)
    lag, _ = can_wheel_timing(omega, np.zeros(4), np.full(4, 0.004), FrontEndConfig())
    np.testing.assert_allclose(lag, 0.004, rtol=1e-12)


def test_a_can_wheel_speeds_variance_is_its_quantum_and_its_timing() -> None:
    """A steady wheel reads to its quantum (``q²/12``) and the edge timer's share; a wheel whose
    speed moves by 100 rad/s² (a ring) gains ``(ω̇ σ_t)²``, ``σ_t²`` the unknown lag's and the
    whole teeth's place in the period (``τ²/12``)."""
    fe = FrontEndConfig(can_lag_std_s=0.003)
    omega = np.full(4, 40.0)
    _, steady = can_wheel_timing(omega, np.zeros(4), np.zeros(4), fe)
    tooth_s = 2.0 * math.pi / (48 * 40.0)
    timer = (40.0 * 1e-6 / (0.02 - tooth_s)) ** 2 / 6.0
    np.testing.assert_allclose(steady**2, 0.025**2 / 12.0 + timer, rtol=1e-12)
    _, ringing = can_wheel_timing(omega, np.full(4, 100.0), np.zeros(4), fe)
    timing = 0.003**2 + tooth_s**2 / 12.0
    np.testing.assert_allclose(ringing**2 - steady**2, 100.0**2 * timing, rtol=1e-12)


def _accelerate_awd(fe_config: FrontEndConfig, ring_radps: float = 0.0) -> list[FrontEndTick]:
    """All four wheels driven and rolling without slip (no rims to read the speed): 4 s at
    10 m/s, then 3 s at 2 m/s²; GNSS (10 Hz) and the IMU true, the CAN wheel speeds each the
    mean over the 20 ms before its stamp (so the speed 10 ms before it); the rear-right
    wheel's readings alternate ``±ring_radps`` about it (a ringing wheel)."""
    config = Wheeled4wdSteeredConfig(
        chassis=ChassisConfig(driven_axle=DrivenAxle.ALL, drag_area_m2=0.0, rolling_resistance=0.0)
    )
    fe = FrontEnd(config, fe_config, 0.02)
    t_imu = np.arange(1, 701) * 10_000_000
    t_s = t_imu / 1e9

    def speed(t: np.ndarray) -> np.ndarray:
        return 10.0 + 2.0 * np.maximum(t - 4.0, 0.0)

    accel = np.zeros((t_imu.size, 3))
    accel[:, 1] = np.where(t_s > 4.0, 2.0, 0.0)
    accel[:, 2] = GRAVITY_MPS2
    fe.push_imu(ImuBatch(t_imu, accel, np.zeros((t_imu.size, 3))))
    radius = config.tyre.unloaded_radius_m  # the front end calibrates it in the first 4 s
    stamps = t_imu[1::2]
    mean_speed = speed(stamps / 1e9 - 0.01)
    omega = np.repeat(mean_speed[:, None] / radius, 4, axis=1)
    omega[:, 3] += ring_radps * (-1.0) ** np.arange(stamps.size)
    fe.push_wheels(WheelSpeeds4(stamps, omega))
    fe.push_steering(SteeringAngles(stamps, np.zeros(stamps.size)))
    v = speed(t_s)
    for k in range(9, t_imu.size, 10):
        fe.push_gnss(
            GnssSample(
                stamp_ns=int(t_imu[k]),
                vel_enu_mps=(v[k] * math.sin(HEADING_RAD), v[k] * math.cos(HEADING_RAD), 0.0),
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


def test_a_lagged_wheel_speed_reads_no_slip() -> None:
    """Accelerating at 2 m/s² on wheels that do not slip, their CAN speeds a period's mean:
    read against the speed of the reading's time (told the ECU averages), the four κ stay
    within 3e-4 of 0 over the last second (14-16 m/s); read as if instantaneous they are
    ``−a·T/2/v``, about −1.3e-3; not told which (the default) the reading is taken at its
    stamp, as an instantaneous one: no lag assumed."""
    told = _accelerate_awd(FrontEndConfig(can_lag_share=1.0))
    default = np.array([t.kappa for t in _accelerate_awd(FrontEndConfig())[-50:]])
    not_told = _accelerate_awd(FrontEndConfig(can_tooth_mean=False, can_lag_std_s=0.0))
    late = slice(-50, None)
    kappa_told = np.array([t.kappa for t in told[late]])
    kappa_not = np.array([t.kappa for t in not_told[late]])
    assert np.max(np.abs(kappa_told)) < 3e-4
    assert np.mean(kappa_not) < -1.0e-3
    assert abs(np.mean(default) - np.mean(kappa_not)) < 5e-5


def test_a_ringing_wheels_slip_loses_weight_whatever_its_ecu() -> None:
    """The rear-right wheel's readings alternate ±0.5 rad/s about the others' (a ring of
    ±50 rad/s²): its κ's own 1-σ takes ``r·ω̇·σ_t/v`` (``σ_t`` the 5 ms not known of the
    reading's timing, ``ω̇`` its rate less the body's ``a_x/r``) in quadrature with the 2e-4
    floor, to more than five times the other wheels'. Theirs, against a front end with no
    timing doubt (``can_lag_std_s`` 0, instantaneous), gains only the CAN quantum (``q²/12``:
    under 6e-5 at 14-16 m/s); the body's 2 m/s² goes to the 1-σ shared by the four κ, as
    ``a·σ_t/v`` in quadrature: 6.25e-4 to 7.1e-4 at 16-14 m/s. Neither reading is shifted (no
    lag taken), so the other wheels' mean κ is the same in both."""
    ticks = _accelerate_awd(FrontEndConfig(), ring_radps=0.5)[-50:]
    plain = _accelerate_awd(
        FrontEndConfig(can_tooth_mean=False, can_lag_std_s=0.0), ring_radps=0.5
    )[-50:]
    k_std = np.array([t.kappa_std for t in ticks])
    k_std_plain = np.array([t.kappa_std for t in plain])
    assert np.median(k_std[:, 3]) > 5.0 * np.median(k_std[:, :3])
    assert np.max(np.abs(k_std[:, :3] - k_std_plain[:, :3])) < 6e-5
    common = np.array([t.kappa_common_std for t in ticks])
    common_plain = np.array([t.kappa_common_std for t in plain])
    shared = np.sqrt(common**2 - common_plain**2)
    assert np.min(shared) > 0.95 * 2.0 * 0.005 / 16.0
    assert np.max(shared) < 1.05 * 2.0 * 0.005 / 14.0
    kappa = np.array([t.kappa for t in ticks])[:, :3]
    kappa_plain = np.array([t.kappa for t in plain])[:, :3]
    assert abs(np.mean(kappa) - np.mean(kappa_plain)) < 5e-5
