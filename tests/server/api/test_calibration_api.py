"""``/vehicles/{id}/calibration``: each calibration of the newest stored row with its std,
converged against the vehicle config's threshold and since when; the reset goes to the runtime.

Real parts: the app over a real store (the test runtime: SQLite, and PostgreSQL), rows written
into it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from estimator.mdsf_spec import MDSF_SPEC
from estimator.tracked_spec import TRACKED_SPEC, TrackedFlag
from estimator.types import EstimateBatch, EstimateFlag, empty_estimates
from server.api.limits import HEAVY_ROUTES
from server.estimation.calibration import stored_calibrations
from server.settings import Settings
from server.storage.base import Store

from ._data import T0
from .conftest import ApiClient, FakeRuntime, error_of, make_settings, running_on

V = "/api/v1/vehicles"
STEP_NS = 100_000_000
RADIUS_M = 0.8


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def settings(tmp_path: Path, request: pytest.FixtureRequest) -> Settings:
    """The test runtime's store: SQLite in ``tmp_path``, or a fresh PostgreSQL database."""
    url = request.getfixturevalue("pg_database_url") if request.param == "postgresql" else None
    return make_settings(tmp_path, url=url)


def _learning(n: int = 50) -> np.ndarray:
    """``n`` rows 0.1 s apart of a calibration being learnt: the left radius's std falls from
    1 % to 0.05 % of 0.816 m (converged below 0.15 % from row 20 on), the GNSS clock offset's
    from 50 to 5 ms (below 10 ms from row 30), the rest stays at its prior; flagged
    UNCALIBRATED until row 40."""
    rows = empty_estimates(n)
    rows["stamp_ns"] = T0 + np.arange(n, dtype=np.int64) * STEP_NS
    k = np.arange(n)
    rows["radius_left_m"] = 0.816
    rows["radius_left_std_m"] = np.where(k < 20, 0.01 * 0.816, 0.0005 * 0.816)
    rows["radius_right_m"] = RADIUS_M
    rows["radius_right_std_m"] = 0.03 * RADIUS_M
    rows["gnss_clock_offset_s"] = -0.08
    rows["gnss_clock_offset_std_s"] = np.where(k < 30, 0.05, 0.005)
    rows["wheel_clock_offset_s"] = 0.0
    rows["wheel_clock_offset_std_s"] = 0.1
    rows["imu_pitch_mount_rad"] = math.radians(3.0)
    rows["imu_pitch_mount_std_rad"] = math.radians(0.1)
    rows["flags"] = np.where(k < 40, int(EstimateFlag.UNCALIBRATED), 0) | int(EstimateFlag.GNSS_OK)
    return rows


def _by_key(part: dict) -> dict[str, dict]:
    return {c["key"]: c for c in part["calibrations"]}


def test_each_calibration_with_its_std_converged_state_and_since_when(
    client: ApiClient, store: Store
) -> None:
    assert client.put(f"{V}/t1", json={}).status_code == 201  # a rear-drive vehicle: mdsf
    store.write_estimates([("t1", _learning())])
    r = client.get(f"{V}/t1/calibration")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["vehicle_id"] == "t1" and body["lookback_s"] == 3600
    [part] = body["estimators"]
    assert part["estimator"] == "mdsf"
    assert part["stamp_ns"] == T0 + 49 * STEP_NS
    assert part["uncalibrated"] is False
    assert part["uncalibrated_since_ns"] == T0 + 40 * STEP_NS
    cal = _by_key(part)
    assert set(cal) == {c.key for c in MDSF_SPEC.calibrations}
    left = cal["radius_left"]
    assert left["unit"] == "m" and left["field"] == "radius_left_m"
    assert left["value"] == pytest.approx(0.816)
    assert left["std"] == pytest.approx(0.0005 * 0.816)
    assert left["limit"] == pytest.approx(0.0015 * 0.816)  # 0.15 % of the radius
    assert left["converged"] and left["since_ns"] == T0 + 20 * STEP_NS
    assert not left["since_window_start"]
    gnss = cal["gnss_clock_offset"]
    assert gnss["converged"] and gnss["since_ns"] == T0 + 30 * STEP_NS
    assert gnss["limit"] == pytest.approx(0.010)
    right = cal["radius_right"]
    assert not right["converged"] and right["since_ns"] == T0 and right["since_window_start"]
    assert cal["imu_pitch_mount"]["converged"]
    # a window that starts after the radius converged: converged at least since its start
    r = client.get(f"{V}/t1/calibration", params={"lookback_s": 1})
    left = _by_key(r.json()["estimators"][0])["radius_left"]
    assert left["since_window_start"] and left["since_ns"] == T0 + 39 * STEP_NS


def test_thresholds_and_switches_come_from_the_vehicles_config(
    client: ApiClient, store: Store
) -> None:
    """A looser radius threshold makes the right radius converged; a calibration the config
    turns off never is."""
    config = {"calibration": {"radius_converged_pct": 5.0, "imu_mounting": False}}
    assert client.put(f"{V}/t1", json=config).status_code == 201
    store.write_estimates([("t1", _learning())])
    cal = _by_key(client.get(f"{V}/t1/calibration").json()["estimators"][0])
    assert cal["radius_right"]["converged"]
    assert cal["radius_right"]["limit"] == pytest.approx(0.05 * RADIUS_M)
    assert not cal["imu_pitch_mount"]["enabled"] and not cal["imu_pitch_mount"]["converged"]


def test_a_vehicle_without_rows_and_one_that_calibrates_nothing(client: ApiClient) -> None:
    client.put(f"{V}/t1", json={})
    [part] = client.get(f"{V}/t1/calibration").json()["estimators"]
    assert part["stamp_ns"] is None and part["uncalibrated"] is None
    assert all(c["value"] is None and not c["converged"] for c in part["calibrations"])
    client.put(f"{V}/c1", json={"kind": "tracked"})
    [part] = client.get(f"{V}/c1/calibration").json()["estimators"]
    assert part["estimator"] == "tracked" and part["uncalibrated"] is None
    gyro, clock = part["calibrations"]
    assert gyro["key"] == "gyro_arw" and gyro["unit"] == "°/√h" and gyro["enabled"]
    assert gyro["value"] is None and gyro["limit"] is None and not gyro["converged"]
    assert clock["key"] == "gnss_clock_offset" and clock["unit"] == "s" and clock["enabled"]
    assert clock["value"] is None and clock["limit"] == pytest.approx(0.010)
    assert not clock["converged"]
    client.put(f"{V}/c2", json={"kind": "tracked", "calibration": {"gyro_noise": False}})
    [part] = client.get(f"{V}/c2/calibration").json()["estimators"]
    assert not part["calibrations"][0]["enabled"]
    error_of(client.get(f"{V}/c1/calibration", params={"estimator": "mdsf"}), 404)
    client.put(f"{V}/s1", json={"kind": "wheeled_4wd_steered"})
    assert client.get(f"{V}/s1/calibration").json()["estimators"] == []
    error_of(client.get(f"{V}/nobody/calibration"), 404)
    error_of(client.get(f"{V}/t1/calibration", params={"lookback_s": 0}), 422)


def _crawler_learning(n: int = 50) -> np.ndarray:
    """``n`` tracked rows 0.1 s apart of a receiver clock being learnt: 65 ms, its std
    falling from 150 ms to 4 ms at row 25 (below 10 ms from there on); no gyro measurement
    (NaN: the crawler has not stood)."""
    rows = TRACKED_SPEC.empty_rows(n)
    rows["stamp_ns"] = T0 + np.arange(n, dtype=np.int64) * STEP_NS
    k = np.arange(n)
    rows["gnss_clock_offset_s"] = 0.065
    rows["gnss_clock_offset_std_s"] = np.where(k < 25, 0.15, 0.004)
    rows["flags"] = int(TrackedFlag.GNSS_OK)
    return rows


def test_a_crawlers_receiver_clock_with_its_std_converged_state_and_since_when(
    client: ApiClient, store: Store
) -> None:
    """The tracked rows' receiver clock is shown as any calibration: its value and std in
    seconds, the limit from the crawler's config (10 ms by default, 2 ms set), converged
    since the row its std fell below it; a restart restores it though the gyro is unmeasured."""
    assert client.put(f"{V}/c1", json={"kind": "tracked"}).status_code == 201
    store.write_estimates(EstimateBatch.of([("c1", _crawler_learning())], TRACKED_SPEC))
    r = client.get(f"{V}/c1/calibration")
    assert r.status_code == 200, r.text
    [part] = r.json()["estimators"]
    assert part["estimator"] == "tracked" and part["stamp_ns"] == T0 + 49 * STEP_NS
    assert part["uncalibrated"] is None  # the tracked spec has no uncalibrated flag
    cal = _by_key(part)
    clock = cal["gnss_clock_offset"]
    assert clock["unit"] == "s" and clock["field"] == "gnss_clock_offset_s"
    assert clock["value"] == pytest.approx(0.065) and clock["std"] == pytest.approx(0.004)
    assert clock["limit"] == pytest.approx(0.010) and clock["enabled"]
    assert clock["converged"] and clock["since_ns"] == T0 + 25 * STEP_NS
    assert cal["gyro_arw"]["value"] is None and not cal["gyro_arw"]["converged"]
    tight = {"kind": "tracked", "calibration": {"clock_offset_converged_ms": 2.0}}
    assert client.put(f"{V}/c1", json=tight).status_code == 200
    clock = _by_key(client.get(f"{V}/c1/calibration").json()["estimators"][0])["gnss_clock_offset"]
    assert clock["limit"] == pytest.approx(0.002) and not clock["converged"]
    assert stored_calibrations(store)[("c1", "tracked")] == pytest.approx(
        {"gnss_clock_offset_s": 0.065, "gnss_clock_offset_std_s": 0.004}
    )


def test_reset_goes_to_the_runtime_or_is_refused_saying_why(
    client: ApiClient, runtime: FakeRuntime
) -> None:
    client.put(f"{V}/t1", json={})
    client.put(f"{V}/c1", json={"kind": "tracked"})
    r = client.delete(f"{V}/t1/calibration/mdsf")
    assert r.status_code == 202, r.text
    assert r.json() == {"vehicle_id": "t1", "estimator": "mdsf", "reset": True}
    assert runtime.calibration_resets == [("t1", "mdsf")]
    _, reason = error_of(client.delete(f"{V}/t1/calibration/friction"), 404)
    assert "those that do: mdsf, tracked" in reason
    _, reason = error_of(client.delete(f"{V}/t1/calibration/tracked"), 409)
    assert "runs mdsf, not 'tracked'" in reason
    _, reason = error_of(client.delete(f"{V}/c1/calibration/mdsf"), 409)
    assert "runs tracked" in reason
    assert client.delete(f"{V}/c1/calibration/tracked").status_code == 202
    error_of(client.delete(f"{V}/nobody/calibration/mdsf"), 404)
    assert runtime.calibration_resets == [("t1", "mdsf"), ("c1", "tracked")]


def test_the_spec_lists_the_calibrations_for_clients(client: ApiClient) -> None:
    mdsf = next(s for s in client.get("/api/v1/estimators").json()["data"] if s["name"] == "mdsf")
    assert mdsf["uncalibrated_flag"] == "UNCALIBRATED"
    assert [c["key"] for c in mdsf["calibrations"]] == [c.key for c in MDSF_SPEC.calibrations]
    tracked = next(
        s for s in client.get("/api/v1/estimators").json()["data"] if s["name"] == "tracked"
    )
    clock = next(c for c in tracked["calibrations"] if c["key"] == "gnss_clock_offset")
    assert (
        clock["field"] == "gnss_clock_offset_s" and clock["std_field"] == "gnss_clock_offset_std_s"
    )
    assert clock["limit_config"] == "calibration.clock_offset_converged_ms"
    assert clock["limit_scale"] == pytest.approx(1e-3) and tracked["uncalibrated_flag"] is None
    doc = client.get("/openapi.json").json()["paths"]
    assert (
        "reset"
        in doc["/api/v1/vehicles/{vehicle_id}/calibration/{estimator}"]["delete"]["summary"].lower()
    )


def test_the_newest_stored_calibration_is_what_a_restart_restores(settings: Settings) -> None:
    """:func:`stored_calibrations` reads every vehicle's newest row (values and stds), and
    leaves out rows without a calibration (NaN)."""
    with running_on(settings) as (client, runtime):
        client.put(f"{V}/t1", json={})
        client.put(f"{V}/t2", json={})
        runtime.store.write_estimates([("t1", _learning())])
        runtime.store.write_estimates([("t2", empty_estimates(1))])
        got = stored_calibrations(runtime.store)
    assert set(got) == {("t1", "mdsf")}
    assert got[("t1", "mdsf")]["radius_left_std_m"] == pytest.approx(0.0005 * 0.816)
    assert got[("t1", "mdsf")]["gnss_clock_offset_s"] == pytest.approx(-0.08)


def test_the_calibration_read_is_an_expensive_route_and_the_reset_is_not() -> None:
    """Reading ``since`` over up to a day of rows is held to the heavy routes' limits."""
    limited = [n for n, p in HEAVY_ROUTES.items() if p.match(f"{V}/t1/calibration")]
    assert limited == ["calibration"]
    assert not any(p.match(f"{V}/t1/calibration/mdsf") for p in HEAVY_ROUTES.values())
