"""/vehicles/{id}/report and /fleet/report against the hand-computed series."""

from __future__ import annotations

import csv
import io
import time

import pytest

from server.storage.base import Store

from ._data import T0, S, hand_series
from .conftest import ApiClient

Q = f"start={T0}&end={T0 + 10 * S}"


@pytest.fixture
def two_vehicles(client: ApiClient, store: Store) -> None:
    client.put("/api/v1/vehicles/t1", json={})
    client.put(
        "/api/v1/vehicles/t2",
        json={"slip": {"band_edges_pct": [10], "min_ground_speed_mps": 3.0}},
    )
    store.write_estimates([("t1", hand_series()), ("t2", hand_series())])
    store.write_counters(
        {"t1": {"received": 12, "accepted": 10, "rejected_bad_payload": 2, "lost": 1}},
        T0,
    )


def test_vehicle_report(client: ApiClient, two_vehicles: None) -> None:
    r = client.get(f"/api/v1/vehicles/t1/report?{Q}")
    assert r.status_code == 200
    body = r.json()
    assert (body["vehicle_id"], body["estimator"]) == ("t1", "mdsf")
    assert body["band_edges_pct"] == [5.0, 15.0]
    rep = body["report"]
    assert rep["rows"] == 10
    assert rep["covered_s"] == 10.0
    assert rep["moving_s"] == 6.0
    assert rep["distance_m"] == pytest.approx(16.0)
    assert rep["degraded_s"] == 2.0
    assert rep["speed"]["mean_mps"] == pytest.approx(16 / 6)
    assert rep["speed"]["max_mps"] == 4.0
    left = rep["slips"]["left"]
    assert left["mean_pct"] == pytest.approx(1.5)
    assert left["median_pct"] == pytest.approx(4.0)
    assert left["p95_pct"] == pytest.approx(17.5)
    assert left["max_pct"] == 20.0
    assert [b["seconds"] for b in left["bands"]] == [2.0, 2.0, 2.0]
    assert left["bands"][2] == {
        "lower_pct": 15.0,
        "upper_pct": None,
        "seconds": 2.0,
        "share": pytest.approx(1 / 3),
    }
    assert rep["slips"]["right"]["samples"] == 2
    ingest = body["ingest"]
    assert ingest["received"] == 12
    assert ingest["accepted"] == 10
    assert ingest["rejected"] == 2
    assert ingest["rejected_by_reason"] == {"bad_payload": 2}
    assert ingest["lost"] == 1


def test_report_uses_vehicle_slip_config(client: ApiClient, two_vehicles: None) -> None:
    body = client.get(f"/api/v1/vehicles/t2/report?{Q}").json()
    assert body["band_edges_pct"] == [10.0]
    assert body["report"]["moving_s"] == 2.0
    assert body["report"]["distance_m"] == pytest.approx(8.0)
    assert [b["seconds"] for b in body["report"]["slips"]["left"]["bands"]] == [3.0, 3.0]
    assert body["ingest"]["received"] == 0


def test_report_errors(client: ApiClient, two_vehicles: None) -> None:
    r = client.get(f"/api/v1/vehicles/t1/report?start={T0}&end={T0 + 2 * 86_400 * S}")
    assert r.status_code == 400
    assert r.json()["error"] == "range_too_large"
    r = client.get("/api/v1/vehicles/t1/report?start=soon&end=later")
    assert r.status_code == 422
    assert r.json()["error"] == "invalid_time"


def test_report_over_a_range_relative_to_the_server_clock(client: ApiClient, store: Store) -> None:
    client.put("/api/v1/vehicles/t3", json={})
    rows = hand_series()
    rows["stamp_ns"] += time.time_ns() - 60 * S - T0  # the 10 s series ended 50 s ago
    store.write_estimates([("t3", rows)])
    body = client.get("/api/v1/vehicles/t3/report?start=now-15m&end=now").json()
    assert body["report"]["rows"] == 10
    assert body["report"]["distance_m"] == pytest.approx(16.0)
    span_ns = body["report"]["end_ns"] - body["report"]["start_ns"]
    assert span_ns == 15 * 60 * S  # both ends read one clock
    assert (
        client.get("/api/v1/vehicles/t3/report?start=now-2m&end=now-1s").json()["report"]["rows"]
        == 10
    )
    assert (
        client.get("/api/v1/vehicles/t3/report?start=now-30s&end=now").json()["report"]["rows"] == 0
    )
    r = client.get("/api/v1/vehicles/t3/report?start=now&end=now-1h")
    assert r.status_code == 422 and r.json()["error"] == "invalid_time"
    r = client.get("/api/v1/vehicles/t3/report?start=now-1w&end=now")
    assert r.status_code == 422 and "start: not a relative time" in r.json()["reason"]


def test_fleet_report_json_and_csv(client: ApiClient, two_vehicles: None) -> None:
    body = client.get(f"/api/v1/fleet/report?{Q}").json()
    assert (body["start_ns"], body["end_ns"]) == (T0, T0 + 10 * S)
    by_id = {v["vehicle_id"]: v for v in body["vehicles"]}
    assert set(by_id) == {"t1", "t2"}
    assert by_id["t1"]["report"]["distance_m"] == pytest.approx(16.0)
    assert by_id["t2"]["report"]["distance_m"] == pytest.approx(8.0)

    r = client.get(f"/api/v1/fleet/report?{Q}&format=csv")
    assert r.headers["content-type"].startswith("text/csv")
    table = {row["vehicle_id"]: row for row in csv.DictReader(io.StringIO(r.text))}
    assert float(table["t1"]["distance_m"]) == pytest.approx(16.0)
    assert float(table["t2"]["moving_s"]) == 2.0
    # band columns are the union over the fleet; empty where a vehicle has no such band
    assert float(table["t1"]["slip_left_share_5_15"]) == pytest.approx(1 / 3)
    assert table["t2"]["slip_left_share_5_15"] == ""
    assert float(table["t2"]["slip_left_share_10_up"]) == pytest.approx(0.5)
    assert table["t1"]["packets_rejected_bad_payload"] == "2"


def test_vehicle_report_csv_is_its_row_of_the_fleet_csv(
    client: ApiClient, two_vehicles: None
) -> None:
    r = client.get(f"/api/v1/vehicles/t2/report?{Q}&format=csv")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    assert r.headers["content-disposition"] == (
        f'attachment; filename="t2_report_{T0}_{T0 + 10 * S}.csv"'
    )
    (row,) = list(csv.DictReader(io.StringIO(r.text)))
    fleet = client.get(f"/api/v1/fleet/report?{Q}&format=csv").text
    in_fleet = {f["vehicle_id"]: f for f in csv.DictReader(io.StringIO(fleet))}["t2"]
    # the same values; the fleet's table also has the other vehicle's band and refusal-reason
    # columns, empty in this vehicle's row
    assert row == {k: v for k, v in in_fleet.items() if k in row}
    others = {k: v for k, v in in_fleet.items() if k not in row}
    assert "slip_left_share_5_15" in others and "packets_rejected_bad_payload" in others
    assert set(others.values()) == {""}
    assert float(row["moving_s"]) == 2.0 and float(row["slip_left_share_10_up"]) == 0.5
    r = client.get(f"/api/v1/vehicles/t1/report?{Q}&format=xlsx")
    assert r.status_code == 422 and r.json()["error"] == "invalid_request"


def test_fleet_report_empty_fleet(client: ApiClient) -> None:
    assert client.get(f"/api/v1/fleet/report?{Q}").json()["vehicles"] == []
    header = client.get(f"/api/v1/fleet/report?{Q}&format=csv").text.splitlines()
    assert len(header) == 1
    # no vehicle, no slip channel: the columns every report has
    assert header[0].startswith("vehicle_id,estimator,rows,")
    assert "distance_m" in header[0] and "slip_" not in header[0]
