"""Every steered four-wheel vehicle's sensor buffers in shared per-slot rows, read for all the
vehicles of an ``advance`` call in one vectorised pass.

:class:`FleetSensors` holds each vehicle's (slot's) IMU, CAN wheel-speed, steering and GNSS
samples in rows of 2-D arrays (:class:`_Rows`: ``(S, C)`` stamps, ``(S, C, w)`` values; a push
appends to its slot's row) and its tick clock, and turns them into what the batched front end
(:mod:`.fleetfront`) needs at each due tick ``t`` of every vehicle of a call:

* the due ticks: ``first IMU sample + k·tick`` (or the grid ``align`` set), up to the call's
  horizon and the last IMU sample held;
* the mean specific force and rate over the IMU samples in ``(t − tick, t]`` (a tick without
  one is not ready): differences of a running sum along each row;
* the latest wheel speeds and steering-wheel angle at or before ``t`` (held from earlier
  ticks; a tick before the first wheel speeds is not ready; an angle older than
  ``steer_timeout_s`` is read as none, NaN);
* the GNSS epoch: the latest one popped from the slot's queue (epochs in arrival order, popped
  while their stamp is at or before ``t``); a new epoch is *fresh* until the first ready tick,
  which uses its body-frame velocity if it is at most ``gnss_timeout_s`` old and has a heading.

The rules are :class:`~.frontend.FrontEnd`'s (its ``_imu_window``, ``_latest``,
``_gnss_velocity`` and ``_steer_angles``); a stream pushed out of time order is sorted
(stably) before it is read.
Samples at or before a vehicle's last tick read are dropped. A row grows (the capacity of
every slot's row doubles) as long as its vehicle's ticks are not read, and the capacity halves
again once every row fits a quarter of it; a vehicle without an IMU sample and tick grid keeps
the newest :data:`MAX_SAMPLES` of each other stream (the oldest counted in ``dropped``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

__all__ = ["MAX_SAMPLES", "FleetSensors", "SensedTicks"]

MAX_SAMPLES = 1024
"""Samples of a stream a vehicle without an IMU holds (10 s of 100 Hz wheel speeds): they
would be read only if its IMU came that far behind."""
_FIRST_CAPACITY = 32
_NEVER_NS = np.iinfo(np.int64).max
"""Stamp of an empty place in a row's window (after every tick)."""


@dataclass(frozen=True, slots=True)
class SensedTicks:
    """The ready ticks of one vehicle (or several, concatenated): ``K`` rows each.

    ``t_ns`` ``(K,)``; ``accel_mps2``, ``gyro_radps`` ``(K, 3)`` IMU means in the sensor's
    frame; ``omega_radps`` ``(K, 4)``; ``steer_rad`` ``(K,)`` (NaN before the first angle and
    while the last is older than ``steer_timeout_s``);
    ``gnss_vel_mps`` ``(K, 2)`` body-frame ``(v_x, v_y)`` of a fresh epoch (NaN without one);
    ``gnss_attitude`` ``(K, 3)`` that epoch's heading, pitch and roll [rad] and
    ``gnss_stamp_ns`` ``(K,)`` its time; ``gnss_recent`` ``(K,)`` whether the latest epoch
    (fresh or not) is at most ``gnss_timeout_s`` old; ``imu_lag_s`` ``(K,)`` how far before
    the tick the IMU means' samples lie on average (``t`` less their mean stamp: 5 ms for
    100 Hz samples in a 20 ms tick).
    """

    t_ns: IntArray
    accel_mps2: FloatArray
    gyro_radps: FloatArray
    omega_radps: FloatArray
    steer_rad: FloatArray
    gnss_vel_mps: FloatArray
    gnss_attitude: FloatArray
    gnss_stamp_ns: IntArray
    gnss_recent: BoolArray
    imu_lag_s: FloatArray

    def take(self, rows: IntArray) -> SensedTicks:
        """The rows ``rows``."""
        return SensedTicks(*(getattr(self, f)[rows] for f in self.__dataclass_fields__))


class _Rows:
    """One stream of every slot: slot ``s`` holds ``count[s]`` samples at columns
    ``head[s] …`` of ``stamps`` ``(S, C)`` and ``values`` ``(S, C, width)``, in push order
    (sorted by :meth:`window` where ``sort``). ``C`` doubles when a row is full and halves
    back (:meth:`shrink`) once every row fits a quarter of it."""

    def __init__(self, width: int, sort: bool) -> None:
        self.sort = sort
        self.stamps: IntArray = np.zeros((0, _FIRST_CAPACITY), dtype=np.int64)
        self.values: FloatArray = np.zeros((0, _FIRST_CAPACITY, width))
        self.head: IntArray = np.zeros(0, dtype=np.int64)
        self.count: IntArray = np.zeros(0, dtype=np.int64)
        self.dropped = 0

    def add_slots(self, rows: int) -> None:
        """Room for ``rows`` slots (the new ones empty)."""
        old = self.head.size
        self.stamps = np.concatenate([self.stamps, np.zeros((rows - old, self.capacity), np.int64)])
        self.values = np.concatenate([self.values, np.zeros((rows - old, *self.values.shape[1:]))])
        self.head = np.concatenate([self.head, np.zeros(rows - old, np.int64)])
        self.count = np.concatenate([self.count, np.zeros(rows - old, np.int64)])

    @property
    def capacity(self) -> int:
        return self.stamps.shape[1]

    def clear(self, slot: int) -> None:
        self.head[slot] = self.count[slot] = 0

    def reserve(self, slot: int, k: int) -> int:
        """Room for ``k`` more samples at the end of ``slot``'s row; the column they go to."""
        head, n = int(self.head[slot]), int(self.count[slot])
        if head + n + k <= self.capacity:
            self.count[slot] = n + k
            return head + n
        if n + k > self.capacity:
            self._resize(max(2 * self.capacity, n + k))
            head = int(self.head[slot])
        self.stamps[slot, :n] = self.stamps[slot, head : head + n]
        self.values[slot, :n] = self.values[slot, head : head + n]
        self.head[slot], self.count[slot] = 0, n + k
        return n

    def forget_oldest(self, slot: int, k: int) -> None:
        """Drop up to ``k`` of ``slot``'s oldest samples, counted in ``dropped``."""
        k = min(k, int(self.count[slot]))
        self.head[slot] += k
        self.count[slot] -= k
        self.dropped += k

    def shrink(self) -> None:
        """Halve the capacity if every row fits a quarter of it."""
        longest = int(self.count.max(initial=0))
        if self.capacity > _FIRST_CAPACITY and 4 * longest <= self.capacity:
            self._resize(max(self.capacity // 2, _FIRST_CAPACITY))

    def _resize(self, capacity: int) -> None:
        """``capacity`` columns, every row moved to start at column 0."""
        cols = np.minimum(self.head[:, None] + np.arange(capacity), self.capacity - 1)
        rows = np.arange(self.head.size)[:, None]
        self.stamps = self.stamps[rows, cols]
        self.values = self.values[rows, cols]
        self.head[:] = 0

    def window(self, s: IntArray) -> tuple[IntArray, FloatArray]:
        """Slots ``s``'s samples ``(V, W)`` stamps (``_NEVER_NS`` past each row's count) and
        ``(V, W, width)`` values, ``W`` the longest row; sorted by stamp (stably) where
        ``sort``, the sorted order written back."""
        n = self.count[s]
        w = max(int(n.max(initial=0)), 1)
        cols = np.minimum(self.head[s, None] + np.arange(w), self.capacity - 1)
        stamps = self.stamps[s[:, None], cols]
        empty = np.arange(w) >= n[:, None]
        stamps[empty] = _NEVER_NS
        values = self.values[s[:, None], cols]
        if self.sort and w > 1:
            late = np.flatnonzero((stamps[:, 1:] < stamps[:, :-1]).any(axis=1))
            if late.size:
                self._sort(s[late], cols[late], ~empty[late], stamps, values, late)
        return stamps, values

    def _sort(
        self,
        slots: IntArray,
        cols: IntArray,
        held: BoolArray,
        stamps: IntArray,
        values: FloatArray,
        late: IntArray,
    ) -> None:
        """Sort the window's rows ``late`` (slots ``slots``, columns ``cols``, ``held`` the
        places with a sample) in place and in the rows."""
        order = np.argsort(stamps[late], axis=1, kind="stable")
        stamps[late] = np.take_along_axis(stamps[late], order, axis=1)
        values[late] = np.take_along_axis(values[late], order[:, :, None], axis=1)
        r, c = np.nonzero(held)
        self.stamps[slots[r], cols[r, c]] = stamps[late][r, c]
        self.values[slots[r], cols[r, c]] = values[late][r, c]

    def drop(self, s: IntArray, k: IntArray) -> None:
        """Forget the first ``k`` samples of slots ``s``."""
        self.head[s] += k
        self.count[s] -= k


@dataclass(frozen=True, slots=True)
class _Due:
    """A call's due ticks: ``t_ns`` ``(R,)``, each vehicle's a run; ``vehicle`` ``(R,)`` the
    index into ``slots`` ``(V,)`` (the vehicles with a tick due), ``last`` ``(V,)`` the
    index of each one's last tick."""

    t_ns: IntArray
    vehicle: IntArray
    slots: IntArray
    last: IntArray


def _runs(n: IntArray) -> tuple[IntArray, IntArray]:
    """For runs of lengths ``n`` ``(V,)`` (each ≥ 1): each element's run ``(R,)`` and its
    place in the run ``(R,)``."""
    run = np.repeat(np.arange(n.size), n)
    return run, np.arange(run.size) - np.repeat(np.cumsum(n) - n, n)


class FleetSensors:
    """Every slot's sensor rows and tick clock (see the module docstring)."""

    def __init__(self, tick_ns: int, gnss_timeout_s: float, steer_timeout_s: float) -> None:
        self.tick_ns = tick_ns
        self.gnss_timeout_ns = gnss_timeout_s * 1e9
        self.steer_timeout_ns = round(steer_timeout_s * 1e9)
        self.imu = _Rows(6, sort=True)  # [accel xyz, gyro xyz]
        self.wheels = _Rows(4, sort=True)
        self.steering = _Rows(1, sort=True)
        self.gnss = _Rows(5, sort=False)  # [v_x, v_y body, heading, pitch, roll], a queue
        self.omega = np.zeros((0, 4))
        self.steer = np.zeros(0)
        self.steer_ns = np.zeros(0, dtype=np.int64)  # the held angle's stamp
        self.omega_ns = np.zeros(0, dtype=np.int64)
        self.epoch = np.zeros((0, 5))  # the latest GNSS epoch popped
        self.epoch_ns = np.zeros(0, dtype=np.int64)
        self.has_epoch = np.zeros(0, dtype=bool)
        self.fresh = np.zeros(0, dtype=bool)
        self.next_ns = np.zeros(0, dtype=np.int64)
        self.has_next = np.zeros(0, dtype=bool)

    @property
    def dropped(self) -> int:
        """Samples dropped by vehicles without an IMU (:data:`MAX_SAMPLES`), every stream."""
        return sum(r.dropped for r in (self.imu, self.wheels, self.steering, self.gnss))

    def add(self, slot: int) -> None:
        """Empty ``slot``'s rows and clock (growing the arrays to hold it)."""
        if slot >= self.next_ns.size:
            rows = max(slot + 1, 2 * self.next_ns.size, 8)
            for r in (self.imu, self.wheels, self.steering, self.gnss):
                r.add_slots(rows)
            names = ("omega", "omega_ns", "steer", "steer_ns", "epoch", "epoch_ns")
            for name in (*names, "has_epoch", "fresh"):
                self._grow(name, rows)
            self._grow("next_ns", rows)
            self._grow("has_next", rows)
        for r in (self.imu, self.wheels, self.steering, self.gnss):
            r.clear(slot)
        self.omega[slot] = self.steer[slot] = math.nan
        self.has_epoch[slot] = self.fresh[slot] = self.has_next[slot] = False

    def _grow(self, name: str, rows: int) -> None:
        a = getattr(self, name)
        setattr(
            self, name, np.concatenate([a, np.zeros((rows - a.shape[0], *a.shape[1:]), a.dtype)])
        )

    def align(self, slot: int, stamp_ns: int) -> None:
        """Ticks of ``slot`` on ``stamp_ns + k·tick`` (unless its grid is already set)."""
        if not self.has_next[slot]:
            self.next_ns[slot], self.has_next[slot] = stamp_ns, True

    def push_imu(self, slot: int, m: ImuBatch) -> None:
        stamps = np.atleast_1d(m.stamp_ns)
        k = stamps.size
        at = self.imu.reserve(slot, k)
        self.imu.stamps[slot, at : at + k] = stamps
        self.imu.values[slot, at : at + k, :3] = m.accel_mps2
        self.imu.values[slot, at : at + k, 3:] = m.gyro_radps

    def push_wheels(self, slot: int, m: WheelSpeeds4) -> None:
        stamps = np.atleast_1d(m.stamp_ns)
        k = stamps.size
        at = self._reserve(self.wheels, slot, k)
        self.wheels.stamps[slot, at : at + k] = stamps
        self.wheels.values[slot, at : at + k] = m.omega_radps

    def push_steering(self, slot: int, m: SteeringAngles) -> None:
        stamps = np.atleast_1d(m.stamp_ns)
        k = stamps.size
        at = self._reserve(self.steering, slot, k)
        self.steering.stamps[slot, at : at + k] = stamps
        self.steering.values[slot, at : at + k, 0] = m.angle_rad

    def push_gnss(self, slot: int, m: GnssSample) -> None:
        """Queue an epoch with its velocity across and along its heading (NaN without one)."""
        at = self._reserve(self.gnss, slot, 1)
        h = m.heading_rad
        ve, vn, _ = m.vel_enu_mps
        self.gnss.stamps[slot, at] = m.stamp_ns
        self.gnss.values[slot, at] = (
            ve * math.sin(h) + vn * math.cos(h) if math.isfinite(h) else math.nan,
            -ve * math.cos(h) + vn * math.sin(h) if math.isfinite(h) else math.nan,
            h,
            m.pitch_rad,
            m.roll_rad,
        )

    def _reserve(self, rows: _Rows, slot: int, k: int) -> int:
        """:meth:`_Rows.reserve`, the oldest forgotten beyond :data:`MAX_SAMPLES` while the
        slot has no tick grid and no IMU sample (nothing would ever read them)."""
        excess = int(rows.count[slot]) + k - MAX_SAMPLES
        if excess > 0 and not self.has_next[slot] and not self.imu.count[slot]:
            rows.forget_oldest(slot, excess)
        return rows.reserve(slot, k)

    def read(self, slots: IntArray, until_ns: IntArray) -> tuple[SensedTicks, IntArray]:
        """The ready ticks at or before ``until_ns`` ``(V,)`` of the vehicles in ``slots``
        ``(V,)``, each vehicle's a run in ``slots``' order, and how many each has ``(V,)``."""
        imu = self.imu.window(slots)
        due, covered = self._due(slots, until_ns, imu[0])
        counts = np.zeros(slots.size, dtype=np.int64)
        if due is None:
            return _no_ticks(), counts
        v = due.vehicle
        window = (imu[0][covered], imu[1][covered])
        means, n_imu, lag_s = self._imu_means(due, window)
        omega, _ = self._latest(self.wheels, (self.omega, self.omega_ns), due)
        steer, steer_ns = self._latest(self.steering, (self.steer[:, None], self.steer_ns), due)
        steer = np.where(due.t_ns - steer_ns <= self.steer_timeout_ns, steer[:, 0], math.nan)
        ready = (n_imu > 0) & np.isfinite(omega).all(axis=1)
        gnss = self._gnss(due, ready)
        keep = np.flatnonzero(ready)
        counts[np.flatnonzero(covered)] = np.bincount(v[keep], minlength=due.slots.size)
        sensed = SensedTicks(
            due.t_ns[keep],
            means[keep, :3],
            means[keep, 3:],
            omega[keep],
            steer[keep],
            *gnss,
            lag_s[keep],
        )
        for rows in (self.imu, self.wheels, self.steering, self.gnss):
            rows.shrink()
        return sensed, counts

    def _due(
        self, slots: IntArray, until_ns: IntArray, imu_ns: IntArray
    ) -> tuple[_Due | None, BoolArray]:
        """The ticks of ``slots`` up to ``until_ns`` the IMU (window stamps ``imu_ns``)
        covers, not yet computed, and which vehicles have one; the grids advanced past them."""
        n_imu = self.imu.count[slots]
        held = n_imu > 0
        start = held & ~self.has_next[slots]
        self.next_ns[slots[start]] = imu_ns[start, 0] + self.tick_ns
        self.has_next[slots[start]] = True
        first = self.next_ns[slots]
        end = np.minimum(until_ns, imu_ns[np.arange(slots.size), np.maximum(n_imu - 1, 0)])
        covered = held & (end >= first)
        if not covered.any():
            return None, covered
        s = slots[covered]
        n = (end[covered] - first[covered]) // self.tick_ns + 1
        self.next_ns[s] = first[covered] + n * self.tick_ns
        vehicle, k = _runs(n)
        t_ns = first[covered][vehicle] + self.tick_ns * k
        return _Due(t_ns, vehicle, s, np.cumsum(n) - 1), covered

    def _imu_means(
        self, due: _Due, window: tuple[IntArray, FloatArray]
    ) -> tuple[FloatArray, IntArray, FloatArray]:
        """Mean of the IMU samples in ``(t − tick, t]`` per tick ``(R, 6)``, their count and
        how far before ``t`` their mean stamp lies [s] ``(R,)``, the means from the running
        sum along each row; the samples up to each vehicle's last tick dropped."""
        stamps, values = window
        mine = stamps[due.vehicle]
        hi = (mine <= due.t_ns[:, None]).sum(axis=1)
        lo = (mine <= (due.t_ns - self.tick_ns)[:, None]).sum(axis=1)
        sums = np.zeros((values.shape[0], values.shape[1] + 1, values.shape[2]))
        np.cumsum(values, axis=1, out=sums[:, 1:])
        count = hi - lo
        means = (sums[due.vehicle, hi] - sums[due.vehicle, lo]) / np.maximum(count, 1)[:, None]
        before_ns = due.t_ns[:, None] - mine
        inside = (before_ns >= 0) & (before_ns < self.tick_ns)
        lag_s = np.where(inside, before_ns, 0).sum(axis=1) / np.maximum(count, 1) * 1e-9
        self.imu.drop(due.slots, hi[due.last])
        return means, count, lag_s

    def _latest(
        self, rows: _Rows, held: tuple[FloatArray, IntArray], due: _Due
    ) -> tuple[FloatArray, IntArray]:
        """The last sample of ``rows`` at or before each tick ``(R, width)`` and its stamp
        ``(R,)``, the slot's ``held`` value ``(S, width)`` and stamp ``(S,)`` (updated to each
        vehicle's last tick) before the first; the samples up to each vehicle's last tick
        dropped."""
        stamps, values = rows.window(due.slots)
        held_value, held_ns = held
        end = (stamps[due.vehicle] <= due.t_ns[:, None]).sum(axis=1)
        at = np.maximum(end - 1, 0)
        out, out_ns = values[due.vehicle, at], stamps[due.vehicle, at]
        before = end == 0
        if before.any():
            out[before] = held_value[due.slots[due.vehicle[before]]]
            out_ns[before] = held_ns[due.slots[due.vehicle[before]]]
        held_value[due.slots], held_ns[due.slots] = out[due.last], out_ns[due.last]
        rows.drop(due.slots, end[due.last])
        return out, out_ns

    def _gnss(
        self, due: _Due, ready: BoolArray
    ) -> tuple[FloatArray, FloatArray, IntArray, BoolArray]:
        """The GNSS columns of :class:`SensedTicks` for the ready ticks; each slot's latest
        epoch and freshness carried to the next call, the epochs popped dropped."""
        stamps, values = self.gnss.window(due.slots)
        v, s = due.vehicle, due.slots
        popped = (np.maximum.accumulate(stamps, axis=1)[v] <= due.t_ns[:, None]).sum(axis=1)
        new = popped > 0
        at = np.maximum(popped - 1, 0)
        epoch = np.where(new[:, None], values[v, at], self.epoch[s[v]])
        epoch_ns = np.where(new, stamps[v, at], self.epoch_ns[s[v]])
        used = ready & (new | self.has_epoch[s[v]])
        fresh = self._fresh(due, used, popped)
        recent = used & (due.t_ns - epoch_ns <= self.gnss_timeout_ns)
        take = fresh & recent & np.isfinite(epoch[:, 2])
        vel = np.where(take[:, None], epoch[:, :2], math.nan)
        att = np.where(take[:, None], epoch[:, 2:], math.nan)
        last = popped[due.last]
        got = last > 0
        self.epoch[s[got]] = values[got, last[got] - 1]
        self.epoch_ns[s[got]] = stamps[got, last[got] - 1]
        self.has_epoch[s[got]] = True
        self.gnss.drop(s, last)
        return vel[ready], att[ready], np.where(take, epoch_ns, 0)[ready], recent[ready]

    def _fresh(self, due: _Due, used: BoolArray, popped: IntArray) -> BoolArray:
        """Per tick ``(R,)``: a ready tick with an epoch (``used``) whose epoch is fresh, i.e.
        one was popped since the vehicle's previous such tick (before the first one of the
        call: since its last such tick, carried in ``fresh``); ``fresh`` updated."""
        v, s = due.vehicle, due.slots
        at = np.flatnonzero(used)
        first = np.ones(at.size, dtype=bool)
        first[1:] = v[at[1:]] != v[at[:-1]]
        before = np.zeros(at.size, dtype=np.int64)
        before[1:] = popped[at[:-1]]
        was = np.where(first, 0, before)
        out = np.zeros(v.size, dtype=bool)
        out[at] = (popped[at] > was) | (first & self.fresh[s[v[at]]])
        final = np.ones(at.size, dtype=bool)  # the last such tick of its vehicle
        final[:-1] = first[1:]
        last_used = np.full(s.size, -1)
        last_used[v[at[final]]] = at[final]
        had = last_used >= 0
        after = popped[due.last] > np.where(had, popped[last_used], 0)
        self.fresh[s] = np.where(had, after, self.fresh[s] | after)
        return out


def _no_ticks() -> SensedTicks:
    f = np.zeros
    return SensedTicks(
        f(0, np.int64),
        f((0, 3)),
        f((0, 3)),
        f((0, 4)),
        f(0),
        f((0, 2)),
        f((0, 3)),
        f(0, np.int64),
        f(0, bool),
        f(0),
    )
