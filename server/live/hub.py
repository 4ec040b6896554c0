"""Latest estimates and decimated sliding windows for live views (dashboard, viser).

:class:`LiveHub` is a pipeline sink: the pipeline thread calls :meth:`LiveHub.on_estimates` once
per estimator per tick with an :class:`estimator.types.EstimateBatch` (rows of that estimator's
spec, time-ordered per vehicle). Everything else (WebSocket handlers on the event loop, the viser
update thread, tests) reads through the hub's methods, which take one short lock and return
copies. Rows are kept per *(vehicle, estimator)* and read through the estimator's
:class:`estimator.spec.EstimatorSpec`, never by one estimator's field names.

Memory is bounded and independent of history length. Each (vehicle, estimator) owns one ring per
*tier*; a tier keeps one row per time bucket of ``bucket_s`` for ``span_s`` seconds:

================  ==========  ==========  ======  ==============================================
tier              bucket_s    span_s      rows    used for
================  ==========  ==========  ======  ==============================================
``fine``          0.05        60          1200    windows up to 60 s (20 Hz, effectively full)
``coarse``        0.5         1800        3600    windows up to 30 min (2 Hz)
================  ==========  ==========  ======  ==============================================

A ring row holds the spec's *live fields* (:func:`live_fields`: chart, slip, motion and position
fields and ``flags``) as float32 plus an int64 stamp: about 250 kB per vehicle for MDSF's eleven.
A bucket's row holds the values of its newest estimate, except the slip channels' fields, which
keep the value of largest magnitude seen in the bucket (peaks survive decimation). The newest
bucket is written while it fills, so the newest estimate is always visible.

A vehicle's *primary* estimator (``primary_of``, e.g. the first of
``server.estimation.registry.estimator_names_for``; else the first estimator that brought rows)
is what the fleet overview shows: its motion speed, slip channels and quality.

Status of a (vehicle, estimator) (``live`` / ``stale`` / ``offline``) comes from the age of its
newest estimate, the larger of

* *sensor age*: newest sensor stamp of the whole fleet minus the newest stamp, and
* *wall age*: wall clock now minus the wall time the newest row arrived at the hub,

compared with ``stale_after_s`` and ``offline_after_s``.

For each row the hub records the wall time it arrived (``arrival_ns``), so a page can measure
sensor → page latency (``receive time - stamp_ns``) and the hub's share of it.

Waking async readers: every batch increments :attr:`LiveHub.version`; :meth:`LiveHub.wait_newer`
awaits a newer version without blocking the event loop (``loop.call_soon_threadsafe`` on
:class:`asyncio.Event` objects registered by each waiting coroutine).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from estimator.catalog import SPECS
from estimator.spec import EstimatorSpec
from estimator.types import EstimateBatch

__all__ = [
    "LiveHub",
    "TierSpec",
    "VehicleStatus",
    "live_fields",
    "quality",
]

log = logging.getLogger(__name__)


class VehicleStatus:
    """Status strings of a vehicle in live views."""

    LIVE: Final[str] = "live"
    STALE: Final[str] = "stale"
    OFFLINE: Final[str] = "offline"


def live_fields(spec: EstimatorSpec) -> tuple[str, ...]:
    """Fields of ``spec`` kept in the sliding windows, in this order, each once.

    The fields of its charts, slip channels, state, value and wheel value channels and motion
    speed, its position's east/north/up and their standard deviations, and ``flags``
    (``stamp_ns`` is stored apart as int64).
    """
    names: list[str] = [f for c in spec.charts for f in c.fields]
    names += [s.field for s in spec.slips]
    names += [s.field for s in spec.states] + [v.field for v in spec.values]
    names += [w.field for w in spec.wheel_values]
    if spec.motion_field is not None:
        names.append(spec.motion_field)
    p = spec.position
    if p is not None:
        fields = (p.east_field, p.north_field, p.up_field, p.east_std_field, p.north_std_field)
        names += [f for f in fields if f is not None]
    if spec.has_field("flags"):
        names.append("flags")
    return tuple(dict.fromkeys(names))


def quality(spec: EstimatorSpec, flags: int) -> str:
    """A row's quality at a glance: ``"degraded"`` (a degraded flag set), ``"ok"`` (its
    ``ok_flag`` set), else ``"none"``."""
    f = int(flags)
    if any(f & spec.flag_mask(name) for name in spec.degraded_flags):
        return "degraded"
    if spec.ok_flag is not None and f & spec.flag_mask(spec.ok_flag):
        return "ok"
    return "none"


@dataclass(frozen=True, slots=True)
class TierSpec:
    """One decimation tier: one row per ``bucket_s`` for ``span_s`` seconds."""

    name: str
    bucket_s: float
    span_s: float

    def __post_init__(self) -> None:
        if not (self.bucket_s > 0 and self.span_s >= self.bucket_s):
            raise ValueError(f"tier {self.name}: need 0 < bucket_s <= span_s")

    @property
    def bucket_ns(self) -> int:
        return max(1, round(self.bucket_s * 1e9))

    @property
    def capacity(self) -> int:
        return math.ceil(self.span_s / self.bucket_s) + 1


DEFAULT_TIERS: Final[tuple[TierSpec, ...]] = (
    TierSpec("fine", 0.05, 60.0),
    TierSpec("coarse", 0.5, 1800.0),
)


def _group_aggregate(
    keys: npt.NDArray[np.int64],
    stamps: npt.NDArray[np.int64],
    vals: npt.NDArray[np.floating],
    peak_cols: tuple[int, ...],
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.int64], npt.NDArray[np.floating]]:
    """Aggregate runs of equal ``keys`` (rows already grouped): newest values, peak |slip|.

    Parameters
    ----------
    keys : (n,) int64, runs of equal values are one group
    stamps : (n,) int64
    vals : (n, f) float, the live fields
    peak_cols : columns of ``vals`` that keep their value of largest magnitude (slips)

    Returns
    -------
    starts : (g,) index of each group's first row
    g_stamps : (g,) stamp of each group's newest row
    g_vals : (g, f) newest values, ``peak_cols`` replaced by the signed peak
    """
    n = keys.shape[0]
    change = np.empty(n, dtype=bool)
    change[0] = True
    np.not_equal(keys[1:], keys[:-1], out=change[1:])
    starts = np.flatnonzero(change)
    ends = np.empty_like(starts)
    ends[:-1] = starts[1:] - 1
    ends[-1] = n - 1
    g_vals = vals[ends].copy()
    if n != starts.shape[0]:  # some group has more than one row: find the slip peaks
        gid = np.cumsum(change) - 1
        for c in peak_cols:
            mag = np.abs(vals[:, c])
            mag = np.where(np.isnan(mag), -1.0, mag)
            # by group, then magnitude: the last row of a group is its peak
            order = np.lexsort((mag, gid))
            peak = order[ends]
            g_vals[:, c] = vals[peak, c]
    return starts, stamps[ends], g_vals


def _peak(a: npt.NDArray[np.floating], b: npt.NDArray[np.floating]) -> npt.NDArray[np.floating]:
    """Element-wise value of larger magnitude (NaN loses to any number)."""
    ma = np.where(np.isnan(a), -1.0, np.abs(a))
    mb = np.where(np.isnan(b), -1.0, np.abs(b))
    return np.where(mb >= ma, b, a)


class _Tier:
    """Per-vehicle rings of one tier, stored as 2-D arrays indexed ``[slot, position]``.

    ``vals`` is ``(slots, capacity, nf)`` of ``dtype``; ``peak_cols`` keep their peak per bucket.
    """

    def __init__(
        self, spec: TierSpec, slots: int, nf: int, dtype: type, peak_cols: tuple[int, ...]
    ) -> None:
        self.spec = spec
        self.nf = nf
        self.dtype = dtype
        self.peak_cols = peak_cols
        self.cap = spec.capacity
        self.bucket_ns = spec.bucket_ns
        # np.full, not np.zeros: every page is written now (zeros would map them lazily and the
        # resident size would creep up for the tier's whole span as the rings fill)
        self.stamp = np.full((slots, self.cap), 0, dtype=np.int64)
        self.vals: npt.NDArray[np.floating] = np.full((slots, self.cap, nf), np.nan, dtype=dtype)
        self.head = np.zeros(slots, dtype=np.int64)  # next write position (monotonic counter)
        self.count = np.zeros(slots, dtype=np.int64)
        self.last_bucket = np.full(slots, -1, dtype=np.int64)

    def grow(self, slots: int) -> None:
        extra = slots - self.head.shape[0]
        self.stamp = np.concatenate([self.stamp, np.full((extra, self.cap), 0, np.int64)])
        more: npt.NDArray[np.floating] = np.full((extra, self.cap, self.nf), np.nan, self.dtype)
        self.vals = np.concatenate([self.vals, more])
        self.head = np.concatenate([self.head, np.zeros(extra, np.int64)])
        self.count = np.concatenate([self.count, np.zeros(extra, np.int64)])
        self.last_bucket = np.concatenate([self.last_bucket, np.full(extra, -1, np.int64)])

    def append(
        self,
        slot: npt.NDArray[np.int64],
        stamp: npt.NDArray[np.int64],
        vals: npt.NDArray[np.floating],
    ) -> None:
        """Add rows grouped by slot, time-ordered within a slot (vectorised over the batch)."""
        bucket = stamp // self.bucket_ns
        slot_change = np.empty(slot.shape[0], dtype=bool)
        slot_change[0] = True
        np.not_equal(slot[1:], slot[:-1], out=slot_change[1:])
        run_start = slot_change.copy()
        run_start[1:] |= bucket[1:] != bucket[:-1]
        key = np.cumsum(run_start)  # one key per run of equal (slot, bucket)
        starts, g_stamp, g_vals = _group_aggregate(key, stamp, vals, self.peak_cols)
        g_slot = slot[starts]
        g_bucket = bucket[starts]
        first_of_slot = slot_change[starts]
        merge = first_of_slot & (g_bucket == self.last_bucket[g_slot]) & (self.count[g_slot] > 0)
        new_i = (~merge).astype(np.int64)
        before = np.cumsum(new_i) - new_i  # new groups before this one, whole batch
        slot_first = np.maximum.accumulate(np.where(first_of_slot, np.arange(g_slot.shape[0]), 0))
        rank = before - before[slot_first]  # ... before this one, same slot
        pos = np.where(merge, self.head[g_slot] - 1, self.head[g_slot] + rank) % self.cap
        if merge.any():
            mi = np.flatnonzero(merge)
            old = self.vals[g_slot[mi], pos[mi]]
            for c in self.peak_cols:
                g_vals[mi, c] = _peak(old[:, c], g_vals[mi, c])
        self.stamp[g_slot, pos] = g_stamp
        self.vals[g_slot, pos] = g_vals
        added = np.bincount(g_slot, weights=new_i, minlength=self.head.shape[0]).astype(np.int64)
        self.head += added
        np.minimum(self.count + added, self.cap, out=self.count)
        last = np.r_[g_slot[1:] != g_slot[:-1], True]
        self.last_bucket[g_slot[last]] = g_bucket[last]

    def read(self, s: int, start_ns: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.floating]]:
        """Rows of slot ``s`` with ``stamp_ns >= start_ns``, oldest first (copies)."""
        n = int(self.count[s])
        if n == 0:
            return np.zeros(0, np.int64), np.zeros((0, self.nf), self.dtype)
        idx = (int(self.head[s]) - n + np.arange(n)) % self.cap
        st = self.stamp[s, idx]
        first = int(np.searchsorted(st, start_ns, side="left"))
        return st[first:].copy(), self.vals[s, idx[first:]].copy()

    def oldest(self, s: int) -> int | None:
        n = int(self.count[s])
        if n == 0:
            return None
        return int(self.stamp[s, (int(self.head[s]) - n) % self.cap])


class _Board:
    """One estimator's rows of every vehicle: newest row, arrival time and tier rings per slot.

    Not locked itself: the hub holds its lock around every call.
    """

    def __init__(self, spec: EstimatorSpec, tiers: Sequence[TierSpec], slots: int) -> None:
        self.spec = spec
        self.fields = live_fields(spec)
        # float32 holds integers exactly below 2**24: wider flag words need float64
        top_bit = max((f.bit for f in spec.flags), default=0)
        dtype: type = np.float32 if top_bit < 24 else np.float64
        peak = tuple(self.fields.index(s.field) for s in spec.slips)
        self.ids: list[str] = []
        self.slot: dict[str, int] = {}
        self.free: list[int] = []  # slots of forgotten vehicles, reused first
        self.latest = np.zeros(slots, dtype=spec.dtype)
        self.arrival_ns = np.zeros(slots, dtype=np.int64)
        self.has = np.zeros(slots, dtype=bool)
        self.tiers = [_Tier(t, slots, len(self.fields), dtype, peak) for t in tiers]
        self.rows_dropped_late = 0

    def slot_of(self, vehicle_id: str) -> int:
        s = self.slot.get(vehicle_id)
        if s is not None:
            return s
        if self.free:
            s = self.free.pop()
            self.ids[s] = vehicle_id
        else:
            s = len(self.ids)
            if s >= self.latest.shape[0]:
                self._grow(2 * self.latest.shape[0])
            self.ids.append(vehicle_id)
        self.slot[vehicle_id] = s
        return s

    def _grow(self, n: int) -> None:
        s = self.latest.shape[0]
        latest = np.zeros(n, dtype=self.spec.dtype)
        latest[:s] = self.latest
        self.latest = latest
        self.arrival_ns = np.r_[self.arrival_ns, np.zeros(n - s, np.int64)]
        self.has = np.r_[self.has, np.zeros(n - s, bool)]
        for t in self.tiers:
            t.grow(n)

    def _keep(
        self, slot: npt.NDArray[np.int64], stamp: npt.NDArray[np.int64]
    ) -> npt.NDArray[np.bool_] | None:
        """Rows newer than their vehicle's newest row and their predecessor (None: all are)."""
        prev = np.where(self.has[slot], self.latest["stamp_ns"][slot], np.iinfo(np.int64).min)
        same = np.r_[False, slot[1:] == slot[:-1]]
        prev = np.where(same, np.r_[np.int64(0), stamp[:-1]], prev)
        if (stamp > prev).all():
            return None
        # rare: compare with the running newest stamp of each vehicle
        newest = np.where(self.has[slot], self.latest["stamp_ns"][slot], 0).tolist()
        keep = [False] * stamp.shape[0]
        cur = newest[0]
        for i, st in enumerate(stamp.tolist()):
            if not same[i]:
                cur = newest[i]
            if st > cur:
                keep[i] = True
                cur = st
        return np.array(keep, dtype=bool)

    def add(self, batch: EstimateBatch, now_ns: int) -> tuple[list[str], int, int]:
        """Take ``batch``; return (vehicles with their first row here, rows kept, newest stamp)."""
        slots = np.fromiter((self.slot_of(v) for v in batch.ids), np.int64, count=len(batch))
        rows, slot = batch.grouped(slots)
        stamp = rows["stamp_ns"].astype(np.int64)
        keep = self._keep(slot, stamp)
        if keep is not None:
            self.rows_dropped_late += int((~keep).sum())
            rows, slot, stamp = rows[keep], slot[keep], stamp[keep]
            if rows.shape[0] == 0:
                return [], 0, 0
        vals: npt.NDArray[np.floating] = np.empty(
            (rows.shape[0], len(self.fields)), dtype=self.tiers[0].dtype
        )
        for i, f in enumerate(self.fields):
            vals[:, i] = rows[f]
        for t in self.tiers:
            t.append(slot, stamp, vals)
        last = np.r_[slot[1:] != slot[:-1], True]
        ls = slot[last]
        first = [self.ids[s] for s in ls[~self.has[ls]].tolist()]
        self.latest[ls] = rows[last]
        self.arrival_ns[ls] = now_ns
        self.has[ls] = True
        return first, int(rows.shape[0]), int(stamp.max())

    def drop(self, vehicle_id: str) -> None:
        s = self.slot.pop(vehicle_id, None)
        if s is None:
            return
        self.has[s] = False
        for t in self.tiers:
            t.head[s] = 0
            t.count[s] = 0
            t.last_bucket[s] = -1
        self.ids[s] = ""
        self.free.append(s)

    def window(
        self, s: int, window_s: float, since_ns: int | None
    ) -> tuple[TierSpec, npt.NDArray[np.int64], npt.NDArray[np.floating]]:
        """The finest tier covering ``window_s`` and its rows of slot ``s`` in the window."""
        newest = int(self.latest["stamp_ns"][s])
        tier = next((t for t in self.tiers if t.spec.span_s >= window_s), self.tiers[-1])
        start = newest - round(window_s * 1e9)
        if since_ns is not None:
            start = max(start, since_ns)
        st, vals = tier.read(s, start)
        return tier.spec, st, vals


def _as_batch(batch: EstimateBatch | Sequence[tuple[str, np.ndarray]]) -> EstimateBatch | None:
    """``batch`` as an :class:`EstimateBatch`; a plain ``[(vehicle_id, rows), ...]`` is taken as
    rows of the catalog's spec with their dtype. None when there are no rows."""
    if isinstance(batch, EstimateBatch):
        return batch if batch.rows.shape[0] else None
    parts = [(vid, rows) for vid, rows in batch if rows.shape[0] > 0]
    if not parts:
        return None
    dtype = parts[0][1].dtype
    spec = next((s for s in SPECS.values() if s.dtype == dtype), None)
    if spec is None:
        raise TypeError(f"rows of dtype {dtype} are no catalog estimator's; pass an EstimateBatch")
    return EstimateBatch.of(parts, spec)


#: Vehicles whose primary is one estimator: (indices into the ids, newest rows, arrival times).
_Group = tuple[list[int], np.ndarray, npt.NDArray[np.int64]]


class LiveHub:
    """Latest row, decimated windows and status of every (vehicle, estimator); a thread-safe
    pipeline sink.

    Parameters
    ----------
    stale_after_s : float
        A vehicle whose newest estimate is older than this is ``stale``.
    offline_after_s : float
        ... older than this is ``offline``.
    tiers : sequence of TierSpec
        Decimation tiers, finest first (see the module docstring).
    clock_ns : callable
        Wall clock in ns (injected in tests).
    primary_of : callable, optional
        Vehicle id → name of its primary estimator (None or an estimator without rows here: the
        first estimator that brought rows). Called under the hub's lock: cheap, never the hub.
    """

    def __init__(
        self,
        *,
        stale_after_s: float = 3.0,
        offline_after_s: float = 30.0,
        tiers: Sequence[TierSpec] = DEFAULT_TIERS,
        clock_ns: Callable[[], int] = time.time_ns,
        initial_slots: int = 64,
        primary_of: Callable[[str], str | None] | None = None,
    ) -> None:
        if not 0 < stale_after_s < offline_after_s:
            raise ValueError("need 0 < stale_after_s < offline_after_s")
        if not tiers or any(b.span_s < a.span_s for a, b in itertools.pairwise(tiers)):
            raise ValueError("tiers must be non-empty, finest (shortest span) first")
        self.stale_after_s = float(stale_after_s)
        self.offline_after_s = float(offline_after_s)
        self._tier_specs = tuple(tiers)
        self._initial_slots = max(1, int(initial_slots))
        self._clock_ns = clock_ns
        self._primary_of = primary_of
        self._lock = threading.Lock()
        self._boards: dict[str, _Board] = {}
        #: vehicle id -> estimators with rows here, in the order they first brought rows
        self._estimators: dict[str, list[str]] = {}
        self._fleet_stamp_ns = 0
        self._version = 0
        self.rows_in = 0
        self._waiters: set[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = set()

    # ------------------------------------------------------------------ writing (pipeline thread)
    @property
    def version(self) -> int:
        """Increments on every batch that added rows."""
        return self._version

    @property
    def rows_dropped_late(self) -> int:
        """Rows not newer than their (vehicle, estimator)'s newest row, ignored."""
        return sum(b.rows_dropped_late for b in self._boards.values())

    def _board(self, spec: EstimatorSpec) -> _Board:
        board = self._boards.get(spec.name)
        if board is None:
            board = self._boards[spec.name] = _Board(spec, self._tier_specs, self._initial_slots)
        elif board.spec.dtype != spec.dtype:
            raise TypeError(f"estimator {spec.name!r} changed its row dtype")
        return board

    def on_estimates(self, batch: EstimateBatch | Sequence[tuple[str, np.ndarray]]) -> None:
        """Take one estimator's new rows (an :class:`EstimateBatch`, see :func:`_as_batch`).

        Rows not newer than the (vehicle, estimator)'s newest row are counted in
        ``rows_dropped_late`` and ignored (the pipeline already reorders by sensor time).
        """
        now_ns = self._clock_ns()
        joined = _as_batch(batch)
        if joined is None:
            return
        with self._lock:
            first, n, newest = self._board(joined.spec).add(joined, now_ns)
            if n == 0:
                return
            for vid in first:
                self._estimators.setdefault(vid, []).append(joined.spec.name)
            self._fleet_stamp_ns = max(self._fleet_stamp_ns, newest)
            self.rows_in += n
            self._version += 1
            waiters = list(self._waiters)
        for loop, ev in waiters:
            try:
                loop.call_soon_threadsafe(ev.set)
            except RuntimeError:  # loop closed: the waiter is gone
                self._waiters.discard((loop, ev))

    def forget(self, vehicle_id: str) -> bool:
        """Drop a vehicle (deleted from the fleet): every estimator's rows, windows, status.
        False if unknown."""
        with self._lock:
            names = self._estimators.pop(vehicle_id, None)
            if names is None:
                return False
            for name in names:
                self._boards[name].drop(vehicle_id)
            self._version += 1
            return True

    # ------------------------------------------------------------------ waiting (event loop)
    async def wait_newer(self, version: int, timeout_s: float) -> int:
        """Wait until :attr:`version` exceeds ``version`` or ``timeout_s`` passes; return it."""
        if self._version > version:
            return self._version
        loop = asyncio.get_running_loop()
        ev = asyncio.Event()
        key = (loop, ev)
        self._waiters.add(key)
        try:
            if self._version <= version:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(ev.wait(), timeout_s)
        finally:
            self._waiters.discard(key)
        return self._version

    # ------------------------------------------------------------------ reading (any thread)
    def vehicle_ids(self) -> list[str]:
        """Vehicles with at least one row, in the order they first appeared."""
        with self._lock:
            return list(self._estimators)

    def __contains__(self, vehicle_id: object) -> bool:
        return vehicle_id in self._estimators

    def spec(self, estimator: str) -> EstimatorSpec | None:
        """The spec of an estimator whose rows reached the hub (None if none did)."""
        board = self._boards.get(estimator)
        return None if board is None else board.spec

    def _primary(self, vehicle_id: str) -> str | None:
        names = self._estimators.get(vehicle_id)
        if not names:
            return None
        if self._primary_of is not None:
            try:
                name = self._primary_of(vehicle_id)
            except Exception:  # a vehicle whose config names no estimator: keep the hub's order
                log.debug("primary estimator of %s unknown", vehicle_id, exc_info=True)
                name = None
            if name in names:
                return name
        return names[0]

    def specs(self) -> list[EstimatorSpec]:
        """Specs of every estimator whose rows reached the hub, in that order."""
        with self._lock:
            return [b.spec for b in self._boards.values()]

    def primary(self, vehicle_id: str) -> str | None:
        """Name of the vehicle's primary estimator (among those with rows), None if unknown."""
        with self._lock:
            return self._primary(vehicle_id)

    def estimators(self, vehicle_id: str) -> list[str]:
        """Estimators with rows of the vehicle, primary first ([] when unknown)."""
        with self._lock:
            p = self._primary(vehicle_id)
            return sorted(self._estimators.get(vehicle_id, ()), key=lambda n: n != p)

    def _slot(self, vehicle_id: str, estimator: str | None) -> tuple[_Board, int] | None:
        name = self._primary(vehicle_id) if estimator is None else estimator
        board = None if name is None else self._boards.get(name)
        s = None if board is None else board.slot.get(vehicle_id)
        if board is None or s is None or not board.has[s]:
            return None
        return board, s

    def latest(
        self, vehicle_id: str, estimator: str | None = None
    ) -> tuple[np.ndarray, int] | None:
        """``(row, arrival_ns)`` of the newest row of the vehicle's ``estimator`` (default: its
        primary) as a 0-d array of that spec's dtype, or None."""
        with self._lock:
            got = self._slot(vehicle_id, estimator)
            if got is None:
                return None
            board, s = got
            return board.latest[s].copy(), int(board.arrival_ns[s])

    def latest_all(
        self, estimator: str, *, primary_only: bool = False
    ) -> tuple[list[str], np.ndarray, npt.NDArray[np.int64]]:
        """Ids, newest rows ``(n,)`` and arrival times ``(n,)`` of every vehicle with rows of
        ``estimator`` (only those whose primary it is with ``primary_only``)."""
        with self._lock:
            board = self._boards.get(estimator)
            if board is None:
                return [], np.zeros(0, np.int64), np.zeros(0, np.int64)
            n = len(board.ids)
            has = board.has[:n].copy()
            if primary_only:
                for s in np.flatnonzero(has).tolist():
                    has[s] = self._primary(board.ids[s]) == estimator
            ids = [v for v, h in zip(board.ids, has.tolist(), strict=True) if h]
            return ids, board.latest[:n][has].copy(), board.arrival_ns[:n][has].copy()

    def _ages(
        self, stamps: npt.NDArray[np.int64], arrivals: npt.NDArray[np.int64], now_ns: int
    ) -> npt.NDArray[np.float64]:
        sensor_age = (self._fleet_stamp_ns - stamps) / 1e9
        wall_age = (now_ns - arrivals) / 1e9
        return np.maximum(np.maximum(sensor_age, wall_age), 0.0)

    def _status(self, age_s: npt.NDArray[np.float64]) -> list[str]:
        return [
            VehicleStatus.LIVE
            if a < self.stale_after_s
            else VehicleStatus.STALE
            if a < self.offline_after_s
            else VehicleStatus.OFFLINE
            for a in age_s.tolist()
        ]

    def status_of_rows(
        self, stamps_ns: npt.ArrayLike, arrivals_ns: npt.ArrayLike, now_ns: int | None = None
    ) -> list[str]:
        """Status of rows (``latest_all``'s stamps and arrival times), one per row."""
        now = self._clock_ns() if now_ns is None else now_ns
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        return self._status(self._ages(stamps, np.asarray(arrivals_ns, dtype=np.int64), now))

    def status(
        self, vehicle_id: str, estimator: str | None = None, now_ns: int | None = None
    ) -> str | None:
        """``live`` / ``stale`` / ``offline`` of a known (vehicle, estimator) (default: its
        primary), None for an unknown one."""
        got = self.latest(vehicle_id, estimator)
        if got is None:
            return None
        row, arr = got
        return self.status_of_rows([int(row["stamp_ns"])], [arr], now_ns)[0]

    def _primary_rows(self) -> tuple[list[str], dict[str, _Group]]:
        """Every vehicle id, and per primary estimator: (indices into ids, rows, arrivals)."""
        with self._lock:
            ids = list(self._estimators)
            groups: dict[str, list[int]] = {}
            for i, vid in enumerate(ids):
                groups.setdefault(self._primary(vid) or "", []).append(i)
            out: dict[str, _Group] = {}
            for name, idx in groups.items():
                board = self._boards[name]
                slots = [board.slot[ids[i]] for i in idx]
                out[name] = (idx, board.latest[slots], board.arrival_ns[slots])
        return ids, out

    def overview(self, now_ns: int | None = None) -> dict[str, Any]:
        """Compact column-wise state of the whole fleet (the ``fleet`` WebSocket message body),
        each vehicle by its primary estimator.

        Keys, each a list with one entry per vehicle: ``ids``, ``estimator`` (the primary),
        ``status``, ``stamp_ns``, ``age_s``, ``speed_mps`` (its motion channel), ``quality``
        (:func:`quality`), ``flags``; and ``slip_pct``: ``{channel key: [...]}`` for every slip
        channel key of any primary (null where a vehicle's primary has no such channel).
        Floats are rounded (speeds to 0.01 m/s, slip to 0.1 %, ages to 0.1 s); NaN becomes null.
        """
        now = self._clock_ns() if now_ns is None else now_ns
        ids, groups = self._primary_rows()
        n = len(ids)
        out: dict[str, Any] = {"t_ns": now, "ids": ids, "estimator": [""] * n}
        cols: dict[str, list[Any]] = {
            k: [None] * n for k in ("status", "stamp_ns", "age_s", "speed_mps", "quality", "flags")
        }
        slips: dict[str, list[float | None]] = {}
        for name, (idx, rows, arr) in groups.items():
            spec = self._boards[name].spec
            stamps = rows["stamp_ns"].astype(np.int64)
            ages = self._ages(stamps, arr, now)
            flags = rows["flags"].astype(np.int64).tolist() if spec.has_field("flags") else None
            part: dict[str, list[Any]] = {
                "status": self._status(ages),
                "stamp_ns": stamps.tolist(),
                "age_s": _rounded(ages, 1),
                "speed_mps": _rounded(rows[spec.motion_field], 2)
                if spec.motion_field
                else [None] * len(idx),
                "flags": flags or [0] * len(idx),
                "quality": [quality(spec, f) for f in flags or [0] * len(idx)],
            }
            for s in spec.slips:
                col = slips.setdefault(s.key, [None] * n)
                for i, v in zip(idx, _rounded(rows[s.field], 1), strict=True):
                    col[i] = v
            for key, values in part.items():
                for i, v in zip(idx, values, strict=True):
                    cols[key][i] = v
            for i in idx:
                out["estimator"][i] = name
        return {**out, **cols, "slip_pct": slips}

    def window(
        self,
        vehicle_id: str,
        window_s: float,
        *,
        estimator: str | None = None,
        since_ns: int | None = None,
        max_points: int | None = None,
    ) -> dict[str, Any] | None:
        """Decimated series of one (vehicle, estimator) over the last ``window_s`` seconds
        (sensor time); ``estimator`` defaults to the vehicle's primary.

        Picks the finest tier whose span covers the window. With ``since_ns`` only rows with
        ``stamp_ns >= since_ns`` are returned (incremental updates). With ``max_points`` rows are
        further bucketed in time so that at most about that many remain.

        Returns None for an unknown (vehicle, estimator), else ``{"estimator", "tier",
        "bucket_s", "stamp_ns": [...], <field>: [...] for field in live_fields(spec)}`` (NaN →
        None).
        """
        with self._lock:
            got = self._slot(vehicle_id, estimator)
            if got is None:
                return None
            board, s = got
            tier, st, vals = board.window(s, window_s, since_ns)
        if max_points is not None and st.shape[0] > max_points > 0:
            width = max(1, (int(st[-1]) - int(st[0])) // max_points + 1)
            key = (st - st[0]) // width
            _, st, vals = _group_aggregate(key, st, vals, board.tiers[0].peak_cols)
        out: dict[str, Any] = {
            "estimator": board.spec.name,
            "tier": tier.name,
            "bucket_s": tier.bucket_s,
            "stamp_ns": st.tolist(),
        }
        for i, f in enumerate(board.fields):
            col = vals[:, i]
            out[f] = [int(x) for x in col] if f == "flags" else _rounded(col, 3)
        return out


def _rounded(a: npt.ArrayLike, digits: int) -> list[float | None]:
    arr = np.round(np.asarray(a, dtype=np.float64), digits)
    return [None if math.isnan(x) else x for x in arr.tolist()]
