"""Load test: a simulated (or replayed) fleet at real rates against a real server process.

::

    slipfleet loadtest --vehicles 1000 --duration 60 [--scenario mix] [--rate-scale 1]
                       [--mix tractor=0.5,tracked=0.3,steered=0.2 [--beside-tractors]]
                       [--publishers N] [--warmup 5] [--json PATH]
                       [--connect tcp/HOST:7447 --api http://HOST:8000 [--server-pid PID]
                        [--token-file FILE]]
                       [--replay REC [REC ...]]

With ``--connect`` the server's API is read once before anything is published: a server that
requires tokens needs a viewer token (``--token-file``, or ``$SLIPFLEET_TOKEN``), and without
one the load test stops there with one line saying so.

Without ``--connect`` a server is started in a child process (embedded router on a free loopback
port, SQLite in a temporary directory unless ``--storage-url``; viewer off, no access tokens;
``--lateness-ms``, ``--advance-step-ms``, ``--estimate-interval-ms``, ``--commit-interval-s``
tune it). ``--publishers``
child processes (default: one per :data:`VEHICLES_PER_PUBLISHER` vehicles) publish the
vehicles, each with ``--sessions`` client sessions, through
:class:`server.tooling.fleet_sim.FleetSim`: GNSS 10 Hz, IMU 100 Hz in 100 ms batches, wheel edges in
100 ms batches (≈30 packets per vehicle-second), BLOCK congestion control, sends spread over the
100 ms tick. Each child publishes all its vehicles from one thread and one merged schedule of
pre-encoded packets (:func:`server.tooling.fleet_sim.publish_fleets`,
:mod:`server.tooling.fleet_schedule`): ≈6–10 µs of CPU per packet at 1,000–3,000 vehicles on
the 2-core reference machine (``slipfleet bench publisher``),
so 3,000 vehicles (90,000 packets/s) cost the load generator about half a core.
``--scenario mix`` spreads vehicles over :data:`MIX`; ``--estimator-mix`` gives every k-th
simulated vehicle of each shard other estimators (:class:`~server.tooling.estimator_mix.
EstimatorMix`). ``--mix`` shares the fleet by vehicle kind (:data:`KINDS`): tractors drive
the scenario(s), crawlers the crawler demo route (:mod:`server.tooling.tracked_fleet`: GNSS,
IMU, odometer and sprocket edges), steered four-wheel vehicles the friction demo drive
(:mod:`server.tooling.steered_fleet`; slow to simulate: one drive per publisher);
``--beside-tractors`` runs a tractor-only fleet of the same size first and prints the two
side by side (:func:`format_side_by_side`). ``--replay`` publishes
recordings (:mod:`server.protocol.recording`) instead: vehicle ``i`` replays the drives of
recording ``i mod len(paths)``, renamed and shifted in time (stamps moved to *now*, phases spread
over the tick), looping.

Measured over the window after the warm-up (every publisher has sent, then ``--warmup`` seconds)
until the publishers stop, plus a drain (the server has counted every packet sent, the writer
backlog is empty and, 1.5 s on, the writer has taken every estimate row produced; at most
``DRAIN_S`` without progress, ``DRAIN_MAX_S`` in all; the publishers keep their sessions open
until it ends, so *missing* is what never arrived, not what a server that fell behind still
had queued):

* packets sent (publishers) / received / accepted / rejected / late / duplicate / lost by
  sequence gap (server ``/metrics``), and *missing* = sent − received over the whole run;
* estimate rows produced, stored and not inserted (stored already, or of a vehicle the store
  does not know), storage rows/s;
* latency from each estimate's sensor timestamp to the live feed and to the committed row
  (:mod:`server.metrics.latency` histograms, differenced over the window — without the drain, whose
  rows the reorder buffers release only after the vehicles fall silent: p50/p95/p99/max,
  ±2.5 %);
* how late the publishers sent their packets over the window (p50/p99/max, whole ms, each
  packet counted by its sending round's first: an upper bound), which the latencies above
  include, and the most they fell behind over the whole run (start-up included);
* server CPU (cores: CPU seconds per wall second, all threads) and RSS (first, last, peak) via
  psutil on the server pid; publisher CPU likewise;
* cores by server thread over the window (``slipfleet_thread_cpu_seconds_total``,
  :mod:`server.metrics.thread_cpu`: the server process's threads and each ingest worker's, the
  workers' as of their last report, at most a second old), the busiest
  :data:`THREADS_SHOWN` in the report: where the server's CPU goes; and the pipeline threads'
  cores by phase (decode, reorder, release, estimate, deliver:
  ``slipfleet_pipeline_cpu_seconds_total``);
* the machine's speed before the load and after it (:mod:`server.tooling.speed_probe`: a fixed
  Python loop, best of three), and its one-minute load average as the window starts and as it
  ends: near the machine's limit a shared machine's drift decides the tail, so runs are
  compared at a like speed and load.

Everything runs on loopback and stops by itself (bounded duration and drain).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from server.tooling.api_client import check_metrics_access, open_client, parse_metric_line
from server.tooling.cli_args import (
    OneLineParser,
    add_scenario_argument,
    add_token_argument,
    count_arg,
    positive_arg,
    read_token,
)
from server.tooling.estimator_mix import EstimatorMix, add_estimator_mix_argument
from server.tooling.server_process import ServerProcess
from server.tooling.speed_probe import probe_s

if TYPE_CHECKING:  # imported where used, so ``slipfleet --help`` stays instant
    import httpx
    import psutil

    from server.tooling.fleet_sim import SimPacket, SimStats

__all__ = [
    "KINDS",
    "MIX",
    "VEHICLES_PER_PUBLISHER",
    "DrainWatch",
    "LoadSpec",
    "Target",
    "assignments",
    "format_report",
    "format_side_by_side",
    "main",
    "parse_kind_mix",
    "publisher_count",
    "run_loadtest",
    "scrape",
]

log = logging.getLogger(__name__)

#: Scenarios of ``--scenario mix`` (vehicles assigned round-robin).
MIX = ("field_work", "figure_eight", "slope_wet_patch", "slow_creep", "hard_braking")
#: Vehicle kinds of ``--mix``: tractors (kind ``wheeled_rear_drive``, the scenarios), crawlers
#: (kind ``tracked``) and steered four-wheel vehicles (kind ``wheeled_4wd_steered``).
KINDS = ("tractor", "tracked", "steered")
#: Longest the drain waits for the server to count every packet sent and empty its writer
#: backlog while nothing moves (no packet counted, no row taken), seconds.
DRAIN_S = 30.0
#: Longest drain in all, seconds: a server that fell minutes behind but still works through its
#: queues is given this long, so packets still queued are not counted as missing too early.
DRAIN_MAX_S = 300.0
#: Scrape period of ``/metrics`` during the run (progress, RSS), seconds. These scrapes ask for
#: fleet totals (``by_vehicle=false``); only the scrapes before and after the window render every
#: vehicle's counters (~25 series each, ~0.1 s of the server's CPU at 1,000 vehicles).
POLL_S = 3.0
#: Busiest server threads the report names (``server_thread_cores`` in the JSON has them all).
THREADS_SHOWN = 8


# ---------------------------------------------------------------------------------- servers


@dataclass(frozen=True)
class Target:
    """Where the load goes: router endpoint(s) for vehicles, server API(s) and pids to watch.

    ``shards`` holds one vehicle id format per server replica (replicas filter on an id
    prefix, :func:`server.tooling.shards.shard_layout`); the fleet is split evenly between them.
    """

    endpoints: tuple[str, ...]
    apis: tuple[str, ...]
    pids: tuple[int, ...] = ()
    shards: tuple[str, ...] = ("sim-{:05d}",)


# ---------------------------------------------------------------------------------- metrics


_PACKET_COUNTERS = ("received", "accepted", "late", "duplicate", "lost_by_seq_gap", "wheel_gaps")
#: Metrics a scrape sums over every sample, by the total they add to.
_SUMMED_METRICS = {
    **{f"slipfleet_packets_{k}_total": k for k in _PACKET_COUNTERS},
    "slipfleet_estimate_rows_total": "estimate_rows",
    "slipfleet_writer_rows_written_total": "rows_written",
    "slipfleet_writer_rows_ignored_total": "rows_not_inserted",
    "slipfleet_writer_rows_dropped_error_total": "rows_not_inserted",
    "slipfleet_writer_rows_dropped_backlog_full_total": "rows_dropped",
    "slipfleet_writer_backlog_rows": "backlog",
}


def scrape(
    api: str, client: httpx.Client | None = None, *, by_vehicle: bool = True
) -> dict[str, Any]:
    """Totals from one server's ``/metrics``: packet counters over every vehicle, rejections,
    estimate rows, writer rows and backlog, the latency histograms, vehicles seen (none with
    ``by_vehicle=False``: the server sums its counters itself, far cheaper for a large
    fleet)."""
    from server.metrics.latency import parse_histogram

    text = _fetch_metrics(api, client, by_vehicle)
    out = _empty_scrape()
    vehicles: set[str] = set()
    for line in text.splitlines():
        parsed = parse_metric_line(line)
        if parsed is not None:
            _add_sample(out, vehicles, *parsed)
    out["vehicles"] = vehicles
    out["latency"] = parse_histogram(text)
    return out


def _fetch_metrics(api: str, client: httpx.Client | None, by_vehicle: bool) -> str:
    """The text of ``api``'s ``/metrics`` (fleet totals unless ``by_vehicle``), read with
    ``client`` or a client of its own."""
    import httpx

    own = client is None
    c = client or httpx.Client(timeout=30.0)
    try:
        params = {} if by_vehicle else {"by_vehicle": "false"}
        return c.get(f"{api}/api/v1/metrics", params=params).raise_for_status().text
    finally:
        if own:
            c.close()


def _empty_scrape() -> dict[str, Any]:
    """A scrape's totals at zero, stamped now (monotonic s)."""
    out: dict[str, Any] = dict.fromkeys(_PACKET_COUNTERS, 0.0)
    out.update(
        rejected=0.0,
        estimate_rows=0.0,
        rows_written=0.0,
        rows_dropped=0.0,
        rows_not_inserted=0.0,
        backlog=0.0,
        ticks_without_wheel_data=0.0,
    )
    out["rejected_by_reason"] = {}
    out["thread_cpu"] = {}
    out["pipeline_cpu"] = {}
    out["at_s"] = time.monotonic()
    return out


def _add_sample(
    out: dict[str, Any], vehicles: set[str], name: str, labels: Mapping[str, str], value: float
) -> None:
    """Add one ``/metrics`` sample to a scrape's totals (and its vehicle to ``vehicles``)."""
    key = _SUMMED_METRICS.get(name)
    if key is not None:
        out[key] += value
        if key == "received" and labels.get("vehicle"):
            vehicles.add(labels["vehicle"])
    elif name == "slipfleet_packets_rejected_total":
        out["rejected"] += value
        reason = labels.get("reason", "?")
        out["rejected_by_reason"][reason] = out["rejected_by_reason"].get(reason, 0) + value
    elif (
        name == "slipfleet_estimator_events_total"
        and labels.get("event") == "ticks_without_wheel_data"
    ):
        out["ticks_without_wheel_data"] += value
    elif name == "slipfleet_pipeline_cpu_seconds_total":
        phase = labels.get("phase", "?")
        out["pipeline_cpu"][phase] = out["pipeline_cpu"].get(phase, 0.0) + value
    elif name == "slipfleet_thread_cpu_seconds_total":
        out["thread_cpu"][f"{labels.get('process', '?')}/{labels.get('thread', '?')}"] = value


def _merge(scrapes: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    counted = (
        "rejected",
        "estimate_rows",
        "rows_written",
        "rows_dropped",
        "rows_not_inserted",
        "ticks_without_wheel_data",
    )
    for k in (*_PACKET_COUNTERS, *counted):
        out[k] = sum(float(s[k]) for s in scrapes)
    out["backlog"] = sum(float(s["backlog"]) for s in scrapes)
    out["rejected_by_reason"] = _summed(scrapes, "rejected_by_reason")
    out["vehicles"] = set().union(*(s["vehicles"] for s in scrapes))
    out["at_s"] = max(s["at_s"] for s in scrapes)
    out["thread_cpu"] = {
        (f"server-{i}:{k}" if len(scrapes) > 1 else k): v
        for i, s in enumerate(scrapes)
        for k, v in s["thread_cpu"].items()
    }
    out["pipeline_cpu"] = _summed(scrapes, "pipeline_cpu")
    lat: dict[str, list[float]] = {}
    for s in scrapes:
        for stage, h in s["latency"].items():
            acc = lat.setdefault(stage, [0.0] * len(h["counts"]))
            for i, c in enumerate(h["counts"]):
                acc[i] += c
    out["latency"] = lat
    return out


def _summed(scrapes: Sequence[Mapping[str, Any]], key: str) -> dict[str, float]:
    """The scrapes' ``{name: value}`` maps under ``key``, added up name by name."""
    out: dict[str, float] = {}
    for s in scrapes:
        for name, value in s[key].items():
            out[name] = out.get(name, 0.0) + value
    return out


def window_cores(
    before: Mapping[str, Any], after: Mapping[str, Any], what: str = "thread_cpu"
) -> dict[str, float]:
    """Cores used between two merged scrapes (CPU seconds over wall seconds), busiest first:
    by server thread (``what="thread_cpu"``, keys ``process/thread``) or by pipeline phase
    (``what="pipeline_cpu"``). A thread started in between counts from zero, one that ended
    is left out."""
    wall = after["at_s"] - before["at_s"]
    if wall <= 0:
        return {}
    start = before[what]
    cores = {k: (v - start.get(k, 0.0)) / wall for k, v in after[what].items()}
    return {k: round(c, 3) for k, c in sorted(cores.items(), key=lambda kv: -kv[1]) if c >= 0.001}


def _latency_window(
    before: Mapping[str, list[float]], after: Mapping[str, list[float]]
) -> dict[str, dict[str, float]]:
    """p50/p95/p99/max (ms) and count per stage of the rows recorded between two scrapes."""
    from server.metrics.latency import BOUNDS_S, quantiles_from_buckets

    out: dict[str, dict[str, float]] = {}
    bounds = list(BOUNDS_S)
    for stage, counts in after.items():
        prev = before.get(stage, [0.0] * len(counts))
        window = [a - b for a, b in zip(counts, prev, strict=True)]
        q = quantiles_from_buckets(bounds, window, (0.5, 0.95, 0.99))
        nonzero = [i for i, c in enumerate(window) if c > 0]
        if nonzero:
            top = nonzero[-1]
            peak = bounds[top] if top < len(bounds) else float("inf")
        else:
            peak = float("nan")
        out[stage] = {
            "rows": sum(window),
            "p50_ms": q[0.5] * 1e3,
            "p95_ms": q[0.95] * 1e3,
            "p99_ms": q[0.99] * 1e3,
            "max_ms": peak * 1e3,
        }
    return out


# ---------------------------------------------------------------------------------- publishers

#: Vehicles one publisher process sends by default. One process sends 1,000 vehicles (30,000
#: packets/s) for 0.18-0.22 cores of the 2-core reference machine and was at most 62-125 ms
#: behind its schedule; two processes sharing them cost 0.27-0.30 cores (each has its own
#: Zenoh runtime and sending loop), CPU the server under test then lacks (loadtest, 1,000
#: vehicles, 20 s windows, the two alternating).
VEHICLES_PER_PUBLISHER = 1500


@dataclass(frozen=True)
class LoadSpec:
    """What to publish and for how long (see the module docstring)."""

    vehicles: int
    duration_s: float
    scenario: str = "mix"
    rate_scale: float = 1.0
    publishers: int | None = None
    """Publisher processes; None: one per :data:`VEHICLES_PER_PUBLISHER` vehicles."""
    sessions_per_publisher: int = 8
    warmup_s: float = 5.0
    distinct_runs: int = 2
    replay: tuple[str, ...] = ()
    seed: int = 0
    estimator_mix: EstimatorMix | None = None
    """Which simulated vehicles run other estimators than their kind's defaults."""
    kind_mix: tuple[tuple[str, float], ...] = (("tractor", 1.0),)
    """Share of the fleet per vehicle kind (:data:`KINDS`), :func:`parse_kind_mix`."""


def parse_kind_mix(text: str) -> tuple[tuple[str, float], ...]:
    """``"tractor=0.5,tracked=0.5"`` → ``(("tractor", 0.5), ("tracked", 0.5))``, shares
    normalised to sum to 1; ValueError naming what is wrong."""
    shares: dict[str, float] = {}
    for part in text.split(","):
        kind, _, value = part.partition("=")
        kind = kind.strip()
        if kind not in KINDS or kind in shares:
            raise ValueError(f"--mix: {kind!r} is not one of {', '.join(KINDS)} (once each)")
        try:
            shares[kind] = float(value)
        except ValueError:
            raise ValueError(f"--mix: {kind}={value!r} is not a number") from None
        if not math.isfinite(shares[kind]) or shares[kind] < 0:
            raise ValueError(f"--mix: {kind}'s share must be >= 0")
    total = sum(shares.values())
    if total <= 0:
        raise ValueError("--mix: the shares must not all be 0")
    return tuple((k, v / total) for k, v in shares.items() if v > 0)


def _kind_counts(n: int, mix: Sequence[tuple[str, float]]) -> list[tuple[str, int]]:
    """``n`` vehicles split by the shares of ``mix`` (largest remainders; the mix's order)."""
    exact = [share * n for _, share in mix]
    counts = [math.floor(x) for x in exact]
    by_remainder = sorted(range(len(mix)), key=lambda i: counts[i] - exact[i])
    for i in by_remainder[: n - sum(counts)]:
        counts[i] += 1
    return [(kind, c) for (kind, _), c in zip(mix, counts, strict=True)]


def publisher_count(spec: LoadSpec) -> int:
    """The publisher processes ``spec`` asks for, or one per :data:`VEHICLES_PER_PUBLISHER`."""
    if spec.publishers is not None:
        return max(1, spec.publishers)
    return max(1, math.ceil(spec.vehicles / VEHICLES_PER_PUBLISHER))


def _shard_groups(spec: LoadSpec, fmt: str, n_shard: int) -> list[dict[str, Any]]:
    """One shard's groups ``{id_format, first, count, scenario, kind}``: per kind of the mix
    (tractors: per scenario) one contiguous id range."""
    scenarios = list(MIX) if spec.scenario == "mix" else [spec.scenario]
    if spec.replay:
        scenarios = ["replay"]
    groups: list[dict[str, Any]] = []
    first = 1
    for kind, n_kind in _kind_counts(n_shard, spec.kind_mix):
        drives = scenarios if kind == "tractor" else [kind]
        for j, scen in enumerate(drives):
            n = n_kind // len(drives) + (1 if j < n_kind % len(drives) else 0)
            if n:
                groups.append(
                    {"id_format": fmt, "first": first, "count": n, "scenario": scen, "kind": kind}
                )
                first += n
    return groups


def assignments(spec: LoadSpec, shards: Sequence[str]) -> list[list[dict[str, Any]]]:
    """Per publisher process, its groups: ``{id_format, first, count, scenario, kind}``.

    Vehicles are numbered per shard; shard ``k`` gets vehicles ``k, k + S, …`` of the fleet, and
    each kind's (tractors: each scenario's) vehicles of a shard are one contiguous id range.
    """
    groups: list[dict[str, Any]] = []
    n_shards = len(shards)
    for k, fmt in enumerate(shards):
        n_shard = spec.vehicles // n_shards + (1 if k < spec.vehicles % n_shards else 0)
        groups += _shard_groups(spec, fmt, n_shard)
    # split groups across publishers so each gets about the same number of vehicles
    n_pub = max(1, min(publisher_count(spec), spec.vehicles))
    per_pub: list[list[dict[str, Any]]] = [[] for _ in range(n_pub)]
    target = spec.vehicles / n_pub
    p, load = 0, 0
    for g in groups:
        first, left = g["first"], g["count"]
        while left:
            room = max(1, round(target * (p + 1)) - load) if p < n_pub - 1 else left
            take = min(left, room)
            per_pub[p].append({**g, "first": first, "count": take})
            first, left, load = first + take, left - take, load + take
            if p < n_pub - 1 and load >= round(target * (p + 1)):
                p += 1
    return [g for g in per_pub if g]


class _Publisher:
    """One publisher child process; parses its progress lines on a reader thread."""

    def __init__(self, index: int, job: dict[str, Any]) -> None:
        self.index = index
        self.sent = 0
        self.behind_ms = 0.0
        self.final: dict[str, Any] | None = None
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "server.tooling.loadtest", "_publish", json.dumps(job)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                msg = json.loads(line)
            except json.JSONDecodeError:
                continue
            if "final" in msg:
                self.final = msg["final"]
            else:
                self.sent = int(msg.get("sent", self.sent))
                self.behind_ms = float(msg.get("behind_ms", self.behind_ms))

    def mark(self) -> None:
        """The measured window starts: the child counts its send lateness from here."""
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            with contextlib.suppress(BrokenPipeError, OSError, ValueError):
                self.proc.stdin.write("mark\n")
                self.proc.stdin.flush()

    def stop(self) -> None:
        """Stop publishing; the child reports its final counts and keeps its sessions open
        (what they still queue reaches the server) until :meth:`close`."""
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            with contextlib.suppress(BrokenPipeError, OSError, ValueError):
                self.proc.stdin.write("stop\n")
                self.proc.stdin.flush()

    def close(self) -> None:
        """Let the child close its sessions and exit (end of its input)."""
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            with contextlib.suppress(BrokenPipeError, OSError, ValueError):
                self.proc.stdin.close()

    def wait_final(self, timeout_s: float = 60.0) -> None:
        """Wait (at most ``timeout_s``) for the child's final counts after :meth:`stop`."""
        deadline = time.monotonic() + timeout_s
        while self.final is None and self.proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)

    def join(self, timeout_s: float = 60.0) -> None:
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        self._reader.join(5.0)
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                with contextlib.suppress(OSError, ValueError):
                    stream.close()


def _replay_fleet_sim_class() -> type:
    """A :class:`FleetSim` whose runs come from recordings instead of the simulator."""
    from estimator.config import WheeledRearDriveConfig
    from server.tooling.fleet_sim import TICK_NS, FleetSim, _Vehicle, loop_period_ns

    class ReplaySim(FleetSim):
        """Vehicle ``i`` replays drive ``i mod n_drives`` of ``paths`` (all vehicles in them)."""

        def __init__(
            self,
            session: Any,
            n: int,
            *,
            paths: Sequence[str],
            id_format: str,
            prefix: str,
            first_index: int,
            **kw: Any,
        ) -> None:
            super().__init__(session, n, prefix=prefix, first_index=first_index, loop=True, **kw)
            self._paths = list(paths)
            self._id_format = id_format

        @property
        def vehicle_ids(self) -> list[str]:
            return [self._id_format.format(self._first + i) for i in range(self._n)]

        def _drives(self) -> list[tuple[list[SimPacket], int, int]]:
            return _recorded_drives(self._paths)

        def _build(self) -> list[Any]:
            # shift_ns relative to the drive start; "now" is added as publishing starts
            drives = self._drives()
            out = []
            for i, vid in enumerate(self.vehicle_ids):
                packets, start, end = drives[i % len(drives)]
                phase = (i * TICK_NS) // self._n
                period = loop_period_ns(start, end)
                out.append(
                    _Vehicle(vid, packets, period, phase, phase - start, WheeledRearDriveConfig())
                )
            return out

    return ReplaySim


def _recorded_drives(paths: Sequence[str]) -> list[tuple[list[SimPacket], int, int]]:
    """Each recorded vehicle's sensor packets in ``paths`` as a drive: (packets, first and last
    stamp); ValueError when there is none."""
    from estimator.sim.sensors import NO_EDGES
    from server.protocol.codec import DecodeError, decode
    from server.protocol.keys import parse_key
    from server.protocol.recording import read_recording
    from server.tooling.fleet_sim import packetize

    drives: list[tuple[list[SimPacket], int, int]] = []
    for path in paths:
        by_vehicle: dict[str, list[tuple[int, Any, int | None]]] = {}
        for rec in read_recording(path):
            parts = rec.key.split("/")
            if "sensors" not in parts:
                continue
            prefix = "/".join(parts[: parts.index("sensors") - 1])
            try:
                vid, _ = parse_key(rec.key, prefix)
                pkt = decode(rec.key, rec.payload, prefix=prefix, max_payload_bytes=1 << 30)
            except (DecodeError, ValueError, IndexError):
                continue
            # a wheel heartbeat has no measurement: carried as edges of no stamps
            for m in pkt.measurements or (NO_EDGES,):
                by_vehicle.setdefault(vid, []).append((rec.stamp_ns, m, pkt.until_ns))
        for items in by_vehicle.values():
            start = items[0][0]
            packets = packetize(items, start)
            drives.append((packets, start, items[-1][0]))
    if not drives:
        raise ValueError(f"no sensor packets in {list(paths)}")
    return drives


def _named_fleet_sim_class(kind: str = "tractor") -> type:
    """The fleet simulator of ``kind`` (:data:`KINDS`) with a configurable vehicle id format
    (shard prefixes)."""
    from server.tooling.fleet_sim import FleetSim
    from server.tooling.steered_fleet import SteeredFleetSim
    from server.tooling.tracked_fleet import TrackedFleetSim

    base = {"tractor": FleetSim, "tracked": TrackedFleetSim, "steered": SteeredFleetSim}[kind]

    class NamedSim(base):  # type: ignore[valid-type,misc]
        def __init__(self, *args: Any, id_format: str, **kw: Any) -> None:
            super().__init__(*args, **kw)
            self._id_format = id_format

        @property
        def vehicle_ids(self) -> list[str]:
            return [self._id_format.format(self._first + i) for i in range(self._n)]

    return NamedSim


def _group_sim(sessions: Sequence[Any], job: dict[str, Any], g: dict[str, Any], mix: Any) -> Any:
    """The simulator of one group of a publisher's job (its kind's; replay aside)."""
    kind = g.get("kind", "tractor")
    kw: dict[str, Any] = {
        "prefix": job["prefix"],
        "rate": job["rate"],
        "first_index": g["first"],
        "id_format": g["id_format"],
        "loop": True,
        "seed": job["seed"],
    }
    if kind == "tractor":  # other estimators than a kind's defaults: the tractors' choice
        kw.update(scenario=g["scenario"], distinct_runs=job["distinct_runs"], estimator_mix=mix)
    elif kind == "tracked":
        kw.update(distinct_runs=job["distinct_runs"])
    # steered: its one drive (simulating one costs a minute of CPU)
    return _named_fleet_sim_class(kind)(sessions, g["count"], **kw)


def _publish_child(job_json: str) -> int:
    """Child entry point: publish the groups of one publisher until told to stop."""
    job = json.loads(job_json)
    sessions = _open_sessions(job["endpoints"], job["sessions"])
    sims = _job_sims(sessions, job)
    from server.tooling.fleet_sim import SimStats

    stop = threading.Event()
    stats = SimStats()
    failed: list[BaseException] = []
    worker = threading.Thread(
        target=_publish,
        args=(sims, stop, stats, failed),
        name="slipfleet-publisher",
        daemon=True,
    )
    worker.start()
    marked: dict[int, int] = {}  # packets by lateness when the window started
    threading.Thread(target=_wait_stop, args=(stop, stats, marked), daemon=True).start()
    cpu0 = time.process_time()
    t0 = time.monotonic()
    while not stop.wait(0.5):
        print(
            json.dumps({"sent": stats.total_packets, "behind_ms": stats.max_behind_ms}),
            flush=True,
        )
    worker.join(30.0)
    print(json.dumps({"final": _final_counts(stats, marked, cpu0, t0)}), flush=True)
    # the sessions stay open until the parent has drained the server: closing them drops what
    # their queues still hold for a server that fell behind (BLOCK held the puts back)
    sys.stdin.read()  # until the end of input
    time.sleep(0.5)  # let the sessions flush before closing
    for session in sessions:
        session.close()
    return 1 if failed else 0


def _open_sessions(endpoints: list[str], n: int) -> list[Any]:
    """``n`` Zenoh client sessions connected to ``endpoints``."""
    import zenoh

    from server.ingest.zenoh_session import make_config
    from server.settings import ZenohSettings

    return [zenoh.open(make_config(ZenohSettings(connect=endpoints))) for _ in range(n)]


def _job_sims(sessions: Sequence[Any], job: dict[str, Any]) -> list[Any]:
    """The simulators of a publisher's groups: recordings replayed, or each group's kind's."""
    ReplaySim = _replay_fleet_sim_class() if job["replay"] else None
    mix = None if job["estimator_mix"] is None else EstimatorMix.parse(job["estimator_mix"])
    if ReplaySim is None:
        return [_group_sim(sessions, job, g, mix) for g in job["groups"]]
    common = {k: job[k] for k in ("prefix", "rate")}
    return [
        ReplaySim(
            sessions,
            g["count"],
            paths=job["replay"],
            first_index=g["first"],
            id_format=g["id_format"],
            **common,
        )
        for g in job["groups"]
    ]


def _publish(
    sims: Sequence[Any], stop: threading.Event, stats: SimStats, failed: list[BaseException]
) -> None:
    """Publish ``sims`` on one merged schedule until ``stop``; a failure is kept in ``failed``
    and sets ``stop``."""
    from server.tooling.fleet_sim import publish_fleets

    try:  # one thread, one merged schedule for every group of this process
        publish_fleets(sims, stop=stop, stats=stats)
    except BaseException as exc:
        failed.append(exc)
        stop.set()
        raise


def _wait_stop(stop: threading.Event, stats: SimStats, marked: dict[int, int]) -> None:
    """Read the parent's lines: on "mark" keep the lateness counts so far in ``marked``; on
    "stop" or the end of input set ``stop``."""
    for line in sys.stdin:  # "mark": the window starts; "stop"; EOF: the parent is gone
        if line.strip() != "mark":
            break
        marked.update(stats.late_packets)  # a copy in one step (under the GIL)
    stop.set()


def _final_counts(
    stats: SimStats, marked: Mapping[int, int], cpu0: float, t0: float
) -> dict[str, Any]:
    """What the child reports at the end: its counts, lateness since "mark", CPU and wall s."""
    return {
        "sent": stats.total_packets,
        "configs": stats.configs,
        "bytes": stats.payload_bytes,
        "max_behind_ms": stats.max_behind_ms,
        "late_packets": {  # since "mark"
            ms: n - marked.get(ms, 0) for ms, n in dict(stats.late_packets).items()
        },
        "cpu_s": time.process_time() - cpu0,
        "wall_s": time.monotonic() - t0,
    }


# ---------------------------------------------------------------------------------- the run


@dataclass
class _ProcWatch:
    """CPU and RSS of processes, sampled on a thread."""

    pids: Sequence[int]
    procs: list[psutil.Process] = field(default_factory=list)
    peak_rss: dict[int, int] = field(default_factory=dict)
    rss_series: list[tuple[float, int]] = field(default_factory=list)  # (t, total rss)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> _ProcWatch:
        import psutil

        # a server's worker processes (ingest.workers) count as the server
        self.procs = []
        for pid in self.pids:
            proc = psutil.Process(pid)
            self.procs.append(proc)
            with contextlib.suppress(psutil.Error):
                self.procs.extend(proc.children(recursive=True))
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        import psutil

        t0 = time.monotonic()
        while not self._stop.wait(0.5):
            total = 0
            for p in self.procs:
                with contextlib.suppress(psutil.Error):
                    rss = p.memory_info().rss
                    total += rss
                    self.peak_rss[p.pid] = max(self.peak_rss.get(p.pid, 0), rss)
            self.rss_series.append((time.monotonic() - t0, total))

    def cpu_s(self) -> float:
        import psutil

        total = 0.0
        for p in self.procs:
            with contextlib.suppress(psutil.Error):
                t = p.cpu_times()
                total += t.user + t.system
        return total

    def rss(self) -> int:
        import psutil

        total = 0
        for p in self.procs:
            with contextlib.suppress(psutil.Error):
                total += p.memory_info().rss
        return total

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)


def _jobs(spec: LoadSpec, target: Target, prefix: str) -> list[dict[str, Any]]:
    """One job (JSON-ready) per publisher process: its groups and what they share."""
    return [
        {
            "endpoints": list(target.endpoints),
            "sessions": max(1, min(spec.sessions_per_publisher, sum(g["count"] for g in groups))),
            "groups": groups,
            "prefix": prefix,
            "rate": spec.rate_scale,
            "replay": list(spec.replay),
            "seed": spec.seed,
            "distinct_runs": spec.distinct_runs,
            "estimator_mix": None if spec.estimator_mix is None else str(spec.estimator_mix),
        }
        for groups in assignments(spec, target.shards)
    ]


def _wait_sending(pubs: Sequence[_Publisher]) -> float:
    """Wait until every publisher sends (they simulate first); the seconds it took."""
    t_start = time.monotonic()
    while not all(p.sent > 0 for p in pubs):
        if any(p.proc.poll() is not None for p in pubs):
            raise RuntimeError("a publisher exited before sending")
        if time.monotonic() - t_start > 300:
            raise TimeoutError("publishers did not start sending within 300 s")
        time.sleep(0.1)
    return round(time.monotonic() - t_start, 2)


@dataclass
class _Cost:
    """CPU and RSS readings at the window's ends (server and publishers)."""

    server_cpu_s: tuple[float, float]
    publisher_cpu_s: tuple[float, float]
    server_rss: tuple[int, int]


@dataclass
class _Window:
    """What the measured window saw: the scrapes at its ends, packets sent, its length, what
    it cost."""

    before: dict[str, Any]
    last: dict[str, Any]
    sent0: int
    sent1: int
    wall_s: float
    cost: _Cost


def _watch_window(
    spec: LoadSpec,
    target: Target,
    http: httpx.Client,
    pubs: Sequence[_Publisher],
    watches: tuple[_ProcWatch, _ProcWatch],
    progress: bool,
) -> _Window:
    """Scrape at the start, then every :data:`POLL_S` (fleet totals, a progress bar) until
    ``spec.duration_s`` has passed; ``watches``: the server's and the publishers' processes."""
    from tqdm import tqdm

    server, publishers = watches
    before = _merge([scrape(a, http) for a in target.apis])
    sent0 = sum(p.sent for p in pubs)
    for p in pubs:
        p.mark()
    cpu0, pcpu0, t0 = server.cpu_s(), publishers.cpu_s(), time.monotonic()
    rss0 = server.rss()
    bar = tqdm(
        total=round(spec.duration_s),
        unit="s",
        desc=f"{spec.vehicles} vehicles",
        disable=not progress,
        leave=False,
    )
    last = before
    with bar:
        while (elapsed := time.monotonic() - t0) < spec.duration_s:
            time.sleep(min(POLL_S, spec.duration_s - elapsed))
            last = _merge([scrape(a, http, by_vehicle=False) for a in target.apis])
            dt = max(time.monotonic() - t0, 1e-9)
            bar.n = min(round(dt), bar.total)
            bar.set_postfix(
                sent_per_s=round((sum(p.sent for p in pubs) - sent0) / dt),
                recv_per_s=round((last["received"] - before["received"]) / dt),
                lost=int(last["lost_by_seq_gap"]),
                backlog=int(last["backlog"]),
                refresh=False,
            )
            bar.refresh()
    sent1, wall = sum(p.sent for p in pubs), time.monotonic() - t0
    cost = _Cost((cpu0, server.cpu_s()), (pcpu0, publishers.cpu_s()), (rss0, server.rss()))
    return _Window(before, last, sent0, sent1, wall, cost)


@dataclass
class DrainWatch:
    """When the drain ends: settled (every packet sent counted, the writer backlog empty and,
    1.5 s on, every row produced taken by the writer), or :data:`DRAIN_S` without progress,
    or :data:`DRAIN_MAX_S` in all. Times in seconds of one monotonic clock."""

    sent_total: int
    started_s: float
    progress_s: float = -math.inf
    seen: tuple[float, float] = (-1.0, -1.0)
    settled_s: float | None = None

    def done(self, last: Mapping[str, Any], now_s: float) -> bool:
        taken = last["rows_written"] + last["rows_not_inserted"] + last["rows_dropped"]
        if (last["received"], taken) != self.seen:
            self.seen, self.progress_s = (last["received"], taken), now_s
        if last["received"] >= self.sent_total and last["backlog"] == 0:
            self.settled_s = self.settled_s or now_s
            if now_s - self.settled_s >= 1.5 and taken >= last["estimate_rows"]:
                return True
        return now_s - self.progress_s > DRAIN_S or now_s - self.started_s > DRAIN_MAX_S


def _drain(target: Target, http: httpx.Client, sent_total: int) -> tuple[dict[str, Any], float]:
    """Scrape until the drain is done (:class:`DrainWatch`); the final per-vehicle scrape and
    the seconds it took."""
    t_drain = time.monotonic()
    watch = DrainWatch(sent_total, t_drain)
    while not watch.done(
        _merge([scrape(a, http, by_vehicle=False) for a in target.apis]), time.monotonic()
    ):
        time.sleep(0.25)
    return _merge([scrape(a, http) for a in target.apis]), time.monotonic() - t_drain


def _packet_result(
    w: _Window, after: Mapping[str, Any], sent_total: int, drain_s: float
) -> dict[str, Any]:
    """Packets and estimate rows of a run (module docstring)."""
    before, wall = w.before, w.wall_s
    return {
        "window_s": round(wall, 2),
        "drain_s": round(drain_s, 2),
        "vehicles_seen": len(after["vehicles"]),
        "packets_sent": int(sent_total),
        "packets_sent_window": int(w.sent1 - w.sent0),
        "packets_per_s": round((w.sent1 - w.sent0) / wall, 1),
        "packets_received": int(after["received"]),
        "packets_received_window": int(w.last["received"] - before["received"]),
        "packets_accepted": int(after["accepted"]),
        "packets_rejected": int(after["rejected"]),
        "packets_rejected_by_reason": {
            k: int(v) for k, v in sorted(after["rejected_by_reason"].items())
        },
        "packets_late": int(after["late"]),
        "packets_duplicate": int(after["duplicate"]),
        "packets_lost_by_seq_gap": int(after["lost_by_seq_gap"]),
        "wheel_gaps": int(after["wheel_gaps"] - before["wheel_gaps"]),
        "ticks_without_wheel_data": int(
            after["ticks_without_wheel_data"] - before["ticks_without_wheel_data"]
        ),
        "packets_missing": int(max(0, sent_total - after["received"])),
        "estimates_produced": int(after["estimate_rows"]),
        "estimates_stored": int(after["rows_written"]),
        "estimates_not_inserted": int(after["rows_not_inserted"]),
        "rows_dropped_backlog_full": int(after["rows_dropped"]),
        "storage_rows_per_s": round(
            (after["rows_written"] - before["rows_written"]) / (wall + drain_s), 1
        ),
        "latency": _latency_window(before["latency"], w.last["latency"]),
        "server_thread_cores": window_cores(before, w.last),
        "pipeline_phase_cores": window_cores(before, w.last, "pipeline_cpu"),
    }


def _cost_result(
    target: Target, w: _Window, server_watch: _ProcWatch, pubs: Sequence[_Publisher]
) -> dict[str, Any]:
    """CPU, memory and send lateness of a run (module docstring)."""
    watched, wall, cost = bool(target.pids), w.wall_s, w.cost
    (cpu0, cpu1), (pcpu0, pcpu1) = cost.server_cpu_s, cost.publisher_cpu_s
    rss0, rss1 = cost.server_rss
    out: dict[str, Any] = {
        "server_cpu_cores": round((cpu1 - cpu0) / wall, 3) if watched else None,
        "server_rss_mb_start": round(rss0 / 2**20, 1) if watched else None,
        "server_rss_mb_end": round(rss1 / 2**20, 1) if watched else None,
        "server_rss_mb_peak": round(sum(server_watch.peak_rss.values()) / 2**20, 1)
        if watched
        else None,
        "publisher_cpu_cores": round((pcpu1 - pcpu0) / wall, 3),
        "publisher_max_behind_ms": round(
            max((p.final or {}).get("max_behind_ms", p.behind_ms) for p in pubs), 1
        ),
        "publisher_late_ms": _send_lateness(pubs),
        "machine_cpus": os.cpu_count(),
    }
    series = server_watch.rss_series
    if watched and series:
        out["server_rss_growth_pct"] = round(100.0 * (rss1 - rss0) / max(rss0, 1), 2)
        step = max(1, len(series) // 120)
        out["server_rss_mb_series"] = [
            (round(t, 1), round(rss / 2**20, 1)) for t, rss in series[::step]
        ]
    return out


def _stop_all(pubs: Sequence[_Publisher], timeout_s: float = 60.0) -> None:
    for p in pubs:
        p.stop()
        p.close()
    for p in pubs:
        p.join(timeout_s)


def run_loadtest(
    spec: LoadSpec,
    target: Target,
    *,
    prefix: str = "fleet",
    progress: bool = True,
    token: str | None = None,
) -> dict[str, Any]:
    """Publish ``spec`` to ``target`` and measure (see the module docstring); a result dict.

    ``token`` is sent to the servers' APIs; each API is read once before anything is published
    (SystemExit with one line if that fails: nothing listening, a token missing or refused)."""
    jobs = _jobs(spec, target, prefix)
    http = open_client(token)
    for api in target.apis:
        check_metrics_access(http, api)
    probe_before_s = probe_s()  # before any load: the machine's speed at the start
    server_watch = _ProcWatch(target.pids).start()
    pubs = [_Publisher(i, job) for i, job in enumerate(jobs)]
    pub_watch = _ProcWatch([p.proc.pid for p in pubs]).start()
    result: dict[str, Any] = {"spec": dataclasses.asdict(spec), "publishers": len(pubs)}
    try:
        result["publisher_start_s"] = _wait_sending(pubs)  # then spec.warmup_s more seconds
        time.sleep(spec.warmup_s)
        # latency is taken over the window only: when the publishers stop, every vehicle's
        # last data is released by the reorder buffers' idle timeout, late by design
        load_before = os.getloadavg()[0]
        window = _watch_window(spec, target, http, pubs, (server_watch, pub_watch), progress)
        result["machine_load_avg"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
        for p in pubs:
            p.stop()
        for p in pubs:
            p.wait_final()
        sent_total = sum((p.final or {}).get("sent", p.sent) for p in pubs)
        after, drain_s = _drain(target, http, sent_total)  # the publishers' sessions still open
        _stop_all(pubs)
    finally:
        _stop_all(pubs, 10.0)
        server_watch.stop()
        pub_watch.stop()
        http.close()
    result.update(_packet_result(window, after, sent_total, drain_s))
    result.update(_cost_result(target, window, server_watch, pubs))
    result["machine_probe_s"] = [round(probe_before_s, 3), round(probe_s(), 3)]
    total_lost = result["packets_lost_by_seq_gap"] + result["packets_missing"]
    result["loss_free"] = total_lost == 0 and result["packets_late"] == 0
    return result


def _send_lateness(pubs: Sequence[_Publisher]) -> dict[str, int | None]:
    """p50 / p99 / max of how late the publishers sent their packets in the window (ms, each
    packet counted by its sending round's first packet: an upper bound); the sensor→stored
    latency includes it."""
    from server.tooling.fleet_schedule import lateness_quantiles

    merged: dict[int, int] = {}
    for p in pubs:
        for ms, n in ((p.final or {}).get("late_packets") or {}).items():
            merged[int(ms)] = merged.get(int(ms), 0) + int(n)
    p50, p99, top = lateness_quantiles(merged, (0.5, 0.99, 1.0))
    return {"p50": p50, "p99": p99, "max": top}


def format_report(r: Mapping[str, Any]) -> str:
    """A human-readable summary of a :func:`run_loadtest` result."""
    lines = _report_head(r)
    lines += _report_latency(r["latency"])
    lines += _report_server(r)
    lines += _report_machine(r)
    return "\n".join(lines)


def _report_head(r: Mapping[str, Any]) -> list[str]:
    """The report's first lines: the fleet and run, packets, send rate and estimates."""
    late = r.get("publisher_late_ms") or {}
    return [
        f"vehicles {r['spec']['vehicles']} (seen {r['vehicles_seen']}; "
        f"{mix_label(r['spec']['kind_mix'])}), scenario "
        f"{r['spec']['scenario'] if not r['spec']['replay'] else 'replay'}, rate x"
        f"{r['spec']['rate_scale']}, {r['publishers']} publisher processes, window "
        f"{r['window_s']} s (+{r['drain_s']} s drain)",
        f"packets  sent {r['packets_sent']}  received {r['packets_received']}  rejected "
        f"{r['packets_rejected']} {r['packets_rejected_by_reason'] or ''}  late "
        f"{r['packets_late']}  duplicate {r['packets_duplicate']}  "
        f"lost(seq gap) {r['packets_lost_by_seq_gap']}  missing {r['packets_missing']}  "
        f"wheel gaps {r.get('wheel_gaps', 0)}",
        f"rate     {r['packets_per_s']:.0f} packets/s sent in the window "
        f"(publishers {r['publisher_cpu_cores']} cores, sent late by p50 "
        f"{late.get('p50')} / p99 {late.get('p99')} / max {late.get('max')} ms in the window, "
        f"{r['publisher_max_behind_ms']} ms at most in the run)",
        f"estimates produced {r['estimates_produced']}  stored {r['estimates_stored']}  "
        f"not inserted {r.get('estimates_not_inserted', 0)}  "
        f"({r['storage_rows_per_s']:.0f} rows/s)  dropped(backlog) "
        f"{r['rows_dropped_backlog_full']}  without wheel data "
        f"{r.get('ticks_without_wheel_data', 0)}",
    ]


def _report_latency(lat: Mapping[str, Any]) -> list[str]:
    """The report's sensor-to-live and sensor-to-stored latency lines (those measured)."""
    lines: list[str] = []
    for stage in ("live", "stored"):
        if stage in lat:
            s = lat[stage]
            lines.append(
                f"latency  sensor→{stage:<6} p50 {s['p50_ms']:.0f}  p95 {s['p95_ms']:.0f}  "
                f"p99 {s['p99_ms']:.0f}  max {s['max_ms']:.0f} ms  ({int(s['rows'])} rows)"
            )
    return lines


def _report_server(r: Mapping[str, Any]) -> list[str]:
    """The report's server CPU and memory, busiest threads and pipeline phases lines."""
    lines: list[str] = []
    if r.get("server_cpu_cores") is not None:
        lines.append(
            f"server   CPU {r['server_cpu_cores']:.2f} cores of {r['machine_cpus']}  RSS "
            f"{r['server_rss_mb_start']} → {r['server_rss_mb_end']} MB (peak "
            f"{r['server_rss_mb_peak']} MB, growth {r.get('server_rss_growth_pct')} %)"
        )
    threads = r.get("server_thread_cores") or {}
    if threads:
        top = list(threads.items())[:THREADS_SHOWN]
        rest = sum(list(threads.values())[THREADS_SHOWN:])
        lines.append(
            "threads  "
            + "  ".join(f"{name} {cores:.2f}" for name, cores in top)
            + (f"  +{len(threads) - len(top)} more {rest:.2f}" if len(threads) > len(top) else "")
            + " (cores)"
        )
    phases = r.get("pipeline_phase_cores") or {}
    if phases:
        lines.append(
            "pipeline "
            + "  ".join(f"{phase} {cores:.2f}" for phase, cores in phases.items())
            + " (cores, every pipeline thread)"
        )
    return lines


def _report_machine(r: Mapping[str, Any]) -> list[str]:
    """The report's machine speed probe and load average lines."""
    lines: list[str] = []
    if r.get("machine_probe_s"):
        before, after = r["machine_probe_s"]
        lines.append(
            f"machine  Python probe {before:.3f} s before, {after:.3f} s after (a fixed loop, "
            "best of 3: runs are comparable at a like speed)"
        )
    if r.get("machine_load_avg"):
        start, end = r["machine_load_avg"]
        lines.append(
            f"machine  load average (1 min) {start:.2f} as the window starts, {end:.2f} as it "
            f"ends, on {r['machine_cpus']} CPUs"
        )
    return lines


def mix_label(kind_mix: Sequence[Sequence[Any]]) -> str:
    """``tractor=0.5,tracked=0.5`` of a spec's ``kind_mix``."""
    return ",".join(f"{kind}={share:g}" for kind, share in kind_mix)


def _lat(r: Mapping[str, Any], stage: str, q: str) -> str:
    s = (r.get("latency") or {}).get(stage)
    return "-" if s is None else f"{s[q]:.0f}"


#: The rows of :func:`format_side_by_side`: label and how to read it off a result.
_SIDE_BY_SIDE: tuple[tuple[str, Any], ...] = (
    ("fleet (--mix)", lambda r: mix_label(r["spec"]["kind_mix"])),
    ("vehicles seen", lambda r: r["vehicles_seen"]),
    ("packets/s sent", lambda r: f"{r['packets_per_s']:.0f}"),
    ("packets sent", lambda r: r["packets_sent"]),
    # never received, and how many sequence gaps the server saw: a packet lost mid-stream is
    # both, so the two are not added
    ("missing (seq gaps)", lambda r: f"{r['packets_missing']} "
     f"({r['packets_lost_by_seq_gap']})"),
    ("late", lambda r: r["packets_late"]),
    ("rejected", lambda r: r["packets_rejected"]),
    ("estimate rows stored", lambda r: r["estimates_stored"]),
    ("sensor→live p50 / p99 ms", lambda r: f"{_lat(r, 'live', 'p50_ms')} / "
     f"{_lat(r, 'live', 'p99_ms')}"),
    ("sensor→stored p50 / p99 ms", lambda r: f"{_lat(r, 'stored', 'p50_ms')} / "
     f"{_lat(r, 'stored', 'p99_ms')}"),
    ("sensor→stored max ms", lambda r: _lat(r, "stored", "max_ms")),
    ("server CPU cores", lambda r: r.get("server_cpu_cores")),
    ("server RSS peak MB", lambda r: r.get("server_rss_mb_peak")),
    ("publisher CPU cores", lambda r: r.get("publisher_cpu_cores")),
    ("machine probe s (before)", lambda r: (r.get("machine_probe_s") or [None])[0]),
    ("load average at window end", lambda r: (r.get("machine_load_avg") or [None, None])[1]),
)  # fmt: skip


def format_side_by_side(results: Sequence[Mapping[str, Any]]) -> str:
    """Load test results side by side, a Markdown table (one column per run): what was
    lost, the p99s and the cost."""
    head = ["", *(f"run {i + 1}" for i in range(len(results)))]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for label, read in _SIDE_BY_SIDE:
        lines.append("| " + " | ".join([label, *(str(read(r)) for r in results)]) + " |")
    return "\n".join(lines)


def _pid_listening_on(api: str) -> int | None:
    import httpx
    import psutil

    port = httpx.URL(api).port
    with contextlib.suppress(psutil.Error):
        for conn in psutil.net_connections("tcp"):
            if conn.status == psutil.CONN_LISTEN and conn.laddr and conn.laddr.port == port:
                return conn.pid
    return None


@contextlib.contextmanager
def local_server(
    settings: Mapping[str, Any] | None = None, storage_url: str | None = None
) -> Iterator[ServerProcess]:
    """A :class:`ServerProcess` with SQLite in a temporary directory (or ``storage_url``)."""
    with tempfile.TemporaryDirectory(prefix="slipfleet-loadtest-") as tmp:
        s: dict[str, Any] = json.loads(json.dumps(dict(settings or {})))
        s.setdefault("storage", {}).setdefault("data_dir", str(Path(tmp) / "data"))
        server = ServerProcess(s, storage_url, log_path=Path(tmp) / "server.log")
        server.start()
        try:
            yield server
        finally:
            code = server.stop()
            if code not in (0, None, -15):
                log_text = (Path(tmp) / "server.log").read_text(errors="replace")[-4000:]
                log.warning("server exited with %s:\n%s", code, log_text)


def server_tuning(args: argparse.Namespace) -> dict[str, Any]:
    """Settings overrides from ``--lateness-ms``, ``--advance-step-ms``,
    ``--estimate-interval-ms``, ``--commit-interval-s``, ``--workers``."""
    s: dict[str, Any] = {}
    if args.workers is not None:
        s.setdefault("ingest", {})["workers"] = args.workers
    if args.lateness_ms is not None:
        s.setdefault("ingest", {})["lateness_ms"] = args.lateness_ms
    if args.advance_step_ms is not None:
        s.setdefault("ingest", {})["advance_step_ms"] = args.advance_step_ms
    if args.estimate_interval_ms is not None:
        s.setdefault("ingest", {})["estimate_interval_ms"] = args.estimate_interval_ms
    if args.commit_interval_s is not None:
        s.setdefault("storage", {})["commit_interval_s"] = args.commit_interval_s
    return s


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``loadtest`` flags (shared by ``slipfleet loadtest`` and ``python -m``)."""
    _add_fleet_arguments(p)
    _add_target_arguments(p)
    _add_tuning_arguments(p)


def _add_fleet_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of the simulated fleet and its publishers: size, kinds, pace, replay."""
    p.add_argument(
        "--vehicles", type=count_arg, required=True, help="simulated vehicles to publish"
    )
    p.add_argument("--duration", type=positive_arg, required=True, help="measured seconds")
    add_scenario_argument(p, "mix", mix=True)
    p.add_argument(
        "--mix",
        type=parse_kind_mix,
        default=(("tractor", 1.0),),
        metavar="KIND=SHARE,...",
        help=f"the fleet's shares by kind ({', '.join(KINDS)}), e.g. tractor=0.5,tracked=0.5 "
        "(default: tractors only; --scenario is the tractors')",
    )
    p.add_argument(
        "--beside-tractors",
        action="store_true",
        help="first run a tractor-only fleet of the same size, then print both side by side",
    )
    p.add_argument("--rate-scale", type=positive_arg, default=1.0, help="2 = twice real time")
    p.add_argument(
        "--publishers",
        type=count_arg,
        default=None,
        help=f"publisher processes (default: one per {VEHICLES_PER_PUBLISHER:,} vehicles)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="worker processes of the started server(s) (ingest.workers; default: its setting)",
    )
    p.add_argument("--sessions", type=int, default=8, help="Zenoh sessions per publisher")
    p.add_argument("--warmup", type=float, default=5.0, help="seconds before the window")
    p.add_argument("--replay", nargs="+", default=None, metavar="PATH", help="recordings")
    add_estimator_mix_argument(p, "default: every vehicle its kind's defaults; not with --replay")


def _add_target_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of where the result goes and which server is loaded: a running one or those
    started, with their store and shards."""
    p.add_argument("--json", type=Path, default=None, help="also write the result as JSON")
    p.add_argument("--connect", default=None, help="router endpoint of a running server")
    p.add_argument("--api", default=None, help="REST base URL of that server (with --connect)")
    add_token_argument(p)
    p.add_argument("--server-pid", type=int, default=None, help="pid for CPU/RSS (--connect)")
    p.add_argument("--storage-url", default=None, help="PostgreSQL URL for the started server")
    p.add_argument(
        "--shards",
        type=int,
        default=1,
        help="start a router and this many server processes, each owning a share of the "
        "fleet (needs --storage-url: they share one PostgreSQL database)",
    )


def _add_tuning_arguments(p: argparse.ArgumentParser) -> None:
    """The started server's ingest and storage timing flags (default: its settings)."""
    p.add_argument(
        "--lateness-ms", type=int, default=None, help="started server: ingest.lateness_ms"
    )
    p.add_argument(
        "--advance-step-ms", type=int, default=None, help="started server: ingest.advance_step_ms"
    )
    p.add_argument(
        "--estimate-interval-ms",
        type=int,
        default=None,
        help="started server: ingest.estimate_interval_ms",
    )
    p.add_argument(
        "--commit-interval-s",
        type=float,
        default=None,
        help="started server: storage.commit_interval_s",
    )


def run_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Run a load test as the command line asks (``--beside-tractors``: a tractor-only run
    first, then the two side by side); print the report; return the (last) result."""
    logging.getLogger("httpx").setLevel(logging.WARNING)
    if not args.beside_tractors:
        return _run_one(args)
    if args.replay:
        raise SystemExit("--beside-tractors compares simulated fleets: not with --replay")
    tractors = _run_one(argparse.Namespace(**{**vars(args), "mix": (("tractor", 1.0),)}))
    mixed = _run_one(args)
    print(format_side_by_side([tractors, mixed]))
    if args.json is not None:
        args.json.write_text(json.dumps([tractors, mixed], indent=2, default=str))
    return mixed


def _run_one(args: argparse.Namespace) -> dict[str, Any]:
    """One load test as the command line asks; prints its report."""
    spec = LoadSpec(
        vehicles=args.vehicles,
        duration_s=args.duration,
        scenario=args.scenario,
        rate_scale=args.rate_scale,
        publishers=args.publishers,
        sessions_per_publisher=args.sessions,
        warmup_s=args.warmup,
        replay=tuple(str(p) for p in args.replay or ()),
        estimator_mix=args.estimator_mix,
        kind_mix=args.mix,
    )
    if args.connect:
        if not args.api:
            raise SystemExit("--connect needs --api")
        pid = args.server_pid or _pid_listening_on(args.api)
        target = Target((args.connect,), (args.api.rstrip("/"),), (pid,) if pid else ())
        result = run_loadtest(spec, target, token=read_token(args.token_file))
        result["server_settings"] = "external"
    elif args.shards > 1:
        from server.tooling.shards import shard_layout, sharded_servers

        if not args.storage_url:
            raise SystemExit("--shards needs --storage-url (a PostgreSQL database they share)")
        tuning = server_tuning(args)
        filters, ids = shard_layout(args.shards)
        with sharded_servers(args.storage_url, filters, tuning) as (router, servers):
            apis = tuple(s.api for s in servers)
            target = Target((router.endpoint,), apis, tuple(s.pid for s in servers), ids)
            result = run_loadtest(spec, target)
        result["server_settings"] = {"shards": args.shards, **tuning}
    else:
        tuning = server_tuning(args)
        with local_server(tuning, args.storage_url) as server:
            target = Target((server.endpoint,), (server.api,), (server.pid,))
            result = run_loadtest(spec, target)
        result["server_settings"] = tuning or "defaults"
    print(format_report(result), flush=True)
    if args.json is not None and not args.beside_tractors:
        args.json.write_text(json.dumps(result, indent=2, default=str))
    return result


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["_publish"]:
        return _publish_child(argv[1])
    p = OneLineParser(prog="python -m server.tooling.loadtest", description=__doc__)
    add_arguments(p)
    logging.basicConfig(level=logging.INFO)
    run_from_args(p.parse_args(argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
