"""Slip-map cells on series small enough to compute by hand."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.types import EstimateFlag, empty_estimates
from server.reports import vehicle_report
from server.slipmap import TooManyCells, bin_cells, map_samples, slip_map

S = 1_000_000_000
L = int(EstimateFlag.SLIP_LEFT_VALID)
R = int(EstimateFlag.SLIP_RIGHT_VALID)


def two_cell_series() -> np.ndarray:
    """8 rows at t = 0, 1, 2, 3, 5, 6, 6.5, 7 s (steps 1, 1, 1, 2, 1, 0.5, 0.5 s; median 1 s).

    row  t    vg    east   left (valid)   right (valid)
    0    0    0     1      -              -             standstill: not a sample
    1    1    2     2      10 (L)         20 (R)
    2    2    2     3      -30 (L)        NaN (R flag)  right NaN: not valid
    3    3    4     12     40 (no flag)   6 (R)         left without flag: not valid
    4    5    4     14     -              -             cell 1, no valid slip
    5    6    1     -5     2 (L)          2 (R)         west of the anchor: cell (-1, 0)
    6    6.5  0.1   15     50 (L)         50 (R)        too slow: not a sample
    7    7    2     NaN    1 (L)          1 (R)         no position: not a sample

    Weights (ns/1e9): 1, 1, 1, 2 (≤ max_gap 2.5 s), 1, 0.5, 0.5, and the last row 1 s clipped
    to end 7.5 s → 0.5.
    """
    rows = empty_estimates(8)
    rows["stamp_ns"] = np.array([0, 1, 2, 3, 5, 6, 6.5, 7]) * S
    rows["vg_mps"] = [0, 2, -2, 4, 4, 1, 0.1, 2]  # reversing counts: |vg|
    rows["east_m"] = [1, 2, 3, 12, 14, -5, 15, np.nan]
    rows["north_m"] = [0.5, 0.5, 9.9, 0.5, 0.5, 0.5, 0.5, 0.5]
    rows["slip_left_pct"] = [np.nan, 10, -30, 40, np.nan, 2, 50, 1]
    rows["slip_right_pct"] = [np.nan, 20, np.nan, 6, np.nan, 2, 50, 1]
    rows["flags"] = [0, L | R, L | R, R, 0, L | R, L | R, L | R]
    return rows


END_NS = int(7.5 * S)


def test_two_cells_time_weighted() -> None:
    m = slip_map(two_cell_series(), end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    assert m.cells == 3
    # ordered by east index, then north
    assert m.index_east.tolist() == [-1, 0, 1]
    assert m.index_north.tolist() == [0, 0, 0]
    assert m.east_m.tolist() == [-10.0, 0.0, 10.0]
    assert m.north_m.tolist() == [0.0, 0.0, 0.0]
    assert m.rows.tolist() == [1, 2, 2]
    # cell (0, 0): rows 1, 2 (1 s each); cell (1, 0): rows 3 (2 s), 4 (1 s); (-1, 0): row 5
    np.testing.assert_allclose(m.time_s, [0.5, 2.0, 3.0])
    np.testing.assert_allclose(m.distance_m, [0.5, 2 + 2, 4 * 2 + 4 * 1])
    # left: (0,0) rows 1, 2 valid: (10·1 − 30·1) / 2; (1,0) none; (-1,0) row 5
    np.testing.assert_allclose(m.slip_valid_s[:, 0], [0.5, 2.0, 0.0])
    np.testing.assert_allclose(m.slip_mean_pct[:, 0], [2.0, -10.0, np.nan])
    # right: (0,0) only row 1 (row 2 NaN); (1,0) row 3 (2 s)
    np.testing.assert_allclose(m.slip_valid_s[:, 1], [0.5, 1.0, 2.0])
    np.testing.assert_allclose(m.slip_mean_pct[:, 1], [2.0, 20.0, 6.0])
    # |slip| over the valid wheel-samples: (0,0): 10, 30, 20 at 1 s each; (1,0): 6 at 2 s
    np.testing.assert_allclose(m.mean_abs_slip_pct, [2.0, 20.0, 6.0])
    np.testing.assert_allclose(m.max_abs_slip_pct, [2.0, 30.0, 6.0])
    # bands [0, 5), [5, 15), [15, ∞): (0,0) 10 → mid, 30 and 20 → high
    np.testing.assert_allclose(m.band_share[1], [0.0, 1 / 3, 2 / 3])
    np.testing.assert_allclose(m.band_share[2], [0.0, 1.0, 0.0])
    np.testing.assert_allclose(m.band_share[0], [1.0, 0.0, 0.0])
    assert m.band_labels == ("0_5", "5_15", "15_up")


def test_cells_add_up_to_the_report() -> None:
    rows = two_cell_series()
    rows["east_m"][7] = 20.0  # every moving row placed: the cells hold the report's moving time
    m = slip_map(rows, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    rep = vehicle_report(rows, start_ns=0, end_ns=END_NS, max_gap_s=2.5)
    assert m.time_s.sum() == pytest.approx(rep.moving_s)
    assert m.distance_m.sum() == pytest.approx(rep.distance_m)


def test_cell_without_valid_slip_keeps_time_and_distance() -> None:
    rows = two_cell_series()
    rows["flags"] = 0  # no wheel valid anywhere
    m = slip_map(rows, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    np.testing.assert_allclose(m.time_s, [0.5, 2.0, 3.0])
    assert np.isnan(m.slip_mean_pct).all()
    assert np.isnan(m.mean_abs_slip_pct).all() and np.isnan(m.max_abs_slip_pct).all()
    assert np.isnan(m.band_share).all()
    np.testing.assert_allclose(m.slip_valid_s, 0.0)


def test_non_moving_and_unplaced_rows_are_left_out() -> None:
    rows = two_cell_series()
    base = slip_map(rows, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    # the standstill row (0), the slow row (6) and the unplaced row (7) carry large slips:
    # changing them changes nothing
    rows["slip_left_pct"][[0, 6, 7]] = 99.0
    rows["flags"][[0, 6, 7]] = L | R
    again = slip_map(rows, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    np.testing.assert_array_equal(base.max_abs_slip_pct, again.max_abs_slip_pct)
    np.testing.assert_array_equal(base.rows, again.rows)
    # with a higher moving threshold, rows at 2 m/s and 1 m/s drop out too
    fast = slip_map(rows, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5, min_ground_speed_mps=3.0)
    assert fast.index_east.tolist() == [1]
    assert fast.rows.tolist() == [2]


def test_band_shares_sum_to_one_and_follow_the_edges() -> None:
    rng = np.random.default_rng(7)
    n = 2_000
    rows = empty_estimates(n)
    rows["stamp_ns"] = np.cumsum(rng.integers(S // 20, S // 5, n))
    rows["vg_mps"] = rng.uniform(0.5, 3.0, n)
    rows["east_m"] = rng.uniform(-50, 50, n)
    rows["north_m"] = rng.uniform(-50, 50, n)
    rows["slip_left_pct"] = rng.normal(0, 15, n)
    rows["slip_right_pct"] = rng.normal(0, 15, n)
    rows["flags"] = rng.choice([0, L, R, L | R], n)
    m = slip_map(
        rows, end_ns=int(rows["stamp_ns"][-1]) + S, cell_m=25.0, band_edges_pct=(2.0, 8.0, 20.0)
    )
    assert m.band_share.shape == (m.cells, 4)
    has_slip = m.slip_valid_s.sum(axis=1) > 0
    np.testing.assert_allclose(m.band_share[has_slip].sum(axis=1), 1.0)
    assert m.band_labels == ("0_2", "2_8", "8_20", "20_up")
    # the cells' sums equal a direct sum over the samples of the same cell
    samples = map_samples(rows, end_ns=int(rows["stamp_ns"][-1]) + S)
    i = np.floor(samples.east_m / 25.0)
    j = np.floor(samples.north_m / 25.0)
    for c in range(m.cells):
        inside = (i == m.index_east[c]) & (j == m.index_north[c])
        w = samples.w_ns[inside] / S
        assert m.time_s[c] == pytest.approx(w.sum())
        left = samples.slip_valid[inside, 0]
        if left.any():
            expected = np.average(samples.slip_pct[inside, 0][left], weights=w[left])
            assert m.slip_mean_pct[c, 0] == pytest.approx(expected)


def test_cell_limit_and_arguments() -> None:
    rows = two_cell_series()
    samples = map_samples(rows, end_ns=END_NS, max_gap_s=2.5)
    with pytest.raises(TooManyCells) as info:
        bin_cells(samples, cell_m=10.0, max_cells=2)
    assert (info.value.cells, info.value.max_cells) == (3, 2)
    assert bin_cells(samples, cell_m=10.0, max_cells=3).cells == 3
    assert bin_cells(samples, cell_m=100.0, max_cells=2).time_s.tolist() == [0.5, 5.0]
    with pytest.raises(ValueError, match="cell_m"):
        bin_cells(samples, cell_m=0.0)
    with pytest.raises(ValueError, match="band_edges_pct"):
        bin_cells(samples, cell_m=1.0, band_edges_pct=(5.0, 5.0))


def test_empty_series_gives_no_cells() -> None:
    m = slip_map(empty_estimates(0), end_ns=S, cell_m=1.0)
    assert m.cells == 0
    assert m.band_share.shape == (0, 3)
