"""/vehicles/{id}/series: JSON columns, CSV, Parquet, decimation, time parsing, limits."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from estimator.geo import EnuFrame
from estimator.types import ESTIMATE_DTYPE
from server.api import ApiLimits, create_app
from server.api.routes.series import encode_columns_json, export_names
from server.storage.base import Store

from ._data import T0, T0_ISO, S, hand_series, ramp_series
from .conftest import ApiClient, FakeRuntime, make_settings, running

U = "/api/v1/vehicles/t1/series"
ALL = f"start={T0}&end={T0 + 3600 * S}"


@pytest.fixture
def filled(client: ApiClient, store: Store) -> np.ndarray:
    client.put("/api/v1/vehicles/t1", json={})
    rows = hand_series()
    store.write_estimates([("t1", rows)])
    return rows


def test_json_full_rate(client: ApiClient, filled: np.ndarray) -> None:
    body = client.get(f"{U}?{ALL}").json()
    assert body["rows"] == 10
    assert body["downsampled"] is False
    assert body["max_points"] == 0
    assert body["fields"] == list(ESTIMATE_DTYPE.names or ())
    cols = body["columns"]
    assert cols["stamp_ns"] == filled["stamp_ns"].tolist()
    assert cols["vg_mps"] == [0, 0, 2, 2, 2, 2, 4, 4, 0.1, 0]
    assert cols["slip_left_pct"][:3] == [None, None, 1.0]  # NaN → null
    assert cols["flags"] == filled["flags"].tolist()


def test_iso_times_and_fields(client: ApiClient, filled: np.ndarray) -> None:
    # 12:00:02 .. 12:00:04 (+02:00 offset spelling) → rows 2 and 3
    r = client.get(
        U,
        params={
            "start": "2024-05-01T14:00:02+02:00",
            "end": "2024-05-01T12:00:04Z",
            "fields": "slip_left_pct, vg_mps,vg_mps",
        },
    )
    body = r.json()
    assert body["fields"] == ["stamp_ns", "slip_left_pct", "vg_mps"]
    assert body["columns"] == {
        "stamp_ns": [T0 + 2 * S, T0 + 3 * S],
        "slip_left_pct": [1.0, 3.0],
        "vg_mps": [2.0, 2.0],
    }


def test_csv_parses_back(client: ApiClient, filled: np.ndarray) -> None:
    r = client.get(f"{U}?{ALL}&format=csv&fields=vg_mps,slip_left_pct,flags")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/csv")
    assert "attachment" in r.headers["content-disposition"]
    table = list(csv.DictReader(io.StringIO(r.text)))
    assert len(table) == 10
    assert [int(t["stamp_ns"]) for t in table] == filled["stamp_ns"].tolist()
    assert [float(t["vg_mps"]) for t in table] == filled["vg_mps"].tolist()
    assert table[0]["slip_left_pct"] == ""  # NaN → empty cell
    assert float(table[6]["slip_left_pct"]) == -30.0
    assert [int(t["flags"]) for t in table] == filled["flags"].tolist()


def test_parquet_parses_back(client: ApiClient, filled: np.ndarray) -> None:
    r = client.get(f"{U}?{ALL}&format=parquet")
    assert r.status_code == 200
    assert r.headers["content-type"] == "application/vnd.apache.parquet"
    table = pq.read_table(io.BytesIO(r.content))
    assert table.column_names == export_names(ESTIMATE_DTYPE.names or ())
    assert table.num_rows == 10
    assert table["stamp_ns"].to_pylist() == filled["stamp_ns"].tolist()
    assert table["vg_mps"].to_pylist() == filled["vg_mps"].tolist()
    assert table["slip_left_pct"].to_pylist()[:3] == [None, None, 1.0]  # NaN → null
    assert str(table.schema.field("flags").type) == "int32"


def test_decimation_keeps_the_spike(client: ApiClient, store: Store) -> None:
    client.put("/api/v1/vehicles/t1", json={})
    rows = ramp_series(36_000)  # one hour at 10 Hz
    rows["slip_left_pct"][12_345] = 250.0  # a single-sample spike
    rows["vg_mps"][20_000] = -9.0  # and a single-sample dip
    store.write_estimates([("t1", rows)])
    body = client.get(f"{U}?{ALL}&max_points=200&fields=vg_mps,slip_left_pct").json()
    assert body["downsampled"] is True
    assert 100 < body["rows"] <= 200
    cols = body["columns"]
    assert max(cols["slip_left_pct"]) == 250.0
    assert min(cols["vg_mps"]) == -9.0
    assert cols["stamp_ns"] == sorted(cols["stamp_ns"])
    # fewer rows than max_points: returned as they are
    body = client.get(f"{U}?start={T0}&end={T0 + 10 * S}&max_points=200").json()
    assert body["downsampled"] is False
    assert body["rows"] == 100


def test_decimation_is_independent_of_chunking(tmp_path: Path) -> None:
    rows = ramp_series(5000, step_ns=S // 10)
    rows["vg_mps"][::7] += 3.0
    results = []
    for chunk_ns in (60 * S, 37 * S, 3600 * S):
        settings = make_settings(tmp_path, require_auth=False)
        app = create_app(settings, FakeRuntime(settings), limits=ApiLimits(query_chunk_ns=chunk_ns))
        with running(app) as client:
            client.put("/api/v1/vehicles/t1", json={})
            client_store = app.state.runtime.store
            client_store.write_estimates([("t1", rows)])
            results.append(client.get(f"{U}?{ALL}&max_points=300").json())
            csv_text = client.get(f"{U}?{ALL}&format=csv&fields=vg_mps").text
            assert len(csv_text.splitlines()) == 5001  # full-rate CSV across chunks
    assert results[0] == results[1] == results[2]


def test_bad_queries(client: ApiClient, filled: np.ndarray) -> None:
    cases = [
        ("start=yesterday&end=1", 422, "invalid_time", "start"),
        ("start=2024-05-01T12:00:00&end=2024-05-01T13:00:00Z", 422, "invalid_time", "offset"),
        (f"start={T0}&end={T0}", 422, "invalid_time", "after start"),
        (f"{ALL}&fields=vg_mps,speed", 422, "invalid", "speed"),
        (f"{ALL}&max_points=1", 422, "invalid", "max_points"),
        (f"{ALL}&max_points=-3", 422, "invalid_request", "max_points"),
        (f"{ALL}&format=xml", 422, "invalid_request", "format"),
        (f"start={T0_ISO}", 422, "invalid_request", "end"),
        (f"start={T0}&end={T0 + 32 * 24 * 3600 * S}", 400, "range_too_large", "limit"),
    ]
    for query, status, code, word in cases:
        r = client.get(f"{U}?{query}")
        assert r.status_code == status, query
        assert r.json()["error"] == code, (query, r.json())
        assert word in r.json()["reason"], (query, r.json())


def test_row_limit(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, require_auth=False)
    app = create_app(settings, FakeRuntime(settings), limits=ApiLimits(series_max_rows=50))
    with running(app) as client:
        client.put("/api/v1/vehicles/t1", json={})
        app.state.runtime.store.write_estimates([("t1", ramp_series(100))])
        r = client.get(f"{U}?{ALL}")
        assert r.status_code == 400
        assert r.json()["error"] == "range_too_large"
        assert "max_points" in r.json()["reason"]
        assert client.get(f"{U}?{ALL}&max_points=40").json()["rows"] <= 40
        assert len(client.get(f"{U}?{ALL}&format=csv").text.splitlines()) == 101


def test_empty_range(client: ApiClient, filled: np.ndarray) -> None:
    q = f"start={T0 + 100 * S}&end={T0 + 200 * S}"
    body = client.get(f"{U}?{q}&fields=vg_mps").json()
    assert body["rows"] == 0
    assert body["columns"] == {"stamp_ns": [], "vg_mps": []}
    assert client.get(f"{U}?{q}&format=csv&fields=vg_mps").text == "stamp_ns,time,vg_mps\n"
    table = pq.read_table(io.BytesIO(client.get(f"{U}?{q}&format=parquet").content))
    assert table.num_rows == 0


def test_json_encoding_of_columns() -> None:
    rows = np.zeros(4, dtype=[("stamp_ns", "i8"), ("x", "f8")])
    rows["stamp_ns"] = [1, 2, 3, 2**62 + 1]
    rows["x"] = [np.nan, -np.inf, 1 / 3, 1e-300]
    text = encode_columns_json(rows)
    assert text == ('{"stamp_ns":[1,2,3,4611686018427387905],"x":[null,null,0.333333333,1e-300]}')
    assert json.loads(text)["x"][2] == pytest.approx(1 / 3, rel=1e-9)


def test_geojson_map_of_whole_rows_in_wgs84(client: ApiClient, store: Store) -> None:
    client.put("/api/v1/vehicles/t1", json={})
    rows = ramp_series(3_000)  # 5 min at 10 Hz, driving east at 2 m/s from the anchor
    rows["east_m"] = np.arange(3_000) * 0.2
    rows["north_m"] = 10.0
    rows["up_m"] = 0.5
    rows["east_m"][:5] = np.nan  # no position yet: no feature
    store.write_estimates([("t1", rows)])
    q = f"{U}?start={T0}&end={T0 + 300 * S}&format=geojson&fields=slip_left_pct,vg_mps"
    r = client.get(q)
    assert r.status_code == 200 and r.headers["content-type"] == "application/geo+json"
    assert r.json()["features"] == []  # the vehicle has no anchor yet
    anchor = (52.0, 5.6, 12.0)
    store.put_anchors({"t1": anchor}, T0)
    fc = client.get(q).json()
    assert fc["type"] == "FeatureCollection"
    # named, as in the vehicle and slip-map answers (a bare list would read lat,lon beside
    # coordinates in lon,lat)
    assert fc["anchor"] == {"lat_deg": 52.0, "lon_deg": 5.6, "height_m": 12.0}
    feats = fc["features"]
    assert len(feats) == 3_000 - 5
    lat, lon, h = EnuFrame(*anchor).to_geodetic(
        rows["east_m"][5:], rows["north_m"][5:], rows["up_m"][5:]
    )
    got = np.array([f["geometry"]["coordinates"] for f in feats])
    np.testing.assert_allclose(got[:, 0], lon, atol=1e-9)
    np.testing.assert_allclose(got[:, 1], lat, atol=1e-9)
    np.testing.assert_allclose(got[:, 2], h, atol=1e-3)
    # 10 m north of the anchor is 10 m north on the ellipsoid, to the millimetre
    assert EnuFrame(*anchor).to_enu(got[0, 1], got[0, 0], got[0, 2])[1] == pytest.approx(10.0)
    props = feats[7]["properties"]
    assert set(props) == {"stamp_ns", "slip_left_pct", "vg_mps"}
    assert props["stamp_ns"] == int(rows["stamp_ns"][12])
    assert props["slip_left_pct"] == pytest.approx(float(rows["slip_left_pct"][12]))
    # thinned: the first whole row of each of max_points time buckets, never a mixed position
    thin = client.get(f"{q}&max_points=60").json()["features"]
    assert 55 <= len(thin) <= 60
    stamps = [f["properties"]["stamp_ns"] for f in thin]
    by_stamp = {int(s): i for i, s in enumerate(rows["stamp_ns"])}
    for f, s in zip(thin, stamps, strict=True):
        i = by_stamp[s]
        assert f["geometry"]["coordinates"][0] == pytest.approx(float(lon[i - 5]), abs=1e-9)
    assert np.all(np.diff(stamps) >= 4 * S)  # 5 s buckets


def _burst(n: int, t0: int) -> np.ndarray:
    """``n`` rows at 10 Hz from ``t0``, driving a lawnmower pattern; every field varies."""
    rows = ramp_series(n, t0=t0)
    k = np.arange(n, dtype=np.float64)
    rows["east_m"] = 20.0 * np.sin(k * 0.02)
    rows["north_m"] = 0.25 * k
    rows["slip_left_pct"] = 8.0 + 6.0 * np.sin(k * 0.05)
    rows["slip_right_pct"] = 7.0 + 6.0 * np.cos(k * 0.03)
    return rows


def test_buckets_follow_the_stored_data_not_the_requested_range(
    client: ApiClient, store: Store
) -> None:
    """A 5-minute drive at the end of a 12 h range keeps its detail: the buckets are sized on
    the stored rows' own span (0.3 s for 2,000 min/max points), not on the 12 h (43.2 s, which
    gave 14 rows: a zig-zag between a few extremes)."""
    client.put("/api/v1/vehicles/t1", json={})
    rows = _burst(3000, T0 + 11 * 3600 * S)
    store.write_estimates([("t1", rows)])
    q = f"{U}?start={T0}&end={T0 + 12 * 3600 * S}&max_points=2000"
    body = client.get(f"{q}&fields=vg_mps,slip_left_pct").json()
    assert 1900 <= body["rows"] <= 2000
    assert body["downsampled"] is True and body["decimation"] == "minmax"
    assert body["stored_rows"] == 3000
    assert body["first_ns"] == int(rows["stamp_ns"][0])
    assert body["last_ns"] == int(rows["stamp_ns"][-1])
    assert body["bucket_ns"] == -(-(299_900_000_000 + 1) // 1000)  # ceil(span / 1000 buckets)
    cols = body["columns"]
    assert max(cols["slip_left_pct"]) == pytest.approx(rows["slip_left_pct"].max(), rel=1e-9)
    assert min(cols["slip_left_pct"]) == pytest.approx(rows["slip_left_pct"].min(), rel=1e-9)
    # the same burst in a range holding only it gives the same answer
    tight = client.get(
        f"{U}?start={rows['stamp_ns'][0]}&end={rows['stamp_ns'][-1] + 1}"
        "&max_points=2000&fields=vg_mps,slip_left_pct"
    ).json()
    assert tight["columns"] == cols
    # fewer stored rows than max_points: all of them, whatever the range
    body = client.get(f"{U}?start={T0}&end={T0 + 12 * 3600 * S}&max_points=4000").json()
    assert body["downsampled"] is False and body["rows"] == body["stored_rows"] == 3000
    assert body["bucket_ns"] == 0


def test_whole_row_thinning_returns_stored_rows(client: ApiClient, store: Store) -> None:
    """decimation=first: every returned row is one stored row, all of its fields (a min/max
    row pairs the east of one estimate with the north of another)."""
    client.put("/api/v1/vehicles/t1", json={})
    rows = _burst(3000, T0 + 6 * 3600 * S)
    store.write_estimates([("t1", rows)])
    q = f"{U}?start={T0}&end={T0 + 12 * 3600 * S}&max_points=500"
    body = client.get(f"{q}&decimation=first").json()
    full = client.get(f"{U}?start={T0}&end={T0 + 12 * 3600 * S}").json()["columns"]
    names = list(full)
    stored = {tuple(full[n][i] for n in names): i for i in range(len(full["stamp_ns"]))}
    cols = body["columns"]
    got = [tuple(cols[n][i] for n in names) for i in range(body["rows"])]
    assert all(g in stored for g in got)
    assert got[0] == tuple(full[n][0] for n in names)
    assert 450 <= body["rows"] <= 500 and body["stored_rows"] == 3000
    assert body["decimation"] == "first" and body["downsampled"] is True
    assert body["bucket_ns"] == -(-(299_900_000_000 + 1) // 500)
    # min/max rows are not stored rows: that is why positions need `first`
    mixed = client.get(q).json()["columns"]
    n_mixed = len(mixed["stamp_ns"])
    not_stored = sum(tuple(mixed[n][i] for n in names) not in stored for i in range(n_mixed))
    assert not_stored > 0
    # GeoJSON thins the same way and refuses min/max
    geo = client.get(f"{q}&format=geojson&fields=east_m")
    assert geo.status_code == 200
    r = client.get(f"{q}&format=geojson&decimation=minmax")
    assert r.status_code == 422 and "decimation" in r.json()["reason"]
    r = client.get(f"{q}&decimation=median")
    assert r.status_code == 422


def test_a_12_hour_drive_at_2000_points(client: ApiClient, store: Store) -> None:
    """A drive filling 12 h (here at 1 Hz) at 2,000 points: 43.2 s min/max buckets, 21.6 s
    whole-row buckets, and the answer says so."""
    client.put("/api/v1/vehicles/t1", json={})
    rows = ramp_series(43_200, step_ns=S)
    store.write_estimates([("t1", rows)])
    q = f"{U}?start={T0}&end={T0 + 12 * 3600 * S}&max_points=2000&fields=vg_mps"
    mm = client.get(q).json()
    # the span is first to last row, 1 s short of 12 h: buckets 1 ms short of 43.2 s
    assert mm["bucket_ns"] == pytest.approx(43.2e9, abs=1e6) and mm["stored_rows"] == 43_200
    assert 1990 <= mm["rows"] <= 2000
    first = client.get(f"{q}&decimation=first").json()
    assert first["bucket_ns"] == pytest.approx(21.6e9, abs=1e6) and first["rows"] == 2000
    assert np.all(np.diff(first["columns"]["stamp_ns"]) >= 21 * S)
