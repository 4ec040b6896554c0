"""Slip map: estimates binned into square cells of a local ENU frame (pure numpy, no I/O).

The dashboard's history page draws its heat grid from this map (``GET /vehicles/{id}/slipmap``).
Time weights, "moving", slip validity and slip bands are those of the field reports
(:mod:`server.analytics.reports`), so a map over a range and the report over the same range agree:
the ``time_s`` of all cells is the report's ``moving_s`` less the moving time without a position.

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
    * ``vehicles``: how many reductions (:func:`cell_sums` calls, one per vehicle) put samples
      into the cell; 1 in a single vehicle's map.

Reduce, merge, finish
---------------------
Every statistic above is a ratio of sums (or a maximum), so a map is made in three steps:
:func:`cell_sums` reduces samples to per-cell **partial sums** (:class:`CellSums`: ``Σ w``,
``Σ |v| w``, row count, per wheel ``Σ w`` and ``Σ w s`` over valid slips, ``Σ w |s|``,
``Σ w`` per band, ``max |s|``, contributors); :func:`merge_cell_sums` adds the sums of cells
with the same index (and takes the larger maximum); :func:`finish_cells` divides. Merging the
sums of two halves of a series gives the map of the whole (to rounding). A fleet map reduces
one vehicle at a time and merges, so it never holds more than one vehicle's rows.

Fleet maps: one frame for all
-----------------------------
Each vehicle's ``east_m``/``north_m``/``up_m`` are metres in its own ENU frame. Before binning
into a shared frame, :func:`reframe` takes its samples through WGS 84 (its frame's
``to_geodetic``, then the shared frame's ``to_enu``; exact ECEF transformations, no small-field
approximation). A row without a finite ``up_m`` is taken on its frame's horizontal plane
(``up_m`` 0): over a field of ``d`` metres that moves it horizontally by about
``|up| · d / 6.4e6`` m.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from estimator.geo import EnuFrame
from server.analytics.reports import (
    band_bounds,
    band_index,
    band_label,
    check_band_edges,
    ground_speed,
    time_weights_ns,
    wheel_slips,
)

__all__ = [
    "FLEET_SLIPMAP_FIELDS",
    "SLIPMAP_FIELDS",
    "CellSums",
    "MapSamples",
    "SlipMap",
    "TooManyCells",
    "bin_cells",
    "cell_sums",
    "finish_cells",
    "map_samples",
    "merge_cell_sums",
    "reframe",
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

#: The fields a fleet map reads: those of :data:`SLIPMAP_FIELDS` and ``up_m``, which the
#: change of frame needs.
FLEET_SLIPMAP_FIELDS: tuple[str, ...] = (*SLIPMAP_FIELDS, "up_m")

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
    up_m : float64, shape (n,)
        Height over the frame's horizontal plane; 0 where the row has none.
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
    up_m: np.ndarray
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
        One vehicle's estimates of the range, sorted by ``stamp_ns``; ``up_m`` is read when
        present (:data:`FLEET_SLIPMAP_FIELDS`), else taken as 0.
    end_ns : end of the range (clips the last row's weight, as in the report).
    min_ground_speed_mps : speed from which a row counts as moving.
    max_gap_s : a step between rows longer than this is a data gap.
    """
    w_ns = time_weights_ns(rows["stamp_ns"].astype(np.int64), end_ns, round(max_gap_s * _NS))
    speed, moving = ground_speed(rows, min_ground_speed_mps)
    east = rows["east_m"].astype(np.float64)
    north = rows["north_m"].astype(np.float64)
    keep = moving & np.isfinite(east) & np.isfinite(north)
    up = np.zeros(int(keep.sum()))
    if "up_m" in (rows.dtype.names or ()):
        up_kept = rows["up_m"][keep].astype(np.float64)
        up = np.where(np.isfinite(up_kept), up_kept, 0.0)
    wheels = wheel_slips(rows)
    return MapSamples(
        east_m=east[keep],
        north_m=north[keep],
        up_m=up,
        w_ns=w_ns[keep],
        speed_mps=speed[keep],
        slip_pct=np.stack([slip[keep] for slip, _ in wheels], axis=1),
        slip_valid=np.stack([valid[keep] for _, valid in wheels], axis=1),
    )


def reframe(samples: MapSamples, source: EnuFrame, target: EnuFrame) -> MapSamples:
    """The samples with their positions moved from the ENU frame ``source`` to ``target``.

    ``(east, north, up)`` of ``source`` → geodetic (``source.to_geodetic``) → ENU of ``target``
    (``target.to_enu``), all samples at once; the same samples when the frames are equal.
    """
    if source == target:
        return samples
    lat_deg, lon_deg, h_m = source.to_geodetic(samples.east_m, samples.north_m, samples.up_m)
    east_m, north_m, up_m = target.to_enu(lat_deg, lon_deg, h_m)
    return replace(samples, east_m=east_m, north_m=north_m, up_m=up_m)


@dataclass(frozen=True, slots=True)
class CellSums:
    """Mergeable per-cell partial sums of a slip map (module docstring), ``m`` cells, ``B`` bands.

    Cells are ordered by ``index_east``, then ``index_north``. Times are in nanoseconds (sums of
    int ns, exact in float64 below 2**53 ns, 104 days).

    Attributes
    ----------
    cell_m : side of a cell.
    band_edges_pct : the slip band edges (``B - 1`` of them).
    index_east, index_north : int64, shape (m,)
    time_ns : float64, shape (m,)
        ``Σ w``.
    speed_ns : float64, shape (m,)
        ``Σ |vg_mps| · w`` (metres times 1e9).
    rows : int64, shape (m,)
    valid_ns, signed_ns : float64, shape (m, 2)
        Per wheel, over its valid slips: ``Σ w`` and ``Σ w · s``.
    abs_ns : float64, shape (m,)
        ``Σ w · |s|`` over the valid wheel-samples of both wheels.
    band_ns : float64, shape (m, B)
        ``Σ w`` of the valid wheel-samples with ``|s|`` in each band.
    max_abs_pct : float64, shape (m,)
        ``max |s|``; NaN where the cell has no valid slip.
    vehicles : int64, shape (m,)
        Reductions that put samples into the cell.
    """

    cell_m: float
    band_edges_pct: tuple[float, ...]
    index_east: np.ndarray
    index_north: np.ndarray
    time_ns: np.ndarray
    speed_ns: np.ndarray
    rows: np.ndarray
    valid_ns: np.ndarray
    signed_ns: np.ndarray
    abs_ns: np.ndarray
    band_ns: np.ndarray
    max_abs_pct: np.ndarray
    vehicles: np.ndarray

    @property
    def cells(self) -> int:
        return int(self.index_east.shape[0])


def _cell_keys(
    i_east: np.ndarray, i_north: np.ndarray, max_cells: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct cells of index pairs ``(i_east, i_north)`` (int64, shape (n,)).

    Returns ``(index_east, index_north, cell)``: the ``m`` distinct pairs ordered by east, then
    north, and the position of each input pair among them (shape (n,)). Dense codes per axis,
    then one key per pair: exact for any index range.

    Raises :class:`TooManyCells` when ``m > max_cells``.
    """
    east_ids, east_code = np.unique(i_east, return_inverse=True)
    north_ids, north_code = np.unique(i_north, return_inverse=True)
    n_north = max(north_ids.shape[0], 1)
    keys, cell = np.unique(east_code * n_north + north_code, return_inverse=True)
    m = int(keys.shape[0])
    if max_cells is not None and m > max_cells:
        raise TooManyCells(m, max_cells)
    index_east = east_ids[keys // n_north].astype(np.int64)
    index_north = north_ids[keys % n_north].astype(np.int64)
    return index_east, index_north, cell.reshape(-1)


def _sum_at(
    cell: np.ndarray, column: np.ndarray, k: int, weights: np.ndarray, m: int
) -> np.ndarray:
    """Sums of ``weights`` at ``(cell, column)`` (all shape (n,)) in an ``(m, k)`` table."""
    return np.bincount(cell * k + column, weights=weights, minlength=m * k).reshape(m, k)


def _sum_by(cell: np.ndarray, values: np.ndarray, m: int) -> np.ndarray:
    """Sum of ``values`` (shape (n,) or (n, k)) over equal ``cell`` (shape (n,)): (m,) or (m, k)."""
    if values.ndim == 1:
        return np.bincount(cell, weights=values, minlength=m)
    n, k = values.shape
    return _sum_at(np.repeat(cell, k), np.tile(np.arange(k), n), k, values.reshape(-1), m)


def cell_sums(
    samples: MapSamples,
    *,
    cell_m: float,
    band_edges_pct: Sequence[float] = (5.0, 15.0),
    max_cells: int | None = None,
) -> CellSums:
    """Reduce samples to the partial sums of the cells of ``cell_m`` they fall into.

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
        More than ``max_cells`` cells (checked before any sum is computed).
    """
    if not (np.isfinite(cell_m) and cell_m > 0):
        raise ValueError("cell_m must be positive and finite")
    edges = check_band_edges(band_edges_pct)
    n_bands = len(edges) + 1
    index_east, index_north, cell = _cell_keys(
        np.floor(samples.east_m / cell_m).astype(np.int64),
        np.floor(samples.north_m / cell_m).astype(np.int64),
        max_cells,
    )
    m = int(index_east.shape[0])

    w = samples.w_ns.astype(np.float64)  # sums of int ns stay exact in float64 (< 2**53)
    pair_row, pair_wheel = np.nonzero(samples.slip_valid)  # the valid wheel-samples (i, k)
    pair_cell = cell[pair_row]
    pair_w = w[pair_row]
    pair_slip = samples.slip_pct[pair_row, pair_wheel]
    pair_abs = np.abs(pair_slip)
    max_abs = np.full(m, np.nan)
    np.fmax.at(max_abs, pair_cell, pair_abs)
    return CellSums(
        cell_m=float(cell_m),
        band_edges_pct=edges,
        index_east=index_east,
        index_north=index_north,
        time_ns=_sum_by(cell, w, m),
        speed_ns=_sum_by(cell, w * samples.speed_mps, m),
        rows=np.bincount(cell, minlength=m).astype(np.int64),
        valid_ns=_sum_at(pair_cell, pair_wheel, _WHEELS, pair_w, m),
        signed_ns=_sum_at(pair_cell, pair_wheel, _WHEELS, pair_w * pair_slip, m),
        abs_ns=_sum_by(pair_cell, pair_w * pair_abs, m),
        band_ns=_sum_at(pair_cell, band_index(pair_abs, edges), n_bands, pair_w, m),
        max_abs_pct=max_abs,
        vehicles=np.ones(m, dtype=np.int64),
    )


def merge_cell_sums(
    parts: Iterable[CellSums],
    *,
    cell_m: float,
    band_edges_pct: Sequence[float] = (5.0, 15.0),
    max_cells: int | None = None,
) -> CellSums:
    """Merge partial sums cell by cell: sums add, maxima take the larger, ``vehicles`` add.

    ``parts`` is consumed one at a time and folded into a running total, so a generator that
    reduces one vehicle per step keeps one vehicle's rows in memory at a time. No parts give
    an empty map.

    Parameters
    ----------
    parts : CellSums, each of ``cell_m`` and ``band_edges_pct``.
    cell_m, band_edges_pct : those of every part (checked).
    max_cells : refuse a total of more cells than this (None: no limit); checked after each
        merge, so :class:`TooManyCells` names the count at the first merge that passed it.

    Raises
    ------
    ValueError
        A part of another ``cell_m`` or other band edges.
    TooManyCells
        The merged cells exceed ``max_cells``.
    """
    edges = check_band_edges(band_edges_pct)
    total = _no_cells(float(cell_m), edges)
    for part in parts:
        if part.cell_m != total.cell_m or part.band_edges_pct != edges:
            raise ValueError(
                f"cannot merge cells of {part.cell_m:g} m with bands {part.band_edges_pct} "
                f"into cells of {total.cell_m:g} m with bands {edges}"
            )
        total = _merge_two(total, part, max_cells)
    return total


def _no_cells(cell_m: float, edges: tuple[float, ...]) -> CellSums:
    none = np.zeros(0)
    ids = np.zeros(0, dtype=np.int64)
    return CellSums(
        cell_m=cell_m,
        band_edges_pct=edges,
        index_east=ids,
        index_north=ids,
        time_ns=none,
        speed_ns=none,
        rows=ids,
        valid_ns=np.zeros((0, _WHEELS)),
        signed_ns=np.zeros((0, _WHEELS)),
        abs_ns=none,
        band_ns=np.zeros((0, len(edges) + 1)),
        max_abs_pct=none,
        vehicles=ids,
    )


def _merge_two(a: CellSums, b: CellSums, max_cells: int | None) -> CellSums:
    index_east, index_north, cell = _cell_keys(
        np.concatenate([a.index_east, b.index_east]),
        np.concatenate([a.index_north, b.index_north]),
        max_cells,
    )
    m = int(index_east.shape[0])

    def add(name: str) -> np.ndarray:
        return _sum_by(cell, np.concatenate([getattr(a, name), getattr(b, name)]), m)

    max_abs = np.full(m, np.nan)
    np.fmax.at(max_abs, cell, np.concatenate([a.max_abs_pct, b.max_abs_pct]))
    return CellSums(
        cell_m=a.cell_m,
        band_edges_pct=a.band_edges_pct,
        index_east=index_east,
        index_north=index_north,
        time_ns=add("time_ns"),
        speed_ns=add("speed_ns"),
        rows=add("rows").astype(np.int64),  # row counts < 2**53: exact through float64
        valid_ns=add("valid_ns"),
        signed_ns=add("signed_ns"),
        abs_ns=add("abs_ns"),
        band_ns=add("band_ns"),
        max_abs_pct=max_abs,
        vehicles=add("vehicles").astype(np.int64),
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
    vehicles : int64, shape (m,)
        Vehicles (reductions) that contributed to each cell.
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
    vehicles: np.ndarray
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


def finish_cells(sums: CellSums) -> SlipMap:
    """Each cell's statistics (module docstring) from its partial sums."""
    slip_ns = sums.valid_ns.sum(axis=1)
    return SlipMap(
        cell_m=sums.cell_m,
        band_edges_pct=sums.band_edges_pct,
        index_east=sums.index_east,
        index_north=sums.index_north,
        time_s=sums.time_ns / _NS,
        distance_m=sums.speed_ns / _NS,
        rows=sums.rows,
        slip_valid_s=sums.valid_ns / _NS,
        slip_mean_pct=_ratio(sums.signed_ns, sums.valid_ns),
        mean_abs_slip_pct=_ratio(sums.abs_ns, slip_ns),
        max_abs_slip_pct=sums.max_abs_pct,
        band_share=_ratio(sums.band_ns, slip_ns[:, None]),
        vehicles=sums.vehicles,
    )


def bin_cells(
    samples: MapSamples,
    *,
    cell_m: float,
    band_edges_pct: Sequence[float] = (5.0, 15.0),
    max_cells: int | None = None,
) -> SlipMap:
    """Bin samples into cells of ``cell_m`` and compute each cell's statistics:
    :func:`cell_sums` then :func:`finish_cells` (parameters and errors as there)."""
    return finish_cells(
        cell_sums(samples, cell_m=cell_m, band_edges_pct=band_edges_pct, max_cells=max_cells)
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
