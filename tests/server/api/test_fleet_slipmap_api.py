"""/fleet/slipmap through the app on a real SQLite file (and once on PostgreSQL).

Two vehicles with different stored anchors drive over the same ground: ``t1`` the series of
``test_slipmap_api.placed_series`` in its frame (anchor ``A``), ``t2`` the same positions
written in its own frame (anchor ``B``, some 450 m away) with twice the left slip.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from estimator.geo import EnuFrame
from server.api import ApiLimits
from server.storage.base import Store

from ._data import T0, S
from .conftest import ApiClient, error_of, make_settings, running_on
from .test_slipmap_api import csv_download, placed_series

Q = f"start={T0}&end={T0 + 10 * S}"
U = "/api/v1/fleet/slipmap"
A = (52.0, 5.6, 12.0)
B = (52.0031, 5.6047, 40.0)


def in_frame(rows: np.ndarray, source: EnuFrame, target: EnuFrame) -> np.ndarray:
    """``rows`` with their positions moved from ``source`` to ``target``."""
    out = rows.copy()
    lat, lon, h = source.to_geodetic(rows["east_m"], rows["north_m"], rows["up_m"])
    out["east_m"], out["north_m"], out["up_m"] = target.to_enu(lat, lon, h)
    return out


def t2_series() -> np.ndarray:
    rows = in_frame(placed_series(), EnuFrame(*A), EnuFrame(*B))
    rows["slip_left_pct"] *= 2
    return rows


def _put(
    client: ApiClient,
    store: Store,
    vehicle_id: str,
    rows: np.ndarray,
    anchor: tuple[float, float, float] | None,
    config: dict[str, object] | None = None,
) -> None:
    assert client.put(f"/api/v1/vehicles/{vehicle_id}", json=config or {}).status_code == 201
    store.write_estimates([(vehicle_id, rows)])
    if anchor is not None:
        store.put_anchors({vehicle_id: anchor}, T0)


def _two_vehicles(client: ApiClient, store: Store) -> None:
    _put(client, store, "t1", placed_series(), A)
    _put(client, store, "t2", t2_series(), B)


def test_same_ground_gives_one_set_of_cells(client: ApiClient, store: Store) -> None:
    _two_vehicles(client, store)
    # in their own frames the two vehicles are hundreds of metres apart
    own = client.get(f"/api/v1/vehicles/t2/slipmap?{Q}&cell_m=10").json()["cells"]
    assert {c["index_east"] for c in own}.isdisjoint({0, 1, 2})
    r = client.get(f"{U}?{Q}&cell_m=10")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    body = r.json()
    assert body["origin"] == {"lat_deg": 52.0, "lon_deg": 5.6, "height_m": 12.0}
    assert body["origin_vehicle_id"] == "t1"  # first in id order with an anchor
    assert body["vehicles"] == [
        {"vehicle_id": "t1", "rows": 6, "cells": 3},
        {"vehicle_id": "t2", "rows": 6, "cells": 3},
    ]
    assert body["skipped"] == []
    assert body["band_edges_pct"] == [5.0, 15.0] and body["band_edges_source"] == "vehicles"
    cells = body["cells"]
    assert body["count"] == 3
    assert [(c["index_east"], c["index_north"]) for c in cells] == [(0, 0), (1, 0), (2, 0)]
    assert [c["vehicles"] for c in cells] == [2, 2, 2]
    assert [c["rows"] for c in cells] == [4, 6, 2]
    assert [c["time_s"] for c in cells] == [4.0, 6.0, 2.0]
    assert [c["distance_m"] for c in cells] == pytest.approx([8.0, 16.0, 8.0])
    # t1 left slip 1 3 | 10 20 -30 | 5, t2 twice that: the time-weighted mean of both
    assert body["estimator"] == "mdsf"
    assert [c["slips"]["left"]["mean_pct"] for c in cells] == pytest.approx([3.0, 0.0, 7.5])
    assert [c["max_abs_slip_pct"] for c in cells] == [6.0, 60.0, 10.0]
    assert [c["slips"]["right"]["mean_pct"] for c in cells] == [0.0, None, None]
    # cell 2: 5 % (an edge belongs to the upper band) and 10 %
    assert cells[2]["slip_band_shares"] == {"0_5": 0.0, "5_15": 1.0, "15_up": 0.0}


def test_geojson_polygons_map_back_to_the_shared_cells(client: ApiClient, store: Store) -> None:
    _two_vehicles(client, store)
    r = client.get(f"{U}?{Q}&cell_m=7.5&format=geojson")
    assert r.status_code == 200 and r.headers["content-type"] == "application/geo+json"
    fc = r.json()
    assert fc["type"] == "FeatureCollection" and fc["origin_vehicle_id"] == "t1"
    assert [v["vehicle_id"] for v in fc["vehicles"]] == ["t1", "t2"]
    feats = fc["features"]
    cells = client.get(f"{U}?{Q}&cell_m=7.5").json()["cells"]
    assert len(feats) == len(cells) == 3
    frame = EnuFrame(*A)
    for feat, cell in zip(feats, cells, strict=True):
        (ring,) = feat["geometry"]["coordinates"]
        lon, lat = np.array(ring).T
        east, north, _ = frame.to_enu(lat, lon, np.full(5, A[2]))
        e0, n0 = cell["east_m"], cell["north_m"]
        np.testing.assert_allclose(east, [e0, e0 + 7.5, e0 + 7.5, e0, e0], atol=1e-3)
        np.testing.assert_allclose(north, [n0, n0, n0 + 7.5, n0 + 7.5, n0], atol=1e-3)
        assert feat["properties"]["vehicles"] == cell["vehicles"] == 2
        assert feat["properties"]["time_s"] == cell["time_s"]


def test_csv_has_vehicles_and_centres(client: ApiClient, store: Store) -> None:
    _two_vehicles(client, store)
    table = csv_download(client.get(f"{U}?{Q}&cell_m=10&format=csv"), "fleet_slipmap")
    assert [int(row["vehicles"]) for row in table] == [2, 2, 2]
    assert [float(row["time_s"]) for row in table] == [4.0, 6.0, 2.0]
    lat, lon, _ = EnuFrame(*A).to_geodetic(15.0, 5.0, 0.0)  # centre of cell (1, 0)
    assert float(table[1]["center_lat_deg"]) == pytest.approx(float(lat), abs=1e-9)
    assert float(table[1]["center_lon_deg"]) == pytest.approx(float(lon), abs=1e-9)


def test_origin_parameters_move_the_grid(client: ApiClient, store: Store) -> None:
    _two_vehicles(client, store)
    # origin 4 m east of t1's anchor: rows at east 6 9 12 | 15 18 21 fall at 2 5 8 | 11 14 17
    lat, lon, _ = EnuFrame(*A).to_geodetic(4.0, 0.0, 0.0)
    q = f"{U}?{Q}&cell_m=10&origin_lat_deg={float(lat)!r}&origin_lon_deg={float(lon)!r}"
    body = client.get(q).json()
    assert body["origin"] == {"lat_deg": float(lat), "lon_deg": float(lon), "height_m": 0.0}
    assert body["origin_vehicle_id"] is None
    cells = body["cells"]
    assert [(c["index_east"], c["index_north"]) for c in cells] == [(0, 0), (1, 0)]
    assert [c["time_s"] for c in cells] == [6.0, 6.0]
    assert [c["vehicles"] for c in cells] == [2, 2]
    fc = client.get(q + "&format=geojson").json()
    (ring,) = fc["features"][1]["geometry"]["coordinates"]
    lon_r, lat_r = np.array(ring).T
    east, north, _ = EnuFrame(float(lat), float(lon), 0.0).to_enu(lat_r, lon_r, np.zeros(5))
    np.testing.assert_allclose(east, [10, 20, 20, 10, 10], atol=1e-3)
    np.testing.assert_allclose(north, [0, 0, 10, 10, 0], atol=1e-3)


def test_vehicle_without_anchor_is_skipped(client: ApiClient, store: Store) -> None:
    _put(client, store, "t0", placed_series(), None)  # first in id order, but no anchor
    _two_vehicles(client, store)
    body = client.get(f"{U}?{Q}&cell_m=10").json()
    assert body["skipped"] == [{"vehicle_id": "t0", "reason": "no_anchor"}]
    assert [v["vehicle_id"] for v in body["vehicles"]] == ["t1", "t2"]
    assert body["origin_vehicle_id"] == "t1"
    assert [c["vehicles"] for c in body["cells"]] == [2, 2, 2]


def test_nothing_placed_gives_no_cells(client: ApiClient, store: Store) -> None:
    _put(client, store, "t0", placed_series(), None)
    body = client.get(f"{U}?{Q}").json()
    assert body["origin"] is None and body["origin_vehicle_id"] is None
    assert body["count"] == 0 and body["vehicles"] == []
    assert body["skipped"] == [{"vehicle_id": "t0", "reason": "no_anchor"}]
    assert client.get(f"{U}?{Q}&format=geojson").json()["features"] == []
    assert csv_download(client.get(f"{U}?{Q}&format=csv"), "fleet_slipmap") == []


def test_vehicles_filter(client: ApiClient, store: Store) -> None:
    _two_vehicles(client, store)
    body = client.get(f"{U}?{Q}&cell_m=10&vehicles=t2").json()
    assert body["origin_vehicle_id"] == "t2"  # the first chosen vehicle's anchor
    assert body["origin"]["lat_deg"] == B[0]
    assert [v["vehicle_id"] for v in body["vehicles"]] == ["t2"]
    # in its own frame, one vehicle's fleet map is its own map, with one vehicle a cell
    own = client.get(f"/api/v1/vehicles/t2/slipmap?{Q}&cell_m=10").json()["cells"]
    assert [c.pop("vehicles") for c in body["cells"]] == [1] * len(own)
    assert body["cells"] == own
    both = client.get(f"{U}?{Q}&cell_m=10&vehicles=t2,%20t1,t2,").json()
    assert [v["vehicle_id"] for v in both["vehicles"]] == ["t1", "t2"]
    r = client.get(f"{U}?{Q}&vehicles=t1,nope,zz")
    assert r.status_code == 404 and r.json()["error"] == "not_found"
    assert "nope, zz" in r.json()["reason"]
    r = client.get(f"{U}?{Q}&vehicles=,")
    assert r.status_code == 422


def test_band_edges_rule_and_moving_per_vehicle(client: ApiClient, store: Store) -> None:
    _put(client, store, "t1", placed_series(), A)
    # t2 moves only at 4 m/s (rows 6, 7: east 18 and 21) and bands at 10 %
    config = {"slip": {"band_edges_pct": [10], "min_ground_speed_mps": 3.0}}
    _put(client, store, "t2", t2_series(), B, config)
    body = client.get(f"{U}?{Q}&cell_m=10").json()
    assert body["band_edges_source"] == "default"  # the configs differ
    assert body["band_labels"] == ["0_5", "5_15", "15_up"]
    assert [v["rows"] for v in body["vehicles"]] == [6, 2]
    assert [c["vehicles"] for c in body["cells"]] == [1, 2, 2]
    asked = client.get(f"{U}?{Q}&cell_m=10&band_edges_pct=10").json()
    assert asked["band_edges_source"] == "query" and asked["band_labels"] == ["0_10", "10_up"]
    one = client.get(f"{U}?{Q}&cell_m=10&vehicles=t2").json()
    assert one["band_edges_source"] == "vehicles" and one["band_edges_pct"] == [10.0]
    for bad in ("15,5", "5,5", "x", "-1,5", "inf", ""):
        r = client.get(f"{U}?{Q}&band_edges_pct={bad}")
        assert r.status_code == 422, bad


def test_origin_errors(client: ApiClient, store: Store) -> None:
    """(cell_m, range and format: test_slipmap_api.test_errors, for both maps.)"""
    _two_vehicles(client, store)
    for half in ("origin_lat_deg=52", "origin_lon_deg=5.6"):
        error, reason = error_of(client.get(f"{U}?{Q}&{half}"), 422)
        assert error == "invalid", half
        assert "origin_lat_deg and origin_lon_deg" in reason, half
    for bad in (
        "origin_lat_deg=91&origin_lon_deg=5",
        "origin_lat_deg=52&origin_lon_deg=-181",
        "origin_lat_deg=nan&origin_lon_deg=5",
    ):
        assert error_of(client.get(f"{U}?{Q}&{bad}"), 422)[0] == "invalid_request", bad


def test_cell_limit(tmp_path: Path) -> None:
    with running_on(make_settings(tmp_path), ApiLimits(slipmap_max_cells=4)) as (client, runtime):
        _two_vehicles(client, runtime.store)
        far = placed_series()
        far["east_m"] += 100.0  # 3 cells of its own, 100 m east of the others
        _put(client, runtime.store, "t3", in_frame(far, EnuFrame(*A), EnuFrame(*B)), B)
        assert client.get(f"{U}?{Q}&cell_m=10&vehicles=t1,t2").json()["count"] == 3
        # each vehicle fits, the fleet does not
        error, reason = error_of(client.get(f"{U}?{Q}&cell_m=10"), 400)
        assert error == "range_too_large"
        assert "at least 6 cells" in reason and "limit of 4" in reason
        assert client.get(f"{U}?{Q}&cell_m=1000").json()["count"] == 1


@pytest.mark.postgres
def test_fleet_slipmap_on_postgres(tmp_path: Path, pg_database_url: str) -> None:
    with running_on(make_settings(tmp_path, url=pg_database_url)) as (client, runtime):
        assert runtime.store.dialect == "postgresql"
        _two_vehicles(client, runtime.store)
        body = client.get(f"{U}?{Q}&cell_m=10").json()
        assert body["origin_vehicle_id"] == "t1"
        assert [c["vehicles"] for c in body["cells"]] == [2, 2, 2]
        assert [c["time_s"] for c in body["cells"]] == [4.0, 6.0, 2.0]
        fc = client.get(f"{U}?{Q}&cell_m=10&format=geojson").json()
        assert len(fc["features"]) == 3


def test_openapi_states_the_rules(client: ApiClient) -> None:
    op = client.get("/openapi.json").json()["paths"][U]["get"]
    assert set(op["responses"]["200"]["content"]) == {
        "application/json",
        "application/geo+json",
        "text/csv",
        "application/zip",
    }
    assert {"400", "404", "422"} <= set(op["responses"])
    for text in ("time_s = Σ w", "shared", "no_anchor", "band_edges_source", "id order"):
        assert text in op["description"], text
    params = {p["name"]: p for p in op["parameters"]}
    assert set(params) >= {"origin_lat_deg", "origin_lon_deg", "vehicles", "band_edges_pct"}
    assert params["cell_m"]["schema"]["minimum"] == 0.5
