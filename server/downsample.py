"""Peak-keeping decimation of estimate series (pure numpy).

Method (min/max per time bucket)
--------------------------------
The time range ``[start_ns, end_ns)`` is cut into ``B = max_points // 2`` buckets of equal width
``w = ceil((end_ns - start_ns) / B)``; bucket ``k`` holds the rows with
``start_ns + k·w <= stamp_ns < start_ns + (k+1)·w``. Every non-empty bucket becomes at most two
output rows:

* for each float field, one row carries the bucket's minimum and the other its maximum, in the
  order they occurred (the extreme seen first goes in the first row), so a spike and a dip both
  survive and a line drawn through the points has the right shape;
* NaN is ignored (a bucket whose values are all NaN gives NaN);
* ``stamp_ns`` of the two rows is the first and the last stamp of the bucket;
* ``flags`` of both rows is the bitwise OR of the bucket's flags (any ``DEGRADED`` row shows);
* a bucket holding one row gives that row unchanged.

So the output has at most ``max_points`` rows, every column's envelope (min and max per bucket)
is exact, but one output row mixes values of different input rows; use full rate
(``max_points`` 0) where rows must be read as a whole. Empty buckets give no rows, so gaps in the
data stay gaps.

Buckets are anchored at ``start_ns``, so decimating ``[a, c)`` equals concatenating the
decimation of ``[a, b)`` and ``[b, c)`` when ``b - a`` is a multiple of the bucket width; the
server uses this to decimate long ranges chunk by chunk (:func:`bucket_width_ns`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["bucket_width_ns", "downsample_minmax"]


def bucket_width_ns(start_ns: int, end_ns: int, max_points: int) -> int:
    """Width of one bucket for ``max_points`` output rows over ``[start_ns, end_ns)``, >= 1 ns."""
    if max_points < 2:
        raise ValueError("max_points must be >= 2")
    span = max(int(end_ns) - int(start_ns), 1)
    buckets = max_points // 2
    return max(-(-span // buckets), 1)


def downsample_minmax(rows: np.ndarray, start_ns: int, width_ns: int) -> np.ndarray:
    """Decimate ``rows`` into min/max pairs per time bucket (see the module docstring).

    Parameters
    ----------
    rows : ndarray, shape (n,), structured with an int ``stamp_ns`` field
        Sorted by ``stamp_ns``; any subset of ``ESTIMATE_DTYPE`` fields.
    start_ns : int
        Anchor of the first bucket (<= every stamp).
    width_ns : int
        Bucket width, >= 1 (:func:`bucket_width_ns`).

    Returns
    -------
    ndarray, shape (m,), same dtype as ``rows``, ``m <= 2 * number of non-empty buckets``.
    """
    if width_ns < 1:
        raise ValueError("width_ns must be >= 1")
    n = rows.shape[0]
    if n == 0:
        return rows.copy()
    stamps = rows["stamp_ns"].astype(np.int64)
    bucket = (stamps - np.int64(start_ns)) // np.int64(width_ns)
    # Rows are sorted, so each bucket is one contiguous run.
    starts = np.flatnonzero(np.r_[True, bucket[1:] != bucket[:-1]])
    ends = np.r_[starts[1:], n]  # exclusive
    counts = ends - starts
    nb = starts.shape[0]
    if nb == n:  # every bucket holds one row: nothing to decimate
        return rows.copy()

    out = np.empty(2 * nb, dtype=rows.dtype)
    first = out[0::2]
    second = out[1::2]
    first["stamp_ns"] = stamps[starts]
    second["stamp_ns"] = stamps[ends - 1]
    seg = np.repeat(np.arange(nb), counts)
    pos = np.arange(n)
    names = rows.dtype.names or ()
    for name in names:
        if name == "stamp_ns":
            continue
        col = rows[name]
        if name == "flags" or col.dtype.kind in "iub":
            if name == "flags":
                ored = np.bitwise_or.reduceat(col, starts)
                first[name] = ored
                second[name] = ored
            else:
                lo_i = np.minimum.reduceat(col, starts)
                hi_i = np.maximum.reduceat(col, starts)
                first[name] = lo_i
                second[name] = hi_i
            continue
        lo = np.fmin.reduceat(col, starts)
        hi = np.fmax.reduceat(col, starts)
        # Where each extreme first occurs, to keep their order within the bucket.
        big = np.int64(n)
        at_lo = np.where(col == lo[seg], pos, big)
        at_hi = np.where(col == hi[seg], pos, big)
        lo_pos = np.minimum.reduceat(at_lo, starts)
        hi_pos = np.minimum.reduceat(at_hi, starts)
        lo_first = lo_pos <= hi_pos
        first[name] = np.where(lo_first, lo, hi)
        second[name] = np.where(lo_first, hi, lo)

    keep = np.ones(2 * nb, dtype=bool)
    single = counts == 1
    keep[1::2] = ~single
    # A one-row bucket passes through unchanged (the code above already gives its values).
    if single.any():
        out[0::2][single] = rows[starts[single]]
    return out[keep]
