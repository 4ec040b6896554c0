"""Decimation of estimate series of any estimator (pure numpy): min/max envelopes and whole-row
thinning. Rows are any structured array with an int ``stamp_ns``; a ``flags`` field (the bit
field of :class:`estimator.spec.EstimatorSpec`) is OR-ed, not enveloped.

Two methods, both over time buckets of equal width ``w`` anchored at ``start_ns`` (bucket ``k``
holds the rows with ``start_ns + k·w <= stamp_ns < start_ns + (k+1)·w``); empty buckets give no
rows, so gaps in the data stay gaps.

Min/max per bucket (:func:`downsample_minmax`), for charts
-----------------------------------------------------------
Every non-empty bucket becomes at most two output rows:

* for each float field, one row carries the bucket's minimum and the other its maximum, in the
  order they occurred (the extreme seen first goes in the first row), so a spike and a dip both
  survive and a line drawn through the points has the right shape;
* NaN is ignored (a bucket whose values are all NaN gives NaN);
* ``stamp_ns`` of the two rows is the first and the last stamp of the bucket;
* ``flags`` of both rows is the bitwise OR of the bucket's flags (any degraded row shows);
* a bucket holding one row gives that row unchanged.

So ``B`` buckets give at most ``2·B`` rows and every column's envelope (min and max per bucket)
is exact, but one output row mixes values of different input rows: the east of one row and the
north of another are no position the vehicle ever had. Read rows as a whole only at full
rate or from :func:`thin_first`.

First whole row per bucket (:func:`thin_first`), for positions
--------------------------------------------------------------
Every non-empty bucket gives its first row, unchanged: each output row is a stored row, so a
position, its slip and its flags belong together. ``B`` buckets give at most ``B`` rows.

Sizing the buckets
------------------
:func:`bucket_width_ns` gives the width for at most ``max_points`` output rows over a span.
The server takes the span of the data itself, from the first to the last stored row in the
requested range (``[first, last + 1)``, anchored at ``first``), not the requested range: a
14-minute drive asked for as "the last 12 hours" keeps 14 minutes' worth of detail. For a
12-hour drive at 10 Hz (432,000 rows) and ``max_points`` 2,000, min/max buckets are 43.2 s
wide (1,000 buckets of two rows) and whole-row buckets 21.6 s wide (one row each).

Buckets are anchored at ``start_ns``, so decimating ``[a, c)`` equals concatenating the
decimation of ``[a, b)`` and ``[b, c)`` when ``b - a`` is a multiple of the bucket width; the
server uses this to decimate long ranges chunk by chunk.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bucket_width_ns", "downsample_minmax", "thin_first"]


def bucket_width_ns(
    start_ns: int, end_ns: int, max_points: int, *, rows_per_bucket: int = 2
) -> int:
    """Width of one bucket, >= 1 ns, so that ``[start_ns, end_ns)`` cut into buckets of at most
    ``rows_per_bucket`` output rows (2 for :func:`downsample_minmax`, 1 for :func:`thin_first`)
    gives at most ``max_points`` rows: ``ceil(span / (max_points // rows_per_bucket))``."""
    if max_points < 2:
        raise ValueError("max_points must be >= 2")
    if rows_per_bucket not in (1, 2):
        raise ValueError("rows_per_bucket must be 1 or 2")
    span = max(int(end_ns) - int(start_ns), 1)
    buckets = max_points // rows_per_bucket
    return max(-(-span // buckets), 1)


def _check_width(width_ns: int) -> None:
    if width_ns < 1:
        raise ValueError("width_ns must be >= 1")


def _bucket_runs(rows: np.ndarray, start_ns: int, width_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps, starts)``: the rows' stamps (int64) and the index where each non-empty bucket's
    run begins (rows are sorted, so each bucket is one contiguous run). ``rows`` non-empty."""
    _check_width(width_ns)
    stamps = rows["stamp_ns"].astype(np.int64)
    bucket = (stamps - np.int64(start_ns)) // np.int64(width_ns)
    return stamps, np.flatnonzero(np.r_[True, bucket[1:] != bucket[:-1]])


def thin_first(rows: np.ndarray, start_ns: int, width_ns: int) -> np.ndarray:
    """The first row of each time bucket, whole (see the module docstring).

    Parameters
    ----------
    rows : ndarray, shape (n,), structured with an int ``stamp_ns`` field
        Sorted by ``stamp_ns``; any subset of a spec's fields.
    start_ns : int
        Anchor of the first bucket (<= every stamp).
    width_ns : int
        Bucket width, >= 1 (:func:`bucket_width_ns` with ``rows_per_bucket=1``).

    Returns
    -------
    ndarray, shape (m,), same dtype as ``rows``: rows of ``rows`` (a copy), one per non-empty
    bucket, in order.
    """
    if rows.shape[0] == 0:
        _check_width(width_ns)
        return rows.copy()
    _, starts = _bucket_runs(rows, start_ns, width_ns)
    return rows[starts]


def downsample_minmax(rows: np.ndarray, start_ns: int, width_ns: int) -> np.ndarray:
    """Decimate ``rows`` into min/max pairs per time bucket (see the module docstring).

    Parameters
    ----------
    rows : ndarray, shape (n,), structured with an int ``stamp_ns`` field
        Sorted by ``stamp_ns``; any subset of a spec's fields.
    start_ns : int
        Anchor of the first bucket (<= every stamp).
    width_ns : int
        Bucket width, >= 1 (:func:`bucket_width_ns`).

    Returns
    -------
    ndarray, shape (m,), same dtype as ``rows``, ``m <= 2 * number of non-empty buckets``.
    """
    n = rows.shape[0]
    if n == 0:
        _check_width(width_ns)
        return rows.copy()
    stamps, starts = _bucket_runs(rows, start_ns, width_ns)
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
    for name in rows.dtype.names or ():
        if name != "stamp_ns":
            first[name], second[name] = _bucket_pair(name, rows[name], starts, seg)

    keep = np.ones(2 * nb, dtype=bool)
    single = counts == 1
    keep[1::2] = ~single
    # A one-row bucket passes through unchanged (the code above already gives its values).
    if single.any():
        out[0::2][single] = rows[starts[single]]
    return out[keep]


def _bucket_pair(
    name: str, col: np.ndarray, starts: np.ndarray, seg: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The two values per bucket of one column (shape (n,); runs begin at ``starts``, shape
    (nb,); ``seg`` is each row's bucket): ``flags`` ORed into both; an integer or boolean
    column's minimum, then maximum; a float column's minimum and maximum (NaN ignored) in the
    order they first occur in the bucket."""
    if name == "flags":
        ored = np.bitwise_or.reduceat(col, starts)
        return ored, ored
    if col.dtype.kind in "iub":
        return np.minimum.reduceat(col, starts), np.maximum.reduceat(col, starts)
    lo = np.fmin.reduceat(col, starts)
    hi = np.fmax.reduceat(col, starts)
    pos = np.arange(col.shape[0])
    big = np.int64(col.shape[0])
    lo_pos = np.minimum.reduceat(np.where(col == lo[seg], pos, big), starts)
    hi_pos = np.minimum.reduceat(np.where(col == hi[seg], pos, big), starts)
    lo_first = lo_pos <= hi_pos
    return np.where(lo_first, lo, hi), np.where(lo_first, hi, lo)
