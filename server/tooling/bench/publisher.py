"""Load-generator cost: CPU per published packet, per-packet path against the encoded schedule.

``slipfleet bench publisher [--vehicles 100,1000,3000] [--window 10] [--json PATH]`` or
``python -m server.tooling.bench.publisher``.

For each fleet size, both paths publish the same fleet (``slipfleet loadtest``'s layout:
scenario mix, :data:`PUBLISHERS` child processes, two simulated drives per scenario shared by
the vehicles, sends spread over the 100 ms tick, real time, BLOCK congestion control) into a
Zenoh router in this process, where a bare subscriber only counts what arrives:

* **per-packet** — the load generator as it was: one thread per scenario group, eight client
  sessions per process, and per packet new measurement objects with shifted stamps, msgpack
  encoding, a heap pop and a ``put`` (:func:`_per_packet_run`, kept here as the baseline);
* **encoded** — :func:`server.tooling.fleet_sim.publish_fleets`
  (:mod:`server.tooling.fleet_schedule`): every drive encoded once, stamps patched per 100 ms
  window in bulk, one merged schedule and one thread per process, ``--sessions`` sessions per
  process.

The children simulate, encode and declare, then start publishing together; after a warm-up
(``--warmup`` s) each child measures ``--window`` seconds: its CPU (``time.process_time``:
every thread, Zenoh's included), the packets it sent, and how late each went out against its
due time (per-packet: exact; encoded: every packet of a sending round is charged the lateness
of the round's first, i.e. earliest due, packet — an upper bound). The table gives µs of CPU
per packet, cores, the sent rate against the 30 × vehicles packets/s the fleet should produce,
received/sent over the whole run (counted by the subscriber after the publishers stop),
lateness p50/p99/max, start-up (process start to ready: simulating, encoding, declaring), and
the publishers' RSS at the end of the window.

The machine's other load counts: CPU per packet grows when cores are shared, and lateness
spikes are mostly the publishers or the router waiting for a core.
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["main", "run"]

#: Publisher child processes (``slipfleet loadtest``'s default).
PUBLISHERS = 2
#: Zenoh sessions per publisher process of the per-packet path (the load test's default;
#: the encoded path uses ``--sessions``, by default the load test's).
OLD_SESSIONS = 8
PATHS = ("per-packet", "encoded")
#: Packets a vehicle sends per second with the mix scenarios (GNSS 10, IMU 10, wheels ~10).
PACKETS_PER_VEHICLE_S = 30


# ------------------------------------------------------------------------------ children


def _per_packet_publishers(sim: Any, vehicles: list[Any]) -> dict[tuple[str, Any], Any]:
    """A publisher per vehicle and stream, spread over ``sim``'s sessions, each vehicle's
    configuration put once."""
    import zenoh

    from server.protocol.codec import encode_config
    from server.protocol.keys import Stream, config_key, sensor_key
    from server.tooling.fleet_sim import _publisher

    pubs: dict[tuple[str, Stream], zenoh.Publisher] = {}
    for i, v in enumerate(vehicles):
        session = sim._sessions[i % len(sim._sessions)]
        for s in Stream:
            pubs[(v.vehicle_id, s)] = _publisher(session, sensor_key(sim._prefix, v.vehicle_id, s))
        session.put(
            config_key(sim._prefix, v.vehicle_id),
            encode_config(v.config),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
    return pubs


def _per_packet_loop(
    sim: Any,
    vehicles: list[Any],
    pubs: dict[tuple[str, Any], Any],
    stop: threading.Event,
    late: list[tuple[int, float]],
) -> None:
    """Publish each vehicle's next packet when due, one at a time, until ``stop``."""

    def due(v: Any) -> int:
        off = v.packets[v.index].arrival_offset_ns + v.phase_ns + v.loop * v.period_ns
        return int(off / sim._rate)

    wall0 = time.perf_counter_ns()
    heap = [(due(v), i) for i, v in enumerate(vehicles) if v.packets]
    heapq.heapify(heap)
    stats = sim.stats
    while heap and not stop.is_set():
        d, i = heap[0]
        now = time.perf_counter_ns() - wall0
        if d > now:
            stop.wait(min((d - now) / 1e9, 0.05))
            continue
        heapq.heappop(heap)
        late.append((now + wall0, (now - d) / 1e6))
        v = vehicles[i]
        p = v.packets[v.index]
        payload = p.encode(v.seq[p.stream], v.shift_ns + v.loop * v.period_ns)
        v.seq[p.stream] += 1
        pubs[(v.vehicle_id, p.stream)].put(payload)
        stats.packets[p.stream.value] += 1
        v.index += 1
        if v.index == len(v.packets):
            v.index = 0
            v.loop += 1
        heapq.heappush(heap, (due(v), i))


def _per_packet_run(
    sim: Any,
    stop: threading.Event,
    late: list[tuple[int, float]],
    ready: threading.Event,
    go: threading.Event,
) -> None:
    """The former ``FleetSim.run`` loop: shift, encode and publish one packet at a time.

    ``late`` gets ``(wall ns, ms late)`` for every packet; ``sim.stats`` is updated per packet.
    """
    vehicles = sim._build()
    pubs = _per_packet_publishers(sim, vehicles)
    ready.set()
    go.wait()
    anchor_ns = sim._clock()
    for v in vehicles:
        v.shift_ns += anchor_ns
    try:
        _per_packet_loop(sim, vehicles, pubs, stop, late)
    finally:
        for pub in pubs.values():
            pub.undeclare()


def _fleet_sims(sessions: list[Any], job: dict[str, Any]) -> list[Any]:
    """One looping simulated fleet per scenario group of ``job``, on ``sessions``."""
    from server.tooling.loadtest import _named_fleet_sim_class

    named = _named_fleet_sim_class()
    return [
        named(
            sessions,
            g["count"],
            scenario=g["scenario"],
            loop=True,
            seed=0,
            distinct_runs=2,
            prefix=job["prefix"],
            first_index=g["first"],
            id_format=g["id_format"],
        )
        for g in job["groups"]
    ]


class _PathThreads:
    """The publishing threads of one path over ``sims``, what they sent and how late.

    ``encoded``: one :func:`publish_fleets` thread, lateness per sending round; ``per-packet``:
    one :func:`_per_packet_run` thread per fleet, lateness per packet. ``ready`` is set once
    every thread has built its schedule; they publish after ``go``.
    """

    def __init__(
        self,
        path: str,
        sims: list[Any],
        stop: threading.Event,
        ready: threading.Event,
        go: threading.Event,
    ) -> None:
        from server.tooling.fleet_sim import SimStats, publish_fleets

        self._sims = sims
        self._late: list[tuple[int, float]] = []  # (wall ns, ms late) per packet
        self._shared = SimStats() if path == "encoded" else None
        if self._shared is not None:
            kwargs = dict(stop=stop, stats=self._shared, keep_lateness=True, ready=ready, go=go)
            self.threads = [threading.Thread(target=publish_fleets, args=(sims,), kwargs=kwargs)]
            return
        builders = [threading.Event() for _ in sims]
        self.threads = [
            threading.Thread(target=_per_packet_run, args=(sim, stop, self._late, built, go))
            for sim, built in zip(sims, builders, strict=True)
        ]

        def _all_built() -> None:
            for b in builders:
                b.wait()
            ready.set()

        threading.Thread(target=_all_built, daemon=True).start()

    def sent(self) -> int:
        """Packets sent so far."""
        if self._shared is not None:
            return int(self._shared.total_packets)
        return sum(s.stats.total_packets for s in self._sims)

    def rounds(self, t0_ns: int, t1_ns: int) -> list[tuple[int, float, int]]:
        """``(wall ns, ms late, packets)`` of the sends between ``t0_ns`` and ``t1_ns``."""
        if self._shared is not None:
            return [(w, ms, n) for w, ms, n in self._shared.send_rounds if t0_ns <= w < t1_ns]
        return [(w, ms, 1) for w, ms in self._late if t0_ns <= w < t1_ns]


def _child(job_json: str) -> int:
    """One publisher process of one path: publish, measure the window, print one JSON line."""
    import zenoh

    from server.ingest.zenoh_session import make_config
    from server.settings import ZenohSettings

    born = time.monotonic()
    job = json.loads(job_json)
    sessions = [
        zenoh.open(make_config(ZenohSettings(connect=job["endpoints"])))
        for _ in range(job["sessions"])
    ]
    stop, ready, go = threading.Event(), threading.Event(), threading.Event()
    run = _PathThreads(job["path"], _fleet_sims(sessions, job), stop, ready, go)
    for t in run.threads:
        t.start()
    ready.wait()
    startup_s = time.monotonic() - born
    print(json.dumps({"ready": startup_s}), flush=True)
    sys.stdin.readline()  # "go": every publisher is ready
    go.set()
    while run.sent() == 0:
        time.sleep(0.01)
    time.sleep(job["warmup_s"])
    out = _measure_window(run, job["window_s"])
    stop.set()
    for t in run.threads:
        t.join(30)
    out["lateness"] = _weighted_quantiles(run.rounds(out.pop("t0_ns"), out.pop("t1_ns")))
    time.sleep(0.5)  # let the sessions flush before closing
    for s in sessions:
        s.close()
    out.update(startup_s=startup_s, sent_total=run.sent())
    print(json.dumps(out), flush=True)
    return 0


def _measure_window(run: _PathThreads, window_s: float) -> dict[str, Any]:
    """CPU, packets sent, RSS and per-thread CPU over ``window_s`` of publishing (the window's
    wall-clock edges as ``t0_ns``/``t1_ns``)."""
    cpu0, sent0, t0 = time.process_time(), run.sent(), time.perf_counter_ns()
    threads0 = _thread_cpu()
    time.sleep(window_s)
    cpu1, sent1, t1 = time.process_time(), run.sent(), time.perf_counter_ns()
    threads1 = _thread_cpu()
    return {
        "window_s": (t1 - t0) / 1e9,
        "cpu_s": cpu1 - cpu0,
        "sent_window": sent1 - sent0,
        "rss_bytes": _rss_bytes(),
        "cpu_s_by_thread": {
            k: round(v - threads0.get(k, 0.0), 3) for k, v in sorted(threads1.items())
        },
        "t0_ns": t0,
        "t1_ns": t1,
    }


def _thread_cpu() -> dict[str, float]:
    """CPU seconds per thread name (``python``: the interpreter's threads; ``tx-*``, ``rx-*``,
    ``net-*``, ``app-*``: Zenoh's runtime), Linux only (empty elsewhere)."""
    import psutil

    out: dict[str, float] = {}
    for t in psutil.Process().threads():
        try:
            name = Path(f"/proc/self/task/{t.id}/comm").read_text().strip()
        except OSError:
            continue
        out[name] = out.get(name, 0.0) + t.user_time + t.system_time
    return out


def _rss_bytes() -> int:
    import psutil

    return int(psutil.Process().memory_info().rss)


def _weighted_quantiles(rounds: Sequence[tuple[int, float, int]]) -> dict[str, float]:
    """p50/p99/max (ms) of lateness, each round's value counted once per packet it sent."""
    from server.tooling.fleet_schedule import weighted_quantiles

    q = weighted_quantiles([r[1] for r in rounds], [r[2] for r in rounds], (0.5, 0.99, 1.0))
    p50, p99, top = q if q is not None else (float("nan"),) * 3
    return {"p50_ms": p50, "p99_ms": p99, "max_ms": top}


# ------------------------------------------------------------------------------ the parent


@dataclasses.dataclass
class _Counter:
    """A bare subscriber's count (a callback: one integer add per sample on Zenoh's thread)."""

    n: int = 0

    def __call__(self, _sample: object) -> None:
        self.n += 1


def _start_children(
    endpoint: str, vehicles: int, path: str, prefix: str, args: argparse.Namespace
) -> list[subprocess.Popen[str]]:
    """One publisher child process per group of the load test's assignment, not yet going."""
    from server.tooling.loadtest import LoadSpec, assignments

    spec = LoadSpec(vehicles=vehicles, duration_s=args.window, publishers=PUBLISHERS)
    procs = []
    for groups in assignments(spec, ("sim-{:05d}",)):
        job = {
            "endpoints": [endpoint],
            "sessions": args.sessions if path == "encoded" else OLD_SESSIONS,
            "groups": groups,
            "prefix": prefix,
            "path": path,
            "warmup_s": args.warmup,
            "window_s": args.window,
        }
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "server.tooling.bench.publisher", "_child", json.dumps(job)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
        )
    return procs


def _go_and_collect(procs: list[subprocess.Popen[str]]) -> list[dict[str, Any]]:
    """Start the children publishing together, once every one has simulated and encoded; the
    last JSON line each prints."""
    for p in procs:
        assert p.stdout is not None
        if "ready" not in json.loads(p.stdout.readline() or "{}"):
            raise RuntimeError("publisher child failed while starting")
    for p in procs:
        assert p.stdin is not None
        p.stdin.write("go\n")
        p.stdin.flush()
    outs = []
    for p in procs:
        stdout, _ = p.communicate(timeout=600)
        if p.returncode != 0:
            raise RuntimeError(f"publisher child exited with {p.returncode}")
        outs.append(json.loads(stdout.strip().splitlines()[-1]))
    return outs


def _one_row(
    vehicles: int, path: str, args: argparse.Namespace, outs: list[dict[str, Any]], received: int
) -> dict[str, Any]:
    """One table row from the children's reports and the packets the router received."""
    sent = sum(o["sent_total"] for o in outs)
    window = max(o["window_s"] for o in outs)
    cpu = sum(o["cpu_s"] for o in outs)
    sent_w = sum(o["sent_window"] for o in outs)
    lat = [o["lateness"] for o in outs]
    return {
        "vehicles": vehicles,
        "path": path,
        "sessions_per_process": args.sessions if path == "encoded" else OLD_SESSIONS,
        "processes": len(outs),
        "sent_per_s": sent_w / window,
        "target_per_s": PACKETS_PER_VEHICLE_S * vehicles,
        "us_per_packet": 1e6 * cpu / max(sent_w, 1),
        "cores": cpu / window,
        "sent": sent,
        "received": received,
        "received_over_sent": received / max(sent, 1),
        "late_p50_ms": max(x["p50_ms"] for x in lat),
        "late_p99_ms": max(x["p99_ms"] for x in lat),
        "late_max_ms": max(x["max_ms"] for x in lat),
        "startup_s": max(o["startup_s"] for o in outs),
        "rss_mb": sum(o["rss_bytes"] for o in outs) / 2**20,
        "cpu_s_by_thread": [o["cpu_s_by_thread"] for o in outs],
    }


def _one(router: Any, endpoint: str, vehicles: int, path: str, args: argparse.Namespace) -> dict:
    """One fleet size on one path: the children publish, the router counts what arrives."""
    import zenoh

    prefix = f"bench-{path}-{vehicles}"
    counter = _Counter()
    sub = router.declare_subscriber(zenoh.KeyExpr(prefix).join("*/sensors/*"), counter)
    procs = _start_children(endpoint, vehicles, path, prefix, args)
    outs = _go_and_collect(procs)
    sent = sum(o["sent_total"] for o in outs)
    deadline = time.monotonic() + 10
    while counter.n < sent and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)  # anything beyond what was sent would show as a ratio > 1
    sub.undeclare()
    return _one_row(vehicles, path, args, outs, counter.n)


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Every fleet size, both paths, one router; rows as dicts."""
    import zenoh

    from server.ingest.zenoh_session import make_config
    from server.settings import ZenohSettings
    from server.tooling.ports import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rows = []
    with zenoh.open(make_config(ZenohSettings(listen=[endpoint]))) as router:
        for n in args.vehicles:
            for path in args.paths:
                row = _one(router, endpoint, n, path, args)
                rows.append(row)
                print(_format_row(row), flush=True)
    return rows


_HEADER = (
    f"{'vehicles':>8} {'path':<10} {'sent/s':>8} {'target/s':>8} {'recv/sent':>9} "
    f"{'µs/pkt':>7} {'cores':>6} {'late p50':>8} {'p99':>7} {'max ms':>7} "
    f"{'start s':>7} {'RSS MB':>7}"
)


def _format_row(r: dict[str, Any]) -> str:
    return (
        f"{r['vehicles']:>8} {r['path']:<10} {r['sent_per_s']:>8.0f} {r['target_per_s']:>8} "
        f"{r['received_over_sent']:>9.4f} {r['us_per_packet']:>7.1f} {r['cores']:>6.3f} "
        f"{r['late_p50_ms']:>8.1f} {r['late_p99_ms']:>7.1f} {r['late_max_ms']:>7.1f} "
        f"{r['startup_s']:>7.1f} {r['rss_mb']:>7.0f}"
    )


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    lines = [_HEADER]
    lines += [_format_row(r) for r in rows]
    by = {(r["vehicles"], r["path"]): r for r in rows}
    for n in sorted({r["vehicles"] for r in rows}):
        old, new = by.get((n, "per-packet")), by.get((n, "encoded"))
        if old and new:
            lines.append(
                f"{n:>8} vehicles: encoded path {old['us_per_packet'] / new['us_per_packet']:.1f}"
                f"× less CPU per packet"
            )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from server.tooling.loadtest import LoadSpec

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["_child"]:
        return _child(argv[1])
    p = argparse.ArgumentParser(prog="slipfleet bench publisher", description=__doc__)
    p.add_argument("--vehicles", default="100,1000,3000", help="comma-separated fleet sizes")
    p.add_argument("--paths", default=",".join(PATHS), help="per-packet,encoded")
    p.add_argument("--warmup", type=float, default=3.0, help="s after each child's first packet")
    p.add_argument("--window", type=float, default=10.0, help="measured seconds")
    p.add_argument(
        "--sessions",
        type=int,
        default=LoadSpec.sessions_per_publisher,
        help="Zenoh sessions per process, encoded path (the per-packet path keeps 8)",
    )
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    args.sessions = max(1, args.sessions)
    args.vehicles = [int(x) for x in args.vehicles.split(",")]
    args.paths = [x for x in args.paths.split(",") if x]
    if unknown := set(args.paths) - set(PATHS):
        p.error(f"unknown path(s) {sorted(unknown)}")
    print(
        f"publisher CPU per packet, {PUBLISHERS} processes, {os.cpu_count()} CPUs; "
        f"window {args.window} s after {args.warmup} s warm-up\n{_HEADER}",
        flush=True,
    )
    rows = run(args)
    print("\n" + format_table(rows))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
