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
* CAN wheel speeds 50 Hz in packets of 5, quantised to 0.025 rad/s;
* steering-wheel angle 50 Hz in packets of 5, noise 0.1°, offset −0.5..0.5°;
* GNSS 10 Hz: ENU velocity noise 0.03 m/s per axis, dual-antenna heading noise 0.15°.

Random vehicles (:func:`random_config`) come from stated distributions; the named manoeuvres
run :data:`FOUR_WHEEL_CONFIG` (a rear-driven utility vehicle).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

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
    "LEAD_S",
    "NAMED",
    "FourWheelRun",
    "Manoeuvre",
    "Truth",
    "named_manoeuvre",
    "random_config",
    "random_manoeuvre",
    "simulate_four_wheel",
]

START_NS = 1_700_000_000_000_000_000
SENSOR_NOISE = NoiseConfig(gnss_vel_std_mps=0.03, accel_std_mps2=0.05, gyro_std_radps=0.003)
FOUR_WHEEL_CONFIG = Wheeled4wdSteeredConfig(
    chassis=ChassisConfig(driven_axle=DrivenAxle.REAR), noise=SENSOR_NOISE
)
_ROW_S = 0.01  # truth and IMU rate
_FRAME = EnuFrame(48.0, 11.0, 500.0)


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
    0.7-1.3e7 N/m², c_py 0.5-0.8 of it, kz 1.8-3.5e5 N/m, r_u 0.30-0.40 m, any driven axle."""
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
    )
    tyre = TyreConfig(
        c_px_npm2=c_px,
        c_py_npm2=c_px * rng.uniform(0.5, 0.8),
        kz_npm=rng.uniform(1.8e5, 3.5e5),
        unloaded_radius_m=rng.uniform(0.30, 0.40),
    )
    return Wheeled4wdSteeredConfig(chassis=chassis, tyre=tyre, noise=SENSOR_NOISE)


def simulate_four_wheel(
    manoeuvres: Sequence[Manoeuvre],
    seeds: Sequence[int],
    configs: Sequence[Wheeled4wdSteeredConfig] | None = None,
    start_ns: int = START_NS,
) -> list[FourWheelRun]:
    """Simulate ``manoeuvres`` side by side (one batched integration), run ``i`` drawing its
    truth and sensors from ``seeds[i]`` alone (the same run whatever it is batched with)."""
    if len(seeds) != len(manoeuvres):
        raise ValueError("one seed per manoeuvre")
    rngs = [np.random.default_rng(s) for s in seeds]
    cfgs = list(configs) if configs is not None else [FOUR_WHEEL_CONFIG] * len(manoeuvres)
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
        sensors = _sensors(one, rngs[i], start_ns)
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


def _can(truth: Truth, rng: np.random.Generator, start_ns: int) -> list[tuple[int, Measurement]]:
    stamps = _stamps(truth, start_ns, 2)
    omega = np.round(truth.omega_radps[::2] / 0.025) * 0.025
    offset = math.radians(rng.uniform(-0.5, 0.5))
    sw = truth.steer_wheel_rad[::2] + offset + rng.normal(0.0, math.radians(0.1), stamps.size)
    out: list[tuple[int, Measurement]] = []
    for k in range(0, stamps.size, 5):
        last = int(stamps[min(k + 4, stamps.size - 1)])
        out.append((last, WheelSpeeds4(stamps[k : k + 5], omega[k : k + 5])))
        out.append((last, SteeringAngles(stamps[k : k + 5], sw[k : k + 5])))
    return out


def _gnss(truth: Truth, rng: np.random.Generator, start_ns: int) -> list[tuple[int, Measurement]]:
    stamps = _stamps(truth, start_ns, 10)
    sel = slice(None, None, 10)
    yaw = truth.yaw_rad[sel]
    vx, vy = truth.vx_mps[sel], truth.vy_mps[sel]
    ve = vx * np.cos(yaw) - vy * np.sin(yaw) + rng.normal(0.0, 0.03, yaw.size)
    vn = vx * np.sin(yaw) + vy * np.cos(yaw) + rng.normal(0.0, 0.03, yaw.size)
    heading = math.pi / 2 - yaw + rng.normal(0.0, math.radians(0.15), yaw.size)
    lat, lon, h = _FRAME.to_geodetic(truth.east_m[sel], truth.north_m[sel], np.zeros(yaw.size))
    return [
        (
            int(stamps[k]),
            GnssSample(
                stamp_ns=int(stamps[k]),
                vel_enu_mps=(float(ve[k]), float(vn[k]), 0.0),
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


def _sensors(truth: Truth, rng: np.random.Generator, start_ns: int) -> list[Measurement]:
    """Every stream's packets, ordered by the time the packet is complete."""
    packets = _imu(truth, rng, start_ns) + _can(truth, rng, start_ns) + _gnss(truth, rng, start_ns)
    packets.sort(key=lambda p: p[0])
    return [m for _, m in packets]
