"""``/slipmap?layer=``: a mapped value channel of the estimator's spec (friction μ, a crawler's
odometer factor) in each cell, through the app on a real SQLite file: JSON, CSV and ISOXML, a
vehicle's map and the fleet's, a steered vehicle's μ; refused for a layer the spec lacks."""

from __future__ import annotations

import csv
import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

from estimator.friction_spec import FRICTION_SPEC, FrictionFlag
from estimator.spec import EstimatorSpec
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag
from estimator.types import EstimateBatch
from server.analytics.isoxml_grid import GRID_FILE, LAYER_DDI
from server.storage.base import Store

from ._data import T0, S
from .conftest import ApiClient, error_of

Q = f"start={T0}&end={T0 + 10 * S}&cell_m=10"
U = "/api/v1/vehicles/c1/slipmap"
ANCHOR = (52.0, 5.6, 12.0)


def _driven_east(spec: EstimatorSpec, speed_field: str) -> np.ndarray:
    """10 rows of ``spec``, 1 s apart from ``T0``, driving east 3 m a second along north 0.5 m
    (cells of 10 m: rows 0..3, 4..6, 7..9), ``speed_field`` 0 then 2 m/s from row 1."""
    rows = spec.empty_rows(10)
    rows["stamp_ns"] = T0 + np.arange(10) * S
    rows[speed_field] = [0, 2, 2, 2, 2, 2, 2, 2, 2, 2]
    rows["east_m"] = np.arange(10) * 3.0 + 0.5
    rows["north_m"] = 0.5
    rows["up_m"] = 0.0
    return rows


def _informing() -> np.ndarray:
    """bool, shape (10,): the rows that inform the layer, 1, 2, 4, 5, 6 and 9."""
    mask = np.zeros(10, dtype=bool)
    mask[[1, 2, 4, 5, 6, 9]] = True
    return mask


def crawler_series() -> np.ndarray:
    """10 crawler rows, 1 s apart, driving east 3 m a second at 2 m/s (moving from row 1).

    Cells of 10 m: rows 0..3 in cell 0 (row 0 standing), 4..6 in cell 1, 7..9 in cell 2.
    Odometer factor 0.90 + 0.01·i; GNSS (the layer's valid flag) on rows 1, 2, 4, 5, 6, 9 only:
    cell 0 mean (0.91 + 0.92)/2, 2 samples; cell 1 (0.94 + 0.95 + 0.96)/3, 3; cell 2 0.99, 1.
    """
    rows = _driven_east(TRACKED_SPEC, "speed_mps")
    rows["odometer_scale"] = 0.90 + 0.01 * np.arange(10)
    gnss = _informing()
    rows["flags"] = np.where(gnss, int(TrackedFlag.GNSS_OK), int(TrackedFlag.DEAD_RECKONING))
    return rows


@pytest.fixture
def crawler(client: ApiClient, store: Store) -> str:
    assert client.put("/api/v1/vehicles/c1", json={"kind": "tracked"}).status_code == 201
    store.write_estimates(EstimateBatch.of([("c1", crawler_series())], TRACKED_SPEC))
    return "c1"


def test_json_cells_hold_the_layers_mean_over_informing_samples(
    client: ApiClient, crawler: str
) -> None:
    r = client.get(f"{U}?{Q}&layer=odometer_factor")
    assert r.status_code == 200
    body = r.json()
    assert body["estimator"] == "tracked"
    assert body["layer"] == {
        "key": "odometer_factor",
        "label": "odometer factor",
        "field": "odometer_scale",
        "unit": "",
        "std_field": None,
        "valid_flag": "GNSS_OK",
        "mapped": True,
    }
    cells = body["cells"]
    assert [c["index_east"] for c in cells] == [0, 1, 2]
    assert [c["rows"] for c in cells] == [3, 3, 3]
    layer = [c["layer"] for c in cells]
    assert [cell["samples"] for cell in layer] == [2, 3, 1]
    assert [cell["valid_s"] for cell in layer] == [2.0, 3.0, 1.0]
    assert [cell["mean"] for cell in layer] == pytest.approx([0.915, 0.95, 0.99], abs=1e-12)
    # without layer=: no layer in the answer, the cells unchanged
    plain = client.get(f"{U}?{Q}").json()
    assert plain["layer"] is None and all(c["layer"] is None for c in plain["cells"])
    assert [c["time_s"] for c in plain["cells"]] == [c["time_s"] for c in cells]


def test_csv_has_the_layer_columns(client: ApiClient, crawler: str) -> None:
    r = client.get(f"{U}?{Q}&layer=odometer_factor&format=csv")
    assert r.status_code == 200
    table = list(csv.DictReader(io.StringIO(r.text)))
    assert [row["layer_samples"] for row in table] == ["2", "3", "1"]
    assert [float(row["layer_mean"]) for row in table] == pytest.approx([0.915, 0.95, 0.99])


def test_isoxml_grid_holds_the_layer_in_millionths(
    client: ApiClient, store: Store, crawler: str, tmp_path: Path
) -> None:
    from isoxml.converter.np_grid import to_numpy_array
    from isoxml.util.isoxml_io import isoxml_from_path

    store.put_anchors({crawler: ANCHOR}, T0)
    r = client.get(f"{U}?{Q}&layer=odometer_factor&format=isoxml")
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    zipfile.ZipFile(io.BytesIO(r.content)).extractall(tmp_path)
    task_data, refs = isoxml_from_path(tmp_path / "TASKDATA")
    task = task_data.tasks[0]
    values = to_numpy_array(refs[GRID_FILE], task.grids[0])
    assert values.tolist() == [[915_000, 950_000, 990_000]]
    ddi = task.treatment_zones[0].process_data_variables[0].process_data_ddi
    assert int.from_bytes(ddi, "big") == LAYER_DDI


def test_the_fleet_map_merges_the_layer(client: ApiClient, store: Store, crawler: str) -> None:
    assert client.put("/api/v1/vehicles/c2", json={"kind": "tracked"}).status_code == 201
    store.write_estimates(EstimateBatch.of([("c2", crawler_series())], TRACKED_SPEC))
    store.put_anchors({"c1": ANCHOR, "c2": ANCHOR}, T0)
    r = client.get(f"/api/v1/fleet/slipmap?{Q}&estimator=tracked&layer=odometer_factor")
    assert r.status_code == 200
    cells = r.json()["cells"]
    # the same drive twice in one frame: twice the samples, the same means
    assert [c["layer"]["samples"] for c in cells] == [4, 6, 2]
    assert [c["layer"]["mean"] for c in cells] == pytest.approx([0.915, 0.95, 0.99])
    assert [c["vehicles"] for c in cells] == [2, 2, 2]


def test_a_layer_the_spec_lacks_is_refused_naming_its_layers(
    client: ApiClient, crawler: str
) -> None:
    _, reason = error_of(client.get(f"{U}?{Q}&layer=mu"), 400)
    assert "no map layer 'mu'" in reason and "['odometer_factor']" in reason


def friction_series() -> np.ndarray:
    """10 rows of a steered vehicle, as :func:`crawler_series` drives: μ 0.50 + 0.01·i, informed
    on rows 1, 2, 4, 5, 6, 9 (held elsewhere, the last informed value); rows 7-9 carried
    through a GNSS outage (``DEAD_RECKONED``: still placed)."""
    rows = _driven_east(FRICTION_SPEC, "vx_mps")
    rows["heading_rad"] = np.pi / 2
    informed = _informing()
    rows["mu"] = np.where(informed, 0.50 + 0.01 * np.arange(10), 0.4)
    flags = np.where(informed, int(FrictionFlag.INFORMED), int(FrictionFlag.HELD))
    flags[7:] |= int(FrictionFlag.DEAD_RECKONED)
    rows["flags"] = flags
    return rows


def test_friction_mu_is_mapped_from_the_informed_samples(client: ApiClient, store: Store) -> None:
    assert FRICTION_SPEC.value("mu").mapped
    assert (
        client.put("/api/v1/vehicles/f1", json={"kind": "wheeled_4wd_steered"}).status_code == 201
    )
    store.write_estimates(EstimateBatch.of([("f1", friction_series())], FRICTION_SPEC))
    r = client.get(f"/api/v1/vehicles/f1/slipmap?{Q}&layer=mu")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["estimator"] == "friction" and body["layer"]["valid_flag"] == "INFORMED"
    cells = body["cells"]
    assert [c["index_east"] for c in cells] == [0, 1, 2]
    assert [c["rows"] for c in cells] == [3, 3, 3]
    layer = [c["layer"] for c in cells]
    assert [cell["samples"] for cell in layer] == [2, 3, 1]
    assert [cell["mean"] for cell in layer] == pytest.approx([0.515, 0.55, 0.59], abs=1e-12)
