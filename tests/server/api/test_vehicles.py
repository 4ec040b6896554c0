"""/vehicles: register, configure, list, delete, latest."""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from estimator.config import (
    DrivenAxle,
    TrackedConfig,
    VehicleKind,
    Wheeled4wdSteeredConfig,
    config_class,
    vehicle_config_from_dict,
)
from estimator.types import EstimateFlag
from server.api import create_app
from server.api.routes.vehicles import VEHICLE_ID_PATTERN
from server.protocol.keys import is_valid_vehicle_id
from server.storage.base import Store

from ._data import T0, hand_series
from .conftest import ApiClient, FakeRuntime, error_of, make_settings, running

V = "/api/v1/vehicles"


def test_register_update_list_get(client: ApiClient, runtime: FakeRuntime) -> None:
    assert client.get(V).json() == {"data": [], "count": 0}

    r = client.put(f"{V}/t1", json={"geometry": {"track_width_m": 2.0}})
    assert r.status_code == 201
    body = r.json()
    assert body["vehicle_id"] == "t1"
    assert body["config"]["geometry"]["track_width_m"] == 2.0
    assert body["config"]["slip"]["band_edges_pct"] == [5.0, 15.0]  # defaults filled in
    assert runtime.config_calls[-1][0] == "t1"
    assert runtime.config_calls[-1][1].geometry.track_width_m == 2.0

    r = client.put(f"{V}/t1", json={"slip": {"band_edges_pct": [10, 20, 30]}})
    assert r.status_code == 200
    assert r.json()["config"]["slip"]["band_edges_pct"] == [10, 20, 30]
    assert r.json()["config"]["geometry"]["track_width_m"] == 1.8  # replaced, not merged
    assert len(runtime.config_calls) == 2
    assert [vid for vid, _ in runtime.config_checks] == ["t1", "t1"]  # checked before stored

    client.put(f"{V}/a0", json={})
    listed = client.get(V).json()
    assert listed["count"] == 2
    assert sorted(v["vehicle_id"] for v in listed["data"]) == ["a0", "t1"]
    one = client.get(f"{V}/t1").json()
    assert one["config"]["slip"]["band_edges_pct"] == [10, 20, 30]
    assert one["created_ns"] <= one["updated_ns"]


def test_vehicle_shows_the_anchor_of_its_frame_once_stored(client: ApiClient, store: Store) -> None:
    client.put(f"{V}/t1", json={})
    client.put(f"{V}/t2", json={})
    assert client.get(f"{V}/t1").json()["anchor"] is None  # no fix yet
    store.put_anchors({"t1": (48.1372, 11.5755, 519.25)}, T0)
    want = {"lat_deg": 48.1372, "lon_deg": 11.5755, "height_m": 519.25}
    assert client.get(f"{V}/t1").json()["anchor"] == want
    listed = {v["vehicle_id"]: v["anchor"] for v in client.get(V).json()["data"]}
    assert listed == {"t1": want, "t2": None}
    r = client.put(f"{V}/t1", json={"geometry": {"track_width_m": 2.0}})  # a new config
    assert r.json()["anchor"] == want  # the frame stays


def test_unknown_vehicle_is_404_json(client: ApiClient) -> None:
    for path in ("nope", "nope/latest", "nope/series?start=0&end=1", "nope/report?start=0&end=1"):
        r = client.get(f"{V}/{path}")
        assert r.status_code == 404, path
        assert r.json()["error"] == "not_found"
        assert "nope" in r.json()["reason"]


def _assert_configs_refused(
    client: ApiClient, runtime: FakeRuntime, cases: list[tuple[dict[str, Any], str]]
) -> None:
    """Each ``(body, words)`` registering ``t1`` is a 422 ``invalid_config`` whose reason holds
    ``words``; none registers the vehicle or reaches the runtime."""
    for body, words in cases:
        r = client.put(f"{V}/t1", json=body)
        assert r.status_code == 422, body
        assert r.json()["error"] == "invalid_config"
        assert words in r.json()["reason"], (body, r.json())
    assert client.get(f"{V}/t1").status_code == 404
    assert runtime.config_calls == []


def test_bad_config_is_422_with_reason(client: ApiClient, runtime: FakeRuntime) -> None:
    cases = [
        ({"geometry": {"h0_m": -1}}, "h0_m"),
        ({"geometry": {"antenna_offset_m": [1]}}, "antenna_offset_m"),
        ({"slip": {"band_edges_pct": [15, 5]}}, "band_edges_pct"),
        ({"wheels": 4}, "unknown field"),
        ({"geometry": {"colour": "red"}}, "unknown field"),
        ({"kind": "hovercraft"}, "kind"),
        ({"estimators": "mdsf"}, "estimators"),
        ({"estimators": [1, 2]}, "estimators"),
        ({"encoder": 7}, "encoder"),
        ({"slip": {"band_edges_pct": [{}]}}, "band_edges_pct"),
        ({"slip": {"band_edges_pct": [-5]}}, "band_edges_pct"),
        ({"geometry": {"h0_m": True}}, "h0_m"),
    ]
    _assert_configs_refused(client, runtime, cases)


def test_malformed_body_and_id(client: ApiClient) -> None:
    r = client.put(f"{V}/t1", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert r.json()["error"] == "invalid_request"
    r = client.put(f"{V}/t1", json=[1, 2])
    assert r.status_code == 422
    r = client.put(f"{V}/bad*id", json={})
    assert r.status_code == 422
    assert "vehicle_id" in r.json()["reason"]


def test_body_size_limit(client: ApiClient) -> None:
    r = client.put(f"{V}/t1", json={"estimators": ["x" * 100_000]})
    assert r.status_code == 413
    assert r.json()["error"] == "payload_too_large"

    async def chunks() -> AsyncIterator[bytes]:  # no Content-Length: counted while streaming
        for _ in range(100):
            yield b" " * 1024

    r = client.put(f"{V}/t1", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413


def test_runtime_may_refuse_config(client: ApiClient, runtime: FakeRuntime) -> None:
    from estimator.config import ConfigError

    def check(vehicle_id: str, config: object) -> None:
        raise ConfigError("estimator 'nope' is not registered")

    runtime.check_vehicle_config = check  # type: ignore[attr-defined]
    r = client.put(f"{V}/t1", json={"estimators": ["nope"]})
    assert r.status_code == 422
    assert "nope" in r.json()["reason"]
    assert client.get(f"{V}/t1").status_code == 404


def test_an_estimator_command_goes_to_the_runtime_or_is_refused_saying_why(
    client: ApiClient, runtime: FakeRuntime
) -> None:
    assert client.put(f"{V}/t1", json={}).status_code == 201  # runs mdsf
    assert client.put(f"{V}/c1", json={"kind": "tracked"}).status_code == 201
    r = client.put(f"{V}/t1/commands/mdsf/calibration_drive", json={"on": True})
    assert r.status_code == 200, r.text
    assert r.json() == {
        "vehicle_id": "t1",
        "estimator": "mdsf",
        "command": "calibration_drive",
        "on": True,
    }
    assert runtime.commands == [("t1", "mdsf", "calibration_drive", True)]

    def put(path: str, body: object) -> httpx.Response:
        return client.put(f"{V}/{path}", json=body)

    _, reason = error_of(put("c1/commands/mdsf/calibration_drive", {"on": True}), 409)
    assert "runs tracked, not 'mdsf'" in reason
    _, reason = error_of(put("t1/commands/mdsf/nope", {"on": True}), 404)
    assert "calibration_drive" in reason  # what it has
    error_of(put("t1/commands/nope/x", {"on": True}), 404)
    error_of(put("nobody/commands/mdsf/calibration_drive", {"on": True}), 404)
    error_of(put("t1/commands/mdsf/calibration_drive", {"on": "x"}), 422)
    error_of(put("t1/commands/mdsf/calibration_drive", {}), 422)
    assert len(runtime.commands) == 1  # none of the refused ones reached the estimator


def test_delete(client: ApiClient, runtime: FakeRuntime, store: Store) -> None:
    client.put(f"{V}/t1", json={})
    store.write_estimates([("t1", hand_series())])
    r = client.delete(f"{V}/t1")
    assert r.status_code == 204
    assert runtime.deleted == ["t1"]
    assert client.get(f"{V}/t1").status_code == 404
    assert store.query_series("t1", 0, 2**62).shape == (0,)
    r = client.delete(f"{V}/t1")
    assert r.status_code == 404


def test_delete_refused_while_auth_required_without_a_token(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, require_auth=True)
    runtime = FakeRuntime(settings)
    with running(create_app(settings, runtime)) as client:
        runtime.store.upsert_vehicle("t1", {}, 1)
        r = client.delete(f"{V}/t1")
        assert r.status_code == 401
        assert r.json()["error"] == "unauthorized"
        r = client.delete(f"{V}/t1", headers={"Authorization": "Bearer anything"})
        assert r.status_code == 401
        assert runtime.store.get_vehicle("t1") is not None


def test_latest(client: ApiClient, store: Store) -> None:
    client.put(f"{V}/t1", json={})
    r = client.get(f"{V}/t1/latest")
    assert r.status_code == 404
    assert "no mdsf estimates" in r.json()["reason"]

    rows = hand_series()
    rows["flags"][-1] = int(EstimateFlag.GNSS_OK | EstimateFlag.SLIP_RIGHT_VALID)
    rows["slip_right_pct"][-1] = 12.5
    store.write_estimates([("t1", rows)])
    body = client.get(f"{V}/t1/latest").json()
    assert (body["vehicle_id"], body["estimator"]) == ("t1", "mdsf")
    assert body["stamp_ns"] == T0 + 9 * 1_000_000_000
    assert body["time"] == "2024-05-01T12:00:09.000000000Z"
    assert body["vg_mps"] == 0.0
    assert body["slip_right_pct"] == 12.5
    assert body["slip_left_pct"] is None  # NaN
    assert body["flags"] == 1 | 32
    assert body["flag_names"] == ["GNSS_OK", "SLIP_RIGHT_VALID"]
    names = {n for n in np.dtype(store.latest("t1").dtype).names or ()}  # type: ignore[union-attr]
    assert names <= set(body)


@given(st.text(max_size=70) | st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,70}", fullmatch=True))
def test_id_pattern_agrees_with_the_wire_protocol(vehicle_id: str) -> None:
    ours = re.fullmatch(VEHICLE_ID_PATTERN.strip("^$"), vehicle_id) is not None
    assert ours == is_valid_vehicle_id(vehicle_id)


KIND_BODIES: dict[str, dict[str, Any]] = {
    "wheeled_rear_drive": {"kind": "wheeled_rear_drive", "geometry": {"track_width_m": 2.1}},
    "tracked": {
        "kind": "tracked",
        "geometry": {"track_gauge_m": 2.4, "imu_lever_arm_m": [0.1, -0.3, 1.4]},
        "odometer": {"distance_per_edge_m": 0.02},
        "motion": {"low_gear_ratio": 1.5},
    },
    "wheeled_4wd_steered": {
        "kind": "wheeled_4wd_steered",
        "chassis": {"mass_kg": 1800, "driven_axle": "rear", "tilt_axis_height_m": 0.45},
        "tyre": {"kz_npm": 50_000},
    },
}


def test_register_each_kind(client: ApiClient, runtime: FakeRuntime, store: Store) -> None:
    for kind, body in KIND_BODIES.items():
        r = client.put(f"{V}/{kind}", json=body)
        assert r.status_code == 201, r.json()
        stored = r.json()["config"]
        assert stored == _merged(config_class(kind)().to_dict(), body)
        assert type(runtime.config_calls[-1][1]) is config_class(kind)
        assert client.get(f"{V}/{kind}").json()["config"] == stored
        record = store.get_vehicle(kind)
        assert record is not None and vehicle_config_from_dict(record.config).to_dict() == stored
    steered, tracked = runtime.config_calls[-1][1], runtime.config_calls[-2][1]
    assert isinstance(steered, Wheeled4wdSteeredConfig)
    assert steered.chassis.driven_axle is DrivenAxle.REAR and steered.tyre.kz_npm == 50_000
    assert steered.chassis.tilt_axis_height_m == 0.45
    assert isinstance(tracked, TrackedConfig) and tracked.geometry.imu_lever_arm_m == (
        0.1,
        -0.3,
        1.4,
    )


def _merged(full: dict[str, Any], body: dict[str, Any]) -> dict[str, Any]:
    """``full`` with every section's fields as ``body`` gives them (and the rest as is)."""
    out = dict(full)
    for name, part in body.items():
        out[name] = {**full[name], **part} if isinstance(part, dict) else part
    return out


def test_wrong_kind_or_field_is_422_naming_it(client: ApiClient, runtime: FakeRuntime) -> None:
    cases = [
        ({"kind": "tracked", "geometry": {"track_width_m": 2.0}}, "tracked: geometry: unknown"),
        ({"kind": "tracked", "encoder": {"teeth_per_rev": 60}}, "tracked: unknown field"),
        ({"kind": "wheeled_4wd_steered", "geometry": {}}, "wheeled_4wd_steered: unknown field"),
        ({"kind": "wheeled_4wd_steered", "chassis": {"driven_axle": "middle"}}, "driven_axle"),
        ({"kind": "tracked", "sprocket": {"teeth_per_rev": 12.0}}, "teeth_per_rev"),
        ({"kind": "tracked", "geometry": {"imu_lever_arm_m": [0, 0]}}, "imu_lever_arm_m"),
        ({"kind": "tracked", "motion": {"low_gear_ratio": True}}, "low_gear_ratio"),
        ({"kind": 3}, "kind"),
        ({"noise": {"accel_std_mps2": 1e200}}, "noise.accel_std_mps2 must be a number in "),
        ({"slip": {"alert_hold_s": 1e12}}, "slip.alert_hold_s must be a number in 0.1..3600 s"),
        ({"kind": "tracked", "odometer": {"distance_per_edge_m": 5}}, "0.0001..1 m"),
        ({"kind": "wheeled_4wd_steered", "tyre": {"kz_npm": 1e3}}, "10000..5e+06 N/m"),
        (
            {"kind": "wheeled_4wd_steered", "chassis": {"tilt_axis_height_m": -0.2}},
            "chassis.tilt_axis_height_m must be a number in 0..4 m",
        ),
        ({"estimators": [""]}, "estimators"),
    ]
    _assert_configs_refused(client, runtime, cases)


def test_a_crawlers_gyro_by_part_or_by_its_figures(
    client: ApiClient, runtime: FakeRuntime, store: Store
) -> None:
    figures = {
        "angle_random_walk_deg_rt_h": 0.9,
        "bias_stability_deg_h": 20.0,
        "noise_density_dps_rt_hz": 0.02,
    }
    bodies = {
        "named": {"part": "ADIS16470"},
        "own": {"part": "MEMS-X", **figures},
        "worse-arw": {"part": "ADIS16470", "angle_random_walk_deg_rt_h": 0.5},
    }
    for vid, gyro in bodies.items():
        r = client.put(f"{V}/{vid}", json={"kind": "tracked", "gyro": gyro})
        assert r.status_code == 201, r.json()
        stored = r.json()["config"]["gyro"]
        assert stored == {**dict.fromkeys(figures), **gyro}  # null: the named part's figures
        record = store.get_vehicle(vid)
        assert record is not None
        config = vehicle_config_from_dict(record.config)
        assert isinstance(config, TrackedConfig) and config == runtime.config_calls[-1][1]
        assert (
            config.to_dict()["gyro"] == stored == client.get(f"{V}/{vid}").json()["config"]["gyro"]
        )
    part = vehicle_config_from_dict(store.get_vehicle("worse-arw").config).gyro.resolved()  # type: ignore[union-attr]
    assert (part.angle_random_walk_deg_rt_h, part.bias_stability_deg_h) == (0.5, 8.0)
    refused = [
        ({"part": "BMI999"}, "tracked: gyro.part 'BMI999' is not a known gyro part ['ADIS16470']"),
        ({"part": "MEMS-X", "bias_stability_deg_h": 2.0}, "give all three of"),
        ({**figures, "part": ""}, "gyro.part must be a name of 1 to 64 characters"),
        ({"angle_random_walk_deg_rt_h": 0}, "gyro.angle_random_walk_deg_rt_h must be a number in"),
        ({"bias_stability_deg_h": -8.0}, "gyro.bias_stability_deg_h must be a number in 0.0001"),
        ({"noise_density_dps_rt_hz": "0.008"}, "gyro.noise_density_dps_rt_hz must be a number"),
        ({"model": "ADIS16470"}, "gyro: unknown field(s) ['model']"),
    ]
    calls = len(runtime.config_calls)
    for gyro, words in refused:
        r = client.put(f"{V}/bad", json={"kind": "tracked", "gyro": gyro})
        assert r.status_code == 422, gyro
        reason = r.json()["reason"]
        assert words in reason and "\n" not in reason, (gyro, reason)
    assert client.get(f"{V}/bad").status_code == 404
    assert len(runtime.config_calls) == calls


def test_config_schema_is_a_union_on_kind_with_ranges_and_units(client: ApiClient) -> None:
    op = client.get("/openapi.json").json()["paths"]["/api/v1/vehicles/{vehicle_id}"]["put"]
    schema = op["requestBody"]["content"]["application/json"]["schema"]
    answer = op["responses"]["200"]["content"]["application/json"]["schema"]
    assert client.get("/openapi.json").json()["components"]["schemas"][
        answer["$ref"].split("/")[-1]
    ]["properties"]["config"]["discriminator"] == {"propertyName": "kind"}
    by_kind = {s["properties"]["kind"]["const"]: s for s in schema["oneOf"]}
    assert set(by_kind) == {k.value for k in VehicleKind}
    accel = by_kind["tracked"]["properties"]["noise"]["properties"]["accel_std_mps2"]
    assert (accel["minimum"], accel["maximum"]) == (1e-6, 10.0)
    assert "m/s²" in accel["description"]
    hold = by_kind["wheeled_rear_drive"]["properties"]["slip"]["properties"]["alert_hold_s"]
    assert hold["maximum"] == 3600.0 and hold["description"].endswith("0.1..3600 s")
    kz = by_kind["wheeled_4wd_steered"]["properties"]["tyre"]["properties"]["kz_npm"]
    assert kz["minimum"] == 1e4 and "N/m" in kz["description"]
    teeth = by_kind["tracked"]["properties"]["sprocket"]["properties"]["teeth_per_rev"]
    assert teeth["type"] == "integer"
    # every number of every kind has a range and a unit
    for kind in by_kind.values():
        for name, section in kind["properties"].items():
            for field, spec in section.get("properties", {}).items():
                if spec.get("type") in ("number", "integer", "array") and name != "estimators":
                    assert "minimum" in spec or "minimum" in spec.get("items", {}), field
                    assert ".." in spec["description"], field


def test_a_config_the_runtime_refuses_is_not_stored(
    client: ApiClient, runtime: FakeRuntime
) -> None:
    runtime.refuse_configs = "estimator 'kalman9' is not on this server"
    r = client.put(f"{V}/t1", json={})
    assert r.status_code == 422
    assert r.json()["error"] == "invalid_config"
    assert "kalman9" in r.json()["reason"]
    assert client.get(f"{V}/t1").status_code == 404
    assert runtime.config_calls == []
