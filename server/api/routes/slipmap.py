"""Slip maps: ``/vehicles/{id}/slipmap`` and ``/fleet/slipmap`` (JSON, GeoJSON or CSV).

The statistics are :mod:`server.analytics.slipmap`'s, over one estimator's rows read through its
spec (``?estimator=``, default the vehicle's primary); this module reads the rows, picks the frame
and writes the answer. GeoJSON cells are polygons whose corners go through the frame's
:meth:`estimator.geo.EnuFrame.to_geodetic` on its horizontal plane (``up`` 0).

The fleet map reads and reduces one vehicle at a time (:func:`_vehicle_cells`) and merges the
partial sums as it goes (:func:`server.analytics.slipmap.merge_cell_sums`): memory holds one
vehicle's rows and the merged cells, never the fleet's rows.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Response

from estimator.catalog import SPECS
from estimator.config import SlipConfig
from estimator.geo import EnuFrame
from estimator.spec import EstimatorSpec, ValueChannel
from server.analytics.isoxml_grid import slipmap_taskdata
from server.analytics.reports import check_band_edges
from server.analytics.slipmap import (
    CellSums,
    NotMappable,
    SlipMap,
    TooManyCells,
    cell_sums,
    check_layer,
    finish_cells,
    map_samples,
    merge_cell_sums,
    reframe,
    slipmap_fields,
)
from server.api.deps import (
    ApiLimits,
    EstimatorDep,
    EstimatorQuery,
    LimitsDep,
    StoreDep,
    TimeRange,
    TimeRangeDep,
    VehicleDep,
    estimator_spec,
    slip_config,
    vehicle_estimators,
    vehicle_slip_map,
)
from server.api.errors import (
    BadRequest,
    NotFound,
    RangeTooLarge,
    Unprocessable,
    error_responses,
)
from server.api.models import (
    AnchorPublic,
    FleetSlipMapCellPublic,
    FleetSlipMapPublic,
    SlipMapCellPublic,
    SlipMapFormat,
    SlipMapPublic,
)
from server.api.routes.series import GEOJSON_MEDIA_TYPE, export_filename
from server.api.tables import csv_table
from server.storage.base import Anchor, Store, VehicleRecord

__all__ = ["FLEET_SLIPMAP_DESCRIPTION", "SLIPMAP_DESCRIPTION", "router"]

router = APIRouter(tags=["slipmap"])

_DEFINITIONS = """\
* **cell** `(i, j)`: the positions (east, north) with `i = floor(east / cell_m)`,
  `j = floor(north / cell_m)`; south-west corner `(i · cell_m, j · cell_m)` (the cell's `east_m`,
  `north_m`).
* **estimator**: the rows are one estimator's (`estimator`); it needs a `position` and a
  `motion` speed channel in its spec (400 `bad_request` otherwise). Positions are its position
  fields (east, north) in metres from the vehicle's anchor.
* **samples**: estimates that are **moving** (`|v| >= slip.min_ground_speed_mps` of the
  vehicle's config, `v` the spec's motion field) and have a position. Each weighs `w`, its
  report **time weight** (the time to the next estimate; a step over 1 s is a gap and the
  estimate before it counts one median step; the last counts one median step), taken over all
  the range's estimates of its vehicle.
* per cell: `time_s = Σ w`; `distance_m = Σ |v| · w`; `rows` = number of samples.
* per slip channel `k` of the spec (`slip_channels`; cells' `slips.<k>`): `valid_s = Σ w` over
  samples with the channel's `valid_flag` and a finite slip; `mean_pct = Σ w · slip / valid_s`
  (**signed** percent), null when that time is 0.
* over the valid channel-samples of every channel (a sample with two valid counts twice):
  `mean_abs_slip_pct = Σ w · |slip| / Σ w`, `max_abs_slip_pct = max |slip|`, and per slip band
  (`[0, e0)`, `[e0, e1)`, …, `[e_last, ∞)` with the map's `band_edges_pct`, labels `0_5`,
  `5_15`, `15_up` for the default 5 and 15 %) the time share `Σ_band w / Σ w`. Null when the
  cell has no valid slip time (time and distance still given); otherwise the shares sum to 1.
* **layer** (`layer=<key>`, a value channel of the estimator's spec that is `mapped`, e.g.
  friction's `mu`; 400 naming its layers otherwise): per cell over the samples that inform it
  (the channel's `valid_flag` set and a finite value `x`): `layer.valid_s = Σ w`,
  `layer.mean = Σ w · x / valid_s` (null when 0) and `layer.samples`, how many such samples
  (flat columns `layer_valid_s`, `layer_mean`, `layer_samples`). A spec
  without a position cannot be mapped, layer or not.
"""

_FORMATS = """\
**Formats**: `json` (cells in the frame, with the frame's {origin}); `geojson`
(`application/geo+json`, RFC 7946): one Polygon per cell, WGS 84 `[longitude, latitude]` corners
of the cell on the frame's horizontal plane, counter-clockwise from the south-west corner, the
statistics as flat properties (`slip_<k>_valid_s`, `slip_<k>_mean_pct` per slip channel, band
shares as `slip_share_<label>`), no features while there is no
{origin_short}; `csv`: one row per cell, the same columns plus the cell centre's
`center_lat_deg`, `center_lon_deg` (empty without {origin_short_a}); `isoxml`: an ISO 11783-10
TASKDATA zip with one type-2 grid over the cells' bounding box, each value the cell's mean
`|slip|` in ppm (1 % = 10,000; 0 where none) under the proprietary DDI 0xE000, or with `layer=`
the layer's mean in millionths (μ 0.8 = 800,000; 0 where none) under DDI 0xE001 (400 without
{origin_short_a} or without a cell).
"""

SLIPMAP_DESCRIPTION = (
    """\
Moving estimates binned into square cells of `cell_m` metres of an east/north (ENU) frame,
over `start <= stamp < end` (server defaults: at most 24 h, 400 `range_too_large` beyond, and
at most 50 000 cells, 400 `range_too_large` beyond: take a larger `cell_m` or a shorter range).
The dashboard's history page draws its heat grid from this map; the definitions are the field
report's. The frame is the vehicle's own; the band edges are `slip.band_edges_pct` of the
vehicle's config (default 5 and 15 %).

"""
    + _DEFINITIONS
    + "\n"
    + _FORMATS.format(
        origin="anchor, null until the vehicle's first fix is stored",
        origin_short="anchor",
        origin_short_a="an anchor",
    )
)

FLEET_SLIPMAP_DESCRIPTION = (
    """\
The slip map of a field from every vehicle that worked it: each vehicle's moving estimates
binned into square cells of `cell_m` metres of **one shared** east/north (ENU) frame, over
`start <= stamp < end` (server defaults: at most 24 h, 400 `range_too_large` beyond, and at most
50 000 cells over all vehicles, 400 `range_too_large` beyond: take a larger `cell_m`, a shorter
range or fewer vehicles).

* **shared frame**: anchored at `origin_lat_deg`, `origin_lon_deg` (give both or neither, else
  422; height 0, which moves no cell: east and north do not depend on it), or else at the stored
  anchor of the first vehicle in id order that has one (`origin_vehicle_id`).
* **vehicles**: every registered vehicle, or those of `vehicles=id1,id2` (an unknown id: 404
  `not_found` naming it). A vehicle's positions (east, north, up of the estimator's `position`)
  are metres from its own anchor: they go to WGS 84 through that anchor and into the shared
  frame (exact ECEF transformations; a missing up is taken as 0). A vehicle without a stored
  anchor cannot be placed: it is left out and listed in `skipped` (`reason` `no_anchor`).
* **estimator**, one for the whole map: `estimator` if given, else the primary of the first
  placed vehicle (by id); without `estimator=`, a vehicle whose primary is another estimator is
  left out and listed in `skipped` (`reason` `other_estimator`).
* **moving** and the time weights are each vehicle's own (its config's
  `slip.min_ground_speed_mps`).
* **band edges**, one set for the whole map: `band_edges_pct` if given (e.g. `5,15`); else
  `slip.band_edges_pct` of the placed vehicles' configs when they all have the same; else the
  default 5 and 15 %. `band_edges_source` says which (`query`, `vehicles`, `default`).
* `vehicles` in the answer: each placed vehicle's samples (`rows`) and cells.

**Cells and statistics**, as in a vehicle's map, each sum over the samples of every vehicle in
the cell (a vehicle weighs by its time there); per cell also `vehicles`, how many vehicles have
samples in it:

"""
    + _DEFINITIONS
    + "\n"
    + _FORMATS.format(
        origin="origin, null when no origin is given and no vehicle has an anchor",
        origin_short="origin",
        origin_short_a="an origin",
    )
)

_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "The map: JSON, GeoJSON (one Polygon per cell), CSV (one row per "
        "cell) or an ISOXML TASKDATA zip (one grid).",
        "content": {
            GEOJSON_MEDIA_TYPE: {"schema": {"type": "object"}},
            "text/csv": {"schema": {"type": "string"}},
            "application/zip": {"schema": {"type": "string", "format": "binary"}},
        },
    },
    **error_responses(400, 404, 422),
}

CellM = Annotated[
    float,
    Query(
        ge=0.5,
        le=1000.0,
        allow_inf_nan=False,
        description="Side of a cell, metres (0.5 to 1000).",
    ),
]
FormatQuery = Annotated[SlipMapFormat, Query(description="Answer format")]
LayerQuery = Annotated[
    str | None,
    Query(
        max_length=64,
        description="Key of a mapped value channel of the estimator (friction: `mu`) whose "
        "time-weighted mean and informing samples each cell also holds (`layer`).",
        examples=["mu"],
    ),
]

_DEFAULT_BAND_EDGES_PCT = SlipConfig().band_edges_pct


def _opt(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _cells(smap: SlipMap, *, vehicles: bool = False) -> list[dict[str, Any]]:
    """Every cell's fields of :class:`SlipMapCellPublic` (and ``vehicles`` of
    :class:`FleetSlipMapCellPublic` when asked), NaN as None."""
    labels = smap.band_labels
    index_east = smap.index_east.tolist()
    index_north = smap.index_north.tolist()
    east_m = smap.east_m.tolist()
    north_m = smap.north_m.tolist()
    time_s = smap.time_s.tolist()
    distance_m = smap.distance_m.tolist()
    rows = smap.rows.tolist()
    valid_s = smap.slip_valid_s.tolist()
    mean_pct = smap.slip_mean_pct.tolist()
    keys = list(enumerate(smap.channels))
    mean_abs_pct = smap.mean_abs_slip_pct.tolist()
    max_abs_pct = smap.max_abs_slip_pct.tolist()
    shares = smap.band_share.tolist()
    cells = [
        {
            "index_east": index_east[c],
            "index_north": index_north[c],
            "east_m": east_m[c],
            "north_m": north_m[c],
            "time_s": time_s[c],
            "distance_m": distance_m[c],
            "rows": rows[c],
            "slips": {
                key: {"valid_s": valid_s[c][k], "mean_pct": _opt(mean_pct[c][k])} for k, key in keys
            },
            "mean_abs_slip_pct": _opt(mean_abs_pct[c]),
            "max_abs_slip_pct": _opt(max_abs_pct[c]),
            "slip_band_shares": {k: _opt(v) for k, v in zip(labels, shares[c], strict=True)},
        }
        for c in range(smap.cells)
    ]
    if vehicles:
        for cell, count in zip(cells, smap.vehicles.tolist(), strict=True):
            cell["vehicles"] = count
    if smap.layer is not None:
        _add_layer(cells, smap)
    return cells


def _add_layer(cells: list[dict[str, Any]], smap: SlipMap) -> None:
    """Each cell's ``layer`` statistics (:class:`LayerCellPublic`), NaN as None."""
    stats = zip(
        smap.layer_valid_s.tolist(),
        smap.layer_mean.tolist(),
        smap.layer_samples.tolist(),
        strict=True,
    )
    for cell, (valid_s, mean, samples) in zip(cells, stats, strict=True):
        cell["layer"] = {"valid_s": valid_s, "mean": _opt(mean), "samples": samples}


_NESTED = ("slips", "slip_band_shares", "layer")
_LAYER_STATS = ("valid_s", "mean", "samples")


def _flat(cell: dict[str, Any]) -> dict[str, Any]:
    """A cell as one flat row: ``slip_<key>_valid_s``, ``slip_<key>_mean_pct`` per slip
    channel and band shares as ``slip_share_<label>`` columns."""
    out = {k: v for k, v in cell.items() if k not in _NESTED}
    for key, stats in cell["slips"].items():
        out[f"slip_{key}_valid_s"] = stats["valid_s"]
        out[f"slip_{key}_mean_pct"] = stats["mean_pct"]
    out.update({f"slip_share_{k}": v for k, v in cell["slip_band_shares"].items()})
    if cell.get("layer") is not None:
        out.update({f"layer_{stat}": cell["layer"][stat] for stat in _LAYER_STATS})
    return out


def _corners_lonlat(smap: SlipMap, frame: EnuFrame) -> np.ndarray:
    """``[lon, lat]`` of each cell's closed ring (SW, SE, NE, NW, SW), shape (m, 5, 2).

    A corner shared by neighbours is computed from the same index, so their edges coincide.
    """
    i = smap.index_east[:, None] + np.array([0, 1, 1, 0, 0])
    j = smap.index_north[:, None] + np.array([0, 0, 1, 1, 0])
    lat, lon, _ = frame.to_geodetic(i * smap.cell_m, j * smap.cell_m, np.zeros(i.shape))
    return np.stack([lon, lat], axis=-1)


def _geojson(
    head: dict[str, Any], smap: SlipMap, cells: list[dict[str, Any]], frame: EnuFrame | None
) -> str:
    features: list[dict[str, Any]] = []
    if frame is not None:
        rings = _corners_lonlat(smap, frame).tolist()
        features = [
            {
                "type": "Feature",
                "geometry": {"type": "Polygon", "coordinates": [ring]},
                "properties": _flat(cell),
            }
            for ring, cell in zip(rings, cells, strict=True)
        ]
    return json.dumps({"type": "FeatureCollection", **head, "features": features})


def _csv(
    smap: SlipMap,
    cells: list[dict[str, Any]],
    frame: EnuFrame | None,
    cell_model: type[SlipMapCellPublic],
) -> str:
    columns = [k for k in cell_model.model_fields if k not in _NESTED]
    for key in smap.channels:
        columns += [f"slip_{key}_valid_s", f"slip_{key}_mean_pct"]
    columns += [f"slip_share_{k}" for k in smap.band_labels]
    if smap.layer is not None:
        columns += [f"layer_{stat}" for stat in _LAYER_STATS]
    columns += ["center_lat_deg", "center_lon_deg"]
    rows = [_flat(cell) for cell in cells]
    if frame is not None:
        half_m = smap.cell_m / 2
        lat, lon, _ = frame.to_geodetic(
            smap.east_m + half_m, smap.north_m + half_m, np.zeros(smap.cells)
        )
        for row, lat_deg, lon_deg in zip(rows, lat.tolist(), lon.tolist(), strict=True):
            row["center_lat_deg"] = lat_deg
            row["center_lon_deg"] = lon_deg
    return csv_table(columns, rows)


def _isoxml(smap: SlipMap, frame: EnuFrame | None, name: str) -> Response:
    """The map as an ISOXML grid in a TASKDATA zip (:mod:`server.analytics.isoxml_grid`)."""
    if frame is None:
        raise BadRequest("an ISOXML grid needs the map placed: no anchor (GNSS fix) stored yet")
    if smap.cells == 0:
        raise BadRequest("no cell in the range: nothing to put in an ISOXML grid")
    return Response(
        slipmap_taskdata(smap, frame, designator=name),
        media_type="application/zip",
        headers={"Content-Disposition": f'attachment; filename="{name}_taskdata.zip"'},
    )


def _answer(
    body: SlipMapPublic | FleetSlipMapPublic,
    smap: SlipMap,
    cells: list[dict[str, Any]],
    frame: EnuFrame | None,
    format: SlipMapFormat,
    download: str,
) -> Response:
    """The map in ``format``; ``body`` holds ``cells`` only for JSON. ``download``: the CSV
    file's name; its columns are the fields of ``body``'s cell model."""
    if format == "json":
        return Response(body.model_dump_json(), media_type="application/json")
    if format == "isoxml":
        return _isoxml(smap, frame, download.rsplit(".", 1)[0])
    if format == "geojson":
        head = body.model_dump(mode="json", exclude={"cells"})
        return Response(_geojson(head, smap, cells, frame), media_type=GEOJSON_MEDIA_TYPE)
    fleet = isinstance(body, FleetSlipMapPublic)
    cell_model = FleetSlipMapCellPublic if fleet else SlipMapCellPublic
    return Response(
        _csv(smap, cells, frame, cell_model),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{download}"'},
    )


def _map_fields(
    spec: EstimatorSpec, *, fleet: bool = False, layer: ValueChannel | None = None
) -> list[str]:
    """The fields a map of ``spec`` (and ``layer``) reads; 400 when it cannot be mapped."""
    try:
        return slipmap_fields(spec, fleet=fleet, layer=layer)
    except NotMappable as exc:
        raise BadRequest(str(exc)) from exc


def _layer(spec: EstimatorSpec | None, key: str | None) -> ValueChannel | None:
    """The mapped value channel ``key`` of ``spec`` (None for None); 400 naming its layers."""
    if key is None or spec is None:
        return None
    try:
        return check_layer(spec, key)
    except NotMappable as exc:
        raise BadRequest(str(exc)) from exc


def _layer_ref(layer: ValueChannel | None) -> dict[str, Any] | None:
    """The map's layer as named in its answer: the value channel as the spec serves it."""
    return None if layer is None else layer.to_dict()


def _channel_refs(spec: EstimatorSpec | None) -> list[dict[str, str]]:
    """The slip channels of a map's estimator, as named in its cells."""
    if spec is None:
        return []
    return [{"key": c.key, "label": c.label, "field": c.field} for c in spec.slips]


def _too_many_cells(exc: TooManyCells, cell_m: float, *, fleet: bool = False) -> RangeTooLarge:
    """The 400 for a map over the cell limit (a fleet map stops at the first vehicle past it,
    so its count is a lower bound)."""
    count = f"at least {exc.cells}" if fleet else f"{exc.cells}"
    fewer = "a shorter range or fewer vehicles" if fleet else "a shorter range"
    return RangeTooLarge(
        f"the map would hold {count} cells of {cell_m:g} m, more than the limit of "
        f"{exc.max_cells}; take a larger cell_m or {fewer}"
    )


@router.get(
    "/vehicles/{vehicle_id}/slipmap",
    response_model=SlipMapPublic,
    responses=_RESPONSES,
    summary="Slip map of one vehicle: time-weighted statistics per square cell",
    description=SLIPMAP_DESCRIPTION,
)
def get_vehicle_slipmap(
    vehicle: VehicleDep,
    spec: EstimatorDep,
    tr: TimeRangeDep,
    store: StoreDep,
    limits: LimitsDep,
    cell_m: CellM = 10.0,
    format: FormatQuery = "json",
    layer: LayerQuery = None,
) -> Response:
    tr.check_span(limits.report_max_range_ns)
    slip = slip_config(vehicle)
    value = _layer(spec, layer)
    fields = _map_fields(spec, layer=value)
    rows = store.query_series(
        vehicle.vehicle_id, tr.start_ns, tr.end_ns, fields, estimator=spec.name
    )
    try:
        smap = vehicle_slip_map(rows, spec, slip, tr, limits, cell_m, layer=value)
    except TooManyCells as exc:
        raise _too_many_cells(exc, cell_m) from exc
    anchor = store.get_anchors(vehicle.vehicle_id).get(vehicle.vehicle_id)
    cells = _cells(smap)
    body = SlipMapPublic.model_validate(
        {
            **_map_head(spec, value, tr, smap, cells if format == "json" else []),
            "vehicle_id": vehicle.vehicle_id,
            "estimator": spec.name,
            "anchor": AnchorPublic.as_json(anchor),
        }
    )
    frame = None if anchor is None else EnuFrame(*anchor)
    name = export_filename(f"{vehicle.vehicle_id}_slipmap", tr, "csv")
    return _answer(body, smap, cells, frame, format, name)


def _map_head(
    spec: EstimatorSpec | None,
    value: ValueChannel | None,
    tr: TimeRange,
    smap: SlipMap,
    cells: list[dict[str, Any]],
) -> dict[str, Any]:
    """What a vehicle's and the fleet's map answers share: the slip channels and layer of
    ``spec``, the range, the cells' side and bands, and the ``cells`` given (none for an
    export)."""
    return {
        "slip_channels": _channel_refs(spec),
        "layer": _layer_ref(value),
        "start_ns": tr.start_ns,
        "end_ns": tr.end_ns,
        "cell_m": smap.cell_m,
        "band_edges_pct": list(smap.band_edges_pct),
        "band_labels": list(smap.band_labels),
        "count": smap.cells,
        "cells": cells,
    }


def _origin(lat_deg: float | None, lon_deg: float | None) -> Anchor | None:
    """The origin asked for (height 0), None when neither is given; 422 for one alone."""
    if lat_deg is None and lon_deg is None:
        return None
    if lat_deg is None or lon_deg is None:
        raise Unprocessable("give both origin_lat_deg and origin_lon_deg, or neither")
    return (lat_deg, lon_deg, 0.0)


def _band_edges(text: str | None) -> tuple[float, ...] | None:
    """The ``band_edges_pct`` parameter (``"5,15"``) as floats, None when not given; 422 unless
    non-negative, finite and increasing."""
    if text is None:
        return None
    try:
        edges = check_band_edges([float(part) for part in text.split(",")])
    except ValueError as exc:
        raise Unprocessable(
            f"band_edges_pct must be increasing numbers separated by commas, e.g. 5,15 ({exc})"
        ) from exc
    if not all(math.isfinite(e) and e >= 0 for e in edges):
        raise Unprocessable("band_edges_pct: the edges must be finite and not negative")
    return edges


def _fleet_vehicles(store: Store, wanted: str | None) -> list[VehicleRecord]:
    """The vehicles of the map in id order: all, or those named in ``wanted`` (``"a,b"``; an
    unknown id is a 404, an empty list a 422)."""
    records = sorted(store.list_vehicles(), key=lambda r: r.vehicle_id)
    if wanted is None:
        return records
    ids = {part.strip() for part in wanted.split(",")} - {""}
    if not ids:
        raise Unprocessable("vehicles: name at least one vehicle id, e.g. vehicles=t1,t2")
    unknown = ids - {r.vehicle_id for r in records}
    if unknown:
        raise NotFound("unknown vehicles: " + ", ".join(sorted(unknown)))
    return [r for r in records if r.vehicle_id in ids]


def _fleet_estimator(
    asked: EstimatorSpec | None, records: list[VehicleRecord], anchors: Mapping[str, Anchor]
) -> tuple[EstimatorSpec | None, list[VehicleRecord], list[dict[str, str]]]:
    """``(estimator, placed vehicles, skipped vehicles)`` of a fleet map, by id.

    The estimator is ``asked``, else the primary of the first anchored vehicle that has one;
    vehicles without an anchor are skipped (``no_anchor``), and without ``asked`` those whose
    primary is another estimator (``other_estimator``). 400 when the estimator cannot be mapped.
    """
    anchored = [r for r in records if r.vehicle_id in anchors]
    skipped = {r.vehicle_id: "no_anchor" for r in records if r.vehicle_id not in anchors}
    spec = asked
    if asked is None:
        primary = {r.vehicle_id: next(iter(vehicle_estimators(r)), None) for r in anchored}
        first = next((name for name in primary.values() if name is not None), None)
        spec = None if first is None else SPECS[first]
        for vid, name in primary.items():
            if spec is None or name != spec.name:
                skipped[vid] = "other_estimator"
        anchored = [r for r in anchored if r.vehicle_id not in skipped]
    if spec is not None:
        _map_fields(spec, fleet=True)
    return spec, anchored, [{"vehicle_id": v, "reason": skipped[v]} for v in sorted(skipped)]


def _vehicle_cells(
    store: Store,
    vehicle_id: str,
    spec: EstimatorSpec,
    slip: SlipConfig,
    anchor: Anchor,
    frame: EnuFrame,
    tr: TimeRange,
    limits: ApiLimits,
    cell_m: float,
    band_edges_pct: tuple[float, ...],
    layer: ValueChannel | None = None,
) -> CellSums:
    """One vehicle's partial sums in the shared ``frame`` (its rows are dropped on return)."""
    fields = _map_fields(spec, fleet=True, layer=layer)
    rows = store.query_series(vehicle_id, tr.start_ns, tr.end_ns, fields, estimator=spec.name)
    samples = map_samples(
        rows,
        spec,
        end_ns=tr.end_ns,
        min_ground_speed_mps=slip.min_ground_speed_mps,
        max_gap_s=limits.report_max_gap_s,
        layer=layer,
    )
    return cell_sums(
        reframe(samples, EnuFrame(*anchor), frame),
        cell_m=cell_m,
        band_edges_pct=band_edges_pct,
        max_cells=limits.slipmap_max_cells,
        layer=None if layer is None else layer.key,
    )


OriginLatQuery = Annotated[
    float | None,
    Query(
        ge=-90.0,
        le=90.0,
        allow_inf_nan=False,
        description="Latitude of the shared frame's origin, WGS 84 degrees (with "
        "origin_lon_deg). Default: the first anchored vehicle's anchor.",
    ),
]
OriginLonQuery = Annotated[
    float | None,
    Query(
        ge=-180.0,
        le=180.0,
        allow_inf_nan=False,
        description="Longitude of the shared frame's origin, WGS 84 degrees (with origin_lat_deg).",
    ),
]
VehiclesQuery = Annotated[
    str | None,
    Query(
        max_length=8192,
        description="Comma-separated vehicle ids to map (default: every vehicle); an "
        "unknown id is a 404.",
        examples=["tractor-1,tractor-2"],
    ),
]
BandEdgesQuery = Annotated[
    str | None,
    Query(
        max_length=256,
        description="Comma-separated increasing slip band edges, percent (e.g. `5,15`). "
        "Default: the vehicles' common edges, or 5,15 when their configs differ.",
        examples=["5,15"],
    ),
]


def _fleet_band_edges(
    asked: tuple[float, ...] | None, slips: Mapping[str, SlipConfig]
) -> tuple[tuple[float, ...], str]:
    """``(edges, source)`` of a fleet map: the query's, else the vehicles' common edges, else
    the default 5,15."""
    if asked is not None:
        return asked, "query"
    theirs = {slip.band_edges_pct for slip in slips.values()}
    if len(theirs) == 1:
        return check_band_edges(theirs.pop()), "vehicles"
    return _DEFAULT_BAND_EDGES_PCT, "default"


@router.get(
    "/fleet/slipmap",
    response_model=FleetSlipMapPublic,
    responses=_RESPONSES,
    summary="Slip map of the fleet: every vehicle's statistics per cell of one shared frame",
    description=FLEET_SLIPMAP_DESCRIPTION,
)
def get_fleet_slipmap(
    tr: TimeRangeDep,
    store: StoreDep,
    limits: LimitsDep,
    cell_m: CellM = 10.0,
    format: FormatQuery = "json",
    origin_lat_deg: OriginLatQuery = None,
    origin_lon_deg: OriginLonQuery = None,
    vehicles: VehiclesQuery = None,
    band_edges_pct: BandEdgesQuery = None,
    estimator: EstimatorQuery = None,
    layer: LayerQuery = None,
) -> Response:
    tr.check_span(limits.report_max_range_ns)
    origin = _origin(origin_lat_deg, origin_lon_deg)
    edges_asked = _band_edges(band_edges_pct)
    plan = _fleet_plan(store, origin, edges_asked, vehicles, estimator, layer)
    total, summary = _fleet_sums(plan, store, tr, limits, cell_m)
    smap = finish_cells(total)
    cells = _cells(smap, vehicles=True)
    spec = plan.spec
    body = FleetSlipMapPublic.model_validate(
        {
            **_map_head(spec, plan.value, tr, smap, cells if format == "json" else []),
            "estimator": None if spec is None else spec.name,
            "origin": AnchorPublic.as_json(plan.origin),
            "origin_vehicle_id": plan.origin_vehicle_id,
            "band_edges_source": plan.edges_source,
            "vehicles": summary,
            "skipped": plan.skipped,
        }
    )
    download = export_filename("fleet_slipmap", tr, "csv")
    return _answer(body, smap, cells, plan.frame, format, download)


@dataclass(frozen=True, slots=True)
class _FleetPlan:
    """What a fleet map reads: its estimator and layer, the vehicles placed (with their slip
    configs and anchors) and skipped, the shared frame's origin and the slip band edges."""

    spec: EstimatorSpec | None
    value: ValueChannel | None
    placed: list[VehicleRecord]
    skipped: list[dict[str, str]]
    slips: dict[str, SlipConfig]
    anchors: Mapping[str, Anchor]
    origin: Anchor | None
    origin_vehicle_id: str | None
    frame: EnuFrame | None
    edges: tuple[float, ...]
    edges_source: str


def _fleet_plan(
    store: Store,
    origin: Anchor | None,
    edges_asked: tuple[float, ...] | None,
    vehicles: str | None,
    estimator: str | None,
    layer: str | None,
) -> _FleetPlan:
    """The fleet map's plan; the origin defaults to the first placed vehicle's anchor."""
    anchors = store.get_anchors()
    records = _fleet_vehicles(store, vehicles)
    asked = None if estimator is None else estimator_spec(estimator)
    spec, placed, skipped = _fleet_estimator(asked, records, anchors)
    value = _layer(spec, layer)
    slips = {r.vehicle_id: slip_config(r) for r in placed}
    origin_vehicle_id = None
    if origin is None and placed:
        origin_vehicle_id = placed[0].vehicle_id
        origin = anchors[origin_vehicle_id]
    frame = None if origin is None else EnuFrame(*origin)
    edges, edges_source = _fleet_band_edges(edges_asked, slips)
    return _FleetPlan(
        spec,
        value,
        placed,
        skipped,
        slips,
        anchors,
        origin,
        origin_vehicle_id,
        frame,
        edges,
        edges_source,
    )


def _fleet_sums(
    plan: _FleetPlan, store: Store, tr: TimeRange, limits: ApiLimits, cell_m: float
) -> tuple[CellSums, list[dict[str, Any]]]:
    """The placed vehicles' cell sums merged one vehicle at a time, and each one's rows and
    cells; 400 past the cell limit."""
    spec, value = plan.spec, plan.value
    summary: list[dict[str, Any]] = []

    def parts(shared: EnuFrame, spec: EstimatorSpec) -> Iterator[CellSums]:
        for record in plan.placed:
            vid = record.vehicle_id
            part = _vehicle_cells(
                store,
                vid,
                spec,
                plan.slips[vid],
                plan.anchors[vid],
                shared,
                tr,
                limits,
                cell_m,
                plan.edges,
                value,
            )
            summary.append({"vehicle_id": vid, "rows": int(part.rows.sum()), "cells": part.cells})
            yield part

    frame = plan.frame
    try:
        total = merge_cell_sums(
            # no frame or estimator: no vehicle placed
            parts(frame, spec) if frame is not None and spec is not None else (),
            cell_m=cell_m,
            channels=() if spec is None else tuple(c.key for c in spec.slips),
            band_edges_pct=plan.edges,
            max_cells=limits.slipmap_max_cells,
            layer=None if value is None else value.key,
        )
    except TooManyCells as exc:
        raise _too_many_cells(exc, cell_m, fleet=True) from exc
    return total, summary
