"""The fleet report's size and time budgets on a real ``slipfleet serve`` over a real SQLite
store of thousands of vehicles: with the defaults it answers whole, every vehicle with its
rows; over ``api.report_max_vehicles`` it answers 413; past ``api.report_time_budget_s`` it
stops between two vehicles and answers 413, each with one line naming the setting."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import pytest

from server.settings import StorageSettings
from server.storage import open_store
from server.storage.sqlite import SqliteStore
from tests.server.api._data import T0, ramp_series
from tests.server.faults._harness import ServerProcess

VEHICLES = 2_000
ROWS = 30  # 3 s at 10 Hz each
REPORT = f"/api/v1/fleet/report?start={T0}&end={T0 + 3_600_000_000_000}"


def _seed(data_dir: Path) -> None:
    store = open_store(StorageSettings(data_dir=data_dir))
    try:
        rows = ramp_series(ROWS)
        for start in range(0, VEHICLES, 500):
            batch = []
            for i in range(start, min(VEHICLES, start + 500)):
                store.upsert_vehicle(f"v{i:05d}", {}, T0)
                batch.append((f"v{i:05d}", rows))
            store.write_estimates(batch)
        # to the final tables, as a running server's writer does within seconds (staged rows
        # are time-ordered, so a per-vehicle read of them scans every vehicle's)
        assert isinstance(store, SqliteStore)
        while store.maintain(everything=True):
            pass
    finally:
        store.close()


def _report(tmp_path: Path, env: dict[str, str], name: str) -> httpx.Response:
    server = ServerProcess(tmp_path, extra_env=env, name=name)
    server.start()
    try:
        server.wait_ready(120)
        with server.client() as c:
            return c.get(REPORT, timeout=600)
    finally:
        server.stop()


@pytest.mark.zenoh
def test_fleet_report_over_thousands_of_vehicles_keeps_its_budgets(tmp_path: Path) -> None:
    _seed(tmp_path / "data")

    whole = _report(tmp_path, {}, "defaults")
    assert whole.status_code == 200, whole.text[:300]
    reported = {(v["vehicle_id"], v["report"]["rows"]) for v in whole.json()["vehicles"]}
    assert reported == {(f"v{i:05d}", ROWS) for i in range(VEHICLES)}

    env = {"SLIPFLEET_API__REPORT_MAX_VEHICLES": str(VEHICLES - 1)}
    too_many = _report(tmp_path, env, "max-vehicles")
    assert too_many.status_code == 413 and too_many.json()["error"] == "payload_too_large"
    message = too_many.json()["reason"]
    assert "api.report_max_vehicles" in message and f"{VEHICLES} vehicles" in message

    # a budget that no two thousand vehicles' reports fit in: spent between two of them
    env = {"SLIPFLEET_API__REPORT_TIME_BUDGET_S": "0.01"}
    too_long = _report(tmp_path, env, "time-budget")
    assert too_long.status_code == 413 and too_long.json()["error"] == "payload_too_large"
    message = too_long.json()["reason"]
    assert "api.report_time_budget_s" in message and "\n" not in message
    done = re.search(rf"after (\d+) of {VEHICLES} vehicles", message)
    assert done is not None and int(done[1]) < VEHICLES, message
