"""Speed from edge times: the odometer's and each sprocket's (period method over a window).

Over the last ``max_edges`` edges within ``window`` before a tick ``t``, ``n`` edges spanning
``Δ`` give ``v = (n − 1)·pitch/Δ``, the mean over ``[first, last]`` (its centre is returned, so
a caller compares it with its own speed *there*, not at ``t``: the lag Eq. 6 of the source
leaves out). The next edge not having come by ``t`` bounds the mean speed over ``[first, t]``
by ``n·pitch/(t − first)`` and over ``[last, t]`` by ``pitch/(t − last)`` (the one a track
being braked meets first: its edges stop coming; taken once an edge is a quarter of a
period overdue, :data:`OVERDUE`, so a tooth's position error never trips it); the smallest
is taken. Fewer than two edges in the
window: the last two edges, until the first of them is older than ``hold`` *and* the next
edge is overdue against their own period (a crawl whose period exceeds the window reads on
until its next edge is late, not 0 while that edge is still due: one sprocket read at 0
beside the other is a pivot), then 0. Edges are forward only (a quadrature direction is
not used).
"""

from __future__ import annotations

import numpy as np

from estimator._arrays import FloatArray, IntArray

__all__ = [
    "OVERDUE",
    "EdgeBuffer",
    "edge_speed",
    "edge_speed_at",
    "span_speed",
    "span_speed_at",
]

OVERDUE = 1.25
"""An edge this many periods late bounds the speed by ``OVERDUE·pitch/(t − last)``."""


def edge_speed(
    stamps_ns: IntArray,
    ticks_ns: IntArray,
    pitch_m: float,
    window_ns: int,
    max_edges: int,
    hold_ns: int,
) -> tuple[FloatArray, FloatArray]:
    """Speed (m/s) and the centre of its span (ns, as float) at each tick; shapes ``(m,)``."""
    s = stamps_ns
    hi = np.searchsorted(s, ticks_ns, side="right")
    lo = np.searchsorted(s, ticks_ns - window_ns, side="right")
    return edge_speed_at(
        s, np.zeros(1, dtype=np.int64), hi, lo, ticks_ns, pitch_m, max_edges, hold_ns
    )


def edge_speed_at(
    s: IntArray,
    base: IntArray,
    hi: IntArray,
    lo_window: IntArray,
    ticks_ns: IntArray,
    pitch_m: float | FloatArray,
    max_edges: int,
    hold_ns: int,
) -> tuple[FloatArray, FloatArray]:
    """:func:`edge_speed` from its searches: ``hi`` and ``lo_window`` index the ticks' own
    stamps (``s[base:]``, ``base`` one per tick or one for all; many vehicles' stamps end to
    end); ``pitch_m`` a float or one per tick."""
    if s.size == 0:
        return np.zeros(ticks_ns.size), ticks_ns.astype(np.float64)
    lo = np.maximum(lo_window, hi - max_edges)
    short = (hi - lo) < 2
    lo = np.where(short, hi - 2, lo)
    ok = lo >= 0
    lo_c, hi_c = np.maximum(lo, 0), np.maximum(hi - 1, 0)
    top = s.size - 1  # an empty vehicle's reads land elsewhere and are not used (ok False)
    first = s[np.minimum(base + lo_c, top)].astype(np.float64)
    last = s[np.minimum(base + hi_c, top)].astype(np.float64)
    span = last - first
    n = (hi - lo - 1).astype(np.float64)
    tick = ticks_ns.astype(np.float64)
    ok &= ~(short & (tick - first > hold_ns) & (tick - last > OVERDUE * span))
    with np.errstate(divide="ignore", invalid="ignore"):
        speed = np.where(ok & (span > 0), n * pitch_m * 1e9 / span, 0.0)
        bound = (n + 1.0) * pitch_m * 1e9 / np.maximum(tick - first, 1.0)
        gap_bound = OVERDUE * pitch_m * 1e9 / np.maximum(tick - last, 1.0)
    slowed = ok & (bound < speed)
    speed = np.where(slowed, bound, speed)
    centre = np.where(ok & (span > 0), 0.5 * (first + last), tick)
    centre = np.where(slowed, 0.5 * (first + tick), centre)
    stopping = ok & (gap_bound < speed)
    speed = np.where(stopping, gap_bound, speed)
    centre = np.where(stopping, 0.5 * (last + tick), centre)
    return speed, centre


def span_speed(
    stamps_ns: IntArray, start_ns: FloatArray, end_ns: FloatArray, pitch_m: float
) -> FloatArray:
    """Mean speed over each span ``[start, end]`` from the edges inside it (period method),
    NaN where fewer than two edges fall in it; shapes ``(m,)``."""
    lo = np.searchsorted(stamps_ns, start_ns, side="left")
    hi = np.searchsorted(stamps_ns, end_ns, side="right")
    return span_speed_at(stamps_ns, np.zeros(1, dtype=np.int64), lo, hi, pitch_m)


def span_speed_at(
    s: IntArray, base: IntArray, lo: IntArray, hi: IntArray, pitch_m: float | FloatArray
) -> FloatArray:
    """:func:`span_speed` from its searches (``lo``, ``hi`` index ``s[base:]``, as in
    :func:`edge_speed_at`)."""
    ok = hi - lo >= 2
    if s.size == 0:
        return np.full(lo.shape, np.nan)
    top = s.size - 1
    first = s[np.minimum(base + lo, top)].astype(np.float64)
    last = s[np.maximum(base + hi - 1, 0)].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        speed = (hi - lo - 1) * pitch_m * 1e9 / (last - first)
    return np.where(ok & (last > first), speed, np.nan)


class EdgeBuffer:
    """Edge times of one stream, kept for the windows still ahead; refuses edges that go
    backwards (counted in :attr:`backwards`, never used)."""

    __slots__ = ("backwards", "last_edge_ns", "stamps")

    def __init__(self) -> None:
        self.stamps: IntArray = np.zeros(0, dtype=np.int64)
        self.backwards = 0
        self.last_edge_ns: int | None = None

    def push(self, stamps_ns: IntArray) -> None:
        t = np.asarray(stamps_ns, dtype=np.int64)
        if t.size == 0:
            return
        floor = self.stamps[-1] if self.stamps.size else np.iinfo(np.int64).min
        running = np.maximum.accumulate(np.concatenate([[floor], t]))[:-1]
        keep = t >= running
        self.backwards += int(t.size - keep.sum())
        self.stamps = np.concatenate([self.stamps, t[keep]])
        if self.stamps.size:
            self.last_edge_ns = int(self.stamps[-1])

    def prune(self, before_ns: int) -> None:
        """Forget edges older than ``before_ns`` (two at least are kept)."""
        self.prune_at(int(np.searchsorted(self.stamps, before_ns)))

    def prune_at(self, older: int) -> None:
        """Forget the ``older`` first edges (two at least are kept)."""
        cut = min(older, max(self.stamps.size - 2, 0))
        if cut:
            self.stamps = self.stamps[cut:]
