"""Slip map: estimates binned into square cells of a local ENU frame (pure numpy, no I/O).

The server-side, time-weighted counterpart of the dashboard's heat grid (``web/js/slipmap.js``).
Time weights, "moving", slip validity and slip bands are those of the field reports
(:mod:`server.reports`), so a map over a range and the report over the same range agree: the
``time_s`` of all cells is the report's ``moving_s`` less the moving time without a position.

Definitions
-----------
Cell
    Cell ``(i, j)`` of side ``c = cell_m`` holds the positions with ``i = floor(east_m / c)``,
    ``j = floor(north_m / c)``; its south-west corner is ``(i·c, j·c)`` in the frame.
Samples
    Rows that are **moving** (``|vg_mps| >= min_ground_speed_mps``) and have a finite
    ``east_m`` and ``north_m``. Row ``i`` weighs ``w_i``, the report's time weight, computed over
    the vehicle's whole series in the range (moving or not, placed or not), so a row's weight
    does not depend on which rows the map keeps.
Per cell, over its samples ``i`` (and wheels ``k`` in {left, right})
    * ``time_s = Σ w_i``; ``distance_m = Σ |vg_mps|_i · w_i``; ``rows`` = number of samples.
    * ``slip_k_valid_s = Σ w_i`` over the samples whose wheel ``k`` slip is valid
      (``SLIP_*_VALID`` flag and finite); ``slip_k_mean_pct = Σ w_i s_ik / slip_k_valid_s``,
      the time-weighted mean **signed** slip; NaN when ``slip_k_valid_s`` is 0.
    * Over the valid wheel-samples ``(i, k)`` of both wheels (a row with both wheels valid counts
      twice): ``mean_abs_slip_pct = Σ w_i |s_ik| / Σ w_i``; ``max_abs_slip_pct = max |s_ik|``;
      the share of band ``b`` (edges ``band_edges_pct``, an edge in the upper band)
      ``Σ_{|s_ik| in b} w_i / Σ w_i``. NaN when the cell has no valid slip time (its time and
      distance are still given); the shares then sum to 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from server.reports import (
    band_bounds,
    band_index,
    band_label,
    check_band_edges,
    ground_speed,
    time_weights_ns,
    wheel_slips,
)

__all__ = [
    "SLIPMAP_FIELDS",
    "MapSamples",
    "SlipMap",
    "TooManyCells",
    "bin_cells",
    "map_samples",
    "slip_map",
]

#: The estimate fields a slip map reads (ask the store for these only).
SLIPMAP_FIELDS: tuple[str, ...] = (
    "stamp_ns",
    "vg_mps",
    "slip_left_pct",
    "slip_right_pct",
    "flags",
    "east_m",
    "north_m",
)

_NS = 1_000_000_000
_WHEELS = 2


class TooManyCells(ValueError):  # noqa: N818  (a ValueError: the arguments ask too much)
    """The samples fall into more cells than ``max_cells``."""

    def __init__(self, cells: int, max_cells: int) -> None:
        super().__init__(f"{cells} cells exceed the limit of {max_cells}")
        self.cells = cells
        self.max_cells = max_cells


@dataclass(frozen=True, slots=True)
class MapSamples:
    """The rows a map bins (see the module docstring), ``n`` of them.

    Attributes
    ----------
    east_m, north_m : float64, shape (n,)
        Position in the map's frame, finite.
    w_ns : int64, shape (n,)
        Time weight of each sample.
    speed_mps : float64, shape (n,)
        ``|vg_mps|``.
    slip_pct : float64, shape (n, 2)
        Signed slip of the left and right wheel (column 0 and 1).
    slip_valid : bool, shape (n, 2)
        Whether each wheel's slip is valid.
    """

    east_m: np.ndarray
    north_m: np.ndarray
    w_ns: np.ndarray
    speed_mps: np.ndarray
    slip_pct: np.ndarray
    slip_valid: np.ndarray

    @property
    def size(self) -> int:
        return int(self.east_m.shape[0])


def map_samples(
    rows: np.ndarray,
    *,
    end_ns: int,
    min_ground_speed_mps: float = 0.2,
    max_gap_s: float = 1.0,
) -> MapSamples:
    """The samples of one vehicle's series: moving rows with a position, with their weights.

    Parameters
    ----------
    rows : ndarray, shape (n,), structured with at least :data:`SLIPMAP_FIELDS`
        One vehicle's estimates of the range, sorted by ``stamp_ns``.
    end_ns : end of the range (clips the last row's weight, as in the report).
    min_ground_speed_mps : speed from which a row counts as moving.
    max_gap_s : a step between rows longer than this is a data gap.
    """
    w_ns = time_weights_ns(rows["stamp_ns"].astype(np.int64), end_ns, round(max_gap_s * _NS))
    speed, moving = ground_speed(rows, min_ground_speed_mps)
    east = rows["east_m"].astype(np.float64)
    north = rows["north_m"].astype(np.float64)
    keep = moving & np.isfinite(east) & np.isfinite(north)
    wheels = wheel_slips(rows)
    return MapSamples(
        east_m=east[keep],
        north_m=north[keep],
        w_ns=w_ns[keep],
        speed_mps=speed[keep],
        slip_pct=np.stack([slip[keep] for slip, _ in wheels], axis=1),
        slip_valid=np.stack([valid[keep] for _, valid in wheels], axis=1),
    )


@dataclass(frozen=True, slots=True)
class SlipMap:
    """Per-cell statistics of a slip map (definitions in the module docstring), ``m`` cells.

    Cells are ordered by ``index_east``, then ``index_north``. Floats are NaN where undefined.

    Attributes
    ----------
    cell_m : side of a cell.
    band_edges_pct : the slip band edges.
    index_east, index_north : int64, shape (m,)
        Cell indices ``i``, ``j``; the south-west corner is ``(i·cell_m, j·cell_m)``.
    time_s, distance_m : float64, shape (m,)
    rows : int64, shape (m,)
    slip_valid_s, slip_mean_pct : float64, shape (m, 2)
        Per wheel (left, right): valid-slip time and time-weighted mean signed slip.
    mean_abs_slip_pct, max_abs_slip_pct : float64, shape (m,)
    band_share : float64, shape (m, len(band_edges_pct) + 1)
        Time share of ``|slip|`` in each band, lowest band first.
    """

    cell_m: float
    band_edges_pct: tuple[float, ...]
    index_east: np.ndarray
    index_north: np.ndarray
    time_s: np.ndarray
    distance_m: np.ndarray
    rows: np.ndarray
    slip_valid_s: np.ndarray
    slip_mean_pct: np.ndarray
    mean_abs_slip_pct: np.ndarray
    max_abs_slip_pct: np.ndarray
    band_share: np.ndarray
    band_labels: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        labels = tuple(band_label(lo, up) for lo, up in band_bounds(self.band_edges_pct))
        object.__setattr__(self, "band_labels", labels)

    @property
    def cells(self) -> int:
        return int(self.index_east.shape[0])

    @property
    def east_m(self) -> np.ndarray:
        """East of each cell's south-west corner, float64, shape (m,)."""
        return self.index_east * self.cell_m

    @property
    def north_m(self) -> np.ndarray:
        """North of each cell's south-west corner, float64, shape (m,)."""
        return self.index_north * self.cell_m


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """``num / den`` elementwise, NaN where ``den`` is 0 (``num`` broadcasts against ``den``)."""
    out = np.full(np.broadcast_shapes(num.shape, den.shape), np.nan)
    np.divide(num, den, out=out, where=den > 0)
    return out


def bin_cells(
    samples: MapSamples,
    *,
    cell_m: float,
    band_edges_pct: Sequence[float] = (5.0, 15.0),
    max_cells: int | None = None,
) -> SlipMap:
    """Bin samples into cells of ``cell_m`` and compute each cell's statistics.

    ``np.unique`` over the cell indices gives every sample its cell ``c``; each sum of the
    module docstring is then one ``np.bincount`` with weights, over ``c`` (per wheel over
    ``2c + k``, per band over ``c·B + b`` for ``B`` bands), the maximum one ``np.fmax.at``.

    Parameters
    ----------
    samples : MapSamples, ``n`` samples.
    cell_m : side of a cell, metres.
    band_edges_pct : increasing edges of the slip bands, percent of ``|slip|``.
    max_cells : refuse more cells than this (None: no limit).

    Raises
    ------
    ValueError
        ``cell_m`` not positive and finite, or band edges not increasing.
    TooManyCells
        More than ``max_cells`` cells (checked before any statistic is computed).
    """
    if not (np.isfinite(cell_m) and cell_m > 0):
        raise ValueError("cell_m must be positive and finite")
    edges = check_band_edges(band_edges_pct)
    n_bands = len(edges) + 1
    i_east = np.floor(samples.east_m / cell_m).astype(np.int64)
    i_north = np.floor(samples.north_m / cell_m).astype(np.int64)
    # dense codes per axis, then one key per cell: exact for any index range
    east_ids, east_code = np.unique(i_east, return_inverse=True)
    north_ids, north_code = np.unique(i_north, return_inverse=True)
    n_north = max(north_ids.shape[0], 1)
    keys, cell = np.unique(east_code * n_north + north_code, return_inverse=True)
    m = int(keys.shape[0])
    if max_cells is not None and m > max_cells:
        raise TooManyCells(m, max_cells)

    w = samples.w_ns.astype(np.float64)  # sums of int ns stay exact in float64 (< 2**53)
    time_ns = np.bincount(cell, weights=w, minlength=m)
    distance_m = np.bincount(cell, weights=w * samples.speed_mps, minlength=m) / _NS
    rows = np.bincount(cell, minlength=m).astype(np.int64)

    pair_row, pair_wheel = np.nonzero(samples.slip_valid)  # the valid wheel-samples (i, k)
    pair_cell = cell[pair_row]
    pair_w = w[pair_row]
    pair_slip = samples.slip_pct[pair_row, pair_wheel]
    pair_abs = np.abs(pair_slip)
    per_wheel = pair_cell * _WHEELS + pair_wheel
    valid_ns = np.bincount(per_wheel, weights=pair_w, minlength=m * _WHEELS).reshape(m, _WHEELS)
    signed_ns = np.bincount(per_wheel, weights=pair_w * pair_slip, minlength=m * _WHEELS)
    slip_ns = valid_ns.sum(axis=1)
    abs_ns = np.bincount(pair_cell, weights=pair_w * pair_abs, minlength=m)
    max_abs = np.full(m, np.nan)
    np.fmax.at(max_abs, pair_cell, pair_abs)
    per_band_ns = np.bincount(
        pair_cell * n_bands + band_index(pair_abs, edges),
        weights=pair_w,
        minlength=m * n_bands,
    ).reshape(m, n_bands)

    return SlipMap(
        cell_m=float(cell_m),
        band_edges_pct=edges,
        index_east=east_ids[keys // n_north].astype(np.int64),
        index_north=north_ids[keys % n_north].astype(np.int64),
        time_s=time_ns / _NS,
        distance_m=distance_m,
        rows=rows,
        slip_valid_s=valid_ns / _NS,
        slip_mean_pct=_ratio(signed_ns.reshape(m, _WHEELS), valid_ns),
        mean_abs_slip_pct=_ratio(abs_ns, slip_ns),
        max_abs_slip_pct=max_abs,
        band_share=_ratio(per_band_ns, slip_ns[:, None]),
    )


def slip_map(
    rows: np.ndarray,
    *,
    end_ns: int,
    cell_m: float,
    band_edges_pct: Sequence[float] = (5.0, 15.0),
    min_ground_speed_mps: float = 0.2,
    max_gap_s: float = 1.0,
    max_cells: int | None = None,
) -> SlipMap:
    """The slip map of one vehicle's series in its own frame: :func:`map_samples` then
    :func:`bin_cells` (parameters as there)."""
    samples = map_samples(
        rows, end_ns=end_ns, min_ground_speed_mps=min_ground_speed_mps, max_gap_s=max_gap_s
    )
    return bin_cells(samples, cell_m=cell_m, band_edges_pct=band_edges_pct, max_cells=max_cells)
