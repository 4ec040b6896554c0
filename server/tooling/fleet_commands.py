"""What the simulated-fleet subcommands run: the demo, ``simulate`` and ``record``.

The demo is the server (:mod:`server.app_main`) with simulated tractors publishing to its
embedded router; ``simulate`` publishes simulated vehicles to a router, ``record`` writes them
to a recording file (replaying one and recording live traffic:
:mod:`server.tooling.recording_commands`).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from estimator.sim import SCENARIOS
from estimator.sim import simulate as run_scenario
from server.app_main import ServerThread, build_app
from server.ingest.zenoh_session import make_config
from server.protocol.keys import sensor_key
from server.protocol.recording import Record, write_recording
from server.settings import Settings, ZenohSettings
from server.tooling.fleet_sim import (
    VEHICLE_ID_FORMAT,
    EstimatorMix,
    FleetSim,
    RunPlan,
    encode_packets,
    packetize,
)
from server.tooling.steered_fleet import SteeredFleetSim
from server.tooling.tracked_fleet import TrackedFleetSim

__all__ = [
    "DEMO_MIX_ESTIMATORS",
    "DEMO_PLANS",
    "demo",
    "demo_plans",
    "mix_summary",
    "record",
    "simulate",
    "vehicle_session",
]

log = logging.getLogger("slipfleet")

#: What the demo's last vehicle runs unless told otherwise: MDSF and the GNSS-free speed beside it.
DEMO_MIX_ESTIMATORS = ("mdsf", "reference_speed")

#: The demo's fleet (``--scenario mix``, the default): each tractor its own work, pace and soil,
#: loops of different lengths (300, 420, 180, 64 s), so stops, wet patches and GNSS outages fall
#: at different times and the vehicles drift further out of step with every loop.
DEMO_PLANS: tuple[RunPlan, ...] = (
    RunPlan("field_work"),
    RunPlan(
        "field_work",
        {
            "work_speed_mps": 3.2,
            "pass_length_m": 130.0,
            "drawbar": 0.12,
            "stop_every_passes": 2,
            "duration_s": 420.0,
            "heading0_deg": 40.0,
            "wet_every_m": 110.0,
            "mu_wet": 0.36,
        },
    ),
    RunPlan(
        "gnss_outage",
        {"duration_s": 180.0, "outage_s": 25.0, "speed_mps": 2.6, "turn_rate_radps": 0.08},
    ),
    RunPlan("slope_wet_patch", {"slope_deg": 10.0, "mu_wet": 0.33}),
)
#: Vehicles beyond this many share the runs of the first ones (each run costs ≈ 0.4 s to simulate).
DEMO_MAX_RUNS = 8


def demo_plans(vehicles: int, scenario: str) -> list[RunPlan]:
    """The distinct runs of a demo of ``vehicles``: :data:`DEMO_PLANS` in turn for ``"mix"``
    (each vehicle its own seed up to :data:`DEMO_MAX_RUNS`), else ``scenario`` for every one."""
    n = min(vehicles, DEMO_MAX_RUNS)
    if scenario != "mix":
        return [RunPlan(scenario)] * n
    return [DEMO_PLANS[k % len(DEMO_PLANS)] for k in range(n)]


def vehicle_session(endpoints: list[str]) -> zenoh.Session:
    """A client session for a (simulated) vehicle connecting to ``endpoints``; SystemExit with
    one line when no router answers there."""
    try:
        return zenoh.open(make_config(ZenohSettings(connect=endpoints)))
    except zenoh.ZError as exc:
        raise SystemExit(f"no Zenoh router answers at {', '.join(endpoints)}") from exc


def demo(
    settings: Settings,
    *,
    vehicles: int = 4,
    scenario: str = "mix",
    duration_s: float = 0.0,
    estimator_mix: EstimatorMix | None = None,
    stop: threading.Event | None = None,
) -> None:
    """Embedded router + server + SQLite + ``vehicles`` simulated tractors, one steered
    four-wheel vehicle after them (friction μ, :mod:`server.tooling.steered_fleet`) and one
    crawler after that (tracked, :mod:`server.tooling.tracked_fleet`), until Ctrl-C, until
    ``duration_s`` (> 0) has passed or until ``stop`` is set, whichever comes first.

    ``estimator_mix`` defaults to the last vehicle running :data:`DEMO_MIX_ESTIMATORS` (a mixed
    fleet: one vehicle's reference speed beside its MDSF estimate)."""
    mix = estimator_mix or EstimatorMix(vehicles, DEMO_MIX_ESTIMATORS)
    _prepare_demo_settings(settings)
    server = ServerThread(build_app(settings), settings.api.host, settings.api.port)
    server.start()
    listen = settings.zenoh.connect or settings.zenoh.listen
    session = vehicle_session(list(listen))
    fleet = _DemoFleet.start(session, settings.zenoh.key_prefix, vehicles, scenario, mix)
    _print_demo_banner(settings, server.port, list(listen), vehicles, scenario, fleet)
    try:
        _wait_for_demo(server, duration_s, stop or threading.Event())
    except KeyboardInterrupt:
        pass
    finally:
        fleet.stop()
        session.close()
        server.stop()


def _prepare_demo_settings(settings: Settings) -> None:
    """Set the demo's settings (no access tokens, no vehicle credentials); SystemExit unless
    the API binds loopback."""
    settings.api.require_auth = False
    # one simulator session publishes for every vehicle: it cannot log in as each of them
    settings.zenoh.credentials_file = None
    if settings.storage.url is not None:
        log.info("demo uses the configured PostgreSQL store")
    if settings.api.host not in ("127.0.0.1", "localhost", "::1"):
        raise SystemExit("the demo runs without access tokens and binds loopback only")


@dataclass(frozen=True, slots=True)
class _DemoFleet:
    """The demo's simulated vehicles: the tractors, one steered vehicle and one crawler."""

    sim: FleetSim
    steered: SteeredFleetSim
    crawler: TrackedFleetSim

    @classmethod
    def start(
        cls,
        session: zenoh.Session,
        prefix: str,
        vehicles: int,
        scenario: str,
        mix: EstimatorMix,
    ) -> _DemoFleet:
        """Start the tractors, then the steered vehicle and the crawler numbered after them."""
        sim = FleetSim(
            session,
            vehicles,
            prefix=prefix,
            loop=True,
            estimator_mix=mix,
            plans=demo_plans(vehicles, scenario),
        )
        sim.start()
        # one steered four-wheel vehicle beside the tractors (friction μ); it joins once simulated
        steered = SteeredFleetSim(session, 1, first_index=vehicles + 1, prefix=prefix, loop=True)
        steered.start()
        crawler = TrackedFleetSim(session, 1, first_index=vehicles + 2, prefix=prefix, loop=True)
        crawler.start()
        return cls(sim, steered, crawler)

    def stop(self) -> None:
        """Stop them in the reverse order."""
        self.crawler.stop()
        self.steered.stop()
        self.sim.stop()


def _print_demo_banner(
    settings: Settings,
    port: int,
    listen: list[str],
    vehicles: int,
    scenario: str,
    fleet: _DemoFleet,
) -> None:
    """Print where the demo's dashboard, API, 3D view and router are, and what it simulates."""
    steered_id, crawler_id = fleet.steered.vehicle_ids[0], fleet.crawler.vehicle_ids[0]
    base = f"http://{settings.api.host}:{port}"
    drives = "each its own drive" if scenario == "mix" else f"scenario {scenario}"
    print(
        "\nSlipfleet demo — no access tokens, no vehicle credentials, loopback only\n"
        f"  dashboard  {base}/\n"
        f"  API docs   {base}/docs\n"
        f"  vehicles   {base}/api/v1/vehicles\n"
        f"  3D view    http://{settings.viewer.host}:{settings.viewer.port}/\n"
        f"  zenoh      {', '.join(listen)}  ({vehicles} simulated vehicles, {drives})\n"
        f"  estimators {mix_summary(fleet.sim)}\n"
        f"  steered    {steered_id}: a steered four-wheel vehicle, friction μ "
        "(joins once its drive is simulated)\n"
        f"  crawler    {crawler_id}: a crawler, motion state, track slip and dead "
        "reckoning (joins once its route is simulated)\n"
        "Ctrl-C stops.\n",
        flush=True,
    )


def _wait_for_demo(server: ServerThread, duration_s: float, stop: threading.Event) -> None:
    """Wait ``duration_s`` (> 0), else until the server thread ends; either cut short by
    ``stop``."""
    if duration_s > 0:
        stop.wait(duration_s)
    else:
        while server.thread.is_alive() and not stop.wait(0.5):
            pass


def mix_summary(sim: FleetSim) -> str:
    """Which vehicles run which estimators, e.g. ``"sim-0004: mdsf + reference_speed; the
    others: their kind's defaults"`` (the first three named, then ``...``)."""
    ids = sim.vehicle_ids
    named = [(vid, names) for i, vid in enumerate(ids) if (names := sim.estimators_of(i))]
    if not named:
        return "every vehicle: its kind's defaults"
    shown = "; ".join(f"{vid}: {' + '.join(names)}" for vid, names in named[:3])
    if len(named) > 3:
        shown += f"; ... ({len(named)} vehicles)"
    return shown if len(named) == len(ids) else f"{shown}; the others: their kind's defaults"


def simulate(
    settings: Settings,
    *,
    vehicles: int,
    scenario: str,
    duration_s: float,
    rate_scale: float = 1.0,
    estimator_mix: EstimatorMix | None = None,
) -> None:
    """Publish simulated vehicles to the configured router(s) for ``duration_s`` seconds."""
    endpoints = list(settings.zenoh.connect or settings.zenoh.listen)
    with vehicle_session(endpoints) as session:
        sim = FleetSim(
            session,
            vehicles,
            scenario=scenario,
            prefix=settings.zenoh.key_prefix,
            rate=rate_scale,
            loop=True,
            estimator_mix=estimator_mix,
        )
        stats = sim.run(duration_s)
    print(
        f"published {stats.total_packets} packets from {vehicles} vehicles in {stats.wall_s:.1f} s"
    )


def record(path: Path, *, vehicles: int, scenario: str, duration_s: float) -> None:
    """Simulate ``vehicles`` and write their packets to a recording file (no network)."""

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
