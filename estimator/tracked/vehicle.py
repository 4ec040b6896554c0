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

__all__ = ["TickInputs", "VehicleInputs"]

_FORWARD, _YAW = 1, 2


@dataclass(frozen=True, slots=True)
class TickInputs:
    """Inputs of ``m`` ticks: shapes ``(m,)``; ``*_pair`` ``(m, 2)`` (left/right or E/N).

    ``sprocket_pair_mps`` are the sprocket speeds carried from their windows' centres to the
    tick with the gearbox's acceleration (each sprocket turns at a fixed ratio of the gearbox
    between lever moves), so both tracks are read at one instant. ``gear_ratio`` is the
    faster sprocket's speed over the odometer's over the same span of
    time (1 in direct drive, 1/1.42 in the low gear; NaN when unknown). ``yaw_accel_radps2``
    is the change of the tick's mean gyro rate from the tick before over one tick (0 on a
    vehicle's first tick). ``*_before`` are the sprocket speeds and gear ratio of the tick
    before, read the same way (their change over the tick shows a lever moving).
    ``steady_s`` is how long the gearbox has run at a steady speed with no sprocket settling
    (the hull's lag behind its tracks, and the slip that acceleration adds, have died out).
    """

    ticks_ns: IntArray
    accel_mps2: FloatArray
    gyro_radps: FloatArray
    yaw_accel_radps2: FloatArray
    odometer_mps: FloatArray
    odometer_lag_s: FloatArray
    sprocket_pair_mps: FloatArray
    sprocket_missing: BoolArray
    sprocket_settling_pair: BoolArray
    gear_ratio: FloatArray
    sprocket_before_pair_mps: FloatArray
    gear_ratio_before: FloatArray
    steady_s: FloatArray
    gnss_pos_pair_m: FloatArray
    gnss_vel_pair_mps: FloatArray
    gnss_vel_std_mps: FloatArray
    gnss_age_s: FloatArray


class VehicleInputs:
    """Buffers of one vehicle and its tick grid."""

    def __init__(self, config: TrackedConfig, cfg: TrackedEstimatorConfig) -> None:
        self.config = config
        self.cfg = cfg
        self.params = VehicleParams.of(config)
        self.tick_ns = cfg.tick_ns
        self.next_ns: int | None = None
        self.imu_ns: IntArray = np.zeros(0, dtype=np.int64)
        self.imu: FloatArray = np.zeros((0, 2))
        self.odometer = EdgeBuffer()
        self.sprockets = (EdgeBuffer(), EdgeBuffer())
        self.gnss: list[tuple[int, float, float, float, float, float]] = []
        self.frame: EnuFrame | None = None
        self.counts = {"imu_skipped": 0, "gnss_skipped": 0, "sprocket_missing_ticks": 0}
        self.last_gyro_radps = math.nan
        self.steady_s = 0.0

    # --- pushing -----------------------------------------------------------------------------
    def push_imu(self, m: ImuBatch) -> None:
        t = np.asarray(m.stamp_ns, dtype=np.int64)
        a = np.asarray(m.accel_mps2, dtype=np.float64).reshape(-1, 3)[:, _FORWARD]
        g = np.asarray(m.gyro_radps, dtype=np.float64).reshape(-1, 3)[:, _YAW]
        keep = np.isfinite(a) & np.isfinite(g)
        if self.imu_ns.size:
            keep &= t > self.imu_ns[-1]
        self.counts["imu_skipped"] += int(t.size - keep.sum())
        self.imu_ns = np.concatenate([self.imu_ns, t[keep]])
        self.imu = np.concatenate([self.imu, np.stack([a[keep], g[keep]], axis=1)])
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
        self.gnss.append((m.stamp_ns, float(e), float(n), values[0], values[1], std))

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
        """Inputs of ``ticks`` (from :meth:`due`); the buffers drop what no later tick needs."""
        accel, gyro = self._imu_means(ticks)
        yaw_accel = self._yaw_accel(gyro)
        cfg = self.cfg
        odo, odo_c = self._odometer_speed(ticks)
        prev, prev_c = self._odometer_speed(ticks - self.tick_ns)
        with np.errstate(divide="ignore", invalid="ignore"):
            odo_accel = np.where(odo_c > prev_c, (odo - prev) / ((odo_c - prev_c) * 1e-9), 0.0)
        spr, spr_c = self._sprocket_speeds(ticks)
        before, before_c = self._sprocket_speeds(ticks - self.tick_ns)
        gear = self._gear_ratio(spr, spr_c, ticks)
        tick_f = ticks.astype(np.float64)
        sprocket = self._at_tick(spr, spr_c, tick_f, odo, odo_accel)
        gear_before = self._gear_ratio(before, before_c, ticks - self.tick_ns)
        sprocket_before = self._at_tick(before, before_c, tick_f - self.tick_ns, prev, odo_accel)
        with np.errstate(divide="ignore", invalid="ignore"):
            own = (spr - before) / ((spr_c - before_c) * 1e-9)
            geared = odo_accel[:, None] * np.where(odo[:, None] > 0.3, spr / odo[:, None], 0.0)
        settling = ~(np.abs(np.nan_to_num(own - geared)) <= cfg.lever_accel_mps2)
        settling |= self._starting(ticks)
        unsteady = settling.any(axis=1) | ~(np.abs(accel) <= cfg.learn_accel_max_mps2)
        unsteady |= ~(np.abs(odo_accel) <= cfg.learn_accel_max_mps2)
        steady_s = self._steady_for(unsteady)
        missing = self._sprocket_missing(ticks, odo)
        self.counts["sprocket_missing_ticks"] += int(missing.sum())
        pos, vel, vstd, age = self._gnss_at(ticks)
        self.next_ns = int(ticks[-1]) + self.tick_ns
        keep_from = int(ticks[-1]) - 3_000_000_000
        for buf in (self.odometer, *self.sprockets):
            buf.prune(keep_from)
        return TickInputs(
            ticks_ns=ticks,
            accel_mps2=accel,
            gyro_radps=gyro,
            yaw_accel_radps2=yaw_accel,
            odometer_mps=odo,
            odometer_lag_s=(tick_f - odo_c) * 1e-9,
            sprocket_pair_mps=sprocket,
            sprocket_missing=missing,
            sprocket_settling_pair=settling,
            gear_ratio=gear,
            sprocket_before_pair_mps=sprocket_before,
            gear_ratio_before=gear_before,
            steady_s=steady_s,
            gnss_pos_pair_m=pos,
            gnss_vel_pair_mps=vel,
            gnss_vel_std_mps=vstd,
            gnss_age_s=age,
        )

    def _imu_means(self, ticks: IntArray) -> tuple[FloatArray, FloatArray]:
        """Mean forward specific force and yaw rate over each tick ``(t − tick, t]``."""
        bounds = np.concatenate([ticks[:1] - self.tick_ns, ticks])
        edges = np.searchsorted(self.imu_ns, bounds, side="right")
        count = np.diff(edges)
        tick_of = np.repeat(np.arange(ticks.size), count)
        part = self.imu[edges[0] : edges[-1]]
        out = []
        for col in (0, 1):
            sums = np.bincount(tick_of, part[:, col], minlength=ticks.size)
            with np.errstate(invalid="ignore", divide="ignore"):
                out.append(np.where(count > 0, sums / count, np.nan))
        cut = int(edges[-1])
        self.imu_ns, self.imu = self.imu_ns[cut:], self.imu[cut:]
        return out[0], out[1]

    def _steady_for(self, unsteady: BoolArray) -> FloatArray:
        """Time (s) since the last unsteady tick, carried from one call to the next."""
        out = np.empty(unsteady.size)
        tick_s = self.tick_ns * 1e-9
        for i, bad in enumerate(unsteady.tolist()):
            self.steady_s = 0.0 if bad else self.steady_s + tick_s
            out[i] = self.steady_s
        return out

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
        last 0.6 s: the track starts (a released brake or lever), faster than a window reads."""
        out = np.zeros((ticks.size, 2), dtype=bool)
        for side, buf in enumerate(self.sprockets):
            s = buf.stamps
            if s.size == 0:
                continue
            hi = np.searchsorted(s, ticks, side="right")
            stamps = np.concatenate([[np.iinfo(np.int64).min // 2], s])
            recent = ticks - stamps[hi] < 600_000_000
            for back in (1, 2):  # the last edge or the one before it ended a silence
                gap = stamps[np.maximum(hi - back + 1, 0)] - stamps[np.maximum(hi - back, 0)]
                out[:, side] |= recent & (hi >= back) & (gap > 1_000_000_000)
        return out

    def _odometer_speed(self, ticks: IntArray) -> tuple[FloatArray, FloatArray]:
        return edge_speed(
            self.odometer.stamps,
            ticks,
            float(self.params.odometer_pitch_m[0]),
            round(self.cfg.odometer_window_s * 1e9),
            1 << 30,
            500_000_000,
        )

    @staticmethod
    def _at_tick(
        speed: FloatArray,
        centre: FloatArray,
        tick: FloatArray,
        odo: FloatArray,
        odo_accel: FloatArray,
    ) -> FloatArray:
        """Sprocket speeds ``(m, 2)`` at the tick: ``v + a_g·(v/v_g)·(tick − centre)``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(odo[:, None] > 0.3, speed / odo[:, None], 0.0)
        lag_s = (tick[:, None] - centre) * 1e-9
        return np.maximum(speed + odo_accel[:, None] * ratio * lag_s, 0.0)

    def _gear_ratio(self, speed: FloatArray, centre: FloatArray, ticks: IntArray) -> FloatArray:
        """Faster sprocket over the odometer, both over the faster sprocket's window (``(m,)``):
        the odometer's speed taken over ``centre ± (tick − centre)``."""
        fast = np.argmax(speed, axis=1)
        rows = np.arange(ticks.size)
        c = centre[rows, fast]
        half = np.maximum(ticks.astype(np.float64) - c, 0.5 * self.tick_ns)
        odo = span_speed(
            self.odometer.stamps, c - half, c + half, float(self.params.odometer_pitch_m[0])
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            return speed[rows, fast] / odo

    def _sprocket_missing(self, ticks: IntArray, odometer_mps: FloatArray) -> BoolArray:
        """A sprocket with no edge for ``sprocket_missing_s`` while the gearbox turns."""
        span = round(self.cfg.sprocket_missing_s * 1e9)
        moving = odometer_mps > 0.5
        out = np.zeros(ticks.size, dtype=bool)
        for buf in self.sprockets:
            last = buf.last_edge_ns
            out |= moving & (last is None or (ticks - (last or 0)) > span)
        return out

    def _gnss_at(self, ticks: IntArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The last fix in each tick ``(t − tick, t]`` (NaN where none) and its age at the tick
        (s); fixes consumed."""
        pos = np.full((ticks.size, 2), np.nan)
        vel = np.full((ticks.size, 2), np.nan)
        vstd = np.full(ticks.size, np.nan)
        age = np.zeros(ticks.size)
        if self.gnss:
            stamps = np.array([g[0] for g in self.gnss], dtype=np.int64)
            k = np.searchsorted(ticks, stamps, side="left")
            for j, g in zip(k.tolist(), self.gnss, strict=True):
                if j < ticks.size and g[0] > ticks[j] - self.tick_ns:
                    pos[j], vel[j], vstd[j] = g[1:3], g[3:5], g[5]
                    age[j] = (int(ticks[j]) - g[0]) * 1e-9
            self.gnss = [g for g, j in zip(self.gnss, k.tolist(), strict=True) if j >= ticks.size]
        return pos, vel, vstd, age
