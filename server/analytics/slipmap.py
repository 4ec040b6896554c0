"""Slip map: one estimator's rows binned into square cells of a local ENU frame (pure numpy).

The dashboard's history page draws its heat grid from this map (``GET /vehicles/{id}/slipmap``).
Time weights, "moving", slip validity and slip bands are those of the field reports
(:mod:`server.analytics.reports`), so a map over a range and the report over the same range agree:
the ``time_s`` of all cells is the report's ``moving_s`` less the moving time without a position.
Every field is read through the estimator's spec: its ``position`` channel (east, north, up),
its ``motion`` speed channel and its slip channels; a spec without a position or a motion channel
cannot be mapped (:func:`check_mappable`), one without slip channels gives time and distance only.

Definitions
-----------
Cell
    Cell ``(i, j)`` of side ``c = cell_m`` holds the positions with ``i = floor(east / c)``,
    ``j = floor(north / c)``; its south-west corner is ``(i·c, j·c)`` in the frame.
Samples
    Rows that are **moving** (``|v| >= min_ground_speed_mps``, ``v`` the spec's motion field)
    and have a finite east and north. Row ``i`` weighs ``w_i``, the report's time weight,
    computed over the vehicle's whole series in the range (moving or not, placed or not), so a
    row's weight does not depend on which rows the map keeps.
Per cell, over its samples ``i`` (and slip channels ``k`` of the spec)
    * ``time_s = Σ w_i``; ``distance_m = Σ |v|_i · w_i``; ``rows`` = number of samples.
    * ``slip_valid_s[k] = Σ w_i`` over the samples whose channel ``k`` slip is valid (its
      ``valid_flag`` and finite); ``slip_mean_pct[k] = Σ w_i s_ik / slip_valid_s[k]``, the
      time-weighted mean **signed** slip; NaN when ``slip_valid_s[k]`` is 0.
    * Over the valid channel-samples ``(i, k)`` of every channel (a row with two channels
      valid counts twice): ``mean_abs_slip_pct = Σ w_i |s_ik| / Σ w_i``;
      ``max_abs_slip_pct = max |s_ik|``;
      the share of band ``b`` (edges ``band_edges_pct``, an edge in the upper band)
      ``Σ_{|s_ik| in b} w_i / Σ w_i``. NaN when the cell has no valid slip time (its time and
      distance are still given); the shares then sum to 1.
    * ``vehicles``: how many reductions (:func:`cell_sums` calls, one per vehicle) put samples
      into the cell; 1 in a single vehicle's map.
    * With a **layer** (a mapped :class:`estimator.spec.ValueChannel` of the spec, e.g. friction
      μ), over the samples that inform it (its ``valid_flag`` set and a finite value ``x_i``):
      ``layer_valid_s = Σ w_i``, ``layer_mean = Σ w_i x_i / layer_valid_s`` (NaN when 0) and
      ``layer_samples``, how many such samples.

Reduce, merge, finish
---------------------
Every statistic above is a ratio of sums (or a maximum), so a map is made in three steps:
:func:`cell_sums` reduces samples to per-cell **partial sums** (:class:`CellSums`: ``Σ w``,
``Σ |v| w``, row count, per channel ``Σ w`` and ``Σ w s`` over valid slips, ``Σ w |s|``,
``Σ w`` per band, ``max |s|``, contributors); :func:`merge_cell_sums` adds the sums of cells
with the same index (and takes the larger maximum); :func:`finish_cells` divides. Merging the
sums of two halves of a series gives the map of the whole (to rounding). A fleet map reduces
one vehicle at a time and merges, so it never holds more than one vehicle's rows.

Fleet maps: one frame for all
-----------------------------
Each vehicle's east/north/up are metres in its own ENU frame. Before binning into a shared
frame, :func:`reframe` takes its samples through WGS 84 (its frame's ``to_geodetic``, then the
shared frame's ``to_enu``; exact ECEF transformations, no small-field approximation). A row
without a finite up is taken on its frame's horizontal plane (up 0): over a field of ``d``
metres that moves it horizontally by about
``|up| · d / 6.4e6`` m.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from estimator.geo import EnuFrame
from estimator.spec import EstimatorSpec, PositionChannel, ValueChannel
from server.analytics.reports import (
    band_bounds,
    band_index,
    band_label,
    channel_slips,
    check_band_edges,
    motion_speed,
    time_weights_ns,
)

__all__ = [
    "CellSums",
    "MapSamples",
    "NotMappable",
    "SlipMap",
    "TooManyCells",
    "bin_cells",
    "cell_sums",
    "check_layer",
    "check_mappable",
    "finish_cells",
    "map_samples",
    "merge_cell_sums",
    "reframe",
    "slip_map",
    "slipmap_fields",
]

_NS = 1_000_000_000


class NotMappable(ValueError):  # noqa: N818  (a ValueError: the estimator cannot give a map)
    """The estimator's spec has no position or no motion channel."""


def check_mappable(spec: EstimatorSpec) -> tuple[PositionChannel, str]:
    """``(spec.position, spec.motion_field)``, or :class:`NotMappable` naming what is missing."""
    if spec.position is None:
        raise NotMappable(f"estimator {spec.name!r} gives no position: it cannot be mapped")
    if spec.motion_field is None:
        raise NotMappable(f"estimator {spec.name!r} has no motion speed: it cannot be mapped")
    return spec.position, spec.motion_field


def check_layer(spec: EstimatorSpec, key: str | None) -> ValueChannel | None:
    """The mapped value channel ``key`` of ``spec`` (None for None), or :class:`NotMappable`
    naming the layers it has."""
    if key is None:
        return None
    for v in spec.values:
        if v.key == key and v.mapped:
            return v
    have = [v.key for v in spec.values if v.mapped]
    raise NotMappable(f"estimator {spec.name!r} has no map layer {key!r} (its layers: {have})")


def slipmap_fields(
    spec: EstimatorSpec, *, fleet: bool = False, layer: ValueChannel | None = None
) -> list[str]:
    """The fields of ``spec`` a map reads (ask the store for these only): ``stamp_ns``, the
    motion field, the slip channels' fields, the ``layer``'s field, ``flags``, east and north,
    and with ``fleet`` the up field too (the change of frame needs it). :class:`NotMappable` if
    it cannot be mapped."""
    position, motion = check_mappable(spec)
    wanted: list[str | None] = ["stamp_ns", motion, *(s.field for s in spec.slips)]
    if layer is not None:
        wanted.append(layer.field)
    if spec.has_field("flags"):
        wanted.append("flags")
    wanted += [position.east_field, position.north_field]
    if fleet:
        wanted.append(position.up_field)
    return list(dict.fromkeys(f for f in wanted if f is not None))


class TooManyCells(ValueError):  # noqa: N818  (a ValueError: the arguments ask too much)
    """The samples fall into more cells than ``max_cells``."""

    def __init__(self, cells: int, max_cells: int) -> None:
        super().__init__(f"{cells} cells exceed the limit of {max_cells}")
        self.cells = cells
        self.max_cells = max_cells


@dataclass(frozen=True, slots=True)
class MapSamples:
    """The rows a map bins (see the module docstring), ``n`` of them, ``K`` slip channels.

    Attributes
    ----------
    channels : tuple of str, length K
        Keys of the slip channels, in the spec's order.
    east_m, north_m : float64, shape (n,)
        Position in the map's frame, finite.
    up_m : float64, shape (n,)
        Height over the frame's horizontal plane; 0 where the row has none.
    w_ns : int64, shape (n,)
        Time weight of each sample.
    speed_mps : float64, shape (n,)
        ``|v|`` of the motion field.
    slip_pct : float64, shape (n, K)
        Signed slip of each channel.
    slip_valid : bool, shape (n, K)
        Whether each channel's slip is valid.
    layer_value : float64, shape (n,)
        The map layer's value (NaN without a layer).
    layer_valid : bool, shape (n,)
        Whether the sample informs the layer (all False without one).
    """

    channels: tuple[str, ...]
    east_m: np.ndarray
    north_m: np.ndarray
    up_m: np.ndarray
    w_ns: np.ndarray
    speed_mps: np.ndarray
    slip_pct: np.ndarray
    slip_valid: np.ndarray
    layer_value: np.ndarray
    layer_valid: np.ndarray

    @property
    def size(self) -> int:
        return int(self.east_m.shape[0])


def _layer_values(
    rows: np.ndarray, spec: EstimatorSpec, layer: ValueChannel | None
) -> tuple[np.ndarray, np.ndarray]:
    """``(value, informs)`` of every row (shape (n,)): the layer's field, and whether the row
    has its ``valid_flag`` and a finite value; NaN and False without a layer."""
    n = rows.shape[0]
    if layer is None:
        return np.full(n, np.nan), np.zeros(n, dtype=bool)
    value = rows[layer.field].astype(np.float64)
    informs = np.isfinite(value)
    if layer.valid_flag is not None:
        informs &= (rows["flags"].astype(np.int64) & spec.flag_mask(layer.valid_flag)) != 0
    return value, informs


def map_samples(
    rows: np.ndarray,
    spec: EstimatorSpec,
    *,
    end_ns: int,
    min_ground_speed_mps: float = 0.2,
    max_gap_s: float = 1.0,
    layer: ValueChannel | None = None,
) -> MapSamples:
    """The samples of one vehicle's series: moving rows with a position, with their weights.

    Parameters
    ----------
    rows : ndarray, shape (n,), structured with at least :func:`slipmap_fields` of ``spec``
        One vehicle's estimates of the range, sorted by ``stamp_ns``; the up field is read when
        present (``fleet=True``), else taken as 0.
    spec : the estimator whose rows these are (:class:`NotMappable` without position or motion).
    end_ns : end of the range (clips the last row's weight, as in the report).
    min_ground_speed_mps : speed from which a row counts as moving.
    max_gap_s : a step between rows longer than this is a data gap.
    layer : a mapped value channel of ``spec`` (:func:`check_layer`) whose value to carry.
    """
    position, _ = check_mappable(spec)
    w_ns = time_weights_ns(rows["stamp_ns"].astype(np.int64), end_ns, round(max_gap_s * _NS))
    motion = motion_speed(rows, spec, min_ground_speed_mps)
    assert motion is not None  # check_mappable: the spec has a motion field
    speed, moving = motion
    east = rows[position.east_field].astype(np.float64)
    north = rows[position.north_field].astype(np.float64)
    keep = moving & np.isfinite(east) & np.isfinite(north)
    slip_pct, slip_valid = _kept_slips(rows, spec, keep)
    layer_value, layer_valid = _layer_values(rows, spec, layer)
    return MapSamples(
        channels=tuple(c.key for c in spec.slips),
        east_m=east[keep],
        north_m=north[keep],
        up_m=_kept_up(rows, position, keep),
        w_ns=w_ns[keep],
        speed_mps=speed[keep],
        slip_pct=slip_pct,
        slip_valid=slip_valid,
        layer_value=layer_value[keep],
        layer_valid=layer_valid[keep],
    )


def _kept_up(rows: np.ndarray, position: PositionChannel, keep: np.ndarray) -> np.ndarray:
    """The up of the ``keep`` rows (bool, shape (n,)) as float64, shape (m,); 0 where it is
    not finite or the rows carry no up field."""
    up = np.zeros(int(keep.sum()))
    if position.up_field is not None and position.up_field in (rows.dtype.names or ()):
        up_kept = rows[position.up_field][keep].astype(np.float64)
        up = np.where(np.isfinite(up_kept), up_kept, 0.0)
    return up


def _kept_slips(
    rows: np.ndarray, spec: EstimatorSpec, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The slip (float64) and its validity (bool) of each of the spec's K slip channels in
    the ``keep`` rows (bool, shape (n,)): each shape (m, K)."""
    slips = channel_slips(rows, spec)
    m = int(keep.sum())
    if not slips:
        return np.zeros((m, 0)), np.zeros((m, 0), dtype=bool)
    return (
        np.stack([slip[keep] for slip, _ in slips], axis=1),
        np.stack([valid[keep] for _, valid in slips], axis=1),
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
class _CellGrid:
    """What every per-cell table starts with: the side of its cells, its slip bands and
    channels, and the indices of its ``m`` cells (int64, shape (m,)), ordered by
    ``index_east``, then ``index_north``."""

    cell_m: float
    band_edges_pct: tuple[float, ...]
    channels: tuple[str, ...]
    index_east: np.ndarray
    index_north: np.ndarray

    @property
    def cells(self) -> int:
        return int(self.index_east.shape[0])


@dataclass(frozen=True, slots=True)
class CellSums(_CellGrid):
    """Mergeable per-cell partial sums of a slip map (module docstring), ``m`` cells, ``B`` bands.

    Cells are ordered by ``index_east``, then ``index_north``. Times are in nanoseconds (sums of
    int ns, exact in float64 below 2**53 ns, 104 days).

    Attributes
    ----------
    cell_m : side of a cell.
    band_edges_pct : the slip band edges (``B - 1`` of them).
    channels : tuple of str, length K
        Keys of the slip channels.
    index_east, index_north : int64, shape (m,)
    time_ns : float64, shape (m,)
        ``Σ w``.
    speed_ns : float64, shape (m,)
        ``Σ |v| · w`` (metres times 1e9).
    rows : int64, shape (m,)
    valid_ns, signed_ns : float64, shape (m, K)
        Per channel, over its valid slips: ``Σ w`` and ``Σ w · s``.
    abs_ns : float64, shape (m,)
        ``Σ w · |s|`` over the valid channel-samples of every channel.
    band_ns : float64, shape (m, B)
        ``Σ w`` of the valid channel-samples with ``|s|`` in each band.
    max_abs_pct : float64, shape (m,)
        ``max |s|``; NaN where the cell has no valid slip.
    vehicles : int64, shape (m,)
        Reductions that put samples into the cell.
    layer : str or None
        Key of the map layer (a value channel), None without one.
    layer_ns, layer_sum_ns : float64, shape (m,)
        Over the samples that inform the layer: ``Σ w`` and ``Σ w · x``.
    layer_rows : int64, shape (m,)
        How many samples inform the layer.
    """

    time_ns: np.ndarray
    speed_ns: np.ndarray
    rows: np.ndarray
    valid_ns: np.ndarray
    signed_ns: np.ndarray
    abs_ns: np.ndarray
    band_ns: np.ndarray
    max_abs_pct: np.ndarray
    vehicles: np.ndarray
    layer: str | None
    layer_ns: np.ndarray
    layer_sum_ns: np.ndarray
    layer_rows: np.ndarray


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
    layer: str | None = None,
) -> CellSums:
    """Reduce samples to the partial sums of the cells of ``cell_m`` they fall into.

    ``np.unique`` over the cell indices gives every sample its cell ``c``; each sum of the
    module docstring is then one ``np.bincount`` with weights, over ``c`` (per channel over
    ``K·c + k``, per band over ``c·B + b`` for ``B`` bands), the maximum one ``np.fmax.at``.

    Parameters
    ----------
    samples : MapSamples, ``n`` samples.
    cell_m : side of a cell, metres.
    band_edges_pct : increasing edges of the slip bands, percent of ``|slip|``.
    max_cells : refuse more cells than this (None: no limit).
    layer : key of the map layer the samples carry (None: none).

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
    index_east, index_north, cell = _cell_keys(
        np.floor(samples.east_m / cell_m).astype(np.int64),
        np.floor(samples.north_m / cell_m).astype(np.int64),
        max_cells,
    )
    return _reduced(samples, cell_m, edges, (index_east, index_north, cell), layer)


def _reduced(
    samples: MapSamples,
    cell_m: float,
    edges: tuple[float, ...],
    keys: tuple[np.ndarray, np.ndarray, np.ndarray],
    layer: str | None,
) -> CellSums:
    """The partial sums of :func:`cell_sums` over the cells ``keys`` (:func:`_cell_keys`'
    ``index_east``, ``index_north``: shape (m,), and each sample's ``cell``: shape (n,))."""
    index_east, index_north, cell = keys
    m = int(index_east.shape[0])
    w = samples.w_ns.astype(np.float64)  # sums of int ns stay exact in float64 (< 2**53)
    valid_ns, signed_ns, abs_ns, band_ns, max_abs = _slip_sums(samples, cell, w, m, edges)
    layer_ns, layer_sum_ns, layer_rows = _layer_sums(samples, cell, w, m)
    return CellSums(
        cell_m=float(cell_m),
        band_edges_pct=edges,
        channels=samples.channels,
        index_east=index_east,
        index_north=index_north,
        time_ns=_sum_by(cell, w, m),
        speed_ns=_sum_by(cell, w * samples.speed_mps, m),
        rows=np.bincount(cell, minlength=m).astype(np.int64),
        valid_ns=valid_ns,
        signed_ns=signed_ns,
        abs_ns=abs_ns,
        band_ns=band_ns,
        max_abs_pct=max_abs,
        vehicles=np.ones(m, dtype=np.int64),
        layer=layer,
        layer_ns=layer_ns,
        layer_sum_ns=layer_sum_ns,
        layer_rows=layer_rows,
    )


def _slip_sums(
    samples: MapSamples, cell: np.ndarray, w: np.ndarray, m: int, edges: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The slip sums of ``m`` cells over the valid channel-samples ``(i, k)``: per channel
    ``Σ w`` and ``Σ w · s`` (shape (m, K)), ``Σ w · |s|`` (m,), ``Σ w`` per band (m, B) and
    ``max |s|`` (m,; NaN without a valid slip). ``cell`` and ``w`` (shape (n,)): each sample's
    cell and weight."""
    n_channels = len(samples.channels)
    pair_row, pair_channel = np.nonzero(samples.slip_valid)
    pair_cell = cell[pair_row]
    pair_w = w[pair_row]
    pair_slip = samples.slip_pct[pair_row, pair_channel]
    pair_abs = np.abs(pair_slip)
    max_abs = np.full(m, np.nan)
    np.fmax.at(max_abs, pair_cell, pair_abs)
    return (
        _sum_at(pair_cell, pair_channel, n_channels, pair_w, m),
        _sum_at(pair_cell, pair_channel, n_channels, pair_w * pair_slip, m),
        _sum_by(pair_cell, pair_w * pair_abs, m),
        _sum_at(pair_cell, band_index(pair_abs, edges), len(edges) + 1, pair_w, m),
        max_abs,
    )


def _layer_sums(
    samples: MapSamples, cell: np.ndarray, w: np.ndarray, m: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The layer sums of ``m`` cells over the samples that inform it: ``Σ w``, ``Σ w · x``
    (float64) and their count (int64), each shape (m,)."""
    informs = samples.layer_valid
    layer_w = np.where(informs, w, 0.0)
    return (
        _sum_by(cell, layer_w, m),
        _sum_by(cell, layer_w * np.where(informs, samples.layer_value, 0.0), m),
        np.bincount(cell, weights=informs, minlength=m).astype(np.int64),
    )


def merge_cell_sums(
    parts: Iterable[CellSums],
    *,
    cell_m: float,
    channels: tuple[str, ...],
    band_edges_pct: Sequence[float] = (5.0, 15.0),
    max_cells: int | None = None,
    layer: str | None = None,
) -> CellSums:
    """Merge partial sums cell by cell: sums add, maxima take the larger, ``vehicles`` add.

    ``parts`` is consumed one at a time and folded into a running total, so a generator that
    reduces one vehicle per step keeps one vehicle's rows in memory at a time. No parts give
    an empty map.

    Parameters
    ----------
    parts : CellSums, each of ``cell_m``, ``channels`` and ``band_edges_pct``.
    cell_m, channels, band_edges_pct, layer : those of every part (checked).
    max_cells : refuse a total of more cells than this (None: no limit); checked after each
        merge, so :class:`TooManyCells` names the count at the first merge that passed it.

    Raises
    ------
    ValueError
        A part of another ``cell_m``, other slip channels, band edges or layer.
    TooManyCells
        The merged cells exceed ``max_cells``.
    """
    edges = check_band_edges(band_edges_pct)
    total = _no_cells(float(cell_m), edges, tuple(channels), layer)
    want = (total.cell_m, edges, total.channels, layer)
    for part in parts:
        if (part.cell_m, part.band_edges_pct, part.channels, part.layer) != want:
            raise ValueError(
                f"cannot merge cells of {part.cell_m:g} m with bands {part.band_edges_pct}, "
                f"slip channels {part.channels} and layer {part.layer} into cells of "
                f"{total.cell_m:g} m with bands {edges}, slip channels {total.channels} and "
                f"layer {layer}"
            )
        total = _merge_two(total, part, max_cells)
    return total


def _no_cells(
    cell_m: float, edges: tuple[float, ...], channels: tuple[str, ...], layer: str | None
) -> CellSums:
    none = np.zeros(0)
    ids = np.zeros(0, dtype=np.int64)
    return CellSums(
        cell_m=cell_m,
        band_edges_pct=edges,
        channels=channels,
        index_east=ids,
        index_north=ids,
        time_ns=none,
        speed_ns=none,
        rows=ids,
        valid_ns=np.zeros((0, len(channels))),
        signed_ns=np.zeros((0, len(channels))),
        abs_ns=none,
        band_ns=np.zeros((0, len(edges) + 1)),
        max_abs_pct=none,
        vehicles=ids,
        layer=layer,
        layer_ns=none,
        layer_sum_ns=none,
        layer_rows=ids,
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
        channels=a.channels,
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
        layer=a.layer,
        layer_ns=add("layer_ns"),
        layer_sum_ns=add("layer_sum_ns"),
        layer_rows=add("layer_rows").astype(np.int64),
    )


@dataclass(frozen=True, slots=True)
class SlipMap(_CellGrid):
    """Per-cell statistics of a slip map (definitions in the module docstring), ``m`` cells.

    Cells are ordered by ``index_east``, then ``index_north``. Floats are NaN where undefined.

    Attributes
    ----------
    cell_m : side of a cell.
    band_edges_pct : the slip band edges.
    channels : tuple of str, length K
        Keys of the slip channels (columns of ``slip_valid_s`` and ``slip_mean_pct``).
    index_east, index_north : int64, shape (m,)
        Cell indices ``i``, ``j``; the south-west corner is ``(i·cell_m, j·cell_m)``.
    time_s, distance_m : float64, shape (m,)
    rows : int64, shape (m,)
    slip_valid_s, slip_mean_pct : float64, shape (m, K)
        Per slip channel: valid-slip time and time-weighted mean signed slip.
    mean_abs_slip_pct, max_abs_slip_pct : float64, shape (m,)
    band_share : float64, shape (m, len(band_edges_pct) + 1)
        Time share of ``|slip|`` in each band, lowest band first.
    vehicles : int64, shape (m,)
        Vehicles (reductions) that contributed to each cell.
    layer : str or None
        Key of the map layer, None without one.
    layer_valid_s, layer_mean : float64, shape (m,)
        Time of the samples that inform the layer, and the layer's time-weighted mean over them
        (NaN where none does).
    layer_samples : int64, shape (m,)
        How many samples inform the layer.
    """

    time_s: np.ndarray
    distance_m: np.ndarray
    rows: np.ndarray
    slip_valid_s: np.ndarray
    slip_mean_pct: np.ndarray
    mean_abs_slip_pct: np.ndarray
    max_abs_slip_pct: np.ndarray
    band_share: np.ndarray
    vehicles: np.ndarray
    layer: str | None
    layer_valid_s: np.ndarray
    layer_mean: np.ndarray
    layer_samples: np.ndarray
    band_labels: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        labels = tuple(band_label(lo, up) for lo, up in band_bounds(self.band_edges_pct))
        object.__setattr__(self, "band_labels", labels)

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
        channels=sums.channels,
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
        layer=sums.layer,
        layer_valid_s=sums.layer_ns / _NS,
        layer_mean=_ratio(sums.layer_sum_ns, sums.layer_ns),
        layer_samples=sums.layer_rows,
    )


def bin_cells(
    samples: MapSamples,
    *,
    cell_m: float,
    band_edges_pct: Sequence[float] = (5.0, 15.0),
    max_cells: int | None = None,
    layer: str | None = None,
) -> SlipMap:
    """Bin samples into cells of ``cell_m`` and compute each cell's statistics:
    :func:`cell_sums` then :func:`finish_cells` (parameters and errors as there)."""
    return finish_cells(
        cell_sums(
            samples,
            cell_m=cell_m,
            band_edges_pct=band_edges_pct,
            max_cells=max_cells,
            layer=layer,
        )
    )


def slip_map(
    rows: np.ndarray,
    spec: EstimatorSpec,
    *,
    end_ns: int,
    cell_m: float,
    band_edges_pct: Sequence[float] = (5.0, 15.0),
    min_ground_speed_mps: float = 0.2,
    max_gap_s: float = 1.0,
    max_cells: int | None = None,
    layer: ValueChannel | None = None,
) -> SlipMap:
    """The slip map of one vehicle's series in its own frame: :func:`map_samples` then
    :func:`bin_cells` (parameters as there)."""
    samples = map_samples(
        rows,
        spec,
        end_ns=end_ns,
        min_ground_speed_mps=min_ground_speed_mps,
        max_gap_s=max_gap_s,
        layer=layer,
    )
    return bin_cells(
        samples,
        cell_m=cell_m,
        band_edges_pct=band_edges_pct,
        max_cells=max_cells,
        layer=None if layer is None else layer.key,
    )
