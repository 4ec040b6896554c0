"""Peak-keeping min/max decimation, checked by hand."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.types import ESTIMATE_DTYPE, EstimateFlag, empty_estimates
from server.downsample import bucket_width_ns, downsample_minmax

S = 1_000_000_000


def _series(values: list[float], step_ns: int = S) -> np.ndarray:
    rows = empty_estimates(len(values))
    rows["stamp_ns"] = np.arange(len(values), dtype=np.int64) * step_ns
    rows["vg_mps"] = values
    return rows


def test_bucket_width() -> None:
    assert bucket_width_ns(0, 10 * S, 4) == 5 * S  # 2 buckets
    assert bucket_width_ns(0, 10, 7) == 4  # 3 buckets, ceil(10/3)
    assert bucket_width_ns(5, 5, 4) == 1
    with pytest.raises(ValueError):
        bucket_width_ns(0, 10, 1)


def test_two_buckets_by_hand() -> None:
    # Buckets [0,5 s) and [5,10 s); values 1..10 with a spike of 100 at t=2 s and a dip at 7 s.
    rows = _series([1, 2, 100, 4, 5, 6, 7, -50, 9, 10])
    rows["flags"] = 0
    rows["flags"][3] = EstimateFlag.DEGRADED
    out = downsample_minmax(rows, 0, 5 * S)
    assert out.dtype == ESTIMATE_DTYPE
    assert out["stamp_ns"].tolist() == [0, 4 * S, 5 * S, 9 * S]
    # first bucket: min 1 (t=0) before max 100 (t=2); second: max 10 (t=9) after min -50 (t=7)
    assert out["vg_mps"].tolist() == [1, 100, -50, 10]
    assert out["flags"].tolist() == [int(EstimateFlag.DEGRADED)] * 2 + [0, 0]


def test_order_of_extremes_is_kept() -> None:
    rows = _series([9, 1, 5])  # max first, then min
    out = downsample_minmax(rows, 0, 10 * S)
    assert out["vg_mps"].tolist() == [9, 1]


def test_nan_is_ignored_and_all_nan_stays_nan() -> None:
    rows = _series([np.nan, 3, np.nan, 7])
    out = downsample_minmax(rows, 0, 10 * S)
    assert out["vg_mps"].tolist() == [3, 7]
    assert np.isnan(out["slip_left_pct"]).all()  # never set: all NaN


def test_single_row_bucket_passes_unchanged_and_gaps_stay_gaps() -> None:
    rows = _series([1, 2, 3, 4])
    rows["stamp_ns"] = [0, 1, 2, 100 * S]  # last row alone in a far bucket
    rows["vl_mps"] = [5, 6, 7, 8]
    out = downsample_minmax(rows, 0, 10 * S)
    assert out.shape == (3,)
    assert out[2].tobytes() == rows[3].tobytes()
    assert out["vl_mps"].tolist() == [5, 7, 8]


def test_one_row_per_bucket_is_identity() -> None:
    rows = _series([3, 1, 2])
    out = downsample_minmax(rows, 0, S)
    assert out.tobytes() == rows.tobytes()


def test_subset_of_fields() -> None:
    rows = _series([1, 5, 2, 8])[["stamp_ns", "vg_mps"]]
    out = downsample_minmax(rows, 0, 2 * S)
    assert out["vg_mps"].tolist() == [1, 5, 2, 8]
    out = downsample_minmax(rows, 0, 4 * S)
    assert out["vg_mps"].tolist() == [1, 8]


@settings(max_examples=60, deadline=None)
@given(
    values=st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=300),
    max_points=st.integers(2, 50),
    spike_at=st.integers(0, 299),
)
def test_properties(values: list[float], max_points: int, spike_at: int) -> None:
    """At most max_points rows, the global max and min survive, chunking changes nothing."""
    rows = _series(values, step_ns=7)
    rows["vg_mps"][spike_at % len(values)] = 1e9
    end = int(rows["stamp_ns"][-1]) + 1
    width = bucket_width_ns(0, end, max_points)
    out = downsample_minmax(rows, 0, width)
    assert out.shape[0] <= max_points
    assert out["vg_mps"].max() == 1e9
    assert out["vg_mps"].min() == rows["vg_mps"].min()
    assert np.all(np.diff(out["stamp_ns"]) >= 0)
    # decimating two chunks cut at a bucket boundary equals decimating the whole
    cut = width * max(1, (end // width) // 2)
    left = rows[rows["stamp_ns"] < cut]
    right = rows[rows["stamp_ns"] >= cut]
    joined = np.concatenate([downsample_minmax(left, 0, width), downsample_minmax(right, 0, width)])
    assert joined.tobytes() == out.tobytes()
