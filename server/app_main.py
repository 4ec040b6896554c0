"""What the CLI subcommands run: the full app, the demo, the simulator, replay and record.

Kept apart from :mod:`server.cli` so the argument parser imports nothing heavy.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import uvicorn
import zenoh
from fastapi import FastAPI

from server.api.app import create_app
from server.gc_policy import settle
from server.ingest.zenoh_session import make_config
from server.settings import Settings, ZenohSettings
from server.web import mount_web

__all__ = ["build_app", "demo", "record", "replay", "serve", "simulate"]

log = logging.getLogger("slipfleet")


def build_app(settings: Settings) -> FastAPI:
    """The whole server app: REST API, live feeds, dashboard at ``/``; runtime in the lifespan."""
    app = create_app(settings)
    mount_web(app)
    return app


def serve(settings: Settings, *, log_level: str = "info") -> None:
    """Run the server until interrupted (this process's collector settled first: see
    :mod:`server.gc_policy`)."""
    app = build_app(settings)
    settle(settings.ingest.gc_gen0)
    uvicorn.run(
        app,
        host=settings.api.host,
        port=settings.api.port,
        log_level=log_level,
        ws="websockets-sansio",
    )


def vehicle_session(endpoints: list[str]) -> zenoh.Session:
    """A client session for a (simulated) vehicle connecting to ``endpoints``."""
    return zenoh.open(make_config(ZenohSettings(connect=endpoints)))


class ServerThread:
    """uvicorn on a background thread; ``start`` returns once the app is up (lifespan done)."""

    def __init__(self, app: FastAPI, host: str, port: int) -> None:
        config = uvicorn.Config(
            app, host=host, port=port, log_level="warning", ws="websockets-sansio"
        )
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)

    def start(self, timeout_s: float = 30.0) -> None:
        self.thread.start()
        deadline = time.monotonic() + timeout_s
        while not self.server.started:
            if not self.thread.is_alive():
                raise RuntimeError("server failed to start (see the log above)")
            if time.monotonic() > deadline:
                raise TimeoutError("server did not start in time")
            time.sleep(0.05)

    @property
    def port(self) -> int:
        sockets = self.server.servers[0].sockets if self.server.servers else []
        return int(sockets[0].getsockname()[1]) if sockets else 0

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(30.0)


def demo(
    settings: Settings, *, vehicles: int = 4, scenario: str = "field_work", duration_s: float = 0.0
) -> None:
    """Embedded router + server + SQLite + ``vehicles`` simulated tractors, until Ctrl-C."""
    from server.fleet_sim import FleetSim

    settings.api.require_auth = False
    # one simulator session publishes for every vehicle: it cannot log in as each of them
    settings.zenoh.credentials_file = None
    if settings.storage.url is not None:
        log.info("demo uses the configured PostgreSQL store")
    if settings.api.host not in ("127.0.0.1", "localhost", "::1"):
        raise SystemExit("the demo runs without access tokens and binds loopback only")
    server = ServerThread(build_app(settings), settings.api.host, settings.api.port)
    server.start()
    listen = settings.zenoh.connect or settings.zenoh.listen
    session = vehicle_session(list(listen))
    sim = FleetSim(
        session, vehicles, scenario=scenario, prefix=settings.zenoh.key_prefix, loop=True
    )
    sim.start()
    base = f"http://{settings.api.host}:{server.port}"
    print(
        "\nSlipfleet demo — no access tokens, no vehicle credentials, loopback only\n"
        f"  dashboard  {base}/\n"
        f"  API docs   {base}/docs\n"
        f"  vehicles   {base}/api/v1/vehicles\n"
        f"  3D view    http://{settings.viewer.host}:{settings.viewer.port}/\n"
        f"  zenoh      {', '.join(listen)}  ({vehicles} simulated vehicles, scenario {scenario})\n"
        "Ctrl-C stops.\n",
        flush=True,
    )
    try:
        if duration_s > 0:
            time.sleep(duration_s)
        else:
            while server.thread.is_alive():
                time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
        session.close()
        server.stop()


def simulate(
    settings: Settings, *, vehicles: int, scenario: str, duration_s: float, rate_scale: float = 1.0
) -> None:
    """Publish simulated vehicles to the configured router(s) for ``duration_s`` seconds."""
    from server.fleet_sim import FleetSim

    endpoints = list(settings.zenoh.connect or settings.zenoh.listen)
    with vehicle_session(endpoints) as session:
        sim = FleetSim(
            session,
            vehicles,
            scenario=scenario,
            prefix=settings.zenoh.key_prefix,
            rate=rate_scale,
            loop=True,
        )
        stats = sim.run(duration_s)
    print(
        f"published {stats.total_packets} packets from {vehicles} vehicles in {stats.wall_s:.1f} s"
    )


def replay(settings: Settings, path: Path, *, rate_scale: float = 1.0) -> None:
    """Publish a recording file to the configured router(s)."""
    from server import fleet_sim

    endpoints = list(settings.zenoh.connect or settings.zenoh.listen)
    with vehicle_session(endpoints) as session:
        stats = fleet_sim.replay(path, session, rate=rate_scale)
    print(f"replayed {stats.total_packets} packets in {stats.wall_s:.1f} s")


def record(path: Path, *, vehicles: int, scenario: str, duration_s: float) -> None:
    """Simulate ``vehicles`` and write their packets to a recording file (no network)."""
    from estimator.sim import SCENARIOS
    from estimator.sim import simulate as run_scenario
    from server.fleet_sim import VEHICLE_ID_FORMAT, encode_packets, packetize
    from server.protocol.keys import sensor_key
    from server.protocol.recording import Record, write_recording

    overrides: dict[str, Any] = (
        {"duration_s": duration_s} if "duration_s" in SCENARIOS[scenario].defaults else {}
    )
    start_ns = time.time_ns()
    records: list[Record] = []
    for i in range(vehicles):
        vehicle_id = VEHICLE_ID_FORMAT.format(i + 1)
        run = run_scenario(scenario, seed=i, start_ns=start_ns, **overrides)
        packets = packetize(run.sent_in_arrival_order(), run.start_ns)
        for pkt, (_, payload) in zip(packets, encode_packets(packets), strict=True):
            key = sensor_key("fleet", vehicle_id, pkt.stream)
            records.append(Record(key, start_ns + pkt.arrival_offset_ns, payload))
    records.sort(key=lambda r: r.stamp_ns)
    n_written = write_recording(path, records)
    print(f"wrote {n_written} records from {vehicles} vehicles to {path}")
