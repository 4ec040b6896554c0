"""The slot bank: encoder edges of many wheels in shared arrays, queried in one vectorised fit.

A :class:`WheelBank` keeps the edges of thousands of wheels (one ring per wheel), queues pushes
and answers a query of any set of wheels, tooth calibration included, in a fixed number of numpy
calls (the fit of :func:`estimator.wheel_speed.methods.omega_at`, row-wise). A fleet front end
holds slot indices and calls :meth:`WheelBank.push` / :meth:`WheelBank.query` directly (arrays,
no per-wheel objects); :class:`~estimator.wheel_speed.tracker.WheelTracker` is one slot of a
bank.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import sliding_window_view

from estimator._arrays import FloatArray, IntArray, as_stamps
from estimator._slots import grow_slot_array
from estimator.wheel_speed.methods import (
    _SPLIT_MIN_ROWS,
    WheelSpeedConfig,
    WheelSpeedResult,
    _fit_mask,
    _quadratic_intercept,
    _row_sum,
    _speed_from_window,
    _split_by_width,
    _tooth,
    _unknown,
)

__all__ = ["WheelBank"]

_NS = 1e-9
_NO_ORIGIN = np.iinfo(np.int64).min
"""``_cal_origin`` of a slot that has had no edge."""

_ARENA = (
    ("_stamp", np.int64),
    ("_angle", np.float64),
    ("_dslot", np.int64),
    ("_corr", np.float64),
)
"""The per-edge arrays of a :class:`WheelBank` (attribute name, dtype)."""

_MIN_SEGMENT = 64
"""Smallest per-wheel ring (edges); rings are powers of two."""


class WheelBank:
    """Encoder edges of many wheels in shared arrays: pushes are queued, queries vectorised.

    Each wheel is a *slot* (:meth:`add` returns its index). Its held edges live in a ring, a
    power-of-two segment of two flat arrays (times, cumulative angles) shared by all slots;
    a ring that fills up moves to a larger one at the end, and the arrays are compacted when
    half of them is abandoned rings. Per-slot state (ring place, calibration, trimming) is in
    arrays indexed by slot, so a query of any set of slots costs a fixed number of numpy
    calls, whatever the number of wheels.

    :meth:`push` only checks time order (skipped edges are counted at once, as
    :class:`WheelTracker` promises) and queues the batch; the queue is written into the rings,
    angles included, by the next query (or any read of held state) in one pass.

    A wheel's results do not depend on which bank holds it or how queries are batched: the
    same edges are held and trimmed, the same tooth calibration runs at the same grid instants.

    Parameters
    ----------
    config : WheelSpeedConfig
        Shared by every slot.
    """

    # per-slot state, grown by _alloc_slots
    _base: IntArray
    _mask: IntArray
    _head: IntArray
    _count: IntArray
    _last_angle: FloatArray
    _angle_before: FloatArray
    _signed: npt.NDArray[np.bool_]
    _cal_from: IntArray
    _cal_upto: IntArray
    _cal_origin: IntArray
    _calibrated: IntArray
    _angle_var: FloatArray
    _delta: FloatArray

    def __init__(self, config: WheelSpeedConfig) -> None:
        self.config = config
        self._step_rad = 2.0 * np.pi / config.teeth_per_rev
        self._w_ns = round(config.window_s * 1e9)
        self._period_ns = round(config.calibration_period_s * 1e9)
        self._prior_var = (config.angle_noise_rel * self._step_rad) ** 2
        self._slots = 0  # high-water mark
        self._free: list[int] = []
        self._alloc_slots(16)
        self._stamp = np.zeros(0, dtype=np.int64)  # the rings
        self._angle = np.zeros(0, dtype=np.float64)
        self._dslot = np.zeros(0, dtype=np.int64)  # index of the edge's tooth in _delta.flat
        self._corr = np.zeros(0, dtype=np.float64)  # angle with the tooth correction in force
        self._used = 0  # arena elements handed out
        self._abandoned = 0  # arena elements of rings that moved
        self.compactions = 0
        """Times the rings were copied into fresh arrays (diagnostics)."""
        # push queue (Python lists: a push costs a few list appends)
        self._q_slot: list[int] = []
        self._q_stamp: list[IntArray] = []
        self._q_dir: list[tuple[int, npt.NDArray[np.int8]]] = []  # (batch number, directions)
        self._q_len: list[int] = []
        self._floor_ns: list[int] = []  # newest accepted stamp per slot (time-order check)
        self._removed: list[int] = []  # slots removed, to clear at the next flush
        self.skipped: list[int] = []
        """Per slot: edges dropped because they went back in time."""

    # --- slots ---------------------------------------------------------------------------
    def _alloc_slots(self, n: int) -> None:
        i64 = np.int64
        grow_slot_array(self, "_base", n, (), i64(0))  # ring start in the arena
        grow_slot_array(self, "_mask", n, (), i64(0))  # ring size − 1 (0: no ring yet)
        grow_slot_array(self, "_head", n, (), i64(0))  # edge number of the oldest held edge
        grow_slot_array(self, "_count", n, (), i64(0))  # edges ever accepted
        grow_slot_array(self, "_last_angle", n, (), 0.0)  # angle of the newest edge
        grow_slot_array(self, "_angle_before", n, (), 0.0)  # before the oldest held
        grow_slot_array(self, "_signed", n, (), False)
        grow_slot_array(self, "_cal_from", n, (), i64(0))  # next edge number to calibrate on
        grow_slot_array(self, "_cal_upto", n, (), i64(np.iinfo(np.int64).min))  # last instant
        grow_slot_array(self, "_cal_origin", n, (), i64(_NO_ORIGIN))  # first edge: grid origin
        grow_slot_array(self, "_calibrated", n, (), i64(0))
        grow_slot_array(self, "_angle_var", n, (), self._prior_var)  # edge angle noise [rad²]
        grow_slot_array(self, "_delta", n, (self.config.teeth_per_rev,), 0.0)

    def add(self) -> int:
        """A new, empty wheel; returns its slot index."""
        if self._removed:
            self._flush()
        if self._free:
            slot = self._free.pop()
        else:
            slot = self._slots
            self._slots += 1
            if slot >= self._base.shape[0]:
                self._alloc_slots(2 * self._base.shape[0])
            self._floor_ns.append(0)
            self.skipped.append(0)
        self._floor_ns[slot] = np.iinfo(np.int64).min
        self.skipped[slot] = 0
        for arr, value in (
            (self._base, 0),
            (self._mask, 0),
            (self._head, 0),
            (self._count, 0),
            (self._last_angle, 0.0),
            (self._angle_before, 0.0),
            (self._signed, False),
            (self._cal_from, 0),
            (self._cal_upto, np.iinfo(np.int64).min),
            (self._cal_origin, _NO_ORIGIN),
            (self._calibrated, 0),
            (self._angle_var, self._prior_var),
            (self._delta, 0.0),
        ):
            arr[slot] = value
        return slot

    def remove(self, slot: int) -> None:
        """Forget a wheel; its index may be handed out again by :meth:`add`.

        Only noted here (a tracker's finalizer may call this at any allocation, even in the
        middle of another call on the bank); the slot is cleared by the next flush.
        """
        self._removed.append(slot)

    def _clear_removed(self) -> None:
        removed, self._removed = self._removed, []
        for slot in removed:
            self._clear(slot)

    def _clear(self, slot: int) -> None:
        self._abandoned += int(self._mask[slot]) + 1 if self._mask[slot] else 0
        self._mask[slot] = self._base[slot] = 0  # no ring: reads of it land on index 0
        self._head[slot] = self._count[slot] = 0
        self._free.append(slot)

    # --- push ----------------------------------------------------------------------------
    def push(
        self, slot: int, stamp_ns: IntArray, direction: npt.NDArray[np.int8] | None = None
    ) -> int:
        """Queue edges of ``slot`` (see :meth:`WheelTracker.push`); back-in-time ones skipped.

        An edge is kept when it is not earlier than any edge before it (held or in the batch).
        Returns how many of these edges were skipped (also added to ``skipped[slot]``).
        """
        t = as_stamps(stamp_ns)
        tl = t.tolist()
        n = len(tl)
        if n == 0:
            return 0
        if direction is not None:
            self._signed[slot] = True
        floor = self._floor_ns[slot]
        skipped = 0
        if tl[0] < floor or (n > 1 and tl != sorted(tl)):
            prev = np.maximum.accumulate(np.concatenate([[floor], t[:-1]]))
            ok = t >= prev
            kept = int(ok.sum())
            skipped = n - kept
            self.skipped[slot] += skipped
            if kept == 0:
                return skipped
            t = t[ok]
            direction = None if direction is None else np.asarray(direction).reshape(-1)[ok]
            n = kept
            tl = t.tolist()
        self._floor_ns[slot] = tl[-1]
        if self._cal_origin[slot] == _NO_ORIGIN:
            self._cal_origin[slot] = tl[0]
        if direction is not None:
            d = np.asarray(direction).reshape(-1)
            if d.shape[0] != n:
                raise ValueError(f"{d.shape[0]} directions for {n} edges")
            self._q_dir.append((len(self._q_slot), d))
        self._q_slot.append(slot)
        self._q_stamp.append(t)
        self._q_len.append(n)
        return skipped

    def _flush(self) -> None:
        """Write the queued batches into the rings, with their cumulative angles."""
        if not self._q_slot:
            if self._removed:
                self._clear_removed()
            return
        slots = np.array(self._q_slot, dtype=np.int64)
        lens = np.array(self._q_len, dtype=np.int64)
        # usually every slot has one batch queued: no chaining of batches within a slot
        one_each = len(set(self._q_slot)) == len(self._q_slot)
        t = np.concatenate(self._q_stamp)
        d_sum = self._direction_sums(slots, lens, t.shape[0])
        self._q_slot, self._q_stamp, self._q_dir, self._q_len = [], [], [], []
        in_batch, k, total = _batch_counts(lens, d_sum, t.shape[0])
        step = self._step_rad
        cur = self._last_angle
        if one_each:
            start = cur[slots]
            cur[slots] = start + step * total.astype(np.float64)
            earlier = np.zeros_like(lens)
            by_slot = np.argsort(slots)
            touched, new_per_slot = slots[by_slot], lens[by_slot]
        else:
            start, earlier, touched, new_per_slot = self._chain_batches(slots, lens, total)
        angle = np.repeat(start, lens) + step * k.astype(np.float64)
        self._write_edges(slots, lens, t, angle, (earlier, in_batch), (touched, new_per_slot))
        if self._removed:
            self._clear_removed()

    def _direction_sums(self, slots: IntArray, lens: IntArray, n_edges: int) -> IntArray | None:
        """Running sum of the queued edges' directions (±1; +1 without a direction), or None."""
        if not self._q_dir:
            return None
        with_dir = np.zeros(slots.shape[0], dtype=bool)
        with_dir[[i for i, _ in self._q_dir]] = True
        d_all = np.ones(n_edges, dtype=np.int8)
        d_all[np.repeat(with_dir, lens)] = np.concatenate([d for _, d in self._q_dir])
        return np.cumsum(np.where(d_all < 0, -1, 1))

    def _chain_batches(
        self, slots: IntArray, lens: IntArray, total: IntArray
    ) -> tuple[FloatArray, IntArray, IntArray, IntArray]:
        """Start angles and earlier edges of several batches per slot; touched slots, new edges.

        Batches of one slot, in push order: their start angles chain batch after batch, and
        their edges follow the edges of the slot's earlier batches (``earlier``).
        """
        step = self._step_rad
        cur = self._last_angle
        order = np.argsort(slots, kind="stable")
        s_sorted = slots[order]
        first = np.flatnonzero(np.concatenate([[True], s_sorted[1:] != s_sorted[:-1]]))
        group = np.repeat(first, np.diff(np.concatenate([first, [slots.shape[0]]])))
        rank = np.empty_like(slots)
        rank[order] = np.arange(slots.shape[0]) - group
        start = np.empty(slots.shape[0])
        for r in range(int(rank.max()) + 1):
            b = np.flatnonzero(rank == r)
            start[b] = cur[slots[b]]
            cur[slots[b]] = start[b] + step * total[b].astype(np.float64)
        before_sorted = np.cumsum(lens[order]) - lens[order]
        earlier = np.empty_like(lens)
        earlier[order] = before_sorted - before_sorted[group]
        per_slot = np.bincount(slots, weights=lens, minlength=self._slots).astype(np.int64)
        touched = np.flatnonzero(per_slot)
        return start, earlier, touched, per_slot[touched]

    def _write_edges(
        self,
        slots: IntArray,
        lens: IntArray,
        t: IntArray,
        angle: FloatArray,
        place: tuple[IntArray, IntArray],
        new: tuple[IntArray, IntArray],
    ) -> None:
        """Store the edges in the rings (``place``: earlier, in batch; ``new``: per slot)."""
        earlier, in_batch = place
        touched, new_per_slot = new
        # Edge numbers: each slot's new edges follow its held ones, in push order.
        e_slot = np.repeat(slots, lens)
        number = self._count[e_slot] + np.repeat(earlier, lens) + in_batch
        self._fit_rings(touched, new_per_slot)
        self._count[touched] += new_per_slot
        at = self._base[e_slot] + (number & self._mask[e_slot])
        self._stamp[at] = t
        self._angle[at] = angle
        ns = self.config.teeth_per_rev
        dslot = e_slot * ns + _tooth(angle, ns)
        self._dslot[at] = dslot
        self._corr[at] = angle + self._delta.reshape(-1)[dslot]

    # --- rings ---------------------------------------------------------------------------
    def _fit_rings(self, slots: IntArray, extra: IntArray) -> None:
        """Move slots whose held edges plus ``extra`` new ones outgrow their ring.

        First compacts the arena when more of it is abandoned rings than live ones.
        """
        if self._abandoned > (1 << 16):
            live = int((self._mask[: self._slots] + (self._mask[: self._slots] > 0)).sum())
            if self._abandoned > live:
                self._compact()
        held = self._count[slots] - self._head[slots] + extra
        small = held > self._mask[slots] + (self._mask[slots] > 0)
        if not small.any():
            return
        grow = slots[small]
        size = np.maximum(
            _MIN_SEGMENT, 1 << np.ceil(np.log2(np.maximum(2 * held[small], 1))).astype(np.int64)
        )
        self._move(grow, size)

    def _move(self, slots: IntArray, size: IntArray) -> None:
        """Give ``slots`` new rings of ``size`` edges at the arena end, copying held edges."""
        need = self._used + int(size.sum())
        if need > self._stamp.shape[0]:
            cap = max(need, 2 * self._stamp.shape[0], 1 << 12)
            for name, dtype in _ARENA:
                new = np.zeros(cap, dtype=dtype)
                new[: self._used] = getattr(self, name)[: self._used]
                setattr(self, name, new)
        new_base = self._used + np.cumsum(size) - size
        self._used = need
        held = self._count[slots] - self._head[slots]
        had = self._mask[slots] > 0
        n = int(held[had].sum())
        if n:
            hs, hh = slots[had], held[had]
            rel = np.arange(n) - np.repeat(np.cumsum(hh) - hh, hh)
            number = np.repeat(self._head[hs], hh) + rel
            src = np.repeat(self._base[hs], hh) + (number & np.repeat(self._mask[hs], hh))
            dst = np.repeat(new_base[had], hh) + (number & np.repeat(size[had] - 1, hh))
            for name, _ in _ARENA:
                arr = getattr(self, name)
                arr[dst] = arr[src]
        self._abandoned += int((self._mask[slots] + had).sum())
        self._base[slots] = new_base
        self._mask[slots] = size - 1

    def _compact(self) -> None:
        """Copy every live ring into fresh arrays (abandoned rings dropped, rings resized)."""
        slots = np.flatnonzero(self._mask[: self._slots] > 0)
        held = self._count[slots] - self._head[slots]
        size = np.maximum(
            _MIN_SEGMENT, 1 << np.ceil(np.log2(np.maximum(2 * held, 1))).astype(np.int64)
        )
        old = {name: getattr(self, name) for name, _ in _ARENA}
        old_base, old_mask = self._base[slots].copy(), self._mask[slots].copy()
        cap = max(int(size.sum()) * 2, 1 << 12)
        for name, dtype in _ARENA:
            setattr(self, name, np.zeros(cap, dtype=dtype))
        new_base = np.cumsum(size) - size
        n = int(held.sum())
        if n:
            rel = np.arange(n) - np.repeat(np.cumsum(held) - held, held)
            number = np.repeat(self._head[slots], held) + rel
            src = np.repeat(old_base, held) + (number & np.repeat(old_mask, held))
            dst = np.repeat(new_base, held) + (number & np.repeat(size - 1, held))
            for name, _ in _ARENA:
                getattr(self, name)[dst] = old[name][src]
        self._base[slots] = new_base
        self._mask[slots] = size - 1
        self._used = int(size.sum())
        self._abandoned = 0
        self.compactions += 1

    def _at(self, slot: IntArray | np.int64, number: IntArray) -> IntArray:
        """Arena index of edge ``number`` of ``slot`` (shapes broadcast)."""
        return self._base[slot] + (number & self._mask[slot])

    def _search(self, slot: IntArray, lo: IntArray, hi: IntArray, value: IntArray) -> IntArray:
        """First edge number in ``[lo, hi)`` with a time after ``value`` (``hi`` if none).

        Bisection of every row at once (held times are non-decreasing), as many halvings as
        the widest range needs; a row whose range is already empty stays where it is.
        ``slot``, ``lo``, ``hi`` have shape ``(n,)``; ``value`` shape ``(n,)`` or ``(s, n)``
        (``s`` searches of the same rows in one pass; the result has ``value``'s shape).
        """
        base = self._base[slot]
        mask = self._mask[slot]
        width = int((hi - lo).max()) if lo.size else 0
        lo = np.broadcast_to(lo, value.shape)
        hi = np.broadcast_to(hi, value.shape)
        if width <= 0:
            return lo.copy()
        for _ in range(width.bit_length()):
            mid = (lo + hi) >> 1
            after = self._stamp[base + (mid & mask)] > value
            lo = np.where(after, lo, np.minimum(mid + 1, hi))
            hi = np.where(after, mid, hi)
        return lo

    # --- query ---------------------------------------------------------------------------
    def query(self, slots: IntArray, query_ns: IntArray) -> WheelSpeedResult:
        """Speeds of ``slots`` at the times ``query_ns``; trims their history.

        Same rules as :meth:`WheelTracker.query` (times not earlier than the slot's previous
        query; tooth corrections of the last calibration instant at or before each time).

        Parameters
        ----------
        slots : ndarray, shape (n,), int
            Slot indices (a slot may repeat when the times are shared).
        query_ns : ndarray, shape (m,) or (n, m), int64, non-decreasing along m
            The same times for every slot, or each slot's own (vehicles whose ticks lie on
            grids of different phase); then the slots must be distinct.

        Returns
        -------
        WheelSpeedResult
            Arrays of shape ``(n, m)``: row ``i`` is slot ``slots[i]``.
        """
        s = np.asarray(slots, dtype=np.int64).reshape(-1)
        n = s.shape[0]
        # one row per distinct slot for the calibration (a repeated slot shares its times)
        uniq, first = np.unique(s, return_index=True) if n > 1 else (s, np.zeros(1, np.int64))
        q2 = _query_grid(np.asarray(query_ns, dtype=np.int64), n, uniq.shape[0])
        m = q2.shape[1]
        self._flush()
        if n == 0 or m == 0:
            r = _unknown(n * m)
            return WheelSpeedResult(
                r.omega_radps.reshape(n, m), r.std_radps.reshape(n, m), r.method.reshape(n, m)
            )
        omega = np.empty((n, m))
        std = np.empty((n, m))
        method = np.empty((n, m), dtype=np.int8)
        i = 0
        tail: tuple[IntArray, IntArray] | None = None
        while i < m:
            j, due, boundary = self._next_chunk(q2, uniq, first, i, m)
            res, tail = self._query_chunk(s, uniq, first, q2, i, j, due, boundary)
            omega[:, i:j] = res.omega_radps.reshape(n, j - i)
            std[:, i:j] = res.std_radps.reshape(n, j - i)
            method[:, i:j] = res.method.reshape(n, j - i)
            i = j
        assert tail is not None
        self._trim(s, *tail)
        return WheelSpeedResult(omega, std, method)

    def _next_chunk(
        self, q2: IntArray, uniq: IntArray, first: IntArray, i: int, m: int
    ) -> tuple[int, npt.NDArray[np.bool_] | None, IntArray | None]:
        """End ``j`` of the chunk of columns from ``i``, the rows due a calibration, boundaries."""
        if not self.config.tooth_calibration:
            return m, None, None
        # each row calibrates on its own grid boundaries; a chunk of columns ends where
        # any row reaches its next boundary (other rows are not due there)
        origin = self._cal_origin[uniq]
        boundary = self._boundary(q2[first, i], origin)
        due = (boundary > self._cal_upto[uniq]) & (origin != _NO_ORIGIN)
        j = int((q2[first] < (boundary + self._period_ns)[:, None]).sum(axis=1).min())
        return j, (due if due.any() else None), boundary

    def _query_chunk(
        self,
        s: IntArray,
        uniq: IntArray,
        first: IntArray,
        q2: IntArray,
        i: int,
        j: int,
        due: npt.NDArray[np.bool_] | None,
        boundary: IntArray | None,
    ) -> tuple[WheelSpeedResult, tuple[IntArray, IntArray]]:
        """Columns ``i:j`` of :meth:`query`: the due calibrations, then the fits."""
        # The edges each fit and calibration needs, found in one bisection over the held
        # edges (a calibration moves no edge): the first after each query time, after it
        # − window_s (at or before the former) and, when a calibration is due, after the
        # slot's grid boundary.
        nq = j - i
        rs = np.repeat(s, nq)
        q = q2[:, i:j].reshape(-1)
        times = [q, q - self._w_ns]
        if due is not None:
            times.append(np.repeat(self._boundary(q2[:, i], self._cal_origin[s]), nq))
        after = self._search(rs, self._head[rs], self._count[rs], np.stack(times))
        if due is not None and boundary is not None:
            self._calibrate(uniq[due], after[2][first[due] * nq] - 1)
            self._cal_upto[uniq[due]] = boundary[due]
        return self._fit(rs, q, nq, after[0], after[1])

    def _corrected(self, at: IntArray) -> FloatArray:
        """Angles of the edges at arena indices ``at``, with their slot's tooth corrections."""
        return self._corr[at]

    def _recorrect(self, slots: IntArray) -> None:
        """Refresh the corrected angles of the held edges of ``slots`` (their corrections moved)."""
        held = self._count[slots] - self._head[slots]
        n = int(held.sum())
        if n == 0:
            return
        number = np.repeat(self._head[slots] - (np.cumsum(held) - held), held) + np.arange(n)
        at = self._at(np.repeat(slots, held), number)
        self._corr[at] = self._angle[at] + self._delta.reshape(-1)[self._dslot[at]]

    def _fit(
        self, rs: IntArray, q: IntArray, nq: int, end: IntArray, first_in: IntArray
    ) -> tuple[WheelSpeedResult, tuple[IntArray, IntArray]]:
        """:func:`omega_at` of slot ``rs[r]`` at time ``q[r]`` for every row ``r`` (shape
        ``(n·nq,)``: ``nq`` times of each slot in turn).

        ``end`` and ``first_in`` are each row's first edge after ``q`` and after
        ``q − window_s`` (edge numbers, :meth:`_search`). Also returns, per slot, the last edge
        at or before its last time and the first edge after that time − ``window_s``, for
        trimming.
        """
        cfg = self.config
        head = self._head[rs]
        last = end - 1
        tail = (last[nq - 1 :: nq], first_in[nq - 1 :: nq])
        has = last >= head
        if not has.any():
            return _unknown(rs.shape[0]), tail
        n_win = np.maximum(last - first_in + 1, 0)
        # Rows are fitted in (at most) two groups by how many edges they may use, so slow
        # wheels do not pay for the columns of the fastest one.
        groups = None
        if rs.shape[0] >= _SPLIT_MIN_ROWS:
            k = np.minimum(np.clip(n_win, cfg.min_edges, cfg.max_edges), end - head)
            groups = _split_by_width(np.where(has, k, 0))
        if groups is None or len(groups) == 1:
            res = self._fit_rows(rs, q, head, last, first_in, n_win, has)
            return res, tail
        m = rs.shape[0]
        omega, std = np.empty(m), np.empty(m)
        method = np.empty(m, dtype=np.int8)
        for g in groups:
            r = self._fit_rows(rs[g], q[g], head[g], last[g], first_in[g], n_win[g], has[g])
            omega[g], std[g], method[g] = r.omega_radps, r.std_radps, r.method
        return WheelSpeedResult(omega, std, method), tail

    def _fit_rows(
        self,
        rs: IntArray,
        q: IntArray,
        head: IntArray,
        last: IntArray,
        first_in: IntArray,
        n_win: IntArray,
        has: npt.NDArray[np.bool_],
    ) -> WheelSpeedResult:
        """Gather each row's edges and fit them (:func:`_speed_from_window`)."""
        cfg = self.config
        if not has.any():
            return _unknown(rs.shape[0])
        w, offs = _fit_mask(last, head, n_win, has, cfg)
        last_c = np.maximum(last, head)
        number = np.maximum(last_c[:, None] - offs[None, :], head[:, None])
        at = self._at(rs[:, None], number)
        stamp = self._stamp[at]  # column 0: the last edge, 1: the one before it (or head)
        tau_s = (stamp - q[:, None]).astype(np.float64) * _NS
        pos = self._corrected(at)
        p = pos - pos[:, :1]
        freq = has & (n_win >= cfg.frequency_min_count)
        freq_omega = None
        if freq.any():
            prior = self._corrected(self._at(rs, np.maximum(first_in - 1, head)))
            before = np.where(first_in > head, prior, self._angle_before[rs])
            freq_omega = (pos[:, 0] - before) / cfg.window_s
        return _speed_from_window(
            q,
            tau_s,
            p,
            w,
            has,
            freq,
            freq_omega,
            stamp[:, 0],
            stamp[:, 1],
            last - 1 >= head,
            cfg,
            self._signed[rs],
            self._angle_var[rs],
        )

    def _boundary(self, q: IntArray, origin: IntArray) -> IntArray:
        """The calibration instant in force at ``q``: the last ``origin + k·period`` at or
        before it, ``origin`` the slot's first edge (the grid moves with the data, so rows do
        not depend on the absolute clock); ``q`` itself where the slot has had no edge."""
        period = self._period_ns
        rel = q - np.where(origin == _NO_ORIGIN, 0, origin)
        return np.where(origin == _NO_ORIGIN, q, q - rel + (rel // period) * period)

    def _trim(self, s: IntArray, last: IntArray, first_in: IntArray) -> None:
        """Drop edges no later query can use."""
        cfg = self.config
        head = self._head[s]
        rel_last = last - head
        rel_old = first_in - 1 - head
        keep = np.maximum(0, np.minimum(rel_last - cfg.max_edges - 1, rel_old - 1))
        if cfg.tooth_calibration:
            keep = np.minimum(
                keep, np.maximum(self._cal_from[s] - head - cfg.calibration_half_window - 1, 0)
            )
        cut = (keep > 0) & (self._count[s] > head)
        if not cut.any():
            return
        cs, new_head = s[cut], head[cut] + keep[cut]
        self._angle_before[cs] = self._angle[self._at(cs, new_head - 1)]
        self._head[cs] = new_head

    def _calibrate(self, slots: IntArray, last: IntArray) -> None:
        """Learn tooth corrections of ``slots`` (distinct, ascending) from edges with a full
        window at or before their calibration instant ``t_ns``; ``last`` is the number of each
        slot's last edge at or before it (``head − 1`` if none).

        For each slot: the edges not yet used that have ``calibration_half_window`` (``h``)
        neighbours on both sides at or before ``t_ns``; per edge, a quadratic fit of its ``2h``
        neighbours' angles against time (corrected with the slot's current corrections, the
        edge itself left out), and the tooth's correction moves by ``calibration_gain`` of the
        edge's residual; corrections are then made zero-mean again. The edges of a slot are
        read once as one run ``lo − h … hi + h``; the windows are rows ``(M, 2h)`` over it.
        """
        cfg = self.config
        h = cfg.calibration_half_window
        head = self._head[slots]
        lo = np.maximum(self._cal_from[slots], head + h)
        hi = last - h
        go = hi >= lo
        if not go.any():
            return
        slots, lo, hi = slots[go], lo[go], hi[go]
        self._cal_from[slots] = hi + 1
        n_c = hi - lo + 1  # centres per slot
        at, stamp, raw, ang, run_first = self._read_runs(slots, lo, n_c, h)
        # window rows: centre index in the run arrays, neighbours −h … −1, 1 … h
        m = int(n_c.sum())
        row_slot = np.repeat(slots, n_c)
        centre = np.repeat(run_first + h - (np.cumsum(n_c) - n_c), n_c) + np.arange(m)
        ok = self._usable_windows(stamp, raw, centre, row_slot, h)
        any_ok = np.zeros(self._slots, dtype=bool)
        any_ok[row_slot[ok]] = True
        if not ok.any():
            return
        centre, row_slot = centre[ok], row_slot[ok]
        resid = _centre_residuals(stamp, ang, centre, h)
        pitch = 2 * np.pi / cfg.teeth_per_rev
        good = np.abs(resid) < 0.3 * pitch
        flat = self._delta.reshape(-1)
        np.add.at(flat, self._dslot[at[centre[good]]], -cfg.calibration_gain * resid[good])
        upd = np.flatnonzero(any_ok)
        self._delta[upd] -= (_row_sum(self._delta[upd]) / cfg.teeth_per_rev)[:, None]
        self._recorrect(upd)
        np.add.at(self._calibrated, row_slot[good], 1)
        self._learn_angle_noise(row_slot[good], resid[good])

    def _read_runs(
        self, slots: IntArray, lo: IntArray, n_c: IntArray, h: int
    ) -> tuple[IntArray, IntArray, FloatArray, FloatArray, IntArray]:
        """Ring places, stamps, raw and corrected angles of the runs ``lo − h … hi + h``."""
        run_len = n_c + 2 * h
        run_first = np.cumsum(run_len) - run_len
        run_slot = np.repeat(slots, run_len)
        n_run = int(run_len.sum())
        number = np.repeat(lo - h - run_first, run_len) + np.arange(n_run)
        at = self._at(run_slot, number)
        return at, self._stamp[at], self._angle[at], self._corr[at], run_first

    def _usable_windows(
        self, stamp: IntArray, raw: FloatArray, centre: IntArray, row_slot: IntArray, h: int
    ) -> npt.NDArray[np.bool_]:
        """Windows without an interval ≥ ``stop_timeout_s``, of span > 0, one way if signed."""
        gap_ns = np.diff(stamp)
        long_gap = np.concatenate([[0], np.cumsum(gap_ns * _NS >= self.config.stop_timeout_s)])
        ok = long_gap[centre + h] == long_gap[centre - h]
        ok &= stamp[centre + h] > stamp[centre - h]  # span > 0
        signed = self._signed[row_slot]
        if signed.any():
            step = np.diff(raw)
            up = np.concatenate([[0], np.cumsum(step > 0)])
            down = np.concatenate([[0], np.cumsum(step < 0)])
            n_up = up[centre + h] - up[centre - h]
            n_down = down[centre + h] - down[centre - h]
            ok &= (n_up == 2 * h) | (n_down == 2 * h) | ~signed
        return ok

    def _learn_angle_noise(self, row_slot: IntArray, resid: FloatArray) -> None:
        """Move each slot's edge angle variance toward its calibration residuals (in place).

        ``resid`` are this calibration's residuals (before their correction), ``row_slot``
        their slots (non-decreasing). The residual of an edge against its neighbours' fit is
        the error a fit would see with the corrections then in force; its mean square over the
        ``M`` new residuals of a slot enters an exponential mean with a memory of one revolution
        (``teeth_per_rev`` edges): ``v ← (1 − β)·v + β·mean(r²)``, ``β = 1 − (1 − 1/Ns)^M``.
        (The residual also carries the neighbours' fit error, a few percent of its variance
        with the default window: the floor errs on the safe side.)
        """
        if resid.shape[0] == 0:
            return
        # row_slot is non-decreasing (from _calibrate): its runs are the slots
        new = np.ones(row_slot.shape[0], dtype=bool)
        new[1:] = row_slot[1:] != row_slot[:-1]
        slots = row_slot[new]
        run = np.cumsum(new) - 1
        n = np.bincount(run)
        mean_sq = np.bincount(run, weights=resid * resid) / n
        beta = 1.0 - (1.0 - 1.0 / self.config.teeth_per_rev) ** n
        self._angle_var[slots] += beta * (mean_sq - self._angle_var[slots])

    # --- per-slot views ------------------------------------------------------------------
    def held_stamp_ns(self, slot: int) -> IntArray:
        """Times of the edges ``slot`` holds, shape ``(n,)`` (pending pushes included)."""
        self._flush()
        number = np.arange(self._head[slot], self._count[slot])
        if number.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        return self._stamp[self._at(np.int64(slot), number)]

    def tooth_correction_rad(self, slot: int) -> FloatArray:
        """Learnt angle correction per tooth of ``slot``, shape ``(teeth_per_rev,)``."""
        self._flush()
        return self._delta[slot].copy()

    def calibrated_edges(self, slot: int) -> int:
        """Edges the tooth calibration of ``slot`` has learnt from."""
        return int(self._calibrated[slot])

    def angle_noise_rad(self, slot: int) -> float:
        """1-sigma angle error of one edge of ``slot`` that its fits are floored by [rad]."""
        self._flush()
        return math.sqrt(float(self._angle_var[slot]))


def _query_grid(q: IntArray, n: int, n_distinct: int) -> IntArray:
    """The query times as ``(n, m)``: each slot's own, or the shared row broadcast."""
    if q.ndim == 2:
        if q.shape[0] != n:
            raise ValueError(f"query_ns has {q.shape[0]} rows for {n} slots")
        if n_distinct != n:
            raise ValueError("slots must be distinct when each has its own times")
        return q
    return np.broadcast_to(q.reshape(1, -1), (n, q.size))


def _batch_counts(
    lens: IntArray, d_sum: IntArray | None, n_edges: int
) -> tuple[IntArray, IntArray, IntArray]:
    """Each edge's index in its batch, its count ``k`` (signed with direction), batch totals.

    The angle is start + step·k, as ``edge_angles`` computes it batch by batch.
    """
    ends = np.cumsum(lens)
    starts = ends - lens
    in_batch = np.arange(n_edges) - np.repeat(starts, lens)  # edge index within its batch
    if d_sum is None:
        return in_batch, in_batch + 1, lens
    before = np.concatenate([[0], d_sum])[starts]
    return in_batch, d_sum - np.repeat(before, lens), d_sum[ends - 1] - before


def _centre_residuals(stamp: IntArray, ang: FloatArray, centre: IntArray, h: int) -> FloatArray:
    """Centre edge's angle minus the quadratic fit of its ``2h`` neighbours, per window.

    Windows as rows (M, 2h + 1) of the run; the centre column is exactly 0 in both time and
    angle, so it adds nothing to the fit: the centre edge is left out (its own error must not
    pull the fit).
    """
    t_run = (stamp - stamp[0]).astype(np.float64) * _NS
    win_t = sliding_window_view(t_run, 2 * h + 1)[centre - h]
    win_a = sliding_window_view(ang, 2 * h + 1)[centre - h]
    ts = win_t - win_t[:, h : h + 1]
    u = ts / (ts[:, -1] - ts[:, 0])[:, None]
    a = win_a - win_a[:, h : h + 1]
    c0 = _quadratic_intercept(u, a, 2 * h)
    return -c0  # centre angle (0 by construction) minus the fit at the centre
