"""A map layer (a spec's mapped value channel, e.g. friction μ) in the slip map's cells: the
time-weighted mean over the samples that inform it and their count, by hand; merging halves
gives the whole."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.spec import (
    EstimatorSpec,
    FieldSpec,
    FlagSpec,
    PositionChannel,
    SpeedChannel,
    ValueChannel,
)
from server.analytics.slipmap import (
    NotMappable,
    cell_sums,
    check_layer,
    finish_cells,
    map_samples,
    merge_cell_sums,
    slip_map,
    slipmap_fields,
)

S = 1_000_000_000
#: A placed friction-like estimator: μ informed where INFORMED is set, held elsewhere.
PLACED_MU = EstimatorSpec(
    name="placed_mu",
    title="μ with a position",
    kinds=("wheeled_4wd_steered",),
    inputs=("imu",),
    fields=(
        FieldSpec("stamp_ns", "i8", "ns", "time"),
        FieldSpec("mu", "f8", "", "μ"),
        FieldSpec("vx_mps", "f8", "m/s", "speed"),
        FieldSpec("east_m", "f8", "m", "east"),
        FieldSpec("north_m", "f8", "m", "north"),
        FieldSpec("flags", "i4", "", "flags"),
    ),
    flags=(FlagSpec("INFORMED", 0), FlagSpec("HELD", 1)),
    speeds=(SpeedChannel("speed", "speed", "vx_mps"),),
    motion="speed",
    position=PositionChannel("east_m", "north_m"),
    values=(
        ValueChannel("mu", "μ", "mu", valid_flag="INFORMED", mapped=True),
        ValueChannel("plain", "not mapped", "mu"),
    ),
)


def _rows() -> np.ndarray:
    """8 rows 1 s apart, east 0, 4, …, 28 m (cells of 10 m: 3, 2, 3 rows), all moving but the
    last; μ 0.2, 0.4, …; informed on rows 0, 2, 3, 5 and 6 (row 1 held, row 4 informed but NaN,
    row 7 standing)."""
    rows = PLACED_MU.empty_rows(8)
    rows["stamp_ns"] = np.arange(8) * S
    rows["vx_mps"] = [1, 1, 1, 1, 1, 1, 1, 0]
    rows["east_m"] = np.arange(8) * 4.0
    rows["north_m"] = 1.0
    rows["mu"] = 0.2 * (1 + np.arange(8))
    rows["mu"][4] = np.nan
    rows["flags"] = [1, 2, 1, 1, 1, 1, 1, 1]
    return rows


def test_cells_hold_the_informed_mean_and_count() -> None:
    layer = check_layer(PLACED_MU, "mu")
    m = slip_map(_rows(), PLACED_MU, end_ns=8 * S, cell_m=10.0, layer=layer)
    assert m.layer == "mu"
    assert m.index_east.tolist() == [0, 1, 2]
    assert m.rows.tolist() == [3, 2, 2]
    # cell 0: rows 0 (0.2) and 2 (0.6), row 1 held; cell 1: row 3 (0.8), row 4 NaN;
    # cell 2: rows 5 (1.2) and 6 (1.4), row 7 standing
    assert m.layer_samples.tolist() == [2, 1, 2]
    assert m.layer_valid_s.tolist() == [2.0, 1.0, 2.0]
    np.testing.assert_allclose(m.layer_mean, [0.4, 0.8, 1.3], rtol=0, atol=1e-12)


def test_time_weights_the_mean() -> None:
    rows = _rows()
    rows["stamp_ns"][2] = 1 * S + S // 4  # row 1 weighs 0.25 s, row 0 1 s, row 2 1.75 s
    layer = check_layer(PLACED_MU, "mu")
    m = slip_map(rows, PLACED_MU, end_ns=8 * S, cell_m=10.0, layer=layer, max_gap_s=2.0)
    assert m.layer_valid_s[0] == pytest.approx(2.75)
    assert m.layer_mean[0] == pytest.approx((0.2 * 1.0 + 0.6 * 1.75) / 2.75)


def test_no_layer_leaves_the_map_as_it_was() -> None:
    m = slip_map(_rows(), PLACED_MU, end_ns=8 * S, cell_m=10.0)
    assert m.layer is None
    assert m.layer_samples.tolist() == [0, 0, 0]
    assert np.isnan(m.layer_mean).all()
    assert "mu" not in slipmap_fields(PLACED_MU)
    assert "mu" in slipmap_fields(PLACED_MU, layer=check_layer(PLACED_MU, "mu"))


def test_merged_halves_give_the_whole() -> None:
    rows = _rows()
    layer = check_layer(PLACED_MU, "mu")
    whole = slip_map(rows, PLACED_MU, end_ns=8 * S, cell_m=10.0, layer=layer)
    samples = map_samples(rows, PLACED_MU, end_ns=8 * S, layer=layer)
    parts = [
        cell_sums(
            map_samples(rows[part], PLACED_MU, end_ns=end, layer=layer),
            cell_m=10.0,
            layer="mu",
        )
        for part, end in ((slice(0, 4), 4 * S), (slice(4, 8), 8 * S))
    ]
    merged = finish_cells(merge_cell_sums(parts, cell_m=10.0, channels=(), layer="mu"))
    assert samples.layer_valid.sum() == 5
    np.testing.assert_array_equal(merged.layer_samples, whole.layer_samples)
    np.testing.assert_allclose(merged.layer_mean, whole.layer_mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(merged.layer_valid_s, whole.layer_valid_s, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="layer mu"):
        merge_cell_sums(parts, cell_m=10.0, channels=(), layer=None)


def test_only_mapped_value_channels_are_layers() -> None:
    assert check_layer(PLACED_MU, None) is None
    with pytest.raises(NotMappable, match=r"no map layer 'plain' \(its layers: \['mu'\]\)"):
        check_layer(PLACED_MU, "plain")
