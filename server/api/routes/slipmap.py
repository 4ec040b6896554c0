"""Slip map: ``/vehicles/{id}/slipmap`` (JSON, GeoJSON or CSV).

The statistics are :mod:`server.slipmap`'s; this module reads the rows, picks the frame and
writes the answer. GeoJSON cells are polygons whose corners go through the frame's
:meth:`estimator.geo.EnuFrame.to_geodetic` on its horizontal plane (``up`` 0).
"""

from __future__ import annotations

import json
import math
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Response

from estimator.geo import EnuFrame
from server.api.deps import (
    LimitsDep,
    StoreDep,
    TimeRangeDep,
    VehicleDep,
    slip_config,
)
from server.api.errors import RangeTooLarge, error_responses
from server.api.models import SlipMapCellPublic, SlipMapFormat, SlipMapPublic
from server.api.routes.series import GEOJSON_MEDIA_TYPE, export_filename
from server.api.tables import csv_table
from server.slipmap import SLIPMAP_FIELDS, SlipMap, TooManyCells, slip_map
from server.storage.base import Anchor

__all__ = ["SLIPMAP_DESCRIPTION", "router"]

router = APIRouter(tags=["slipmap"])

SLIPMAP_DESCRIPTION = """\
Moving estimates binned into square cells of `cell_m` metres of an east/north (ENU) frame,
over `start <= stamp < end` (server defaults: at most 24 h, 400 `range_too_large` beyond, and
at most 50 000 cells, 400 `range_too_large` beyond: take a larger `cell_m` or a shorter range).
The server-side, time-weighted form of the dashboard's heat grid; the definitions are the field
report's.

* **cell** `(i, j)`: the positions with `i = floor(east_m / cell_m)`, `j = floor(north_m /
  cell_m)`; south-west corner `(i · cell_m, j · cell_m)`.
* **samples**: estimates that are **moving** (`|vg_mps| >= slip.min_ground_speed_mps` of the
  vehicle's config) and have a position. Each weighs `w`, its report **time weight** (the
  time to the next estimate; a step over 1 s is a gap and the estimate before it counts one
  median step; the last counts one median step), taken over all the range's estimates.
* per cell: `time_s = Σ w`; `distance_m = Σ |vg_mps| · w`; `rows` = number of samples.
* per wheel: `slip_<wheel>_valid_s = Σ w` over samples with the wheel's `SLIP_*_VALID` flag and
  a finite slip; `slip_<wheel>_mean_pct = Σ w · slip / slip_<wheel>_valid_s` (**signed**
  percent), null when that time is 0.
* over the valid wheel-samples of both wheels (a sample with both valid counts twice):
  `mean_abs_slip_pct = Σ w · |slip| / Σ w`, `max_abs_slip_pct = max |slip|`, and per slip band
  (`[0, e0)`, `[e0, e1)`, …, `[e_last, ∞)` with the edges `slip.band_edges_pct` of the
  vehicle's config, default 5 and 15 %; labels `0_5`, `5_15`, `15_up`) the time share
  `Σ_band w / Σ w`. Null when the cell has no valid slip time (time and distance still given);
  otherwise the shares sum to 1.

**Formats**: `json` (cells in the frame, with the frame's anchor, null until the vehicle's first
fix is stored); `geojson` (`application/geo+json`, RFC 7946): one Polygon per cell, WGS 84
`[longitude, latitude]` corners of the cell on the frame's horizontal plane, counter-clockwise
from the south-west corner, the statistics as properties (band shares as `slip_share_<label>`),
no features while there is no anchor; `csv`: one row per cell, the same columns plus the cell
centre's `center_lat_deg`, `center_lon_deg` (empty without an anchor).
"""

_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "The map: JSON, GeoJSON (one Polygon per cell) or CSV (one row per cell).",
        "content": {
            GEOJSON_MEDIA_TYPE: {"schema": {"type": "object"}},
            "text/csv": {"schema": {"type": "string"}},
        },
    },
}


_ANCHOR_KEYS = ("lat_deg", "lon_deg", "height_m")


def _opt(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _cells(smap: SlipMap) -> list[dict[str, Any]]:
    """Every cell's fields of :class:`SlipMapCellPublic`, NaN as None."""
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
    mean_abs_pct = smap.mean_abs_slip_pct.tolist()
    max_abs_pct = smap.max_abs_slip_pct.tolist()
    shares = smap.band_share.tolist()
    return [
        {
            "index_east": index_east[c],
            "index_north": index_north[c],
            "east_m": east_m[c],
            "north_m": north_m[c],
            "time_s": time_s[c],
            "distance_m": distance_m[c],
            "rows": rows[c],
            "slip_left_valid_s": valid_s[c][0],
            "slip_right_valid_s": valid_s[c][1],
            "slip_left_mean_pct": _opt(mean_pct[c][0]),
            "slip_right_mean_pct": _opt(mean_pct[c][1]),
            "mean_abs_slip_pct": _opt(mean_abs_pct[c]),
            "max_abs_slip_pct": _opt(max_abs_pct[c]),
            "slip_band_shares": {k: _opt(v) for k, v in zip(labels, shares[c], strict=True)},
        }
        for c in range(smap.cells)
    ]


def _flat(cell: dict[str, Any]) -> dict[str, Any]:
    """A cell as one flat row: band shares as ``slip_share_<label>`` columns."""
    out = {k: v for k, v in cell.items() if k != "slip_band_shares"}
    out.update({f"slip_share_{k}": v for k, v in cell["slip_band_shares"].items()})
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
    head: dict[str, Any], smap: SlipMap, cells: list[dict[str, Any]], anchor: Anchor | None
) -> str:
    features: list[dict[str, Any]] = []
    if anchor is not None:
        rings = _corners_lonlat(smap, EnuFrame(*anchor)).tolist()
        features = [
            {
                "type": "Feature",
                "geometry": {"type": "Polygon", "coordinates": [ring]},
                "properties": _flat(cell),
            }
            for ring, cell in zip(rings, cells, strict=True)
        ]
    return json.dumps({"type": "FeatureCollection", **head, "features": features})


def _csv(smap: SlipMap, cells: list[dict[str, Any]], anchor: Anchor | None) -> str:
    columns = [k for k in SlipMapCellPublic.model_fields if k != "slip_band_shares"]
    columns += [f"slip_share_{k}" for k in smap.band_labels]
    columns += ["center_lat_deg", "center_lon_deg"]
    rows = [_flat(cell) for cell in cells]
    if anchor is not None:
        half_m = smap.cell_m / 2
        lat, lon, _ = EnuFrame(*anchor).to_geodetic(
            smap.east_m + half_m, smap.north_m + half_m, np.zeros(smap.cells)
        )
        for row, lat_deg, lon_deg in zip(rows, lat.tolist(), lon.tolist(), strict=True):
            row["center_lat_deg"] = lat_deg
            row["center_lon_deg"] = lon_deg
    return csv_table(columns, rows)


@router.get(
    "/vehicles/{vehicle_id}/slipmap",
    response_model=SlipMapPublic,
    responses={**_RESPONSES, **error_responses(400, 404, 422)},
    summary="Slip map of one vehicle: time-weighted statistics per square cell",
    description=SLIPMAP_DESCRIPTION,
)
def get_vehicle_slipmap(
    vehicle: VehicleDep,
    tr: TimeRangeDep,
    store: StoreDep,
    limits: LimitsDep,
    cell_m: Annotated[
        float,
        Query(
            ge=0.5,
            le=1000.0,
            allow_inf_nan=False,
            description="Side of a cell, metres (0.5 to 1000).",
        ),
    ] = 10.0,
    format: Annotated[SlipMapFormat, Query(description="Answer format")] = "json",
) -> Response:
    tr.check_span(limits.report_max_range_ns)
    slip = slip_config(vehicle)
    rows = store.query_series(vehicle.vehicle_id, tr.start_ns, tr.end_ns, SLIPMAP_FIELDS)
    try:
        smap = slip_map(
            rows,
            end_ns=tr.end_ns,
            cell_m=cell_m,
            band_edges_pct=slip.band_edges_pct,
            min_ground_speed_mps=slip.min_ground_speed_mps,
            max_gap_s=limits.report_max_gap_s,
            max_cells=limits.slipmap_max_cells,
        )
    except TooManyCells as exc:
        raise RangeTooLarge(
            f"the map would hold {exc.cells} cells of {cell_m:g} m, more than the limit of "
            f"{exc.max_cells}; take a larger cell_m or a shorter range"
        ) from exc
    anchor = store.get_anchors(vehicle.vehicle_id).get(vehicle.vehicle_id)
    cells = _cells(smap)
    body = SlipMapPublic.model_validate(
        {
            "vehicle_id": vehicle.vehicle_id,
            "start_ns": tr.start_ns,
            "end_ns": tr.end_ns,
            "cell_m": smap.cell_m,
            "anchor": None if anchor is None else dict(zip(_ANCHOR_KEYS, anchor, strict=True)),
            "band_edges_pct": list(smap.band_edges_pct),
            "band_labels": list(smap.band_labels),
            "count": smap.cells,
            "cells": cells if format == "json" else [],
        }
    )
    if format == "json":
        return Response(body.model_dump_json(), media_type="application/json")
    if format == "geojson":
        head = body.model_dump(mode="json", exclude={"cells"})
        return Response(_geojson(head, smap, cells, anchor), media_type=GEOJSON_MEDIA_TYPE)
    name = export_filename(f"{vehicle.vehicle_id}_slipmap", tr, "csv")
    return Response(
        _csv(smap, cells, anchor),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )
