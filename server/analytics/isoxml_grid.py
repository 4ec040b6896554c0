"""A slip map as an ISO 11783-10 (ISOXML) grid in a TASKDATA zip, for farm-management software
and terminals.

``TASKDATA/TASKDATA.XML`` (version 4.3) holds one task (``TSK1``) with one treatment zone
(``TZN`` code 1) whose process data variable names :data:`SLIP_DDI`, and a type-2 grid
(``GRD``) over the map's bounding box of cells; ``TASKDATA/GRD00001.bin`` holds the cell values,
int32 little-endian, rows from south to north, each row west to east (ISO 11783-10 §6.13).

Each cell value is the cell's time-weighted mean ``|slip|`` (``mean_abs_slip_pct``) in ppm of
slip (1 % = 10,000), rounded; cells without a valid slip and cells not worked are 0. ISO
11783-11 defines no data dictionary entry for wheel slip, so :data:`SLIP_DDI` is the first
proprietary one (0xE000, unit ppm). A map with a layer (friction μ) gives that layer's mean
instead, in millionths of its value (μ 0.8 = 800,000), under :data:`LAYER_DDI` (0xE001): ISO
11783-11 has no entry for a friction coefficient either.

The slip map's cells are squares of its ENU frame; the grid's are in degrees. The grid starts at
the south-west corner of the map's south-west cell and its cell sizes are those of that cell in
latitude and longitude, so across a field (a few km) the two agree to centimetres.
"""

from __future__ import annotations

import io
from decimal import Decimal

import numpy as np

from estimator.geo import EnuFrame
from server.analytics.slipmap import SlipMap

__all__ = [
    "GRID_FILE",
    "LAYER_DDI",
    "SLIP_DDI",
    "layer_grid_ppm",
    "slip_grid_ppm",
    "slipmap_taskdata",
]

#: Proprietary data dictionary entry of the grid's value: mean |slip| in ppm.
SLIP_DDI = 0xE000
#: Proprietary data dictionary entry of a layer's grid: the layer's mean in millionths.
LAYER_DDI = 0xE001
#: The grid's binary file (without ``.bin``).
GRID_FILE = "GRD00001"
_PPM_PER_PCT = 10_000


def _grid(smap: SlipMap, values: np.ndarray) -> np.ndarray:
    """``values`` (shape (m,), one per cell) rounded into an int32 grid of shape ``(rows north,
    columns east)`` at ``[index_north - min, index_east - min]``, 0 where NaN or no cell."""
    i = smap.index_east - smap.index_east.min()
    j = smap.index_north - smap.index_north.min()
    grid = np.zeros((int(j.max()) + 1, int(i.max()) + 1), dtype=np.int32)
    grid[j, i] = np.round(np.nan_to_num(values, nan=0.0)).astype(np.int32)
    return grid


def slip_grid_ppm(smap: SlipMap) -> np.ndarray:
    """The grid's values: each cell's mean ``|slip|`` in ppm (:func:`_grid`)."""
    return _grid(smap, smap.mean_abs_slip_pct * _PPM_PER_PCT)


def layer_grid_ppm(smap: SlipMap) -> np.ndarray:
    """The grid's values of a map with a layer: each cell's layer mean in millionths."""
    return _grid(smap, smap.layer_mean * 1e6)


def _corner_deg(smap: SlipMap, frame: EnuFrame) -> tuple[float, float, float, float]:
    """``(lat, lon)`` of the grid's south-west corner and the south-west cell's size in
    degrees ``(dlat, dlon)``."""
    i0, j0 = int(smap.index_east.min()), int(smap.index_north.min())
    east = np.array([i0, i0 + 1]) * smap.cell_m
    north = np.array([j0, j0 + 1]) * smap.cell_m
    lat, lon, _ = frame.to_geodetic(east, north, np.zeros(2))
    return float(lat[0]), float(lon[0]), float(lat[1] - lat[0]), float(lon[1] - lon[0])


def slipmap_taskdata(smap: SlipMap, frame: EnuFrame, designator: str) -> bytes:
    """The TASKDATA zip of ``smap`` (at least one cell), placed through ``frame``: its mean
    ``|slip|``, or its layer's mean when it has a layer."""
    import isoxml.models.base.v4 as iso
    from isoxml.util.isoxml_io import isoxml_to_zip

    if smap.layer is None:
        values, ddi, zone_name = slip_grid_ppm(smap), SLIP_DDI, "mean |slip| ppm"
    else:
        values, ddi, zone_name = layer_grid_ppm(smap), LAYER_DDI, f"mean {smap.layer} x1e6"
    payload = values.astype("<i4").tobytes(order="C")
    lat, lon, dlat, dlon = _corner_deg(smap, frame)
    grid = iso.Grid(
        minimum_north_position=Decimal(f"{lat:.9f}"),
        minimum_east_position=Decimal(f"{lon:.9f}"),
        cell_north_size=dlat,
        cell_east_size=dlon,
        maximum_column=values.shape[1],
        maximum_row=values.shape[0],
        filename=GRID_FILE,
        filelength=len(payload),
        type=iso.GridType.GridType2,
        treatment_zone_code=1,
    )
    zone = iso.TreatmentZone(
        code=1,
        designator=zone_name[:32],
        process_data_variables=[
            iso.ProcessDataVariable(process_data_ddi=ddi.to_bytes(2, "big"), process_data_value=0)
        ],
    )
    task = iso.Task(
        id="TSK1",
        designator=designator[:32],
        status=iso.TaskStatus.Completed,
        treatment_zones=[zone],
        grids=[grid],
    )
    task_data = iso.Iso11783TaskData(
        version_minor=iso.Iso11783TaskDataVersionMinor.VALUE_3,
        management_software_manufacturer="Slipfleet",
        management_software_version="1",
        data_transfer_origin=iso.Iso11783TaskDataDataTransferOrigin.FMIS,
        tasks=[task],
    )
    out = io.BytesIO()
    isoxml_to_zip(out, task_data, {GRID_FILE: payload})
    return out.getvalue()
