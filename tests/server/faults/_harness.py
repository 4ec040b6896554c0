"""Real processes for fault tests: the server (``slipfleet serve``), a standalone Zenoh router,
a deterministic vehicle publisher, and the reference estimates the server must store.

The publisher replays simulated runs (fixed start time, fixed seeds) over a Zenoh client
session, like :class:`server.tooling.fleet_sim.FleetSim`, and records when it published what: the
newest sensor stamp per vehicle over wall time, so a test can say which estimates the server
must have produced before a fault. :func:`reference_rows` feeds the same packets, in the same
order, through an in-process :class:`Pipeline` with the real estimators: what a server that
never failed would store.
"""

from __future__ import annotations

import bisect
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import zenoh

from estimator.mdsf import MdsfConfig
from estimator.sim import simulate
from server.estimation import EstimatorRegistry
from server.ingest import Pipeline
from server.protocol import Stream, config_key, decode, encode_config, sensor_key
from server.protocol.codec import Packet
from server.settings import IngestSettings, Settings
from server.tooling.fleet_commands import vehicle_session
from server.tooling.fleet_sim import SimPacket, packetize
from server.tooling.procs import stop_process
from tests.support import free_port

__all__ = [
    "LATENESS_NS",
    "TICK_NS",
    "Publisher",
    "RouterProcess",
    "ServerProcess",
    "reference_rows",
    "series_stamps",
    "wait_until",
]

TICK_NS = MdsfConfig().tick_ns  # MDSF product tick
LATENESS_NS = IngestSettings().lateness_ms * 1_000_000
ADVANCE_STEP_NS = IngestSettings().advance_step_ms * 1_000_000
PREFIX = "fleet"
REPO = Path(__file__).resolve().parents[3]


def wait_until(cond: Any, timeout_s: float, what: str, poll_s: float = 0.1) -> float:
    """Poll ``cond()`` until true; return the seconds waited (AssertionError on timeout)."""
    t0 = time.monotonic()
    while True:
        try:
            if cond():
                return time.monotonic() - t0
        except (httpx.HTTPError, OSError):
            pass
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(poll_s)


# ------------------------------------------------------------------------------ processes


class ServerProcess:
    """``slipfleet serve`` in a subprocess, configured through ``SLIPFLEET_*`` variables."""

    def __init__(
        self,
        tmp_path: Path,
        *,
        zenoh_listen: str | None = None,
        zenoh_connect: str | None = None,
        storage_url: str | None = None,
        commit_interval_s: float = 0.2,
        extra_env: Mapping[str, str] | None = None,
        name: str = "server",
    ) -> None:
        self.api_port = free_port()
        self.zenoh_listen = zenoh_listen or f"tcp/127.0.0.1:{free_port()}"
        self.env = {
            **os.environ,
            "SLIPFLEET_API__PORT": str(self.api_port),
            "SLIPFLEET_API__REQUIRE_AUTH": "false",
            "SLIPFLEET_VIEWER__ENABLED": "false",
            "SLIPFLEET_STORAGE__DATA_DIR": str(tmp_path / "data"),
            "SLIPFLEET_STORAGE__COMMIT_INTERVAL_S": str(commit_interval_s),
            "PYTHONUNBUFFERED": "1",
        }
        if zenoh_connect is not None:
            self.env["SLIPFLEET_ZENOH__CONNECT"] = f'["{zenoh_connect}"]'
        else:
            self.env["SLIPFLEET_ZENOH__LISTEN"] = f'["{self.zenoh_listen}"]'
        if storage_url is not None:
            self.env["SLIPFLEET_STORAGE__URL"] = storage_url
        self.env.pop("SLIPFLEET_CONFIG", None)
        self.env.update(extra_env or {})
        self.log_path = tmp_path / f"{name}.log"
        self.proc: subprocess.Popen[bytes] | None = None
        self.base_url = f"http://127.0.0.1:{self.api_port}"
        self.starts = 0

    def start(self) -> None:
        self.starts += 1
        with open(self.log_path, "ab") as log:
            log.write(f"\n===== start {self.starts} =====\n".encode())
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "server.cli", "serve"],
                cwd=REPO,
                env=self.env,
                stdout=log,
                stderr=subprocess.STDOUT,
            )

    def wait_ready(self, timeout_s: float = 60.0) -> float:
        """Seconds until ``/api/v1/health`` answers 200."""

        def ok() -> bool:
            assert self.proc is not None and self.proc.poll() is None, self.log_tail()
            return httpx.get(f"{self.base_url}/api/v1/health", timeout=2).status_code == 200

        return wait_until(ok, timeout_s, "server health 200")

    def signal(self, sig: signal.Signals) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def wait_exit(self, timeout_s: float = 60.0) -> int:
        assert self.proc is not None
        rc = self.proc.wait(timeout_s)
        self.proc = None
        return rc

    def stop(self) -> None:
        """Leave nothing behind (SIGTERM, then SIGKILL)."""
        if self.proc is None:
            return
        stop_process(self.proc, 30)
        self.proc = None

    def log_tail(self, n: int = 40) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=30)


_ROUTER_MAIN = """
import signal, sys, threading
from server.ingest.zenoh_session import make_config
from server.settings import ZenohSettings
import zenoh
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *a: stop.set())
with zenoh.open(make_config(ZenohSettings(listen=[sys.argv[1]]))):
    print("router up", flush=True)
    stop.wait()
"""


class RouterProcess:
    """A standalone Zenoh router (embedded-router config of the server, no server around it)."""

    def __init__(self, tmp_path: Path) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.log_path = tmp_path / "router.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-c", _ROUTER_MAIN, self.endpoint],
                cwd=REPO,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        wait_until(lambda: "router up" in self.log_path.read_text(), 30, "router start")

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait(10)
        self.proc = None
        # the next start appends; count "router up" lines afresh
        self.log_path.write_text("")

    def stop(self) -> None:
        if self.proc is not None:
            stop_process(self.proc, 10)
            self.proc = None


# ------------------------------------------------------------------------------ vehicles


@dataclass
class _Run:
    vehicle_id: str
    packets: list[SimPacket]
    config_payload: bytes
    phase_ns: int


@dataclass
class Publisher:
    """Publishes simulated vehicles (deterministic), recording the newest stamp over time."""

    endpoint: str
    n_vehicles: int = 2
    scenario: str = "field_work"
    duration_s: float = 60.0
    rate: float = 2.0
    start_ns: int = 0
    id_prefix: str = "flt"
    #: pause publishing for ``stall_s`` of wall time once ``stall_at_s`` of sensor time is out
    #: (a link that stalls: everything after it comes late, nothing is lost)
    stall_at_s: float | None = None
    stall_s: float = 0.0
    #: leave out the wheel packets sent in this span of sensor time, s (lost on the link)
    drop_wheels_s: tuple[float, float] | None = None
    runs: list[_Run] = field(default_factory=list)
    timeline: list[tuple[float, dict[str, int]]] = field(default_factory=list)
    published: dict[str, list[tuple[str, bytes]]] = field(default_factory=dict)
    sent_order: list[tuple[str, bytes]] = field(default_factory=list)
    dropped: list[tuple[str, bytes]] = field(default_factory=list)
    done: threading.Event = field(default_factory=threading.Event)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None
    error: BaseException | None = None

    def __post_init__(self) -> None:
        if not self.start_ns:
            now = time.time_ns()
            self.start_ns = now - now % 100_000_000
        for i in range(self.n_vehicles):
            run = simulate(
                self.scenario, seed=20 + i, start_ns=self.start_ns, duration_s=self.duration_s
            )
            vid = f"{self.id_prefix}-{i + 1}"
            self.runs.append(
                _Run(
                    vid,
                    packetize(run.sent_in_arrival_order(), run.start_ns),
                    encode_config(run.config),
                    (i * 100_000_000) // self.n_vehicles,
                )
            )

    @property
    def vehicle_ids(self) -> list[str]:
        return [r.vehicle_id for r in self.runs]

    def schedule(self) -> list[tuple[int, str, SimPacket]]:
        """Every packet as ``(sensor offset ns, vehicle id, packet)`` in publishing order."""
        out = [
            (p.arrival_offset_ns + r.phase_ns, r.vehicle_id, p)
            for r in self.runs
            for p in r.packets
        ]
        out.sort(key=lambda x: x[0])
        return out

    def encoded(self) -> list[tuple[str, bytes, int]]:
        """``(key, payload, newest stamp)`` of every packet in publishing order (phases applied,
        sequence numbers per stream)."""
        seq: dict[tuple[str, Stream], int] = {}
        out = []
        for _, vid, p in self.schedule():
            phase = next(r.phase_ns for r in self.runs if r.vehicle_id == vid)
            n = seq.get((vid, p.stream), 0)
            seq[(vid, p.stream)] = n + 1
            payload = p.encode(n, phase)
            pk = decode(sensor_key(PREFIX, vid, p.stream), payload, prefix=PREFIX)
            out.append((sensor_key(PREFIX, vid, p.stream), payload, pk.last_stamp_ns))
        return out

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="fault-publisher", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(30)

    def wait_done(self, timeout_s: float) -> None:
        assert self.done.wait(timeout_s), "publisher did not finish"
        assert self.error is None, self.error

    def newest_at(self, t_monotonic: float) -> dict[str, int]:
        """Newest stamp published per vehicle at monotonic time ``t`` (or before)."""
        i = bisect.bisect_right([t for t, _ in self.timeline], t_monotonic)
        return dict(self.timeline[i - 1][1]) if i else {}

    def _run(self) -> None:
        try:
            self._publish()
        except BaseException as exc:  # reported by wait_done
            self.error = exc
        finally:
            self.done.set()

    def _publish(self) -> None:
        packets = self.encoded()
        offsets = [off for off, _, _ in self.schedule()]
        with vehicle_session([self.endpoint]) as session:
            pubs: dict[str, zenoh.Publisher] = {}
            for r in self.runs:
                session.put(config_key(PREFIX, r.vehicle_id), r.config_payload)
            time.sleep(0.5)  # configs first, so the vehicles start with their own config
            newest: dict[str, int] = {}
            t0 = time.monotonic()
            stall_at_ns = None if self.stall_at_s is None else int(self.stall_at_s * 1e9)
            drop = self.drop_wheels_s and [int(x * 1e9) for x in self.drop_wheels_s]
            for (key, payload, stamp), off in zip(packets, offsets, strict=True):
                if self._stop.is_set():
                    return
                if stall_at_ns is not None and off >= stall_at_ns:
                    stall_at_ns = None
                    time.sleep(self.stall_s)
                    t0 += self.stall_s  # then on at the usual pace, everything late by stall_s
                if drop is not None and key.endswith("/wheels") and drop[0] <= off < drop[1]:
                    self.dropped.append((key, payload))
                    continue
                due = t0 + off / 1e9 / self.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                pub = pubs.get(key)
                if pub is None:
                    pub = pubs[key] = session.declare_publisher(
                        key,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                        reliability=zenoh.Reliability.RELIABLE,
                    )
                pub.put(payload)
                vid = key.split("/")[1]
                newest[vid] = max(newest.get(vid, 0), stamp)
                self.timeline.append((time.monotonic(), dict(newest)))
                self.sent_order.append((key, payload))
            for pub in pubs.values():
                pub.undeclare()


# ------------------------------------------------------------------------------ expectations


class _Rows:
    def __init__(self) -> None:
        self.rows: dict[str, list[np.ndarray]] = {}

    def on_estimates(self, batch: list[tuple[str, np.ndarray]]) -> None:
        for vid, rows in batch:
            self.rows.setdefault(vid, []).append(rows.copy())


def reference_rows(publisher: Publisher) -> dict[str, np.ndarray]:
    """Estimates of a server that never failed: every packet, in order, through a pipeline."""
    from estimator.config import vehicle_config_from_dict

    sink = _Rows()
    registry = EstimatorRegistry()
    pipe = Pipeline(Settings(), None, registry, [sink])
    import json

    for r in publisher.runs:
        pipe.register_vehicle(r.vehicle_id, vehicle_config_from_dict(json.loads(r.config_payload)))
    pipe.start()
    items: list[Packet] = [decode(k, p, prefix=PREFIX) for k, p, _ in publisher.encoded()]
    for i in range(0, len(items), 200):
        pipe.submit(list(items[i : i + 200]))
    pipe.stop(timeout_s=120)
    return {vid: np.concatenate(chunks) for vid, chunks in sink.rows.items()}


def series_stamps(client: httpx.Client, vehicle_id: str, start_ns: int, end_ns: int) -> np.ndarray:
    """Stored estimate stamps of one vehicle (REST series, every row)."""
    r = client.get(
        f"/api/v1/vehicles/{vehicle_id}/series",
        params={"start": start_ns, "end": end_ns, "fields": "flags", "format": "json"},
    )
    r.raise_for_status()
    return np.asarray(r.json()["columns"]["stamp_ns"], dtype=np.int64)


def series_positions(
    client: httpx.Client, vehicle_id: str, start_ns: int, end_ns: int
) -> dict[str, np.ndarray]:
    """Stored ``stamp_ns``, ``east_m`` and ``north_m`` of one vehicle (REST series, every row;
    a missing position is NaN)."""
    r = client.get(
        f"/api/v1/vehicles/{vehicle_id}/series",
        params={"start": start_ns, "end": end_ns, "fields": "east_m,north_m", "format": "json"},
    )
    r.raise_for_status()
    cols = r.json()["columns"]
    return {
        "stamp_ns": np.asarray(cols["stamp_ns"], dtype=np.int64),
        "east_m": np.array([np.nan if v is None else v for v in cols["east_m"]], dtype=float),
        "north_m": np.array([np.nan if v is None else v for v in cols["north_m"]], dtype=float),
    }


def stamp_gaps(stamps: np.ndarray) -> list[tuple[int, int]]:
    """``(last stamp before, first stamp after)`` of every break in the tick spacing."""
    d = np.diff(stamps)
    idx = np.flatnonzero(d != TICK_NS)
    return [(int(stamps[i]), int(stamps[i + 1])) for i in idx]
