"""Array helpers shared by the fleet front ends and engines: the same results as their numpy
counterparts in fewer array calls (each numpy call costs microseconds on the small arrays of
one assembly, whatever their size), and the array type names they annotate with."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "BoolArray",
    "CArray",
    "FloatArray",
    "IntArray",
    "as_rows",
    "as_stamps",
    "due_ticks",
    "nan_to_num",
    "seg_cumsum",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
CArray = npt.NDArray[np.complexfloating[Any, Any]]

_F64_MAX = float(np.finfo(np.float64).max)
_I8 = np.dtype(np.int64)
_F8 = np.dtype(np.float64)


def as_stamps(t: object) -> npt.NDArray[np.int64]:
    """``np.asarray(t, dtype=np.int64).reshape(-1)``; an array that is that already (what the
    decoder hands over) is returned as it is, without the two calls (~0.35 µs a packet)."""
    if type(t) is np.ndarray and t.dtype == _I8 and t.ndim == 1:
        return t
    return np.asarray(t, dtype=np.int64).reshape(-1)


def as_rows(a: object, width: int) -> npt.NDArray[np.float64]:
    """``np.asarray(a, dtype=np.float64).reshape(-1, width)``, returning a float array of
    shape ``(n, width)`` as it is."""
    if type(a) is np.ndarray and a.dtype == _F8 and a.ndim == 2 and a.shape[1] == width:
        return a
    return np.asarray(a, dtype=np.float64).reshape(-1, width)


def nan_to_num(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``np.nan_to_num(x)`` of a float array (NaN → 0, ±inf → ± the largest float) in three
    array calls instead of its dozen."""
    return np.where(np.isfinite(x), x, np.where(np.isnan(x), 0.0, np.copysign(_F64_MAX, x)))


def seg_cumsum(
    x: npt.NDArray[np.float64], start_of: npt.NDArray[np.int64]
) -> npt.NDArray[np.float64]:
    """Cumulative sum of ``x`` along its first axis restarting at each segment; ``start_of[i]``
    is the index where element ``i``'s segment starts (``c − (c − x)[start_of]``, the gather
    by ``np.take``: half the work of indexing with an array)."""
    c = np.cumsum(x, axis=0)
    return c - np.take(c - x, start_of, axis=0)


def due_ticks(next_ns: int | None, covered_ns: IntArray, tick_ns: int, until_ns: int) -> IntArray:
    """The ticks ``next_ns, next_ns + tick_ns, …`` at or before both ``until_ns`` and the last
    stamp of ``covered_ns`` (the input that must cover a tick, e.g. the IMU), oldest first;
    shape ``(m,)``, empty before the grid is set (``next_ns`` None) or without input."""
    if next_ns is None or not covered_ns.size:
        return np.zeros(0, dtype=np.int64)
    last = min(until_ns, int(covered_ns[-1]))
    if last < next_ns:
        return np.zeros(0, dtype=np.int64)
    n = (last - next_ns) // tick_ns + 1
    return next_ns + tick_ns * np.arange(n, dtype=np.int64)
