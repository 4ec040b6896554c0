"""Slip-map cells on series small enough to compute by hand."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.geo import EnuFrame
from estimator.mdsf_spec import MDSF_SPEC as MDSF
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.spec import EstimatorSpec, FieldSpec, PositionChannel, SpeedChannel
from estimator.types import EstimateFlag, empty_estimates
from server.analytics.reports import vehicle_report
from server.analytics.slipmap import (
    MapSamples,
    NotMappable,
    SlipMap,
    TooManyCells,
    bin_cells,
    cell_sums,
    finish_cells,
    map_samples,
    merge_cell_sums,
    reframe,
    slip_map,
    slipmap_fields,
)

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
LR = ("left", "right")


def test_two_cells_time_weighted() -> None:
    m = slip_map(two_cell_series(), MDSF, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
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
    m = slip_map(rows, MDSF, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    rep = vehicle_report(rows, MDSF, start_ns=0, end_ns=END_NS, max_gap_s=2.5)
    assert m.time_s.sum() == pytest.approx(rep.moving_s)
    assert m.distance_m.sum() == pytest.approx(rep.distance_m)


def test_cell_without_valid_slip_keeps_time_and_distance() -> None:
    rows = two_cell_series()
    rows["flags"] = 0  # no wheel valid anywhere
    m = slip_map(rows, MDSF, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    np.testing.assert_allclose(m.time_s, [0.5, 2.0, 3.0])
    assert np.isnan(m.slip_mean_pct).all()
    assert np.isnan(m.mean_abs_slip_pct).all() and np.isnan(m.max_abs_slip_pct).all()
    assert np.isnan(m.band_share).all()
    np.testing.assert_allclose(m.slip_valid_s, 0.0)


def test_non_moving_and_unplaced_rows_are_left_out() -> None:
    rows = two_cell_series()
    base = slip_map(rows, MDSF, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    # the standstill row (0), the slow row (6) and the unplaced row (7) carry large slips:
    # changing them changes nothing
    rows["slip_left_pct"][[0, 6, 7]] = 99.0
    rows["flags"][[0, 6, 7]] = L | R
    again = slip_map(rows, MDSF, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5)
    np.testing.assert_array_equal(base.max_abs_slip_pct, again.max_abs_slip_pct)
    np.testing.assert_array_equal(base.rows, again.rows)
    # with a higher moving threshold, rows at 2 m/s and 1 m/s drop out too
    fast = slip_map(rows, MDSF, end_ns=END_NS, cell_m=10.0, max_gap_s=2.5, min_ground_speed_mps=3.0)
    assert fast.index_east.tolist() == [1]
    assert fast.rows.tolist() == [2]


def random_series(n: int = 2_000, seed: int = 7) -> np.ndarray:
    """``n`` moving rows with random steps, positions in ±50 m, slips and validity flags."""
    rng = np.random.default_rng(seed)
    rows = empty_estimates(n)
    rows["stamp_ns"] = np.cumsum(rng.integers(S // 20, S // 5, n))
    rows["vg_mps"] = rng.uniform(0.5, 3.0, n)
    rows["east_m"] = rng.uniform(-50, 50, n)
    rows["north_m"] = rng.uniform(-50, 50, n)
    rows["slip_left_pct"] = rng.normal(0, 15, n)
    rows["slip_right_pct"] = rng.normal(0, 15, n)
    rows["flags"] = rng.choice([0, L, R, L | R], n)
    return rows


def test_band_shares_sum_to_one_and_follow_the_edges() -> None:
    rows = random_series()
    m = slip_map(
        rows,
        MDSF,
        end_ns=int(rows["stamp_ns"][-1]) + S,
        cell_m=25.0,
        band_edges_pct=(2.0, 8.0, 20.0),
    )
    assert m.band_share.shape == (m.cells, 4)
    has_slip = m.slip_valid_s.sum(axis=1) > 0
    np.testing.assert_allclose(m.band_share[has_slip].sum(axis=1), 1.0)
    assert m.band_labels == ("0_2", "2_8", "8_20", "20_up")
    # the cells' sums equal a direct sum over the samples of the same cell
    samples = map_samples(rows, MDSF, end_ns=int(rows["stamp_ns"][-1]) + S)
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
    samples = map_samples(rows, MDSF, end_ns=END_NS, max_gap_s=2.5)
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
    m = slip_map(empty_estimates(0), MDSF, end_ns=S, cell_m=1.0)
    assert m.cells == 0
    assert m.band_share.shape == (0, 3)


def _half(samples: MapSamples, part: slice) -> MapSamples:
    arrays = {
        n: getattr(samples, n)[part] for n in MapSamples.__dataclass_fields__ if n != "channels"
    }
    return MapSamples(channels=samples.channels, **arrays)


def _assert_same_statistics(a: SlipMap, b: SlipMap) -> None:
    """Every statistic of two maps equal to 1e-12 (``vehicles`` aside)."""
    assert (a.cell_m, a.band_edges_pct) == (b.cell_m, b.band_edges_pct)
    np.testing.assert_array_equal(a.index_east, b.index_east)
    np.testing.assert_array_equal(a.index_north, b.index_north)
    np.testing.assert_array_equal(a.rows, b.rows)
    for name in (
        "time_s",
        "distance_m",
        "slip_valid_s",
        "slip_mean_pct",
        "mean_abs_slip_pct",
        "max_abs_slip_pct",
        "band_share",
    ):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-12, atol=1e-12)


def test_merged_halves_equal_binning_all_at_once() -> None:
    rows = random_series(600)  # ~3 samples a cell: some cells hold samples of one half only
    samples = map_samples(rows, MDSF, end_ns=int(rows["stamp_ns"][-1]) + S)
    edges = (2.0, 8.0, 20.0)
    whole = bin_cells(samples, cell_m=5.0, band_edges_pct=edges)
    first = cell_sums(_half(samples, slice(0, 280)), cell_m=5.0, band_edges_pct=edges)
    second = cell_sums(_half(samples, slice(280, None)), cell_m=5.0, band_edges_pct=edges)
    merged = finish_cells(
        merge_cell_sums([first, second], cell_m=5.0, channels=LR, band_edges_pct=edges)
    )
    _assert_same_statistics(merged, whole)
    # the other order gives the same map
    swapped = finish_cells(
        merge_cell_sums([second, first], cell_m=5.0, channels=LR, band_edges_pct=edges)
    )
    _assert_same_statistics(swapped, whole)
    # each part counts once in every cell it has samples in
    in_first = {(int(i), int(j)) for i, j in zip(first.index_east, first.index_north, strict=True)}
    in_second = {
        (int(i), int(j)) for i, j in zip(second.index_east, second.index_north, strict=True)
    }
    expected = [
        ((i, j) in in_first) + ((i, j) in in_second)
        for i, j in zip(merged.index_east.tolist(), merged.index_north.tolist(), strict=True)
    ]
    assert merged.vehicles.tolist() == expected
    assert set(expected) == {1, 2}
    assert whole.vehicles.tolist() == [1] * whole.cells


def test_merge_arguments_and_limit() -> None:
    samples = map_samples(two_cell_series(), MDSF, end_ns=END_NS, max_gap_s=2.5)
    part = cell_sums(samples, cell_m=10.0)
    none = merge_cell_sums([], cell_m=10.0, channels=LR)
    assert none.cells == 0 and finish_cells(none).band_share.shape == (0, 3)
    alone = finish_cells(merge_cell_sums([part], cell_m=10.0, channels=LR))
    _assert_same_statistics(alone, bin_cells(samples, cell_m=10.0))
    with pytest.raises(ValueError, match="cannot merge"):
        merge_cell_sums([part], cell_m=5.0, channels=LR)
    with pytest.raises(ValueError, match="cannot merge"):
        merge_cell_sums([part], cell_m=10.0, channels=LR, band_edges_pct=(10.0,))
    moved = cell_sums(
        MapSamples(**{**_fields(samples), "east_m": samples.east_m + 100.0}), cell_m=10.0
    )
    assert merge_cell_sums([part, part], cell_m=10.0, channels=LR, max_cells=3).cells == 3
    with pytest.raises(TooManyCells) as info:
        merge_cell_sums([part, moved], cell_m=10.0, channels=LR, max_cells=5)
    assert (info.value.cells, info.value.max_cells) == (6, 5)


def _fields(samples: MapSamples) -> dict[str, np.ndarray]:
    return {name: getattr(samples, name) for name in MapSamples.__dataclass_fields__}


A = EnuFrame(52.0, 5.6, 12.0)
B = EnuFrame(52.0031, 5.6047, 40.0)  # ~450 m north-east of A, 28 m higher


def _rows_at(frame: EnuFrame, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Moving rows (1 s apart, 2 m/s, left slip 10 %) at the geodetic points, in ``frame``."""
    rows = empty_estimates(lat.shape[0])
    rows["stamp_ns"] = np.arange(lat.shape[0]) * S
    rows["vg_mps"] = 2.0
    rows["east_m"], rows["north_m"], rows["up_m"] = frame.to_enu(lat, lon, h)
    rows["slip_left_pct"] = 10.0
    rows["flags"] = L
    return rows


def test_two_frames_same_ground_same_cells() -> None:
    shared = EnuFrame(52.001, 5.602, 0.0)
    # cell centres of the shared frame (10 m cells), on the ground 15 m above the ellipsoid;
    # the last point only vehicle "a" drives over
    east = np.array([5.0, 15.0, 25.0, 205.0])
    north = np.array([5.0, 5.0, -35.0, 95.0])
    lat, lon, h = shared.to_geodetic(east, north, np.full(4, 15.0))
    end_ns = 4 * S
    a = map_samples(_rows_at(A, lat, lon, h), MDSF, end_ns=end_ns)
    b = map_samples(_rows_at(B, lat[:3], lon[:3], h[:3]), MDSF, end_ns=end_ns)
    assert not np.allclose(a.east_m[:3], b.east_m)  # the two frames differ by hundreds of metres
    a_shared, b_shared = reframe(a, A, shared), reframe(b, B, shared)
    np.testing.assert_allclose(a_shared.east_m, east, atol=1e-6)
    np.testing.assert_allclose(b_shared.north_m, north[:3], atol=1e-6)
    np.testing.assert_allclose(b_shared.up_m, 15.0, atol=1e-6)
    merged = finish_cells(
        merge_cell_sums(
            [cell_sums(a_shared, cell_m=10.0), cell_sums(b_shared, cell_m=10.0)],
            cell_m=10.0,
            channels=LR,
        )
    )
    cells = list(zip(merged.index_east.tolist(), merged.index_north.tolist(), strict=True))
    assert cells == [(0, 0), (1, 0), (2, -4), (20, 9)]
    assert merged.vehicles.tolist() == [2, 2, 2, 1]
    assert merged.rows.tolist() == [2, 2, 2, 1]
    np.testing.assert_allclose(merged.time_s, [2.0, 2.0, 2.0, 1.0])
    np.testing.assert_allclose(merged.slip_mean_pct[:, 0], 10.0)
    # in its own frame, the same samples are elsewhere: the shared frame is what joins them
    own = bin_cells(b, cell_m=10.0)
    assert not set(zip(own.index_east.tolist(), own.index_north.tolist(), strict=True)) & set(cells)


def test_reframe_keeps_samples_in_the_same_frame_and_reads_up() -> None:
    rows = two_cell_series()
    samples = map_samples(rows, MDSF, end_ns=END_NS, max_gap_s=2.5)
    assert reframe(samples, A, EnuFrame(*(52.0, 5.6, 12.0))) is samples
    np.testing.assert_array_equal(samples.up_m, 0.0)  # the series has no height: NaN → 0
    rows["up_m"] = 3.0
    with_up = map_samples(rows, MDSF, end_ns=END_NS, max_gap_s=2.5)
    np.testing.assert_array_equal(with_up.up_m, 3.0)
    no_up = map_samples(
        rows[
            ["stamp_ns", "vg_mps", "slip_left_pct", "slip_right_pct", "flags", "east_m", "north_m"]
        ],
        MDSF,
        end_ns=END_NS,
        max_gap_s=2.5,
    )
    np.testing.assert_array_equal(no_up.up_m, 0.0)


PLACED = EstimatorSpec(
    name="placed",
    title="speed and position, no slip",
    kinds=("tracked",),
    inputs=("gnss",),
    fields=(
        FieldSpec("stamp_ns", "i8", "ns", "time"),
        FieldSpec("v_mps", "f8", "m/s", "speed"),
        FieldSpec("x_m", "f8", "m", "east"),
        FieldSpec("y_m", "f8", "m", "north"),
    ),
    speeds=(SpeedChannel("v", "speed", "v_mps"),),
    motion="v",
    position=PositionChannel("x_m", "y_m"),
)


def test_spec_without_slip_channels_maps_time_and_distance() -> None:
    rows = PLACED.empty_rows(4)
    rows["stamp_ns"] = np.arange(4) * S
    rows["v_mps"] = [2.0, 2.0, 0.0, 3.0]
    rows["x_m"] = [1.0, 11.0, 12.0, 13.0]
    rows["y_m"] = 0.5
    assert slipmap_fields(PLACED, fleet=True) == ["stamp_ns", "v_mps", "x_m", "y_m"]
    m = slip_map(rows, PLACED, end_ns=4 * S, cell_m=10.0)
    assert m.channels == ()
    assert m.index_east.tolist() == [0, 1]
    np.testing.assert_allclose(m.time_s, [1.0, 2.0])
    np.testing.assert_allclose(m.distance_m, [2.0, 5.0])
    assert m.slip_valid_s.shape == (2, 0)
    assert np.isnan(m.mean_abs_slip_pct).all() and np.isnan(m.band_share).all()


def test_fields_follow_the_spec_and_unmappable_specs_are_refused() -> None:
    assert slipmap_fields(MDSF) == [
        "stamp_ns",
        "vg_mps",
        "slip_left_pct",
        "slip_right_pct",
        "flags",
        "east_m",
        "north_m",
    ]
    assert slipmap_fields(MDSF, fleet=True)[-1] == "up_m"
    with pytest.raises(NotMappable, match=r"reference_speed.*no position"):
        slipmap_fields(REFERENCE_SPEED_SPEC)
    rows = REFERENCE_SPEED_SPEC.empty_rows(2)
    with pytest.raises(NotMappable):
        map_samples(rows, REFERENCE_SPEED_SPEC, end_ns=S)


def test_parts_of_other_channels_do_not_merge() -> None:
    samples = map_samples(two_cell_series(), MDSF, end_ns=END_NS, max_gap_s=2.5)
    part = cell_sums(samples, cell_m=10.0)
    assert part.channels == LR
    with pytest.raises(ValueError, match="slip channels"):
        merge_cell_sums([part], cell_m=10.0, channels=("left",))
