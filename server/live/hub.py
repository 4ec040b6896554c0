"""Latest estimates and decimated sliding windows for live views (dashboard, viser).

:class:`LiveHub` is a pipeline sink: the pipeline thread calls :meth:`LiveHub.on_estimates` with
``[(vehicle_id, rows), ...]`` where ``rows`` is a structured array of
:data:`estimator.types.ESTIMATE_DTYPE`, time-ordered per vehicle. Everything else (WebSocket
handlers on the event loop, the viser update thread, tests) reads through the hub's methods, which
take one short lock and return copies.

Memory is bounded and independent of history length. Each vehicle owns one ring per *tier*; a tier
keeps one row per time bucket of ``bucket_s`` for ``span_s`` seconds:

================  ==========  ==========  ======  ==============================================
tier              bucket_s    span_s      rows    used for
================  ==========  ==========  ======  ==============================================
``fine``          0.05        60          1200    windows up to 60 s (20 Hz, effectively full)
``coarse``        0.5         1800        3600    windows up to 30 min (2 Hz)
================  ==========  ==========  ======  ==============================================

About 250 kB per vehicle with the defaults (eleven float32 columns and an int64 stamp per row).
A bucket's row holds the values of its newest estimate, except the two slip columns, which keep
the value of largest magnitude seen in the bucket (peaks survive decimation). The newest bucket is
written while it fills, so the newest estimate is always visible.

Status of a vehicle (``live`` / ``stale`` / ``offline``) comes from the age of its newest estimate,
the larger of

* *sensor age*: newest sensor stamp of the whole fleet minus the vehicle's newest stamp, and
* *wall age*: wall clock now minus the wall time the vehicle's newest row arrived at the hub,

compared with ``stale_after_s`` and ``offline_after_s``.

For each vehicle the hub records the wall time its newest row arrived (``arrival_ns``), so a page
can measure sensor → page latency (``receive time - stamp_ns``) and the hub's share of it.

Waking async readers: every batch increments :attr:`LiveHub.version`; :meth:`LiveHub.wait_newer`
awaits a newer version without blocking the event loop (``loop.call_soon_threadsafe`` on
:class:`asyncio.Event` objects registered by each waiting coroutine).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from estimator.types import ESTIMATE_DTYPE, EstimateBatch, EstimateFlag

__all__ = [
    "LIVE_FIELDS",
    "LiveHub",
    "TierSpec",
    "VehicleStatus",
    "gnss_quality",
    "slip_note",
]

#: Columns kept in the sliding windows, in this order (``stamp_ns`` is stored apart as int64).
LIVE_FIELDS: Final[tuple[str, ...]] = (
    "vg_mps",
    "vl_mps",
    "vr_mps",
    "rim_left_mps",
    "rim_right_mps",
    "slip_left_pct",
    "slip_right_pct",
    "east_m",
    "north_m",
    "up_m",
    "flags",
)
_SLIP_COLS: Final[tuple[int, ...]] = (
    LIVE_FIELDS.index("slip_left_pct"),
    LIVE_FIELDS.index("slip_right_pct"),
)
_NF: Final[int] = len(LIVE_FIELDS)


class VehicleStatus:
    """Status strings of a vehicle in live views."""

    LIVE: Final[str] = "live"
    STALE: Final[str] = "stale"
    OFFLINE: Final[str] = "offline"


_GNSS_LABELS = (
    (EstimateFlag.DEGRADED, "degraded"),
    (EstimateFlag.GATED, "gated"),
    (EstimateFlag.GNSS_OK, "ok"),
)
_SLIP_NOTES = (
    (EstimateFlag.STANDSTILL, "standstill"),
    (EstimateFlag.SETTLING, "starting/stopping"),
    (EstimateFlag.WHEEL_GAP, "wheel data lost"),
)


def _first_label(flags: int, labels: tuple[tuple[EstimateFlag, str], ...], default: str) -> str:
    """The label of the first flag of ``labels`` set in ``flags``, else ``default``."""
    f = int(flags)
    for flag, label in labels:
        if f & flag:
            return label
    return default


def gnss_quality(flags: int) -> str:
    """Summarise an estimate's flags as ``"ok"``, ``"gated"``, ``"degraded"`` or ``"none"``.

    ``degraded`` means GNSS is lost and the speed is carried by IMU + wheels.
    """
    return _first_label(flags, _GNSS_LABELS, "none")


def slip_note(flags: int) -> str:
    """Why an estimate carries no slip value: ``"standstill"``, ``"starting/stopping"``
    (:attr:`EstimateFlag.SETTLING`), ``"wheel data lost"`` (:attr:`EstimateFlag.WHEEL_GAP`), or
    ``""`` (a value, or no known reason)."""
    return _first_label(flags, _SLIP_NOTES, "")


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
    keys: npt.NDArray[np.int64], stamps: npt.NDArray[np.int64], vals: npt.NDArray[np.float32]
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """Aggregate runs of equal ``keys`` (rows already grouped): newest values, peak |slip|.

    Parameters
    ----------
    keys : (n,) int64, runs of equal values are one group
    stamps : (n,) int64
    vals : (n, len(LIVE_FIELDS)) float32

    Returns
    -------
    starts : (g,) index of each group's first row
    g_stamps : (g,) stamp of each group's newest row
    g_vals : (g, len(LIVE_FIELDS)) newest values, slip columns replaced by the signed peak
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
        for c in _SLIP_COLS:
            mag = np.abs(vals[:, c])
            mag = np.where(np.isnan(mag), -1.0, mag)
            # by group, then magnitude: the last row of a group is its peak
            order = np.lexsort((mag, gid))
            peak = order[ends]
            g_vals[:, c] = vals[peak, c]
    return starts, stamps[ends], g_vals


def _peak(a: npt.NDArray[np.float32], b: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """Element-wise value of larger magnitude (NaN loses to any number)."""
    ma = np.where(np.isnan(a), -1.0, np.abs(a))
    mb = np.where(np.isnan(b), -1.0, np.abs(b))
    return np.where(mb >= ma, b, a)


class _Tier:
    """Per-vehicle rings of one tier, stored as 2-D arrays indexed ``[slot, position]``."""

    def __init__(self, spec: TierSpec, slots: int) -> None:
        self.spec = spec
        self.cap = spec.capacity
        self.bucket_ns = spec.bucket_ns
        # np.full, not np.zeros: every page is written now (zeros would map them lazily and the
        # resident size would creep up for the tier's whole span as the rings fill)
        self.stamp = np.full((slots, self.cap), 0, dtype=np.int64)
        self.vals = np.full((slots, self.cap, _NF), np.nan, dtype=np.float32)
        self.head = np.zeros(slots, dtype=np.int64)  # next write position (monotonic counter)
        self.count = np.zeros(slots, dtype=np.int64)
        self.last_bucket = np.full(slots, -1, dtype=np.int64)

    def grow(self, slots: int) -> None:
        extra = slots - self.head.shape[0]
        self.stamp = np.concatenate([self.stamp, np.full((extra, self.cap), 0, np.int64)])
        self.vals = np.concatenate([self.vals, np.full((extra, self.cap, _NF), np.nan, np.float32)])
        self.head = np.concatenate([self.head, np.zeros(extra, np.int64)])
        self.count = np.concatenate([self.count, np.zeros(extra, np.int64)])
        self.last_bucket = np.concatenate([self.last_bucket, np.full(extra, -1, np.int64)])

    def append(
        self,
        slot: npt.NDArray[np.int64],
        stamp: npt.NDArray[np.int64],
        vals: npt.NDArray[np.float32],
    ) -> None:
        """Add rows grouped by slot, time-ordered within a slot (vectorised over the batch)."""
        bucket = stamp // self.bucket_ns
        slot_change = np.empty(slot.shape[0], dtype=bool)
        slot_change[0] = True
        np.not_equal(slot[1:], slot[:-1], out=slot_change[1:])
        run_start = slot_change.copy()
        run_start[1:] |= bucket[1:] != bucket[:-1]
        key = np.cumsum(run_start)  # one key per run of equal (slot, bucket)
        starts, g_stamp, g_vals = _group_aggregate(key, stamp, vals)
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
            for c in _SLIP_COLS:
                g_vals[mi, c] = _peak(old[:, c], g_vals[mi, c])
        self.stamp[g_slot, pos] = g_stamp
        self.vals[g_slot, pos] = g_vals
        added = np.bincount(g_slot, weights=new_i, minlength=self.head.shape[0]).astype(np.int64)
        self.head += added
        np.minimum(self.count + added, self.cap, out=self.count)
        last = np.r_[g_slot[1:] != g_slot[:-1], True]
        self.last_bucket[g_slot[last]] = g_bucket[last]

    def read(self, s: int, start_ns: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
        """Rows of slot ``s`` with ``stamp_ns >= start_ns``, oldest first (copies)."""
        n = int(self.count[s])
        if n == 0:
            return np.zeros(0, np.int64), np.zeros((0, _NF), np.float32)
        idx = (int(self.head[s]) - n + np.arange(n)) % self.cap
        st = self.stamp[s, idx]
        first = int(np.searchsorted(st, start_ns, side="left"))
        return st[first:].copy(), self.vals[s, idx[first:]].copy()

    def oldest(self, s: int) -> int | None:
        n = int(self.count[s])
        if n == 0:
            return None
        return int(self.stamp[s, (int(self.head[s]) - n) % self.cap])


class LiveHub:
    """Latest row, decimated windows and status of every vehicle; a thread-safe pipeline sink.

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
    """

    def __init__(
        self,
        *,
        stale_after_s: float = 3.0,
        offline_after_s: float = 30.0,
        tiers: Sequence[TierSpec] = DEFAULT_TIERS,
        clock_ns: Callable[[], int] = time.time_ns,
        initial_slots: int = 64,
    ) -> None:
        if not 0 < stale_after_s < offline_after_s:
            raise ValueError("need 0 < stale_after_s < offline_after_s")
        if not tiers or any(b.span_s < a.span_s for a, b in itertools.pairwise(tiers)):
            raise ValueError("tiers must be non-empty, finest (shortest span) first")
        self.stale_after_s = float(stale_after_s)
        self.offline_after_s = float(offline_after_s)
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._ids: list[str] = []
        self._slot: dict[str, int] = {}
        self._free: list[int] = []  # slots of forgotten vehicles, reused first
        n = max(1, int(initial_slots))
        self._latest = np.zeros(n, dtype=ESTIMATE_DTYPE)
        self._arrival_ns = np.zeros(n, dtype=np.int64)
        self._has = np.zeros(n, dtype=bool)
        self._tiers = [_Tier(t, n) for t in tiers]
        self._fleet_stamp_ns = 0
        self._version = 0
        self.rows_in = 0
        self.rows_dropped_late = 0
        self._waiters: set[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = set()

    # ------------------------------------------------------------------ writing (pipeline thread)
    @property
    def version(self) -> int:
        """Increments on every batch that added rows."""
        return self._version

    def _slot_of(self, vehicle_id: str) -> int:
        s = self._slot.get(vehicle_id)
        if s is None and self._free:
            s = self._free.pop()
            self._ids[s] = vehicle_id
            self._slot[vehicle_id] = s
        elif s is None:
            s = len(self._ids)
            if s >= self._latest.shape[0]:
                n = 2 * self._latest.shape[0]
                latest = np.zeros(n, dtype=ESTIMATE_DTYPE)
                latest[:s] = self._latest
                self._latest = latest
                self._arrival_ns = np.r_[self._arrival_ns, np.zeros(n - s, np.int64)]
                self._has = np.r_[self._has, np.zeros(n - s, bool)]
                for t in self._tiers:
                    t.grow(n)
            self._ids.append(vehicle_id)
            self._slot[vehicle_id] = s
        return s

    def on_estimates(self, batch: Sequence[tuple[str, np.ndarray]]) -> None:
        """Take new estimate rows: ``[(vehicle_id, rows of ESTIMATE_DTYPE), ...]``.

        Rows not newer than the vehicle's newest row are counted in ``rows_dropped_late`` and
        ignored (the pipeline already reorders by sensor time).
        """
        now_ns = self._clock_ns()
        joined = EstimateBatch.of(batch)
        if not joined:
            return
        with self._lock:
            slots = np.fromiter(
                (self._slot_of(v) for v in joined.ids), dtype=np.int64, count=len(joined)
            )
            rows, slot = joined.grouped(slots)
            stamp = rows["stamp_ns"].astype(np.int64)
            # drop rows not newer than the vehicle's newest row or than their predecessor
            prev = np.where(self._has[slot], self._latest["stamp_ns"][slot], np.iinfo(np.int64).min)
            same = np.r_[False, slot[1:] == slot[:-1]]
            prev = np.where(same, np.r_[np.int64(0), stamp[:-1]], prev)
            keep = stamp > prev
            if not keep.all():  # rare: compare with the running newest stamp of each vehicle
                newest = np.where(self._has[slot], self._latest["stamp_ns"][slot], 0).tolist()
                st_list = stamp.tolist()
                keep_list = [False] * len(st_list)
                cur = newest[0]
                for i, st in enumerate(st_list):
                    if not same[i]:
                        cur = newest[i]
                    if st > cur:
                        keep_list[i] = True
                        cur = st
                keep = np.array(keep_list, dtype=bool)
                self.rows_dropped_late += int((~keep).sum())
                rows, slot, stamp = rows[keep], slot[keep], stamp[keep]
                if rows.shape[0] == 0:
                    return
            vals = np.empty((rows.shape[0], _NF), dtype=np.float32)
            for i, f in enumerate(LIVE_FIELDS):
                vals[:, i] = rows[f]
            for t in self._tiers:
                t.append(slot, stamp, vals)
            last = np.r_[slot[1:] != slot[:-1], True]
            ls = slot[last]
            self._latest[ls] = rows[last]
            self._arrival_ns[ls] = now_ns
            self._has[ls] = True
            self._fleet_stamp_ns = max(self._fleet_stamp_ns, int(stamp.max()))
            self.rows_in += int(rows.shape[0])
            self._version += 1
            waiters = list(self._waiters)
        for loop, ev in waiters:
            try:
                loop.call_soon_threadsafe(ev.set)
            except RuntimeError:  # loop closed: the waiter is gone
                self._waiters.discard((loop, ev))

    def forget(self, vehicle_id: str) -> bool:
        """Drop a vehicle (deleted from the fleet): rows, windows, status. False if unknown."""
        with self._lock:
            s = self._slot.pop(vehicle_id, None)
            if s is None:
                return False
            self._has[s] = False
            for t in self._tiers:
                t.head[s] = 0
                t.count[s] = 0
                t.last_bucket[s] = -1
            self._ids[s] = ""
            self._free.append(s)
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
            return [v for v in self._ids if v in self._slot]

    def __contains__(self, vehicle_id: object) -> bool:
        return vehicle_id in self._slot

    def latest(self, vehicle_id: str) -> tuple[np.ndarray, int] | None:
        """``(row, arrival_ns)`` of the vehicle's newest estimate (0-d structured array) or None."""
        with self._lock:
            s = self._slot.get(vehicle_id)
            if s is None or not self._has[s]:
                return None
            return self._latest[s].copy(), int(self._arrival_ns[s])

    def latest_all(self) -> tuple[list[str], np.ndarray, npt.NDArray[np.int64]]:
        """Ids, newest rows ``(n,)`` and arrival times ``(n,)`` of every vehicle with a row."""
        with self._lock:
            n = len(self._ids)
            has = self._has[:n]
            ids = [v for v, h in zip(self._ids, has, strict=True) if h]
            return ids, self._latest[:n][has].copy(), self._arrival_ns[:n][has].copy()

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

    def status(self, vehicle_id: str, now_ns: int | None = None) -> str | None:
        """``live`` / ``stale`` / ``offline`` for a known vehicle, None for an unknown one."""
        got = self.latest(vehicle_id)
        if got is None:
            return None
        now = self._clock_ns() if now_ns is None else now_ns
        row, arr = got
        age = self._ages(np.array([int(row["stamp_ns"])]), np.array([arr]), now)
        return self._status(age)[0]

    def overview(self, now_ns: int | None = None) -> dict[str, Any]:
        """Compact column-wise state of the whole fleet (the ``fleet`` WebSocket message body).

        Keys: ``ids``, ``status``, ``stamp_ns``, ``age_s``, ``vg_mps``, ``slip_left_pct``,
        ``slip_right_pct``, ``gnss`` and ``flags``, each a list with one entry per vehicle.
        Floats are rounded (speeds to 0.01 m/s, slip to 0.1 %, ages to 0.1 s); NaN becomes null.
        """
        now = self._clock_ns() if now_ns is None else now_ns
        ids, rows, arr = self.latest_all()
        ages = self._ages(rows["stamp_ns"].astype(np.int64), arr, now)
        flags = rows["flags"].astype(np.int64).tolist()
        return {
            "t_ns": now,
            "ids": ids,
            "status": self._status(ages),
            "stamp_ns": rows["stamp_ns"].astype(np.int64).tolist(),
            "age_s": _rounded(ages, 1),
            "vg_mps": _rounded(rows["vg_mps"], 2),
            "slip_left_pct": _rounded(rows["slip_left_pct"], 1),
            "slip_right_pct": _rounded(rows["slip_right_pct"], 1),
            "gnss": [gnss_quality(f) for f in flags],
            "flags": flags,
        }

    def window(
        self,
        vehicle_id: str,
        window_s: float,
        *,
        since_ns: int | None = None,
        max_points: int | None = None,
    ) -> dict[str, Any] | None:
        """Decimated series of one vehicle over the last ``window_s`` seconds (sensor time).

        Picks the finest tier whose span covers the window. With ``since_ns`` only rows with
        ``stamp_ns >= since_ns`` are returned (incremental updates). With ``max_points`` rows are
        further bucketed in time so that at most about that many remain.

        Returns None for an unknown vehicle, else ``{"tier", "bucket_s", "stamp_ns": [...],
        <field>: [...] for field in LIVE_FIELDS}`` (NaN → None).
        """
        with self._lock:
            s = self._slot.get(vehicle_id)
            if s is None or not self._has[s]:
                return None
            newest = int(self._latest["stamp_ns"][s])
            tier = next((t for t in self._tiers if t.spec.span_s >= window_s), self._tiers[-1])
            start = newest - round(window_s * 1e9)
            if since_ns is not None:
                start = max(start, since_ns)
            st, vals = tier.read(s, start)
        if max_points is not None and st.shape[0] > max_points > 0:
            width = max(1, (int(st[-1]) - int(st[0])) // max_points + 1)
            key = (st - st[0]) // width
            _, st, vals = _group_aggregate(key, st, vals)
        out: dict[str, Any] = {
            "tier": tier.spec.name,
            "bucket_s": tier.spec.bucket_s,
            "stamp_ns": st.tolist(),
        }
        for i, f in enumerate(LIVE_FIELDS):
            col = vals[:, i]
            out[f] = [int(x) for x in col] if f == "flags" else _rounded(col, 3)
        return out


def _rounded(a: npt.ArrayLike, digits: int) -> list[float | None]:
    arr = np.round(np.asarray(a, dtype=np.float64), digits)
    return [None if math.isnan(x) else x for x in arr.tolist()]
