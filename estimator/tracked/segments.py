"""Searches in many sorted arrays at once: every vehicle's buffer of one stream laid end to
end (:class:`Segments`), searched with one ``np.searchsorted`` instead of one per vehicle.

Segment ``j``'s values and keys are taken relative to a base of its own and clipped to
``[−H, H]`` (``H`` beyond every key's distance from its base), then moved to ``j·(2H + 2)``:
clipping keeps the order of a value against any key inside the range, and the segments'
ranges do not overlap, so the search of the whole equals each segment's own. When the
ranges would overflow int64 (keys far apart, negative values), each segment is searched
on its own instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from estimator._arrays import FloatArray, IntArray

__all__ = ["Segments"]

Side = Literal["left", "right"]
_LIMIT = 1 << 61


class Segments:
    """``n`` non-decreasing int64 arrays end to end: ``values (N,)``, ``starts (n + 1,)``
    (segment ``j`` is ``values[starts[j]:starts[j + 1]]``)."""

    __slots__ = ("negative", "starts", "value_seg", "values")

    def __init__(self, parts: Sequence[IntArray]) -> None:
        self.values: IntArray = np.concatenate([np.zeros(0, dtype=np.int64), *parts])
        sizes = np.array([p.size for p in parts], dtype=np.int64)
        self.starts: IntArray = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        #: each value's segment ``(N,)`` and whether any value is negative, shared by searches
        self.value_seg: IntArray = np.repeat(np.arange(len(parts), dtype=np.int64), sizes)
        self.negative = bool(self.values.size and self.values.min() < 0)

    @property
    def last(self) -> IntArray:
        """Index (global) of each segment's last value; ``starts[j] − 1`` when it is empty."""
        return self.starts[1:] - 1

    def search(self, seg: IntArray, keys: IntArray, side: Side) -> IntArray:
        """``np.searchsorted(segment(seg[i]), keys[i], side)`` for every key, shape ``(m,)``
        (an index inside the key's segment)."""
        if self.negative:
            return _each(self.values, self.starts, seg, keys, side)
        return _search(self.values, self.starts, self.value_seg, seg, keys, side)

    def search_all(self, seg: IntArray, keys: Sequence[IntArray], side: Side) -> list[IntArray]:
        """:meth:`search` of each array of ``keys`` (all with ``seg``), in one search."""
        found = self.search(np.tile(seg, len(keys)), np.concatenate(keys), side)
        return np.split(found, len(keys))

    def search_float_all(
        self, seg: IntArray, keys: Sequence[FloatArray], side: Side
    ) -> list[IntArray]:
        """:meth:`search_float` of each array of ``keys`` (all with ``seg``), in one search."""
        found = self.search_float(np.tile(seg, len(keys)), np.concatenate(keys), side)
        return np.split(found, len(keys))

    def search_float(self, seg: IntArray, keys: FloatArray, side: Side) -> IntArray:
        """As :meth:`search` with float keys, the values compared as float64 (what
        ``np.searchsorted`` of an int64 array with float keys does)."""
        as_float = self.values.astype(np.float64)
        if np.signbit(as_float).any() or np.signbit(keys).any() or not np.isfinite(keys).all():
            return _each(as_float, self.starts, seg, keys, side)
        # a non-negative float64's bits, read as int64, are in the float's order
        as_int = as_float.view(np.int64)
        return _search(as_int, self.starts, self.value_seg, seg, keys.view(np.int64), side)


def _search(
    values: IntArray,
    starts: IntArray,
    value_seg: IntArray,
    seg: IntArray,
    keys: IntArray,
    side: Side,
) -> IntArray:
    """The segmented search of non-negative ``values`` (``value_seg`` each one's segment)."""
    n = starts.size - 1
    if keys.size == 0:
        return np.zeros(0, dtype=np.int64)
    base = np.zeros(n, dtype=np.int64)
    base[seg] = keys  # any key of a segment will do as its base
    if keys.min() < 0:
        return _each(values, starts, seg, keys, side)
    rel = keys - base[seg]
    half = int(np.abs(rel).max()) + 1
    width = 2 * half + 2
    if half >= _LIMIT or n * width >= _LIMIT:
        return _each(values, starts, seg, keys, side)
    shifted = np.minimum(np.maximum(values - base[value_seg], -half), half) + value_seg * width
    found = np.searchsorted(shifted, rel + seg * width, side=side)
    return found - starts[seg]


def _each(
    values: IntArray | FloatArray,
    starts: IntArray,
    seg: IntArray,
    keys: IntArray | FloatArray,
    side: Side,
) -> IntArray:
    """The same, one segment at a time."""
    out = np.zeros(keys.size, dtype=np.int64)
    for j in np.unique(seg).tolist():
        mine = seg == j
        out[mine] = np.searchsorted(values[starts[j] : starts[j + 1]], keys[mine], side=side)
    return out
