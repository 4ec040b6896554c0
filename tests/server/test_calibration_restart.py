"""End to end: a vehicle's online calibration survives a server restart, and so does a reset.

A simulated tractor whose rear wheels roll free (so MDSF learns their rolling radius, 2 % off the
configured one) publishes over a real Zenoh session on loopback to the server (embedded router,
pipeline, MDSF) and its store (SQLite, SQLite with two worker processes, PostgreSQL). The server
is stopped and started again: the next drive's first rows carry the learnt radius with its small
std (restored, not relearnt). An operator's reset over REST makes MDSF forget it: the drives after
it have driven wheels (a new config, which keeps the calibration it finds), so the radius stays at
its prior; after another restart the vehicle goes on from that prior, not from the old radius.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from estimator.config import VehicleGeometry, WheeledRearDriveConfig
from server.app_main import ServerThread, build_app
from server.settings import Settings
from tests.server.fleet_stack import (
    BACKENDS,
    backend_of,
    calibration_resets,
    publish_drive,
    stack_settings,
    stored_columns,
)
from tests.support import poll_until

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

VID = "sim-0001"
RADIUS_M = WheeledRearDriveConfig().geometry.wheel_radius_left_m
FREE = WheeledRearDriveConfig(
    geometry=VehicleGeometry(wheel_driven_left=False, wheel_driven_right=False)
)
S = 1_000_000_000
FIELDS = "radius_left_m,radius_left_std_m,flags"


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> Iterator[tuple[str | None, int]]:
    yield from backend_of(request)


def _serve(settings: Settings) -> ServerThread:
    server = ServerThread(build_app(settings), "127.0.0.1", 0)
    server.start()
    return server


def _drive(
    settings: Settings, start_ns: int, duration_s: float, seed: int, *, free: bool = True
) -> int:
    """Publish one drive of ``duration_s`` from ``start_ns`` (rear wheels rolling free, else
    driven); its end [ns]."""
    publish_drive(
        settings,
        start_ns,
        duration_s,
        seed,
        config=FREE if free else WheeledRearDriveConfig(),
        free_rolling=(free, free),
        wheel_radius_error_rel=(0.02, 0.02),
    )
    return start_ns + int(duration_s * S)


def _radius(client: httpx.Client) -> dict:
    r = client.get(f"/api/v1/vehicles/{VID}/calibration", params={"estimator": "mdsf"})
    r.raise_for_status()
    return next(c for c in r.json()["estimators"][0]["calibrations"] if c["key"] == "radius_left")


def test_calibration_restored_after_a_restart_and_a_reset_kept(
    tmp_path: Path, backend: tuple[str | None, int]
) -> None:
    settings = stack_settings(tmp_path, *backend)
    url = lambda server: f"http://127.0.0.1:{server.port}"  # noqa: E731
    t0 = time.time_ns()

    server = _serve(settings)
    try:
        end_a = _drive(settings, t0, 50.0, seed=3)
        with httpx.Client(base_url=url(server), timeout=30) as client:
            rows_a = stored_columns(client, VID, t0, end_a, FIELDS)
            learnt = _radius(client)
    finally:
        server.stop()
    # learnt while streaming: converged near the true radius
    assert learnt["converged"], learnt
    assert abs(learnt["value"] / (RADIUS_M * 1.02) - 1) < 0.004, learnt
    std_a = rows_a["radius_left_std_m"][-1]
    prior_std = 0.03 * RADIUS_M  # CalibrationConfig.radius_prior_pct
    assert std_a < prior_std / 10

    server = _serve(settings)
    try:
        with httpx.Client(base_url=url(server), timeout=30) as client:
            start_b = end_a + S
            end_b = _drive(settings, start_b, 20.0, seed=5)
            rows_b = stored_columns(client, VID, start_b, end_b, FIELDS)
            # restored, not relearnt: the first row after the restart holds the learnt radius
            assert rows_b["radius_left_std_m"][0] < 1.5 * std_a, rows_b["radius_left_std_m"][:3]
            assert abs(rows_b["radius_left_m"][0] - learnt["value"]) < 3 * std_a

            assert client.delete(f"/api/v1/vehicles/{VID}/calibration/mdsf").status_code == 202
            start_c = end_b + S
            end_c = _drive(settings, start_c, 20.0, seed=7, free=False)
            rows_c = stored_columns(client, VID, start_c, end_c, FIELDS)
            # forgotten: back at the prior (driven wheels do not teach it), and counted
            assert rows_c["radius_left_std_m"][0] > 0.9 * prior_std, rows_c["radius_left_std_m"][0]
            assert rows_c["radius_left_m"][0] == pytest.approx(RADIUS_M)
            std_c = rows_c["radius_left_std_m"][-1]
            assert not _radius(client)["converged"]
            poll_until(lambda: calibration_resets(client, VID) >= 1, "counted reset", timeout_s=10)
    finally:
        server.stop()

    server = _serve(settings)
    try:
        with httpx.Client(base_url=url(server), timeout=30) as client:
            start_d = end_c + S
            end_d = _drive(settings, start_d, 20.0, seed=9, free=False)
            rows_d = stored_columns(client, VID, start_d, end_d, FIELDS)
    finally:
        server.stop()
    # the reset survived the restart: the vehicle goes on from the prior, not the old radius
    first_d = rows_d["radius_left_std_m"][0]
    assert first_d > 0.9 * prior_std and abs(first_d / std_c - 1) < 0.01, (first_d, std_c)
    assert rows_d["radius_left_m"][0] == pytest.approx(RADIUS_M)
