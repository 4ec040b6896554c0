"""The crawler's sensors: IMU (100 Hz, batches of 10), GNSS (10 Hz, outages), odometer and
sprocket edges (100 ms packets), each with the imperfections :class:`CrawlerSensors` states.

Every packet's key is the end of its 100 ms window (a GNSS epoch: its stamp), so once every
packet keyed at or before ``T`` is delivered, each stream is complete up to ``T``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.base import Measurement
from estimator.config import TrackedConfig
from estimator.geo import EnuFrame
from estimator.gyro import ADIS16470, GyroPart
from estimator.sim._signals import cumtrapz
from estimator.sim.tracked.physics import GRAVITY_MPS2, RATE_HZ, CrawlerTruth
from estimator.types import GnssFix, GnssSample, ImuBatch, OdometerEdges, SprocketEdges, TrackSide

__all__ = [
    "CrawlerSensors",
    "SensorErrors",
    "antenna_offset_m",
    "antenna_offset_rate_mps",
    "body_rates",
    "draw_errors",
    "emissions",
    "gnss_epochs_s",
    "tilt_bias_walk",
]

_WINDOW = RATE_HZ // 10  # grid points per 100 ms packet


@dataclass(frozen=True, slots=True)
class CrawlerSensors:
    """Sensor imperfections (1-sigma unless said).

    The gyro is ``gyro_part`` (by default the ADIS16470, :mod:`estimator.gyro`) with
    its white rate noise and in-run bias walk both ``gyro_grade`` times the data sheet's (the
    knob for a worse part: 1 is the part, 1.2-1.7 a consumer MEMS gyro such as the BMI088).
    The gyro z turn-on bias, scale error and the odometer's true ``K_D`` error are drawn per
    run; ``*_tooth_error`` is each tooth's position error as a fraction of the pitch (fixed
    per tooth, so it repeats every revolution of the shaft or sprocket). The GNSS up
    velocity's noise is ``gnss_up_vel_std_ratio`` times the horizontal ``gnss_vel_std_mps``
    (a receiver's vertical is 1.5-2 times noisier; 1 keeps the named routes' draws).

    Clocks: the IMU's is the reference (the filter ticks on it). ``*_clock_offset_s`` is a
    stream's clock less the IMU's (+: its stamps lead, a sample stamped ``s`` was taken at
    ``s − offset`` on the IMU's clock): the receiver's, the odometer's and the sprockets'
    (one counter board for both). The receiver's epochs sit on whole tenths of its own clock,
    each moved by a jitter of 1σ ``gnss_epoch_jitter_s`` (clipped at 3σ) that its stamp
    carries. All 0 (the named routes): every fix on a whole tenth of the IMU's clock.
    """

    gyro_part: GyroPart = ADIS16470
    gyro_grade: float = 1.0
    gyro_bias_std_radps: float = 5e-4
    gyro_scale_std: float = 0.003
    accel_bias_std_mps2: float = 0.03
    accel_noise_mps2: float = 0.05
    gnss_pos_std_m: float = 0.02
    gnss_vel_std_mps: float = 0.03
    gnss_up_vel_std_ratio: float = 1.0
    kd_error_std: float = 0.005
    odometer_teeth: int = 60
    odometer_tooth_error: float = 0.015
    sprocket_tooth_error: float = 0.005
    sprocket_radius_error_std: float = 0.002
    edge_jitter_s: float = 2e-5
    gnss_clock_offset_s: float = 0.0
    odometer_clock_offset_s: float = 0.0
    sprocket_clock_offset_s: float = 0.0
    gnss_epoch_jitter_s: float = 0.0

    @property
    def gyro_fitted(self) -> GyroPart:
        """The gyro as its figures are: the part's, times the grade (the part itself at 1)."""
        return self.gyro_part if self.gyro_grade == 1.0 else self.gyro_part.scaled(self.gyro_grade)

    @property
    def gyro_noise_radps(self) -> float:
        """White rate noise of one 100 Hz sample (rad/s)."""
        return self.gyro_grade * self.gyro_part.sample_noise_radps(RATE_HZ)

    @property
    def gyro_bias_walk_radps(self) -> float:
        """In-run bias walk (rad/s per √s)."""
        return self.gyro_grade * self.gyro_part.bias_walk_radps_rt_s


@dataclass(frozen=True, slots=True)
class SensorErrors:
    """The run's drawn errors: true ``K_D`` and sprocket radius over the configured ones,
    gyro z bias (rad/s, its walk), gyro scale error, accelerometer biases (x, y)."""

    kd_scale: float
    sprocket_scale: float
    gyro_bias_radps: FloatArray
    gyro_scale: float
    accel_bias_mps2: tuple[float, float]


def draw_errors(rng: np.random.Generator, n: int, spec: CrawlerSensors) -> SensorErrors:
    walk = np.cumsum(rng.standard_normal(n)) * spec.gyro_bias_walk_radps / np.sqrt(RATE_HZ)
    return SensorErrors(
        kd_scale=1.0 + float(np.clip(rng.normal(0, spec.kd_error_std), -0.015, 0.015)),
        sprocket_scale=1.0 + float(rng.normal(0, spec.sprocket_radius_error_std)),
        gyro_bias_radps=rng.normal(0, spec.gyro_bias_std_radps) + walk,
        gyro_scale=float(rng.normal(0, spec.gyro_scale_std)),
        accel_bias_mps2=(
            float(rng.normal(0, spec.accel_bias_std_mps2)),
            float(rng.normal(0, spec.accel_bias_std_mps2)),
        ),
    )


def tilt_bias_walk(rng: np.random.Generator, n: int, spec: CrawlerSensors) -> FloatArray:
    """The pitch and roll gyros' in-run bias walk ``(n, 2)`` (rad/s) over ``n`` samples at
    ``RATE_HZ``, from 0: a random walk of ``spec.gyro_bias_walk_radps`` per √s, the yaw
    gyro's (an IMU's data sheet states one in-run bias stability for its three gyros)."""
    steps = rng.standard_normal((n, 2)) * spec.gyro_bias_walk_radps / np.sqrt(RATE_HZ)
    return np.asarray(np.cumsum(steps, axis=0))


def _stamps(start_ns: int, t_s: FloatArray) -> IntArray:
    return start_ns + np.round(t_s * 1e9).astype(np.int64)


def _edge_times(
    t_s: FloatArray,
    dist_m: FloatArray,
    pitch_m: float,
    tooth_err: FloatArray,
    rng: np.random.Generator,
    jitter_s: float,
) -> FloatArray:
    """Times at which ``dist_m`` (non-decreasing) passes each tooth ``(k + err[k mod T])·pitch``."""
    count = int(dist_m[-1] // pitch_m)
    if count < 2:
        return np.zeros(0)
    k = np.arange(1, count)
    pos = (k + tooth_err[k % tooth_err.size]) * pitch_m
    idx = np.clip(np.searchsorted(dist_m, pos, side="left"), 1, dist_m.size - 1)
    d0, d1 = dist_m[idx - 1], dist_m[idx]
    frac = np.clip((pos - d0) / np.maximum(d1 - d0, 1e-12), 0.0, 1.0)
    t = t_s[idx - 1] + frac * (t_s[idx] - t_s[idx - 1])
    return np.sort(t + jitter_s * rng.standard_normal(t.size))


def _packets(edge_t: FloatArray, window_ends_s: FloatArray) -> list[FloatArray]:
    """Edges split by window ``(end − 0.1, end]``."""
    cuts = np.searchsorted(edge_t, window_ends_s, side="right")
    starts = np.concatenate([[0], cuts[:-1]])
    return [edge_t[a:b] for a, b in zip(starts, cuts, strict=True)]


def body_rates(truth: CrawlerTruth) -> FloatArray:
    """The hull's body rates ``(n, 3)``: pitch rate (about the right axis), roll rate (about
    the forward axis) and yaw rate (about its up axis), from the Z-X-Y Euler rates:
    ``ω_x = θ̇·cos φ − Ẏ·cos θ·sin φ``, ``ω_y = φ̇ + Ẏ·sin θ``, ``ω_z = θ̇·sin φ + Ẏ·cos θ·cos φ``
    with ``Ẏ`` the heading's counter-clockwise rate (``ω_z`` is the tracks' turn rate)."""
    dt = 1.0 / RATE_HZ
    theta, phi = truth.pitch_rad, truth.roll_rad
    d_theta, d_phi = np.gradient(theta, dt), np.gradient(phi, dt)
    d_yaw = -np.gradient(truth.heading_rad, dt) if truth.heading_rad.size > 1 else 0.0 * theta
    wx = d_theta * np.cos(phi) - d_yaw * np.cos(theta) * np.sin(phi)
    wy = d_phi + d_yaw * np.sin(theta)
    return np.stack([wx, wy, truth.yaw_rate_radps], axis=1)


def _imu(
    truth: CrawlerTruth,
    cfg: TrackedConfig,
    err: SensorErrors,
    spec: CrawlerSensors,
    rng: np.random.Generator,
    tilt_bias_radps: tuple[float, float] | FloatArray = (0.0, 0.0),
) -> tuple[FloatArray, FloatArray]:
    """Specific force and angular rate at the IMU's lever arm in the body frame (X right,
    Y forward, Z up), shapes ``(n, 3)``: ``f = a + g·u`` with ``u`` the world's up in the
    body frame, ``(−cos θ·sin φ, sin θ, cos θ·cos φ)``, and ``a`` the hull's acceleration
    ``v̇ + ω×v`` (``v = (v_x, V, 0)``; lever-arm terms of the yaw only). The pitch and roll
    gyros read :func:`body_rates` plus ``tilt_bias_radps`` (two numbers, or ``(n, 2)``: a
    bias that walks); the yaw gyro its rate with the run's bias and scale error."""
    dt = 1.0 / RATE_HZ
    w, v, vx = truth.yaw_rate_radps, truth.speed_mps, truth.lateral_mps
    rates = body_rates(truth)
    alpha = np.gradient(w, dt)
    x, y, _ = cfg.geometry.imu_lever_arm_m
    ax = np.gradient(vx, dt) - w * v - alpha * y - w * w * x
    ay = np.gradient(v, dt) + w * vx + alpha * x - w * w * y
    az = rates[:, 0] * v - rates[:, 1] * vx
    theta, phi = truth.pitch_rad, truth.roll_rad
    n = w.size
    g = GRAVITY_MPS2
    accel = np.stack(
        [
            ax - g * np.cos(theta) * np.sin(phi) + err.accel_bias_mps2[0],
            ay + g * np.sin(theta) + err.accel_bias_mps2[1],
            az + g * np.cos(theta) * np.cos(phi),
        ],
        axis=1,
    )
    accel += spec.accel_noise_mps2 * rng.standard_normal((n, 3))
    gyro = spec.gyro_noise_radps * rng.standard_normal((n, 3))
    tilt = np.broadcast_to(np.asarray(tilt_bias_radps, dtype=np.float64), (n, 2))
    gyro[:, :2] += rates[:, :2] + tilt
    gyro[:, 2] += (1.0 + err.gyro_scale) * w + err.gyro_bias_radps
    return accel, gyro


def gnss_epochs_s(
    t_s: FloatArray, spec: CrawlerSensors, jitter_rng: np.random.Generator | None
) -> tuple[FloatArray, FloatArray | None]:
    """The receiver's epochs: their stamps ``(m,)`` (s, the receiver's clock: the whole
    tenths ``t_s`` each moved by its jitter, drawn by ``jitter_rng``; none without it) and the
    instants they were taken on the IMU's clock, ``stamp − gnss_clock_offset_s`` (None where
    those are ``t_s`` itself: no offset and no jitter)."""
    stamp = t_s
    if jitter_rng is not None and spec.gnss_epoch_jitter_s > 0.0:
        z = np.clip(jitter_rng.standard_normal(t_s.size), -3.0, 3.0)
        stamp = t_s + spec.gnss_epoch_jitter_s * z
    if stamp is t_s and spec.gnss_clock_offset_s == 0.0:
        return t_s, None
    return stamp, stamp - spec.gnss_clock_offset_s


def _at(truth: CrawlerTruth, name: str, idx: IntArray, t_s: FloatArray | None) -> FloatArray:
    """The truth's ``name`` at the grid points ``idx``, or at the instants ``t_s`` (linear
    between grid points, held beyond the run) where given."""
    values: FloatArray = getattr(truth, name)
    return values[idx] if t_s is None else np.interp(t_s, truth.t_s, values)


def antenna_offset_m(
    lever_arm_m: tuple[float, float, float], pitch_rad: FloatArray, roll_rad: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The antenna's offset from the hull centre, each shaped as the angles: forward and right
    (level, along and across the heading) and up, its lever arm ``(x, y, z)`` (right,
    forward, up) pitched by ``θ`` (nose up +) and rolled by ``φ`` (right side down +):
    ``fwd = y·cos θ − z·sin θ·cos φ``, ``right = x·cos φ + z·sin φ``, ``up = z·cos θ·cos φ
    + y·sin θ − x·sin φ``."""
    x, y, z = lever_arm_m
    ct, st, cp, sp = np.cos(pitch_rad), np.sin(pitch_rad), np.cos(roll_rad), np.sin(roll_rad)
    return y * ct - z * st * cp, x * cp + z * sp, z * ct * cp + y * st - x * sp


def antenna_offset_rate_mps(
    truth: CrawlerTruth, lever_arm_m: tuple[float, float, float]
) -> FloatArray:
    """The time derivative of the antenna's offset from the hull centre in east, north, up
    ``(n, 3)`` on the truth's grid (m/s): :func:`antenna_offset_m` turned by the heading
    ``ψ`` (from north, clockwise), ``east = right·cos ψ + fwd·sin ψ``, ``north = −right·sin ψ
    + fwd·cos ψ``, differentiated by central differences. It holds the yaw's turn of the
    lever arm and the mast's swing with the pitch and roll rates; 0 where the lever arm is
    upright (``x = y = 0``) on level ground."""
    fwd, right, up = antenna_offset_m(lever_arm_m, truth.pitch_rad, truth.roll_rad)
    psi = truth.heading_rad
    east = right * np.cos(psi) + fwd * np.sin(psi)
    north = -right * np.sin(psi) + fwd * np.cos(psi)
    offset = np.stack([east, north, up], axis=1)
    if offset.shape[0] < 2:
        return np.zeros_like(offset)
    return np.asarray(np.gradient(offset, 1.0 / RATE_HZ, axis=0))


def _interp_rows(t_s: FloatArray, grid_s: FloatArray, values: FloatArray) -> FloatArray:
    """Each column of ``values (n, c)`` on ``grid_s`` read at ``t_s (m,)``: ``(m, c)``."""
    return np.stack([np.interp(t_s, grid_s, values[:, i]) for i in range(values.shape[1])], 1)


def _gnss(
    truth: CrawlerTruth,
    cfg: TrackedConfig,
    spec: CrawlerSensors,
    frame: EnuFrame,
    outages_s: tuple[tuple[float, float], ...],
    start_ns: int,
    rng: np.random.Generator,
    up_rng: np.random.Generator | None = None,
    jitter_rng: np.random.Generator | None = None,
) -> list[tuple[int, Measurement]]:
    """10 Hz fixes of the antenna, each taken at its epoch's instant and stamped on the
    receiver's clock (:func:`gnss_epochs_s`): its position the hull centre's plus the lever
    arm turned by heading, pitch and roll (:func:`antenna_offset_m`), height included; its
    velocity the hull centre's (``V·cos θ`` along the heading, ``v_x`` to its right, ``V·sin
    θ`` up) plus the offset's rate (:func:`antenna_offset_rate_mps`: the yaw's, the pitch's
    and the roll's swing of the mast), so the velocity is the position's derivative. The up
    velocity's noise from ``up_rng`` (none without it)."""
    idx = np.arange(_WINDOW, truth.t_s.size, _WINDOW)
    stamp_s, taken_s = gnss_epochs_s(truth.t_s[idx], spec, jitter_rng)

    def at(name: str) -> FloatArray:
        return _at(truth, name, idx, taken_s)

    psi, theta = at("heading_rad"), at("pitch_rad")
    east, north, up = _antenna_enu(cfg, at, psi, theta)
    ve, vn, vu = _antenna_velocity(at, psi, theta, _offset_rate(truth, cfg, idx, taken_s))
    east, north, ve, vn, vu = _gnss_noise(spec, (east, north, ve, vn, vu), rng, up_rng)
    lat, lon, h = frame.to_geodetic(east, north, up)
    t = truth.t_s[idx] if taken_s is None else taken_s  # the sky is lost on the IMU's clock
    lost = _lost(t, outages_s)
    return _gnss_samples(
        _stamps(start_ns, stamp_s).tolist(), lost, (ve, vn, vu), (lat, lon, h), spec
    )


def _antenna_enu(
    cfg: TrackedConfig, at: Callable[[str], FloatArray], psi: FloatArray, theta: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The antenna's east, north, up ``(m,)`` at the fixes: the hull centre's (``at``: the
    truth at the fixes) plus the lever arm turned by heading ``psi``, pitch ``theta`` and roll."""
    fwd, right, up_off = antenna_offset_m(cfg.geometry.antenna_lever_arm_m, theta, at("roll_rad"))
    up = at("up_m") + up_off
    east = at("east_m") + right * np.cos(psi) + fwd * np.sin(psi)
    north = at("north_m") - right * np.sin(psi) + fwd * np.cos(psi)
    return east, north, up


def _offset_rate(
    truth: CrawlerTruth, cfg: TrackedConfig, idx: IntArray, taken_s: FloatArray | None
) -> FloatArray:
    """The lever arm's rate ``(m, 3)`` (east, north, up) at the grid points ``idx`` or at the
    instants ``taken_s`` (:func:`antenna_offset_rate_mps`)."""
    grid_rate = antenna_offset_rate_mps(truth, cfg.geometry.antenna_lever_arm_m)
    return grid_rate[idx] if taken_s is None else _interp_rows(taken_s, truth.t_s, grid_rate)


def _antenna_velocity(
    at: Callable[[str], FloatArray], psi: FloatArray, theta: FloatArray, rate: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The antenna's east, north, up velocity ``(m,)``: the hull centre's (``V·cos θ`` along
    the heading, ``v_x`` to its right, ``V·sin θ`` up) plus the offset's ``rate`` ``(m, 3)``."""
    v_along = at("speed_mps")
    vf, vr = v_along * np.cos(theta), at("lateral_mps")
    ve = vf * np.sin(psi) + vr * np.cos(psi) + rate[:, 0]
    vn = vf * np.cos(psi) - vr * np.sin(psi) + rate[:, 1]
    vu = v_along * np.sin(theta) + rate[:, 2]
    return ve, vn, vu


def _gnss_noise(
    spec: CrawlerSensors,
    fixes: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray],
    rng: np.random.Generator,
    up_rng: np.random.Generator | None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """``fixes`` (east, north, v_east, v_north, v_up, each ``(m,)``) with the receiver's noise,
    drawn from ``rng`` in that order; the up velocity's from ``up_rng`` (none without it)."""
    east, north, ve, vn, vu = fixes
    n = east.size
    east = east + spec.gnss_pos_std_m * rng.standard_normal(n)
    north = north + spec.gnss_pos_std_m * rng.standard_normal(n)
    ve = ve + spec.gnss_vel_std_mps * rng.standard_normal(n)
    vn = vn + spec.gnss_vel_std_mps * rng.standard_normal(n)
    if up_rng is not None:
        up_std = spec.gnss_up_vel_std_ratio * spec.gnss_vel_std_mps
        vu = vu + up_std * up_rng.standard_normal(n)
    return east, north, ve, vn, vu


def _lost(t_s: FloatArray, outages_s: tuple[tuple[float, float], ...]) -> BoolArray:
    """Fixes ``(m,)`` taken within an outage ``(start, duration)``."""
    lost = np.zeros(t_s.size, dtype=bool)
    for a, d in outages_s:
        lost |= (t_s >= a) & (t_s < a + d)
    return lost


def _gnss_samples(
    stamps: list[int],
    lost: BoolArray,
    vel: tuple[FloatArray, FloatArray, FloatArray],
    geo: tuple[FloatArray, FloatArray, FloatArray],
    spec: CrawlerSensors,
) -> list[tuple[int, Measurement]]:
    """One :class:`GnssSample` per stamp: RTK fixed with velocity ``vel`` (east, north, up) and
    position ``geo`` (lat, lon, height), each ``(m,)``, or no fix where ``lost``."""
    ve, vn, vu = vel
    lat, lon, h = geo
    out: list[tuple[int, Measurement]] = []
    nan = float("nan")
    for k, stamp in enumerate(stamps):
        if lost[k]:
            sample = GnssSample(stamp, (nan, nan, nan), nan, nan, nan, nan, nan, nan, GnssFix.NONE)
        else:
            sample = GnssSample(
                stamp,
                (float(ve[k]), float(vn[k]), float(vu[k])),
                nan,
                nan,
                nan,
                float(lat[k]),
                float(lon[k]),
                float(h[k]),
                GnssFix.RTK_FIXED,
                spec.gnss_vel_std_mps,
            )
        out.append((stamp, sample))
    return out


def emissions(
    truth: CrawlerTruth,
    cfg: TrackedConfig,
    spec: CrawlerSensors,
    err: SensorErrors,
    frame: EnuFrame,
    outages_s: tuple[tuple[float, float], ...],
    start_ns: int,
    rng: np.random.Generator,
    extra_rng: np.random.Generator | None = None,
    walk_rng: np.random.Generator | None = None,
    jitter_rng: np.random.Generator | None = None,
) -> list[tuple[int, Measurement]]:
    """Every packet as ``(key_ns, measurement)``, sorted by key (GNSS, edges, IMU within one).

    ``extra_rng`` draws what the level-ground sensors never drew (the pitch and roll gyros'
    turn-on biases, 1σ ``gyro_bias_std_radps``, and the GNSS up velocity's noise), so every
    draw of ``rng`` stays as it was; without it those are 0. ``walk_rng`` draws the pitch and
    roll gyros' in-run bias walk, the part's figure as the yaw gyro's
    (:func:`tilt_bias_walk`); without it their biases stay at the turn-on value.
    ``jitter_rng`` draws the receiver's epoch jitter (:func:`gnss_epochs_s`; none without
    it). Each stream is stamped on its own clock (``spec``'s ``*_clock_offset_s``); a fix is
    keyed by its stamp, an edge packet by the end of its window on its stream's clock."""
    t = truth.t_s
    ends = t[_WINDOW::_WINDOW]
    windows = (start_ns, ends, _stamps(start_ns, ends).tolist())
    tilt_bias = _tilt_bias(extra_rng, walk_rng, t.size, spec)
    accel, gyro = _imu(truth, cfg, err, spec, rng, tilt_bias)
    out = _gnss(truth, cfg, spec, frame, outages_s, start_ns, rng, extra_rng, jitter_rng)
    out += _edge_packets(truth, cfg, spec, err, rng, windows)
    stamps = _stamps(start_ns, t)
    for j, key in enumerate(windows[2]):
        sl = slice(j * _WINDOW + 1, (j + 1) * _WINDOW + 1)
        out.append((key, ImuBatch(stamps[sl], accel[sl], gyro[sl])))
    order = {GnssSample: 0, OdometerEdges: 1, SprocketEdges: 2, ImuBatch: 3}
    out.sort(key=lambda km: (km[0], order[type(km[1])]))
    return out


def _tilt_bias(
    extra_rng: np.random.Generator | None,
    walk_rng: np.random.Generator | None,
    n: int,
    spec: CrawlerSensors,
) -> FloatArray:
    """The pitch and roll gyros' biases: turn-on ``(2,)`` from ``extra_rng`` (0 without it),
    plus the in-run walk ``(n, 2)`` from ``walk_rng`` (:func:`tilt_bias_walk`) if given."""
    tilt_bias: FloatArray = np.zeros(2)
    if extra_rng is not None:
        tilt_bias = extra_rng.normal(0.0, spec.gyro_bias_std_radps, 2)
    if walk_rng is not None:
        tilt_bias = tilt_bias + tilt_bias_walk(walk_rng, n, spec)
    return tilt_bias


def _edge_packets(
    truth: CrawlerTruth,
    cfg: TrackedConfig,
    spec: CrawlerSensors,
    err: SensorErrors,
    rng: np.random.Generator,
    windows: tuple[int, FloatArray, list[int]],
) -> list[tuple[int, Measurement]]:
    """The odometer's edges, then each sprocket's (left, right), one packet per window
    (``windows``: start ns, window ends s ``(w,)``, their keys ns), each stream stamped on its
    clock; per stream its tooth errors, then its edges' jitter, from ``rng``."""
    start_ns, ends, ends_ns = windows
    dt = 1.0 / RATE_HZ
    odo_err = spec.odometer_tooth_error * rng.standard_normal(spec.odometer_teeth)
    odo_t = _edge_times(
        truth.t_s,
        cumtrapz(truth.gearbox_mps, dt),
        cfg.odometer.distance_per_edge_m * err.kd_scale,
        odo_err,
        rng,
        spec.edge_jitter_s,
    )
    odo_t = odo_t + spec.odometer_clock_offset_s
    out: list[tuple[int, Measurement]] = []
    for key, part in zip(ends_ns, _packets(odo_t, ends), strict=True):
        out.append((key, OdometerEdges(_stamps(start_ns, part))))
    pitch = 2.0 * np.pi * cfg.sprocket.pitch_radius_m * err.sprocket_scale
    pitch /= cfg.sprocket.teeth_per_rev
    for side in TrackSide:
        tooth = spec.sprocket_tooth_error * rng.standard_normal(cfg.sprocket.teeth_per_rev)
        dist = cumtrapz(truth.sprocket_mps[:, int(side)], dt)
        edge_t = _edge_times(truth.t_s, dist, pitch, tooth, rng, spec.edge_jitter_s)
        edge_t = edge_t + spec.sprocket_clock_offset_s
        for key, part in zip(ends_ns, _packets(edge_t, ends), strict=True):
            out.append((key, SprocketEdges(side, _stamps(start_ns, part))))
    return out
