"""The whole server for end-to-end tests: its settings per storage backend, the server with a
simulated fleet streaming into it, and waiting until every packet a simulated fleet published
has been counted."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi import FastAPI

from server.app_main import ServerThread, build_app
from server.settings import Settings
from server.tooling.fleet_commands import vehicle_session
from server.tooling.fleet_sim import FleetSim, SimStats
from tests.support import free_port

__all__ = [
    "BACKENDS",
    "START_TIMEOUT_S",
    "backend_of",
    "calibration_resets",
    "publish_drive",
    "running_server",
    "stack_settings",
    "stored_columns",
    "streaming_fleet",
    "wait_counted",
]

#: Storage backends and ingest layouts the end-to-end tests run on (``backend_of`` reads them).
BACKENDS = [
    "sqlite",
    "sqlite, 2 worker processes",
    pytest.param("postgresql", marks=pytest.mark.postgres),
]


def backend_of(request: pytest.FixtureRequest) -> Iterator[tuple[str | None, int]]:
    """``(storage URL or None for SQLite, ingest.workers)`` of a ``BACKENDS`` parameter."""
    if request.param.startswith("sqlite"):
        yield None, 2 if "worker" in request.param else 0
    else:
        yield request.getfixturevalue("pg_database_url"), 0


def stack_settings(tmp_path: Path, storage_url: str | None, workers: int) -> Settings:
    """A server on loopback: embedded router on a free port, no auth, no 3D view."""
    return Settings(
        zenoh={"listen": [f"tcp/127.0.0.1:{free_port()}"]},
        storage={"url": storage_url, "data_dir": tmp_path / "data", "commit_interval_s": 0.2},
        ingest={"workers": workers},
        api={"port": 0, "require_auth": False},
        viewer={"enabled": False},
    )


#: How long the server may take to start, s: its lifespan opens Zenoh, the store and the
#: estimators, several times slower on a loaded host than on a quiet one.
START_TIMEOUT_S = 120.0


@contextmanager
def running_server(settings: Settings) -> Iterator[tuple[FastAPI, ServerThread]]:
    """The whole server of ``settings`` on loopback, started, until the block ends."""
    app = build_app(settings)
    server = ServerThread(app, "127.0.0.1", 0)
    server.start(timeout_s=START_TIMEOUT_S)
    try:
        yield app, server
    finally:
        server.stop()


@contextmanager
def streaming_fleet(
    settings: Settings, n_vehicles: int, **fleet: Any
) -> Iterator[tuple[FastAPI, ServerThread, FleetSim]]:
    """:func:`running_server` with a :class:`FleetSim` of ``n_vehicles`` (``fleet``: its
    further arguments) publishing into it on a session of its own, until the block ends; the
    fleet stops before the server."""
    with (
        running_server(settings) as (app, server),
        vehicle_session(list(settings.zenoh.listen)) as session,
    ):
        sim = FleetSim(session, n_vehicles, prefix=settings.zenoh.key_prefix, **fleet)
        sim.start()
        try:
            yield app, server, sim
        finally:
            sim.stop()


def wait_counted(
    client: httpx.Client, n_vehicles: int, packets: int, window: dict[str, int]
) -> dict[str, Any]:
    """Each vehicle's report once ``n_vehicles`` are registered and their ``received`` counters
    add up to ``packets`` (the lateness window releases, the writer commits: at most 120 s, for
    a loaded host)."""
    deadline = time.monotonic() + 120
    while True:
        vehicles = client.get("/api/v1/vehicles").json()["data"]
        ids = sorted(v["vehicle_id"] for v in vehicles)
        reports = {
            vid: client.get(f"/api/v1/vehicles/{vid}/report", params=window).json() for vid in ids
        }
        received = sum(rep["ingest"]["received"] for rep in reports.values())
        if received >= packets and len(ids) == n_vehicles:
            return reports
        assert time.monotonic() < deadline, f"only {received}/{packets} packets counted"
        time.sleep(0.5)


def stored_columns(
    client: httpx.Client, vehicle_id: str, start_ns: int, end_ns: int, fields: str
) -> dict[str, np.ndarray]:
    """The vehicle's stored ``fields`` (comma-separated) from ``start_ns`` on, as float columns
    (null → NaN), once a row within 2 s of ``end_ns`` is stored (at most 60 s)."""
    deadline = time.monotonic() + 60
    while True:
        r = client.get(
            f"/api/v1/vehicles/{vehicle_id}/series",
            params={
                "start": start_ns,
                "end": end_ns + 1_000_000_000,
                "fields": fields,
                "format": "json",
            },
        )
        if r.status_code == 200:
            cols = {
                k: np.array([np.nan if x is None else x for x in v], dtype=float)
                for k, v in r.json()["columns"].items()
            }
            if cols["stamp_ns"].size and cols["stamp_ns"][-1] >= end_ns - 2_000_000_000:
                return cols
        assert time.monotonic() < deadline, f"the drive's rows did not arrive: {r.text}"
        time.sleep(0.5)


def calibration_resets(client: httpx.Client, vehicle_id: str) -> float:
    """The vehicle's ``calibration_resets`` counter in ``/metrics`` (0 while it has none)."""
    for line in client.get("/api/v1/metrics").text.splitlines():
        if 'event="calibration_resets"' in line and f'vehicle="{vehicle_id}"' in line:
            return float(line.rsplit(" ", 1)[1])
    return 0.0


def publish_drive(
    settings: Settings, start_ns: int, duration_s: float, seed: int, **fleet: Any
) -> SimStats:
    """Publish one simulated vehicle's ``random_drive`` of ``duration_s`` from sensor time
    ``start_ns``, 4× faster than real time, on a session of its own (a fresh simulator start:
    sequence numbers from 0, a new boot id); ``fleet``: further :class:`FleetSim` arguments.
    Returns the run's statistics."""
    with vehicle_session(list(settings.zenoh.listen)) as session:
        return FleetSim(
            session,
            1,
            scenario="random_drive",
            prefix=settings.zenoh.key_prefix,
            seed=seed,
            rate=4.0,
            clock_ns=lambda: start_ns,
            duration_s=duration_s,
            **fleet,
        ).run()
