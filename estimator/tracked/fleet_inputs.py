"""The input stage of many vehicles at once: :func:`take_fleet` gives what
:meth:`VehicleInputs.take <estimator.tracked.vehicle.VehicleInputs.take>` gives each vehicle,
every vehicle's ticks end to end, in a fixed number of array calls.

Each stream's buffers are laid end to end (:class:`~estimator.tracked.segments.Segments`)
and searched at once; the edge windows, IMU means and fix matching then work on the whole
fleet's ticks with each tick's own offset. Only the bookkeeping (cutting each buffer, the
steady-time recursion) stays per vehicle.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray, nan_to_num
from estimator.tracked.edges import edge_speed_at, span_speed_at
from estimator.tracked.segments import Segments
from estimator.tracked.vehicle import (
    KEEP_NS,
    GnssAtTicks,
    Reads,
    TickInputs,
    VehicleInputs,
    derive,
    gear_span,
    mean_by_tick,
    odometer_edges_at,
    sprocket_missing,
    starting_at,
    tick_inputs,
)

__all__ = ["take_fleet"]


class _Fleet:
    """The vehicles of one call and their ticks: ``ticks (M,)`` end to end, ``seg (M,)``
    (each tick's vehicle), ``starts (n + 1,)`` (vehicle ``j``'s ticks
    ``ticks[starts[j]:starts[j + 1]]``)."""

    def __init__(self, vehicles: Sequence[VehicleInputs], ticks: Sequence[IntArray]) -> None:
        self.vehicles = vehicles
        self.cfg = vehicles[0].cfg
        self.tick_ns = vehicles[0].tick_ns
        self.grid = Segments(ticks)
        self.ticks = self.grid.values
        self.starts = self.grid.starts
        n = len(vehicles)
        self.seg = np.repeat(np.arange(n, dtype=np.int64), np.diff(self.starts))
        self.odometer = Segments([v.odometer.stamps for v in vehicles])
        self.sprockets = [Segments([v.sprockets[s].stamps for v in vehicles]) for s in (0, 1)]
        params = [v.params for v in vehicles]
        self.odo_pitch = np.array([float(p.odometer_pitch_m[0]) for p in params])[self.seg]
        self.spr_pitch = np.array([float(p.sprocket_pitch_m[0]) for p in params])[self.seg]

    def edges(
        self,
        segs: Segments,
        tick_sets: Sequence[IntArray],
        pitch: FloatArray,
        window_s: float,
        max_edges: int,
        hold_ns: int,
    ) -> tuple[list[tuple[FloatArray, FloatArray]], IntArray]:
        """Each tick's edge speed and window centre (:func:`edge_speed_at`) in ``segs``, for
        every array of ``tick_sets`` (one search of the buffer for all); and the first set's
        ``hi`` (its ticks' edge counts, for :func:`starting_at`)."""
        window_ns = round(window_s * 1e9)
        keys = [k for t in tick_sets for k in (t, t - window_ns)]
        found = segs.search_all(self.seg, keys, "right")
        base = segs.starts[self.seg]
        out = [
            edge_speed_at(segs.values, base, hi, lo, t, pitch, max_edges, hold_ns)
            for t, hi, lo in zip(tick_sets, found[0::2], found[1::2], strict=True)
        ]
        return out, found[0]

    def odometer_speeds(self, tick_sets: Sequence[IntArray]) -> list[tuple[FloatArray, FloatArray]]:
        cfg = self.cfg
        window_s, hold_ns = cfg.odometer_window_s, 500_000_000
        return self.edges(self.odometer, tick_sets, self.odo_pitch, window_s, 1 << 30, hold_ns)[0]

    def odometer_edges(self) -> tuple[IntArray, FloatArray]:
        """The odometer's edges in each tick and the silence before the first of them."""
        segs = self.odometer
        hi, lo = segs.search_all(self.seg, [self.ticks, self.ticks - self.tick_ns], "right")
        return odometer_edges_at(segs.values, segs.starts[self.seg], lo, hi)

    def sprocket_speeds(
        self, tick_sets: Sequence[IntArray]
    ) -> tuple[list[tuple[FloatArray, FloatArray]], BoolArray]:
        """Both sprockets' ``(speed (m, 2), centre (m, 2))`` for every array of ``tick_sets``,
        and whether each starts at the first set's ticks ``(m, 2)``."""
        cfg = self.cfg
        hold_ns = round(cfg.sprocket_hold_s * 1e9)
        window_s, most = cfg.sprocket_window_s, cfg.sprocket_max_edges
        sides = [
            self.edges(segs, tick_sets, self.spr_pitch, window_s, most, hold_ns)
            for segs in self.sprockets
        ]
        starting = np.zeros((self.ticks.size, 2), dtype=bool)
        for side, (segs, (_, hi)) in enumerate(zip(self.sprockets, sides, strict=True)):
            starting[:, side] = starting_at(segs.values, segs.starts[self.seg], hi, tick_sets[0])
        pairs = [
            (np.stack([a[0], b[0]], axis=1), np.stack([a[1], b[1]], axis=1))
            for a, b in zip(sides[0][0], sides[1][0], strict=True)
        ]
        return pairs, starting

    def gear_ratios(
        self, sprockets: Sequence[tuple[FloatArray, FloatArray]], tick_sets: Sequence[IntArray]
    ) -> list[FloatArray]:
        """The gear ratio (fast sprocket over odometer) at every array of ``tick_sets``."""
        spans = [
            gear_span(speed, c, t, self.tick_ns)
            for (speed, c), t in zip(sprockets, tick_sets, strict=True)
        ]
        segs = self.odometer
        los = segs.search_float_all(self.seg, [sp[1] for sp in spans], "left")
        his = segs.search_float_all(self.seg, [sp[2] for sp in spans], "right")
        out = []
        for (fast, _, _), lo, hi in zip(spans, los, his, strict=True):
            odo = span_speed_at(segs.values, segs.starts[self.seg], lo, hi, self.odo_pitch)
            with np.errstate(divide="ignore", invalid="ignore"):
                out.append(fast / odo)
        return out

    def missing(self, odo: FloatArray) -> BoolArray:
        lasts = [[b.last_edge_ns for b in v.sprockets] for v in self.vehicles]
        last_ns = np.array([[x or 0 for x in pair] for pair in lasts], dtype=np.int64)
        known = np.array([[x is not None for x in pair] for pair in lasts], dtype=bool)
        return sprocket_missing(self.ticks, odo, last_ns[self.seg], known[self.seg], self.cfg)

    def imu_means(self) -> tuple[list[FloatArray], IntArray, FloatArray]:
        """Mean of each IMU column over each tick ``(t − tick, t]`` (the
        per-vehicle sums, element by element in the same order), the samples each mean
        is of and how long before the tick their stamps lie on average; the IMU consumed."""
        imu = Segments([v.imu_ns for v in self.vehicles])
        values = np.concatenate([v.imu for v in self.vehicles])
        lo, hi = imu.search_all(self.seg, [self.ticks - self.tick_ns, self.ticks], "right")
        count = hi - lo
        m = self.ticks.size
        tick_of = np.repeat(np.arange(m), count)
        first = np.cumsum(count) - count
        elem = np.arange(tick_of.size) - first[tick_of] + (imu.starts[self.seg] + lo)[tick_of]
        out = []
        for col in range(values.shape[1]):
            sums = np.bincount(tick_of, values[elem, col], minlength=m)
            with np.errstate(invalid="ignore", divide="ignore"):
                out.append(np.where(count > 0, sums / count, np.nan))
        age = mean_by_tick(
            tick_of, (self.ticks[tick_of] - imu.values[elem]).astype(np.float64) * 1e-9, count
        )
        for v, cut in zip(self.vehicles, hi[self.starts[1:] - 1].tolist(), strict=True):
            v.imu_ns, v.imu = v.imu_ns[cut:], v.imu[cut:]
        return out, count, age

    def yaw_accel(self, gyro: FloatArray) -> FloatArray:
        before = np.empty_like(gyro)
        before[1:] = gyro[:-1]
        before[self.starts[:-1]] = [v.last_gyro_radps for v in self.vehicles]
        for v, last in zip(self.vehicles, gyro[self.starts[1:] - 1].tolist(), strict=True):
            v.last_gyro_radps = last
        return nan_to_num((gyro - before) / (self.tick_ns * 1e-9))

    def gnss_at(self) -> GnssAtTicks:
        """The last fix in each tick ``(t − tick, t]`` and its age; fixes consumed."""
        m = self.ticks.size
        pos, vel = np.full((m, 2), np.nan), np.full((m, 2), np.nan)
        vstd, age, up = np.full(m, np.nan), np.zeros(m), np.full(m, np.nan)
        fixes = [g for v in self.vehicles for g in v.gnss]
        if not fixes:
            return pos, vel, vstd, age, up
        n_fixes = np.array([len(v.gnss) for v in self.vehicles])
        fseg = np.repeat(np.arange(n_fixes.size), n_fixes)
        stamps = np.array([g[0] for g in fixes], dtype=np.int64)
        values = np.array([g[1:] for g in fixes], dtype=np.float64)
        k = self.grid.search(fseg, stamps, "left")
        inside = k < np.diff(self.starts)[fseg]
        at = self.starts[fseg] + np.where(inside, k, 0)
        valid = inside & (stamps > self.ticks[np.minimum(at, m - 1)] - self.tick_ns)
        # fixes of one tick: the last one (the valid ones are the latest)
        later = np.zeros(stamps.size, dtype=bool)
        later[:-1] = (fseg[1:] == fseg[:-1]) & (k[1:] == k[:-1])
        take = valid & ~later
        j = at[take]
        pos[j], vel[j], vstd[j] = values[take, 0:2], values[take, 2:4], values[take, 4]
        up[j] = values[take, 5]
        age[j] = (self.ticks[j] - stamps[take]) * 1e-9
        used = np.bincount(fseg[inside], minlength=n_fixes.size).tolist()
        for v, u in zip(self.vehicles, used, strict=True):
            if u:
                v.gnss = v.gnss[u:]
        return pos, vel, vstd, age, up

    def reads(self) -> Reads:
        means, samples, imu_age = self.imu_means()
        accel, gyro, pitch_rate, roll_rate, lateral = means
        tick_sets = (self.ticks, self.ticks - self.tick_ns)
        odo, prev = self.odometer_speeds(tick_sets)
        sprockets, starting = self.sprocket_speeds(tick_sets)
        gear, gear_before = self.gear_ratios(sprockets, tick_sets)
        return Reads(
            ticks_ns=self.ticks,
            accel=accel,
            gyro=gyro,
            pitch_rate=pitch_rate,
            roll_rate=roll_rate,
            lateral_accel=lateral,
            imu_samples=samples,
            imu_age=imu_age,
            yaw_accel=self.yaw_accel(gyro),
            odo=odo,
            prev=prev,
            spr=sprockets[0],
            before=sprockets[1],
            gear=gear,
            gear_before=gear_before,
            starting=starting,
            odometer_edges=self.odometer_edges(),
            missing=self.missing(odo[0]),
            gnss=self.gnss_at(),
        )

    def steady(self, unsteady: BoolArray) -> FloatArray:
        """:func:`~estimator.tracked.vehicle.steady_run` of every vehicle, the r-th tick of
        all vehicles at once (the same additions in the same order)."""
        out = np.empty(unsteady.size)
        sizes = np.diff(self.starts)
        tick_s = self.tick_ns * 1e-9
        run = np.array([v.steady_s for v in self.vehicles], dtype=np.float64)
        for r in range(int(sizes.max(initial=0))):
            part = np.flatnonzero(sizes > r)
            at = self.starts[part] + r
            run[part] = np.where(unsteady[at], 0.0, run[part] + tick_s)
            out[at] = run[part]
        for v, last in zip(self.vehicles, run.tolist(), strict=True):
            v.steady_s = last
        return out

    def close(self, missing: BoolArray) -> None:
        """Counters, the next tick and the edges no later window reaches, per vehicle."""
        n = len(self.vehicles)
        last = self.ticks[self.starts[1:] - 1]
        counts = np.bincount(self.seg, missing, minlength=n).astype(np.int64).tolist()
        for v, c, t in zip(self.vehicles, counts, last.tolist(), strict=True):
            v.counts["sprocket_missing_ticks"] += c
            v.next_ns = t + self.tick_ns
        own = np.arange(n, dtype=np.int64)
        for segs, bufs in (
            (self.odometer, [v.odometer for v in self.vehicles]),
            *((self.sprockets[s], [v.sprockets[s] for v in self.vehicles]) for s in (0, 1)),
        ):
            older = segs.search(own, last - KEEP_NS, "left").tolist()
            for buf, cut in zip(bufs, older, strict=True):
                buf.prune_at(cut)


def take_fleet(
    vehicles: Sequence[VehicleInputs], ticks: Sequence[IntArray]
) -> tuple[TickInputs, IntArray]:
    """Inputs of every vehicle's ``ticks`` (each non-empty, from its :meth:`due`), end to end:
    ``(TickInputs (M,), starts (n + 1,))``, vehicle ``j``'s rows
    ``starts[j]:starts[j + 1]``, each equal to ``vehicles[j].take(ticks[j])``. The vehicles
    share one estimator configuration."""
    fleet = _Fleet(vehicles, ticks)
    reads = fleet.reads()
    odo_accel, settling, unsteady = derive(reads, fleet.cfg)
    steady_s = fleet.steady(unsteady)
    fleet.close(reads.missing)
    return tick_inputs(reads, odo_accel, settling, steady_s, fleet.tick_ns), fleet.starts
