"""``/slipmap?format=isoxml``: the slip map as an ISOXML grid in a TASKDATA zip, read back by the
``isoxml`` package with the cell values it was given, placed where the cells lie."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

from estimator.geo import EnuFrame
from server.analytics.isoxml_grid import GRID_FILE, SLIP_DDI
from server.storage.base import Store

from ._data import T0, S
from .conftest import ApiClient, error_of
from .test_slipmap_api import ANCHOR, placed_series

Q = f"start={T0}&end={T0 + 10 * S}&cell_m=10&format=isoxml"


def _put(client: ApiClient, store: Store) -> None:
    """The hand series of ``test_slipmap_api`` with its last moving row 12 m north: cells
    (0, 0) mean |slip| 1 %, (1, 0) 20 %, (2, 1) 5 %."""
    assert client.put("/api/v1/vehicles/t1", json={}).status_code == 201
    rows = placed_series()
    rows["north_m"][7] = 12.0
    store.write_estimates([("t1", rows)])


def _read_back(zipped: bytes, tmp_path: Path) -> tuple[object, np.ndarray]:
    from isoxml.converter.np_grid import to_numpy_array
    from isoxml.util.isoxml_io import isoxml_from_path

    zipfile.ZipFile(io.BytesIO(zipped)).extractall(tmp_path)  # as a terminal's USB stick holds it
    task_data, refs = isoxml_from_path(tmp_path / "TASKDATA")
    grid = task_data.tasks[0].grids[0]
    return task_data, to_numpy_array(refs[GRID_FILE], grid)


def test_grid_read_back_holds_each_cells_mean_abs_slip_in_ppm(
    client: ApiClient, store: Store, tmp_path: Path
) -> None:
    _put(client, store)
    store.put_anchors({"t1": ANCHOR}, T0)
    r = client.get(f"/api/v1/vehicles/t1/slipmap?{Q}")
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    assert "_taskdata.zip" in r.headers["content-disposition"]
    assert sorted(zipfile.ZipFile(io.BytesIO(r.content)).namelist()) == [
        "TASKDATA/GRD00001.bin",
        "TASKDATA/TASKDATA.XML",
    ]
    task_data, values = _read_back(r.content, tmp_path)
    # rows from south to north, columns west to east
    assert values.tolist() == [[10_000, 200_000, 0], [0, 0, 50_000]]

    task = task_data.tasks[0]  # type: ignore[attr-defined]
    grid = task.grids[0]
    assert (grid.maximum_row, grid.maximum_column) == (2, 3)
    zone = task.treatment_zones[0]
    assert zone.code == grid.treatment_zone_code == 1
    assert zone.process_data_variables[0].process_data_ddi == SLIP_DDI.to_bytes(2, "big")
    frame = EnuFrame(*ANCHOR)
    lat, lon, _ = frame.to_geodetic(np.array([0.0, 10.0]), np.array([0.0, 10.0]), np.zeros(2))
    assert float(grid.minimum_north_position) == pytest.approx(lat[0], abs=1e-9)
    assert float(grid.minimum_east_position) == pytest.approx(lon[0], abs=1e-9)
    assert grid.cell_north_size == pytest.approx(lat[1] - lat[0], rel=1e-12)
    assert grid.cell_east_size == pytest.approx(lon[1] - lon[0], rel=1e-12)


def test_fleet_map_as_isoxml(client: ApiClient, store: Store, tmp_path: Path) -> None:
    _put(client, store)
    store.put_anchors({"t1": ANCHOR}, T0)
    r = client.get(f"/api/v1/fleet/slipmap?{Q}")
    assert r.status_code == 200, r.text
    _, values = _read_back(r.content, tmp_path)
    assert values.tolist() == [[10_000, 200_000, 0], [0, 0, 50_000]]


def test_without_an_anchor_or_a_cell_it_says_why(client: ApiClient, store: Store) -> None:
    _put(client, store)
    r = client.get(f"/api/v1/vehicles/t1/slipmap?{Q}")
    assert "no anchor" in error_of(r, 400)[1]
    store.put_anchors({"t1": ANCHOR}, T0)
    empty = f"start={T0 + 20 * S}&end={T0 + 30 * S}&format=isoxml"
    r = client.get(f"/api/v1/vehicles/t1/slipmap?{empty}")
    assert "no cell" in error_of(r, 400)[1]
