"""Estimate routes of any estimator: the spec list, ``estimator=`` on every route, fields and
formats checked against the spec, and REST writes through the store writer.

A vehicle stores rows of two estimators (MDSF and the GNSS-free reference speed) in a real
SQLite file; every route reads the one it is asked for.
"""

from __future__ import annotations

import csv
import io

import pytest

from estimator.catalog import SPECS
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC as REF
from estimator.types import EstimateBatch
from server.storage.base import Store

from ._data import T0, S, hand_series, reference_series
from .conftest import ApiClient, FakeRuntime, error_of

Q = f"start={T0}&end={T0 + 10 * S}"
V = "/api/v1/vehicles"


@pytest.fixture
def both(client: ApiClient, store: Store) -> None:
    """Vehicle ``t1`` (default config: MDSF primary) with rows of MDSF and reference speed."""
    assert client.put(f"{V}/t1", json={}).status_code == 201
    store.write_estimates(EstimateBatch.of([("t1", hand_series())], SPECS["mdsf"]))
    store.write_estimates(EstimateBatch.of([("t1", reference_series())], REF))


def test_estimators_lists_every_spec(client: ApiClient) -> None:
    body = client.get("/api/v1/estimators").json()
    assert body["count"] == len(SPECS)
    assert body["data"] == [SPECS[name].to_dict() for name in sorted(SPECS)]
    rules = {s["name"]: {a["key"] for a in s["alerts"]} for s in body["data"]}
    assert "long_dead_reckoning" in rules["tracked"] and "low_mu" in rules["friction"]


def test_vehicle_names_its_estimators_primary_first(client: ApiClient, both: None) -> None:
    assert client.get(f"{V}/t1").json()["estimators"] == ["mdsf"]
    assert client.get(V).json()["data"][0]["estimators"] == ["mdsf"]
    client.put(f"{V}/tracked", json={"kind": "tracked"})  # its kind's default estimator
    assert client.get(f"{V}/tracked").json()["estimators"] == ["tracked"]
    r = client.get(f"{V}/tracked/report?{Q}")
    assert r.json()["estimator"] == "tracked" and r.json()["report"]["rows"] == 0
    assert client.get(f"{V}/tracked/report?{Q}&estimator=mdsf").json()["report"]["rows"] == 0


def test_series_of_each_estimator(client: ApiClient, both: None) -> None:
    mdsf = client.get(f"{V}/t1/series?{Q}").json()
    assert mdsf["estimator"] == "mdsf" and mdsf["fields"] == list(SPECS["mdsf"].field_names)
    ref = client.get(f"{V}/t1/series?{Q}&estimator=reference_speed").json()
    assert ref["estimator"] == "reference_speed"
    assert ref["fields"] == list(REF.field_names)
    assert ref["columns"]["speed_mps"] == [0, 0, 1, 2, 2, 3, 3, 1, 0.1, 0]
    assert ref["columns"]["speed_std_mps"] == [None] * 10
    csv_text = client.get(
        f"{V}/t1/series?{Q}&estimator=reference_speed&format=csv&fields=speed_mps,flags"
    ).text
    table = list(csv.DictReader(io.StringIO(csv_text)))
    assert [float(r["speed_mps"]) for r in table][:4] == [0, 0, 1, 2]
    assert int(table[2]["flags"]) == REF.flag_mask("NO_WHEEL")


def test_fields_and_estimators_are_checked_against_the_spec(client: ApiClient, both: None) -> None:
    r = client.get(f"{V}/t1/series?{Q}&estimator=reference_speed&fields=speed_mps,vg_mps")
    error, reason = error_of(r, 422)
    assert error == "invalid"
    assert "'reference_speed'" in reason and "vg_mps" in reason and "speed_mps" in reason
    error, reason = error_of(client.get(f"{V}/t1/series?{Q}&estimator=kalman9"), 422)
    assert "unknown estimator 'kalman9'" in reason and "reference_speed" in reason
    for route in ("latest?", f"report?{Q}&", f"slipmap?{Q}&"):
        assert error_of(client.get(f"{V}/t1/{route}estimator=nope"), 422)[0] == "invalid", route


def test_geojson_and_slipmap_need_a_position(client: ApiClient, both: None) -> None:
    r = client.get(f"{V}/t1/series?{Q}&estimator=reference_speed&format=geojson")
    error, reason = error_of(r, 400)
    assert error == "bad_request" and "'reference_speed' gives no position" in reason
    error, reason = error_of(client.get(f"{V}/t1/slipmap?{Q}&estimator=reference_speed"), 400)
    assert "'reference_speed' gives no position" in reason
    r = client.get(f"/api/v1/fleet/slipmap?{Q}&estimator=reference_speed")
    assert error_of(r, 400)[0] == "bad_request"
    # the primary (MDSF) has one
    assert client.get(f"{V}/t1/series?{Q}&format=geojson").status_code == 200


def test_report_of_an_estimator_without_slip_channels(client: ApiClient, both: None) -> None:
    body = client.get(f"{V}/t1/report?{Q}&estimator=reference_speed").json()
    assert body["estimator"] == "reference_speed"
    rep = body["report"]
    assert (rep["motion"], rep["motion_field"]) == ("reference", "speed_mps")
    assert rep["slips"] == {}
    assert rep["moving_s"] == 6.0  # |speed| >= 0.2 m/s on rows 2..7 (row 8: 0.1 m/s)
    assert rep["distance_m"] == pytest.approx(12.0)
    assert rep["degraded_s"] == 2.0  # NO_WHEEL on rows 2 and 3
    assert rep["speed"]["max_mps"] == 3.0


def test_fleet_report_per_estimator(client: ApiClient, both: None) -> None:
    default = client.get(f"/api/v1/fleet/report?{Q}").json()["vehicles"]
    assert [(v["vehicle_id"], v["estimator"]) for v in default] == [("t1", "mdsf")]
    ref = client.get(f"/api/v1/fleet/report?{Q}&estimator=reference_speed").json()["vehicles"]
    assert [(v["vehicle_id"], v["estimator"]) for v in ref] == [("t1", "reference_speed")]
    assert ref[0]["report"]["distance_m"] == pytest.approx(1 + 2 + 2 + 3 + 3 + 1)
    table = client.get(f"/api/v1/fleet/report?{Q}&estimator=reference_speed&format=csv").text
    (row,) = list(csv.DictReader(io.StringIO(table)))
    assert row["estimator"] == "reference_speed" and float(row["degraded_s"]) == 2.0
    assert not [k for k in row if k.startswith("slip_")]


def test_latest_of_each_estimator(client: ApiClient, both: None) -> None:
    mdsf = client.get(f"{V}/t1/latest").json()
    assert mdsf["estimator"] == "mdsf" and "vg_mps" in mdsf
    ref = client.get(f"{V}/t1/latest?estimator=reference_speed").json()
    assert ref["estimator"] == "reference_speed"
    assert set(ref) == {"vehicle_id", "estimator", "time", "flag_names", *REF.field_names}
    assert ref["flag_names"] == ["WHEEL_OK"] and ref["speed_mps"] == 0.0


def test_openapi_describes_each_estimator(client: ApiClient) -> None:
    spec = client.get("/openapi.json").json()
    series = spec["paths"]["/api/v1/vehicles/{vehicle_id}/series"]["get"]
    params = {p["name"]: p for p in series["parameters"]}
    assert "`reference_speed`" in params["estimator"]["description"]
    fields_doc = params["fields"]["description"]
    assert "`speed_mps` (m/s)" in fields_doc and "`slip_left_pct` (%)" in fields_doc
    latest = spec["paths"]["/api/v1/vehicles/{vehicle_id}/latest"]["get"]
    one_of = latest["responses"]["200"]["content"]["application/json"]["schema"]["oneOf"]
    names = {ref["$ref"].rsplit("/", 1)[1] for ref in one_of}
    camel = {name: "".join(w.title() for w in name.split("_")) for name in SPECS}
    assert names == {f"Estimate{c}Public" for c in camel.values()}
    assert {"EstimateMdsfPublic", "EstimateReferenceSpeedPublic", "EstimateTrackedPublic"} <= names
    ref_model = spec["components"]["schemas"]["EstimateReferenceSpeedPublic"]["properties"]
    assert "m/s" in ref_model["speed_mps"]["description"]
    for path in ("report", "slipmap", "latest", "series"):
        op = spec["paths"][f"/api/v1/vehicles/{{vehicle_id}}/{path}"]["get"]
        assert "estimator" in {p["name"] for p in op["parameters"]}, path


def test_rest_writes_need_the_store_writer(client: ApiClient, runtime: FakeRuntime) -> None:
    """Vehicle and token writes go through the writer: without one they are refused (503) and
    nothing is written beside it."""
    assert client.put(f"{V}/t1", json={}).status_code == 201
    writer = runtime.writer
    runtime.writer = None
    try:
        assert error_of(client.put(f"{V}/t2", json={}), 503)[0] == "unavailable"
        assert error_of(client.delete(f"{V}/t1"), 503)[0] == "unavailable"
        r = client.post("/api/v1/tokens", json={"name": "x", "role": "viewer"})
        assert error_of(r, 503)[0] == "unavailable"
    finally:
        runtime.writer = writer
    assert runtime.store.get_vehicle("t2") is None
    assert runtime.store.get_vehicle("t1") is not None
    assert runtime.store.list_tokens() == []
    assert client.delete(f"{V}/t1").status_code == 204
    assert runtime.store.get_vehicle("t1") is None


def test_fleet_slipmap_skips_vehicles_of_another_estimator(
    client: ApiClient, store: Store, both: None
) -> None:
    """Without ``estimator=`` the map is of the first placed vehicle's primary (MDSF); an
    anchored vehicle whose primary differs (here: none) is listed as ``other_estimator``."""
    client.put(f"{V}/tracked", json={"kind": "tracked"})
    client.put(f"{V}/u-no-fix", json={})
    store.put_anchors({"t1": (52.0, 5.6, 12.0), "tracked": (52.0, 5.6, 12.0)}, T0)
    body = client.get(f"/api/v1/fleet/slipmap?{Q}").json()
    assert body["estimator"] == "mdsf"
    assert [v["vehicle_id"] for v in body["vehicles"]] == ["t1"]
    assert body["skipped"] == [
        {"vehicle_id": "tracked", "reason": "other_estimator"},
        {"vehicle_id": "u-no-fix", "reason": "no_anchor"},
    ]
    asked = client.get(f"/api/v1/fleet/slipmap?{Q}&estimator=mdsf").json()
    assert [v["vehicle_id"] for v in asked["vehicles"]] == ["t1", "tracked"]
    assert [v["rows"] for v in asked["vehicles"]] == [0, 0]  # no position in hand_series
