"""One vehicle's inputs between ticks: IMU samples, GNSS fixes, odometer and sprocket edges.

:meth:`VehicleInputs.take` turns them into per-tick arrays (:class:`TickInputs`) for the
ticks due; bad input (non-finite samples, edges going backwards, fixes out of order) is
counted and never reaches the filter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray, due_ticks
from estimator.config import TrackedConfig
from estimator.geo import EnuFrame
from estimator.tracked.edges import EdgeBuffer, edge_speed, span_speed
from estimator.tracked.params import VehicleParams
from estimator.tracked.settings import TrackedEstimatorConfig
from estimator.types import GnssFix, GnssSample, ImuBatch, OdometerEdges, SprocketEdges

__all__ = [
    "KEEP_NS",
    "GnssAtTicks",
    "Reads",
    "TickInputs",
    "VehicleInputs",
    "at_tick",
    "derive",
    "gear_span",
    "mean_by_tick",
    "odometer_edges_at",
    "sprocket_missing",
    "starting_at",
    "steady_run",
    "tick_inputs",
]

_PITCH, _FORWARD, _YAW = 0, 1, 2
_RIGHT, _ROLL = 0, 1  # accelerometer's lateral axis, gyro's roll axis
_IMU_COLUMNS = 5  # forward force, yaw rate, pitch rate, roll rate, lateral force


GnssAtTicks = tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]
"""A tick's fix: position ``(m, 2)``, horizontal velocity ``(m, 2)``, its std, its age (s)
and the up velocity ``(m,)`` each."""


@dataclass(frozen=True, slots=True)
class TickInputs:
    """Inputs of ``m`` ticks: shapes ``(m,)``; ``*_pair`` ``(m, 2)`` (left/right or E/N).

    ``accel_mps2`` (forward specific force), ``gyro_radps`` (yaw rate),
    ``pitch_rate_radps`` and ``roll_rate_radps`` (the gyro about the right and the forward
    axis) and ``lateral_accel_mps2`` (the specific force to the right) are the means of the
    tick's ``imu_samples`` IMU samples; ``imu_age_s`` is how long before the tick their
    stamps lie on average (each sample is the rate or force at its stamp; NaN without one).

    ``sprocket_pair_mps`` are the sprocket speeds carried from their windows' centres to the
    tick with the gearbox's acceleration (each sprocket turns at a fixed ratio of the gearbox
    between lever moves), so both tracks are read at one instant. ``gear_ratio`` is the
    faster sprocket's speed over the odometer's over the same span of
    time (1 in direct drive, 1/1.42 in the low gear; NaN when unknown). ``yaw_accel_radps2``
    is the change of the tick's mean gyro rate from the tick before over one tick (0 on a
    vehicle's first tick). ``*_before`` are the sprocket speeds and gear ratio of the tick
    before, read the same way (their change over the tick shows a lever moving).
    ``sprocket_starting_pair`` marks a sprocket's first edges after a silence (a brake being
    released, or a start from standstill), ``(m, 2)``.
    ``gearbox_accel_mps2`` is the odometer's acceleration (two consecutive windows), the
    gearbox's: the hull's lags it, and slows in every lever move.
    ``steady_s`` is how long the gearbox has run at a steady speed with no sprocket settling
    (the hull's lag behind its tracks, and the slip that acceleration adds, have died out).
    ``odometer_edges`` counts the odometer's edges in the tick ``(t − tick, t]`` and
    ``odometer_gap_s`` is the silence before the first of them (s; inf when no edge came
    before it, 0 in a tick without an edge): a start's first edges after a stop, which the
    windows cannot yet turn into a speed (:func:`odometer_edges_at`).
    """

    ticks_ns: IntArray
    accel_mps2: FloatArray
    gyro_radps: FloatArray
    pitch_rate_radps: FloatArray
    roll_rate_radps: FloatArray
    lateral_accel_mps2: FloatArray
    imu_samples: IntArray
    imu_age_s: FloatArray
    yaw_accel_radps2: FloatArray
    odometer_mps: FloatArray
    odometer_lag_s: FloatArray
    sprocket_pair_mps: FloatArray
    sprocket_missing: BoolArray
    sprocket_settling_pair: BoolArray
    sprocket_starting_pair: BoolArray
    gear_ratio: FloatArray
    sprocket_before_pair_mps: FloatArray
    gear_ratio_before: FloatArray
    gearbox_accel_mps2: FloatArray
    steady_s: FloatArray
    odometer_edges: IntArray
    odometer_gap_s: FloatArray
    gnss_pos_pair_m: FloatArray
    gnss_vel_pair_mps: FloatArray
    gnss_vel_std_mps: FloatArray
    gnss_age_s: FloatArray
    gnss_vel_up_mps: FloatArray


class VehicleInputs:
    """Buffers of one vehicle and its tick grid."""

    def __init__(self, config: TrackedConfig, cfg: TrackedEstimatorConfig) -> None:
        self.config = config
        self.cfg = cfg
        self.params = VehicleParams.of(config)
        self.tick_ns = cfg.tick_ns
        self.next_ns: int | None = None
        self.imu_ns: IntArray = np.zeros(0, dtype=np.int64)
        self.imu: FloatArray = np.zeros((0, _IMU_COLUMNS))
        self.odometer = EdgeBuffer()
        self.sprockets = (EdgeBuffer(), EdgeBuffer())
        # (stamp_ns, east_m, north_m, ve_mps, vn_mps, vel_std_mps, vu_mps)
        self.gnss: list[tuple[int, float, float, float, float, float, float]] = []
        self.frame: EnuFrame | None = None
        self.counts = {"imu_skipped": 0, "gnss_skipped": 0, "sprocket_missing_ticks": 0}
        self.last_gyro_radps = math.nan
        self.steady_s = 0.0

    # --- pushing -----------------------------------------------------------------------------
    def push_imu(self, m: ImuBatch) -> None:
        t = np.asarray(m.stamp_ns, dtype=np.int64)
        force = np.asarray(m.accel_mps2, dtype=np.float64).reshape(-1, 3)
        rates = np.asarray(m.gyro_radps, dtype=np.float64).reshape(-1, 3)
        cols = np.stack(
            [
                force[:, _FORWARD],
                rates[:, _YAW],
                rates[:, _PITCH],
                rates[:, _ROLL],
                force[:, _RIGHT],
            ],
            axis=1,
        )
        keep = np.isfinite(cols).all(axis=1)
        if self.imu_ns.size:
            keep &= t > self.imu_ns[-1]
        self.counts["imu_skipped"] += int(t.size - keep.sum())
        self.imu_ns = np.concatenate([self.imu_ns, t[keep]])
        self.imu = np.concatenate([self.imu, cols[keep]])
        if self.next_ns is None and self.imu_ns.size:
            self.next_ns = int(self.imu_ns[0]) + self.tick_ns

    def push_gnss(self, m: GnssSample) -> None:
        values = (*m.vel_enu_mps[:2], m.lat_deg, m.lon_deg, m.height_m)
        late = bool(self.gnss) and m.stamp_ns <= self.gnss[-1][0]
        if m.fix == GnssFix.NONE:
            return
        if late or not all(math.isfinite(v) for v in values):
            self.counts["gnss_skipped"] += 1
            return
        if self.frame is None:
            self.frame = EnuFrame(m.lat_deg, m.lon_deg, m.height_m)
        e, n, _ = self.frame.to_enu(m.lat_deg, m.lon_deg, m.height_m)
        std = m.vel_std_mps if math.isfinite(m.vel_std_mps) and m.vel_std_mps > 0 else math.nan
        up = float(m.vel_enu_mps[2])  # NaN where the receiver gives none: not fused
        self.gnss.append((m.stamp_ns, float(e), float(n), values[0], values[1], std, up))

    def push_edges(self, m: OdometerEdges | SprocketEdges) -> None:
        if isinstance(m, OdometerEdges):
            self.odometer.push(m.stamp_ns)
        else:
            self.sprockets[int(m.side)].push(m.stamp_ns)

    # --- ticks -------------------------------------------------------------------------------
    def due(self, until_ns: int) -> IntArray:
        """Ticks ``<= until_ns`` the IMU already covers, oldest first."""
        return due_ticks(self.next_ns, self.imu_ns, self.tick_ns, until_ns)

    def take(self, ticks: IntArray) -> TickInputs:
        """Inputs of ``ticks`` (from :meth:`due`); the buffers drop what no later tick needs.
        ``steady_s`` counts the gearbox and the sprockets only: the hull's own acceleration
        needs the pitch (gravity out of the accelerometer), so the filter counts it."""
        reads = self._reads(ticks)
        odo_accel, settling, unsteady = derive(reads, self.cfg)
        steady_s = steady_run(self.steady_s, unsteady, self.tick_ns)
        self.steady_s = float(steady_s[-1])
        self.counts["sprocket_missing_ticks"] += int(reads.missing.sum())
        self.next_ns = int(ticks[-1]) + self.tick_ns
        keep_from = int(ticks[-1]) - KEEP_NS
        for buf in (self.odometer, *self.sprockets):
            buf.prune(keep_from)
        return tick_inputs(reads, odo_accel, settling, steady_s, self.tick_ns)

    def _reads(self, ticks: IntArray) -> Reads:
        """What the buffers give for ``ticks`` (IMU and fixes consumed)."""
        means, samples, imu_age = self._imu_means(ticks)
        accel, gyro, pitch_rate, roll_rate, lateral = means
        odo, odo_c = self._odometer_speed(ticks)
        prev, prev_c = self._odometer_speed(ticks - self.tick_ns)
        spr, spr_c = self._sprocket_speeds(ticks)
        before, before_c = self._sprocket_speeds(ticks - self.tick_ns)
        return Reads(
            ticks_ns=ticks,
            accel=accel,
            gyro=gyro,
            pitch_rate=pitch_rate,
            roll_rate=roll_rate,
            lateral_accel=lateral,
            imu_samples=samples,
            imu_age=imu_age,
            yaw_accel=self._yaw_accel(gyro),
            odo=(odo, odo_c),
            prev=(prev, prev_c),
            spr=(spr, spr_c),
            before=(before, before_c),
            gear=self._gear_ratio(spr, spr_c, ticks),
            gear_before=self._gear_ratio(before, before_c, ticks - self.tick_ns),
            starting=self._starting(ticks),
            odometer_edges=self._odometer_edges(ticks),
            missing=self._sprocket_missing(ticks, odo),
            gnss=self._gnss_at(ticks),
        )

    def _imu_means(self, ticks: IntArray) -> tuple[list[FloatArray], IntArray, FloatArray]:
        """Mean of each IMU column (forward force, yaw, pitch and roll rate, lateral force)
        over each tick ``(t − tick, t]``, the samples each mean is of, and how long before
        the tick their stamps lie on average (s; NaN without a sample)."""
        bounds = np.concatenate([ticks[:1] - self.tick_ns, ticks])
        edges = np.searchsorted(self.imu_ns, bounds, side="right")
        count = np.diff(edges)
        tick_of = np.repeat(np.arange(ticks.size), count)
        part = self.imu[edges[0] : edges[-1]]
        out = []
        for col in range(_IMU_COLUMNS):
            sums = np.bincount(tick_of, part[:, col], minlength=ticks.size)
            with np.errstate(invalid="ignore", divide="ignore"):
                out.append(np.where(count > 0, sums / count, np.nan))
        before = (ticks[tick_of] - self.imu_ns[edges[0] : edges[-1]]).astype(np.float64) * 1e-9
        age = mean_by_tick(tick_of, before, count)
        cut = int(edges[-1])
        self.imu_ns, self.imu = self.imu_ns[cut:], self.imu[cut:]
        return out, count, age

    def _yaw_accel(self, gyro: FloatArray) -> FloatArray:
        """``(ω_t − ω_{t−1})/tick`` per tick from the ticks' mean rates (0 where unknown)."""
        before = np.concatenate([[self.last_gyro_radps], gyro[:-1]])
        self.last_gyro_radps = float(gyro[-1])
        return np.nan_to_num((gyro - before) / (self.tick_ns * 1e-9))

    def _sprocket_speeds(self, ticks: IntArray) -> tuple[FloatArray, FloatArray]:
        """Each sprocket's window speed and window centre, shapes ``(m, 2)``."""
        out = [
            edge_speed(
                buf.stamps,
                ticks,
                float(self.params.sprocket_pitch_m[0]),
                round(self.cfg.sprocket_window_s * 1e9),
                self.cfg.sprocket_max_edges,
                round(self.cfg.sprocket_hold_s * 1e9),
            )
            for buf in self.sprockets
        ]
        return np.stack([o[0] for o in out], axis=1), np.stack([o[1] for o in out], axis=1)

    def _starting(self, ticks: IntArray) -> BoolArray:
        """Sprockets, ``(m, 2)``, whose first edges after a second's silence came within the
        last 0.6 s (:func:`starting_at`)."""
        out = np.zeros((ticks.size, 2), dtype=bool)
        for side, buf in enumerate(self.sprockets):
            hi = np.searchsorted(buf.stamps, ticks, side="right")
            out[:, side] = starting_at(buf.stamps, np.zeros(1, dtype=np.int64), hi, ticks)
        return out

    def _odometer_edges(self, ticks: IntArray) -> tuple[IntArray, FloatArray]:
        """The odometer's edges in each tick and the silence before the first of them."""
        s = self.odometer.stamps
        hi = np.searchsorted(s, ticks, side="right")
        lo = np.searchsorted(s, ticks - self.tick_ns, side="right")
        return odometer_edges_at(s, np.zeros(1, dtype=np.int64), lo, hi)

    def _odometer_speed(self, ticks: IntArray) -> tuple[FloatArray, FloatArray]:
        return edge_speed(
            self.odometer.stamps,
            ticks,
            float(self.params.odometer_pitch_m[0]),
            round(self.cfg.odometer_window_s * 1e9),
            1 << 30,
            500_000_000,
        )

    def _gear_ratio(self, speed: FloatArray, centre: FloatArray, ticks: IntArray) -> FloatArray:
        """Faster sprocket over the odometer (:func:`gear_span`)."""
        fast, start, end = gear_span(speed, centre, ticks, self.tick_ns)
        odo = span_speed(self.odometer.stamps, start, end, float(self.params.odometer_pitch_m[0]))
        with np.errstate(divide="ignore", invalid="ignore"):
            return fast / odo

    def _sprocket_missing(self, ticks: IntArray, odometer_mps: FloatArray) -> BoolArray:
        """A sprocket with no edge for ``sprocket_missing_s`` while the gearbox turns."""
        lasts = [buf.last_edge_ns for buf in self.sprockets]
        last_ns = np.array([[x or 0 for x in lasts]], dtype=np.int64)
        known = np.array([[x is not None for x in lasts]])
        return sprocket_missing(ticks, odometer_mps, last_ns, known, self.cfg)

    def _gnss_at(self, ticks: IntArray) -> GnssAtTicks:
        """The last fix in each tick ``(t − tick, t]`` (NaN where none): position, horizontal
        velocity, its std, its age at the tick (s) and the up velocity; fixes consumed."""
        pos = np.full((ticks.size, 2), np.nan)
        vel = np.full((ticks.size, 2), np.nan)
        vstd = np.full(ticks.size, np.nan)
        age = np.zeros(ticks.size)
        up = np.full(ticks.size, np.nan)
        if self.gnss:
            stamps = np.array([g[0] for g in self.gnss], dtype=np.int64)
            k = np.searchsorted(ticks, stamps, side="left")
            for j, g in zip(k.tolist(), self.gnss, strict=True):
                if j < ticks.size and g[0] > ticks[j] - self.tick_ns:
                    pos[j], vel[j], vstd[j], up[j] = g[1:3], g[3:5], g[5], g[6]
                    age[j] = (int(ticks[j]) - g[0]) * 1e-9
            self.gnss = [g for g, j in zip(self.gnss, k.tolist(), strict=True) if j >= ticks.size]
        return pos, vel, vstd, age, up


KEEP_NS = 3_000_000_000
"""Edges older than this before a vehicle's last tick are dropped (no later window reaches)."""


@dataclass(frozen=True, slots=True)
class Reads:
    """What the buffers give for ``m`` ticks, before the inputs are derived from it: IMU
    means and their sample counts ``(m,)``; ``odo``/``prev`` the odometer's speed and window
    centre at the tick and the tick before ``(m,)``; ``spr``/``before`` the sprockets'
    ``(m, 2)``; gear ratios at both; sprockets starting ``(m, 2)``; the odometer's edges in
    the tick and the silence before them ``(m,)`` each; a sprocket missing ``(m,)``; the
    tick's fix (:meth:`VehicleInputs._gnss_at`)."""

    ticks_ns: IntArray
    accel: FloatArray
    gyro: FloatArray
    pitch_rate: FloatArray
    roll_rate: FloatArray
    lateral_accel: FloatArray
    imu_samples: IntArray
    imu_age: FloatArray
    yaw_accel: FloatArray
    odo: tuple[FloatArray, FloatArray]
    prev: tuple[FloatArray, FloatArray]
    spr: tuple[FloatArray, FloatArray]
    before: tuple[FloatArray, FloatArray]
    gear: FloatArray
    gear_before: FloatArray
    starting: BoolArray
    odometer_edges: tuple[IntArray, FloatArray]
    missing: BoolArray
    gnss: GnssAtTicks


def mean_by_tick(tick_of: IntArray, values: FloatArray, count: IntArray) -> FloatArray:
    """Mean ``(m,)`` of the ``values`` of each tick (``tick_of`` each value's tick, in
    order; ``count (m,)`` the values per tick); NaN for a tick without one."""
    sums = np.bincount(tick_of, values, minlength=count.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(np.where(count > 0, sums / count, np.nan))


def derive(r: Reads, cfg: TrackedEstimatorConfig) -> tuple[FloatArray, BoolArray, BoolArray]:
    """``(odometer acceleration (m,), sprockets settling (m, 2), unsteady (m,))``: a sprocket
    settles while its own acceleration differs from the gearbox's (scaled by its ratio) by
    more than ``lever_accel_mps2``, or while it starts; a tick is unsteady while a sprocket
    settles or the odometer accelerates (the hull's own acceleration, gravity taken out with
    the filter's pitch, is counted by the filter: ``step.accel_steady``)."""
    (odo, odo_c), (prev, prev_c) = r.odo, r.prev
    (spr, spr_c), (before, before_c) = r.spr, r.before
    with np.errstate(divide="ignore", invalid="ignore"):
        odo_accel = np.where(odo_c > prev_c, (odo - prev) / ((odo_c - prev_c) * 1e-9), 0.0)
        own = (spr - before) / ((spr_c - before_c) * 1e-9)
        geared = odo_accel[:, None] * np.where(odo[:, None] > 0.3, spr / odo[:, None], 0.0)
    settling = ~(np.abs(np.nan_to_num(own - geared)) <= cfg.lever_accel_mps2)
    settling |= r.starting
    unsteady = settling.any(axis=1) | ~(np.abs(odo_accel) <= cfg.learn_accel_max_mps2)
    return odo_accel, settling, unsteady


def tick_inputs(
    r: Reads, odo_accel: FloatArray, settling: BoolArray, steady_s: FloatArray, tick_ns: int
) -> TickInputs:
    """The filter's inputs from the reads and what :func:`derive` gave."""
    tick_f = r.ticks_ns.astype(np.float64)
    (odo, odo_c), (prev, _) = r.odo, r.prev
    pos, vel, vstd, age, up = r.gnss
    return TickInputs(
        ticks_ns=r.ticks_ns,
        accel_mps2=r.accel,
        gyro_radps=r.gyro,
        pitch_rate_radps=r.pitch_rate,
        roll_rate_radps=r.roll_rate,
        lateral_accel_mps2=r.lateral_accel,
        imu_samples=r.imu_samples,
        imu_age_s=r.imu_age,
        yaw_accel_radps2=r.yaw_accel,
        odometer_mps=odo,
        odometer_lag_s=(tick_f - odo_c) * 1e-9,
        sprocket_pair_mps=at_tick(*r.spr, tick_f, odo, odo_accel),
        sprocket_missing=r.missing,
        sprocket_settling_pair=settling,
        sprocket_starting_pair=r.starting,
        gear_ratio=r.gear,
        sprocket_before_pair_mps=at_tick(*r.before, tick_f - tick_ns, prev, odo_accel),
        gear_ratio_before=r.gear_before,
        gearbox_accel_mps2=odo_accel,
        steady_s=steady_s,
        odometer_edges=r.odometer_edges[0],
        odometer_gap_s=r.odometer_edges[1],
        gnss_pos_pair_m=pos,
        gnss_vel_pair_mps=vel,
        gnss_vel_std_mps=vstd,
        gnss_age_s=age,
        gnss_vel_up_mps=up,
    )


def steady_run(start_s: float, unsteady: BoolArray, tick_ns: int) -> FloatArray:
    """Time (s) since the last unsteady tick, from ``start_s`` before the first."""
    out = np.empty(unsteady.size)
    tick_s = tick_ns * 1e-9
    steady = start_s
    for i, bad in enumerate(unsteady.tolist()):
        steady = 0.0 if bad else steady + tick_s
        out[i] = steady
    return out


def at_tick(
    speed: FloatArray, centre: FloatArray, tick: FloatArray, odo: FloatArray, odo_accel: FloatArray
) -> FloatArray:
    """Sprocket speeds ``(m, 2)`` at the tick: ``v + a_g·(v/v_g)·(tick − centre)``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(odo[:, None] > 0.3, speed / odo[:, None], 0.0)
    lag_s = (tick[:, None] - centre) * 1e-9
    return np.maximum(speed + odo_accel[:, None] * ratio * lag_s, 0.0)


def gear_span(
    speed: FloatArray, centre: FloatArray, ticks: IntArray, tick_ns: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The faster sprocket's speed ``(m,)`` and the span ``centre ± (tick − centre)`` (at
    least ± half a tick) of its window, over which the odometer's speed is to be taken."""
    fast = np.argmax(speed, axis=1)
    rows = np.arange(ticks.size)
    c = centre[rows, fast]
    half = np.maximum(ticks.astype(np.float64) - c, 0.5 * tick_ns)
    return speed[rows, fast], c - half, c + half


def starting_at(s: IntArray, base: IntArray, hi: IntArray, ticks: IntArray) -> BoolArray:
    """One sprocket's first edges after a second's silence within the last 0.6 s, per tick:
    ``hi`` (from a search of ``ticks`` in ``s[base:]``, side right) counts the tick's edges
    (as :func:`~estimator.tracked.edges.edge_speed_at`)."""
    if s.size == 0:
        return np.zeros(ticks.size, dtype=bool)
    never = np.iinfo(np.int64).min // 2
    top = s.size - 1

    def stamp(k: IntArray) -> IntArray:  # the k-th edge (1-based), ``never`` for the 0th
        return np.where(k >= 1, s[np.clip(base + k - 1, 0, top)], never)

    recent = ticks - stamp(hi) < 600_000_000
    out = np.zeros(ticks.size, dtype=bool)
    for back in (1, 2):  # the last edge or the one before it ended a silence
        gap = stamp(np.maximum(hi - back + 1, 0)) - stamp(np.maximum(hi - back, 0))
        out |= recent & (hi >= back) & (gap > 1_000_000_000)
    return out


def odometer_edges_at(
    s: IntArray, base: IntArray, lo: IntArray, hi: IntArray
) -> tuple[IntArray, FloatArray]:
    """Edges per tick ``hi − lo`` and the silence before each tick's first edge (s; inf when
    none came before it, 0 where the tick has none), shapes ``(m,)``: ``lo``/``hi`` index
    ``s[base:]``, from searches of ``t − tick`` and ``t`` (side right) as in
    :func:`~estimator.tracked.edges.edge_speed_at`."""
    count = hi - lo
    if s.size == 0:
        return count, np.zeros(count.shape)
    top = s.size - 1
    first = s[np.minimum(base + lo, top)]
    before = s[np.clip(base + lo - 1, 0, top)]
    gap = np.where(lo >= 1, (first - before) * 1e-9, np.inf)
    return count, np.where(count > 0, gap, 0.0)


def sprocket_missing(
    ticks: IntArray,
    odometer_mps: FloatArray,
    last_ns: IntArray,
    known: BoolArray,
    cfg: TrackedEstimatorConfig,
) -> BoolArray:
    """A sprocket with no edge for ``sprocket_missing_s`` while the gearbox turns, ``(m,)``;
    ``last_ns``/``known`` the sprockets' last edge, ``(m, 2)`` or ``(1, 2)``."""
    span = round(cfg.sprocket_missing_s * 1e9)
    late = ~known | ((ticks[:, None] - last_ns) > span)
    return (odometer_mps > 0.5) & late.any(axis=1)
