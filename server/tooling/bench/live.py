"""Sensor → page latency of the live views, and a synthetic fleet that feeds them.

Run ``python -m server.tooling.bench.live [--real] [--vehicles 100] [--rate-hz 20] [--seconds 15]
[--watch 10] [--browser /usr/bin/chromium]``.

With ``--real`` the whole server runs instead (embedded Zenoh router, pipeline with the MDSF
estimators, SQLite writer, API and dashboard) and ``--vehicles`` simulated vehicles
(:class:`server.tooling.fleet_sim.FleetSim`, ``field_work``) publish over Zenoh on loopback in real
time; the latency then includes ingest, the reorder window (``ingest.lateness_ms``) and estimation.

A :class:`SyntheticFleet` produces estimate rows (``ESTIMATE_DTYPE``) for ``--vehicles`` vehicles
at ``--rate-hz`` stamped with the wall clock, and :class:`FeedThread` pushes them into a
:class:`~server.live.hub.LiveHub` (and any other sink) in real time, as the pipeline thread would.
The app (live routes + dashboard) runs under uvicorn on 127.0.0.1; ``--watch`` WebSocket clients
follow one vehicle each on ``/api/v1/live/vehicles/{id}`` and one client follows
``/api/v1/live/fleet``. Each records, per message, *receive wall time − sensor stamp* of the
newest row in it. Sensor and server share the clock here, so with the synthetic feed this is the
latency the live path adds (hub, WebSocket cadence, JSON, network stack).

With ``--browser`` a headless Chromium also opens the dashboard: one vehicle page, whose script
records *receive time − stamp* of every update that brings a new estimate of a live vehicle
(``window.slipfleetStats.latencyMs``, the value on the page; the heartbeat that repeats the
last estimate and a stale vehicle's data are not latency and are left out), and the fleet
overview, which records the cost of applying each fleet message
(sort + render of the virtualised table, ``window.slipfleetStats.fleetUpdateMs``).

The synthetic fleet: each vehicle drives a figure of eight (20–60 m lobes, 1.5–4 m/s) with slip
that wanders between about 0 and 12 % and, for 7 s out of every 40 s, a burst above 18 % on the
left wheel (long enough for a slip alert); one vehicle in ten loses GNSS for 5 s every minute
(``EstimateFlag.DEGRADED``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import statistics
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import EstimateBatch, EstimateFlag, empty_estimates
from server.tooling.bench import percentile
from server.tooling.ports import free_port as _free_port

__all__ = ["FeedThread", "SyntheticFleet", "main"]

_TRACK_WIDTH_M = 1.8
_OK_FLAGS = int(EstimateFlag.GNSS_OK | EstimateFlag.SLIP_LEFT_VALID | EstimateFlag.SLIP_RIGHT_VALID)
_DEGRADED_FLAGS = int(
    EstimateFlag.DEGRADED | EstimateFlag.SLIP_LEFT_VALID | EstimateFlag.SLIP_RIGHT_VALID
)


class Sink(Protocol):
    def on_estimates(self, batch: EstimateBatch) -> None: ...


class SyntheticFleet:
    """Deterministic estimate rows of ``n`` vehicles as a function of time.

    Parameters
    ----------
    n : int
        Vehicles, named ``veh-000`` … .
    seed : int
        Picks each vehicle's lobe size, speed, phase and slip pattern.
    """

    def __init__(self, n: int, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.ids = [f"veh-{i:03d}" for i in range(n)]
        self.lobe_m = rng.uniform(20.0, 60.0, n)
        self.speed_mps = rng.uniform(1.5, 4.0, n)
        self.phase = rng.uniform(0.0, 2 * math.pi, n)
        self.slip_freq = rng.uniform(0.02, 0.08, n)  # Hz
        self.burst_offset_s = rng.uniform(0.0, 40.0, n)
        self.degrades = (np.arange(n) % 10) == 3

    def rows_at(self, stamp_ns: int) -> list[tuple[str, np.ndarray]]:
        """One row per vehicle at ``stamp_ns`` (vectorised over the fleet)."""
        n = len(self.ids)
        t = stamp_ns / 1e9
        # figure of eight (lemniscate of Gerono), parameter advancing so the speed is ~constant
        a = self.lobe_m
        omega = self.speed_mps / (1.6 * a)
        u = omega * t + self.phase
        east = a * np.sin(u)
        north = a * np.sin(u) * np.cos(u)
        de = a * np.cos(u) * omega
        dn = a * np.cos(2 * u) * omega
        d2e = -a * np.sin(u) * omega**2
        d2n = -2 * a * np.sin(2 * u) * omega**2
        vg = np.hypot(de, dn)
        heading = np.arctan2(de, dn)  # from north, clockwise
        yaw_rate = -(de * d2n - dn * d2e) / np.maximum(vg**2, 1e-9)  # CCW positive
        vl = vg - yaw_rate * _TRACK_WIDTH_M / 2
        vr = vg + yaw_rate * _TRACK_WIDTH_M / 2
        base = 6.0 + 6.0 * np.sin(2 * math.pi * self.slip_freq * t + self.phase)
        burst = ((t + self.burst_offset_s) % 40.0) < 7.0
        sl = base + np.where(burst, 18.0, 0.0)
        sr = 0.8 * base + 1.0 * np.sin(0.5 * t + self.phase)
        degraded = self.degrades & ((t % 60.0) < 5.0)
        r = empty_estimates(n)
        r["stamp_ns"] = stamp_ns
        r["vg_mps"] = vg
        r["v1_mps"] = vg
        r["v0_mps"] = vg
        r["vl_mps"] = vl
        r["vr_mps"] = vr
        r["rim_left_mps"] = vl / (1 - sl / 100)
        r["rim_right_mps"] = vr / (1 - sr / 100)
        r["omega_left_radps"] = r["rim_left_mps"] / 0.85
        r["omega_right_radps"] = r["rim_right_mps"] / 0.85
        r["slip_left_pct"] = sl
        r["slip_right_pct"] = sr
        r["yaw_rate_radps"] = yaw_rate
        r["east_m"] = east
        r["north_m"] = north
        r["up_m"] = 0.5 * np.sin(east / 15.0)
        r["heading_rad"] = heading
        r["pitch_rad"] = 0.04 * np.cos(east / 15.0)
        r["roll_rad"] = 0.03 * np.sin(u * 2)
        r["flags"] = np.where(degraded, _DEGRADED_FLAGS, _OK_FLAGS)
        return [(vid, r[i : i + 1]) for i, vid in enumerate(self.ids)]


class FeedThread:
    """Push :class:`SyntheticFleet` rows stamped with the wall clock into sinks at ``rate_hz``."""

    def __init__(
        self,
        fleet: SyntheticFleet,
        sinks: Sequence[Sink],
        rate_hz: float = 20.0,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.fleet = fleet
        self.sinks = list(sinks)
        self.period_s = 1.0 / rate_hz
        self._clock_ns = clock_ns
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="synthetic-feed", daemon=True)
        self.batches = 0

    def backfill(self, seconds: float, rate_hz: float = 5.0) -> None:
        """Push ``seconds`` of history before now (so windows and maps start filled)."""
        now = self._clock_ns()
        step = round(1e9 / rate_hz)
        for t in range(now - round(seconds * 1e9), now, step):
            batch = self._batch_at(t)
            for s in self.sinks:
                s.on_estimates(batch)

    def _batch_at(self, stamp_ns: int) -> EstimateBatch:
        """The fleet's rows at ``stamp_ns`` as the pipeline hands them to sinks: one MDSF batch."""
        return EstimateBatch.of(self.fleet.rows_at(stamp_ns), MDSF_SPEC)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            batch = self._batch_at(self._clock_ns())
            for s in self.sinks:
                s.on_estimates(batch)
            self.batches += 1
            next_t += self.period_s
            self._stop.wait(max(0.0, next_t - time.monotonic()))


#: Headless Chromium flags for this machine's closed network (no background fetches, no GPU,
#: root without a sandbox); the browser tests use the same.
CHROMIUM_ARGS: tuple[str, ...] = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


async def _watch(
    url: str, seconds: float, out: list[float], key: str, hub_out: list[float] | None = None
) -> None:
    import websockets

    deadline = time.monotonic() + seconds
    async with websockets.connect(url, max_size=2**24) as ws:
        while time.monotonic() < deadline:
            try:
                text = await asyncio.wait_for(ws.recv(), timeout=deadline - time.monotonic())
            except TimeoutError:
                break
            recv_ns = time.time_ns()
            msg: dict[str, Any] = json.loads(text)
            if key == "vehicle" and msg.get("latest"):
                stamp = int(msg["latest"]["stamp_ns"])
                out.append((recv_ns - stamp) / 1e6)
                if hub_out is not None:
                    hub_out.append((int(msg["latest"]["arrival_ns"]) - stamp) / 1e6)
            elif key == "fleet" and msg.get("stamp_ns"):
                out.append((recv_ns - max(int(s) for s in msg["stamp_ns"])) / 1e6)


def _synthetic_setup(n: int, rate_hz: float) -> tuple[int, list[str], Any, Callable[[], None]]:
    """Live routes + dashboard over a hub fed by :class:`FeedThread`: ``(port, ids, hub, stop)``."""
    import uvicorn
    from fastapi import FastAPI

    from server.api.routes import live as live_routes
    from server.live.hub import LiveHub
    from server.web import mount_web

    hub = LiveHub()
    app = FastAPI()
    app.state.live_hub = hub
    app.include_router(live_routes.router, prefix="/api/v1")
    mount_web(app)
    port = _free_port()
    server = uvicorn.Server(
        uvicorn.Config(
            app, host="127.0.0.1", port=port, log_level="warning", ws="websockets-sansio"
        )
    )
    srv_thread = threading.Thread(target=server.run, daemon=True)
    srv_thread.start()
    while not server.started:
        time.sleep(0.05)
    fleet = SyntheticFleet(n, seed=1)
    feed = FeedThread(fleet, [hub], rate_hz=rate_hz)
    feed.backfill(30.0)
    feed.start()

    def stop() -> None:
        feed.stop()
        server.should_exit = True
        srv_thread.join(timeout=10)

    return port, fleet.ids, hub, stop


def _real_setup(n: int, data_dir: str) -> tuple[int, list[str], Any, Callable[[], None]]:
    """The whole server (Zenoh router, pipeline, MDSF, SQLite, API, dashboard) with ``n``
    simulated vehicles publishing in real time over Zenoh on loopback."""
    from server.app_main import ServerThread, build_app
    from server.settings import Settings
    from server.tooling.fleet_commands import vehicle_session
    from server.tooling.fleet_sim import FleetSim

    settings = Settings.model_validate(
        {
            "zenoh": {"listen": [f"tcp/127.0.0.1:{_free_port()}"]},
            "storage": {"data_dir": data_dir},
            "api": {"port": 0, "require_auth": False},
            "viewer": {"enabled": False},
        }
    )
    app = build_app(settings)
    server = ServerThread(app, "127.0.0.1", 0)
    server.start()
    session = vehicle_session(list(settings.zenoh.listen))
    sim = FleetSim(session, n, scenario="field_work", prefix=settings.zenoh.key_prefix, loop=True)
    sim.start()
    hub = app.state.runtime.live_hub
    deadline = time.monotonic() + 120
    while len(hub.vehicle_ids()) < n and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(3.0)  # past start-up

    def stop() -> None:
        sim.stop()
        session.close()
        server.stop()

    return server.port, sim.vehicle_ids, hub, stop


def _parser() -> argparse.ArgumentParser:
    """The command line: fleet size, feed rate, duration, clients, browser, ``--real``."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--vehicles", type=int, default=100)
    p.add_argument("--rate-hz", type=float, default=20.0, help="synthetic feed rate")
    p.add_argument("--seconds", type=float, default=15.0)
    p.add_argument("--watch", type=int, default=10, help="vehicle WebSocket clients")
    p.add_argument("--browser", default=None, help="Chromium executable: also measure in a page")
    p.add_argument(
        "--real",
        action="store_true",
        help="the whole server fed by simulated vehicles over Zenoh instead of the synthetic feed",
    )
    return p


def _setup(args: argparse.Namespace, data_dir: str) -> tuple[int, list[str], Any, Any, str]:
    """The server the clients watch, whole or synthetic: ``(port, ids, hub, stop, source)``."""
    if args.real:
        port, ids, hub, stop = _real_setup(args.vehicles, data_dir)
        source = f"{args.vehicles} simulated vehicles over Zenoh, whole server"
    else:
        port, ids, hub, stop = _synthetic_setup(args.vehicles, args.rate_hz)
        source = f"{args.vehicles} synthetic vehicles at {args.rate_hz:g} Hz into the hub"
    return port, ids, hub, stop, source


def _watch_all(args: argparse.Namespace, port: int, ids: list[str]) -> dict[str, list[float]]:
    """Follow the vehicle and fleet streams (and the pages with ``--browser``) for
    ``--seconds``; the latencies in ms per stream (``vehicle``, ``hub``, ``fleet``, ``page``,
    ``render``)."""
    ms: dict[str, list[float]] = {k: [] for k in ("vehicle", "hub", "fleet", "page", "render")}

    async def run() -> None:
        base = f"ws://127.0.0.1:{port}/api/v1/live"
        tasks = [
            _watch(
                f"{base}/vehicles/{vid}?window_s=60",
                args.seconds,
                ms["vehicle"],
                "vehicle",
                ms["hub"],  # stamp -> row reaches the hub (the pipeline's share)
            )
            for vid in ids[: args.watch]
        ]
        tasks.append(_watch(f"{base}/fleet", args.seconds, ms["fleet"], "fleet"))
        await asyncio.gather(*tasks)

    browser_thread = None
    if args.browser:
        url = f"http://127.0.0.1:{port}/"
        browser_thread = threading.Thread(
            target=_browser_measure,
            args=(args.browser, url, ids[0], args.seconds, ms["page"], ms["render"]),
            daemon=True,
        )
        browser_thread.start()
    asyncio.run(run())
    if browser_thread is not None:
        browser_thread.join(timeout=args.seconds + 60)
    return ms


def _print_report(
    args: argparse.Namespace, source: str, hub: Any, ms: dict[str, list[float]]
) -> None:
    """The latency table per stream, and the fleet page's cost with ``--browser``."""
    print(
        f"\nLive latency, sensor stamp -> message received ({source}, {args.seconds:g} s, "
        f"hub rows in: {hub.rows_in})\n"
    )
    print(f"{'stream':<34}{'messages':>9}{'msg/s':>8}{'p50 ms':>9}{'p99 ms':>9}{'max ms':>9}")
    rows: list[tuple[str, list[float], int]] = [
        (f"/live/vehicles/{{id}} x{args.watch}", ms["vehicle"], args.watch),
        ("/live/fleet x1", ms["fleet"], 1),
    ]
    if args.browser:
        rows.append(("vehicle page in Chromium", ms["page"], 1))
    rows.append(("  of which: stamp -> in the hub", ms["hub"], args.watch))
    for name, vals, clients in rows:
        if not vals:
            print(f"{name:<34}{0:>9}")
            continue
        rate = len(vals) / args.seconds / clients
        print(
            f"{name:<34}{len(vals):>9}{rate:>8.1f}{statistics.median(vals):>9.1f}"
            f"{percentile(vals, 99):>9.1f}{max(vals):>9.1f}"
        )
    render_ms = ms["render"]
    if args.browser and render_ms:
        print(
            f"\nfleet page, applying one message for {args.vehicles} vehicles: "
            f"p50 {statistics.median(render_ms):.1f} ms, p99 {percentile(render_ms, 99):.1f} ms "
            f"({len(render_ms)} messages)"
        )


def main(argv: Sequence[str] | None = None) -> None:
    import tempfile

    args = _parser().parse_args(argv)
    tmp = tempfile.TemporaryDirectory(prefix="slipfleet-bench-")
    port, ids, hub, stop, source = _setup(args, tmp.name)
    try:
        ms = _watch_all(args, port, ids)
    finally:
        stop()
        tmp.cleanup()
    _print_report(args, source, hub, ms)


def _browser_measure(
    executable: str,
    url: str,
    vehicle_id: str,
    seconds: float,
    page_ms: list[float],
    render_ms: list[float],
) -> None:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=executable, args=list(CHROMIUM_ARGS), headless=True
        )
        try:
            ctx = browser.new_context(viewport={"width": 1400, "height": 900})
            vehicle_page = ctx.new_page()
            vehicle_page.goto(f"{url}#/vehicle/{vehicle_id}")
            fleet_page = ctx.new_page()
            fleet_page.goto(f"{url}#/fleet")
            time.sleep(seconds)
            page_ms.extend(vehicle_page.evaluate("() => window.slipfleetStats.latencyMs"))
            render_ms.extend(fleet_page.evaluate("() => window.slipfleetStats.fleetUpdateMs"))
        finally:
            browser.close()


if __name__ == "__main__":
    main()
