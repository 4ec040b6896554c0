"""Simulated steered four-wheel vehicle: truth and raw sensor streams for the friction estimator.

Pure: numpy only, every draw from the seeded generator, no I/O, no clock.

>>> runs = simulate_four_wheel([named_manoeuvre("steer_mu08")], seeds=[1])
>>> runs[0].measurements[0]        # ImuBatch / WheelSpeeds4 / SteeringAngles / GnssSample
>>> runs[0].truth.mu               # 100 Hz truth (:class:`~.dynamics.Truth`)

The truth (:mod:`.dynamics`) is not the estimator's model: relaxation lengths, differentials
and traction control, lagged load transfer with a roll-stiffness split, radius falling with
load, body roll and pitch tilting the accelerometers. Sensors (per run, uniform draws):

* IMU 100 Hz in packets of 10: accelerometer noise 0.05 m/s², bias −0.05..0.05 m/s² per axis;
  gyro noise 0.003 rad/s, bias −0.003..0.003 rad/s; the accelerometers read the tilt's
  ``g·sin`` (specific force in the body frame X right, Y forward, Z up);
* CAN wheel speeds 50 Hz in packets of 5, quantised to 0.025 rad/s, from the vehicle's
  :class:`WheelSpeedSensor`: by default (an ABS ECU timing its tone ring's edges, ``method.md``
  §2's period method over ``k`` teeth) each sample is the mean speed over the whole teeth that
  passed in the period before its stamp; an ECU that samples (``tooth_mean=False``) reports
  the instantaneous speed at its stamp;
* steering-wheel angle 50 Hz in packets of 5, noise 0.1°, offset −0.5..0.5°;
* GNSS 10 Hz: the antenna's ENU velocity and position (:func:`antenna_motion`, at the
  config's ``antenna_lever_arm_m`` from the CG, the body rolling and pitching about the axis
  ``tilt_axis_height_m`` above the ground), velocity noise 0.03 m/s per axis, dual-antenna
  heading noise 0.15°.

The truth's planar position and velocity are those of the tilt axis's point below the CG
(the chassis the tyres carry); the body's roll and pitch angles are the truth's, whatever
the axis (the axis moves only what the body carries above it).

Random vehicles (:func:`random_config`) come from stated distributions; the named manoeuvres
run :data:`FOUR_WHEEL_CONFIG` (a rear-driven utility vehicle, its antenna on the cab roof
0.5 m ahead of the CG on the centre line, 1.9 m above the ground, the tilt axis the config's
default 0.3 m above the ground).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator._arrays import FloatArray
from estimator.base import Measurement
from estimator.config import (
    ChassisConfig,
    DrivenAxle,
    NoiseConfig,
    TyreConfig,
    Wheeled4wdSteeredConfig,
)
from estimator.geo import EnuFrame
from estimator.sim.four_wheel.dynamics import DT_S, GRAVITY_MPS2, Truth, TruthParams, integrate
from estimator.sim.four_wheel.manoeuvres import (
    LEAD_S,
    NAMED,
    Manoeuvre,
    named_manoeuvre,
    random_manoeuvre,
)
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

__all__ = [
    "FOUR_WHEEL_CONFIG",
    "INSTANT_WHEEL_SENSOR",
    "LEAD_S",
    "NAMED",
    "FourWheelRun",
    "Manoeuvre",
    "Truth",
    "WheelSpeedSensor",
    "antenna_motion",
    "named_manoeuvre",
    "random_config",
    "random_manoeuvre",
    "random_wheel_sensor",
    "simulate_four_wheel",
    "tooth_mean_speed",
]

START_NS = 1_700_000_000_000_000_000
SENSOR_NOISE = NoiseConfig(gnss_vel_std_mps=0.03, accel_std_mps2=0.05, gyro_std_radps=0.003)
FOUR_WHEEL_CONFIG = Wheeled4wdSteeredConfig(
    chassis=ChassisConfig(driven_axle=DrivenAxle.REAR, antenna_lever_arm_m=(0.0, 0.5, 1.9)),
    noise=SENSOR_NOISE,
)
_ROW_S = 0.01  # truth and IMU rate
_FRAME = EnuFrame(48.0, 11.0, 500.0)
_LEAD_IN_S = 0.1  # the wheels' angle before the run's start (so the first samples have edges)


@dataclass(frozen=True, slots=True)
class WheelSpeedSensor:
    """A vehicle's CAN wheel-speed sensor: ``teeth`` on each tone ring, a sample every
    ``period_s`` rounded to ``quantum_radps``. ``tooth_mean``: the sample is the mean over the
    whole teeth whose edges fall in ``(t − period, t]`` (edges timed exactly; at a crawl, with
    fewer than two edges there, the last full tooth before ``t``); otherwise the instantaneous
    speed at ``t`` (an ECU that samples, or the speed's own estimate)."""

    teeth: int = 48
    tooth_mean: bool = True
    period_s: float = 0.02
    quantum_radps: float = 0.025

    def __post_init__(self) -> None:
        if self.teeth < 4 or self.period_s <= 0.0 or self.quantum_radps <= 0.0:
            raise ValueError("a wheel-speed sensor needs ≥ 4 teeth, a period and a quantum")
        if abs(self.period_s / _ROW_S - round(self.period_s / _ROW_S)) > 1e-9:
            raise ValueError(f"the period must be a multiple of the truth's {_ROW_S} s rows")


INSTANT_WHEEL_SENSOR = WheelSpeedSensor(tooth_mean=False)


def random_wheel_sensor(rng: np.random.Generator) -> WheelSpeedSensor:
    """A tone ring of 40-100 teeth (uniform; an assumed range for road vehicles, not a data
    sheet's) timed by the ECU, except in one drive of ten (an ECU that samples the speed)."""
    teeth = int(rng.integers(40, 101))
    return WheelSpeedSensor(teeth=teeth, tooth_mean=bool(rng.uniform() >= 0.1))


@dataclass(frozen=True, slots=True)
class FourWheelRun:
    """One simulated run: the manoeuvre, the config the estimator is told, the truth
    (100 Hz rows), the sensor measurements in time order, and the truth's tyres per wheel
    ``(4,)`` (``c_px``, ``c_py`` [N/m²], ``kz`` [N/m]: what the config only approximates)."""

    manoeuvre: Manoeuvre
    config: Wheeled4wdSteeredConfig
    truth: Truth
    measurements: list[Measurement]
    start_ns: int
    tyre_c_px_npm2: FloatArray
    tyre_c_py_npm2: FloatArray
    tyre_kz_npm: FloatArray


def random_config(rng: np.random.Generator) -> Wheeled4wdSteeredConfig:
    """A vehicle drawn uniformly: mass 1,200-3,500 kg, lf and lr 1.0-1.7 m, tracks 1.4-1.8 m,
    CG height 0.5-0.9 m, yaw inertia m·lf·lr·(0.9-1.3), steering ratio 14-20, c_px
    0.7-1.3e7 N/m², c_py 0.5-0.8 of it, kz 1.8-3.5e5 N/m, r_u 0.30-0.40 m, any driven axle;
    the GNSS antenna −1.5..+2.0 m ahead of the CG, −0.4..+0.4 m right of it, 1.5-3.2 m above
    the ground, the tilt axis 0.05-0.5 m above the ground (the antenna from a generator
    spawned off ``rng``, the axis from one spawned off that, so every other draw is the same
    as without them)."""
    mass = rng.uniform(1200.0, 3500.0)
    lf, lr = rng.uniform(1.0, 1.7, 2)
    c_px = rng.uniform(0.7e7, 1.3e7)
    chassis = ChassisConfig(
        mass_kg=mass,
        yaw_inertia_kgm2=mass * lf * lr * rng.uniform(0.9, 1.3),
        cg_to_front_axle_m=lf,
        cg_to_rear_axle_m=lr,
        front_track_m=rng.uniform(1.4, 1.8),
        rear_track_m=rng.uniform(1.4, 1.8),
        cg_height_m=rng.uniform(0.5, 0.9),
        steering_ratio=rng.uniform(14.0, 20.0),
        driven_axle=list(DrivenAxle)[int(rng.integers(0, 3))],
        **_mast(rng.spawn(1)[0]),
    )
    tyre = TyreConfig(
        c_px_npm2=c_px,
        c_py_npm2=c_px * rng.uniform(0.5, 0.8),
        kz_npm=rng.uniform(1.8e5, 3.5e5),
        unloaded_radius_m=rng.uniform(0.30, 0.40),
    )
    return Wheeled4wdSteeredConfig(chassis=chassis, tyre=tyre, noise=SENSOR_NOISE)


def _mast(rng: np.random.Generator) -> dict[str, Any]:
    """The antenna's lever arm (x right, y forward, z up from the ground below the CG) and,
    from a generator spawned off ``rng``, the tilt axis's height: :func:`random_config`'s
    ranges."""
    right, ahead, up = rng.uniform((-0.4, -1.5, 1.5), (0.4, 2.0, 3.2))
    axis_m = rng.spawn(1)[0].uniform(0.05, 0.5)
    return {
        "antenna_lever_arm_m": (float(right), float(ahead), float(up)),
        "tilt_axis_height_m": float(axis_m),
    }


def simulate_four_wheel(
    manoeuvres: Sequence[Manoeuvre],
    seeds: Sequence[int],
    configs: Sequence[Wheeled4wdSteeredConfig] | None = None,
    start_ns: int = START_NS,
    wheel_sensors: Sequence[WheelSpeedSensor] | None = None,
) -> list[FourWheelRun]:
    """Simulate ``manoeuvres`` side by side (one batched integration), run ``i`` drawing its
    truth and sensors from ``seeds[i]`` alone (the same run whatever it is batched with);
    ``wheel_sensors`` per run (default: :class:`WheelSpeedSensor`'s 48-tooth tooth mean)."""
    if len(seeds) != len(manoeuvres):
        raise ValueError("one seed per manoeuvre")
    rngs = [np.random.default_rng(s) for s in seeds]
    cfgs = list(configs) if configs is not None else [FOUR_WHEEL_CONFIG] * len(manoeuvres)
    wss = list(wheel_sensors) if wheel_sensors is not None else [WheelSpeedSensor()] * len(seeds)
    kz = np.array([[c.tyre.kz_npm] * 4 for c in cfgs])
    for i, m in enumerate(manoeuvres):
        if m.damaged_wheel >= 0:
            kz[i, m.damaged_wheel] = m.damaged_kz_npm
    params = TruthParams.draw(cfgs, rngs, kz)
    steps = round(max(m.duration_s for m in manoeuvres) / DT_S) + 1
    t_s = np.arange(steps) * DT_S
    speed, steer, mu = (np.stack(p) for p in zip(*(m.sample(t_s) for m in manoeuvres), strict=True))
    truth = integrate(params, speed, steer, mu, every=round(_ROW_S / DT_S))
    runs = []
    for i, m in enumerate(manoeuvres):
        rows = round(m.duration_s / _ROW_S) + 1
        one = truth.take(i)
        one = Truth(*(getattr(one, f)[:rows] for f in one.__dataclass_fields__))
        sensors = _sensors(one, rngs[i], start_ns, wss[i], cfgs[i].chassis)
        tyres = (params.c_px_npm2[i], params.c_py_npm2[i], params.kz_npm[i])
        runs.append(FourWheelRun(m, cfgs[i], one, sensors, start_ns, *tyres))
    return runs


def _stamps(truth: Truth, start_ns: int, step: int) -> np.ndarray:
    return start_ns + np.round(truth.t_s[::step] * 1e9).astype(np.int64)


def _imu(truth: Truth, rng: np.random.Generator, start_ns: int) -> list[tuple[int, Measurement]]:
    g = GRAVITY_MPS2
    n = truth.t_s.size
    fwd = truth.ax_mps2 + g * np.sin(truth.pitch_rad)
    left = truth.ay_mps2 + g * np.sin(truth.roll_rad)
    up = g * np.cos(truth.roll_rad) * np.cos(truth.pitch_rad)
    accel = np.stack([-left, fwd, up], axis=-1)
    accel += rng.uniform(-0.05, 0.05, 3) + rng.normal(0.0, 0.05, (n, 3))
    gyro = np.stack([truth.pitch_rate_radps, truth.roll_rate_radps, truth.yaw_rate_radps], axis=-1)
    gyro += rng.uniform(-0.003, 0.003, 3) + rng.normal(0.0, 0.003, (n, 3))
    stamps = _stamps(truth, start_ns, 1)
    return [
        (
            int(stamps[min(k + 9, n - 1)]),
            ImuBatch(stamps[k : k + 10], accel[k : k + 10], gyro[k : k + 10]),
        )
        for k in range(0, n, 10)
    ]


def tooth_mean_speed(
    truth: Truth, t_s: FloatArray, phase_rad: FloatArray, sensor: WheelSpeedSensor
) -> FloatArray:
    """Each wheel's tone-ring reading at the times ``t_s`` ``(K,)`` → ``(K, 4)`` [rad/s].

    An edge passes where ``θ_w + φ_w`` crosses a multiple of the tooth ``Δ = 2π/teeth``
    (``θ_w`` the truth's angle on its 2 ms grid, interpolated; ``phase_rad`` ``(4,)`` the
    rings' ``φ_w``). With ``n ≥ 2`` edges in ``(t − T, t]``: ``ω = (n − 1) Δ/(t_last − t_first)``
    (``method.md`` §2, period method over whole teeth); fewer: ``Δ`` over the last full
    tooth before ``t``."""
    tooth = 2.0 * math.pi / sensor.teeth
    angle = truth.angle_sub_rad.reshape(-1, 4)
    grid_s = truth.t_s[0] + DT_S * np.arange(angle.shape[0])
    lead_s = DT_S * np.arange(-round(_LEAD_IN_S / DT_S), 0)
    out = np.empty((t_s.size, 4))
    for w in range(4):
        theta = np.concatenate([angle[0, w] + truth.omega_radps[0, w] * lead_s, angle[:, w]])
        theta = np.maximum.accumulate(theta + phase_rad[w])
        times = np.concatenate([grid_s[0] + lead_s, grid_s])
        marks = np.arange(np.ceil(theta[0] / tooth), np.floor(theta[-1] / tooth) + 1) * tooth
        edges = np.interp(marks, theta, times)
        if edges.size < 2:  # not a whole tooth turned in the run: a wheel at rest
            out[:, w] = 0.0
            continue
        last = np.searchsorted(edges, t_s + 1e-12, side="right") - 1
        first = np.searchsorted(edges, t_s - sensor.period_s + 1e-12, side="right")
        last = np.maximum(last, 1)
        many = last - first >= 1
        lo = np.where(many, first, last - 1)
        out[:, w] = (last - lo) * tooth / np.maximum(edges[last] - edges[lo], 1e-9)
    return out


def _can(
    truth: Truth, rng: np.random.Generator, start_ns: int, sensor: WheelSpeedSensor
) -> list[tuple[int, Measurement]]:
    """Wheel-speed and steering packets, the wheel speeds instantaneous (a tooth-mean
    sensor's are replaced in :func:`_sensors` once the rings' phases are drawn)."""
    step = round(sensor.period_s / _ROW_S)
    stamps = _stamps(truth, start_ns, step)
    omega = np.round(truth.omega_radps[::step] / sensor.quantum_radps) * sensor.quantum_radps
    offset = math.radians(rng.uniform(-0.5, 0.5))
    sw = truth.steer_wheel_rad[::step] + offset + rng.normal(0.0, math.radians(0.1), stamps.size)
    out: list[tuple[int, Measurement]] = []
    for k in range(0, stamps.size, 5):
        last = int(stamps[min(k + 4, stamps.size - 1)])
        out.append((last, WheelSpeeds4(stamps[k : k + 5], omega[k : k + 5])))
        out.append((last, SteeringAngles(stamps[k : k + 5], sw[k : k + 5])))
    return out


def antenna_motion(truth: Truth, chassis: ChassisConfig) -> tuple[FloatArray, FloatArray]:
    """The antenna's ENU position (up: above the ground) and velocity from the CG's, ``(T, 3)``
    each [m, m/s].

    The lever arm ``r`` from the tilt axis's point below the CG (``antenna_lever_arm_m``
    less ``tilt_axis_height_m``, in the body frame x forward, y left, z up) tilts with the
    body about that point, pitch ``θ`` (nose up) then roll ``φ`` (right side down):
    ``d = R_x(φ) R_y(−θ) r``. Then ``p_ant = p_cg + R_z(ψ) d`` and
    ``v_ant = v_cg + R_z(ψ)(ḋ + r_z ẑ × d)`` (``v = v_cg + ω × r``; ``ψ`` the yaw, ``r_z`` the
    yaw rate, ``p_cg``, ``v_cg`` the truth's planar ones): a steady turn adds ``r_z·d_x``
    across the heading and ``−r_z·d_y`` along it, a roll rate ``−φ̇·d_z`` across.
    """
    right, ahead, up = chassis.antenna_lever_arm_m
    f, lft, h = ahead, -right, up - chassis.tilt_axis_height_m
    th, ph = truth.pitch_rad, truth.roll_rad
    f1, h1 = f * np.cos(th) - h * np.sin(th), f * np.sin(th) + h * np.cos(th)
    l2, h2 = lft * np.cos(ph) - h1 * np.sin(ph), lft * np.sin(ph) + h1 * np.cos(ph)
    dth, dph = truth.pitch_rate_radps, truth.roll_rate_radps
    f_dot = -h1 * dth
    l_dot = -h2 * dph - f1 * dth * np.sin(ph)
    h_dot = l2 * dph + f1 * dth * np.cos(ph)
    r = truth.yaw_rate_radps
    fwd = truth.vx_mps + f_dot - r * l2
    left = truth.vy_mps + l_dot + r * f1
    c, s = np.cos(truth.yaw_rad), np.sin(truth.yaw_rad)
    vel = np.stack([fwd * c - left * s, fwd * s + left * c, h_dot], axis=-1)
    pos = np.stack(
        [truth.east_m + f1 * c - l2 * s, truth.north_m + f1 * s + l2 * c, h2 + up - h],
        axis=-1,
    )
    return pos, vel


def _gnss(
    truth: Truth, rng: np.random.Generator, start_ns: int, chassis: ChassisConfig
) -> list[tuple[int, Measurement]]:
    """The receiver's 10 Hz epochs: the antenna's position and velocity, the body's attitude."""
    stamps = _stamps(truth, start_ns, 10)
    sel = slice(None, None, 10)
    yaw = truth.yaw_rad[sel]
    pos, vel = (a[sel] for a in antenna_motion(truth, chassis))
    ve = vel[:, 0] + rng.normal(0.0, 0.03, yaw.size)
    vn = vel[:, 1] + rng.normal(0.0, 0.03, yaw.size)
    heading = math.pi / 2 - yaw + rng.normal(0.0, math.radians(0.15), yaw.size)
    lat, lon, h = _FRAME.to_geodetic(pos[:, 0], pos[:, 1], pos[:, 2])
    return [
        (
            int(stamps[k]),
            GnssSample(
                stamp_ns=int(stamps[k]),
                vel_enu_mps=(float(ve[k]), float(vn[k]), float(vel[k, 2])),
                heading_rad=float(heading[k]),
                pitch_rad=float(truth.pitch_rad[sel][k]),
                roll_rad=float(truth.roll_rad[sel][k]),
                lat_deg=float(lat[k]),
                lon_deg=float(lon[k]),
                height_m=float(h[k]),
                vel_std_mps=0.03,
            ),
        )
        for k in range(yaw.size)
    ]


def _sensors(
    truth: Truth,
    rng: np.random.Generator,
    start_ns: int,
    wheels: WheelSpeedSensor,
    chassis: ChassisConfig,
) -> list[Measurement]:
    """Every stream's packets, ordered by the time the packet is complete. The tone rings'
    phases are drawn after every other draw, so the other streams do not depend on the
    wheel-speed sensor."""
    imu = _imu(truth, rng, start_ns)
    can = _can(truth, rng, start_ns, wheels)
    gnss = _gnss(truth, rng, start_ns, chassis)
    if wheels.tooth_mean:
        phase_rad = rng.uniform(0.0, 2.0 * math.pi, 4)
        step = round(wheels.period_s / _ROW_S)
        speed = tooth_mean_speed(truth, truth.t_s[::step], phase_rad, wheels)
        speed = np.round(speed / wheels.quantum_radps) * wheels.quantum_radps
        for k in range(0, len(can), 2):
            stamp, m = can[k]
            assert isinstance(m, WheelSpeeds4)
            rows = slice(5 * (k // 2), 5 * (k // 2) + m.stamp_ns.size)
            can[k] = (stamp, WheelSpeeds4(m.stamp_ns, speed[rows]))
    packets = imu + can + gnss
    packets.sort(key=lambda p: p[0])
    return [m for _, m in packets]
