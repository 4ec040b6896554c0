"""Peak-keeping min/max decimation and whole-row thinning, checked by hand."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.types import ESTIMATE_DTYPE, EstimateFlag, empty_estimates
from server.analytics.downsample import bucket_width_ns, downsample_minmax, thin_first

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


H = 3600 * S


def _drive(n: int, step_ns: int, t0: int = 0) -> np.ndarray:
    """``n`` rows of a drive: every field varies from row to row (a mixed row would show)."""
    rows = empty_estimates(n)
    rows["stamp_ns"] = t0 + np.arange(n, dtype=np.int64) * step_ns
    k = np.arange(n, dtype=np.float64)
    for i, name in enumerate(rows.dtype.names or ()):
        if rows.dtype[name].kind == "f":
            rows[name] = np.sin(k * (0.013 + 0.007 * i) + i) * (10 + i)
    rows["flags"] = (np.arange(n) % 3).astype(np.int32) << 4
    return rows


def test_bucket_width_of_a_12_hour_drive() -> None:
    # 2,000 points over 12 h: 1,000 min/max buckets of 43.2 s, or 2,000 whole rows 21.6 s apart
    assert bucket_width_ns(0, 12 * H, 2000) == 43_200_000_000
    assert bucket_width_ns(0, 12 * H, 2000, rows_per_bucket=1) == 21_600_000_000
    with pytest.raises(ValueError):
        bucket_width_ns(0, 10, 4, rows_per_bucket=3)


def test_a_short_burst_keeps_its_detail_when_buckets_follow_the_data() -> None:
    """5 min of 10 Hz rows late in a 12 h range: buckets sized on the burst's own span give
    far more than the ~14 rows of buckets sized on the range."""
    t0 = 11 * H
    burst = _drive(3000, S // 10, t0=t0)
    first, last = int(burst["stamp_ns"][0]), int(burst["stamp_ns"][-1])
    on_range = downsample_minmax(burst, 0, bucket_width_ns(0, 12 * H, 2000))
    assert on_range.shape[0] <= 16  # what sizing on the requested range gave: junk
    width = bucket_width_ns(first, last + 1, 2000)
    out = downsample_minmax(burst, first, width)
    assert 1900 <= out.shape[0] <= 2000
    thin = thin_first(burst, first, bucket_width_ns(first, last + 1, 2000, rows_per_bucket=1))
    assert 1500 <= thin.shape[0] <= 2000


def test_thin_first_by_hand() -> None:
    rows = _series([1, 2, 3, 4, 5, 6, 7])
    rows["stamp_ns"] = [0, 1, 4, 5, 6, 30, 31]  # buckets of 5: {0,1,4}, {5,6}, -, -, -, -, {30,31}
    out = thin_first(rows, 0, 5)
    assert out["stamp_ns"].tolist() == [0, 5, 30]
    assert out.tobytes() == rows[[0, 3, 5]].tobytes()
    assert thin_first(rows[:0], 0, 5).shape == (0,)
    with pytest.raises(ValueError):
        thin_first(rows, 0, 0)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 400),
    step=st.integers(1, 50),
    max_points=st.integers(2, 60),
    holes=st.lists(st.integers(0, 399), max_size=40),
)
def test_thin_first_returns_only_stored_rows(
    n: int, step: int, max_points: int, holes: list[int]
) -> None:
    """Every returned row equals a stored row, byte for byte (no field is taken from another
    row), at most max_points of them, in time order, one per non-empty bucket; chunking at a
    bucket boundary changes nothing."""
    rows = _drive(n, step)
    rows = rows[np.setdiff1d(np.arange(n), holes)] if len(holes) < n else rows
    first, last = int(rows["stamp_ns"][0]), int(rows["stamp_ns"][-1])
    width = bucket_width_ns(first, last + 1, max_points, rows_per_bucket=1)
    out = thin_first(rows, first, width)
    stored = {r.tobytes() for r in rows}
    assert all(r.tobytes() in stored for r in out)
    assert out.shape[0] <= max_points
    assert np.all(np.diff(out["stamp_ns"]) > 0)
    buckets = (rows["stamp_ns"] - first) // width
    assert out.shape[0] == np.unique(buckets).shape[0]
    assert out[0].tobytes() == rows[0].tobytes()
    cut = first + width * max(1, int(buckets[-1]) // 2)
    left = rows[rows["stamp_ns"] < cut]
    right = rows[rows["stamp_ns"] >= cut]
    joined = np.concatenate([thin_first(left, first, width), thin_first(right, first, width)])
    assert joined.tobytes() == out.tobytes()


def test_minmax_rows_are_not_stored_rows() -> None:
    """Why positions need thin_first: a min/max row pairs an east of one row with a north of
    another."""
    rows = _drive(200, S)
    out = downsample_minmax(rows, 0, 20 * S)
    stored = {r.tobytes() for r in rows}
    assert sum(r.tobytes() not in stored for r in out) > out.shape[0] // 2


def test_rows_of_another_spec() -> None:
    """Any spec's rows: its floats enveloped, its ``flags`` OR-ed, its dtype kept."""
    ref = REFERENCE_SPEED_SPEC
    rows = ref.empty_rows(4)
    rows["stamp_ns"] = np.arange(4) * S
    rows["speed_mps"] = [1.0, 3.0, 2.0, 0.5]
    rows["flags"] = [ref.flag_mask("WHEEL_OK"), 0, ref.flag_mask("NO_WHEEL"), 0]
    out = downsample_minmax(rows, 0, 4 * S)
    assert out.dtype == ref.dtype
    assert out["speed_mps"].tolist() == [3.0, 0.5]
    assert ref.flag_names(int(out["flags"][0])) == ["WHEEL_OK", "NO_WHEEL"]
    assert thin_first(rows, 0, 2 * S)["speed_mps"].tolist() == [1.0, 2.0]
