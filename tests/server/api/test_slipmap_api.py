"""/vehicles/{id}/slipmap through the app on a real SQLite file (and once on PostgreSQL)."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import httpx
import numpy as np
import pytest

from estimator.geo import EnuFrame
from server.api import ApiLimits
from server.storage.base import Store

from ._data import T0, S, hand_series
from .conftest import ApiClient, error_of, make_settings, running_on

Q = f"start={T0}&end={T0 + 10 * S}"
U = "/api/v1/vehicles/t1/slipmap"
ANCHOR = (52.0, 5.6, 12.0)


def placed_series() -> np.ndarray:
    """The reports' hand series driving east 3 m a second, 0.5 m north of the anchor.

    Moving rows 2..7 (vg 2 2 2 2 4 4, 1 s each) at east 6 9 | 12 15 18 | 21: with 10 m cells,
    cell 0 holds rows 2, 3, cell 1 rows 4-6, cell 2 row 7. Left slip 1 3 | 10 20 -30 | 5,
    right slip 0 0 | NaN (flagged valid, not a sample).
    """
    rows = hand_series()
    rows["east_m"] = np.arange(10) * 3.0
    rows["north_m"] = 0.5
    rows["up_m"] = 1.0
    return rows


def _put(
    client: ApiClient, store: Store, vehicle_id: str = "t1", config: dict[str, object] | None = None
) -> None:
    assert client.put(f"/api/v1/vehicles/{vehicle_id}", json=config or {}).status_code == 201
    store.write_estimates([(vehicle_id, placed_series())])


def test_json_cells_by_hand(client: ApiClient, store: Store) -> None:
    _put(client, store)
    r = client.get(f"{U}?{Q}&cell_m=10")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    body = r.json()
    assert body["anchor"] is None  # no fix stored yet: cells still given in the frame
    assert body["cell_m"] == 10.0 and body["count"] == 3
    assert body["band_edges_pct"] == [5.0, 15.0]
    assert body["band_labels"] == ["0_5", "5_15", "15_up"]
    cells = body["cells"]
    assert [(c["index_east"], c["index_north"]) for c in cells] == [(0, 0), (1, 0), (2, 0)]
    assert [(c["east_m"], c["north_m"]) for c in cells] == [(0, 0), (10, 0), (20, 0)]
    assert [c["time_s"] for c in cells] == [2.0, 3.0, 1.0]
    assert [c["distance_m"] for c in cells] == pytest.approx([4.0, 8.0, 4.0])
    assert [c["rows"] for c in cells] == [2, 3, 1]
    assert body["estimator"] == "mdsf"
    assert [c["key"] for c in body["slip_channels"]] == ["left", "right"]
    assert [c["slips"]["left"]["mean_pct"] for c in cells] == pytest.approx([2.0, 0.0, 5.0])
    assert [c["slips"]["right"]["mean_pct"] for c in cells] == [0.0, None, None]
    assert [c["slips"]["right"]["valid_s"] for c in cells] == [2.0, 0.0, 0.0]
    assert [c["mean_abs_slip_pct"] for c in cells] == pytest.approx([1.0, 20.0, 5.0])
    assert [c["max_abs_slip_pct"] for c in cells] == [3.0, 30.0, 5.0]
    assert cells[1]["slip_band_shares"] == {
        "0_5": 0.0,
        "5_15": pytest.approx(1 / 3),
        "15_up": pytest.approx(2 / 3),
    }
    # the map's time is the report's moving time (every moving row has a position)
    rep = client.get(f"/api/v1/vehicles/t1/report?{Q}").json()["report"]
    assert sum(c["time_s"] for c in cells) == rep["moving_s"]
    assert sum(c["distance_m"] for c in cells) == pytest.approx(rep["distance_m"])


def test_vehicle_config_sets_bands_and_moving(client: ApiClient, store: Store) -> None:
    _put(client, store, "t2", {"slip": {"band_edges_pct": [10], "min_ground_speed_mps": 3.0}})
    body = client.get(f"/api/v1/vehicles/t2/slipmap?{Q}&cell_m=10").json()
    assert body["band_labels"] == ["0_10", "10_up"]
    # only rows 6, 7 (4 m/s) move: east 18 (cell 1, slip -30) and 21 (cell 2, slip 5)
    assert [(c["index_east"], c["time_s"]) for c in body["cells"]] == [(1, 1.0), (2, 1.0)]
    assert [c["slip_band_shares"] for c in body["cells"]] == [
        {"0_10": 0.0, "10_up": 1.0},
        {"0_10": 1.0, "10_up": 0.0},
    ]


def test_geojson_polygons_map_back_to_the_cell_corners(client: ApiClient, store: Store) -> None:
    _put(client, store)
    q = f"{U}?{Q}&cell_m=7.5&format=geojson"
    r = client.get(q)
    assert r.status_code == 200 and r.headers["content-type"] == "application/geo+json"
    assert r.json()["features"] == []  # no anchor yet: nothing to place on the globe
    store.put_anchors({"t1": ANCHOR}, T0)
    fc = client.get(q).json()
    assert fc["type"] == "FeatureCollection"
    assert fc["anchor"] == {"lat_deg": 52.0, "lon_deg": 5.6, "height_m": 12.0}
    cells = client.get(f"{U}?{Q}&cell_m=7.5").json()["cells"]
    feats = fc["features"]
    assert len(feats) == len(cells) == 3  # east 6, 9 | 12 | 15, 18, 21 with 7.5 m cells
    frame = EnuFrame(*ANCHOR)
    for feat, cell in zip(feats, cells, strict=True):
        assert feat["geometry"]["type"] == "Polygon"
        (ring,) = feat["geometry"]["coordinates"]
        assert len(ring) == 5 and ring[0] == ring[-1]  # closed
        lon, lat = np.array(ring).T  # GeoJSON order: longitude, latitude
        east, north, _ = frame.to_enu(lat, lon, np.full(5, ANCHOR[2]))
        e0, n0 = cell["east_m"], cell["north_m"]
        np.testing.assert_allclose(east, [e0, e0 + 7.5, e0 + 7.5, e0, e0], atol=1e-3)
        np.testing.assert_allclose(north, [n0, n0, n0 + 7.5, n0 + 7.5, n0], atol=1e-3)
        props = feat["properties"]
        assert props["index_east"] == cell["index_east"]
        assert props["time_s"] == cell["time_s"]
        assert props["slip_right_mean_pct"] == cell["slips"]["right"]["mean_pct"]
        assert props["slip_left_valid_s"] == cell["slips"]["left"]["valid_s"]
        for label, share in cell["slip_band_shares"].items():
            assert props[f"slip_share_{label}"] == share
    # neighbours share their edge exactly (no slivers in a GIS)
    assert feats[0]["geometry"]["coordinates"][0][1] == feats[1]["geometry"]["coordinates"][0][0]
    assert feats[2]["properties"]["slip_right_mean_pct"] is None  # NaN → null


def csv_download(response: httpx.Response, name: str) -> list[dict[str, str]]:
    """The rows of a CSV answer, which must be a download whose file name holds ``name``."""
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/csv")
    assert name in response.headers["content-disposition"]
    return list(csv.DictReader(io.StringIO(response.text)))


def test_csv_one_row_per_cell(client: ApiClient, store: Store) -> None:
    _put(client, store)
    store.put_anchors({"t1": ANCHOR}, T0)
    table = csv_download(client.get(f"{U}?{Q}&cell_m=10&format=csv"), "t1_slipmap")
    assert [int(row["index_east"]) for row in table] == [0, 1, 2]
    assert [float(row["time_s"]) for row in table] == [2.0, 3.0, 1.0]
    assert table[1]["slip_right_mean_pct"] == ""  # null
    assert float(table[1]["slip_share_15_up"]) == pytest.approx(2 / 3)
    lat, lon, _ = EnuFrame(*ANCHOR).to_geodetic(15.0, 5.0, 0.0)  # centre of cell (1, 0)
    assert float(table[1]["center_lat_deg"]) == pytest.approx(float(lat), abs=1e-9)
    assert float(table[1]["center_lon_deg"]) == pytest.approx(float(lon), abs=1e-9)


@pytest.mark.parametrize("url", [U, "/api/v1/fleet/slipmap"])
def test_errors(client: ApiClient, store: Store, url: str) -> None:
    """The arguments both maps share are checked alike."""
    _put(client, store)
    store.put_anchors({"t1": ANCHOR}, T0)
    for bad in ("0.4", "1001", "nan", "inf", "x"):
        assert error_of(client.get(f"{url}?{Q}&cell_m={bad}"), 422)[0] == "invalid_request", bad
    assert client.get(f"{url}?{Q}&cell_m=0.5").status_code == 200
    assert client.get(f"{url}?{Q}&cell_m=1000").status_code == 200
    r = client.get(f"{url}?start={T0}&end={T0 + 2 * 86_400 * S}")
    assert error_of(r, 400)[0] == "range_too_large"
    assert client.get(f"{url}?{Q}&format=kml").status_code == 422


def test_unknown_vehicle(client: ApiClient) -> None:
    assert error_of(client.get(f"/api/v1/vehicles/nope/slipmap?{Q}"), 404)[0] == "not_found"


def test_cell_limit(tmp_path: Path) -> None:
    with running_on(make_settings(tmp_path), ApiLimits(slipmap_max_cells=2)) as (client, runtime):
        _put(client, runtime.store)
        error, reason = error_of(client.get(f"{U}?{Q}&cell_m=10"), 400)  # 3 cells
        assert error == "range_too_large"
        assert "3 cells" in reason and "limit of 2" in reason
        assert client.get(f"{U}?{Q}&cell_m=20").json()["count"] == 2  # east 6..18 | 21


@pytest.mark.postgres
def test_slipmap_on_postgres(tmp_path: Path, pg_database_url: str) -> None:
    with running_on(make_settings(tmp_path, url=pg_database_url)) as (client, runtime):
        assert runtime.store.dialect == "postgresql"
        _put(client, runtime.store)
        runtime.store.put_anchors({"t1": ANCHOR}, T0)
        body = client.get(f"{U}?{Q}&cell_m=10").json()
        assert body["anchor"]["lat_deg"] == 52.0
        assert [c["time_s"] for c in body["cells"]] == [2.0, 3.0, 1.0]
        assert [c["max_abs_slip_pct"] for c in body["cells"]] == [3.0, 30.0, 5.0]
        fc = client.get(f"{U}?{Q}&cell_m=10&format=geojson").json()
        assert len(fc["features"]) == 3


def test_openapi_states_the_formats_and_formulas(client: ApiClient) -> None:
    op = client.get("/openapi.json").json()["paths"]["/api/v1/vehicles/{vehicle_id}/slipmap"]["get"]
    assert set(op["responses"]["200"]["content"]) == {
        "application/json",
        "application/geo+json",
        "text/csv",
        "application/zip",
    }
    assert "time_s = Σ w" in op["description"]
    assert "mean_abs_slip_pct = Σ w · |slip| / Σ w" in op["description"]
    params = {p["name"]: p for p in op["parameters"]}
    assert params["cell_m"]["schema"]["minimum"] == 0.5
    assert params["cell_m"]["schema"]["maximum"] == 1000.0
