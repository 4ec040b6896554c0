"""The fleet report's size and time budgets on a real ``slipfleet serve`` over a real SQLite
store of thousands of vehicles: with the defaults it answers whole within its stated time
budget; over ``api.report_max_vehicles`` it answers 413 at once; past
``api.report_time_budget_s`` it stops and answers 413 soon after, each with one line naming
the setting."""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import pytest

from server.settings import ApiSettings, StorageSettings
from server.storage import open_store
from server.storage.sqlite import SqliteStore
from tests.server.api._data import T0, ramp_series
from tests.server.faults._harness import ServerProcess

VEHICLES = 2_000
ROWS = 300  # 30 s at 10 Hz each
REPORT = f"/api/v1/fleet/report?start={T0}&end={T0 + 3_600_000_000_000}"
#: What a refusal may take beyond its budget: one vehicle's report and the answer.
SLACK_S = 2.0


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


def _timed_report(tmp_path: Path, env: dict[str, str], name: str) -> tuple[httpx.Response, float]:
    server = ServerProcess(tmp_path, extra_env=env, name=name)
    server.start()
    try:
        server.wait_ready(120)
        with server.client() as c:
            t0 = time.perf_counter()
            got = c.get(REPORT, timeout=600)
            return got, time.perf_counter() - t0
    finally:
        server.stop()


@pytest.mark.zenoh
def test_fleet_report_over_thousands_of_vehicles_keeps_its_budgets(tmp_path: Path) -> None:
    _seed(tmp_path / "data")
    default_budget_s = ApiSettings().report_time_budget_s

    whole, whole_s = _timed_report(tmp_path, {}, "defaults")
    assert whole.status_code == 200, whole.text[:300]
    assert len(whole.json()["vehicles"]) == VEHICLES
    assert whole_s < default_budget_s

    env = {"SLIPFLEET_API__REPORT_MAX_VEHICLES": str(VEHICLES - 1)}
    too_many, too_many_s = _timed_report(tmp_path, env, "max-vehicles")
    assert too_many.status_code == 413 and too_many.json()["error"] == "payload_too_large"
    assert too_many_s < SLACK_S
    message = too_many.json()["reason"]
    assert "api.report_max_vehicles" in message and f"{VEHICLES} vehicles" in message

    budget_s = 0.3
    env = {"SLIPFLEET_API__REPORT_TIME_BUDGET_S": str(budget_s)}
    too_long, too_long_s = _timed_report(tmp_path, env, "time-budget")
    assert too_long.status_code == 413 and too_long_s < budget_s + SLACK_S
    message = too_long.json()["reason"]
    assert "api.report_time_budget_s" in message and "\n" not in message
    print(
        f"fleet report over {VEHICLES} vehicles: whole in {whole_s:.2f} s (budget "
        f"{default_budget_s:g} s, {len(whole.content) / 1e6:.1f} MB); over the vehicle cap "
        f"413 in {too_many_s:.3f} s; {budget_s} s budget: 413 in {too_long_s:.2f} s "
        f"({message})"
    )
