"""Raw sensor streams sampled from a :class:`~estimator.sim.kinematics.FineTruth`.

Imperfections, all switchable through :class:`SensorSpec` (defaults are a good RTK receiver, a
consumer MEMS IMU and a 120-tooth Hall encoder ring):

GNSS (``gnss_rate_hz``, epochs on whole multiples of the period)
    Antenna velocity in ENU with the lever-arm terms ``ω × p`` of yaw, pitch and roll rate;
    white noise per axis (vertical ×1.5); optional multiplicative speed noise, uniform in
    ``±gnss_speed_noise_rel`` (the source's "≈5 % amplitude" noise); scheduled speed
    disturbances along the forward axis; random outliers (multipath) that the receiver does not
    flag; RTK-float windows with larger noise; outages (``fix = NONE`` with NaN values, or epochs
    left out); a data lag (the solution describes an instant ``gnss_data_lag_ms`` before its
    stamp) and a delivery latency (arrival after the stamp). Attitude from a dual-antenna
    receiver with white noise; position through :class:`estimator.geo.EnuFrame`.
IMU (``imu_rate_hz``, batches of ``imu_batch_len``)
    Specific force at the IMU's mounting point, gravity included, and body angular rate; each
    axis gets a constant bias (drawn once per run), a random-walk bias, white noise and
    optionally white noise proportional to the signal.
Wheel encoders
    Rising-edge times where the integrated wheel angle crosses a tooth edge. Each ring has a
    fixed random pattern of tooth-edge deviations (``tooth_error_rel`` of the tooth pitch, 1σ),
    and the wheel starts at a random angle. Edge times are quantised to the capture timer
    (``edge_clock_hz``) and grouped per wheel in windows of ``wheel_batch_ms``; a window in
    which neither wheel had an edge sends a heartbeat (:func:`wheel_heartbeats`: the window's
    end, no edges) when ``wheel_heartbeats`` is on, else nothing.

Every generator returns :class:`Emission` records: the measurement, the sensor time that
completes it (``key_ns``, the last sample's stamp) and the time it reaches the server
(``arrival_ns``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from estimator._arrays import FloatArray, IntArray
from estimator.base import Measurement
from estimator.config import WheeledRearDriveConfig
from estimator.geo import EnuFrame
from estimator.sim.kinematics import FineTruth
from estimator.types import GnssFix, GnssSample, ImuBatch, Wheel, WheelEdges

__all__ = [
    "Emission",
    "SensorSpec",
    "antenna_point_m",
    "edge_times_s",
    "gnss_emissions",
    "imu_emissions",
    "imu_mounting",
    "imu_point_m",
    "wheel_emissions",
]

Window = tuple[float, float]


@dataclass(frozen=True, slots=True)
class SensorSpec:
    """Sensor rates and imperfections (units in the names; times in seconds from the start).

    GNSS
    ----
    gnss_rate_hz : 10.0
    gnss_vel_std_mps : 0.03 — white noise per horizontal axis (vertical ×1.5), RTK fixed.
    gnss_speed_noise_rel : 0.0 — multiplicative speed noise, uniform in ±this (0.05 = "5 %").
    gnss_pos_std_m : 0.015 — horizontal position noise (vertical ×2).
    gnss_heading_std_rad, gnss_pitch_std_rad, gnss_roll_std_rad : dual-antenna attitude noise.
    gnss_attitude : True — the receiver reports heading, pitch and roll; False: one antenna,
    NaN attitude (noise still drawn, so the other imperfections keep their values).
    gnss_outlier_prob : 0.0 — chance per epoch of an unflagged velocity outlier.
    gnss_outlier_mps : 1.0 — outlier size, 1σ per axis.
    gnss_speed_steps : ((t_s, dv_mps, duration_s), ...) — forward-speed disturbances.
    gnss_outages : ((t0_s, t1_s), ...) — no solution in ``[t0, t1)``.
    gnss_outage_mode : "no_fix" (epochs with ``fix=NONE`` and NaN values) or "missing".
    gnss_float_windows : ((t0_s, t1_s), ...) — RTK float: noise × ``gnss_float_noise_scale``.
    gnss_latency_ms : delivery delay after the epoch stamp.
    gnss_data_lag_ms : the solution describes the instant this long before its stamp.
    gnss_epoch_phase_ms : 0.0 — epochs at ``phase + k/rate`` from the start (0: on whole
    periods of the start, e.g. whole tenths of a second at 10 Hz).
    gnss_epoch_jitter_ms : 0.0 — each epoch stamped up to ± this off its grid instant (uniform;
    the solution describes the stamped instant), so two epochs can share a filter tick.

    IMU
    ---
    imu_rate_hz : 100.0, imu_batch_len : 10
    accel_std_mps2, gyro_std_radps : white noise per sample.
    accel_noise_rel, gyro_noise_rel : 0.0 — white noise proportional to the signal (1σ, fraction
    of the inertial acceleration at the IMU — gravity excluded — and of the angular rate, per
    axis and sample); the source's "accel 3 %, gyro 2 %".
    accel_bias_std_mps2, gyro_bias_std_radps : constant bias per axis (1σ, drawn per run).
    accel_bias_walk_mps2, gyro_bias_walk_radps : bias random walk per √s.
    imu_latency_ms : delivery delay after the batch's last sample.

    Wheels
    ------
    tooth_error_rel : 0.01 — per-tooth edge deviation, fraction of the tooth pitch (1σ).
    edge_clock_hz : 1e6 — edge capture timer; must divide 1e9.
    wheel_batch_ms : 100.0 — one packet per wheel per window.
    wheel_latency_ms : delivery delay after the window's end.
    wheel_heartbeats : True — a window without an edge on either wheel sends an empty packet
    saying so (the wheels stream is complete to the window's end).
    wheel_radius_error_rel : (left, right) — true radius = configured × (1 + error).

    Clocks and mounting
    -------------------
    clock_offset_ms : (gnss, imu, wheels) — each stream's clock runs ahead of the true time by
    this much (signed): its sample stamped ``t`` describes the instant ``t − offset``.
    imu_misalign_deg : (yaw, pitch) — the IMU's axes turned against the body's (yaw about Z,
    then pitch about X): it reads ``Rᵀ·v`` of every body vector ``v``.

    Truth grid
    ----------
    fine_rate_hz : 500.0 — internal integration grid; the GNSS, IMU and truth rates must
    divide it.
    truth_rate_hz : 100.0 — rate of the returned truth table.
    """

    gnss_rate_hz: float = 10.0
    gnss_vel_std_mps: float = 0.03
    gnss_speed_noise_rel: float = 0.0
    gnss_pos_std_m: float = 0.015
    gnss_heading_std_rad: float = 0.0035
    gnss_pitch_std_rad: float = 0.005
    gnss_roll_std_rad: float = 0.005
    gnss_attitude: bool = True
    gnss_outlier_prob: float = 0.0
    gnss_outlier_mps: float = 1.0
    gnss_speed_steps: tuple[tuple[float, float, float], ...] = ()
    gnss_outages: tuple[Window, ...] = ()
    gnss_outage_mode: str = "no_fix"
    gnss_float_windows: tuple[Window, ...] = ()
    gnss_float_noise_scale: float = 5.0
    gnss_latency_ms: float = 50.0
    gnss_data_lag_ms: float = 0.0
    imu_rate_hz: float = 100.0
    imu_batch_len: int = 10
    accel_std_mps2: float = 0.05
    gyro_std_radps: float = 0.005
    accel_noise_rel: float = 0.0
    gyro_noise_rel: float = 0.0
    accel_bias_std_mps2: float = 0.03
    gyro_bias_std_radps: float = 0.002
    accel_bias_walk_mps2: float = 0.002
    gyro_bias_walk_radps: float = 1e-4
    imu_latency_ms: float = 2.0
    tooth_error_rel: float = 0.01
    edge_clock_hz: float = 1e6
    wheel_batch_ms: float = 100.0
    wheel_latency_ms: float = 5.0
    wheel_heartbeats: bool = True
    wheel_radius_error_rel: tuple[float, float] = (0.0, 0.0)
    gnss_epoch_phase_ms: float = 0.0
    gnss_epoch_jitter_ms: float = 0.0
    clock_offset_ms: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_misalign_deg: tuple[float, float] = (0.0, 0.0)
    fine_rate_hz: float = 500.0
    truth_rate_hz: float = 100.0

    def __post_init__(self) -> None:
        for name in ("gnss_rate_hz", "imu_rate_hz", "truth_rate_hz"):
            rate = getattr(self, name)
            ratio = self.fine_rate_hz / rate if rate > 0 else math.nan
            if not (rate > 0 and abs(ratio - round(ratio)) < 1e-9):
                raise ValueError(
                    f"{name}={rate} must be > 0 and divide fine_rate_hz={self.fine_rate_hz}"
                )
        if self.gnss_outage_mode not in ("no_fix", "missing"):
            raise ValueError("gnss_outage_mode must be 'no_fix' or 'missing'")
        tick = 1e9 / self.edge_clock_hz
        if abs(tick - round(tick)) > 1e-9 or tick < 1:
            raise ValueError("edge_clock_hz must divide 1e9")
        if self.imu_batch_len < 1:
            raise ValueError("imu_batch_len must be >= 1")
        if self.wheel_batch_ms <= 0:
            raise ValueError("wheel_batch_ms must be > 0")
        if not 0.0 <= self.tooth_error_rel < 0.2:
            raise ValueError("tooth_error_rel must be in [0, 0.2)")
        for name in (
            "gnss_vel_std_mps",
            "gnss_speed_noise_rel",
            "gnss_pos_std_m",
            "gnss_outlier_prob",
            "accel_std_mps2",
            "gyro_std_radps",
            "accel_noise_rel",
            "gyro_noise_rel",
            "accel_bias_std_mps2",
            "gyro_bias_std_radps",
            "accel_bias_walk_mps2",
            "gyro_bias_walk_radps",
            "gnss_latency_ms",
            "gnss_data_lag_ms",
            "imu_latency_ms",
            "wheel_latency_ms",
            "gnss_epoch_phase_ms",
            "gnss_epoch_jitter_ms",
        ):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")

    @classmethod
    def field_names(cls) -> frozenset[str]:
        """Names accepted as overrides."""
        return frozenset(f.name for f in dataclasses.fields(cls))


class Emission(NamedTuple):
    """One measurement with the sensor time that completes it and its arrival time (ns).

    ``until_ns`` is what the sensor knows when it sends: no later sample of its stream is
    stamped at or before it (the end of the batch window; for GNSS, the next epoch − 1 ns).
    """

    key_ns: int
    arrival_ns: int
    rank: int
    measurement: Measurement
    until_ns: int


def imu_point_m(config: WheeledRearDriveConfig) -> FloatArray:
    """IMU position in the body frame from ``O``: ``(x, y, h0)``."""
    g = config.geometry
    return np.array([g.imu_offset_m[0], g.imu_offset_m[1], g.h0_m])


def antenna_point_m(config: WheeledRearDriveConfig) -> FloatArray:
    """Antenna position in the body frame from ``O``: ``(x, y, h0 + h1)``."""
    g = config.geometry
    return np.array([g.antenna_offset_m[0], g.antenna_offset_m[1], g.h0_m + g.h1_m])


def _in_windows(t: FloatArray, windows: tuple[Window, ...]) -> npt.NDArray[np.bool_]:
    mask = np.zeros(t.shape, dtype=bool)
    for t0, t1 in windows:
        mask |= (t >= t0) & (t < t1)
    return mask


def _stamps(start_ns: int, t_s: FloatArray) -> npt.NDArray[np.int64]:
    return start_ns + np.round(t_s * 1e9).astype(np.int64)


def _gnss_instants(
    t_s: FloatArray, idx: npt.NDArray[np.int64], spec: SensorSpec, unit_jitter: FloatArray
) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """Stamped time of each epoch (its grid instant ``t_s[idx]`` plus the jitter, ``unit_jitter``
    in ±1 scaled by ``gnss_epoch_jitter_ms``) and the fine-grid sample its solution describes:
    ``gnss_data_lag_ms`` and the GNSS clock offset before the stamp, within the run."""
    t = t_s[idx]
    if spec.gnss_epoch_jitter_ms > 0:
        t = np.clip(t + unit_jitter * spec.gnss_epoch_jitter_ms * 1e-3, 0.0, t_s[-1])
    back_s = (spec.gnss_data_lag_ms + spec.clock_offset_ms[0]) * 1e-3
    if spec.gnss_epoch_jitter_ms > 0 or spec.clock_offset_ms[0] != 0:
        src = np.round((t - back_s) * spec.fine_rate_hz).astype(np.int64)
    else:  # the grid's own index (bit-identical runs without jitter or offset)
        src = idx - round(spec.gnss_data_lag_ms * 1e-3 * spec.fine_rate_hz)
    return t, np.clip(src, 0, t_s.size - 1)


def gnss_emissions(
    truth: FineTruth,
    spec: SensorSpec,
    config: WheeledRearDriveConfig,
    frame: EnuFrame,
    start_ns: int,
    rng: np.random.Generator,
) -> list[Emission]:
    """GNSS epochs (see the module docstring for the error model)."""
    step = round(spec.fine_rate_hz / spec.gnss_rate_hz)
    phase = round(spec.gnss_epoch_phase_ms * 1e-3 * spec.fine_rate_hz)
    idx = np.arange(phase, truth.t_s.size, step)
    n = idx.size

    # draw everything every time, so switching one imperfection off keeps the others' values
    rel = rng.uniform(-1.0, 1.0, n) * spec.gnss_speed_noise_rel
    white = rng.standard_normal((n, 3)) * np.array([1.0, 1.0, 1.5])
    pos_noise = rng.standard_normal((n, 3)) * np.array([1.0, 1.0, 2.0])
    att_noise = rng.standard_normal((n, 3))
    outlier = rng.random(n) < spec.gnss_outlier_prob
    outlier_v = rng.standard_normal((n, 3)) * np.array([1.0, 1.0, 0.5]) * spec.gnss_outlier_mps
    t, src = _gnss_instants(truth.t_s, idx, spec, rng.uniform(-1.0, 1.0, n))

    p_ant = antenna_point_m(config)
    rot = truth.rot[src]
    v_body = truth.point_velocity_body(p_ant)[src]
    vel = np.einsum("nij,nj->ni", rot, v_body)
    pos = truth.pos_enu_m[src] + rot @ p_ant

    scale = np.where(_in_windows(t, spec.gnss_float_windows), spec.gnss_float_noise_scale, 1.0)
    vel_meas = _measured_velocity(vel, rot[:, :, 1], t, rel, white, scale, spec)
    vel_meas[outlier] += outlier_v[outlier]
    pos_meas = pos + pos_noise * (spec.gnss_pos_std_m * scale)[:, None]
    heading, pitch, roll = _measured_attitude(truth, src, att_noise, spec)
    lat, lon, h = frame.to_geodetic(pos_meas[:, 0], pos_meas[:, 1], pos_meas[:, 2])
    speed = np.linalg.norm(vel, axis=1)
    reported = np.sqrt(
        (spec.gnss_vel_std_mps * scale) ** 2 + (spec.gnss_speed_noise_rel * speed) ** 2 / 3
    )
    fix_ok = np.where(scale > 1.0, GnssFix.RTK_FLOAT, GnssFix.RTK_FIXED)
    fields = (vel_meas, heading, pitch, roll, lat, lon, h, fix_ok, reported)
    return _gnss_samples(_stamps(start_ns, t), _in_windows(t, spec.gnss_outages), fields, spec)


def _measured_velocity(
    vel: FloatArray,
    forward: FloatArray,
    t: FloatArray,
    rel: FloatArray,
    white: FloatArray,
    scale: FloatArray,
    spec: SensorSpec,
) -> FloatArray:
    """The antenna velocity with its scale error, white noise and the spec's speed steps."""
    vel_meas = vel * (1.0 + rel[:, None]) + white * (spec.gnss_vel_std_mps * scale)[:, None]
    for t0, dv, dur in spec.gnss_speed_steps:
        hit = (t >= t0 - 1e-9) & (t < t0 + dur - 1e-9)
        vel_meas[hit] += dv * forward[hit]
    return vel_meas


def _measured_attitude(
    truth: FineTruth, src: IntArray, att_noise: FloatArray, spec: SensorSpec
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Heading, pitch and roll with their noise; NaN when the receiver has no attitude."""
    heading = np.mod(truth.psi_rad[src] + att_noise[:, 0] * spec.gnss_heading_std_rad, 2 * np.pi)
    pitch = truth.theta_rad[src] + att_noise[:, 1] * spec.gnss_pitch_std_rad
    roll = truth.phi_rad[src] + att_noise[:, 2] * spec.gnss_roll_std_rad
    if not spec.gnss_attitude:
        heading, pitch, roll = (np.full(att_noise.shape[0], np.nan) for _ in range(3))
    return heading, pitch, roll


def _gnss_samples(
    stamps: IntArray,
    out_mask: npt.NDArray[np.bool_],
    fields: tuple[FloatArray, ...],
    spec: SensorSpec,
) -> list[Emission]:
    """One emission per epoch (an outage: an empty fix, or none when ``missing``)."""
    vel_meas, heading, pitch, roll, lat, lon, h, fix_ok, reported = fields
    latency = round(spec.gnss_latency_ms * 1e6)
    period_ns = round(1e9 / spec.gnss_rate_hz)
    nan = math.nan
    out: list[Emission] = []
    for k in range(stamps.shape[0]):
        stamp = int(stamps[k])
        if out_mask[k]:
            if spec.gnss_outage_mode == "missing":
                continue
            sample = GnssSample(
                stamp_ns=stamp,
                vel_enu_mps=(nan, nan, nan),
                heading_rad=nan,
                pitch_rad=nan,
                roll_rad=nan,
                lat_deg=nan,
                lon_deg=nan,
                height_m=nan,
                fix=GnssFix.NONE,
                vel_std_mps=nan,
            )
        else:
            sample = GnssSample(
                stamp_ns=stamp,
                vel_enu_mps=(float(vel_meas[k, 0]), float(vel_meas[k, 1]), float(vel_meas[k, 2])),
                heading_rad=float(heading[k]),
                pitch_rad=float(pitch[k]),
                roll_rad=float(roll[k]),
                lat_deg=float(lat[k]),
                lon_deg=float(lon[k]),
                height_m=float(h[k]),
                fix=GnssFix(int(fix_ok[k])),
                vel_std_mps=float(reported[k]),
            )
        out.append(Emission(stamp, stamp + latency, 0, sample, stamp + period_ns - 1))
    return out


def _random_walk(rng: np.random.Generator, n: int, dt: float, walk: float) -> FloatArray:
    steps = rng.standard_normal((n, 3)) * (walk * math.sqrt(dt))
    return np.cumsum(steps, axis=0) - steps[0]


def imu_mounting(misalign_deg: tuple[float, float]) -> FloatArray:
    """Rotation ``R = Rz(yaw)·Rx(pitch)`` (shape (3, 3)) of the IMU's axes in the body frame;
    row vectors ``v`` of the body read ``v @ R`` (``Rᵀ·v``) in the IMU's axes."""
    yaw, pitch = (math.radians(a) for a in misalign_deg)
    cz, sz, cx, sx = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    return rz @ rx


def imu_emissions(
    truth: FineTruth,
    spec: SensorSpec,
    config: WheeledRearDriveConfig,
    start_ns: int,
    rng: np.random.Generator,
) -> list[Emission]:
    """IMU batches of specific force (gravity included) and angular rate at the IMU's point."""
    step = round(spec.fine_rate_hz / spec.imu_rate_hz)
    idx = np.arange(0, truth.t_s.size, step)
    n = idx.size
    dt = 1.0 / spec.imu_rate_hz
    p_imu = imu_point_m(config)
    src = np.clip(idx - round(spec.clock_offset_ms[1] * 1e-3 * spec.fine_rate_hz), 0, idx[-1])
    turn = imu_mounting(spec.imu_misalign_deg)
    inertial = truth.point_accel_body(p_imu)[src] @ turn
    force = truth.specific_force_body(p_imu)[src] @ turn
    rate = truth.omega_radps[src] @ turn

    accel_bias = rng.standard_normal(3) * spec.accel_bias_std_mps2
    gyro_bias = rng.standard_normal(3) * spec.gyro_bias_std_radps
    accel = (
        force
        + accel_bias[None, :]
        + _random_walk(rng, n, dt, spec.accel_bias_walk_mps2)
        + rng.standard_normal((n, 3)) * spec.accel_std_mps2
        + rng.standard_normal((n, 3)) * spec.accel_noise_rel * inertial
    )
    gyro = (
        rate
        + gyro_bias[None, :]
        + _random_walk(rng, n, dt, spec.gyro_bias_walk_radps)
        + rng.standard_normal((n, 3)) * spec.gyro_std_radps
        + rng.standard_normal((n, 3)) * spec.gyro_noise_rel * rate
    )
    stamps = _stamps(start_ns, truth.t_s[idx])
    latency = round(spec.imu_latency_ms * 1e6)
    period_ns = round(1e9 / spec.imu_rate_hz)
    out: list[Emission] = []
    for lo in range(0, n, spec.imu_batch_len):
        hi = min(lo + spec.imu_batch_len, n)
        batch = ImuBatch(
            stamp_ns=stamps[lo:hi].copy(),
            accel_mps2=accel[lo:hi].copy(),
            gyro_radps=gyro[lo:hi].copy(),
        )
        key = int(stamps[hi - 1])
        out.append(Emission(key, key + latency, 1, batch, key + period_ns - 1))
    return out


def edge_times_s(
    t_s: FloatArray,
    angle_rad: FloatArray,
    tooth_edges_rad: FloatArray,
    angle0_rad: float,
) -> FloatArray:
    """Times at which ``angle0 + angle(t)`` crosses ``tooth_edges + 2π·m`` (any integer m ≥ 0).

    ``angle_rad`` is non-decreasing (wheels never roll backwards in the scenarios); crossings are
    located by linear interpolation between grid points. ``tooth_edges_rad`` is sorted in
    ``[0, 2π)``.
    """
    a = angle0_rad + angle_rad
    a_lo, a_hi = float(a[0]), float(a[-1])
    m0 = math.floor(a_lo / (2 * math.pi))
    m1 = math.floor(a_hi / (2 * math.pi))
    turns = np.arange(m0, m1 + 1) * (2 * math.pi)
    targets = (turns[:, None] + tooth_edges_rad[None, :]).ravel()
    targets = targets[(targets > a_lo) & (targets <= a_hi)]
    if targets.size == 0:
        return np.zeros(0)
    j = np.searchsorted(a, targets, side="left")
    j = np.clip(j, 1, a.size - 1)
    a0, a1 = a[j - 1], a[j]
    t0, t1 = t_s[j - 1], t_s[j]
    frac = (targets - a0) / np.where(a1 > a0, a1 - a0, 1.0)
    return t0 + frac * (t1 - t0)


def wheel_emissions(
    truth: FineTruth,
    spec: SensorSpec,
    config: WheeledRearDriveConfig,
    start_ns: int,
    rng: np.random.Generator,
) -> list[Emission]:
    """Per-wheel rising edges, grouped in ``wheel_batch_ms`` windows."""
    ns = config.encoder.teeth_per_rev
    pitch = 2 * math.pi / ns
    tick_ns = round(1e9 / spec.edge_clock_hz)
    window_ns = round(spec.wheel_batch_ms * 1e6)
    latency = round(spec.wheel_latency_ms * 1e6)
    out: list[Emission] = []
    for wheel in (Wheel.LEFT, Wheel.RIGHT):
        dev = np.clip(rng.standard_normal(ns) * spec.tooth_error_rel, -0.4, 0.4) * pitch
        teeth = np.arange(ns) * pitch + dev
        teeth = np.sort(np.mod(teeth, 2 * math.pi))
        angle0 = float(rng.uniform(0.0, 2 * math.pi))
        t_edges = edge_times_s(truth.t_s, truth.wheel_angle_rad[:, int(wheel)], teeth, angle0)
        t_edges = t_edges + spec.clock_offset_ms[2] * 1e-3
        t_edges = t_edges[(t_edges >= 0.0) & (t_edges <= truth.t_s[-1])]
        rel_ns = np.floor(t_edges * 1e9 / tick_ns).astype(np.int64) * tick_ns
        stamps = start_ns + rel_ns
        win = rel_ns // window_ns
        if stamps.size == 0:
            continue
        cuts = np.flatnonzero(np.diff(win)) + 1
        for chunk, w in zip(np.split(stamps, cuts), np.split(win, cuts), strict=True):
            direction = np.ones(chunk.size, dtype=np.int8) if config.encoder.has_direction else None
            edges = WheelEdges(wheel=wheel, stamp_ns=chunk.copy(), direction=direction)
            end = start_ns + int(w[0] + 1) * window_ns
            out.append(Emission(int(chunk[-1]), end + latency, 2 + int(wheel), edges, end - 1))
    return out


#: A wheel heartbeat as a measurement: edges of no stamps (nothing on either wheel); with an
#: ``until_ns`` it is sent as an empty wheels packet.
NO_EDGES = WheelEdges(Wheel.LEFT, np.zeros(0, dtype=np.int64))


def wheel_heartbeats(
    wheels: Sequence[Emission], spec: SensorSpec, start_ns: int, end_ns: int
) -> npt.NDArray[np.int64]:
    """The wheel windows in which neither wheel had an edge, as heartbeats.

    A vehicle standing still (or creeping slower than one tooth per window) has no edge to send;
    a heartbeat tells the server that nothing is missing up to the window's end, so it need not
    hold the vehicle's other streams back waiting for wheel data.

    Parameters
    ----------
    wheels : sequence of Emission
        What :func:`wheel_emissions` returned for the run.
    spec : SensorSpec
        ``wheel_batch_ms``, ``wheel_latency_ms``, ``wheel_heartbeats``.
    start_ns, end_ns : int
        The run's first and last sensor time; whole windows in between are covered.

    Returns
    -------
    ndarray, shape (k, 2), int64
        ``(arrival_ns, until_ns)`` per heartbeat, in time order: ``until_ns`` is the window's
        end − 1 ns; it arrives ``wheel_latency_ms`` after the end. Empty when heartbeats are off.
    """
    window_ns = round(spec.wheel_batch_ms * 1e6)
    n = (end_ns - start_ns) // window_ns if spec.wheel_heartbeats else 0
    sent = np.zeros(max(n, 0), dtype=bool)
    if wheels and n > 0:
        until = np.array([e.until_ns for e in wheels], dtype=np.int64)
        windows = (until + 1 - start_ns) // window_ns - 1
        sent[windows[windows < n]] = True
    ends = start_ns + (np.flatnonzero(~sent).astype(np.int64) + 1) * window_ns
    latency = round(spec.wheel_latency_ms * 1e6)
    return np.stack([ends + latency, ends - 1], axis=1).astype(np.int64).reshape(-1, 2)
