"""Server CPU per vehicle-second with Zenoh left out: decode, reorder, estimate, sinks.

``slipfleet bench pipeline [--vehicles 300,1000] [--seconds 20] [--baseline REV]
[--repeats 2] [--json PATH]`` or ``python -m server.tooling.bench.pipeline``.

What one server process does with a fleet's packets once Zenoh has handed them over, timed
stage by stage at real-time pace: ``N`` simulated vehicles (the load test's ``mix`` of
scenarios, encoded once and stamp-patched like :mod:`server.tooling.fleet_schedule`, tick phases
spread evenly) arrive as the ingest thread would take them, one burst every ``GATHER_MS``; each
burst is decoded (``decode_burst``) and offered to a :class:`~server.ingest.pipeline.Pipeline`
(no Zenoh session) whose clocks are the simulated time, which ticks every
``ingest.process_interval_ms`` and hands its rows to the server's sinks (store writer on a
SQLite file in a temporary directory, live hub, alerts, latency probe). The loop sleeps so that
simulated time runs no faster than the wall clock, so the writer commits as often as in the
server; when the machine cannot keep up it simply runs behind.

Reported per fleet size, in CPU µs per vehicle-second of sensor time (thread CPU time of the
loop for ``decode``, ``offer`` — reorder buffers and counters — and ``tick`` — release, push,
estimator calls, sinks; ``writer`` is the rest of the process's CPU, mostly the writer thread),
and ``total``, the process CPU per vehicle-second; ``cores at real time`` is ``total`` times the
fleet size. The first ``WARMUP_S`` seconds are not measured.

``--baseline REV`` runs the same loop on the ``estimator/`` and ``server/`` packages of git
revision ``REV`` (extracted to a temporary directory; this file runs as a script in a child
process whose path puts them first), alternating with the working tree ``--repeats`` times;
each case keeps its least total. ``after/before`` is the ratio of the totals.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["main", "measure", "run"]

GATHER_MS = 5
"""Simulated time between two bursts handed to the pipeline (the ingest thread's gather)."""
WARMUP_S = 3.0
"""Sensor seconds at the start that are not measured."""
START_NS = 1_800_000_000_000_000_000
"""Simulated UTC time of the start (stamps and the pipeline's clocks follow it)."""
STAGES = ("decode", "offer", "tick", "writer")
TICK_PHASES = ("release", "estimate", "deliver")
"""The tick's parts as the pipeline counts them (``Pipeline.PHASES``): reorder releases and
pushes to the estimators' buffers, the estimator calls, the sinks."""
_REPO = Path(__file__).resolve().parents[3]


class _Collect:
    """Stands in for a vehicle's publisher on one stream: keeps ``(key, payload)``."""

    __slots__ = ("key", "out")

    def __init__(self, key: str, out: list[tuple[str, bytes]]) -> None:
        self.key = key
        self.out = out

    def __call__(self, payload: bytes) -> None:
        self.out.append((self.key, payload))


def _replayed_fleet(ids: list[str], received: list[tuple[str, bytes]]) -> tuple[list[Any], Any]:
    """The load test's simulated runs and a schedule replaying them for ``ids`` (phases spread
    over a tick), its packets collected into ``received`` as ``(key, payload)``."""
    from estimator.sim import simulate
    from server.protocol.keys import sensor_key
    from server.tooling.fleet_schedule import STREAMS, EncodedDrive, ScheduledVehicle, _Fleet
    from server.tooling.fleet_sim import TICK_NS, packetize
    from server.tooling.loadtest import MIX

    runs = [simulate(s, seed=k + 1, start_ns=START_NS) for k, s in enumerate(MIX)]
    drives = [
        EncodedDrive(packetize(r.sent_in_arrival_order(), r.start_ns), r.end_ns - r.start_ns)
        for r in runs
    ]
    n = len(ids)
    schedule = [
        ScheduledVehicle(
            drive=i % len(runs),
            phase_ns=(i * TICK_NS) // n,
            shift_ns=(i * TICK_NS) // n,
            publishers=tuple(_Collect(sensor_key("fleet", vid, s), received) for s in STREAMS),
        )
        for i, vid in enumerate(ids)
    ]
    return runs, _Fleet(drives, schedule)


@dataclasses.dataclass
class _Meter:
    """The measured part's CPU counters: seconds per stage, the load generator's share, and
    the process and thread CPU and the pipeline's stats where measuring started."""

    stats0: dict[str, Any]
    spent: dict[str, float] = dataclasses.field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    generate: float = 0.0
    proc0: float = 0.0
    thread0: float = 0.0

    def restart(self, pipeline: Any) -> None:
        """Start measuring here (the warm-up is over)."""
        self.proc0, self.thread0 = time.process_time(), time.thread_time()
        self.spent = dict.fromkeys(STAGES, 0.0)
        self.generate = 0.0
        self.stats0 = pipeline.stats()


def _pipeline(
    settings: Any, runs: list[Any], ids: list[str], writer: Any, latency: Any, clock: Any
) -> Any:
    """A :class:`~server.ingest.pipeline.Pipeline` without Zenoh on the simulated clock, the
    server's sinks behind it and every vehicle registered with its run's configuration."""
    from server.analytics.alerts import AlertEngine
    from server.estimation.registry import EstimatorRegistry
    from server.ingest.pipeline import Pipeline
    from server.live.hub import LiveHub

    run_configs = [dataclasses.replace(r.config, noise=r.sensor_noise) for r in runs]
    configs = {vid: run_configs[i % len(runs)] for i, vid in enumerate(ids)}
    alerts = AlertEngine(slip_config_for=lambda vid: configs[vid].slip, clock_ns=clock)
    pipeline = Pipeline(
        settings,
        None,
        EstimatorRegistry(),
        sinks=[writer, LiveHub(), alerts, latency],
        clock_ns=clock,
        wall_clock_ns=clock,
    )
    for vid, config in configs.items():
        pipeline.register_vehicle(vid, config)
    pipeline._apply_control()  # what the pipeline thread does first
    return pipeline


def _render(fleet: Any, start_ns: int, gather_ns: int) -> None:
    """The fleet's packets of one gather window, collected by its publishers."""
    from server.tooling.fleet_schedule import render

    window = render(fleet, start_ns, start_ns + gather_ns, loop=True)
    for call, payload in zip(window.calls, window.payloads, strict=True):
        call(payload)


def _pace(step: int, wall0: float) -> None:
    """Sleep until the wall clock reaches the simulated time after ``step``."""
    ahead = (step + 1) * GATHER_MS / 1000 - (time.perf_counter() - wall0)
    if ahead > 0:
        time.sleep(ahead)


def _loop(
    pipeline: Any,
    fleet: Any,
    received: list[tuple[str, bytes]],
    sim_ns: list[int],
    seconds: float,
    paced: bool,
    tick_every: int,
) -> _Meter:
    """One burst every ``GATHER_MS`` of simulated time for ``seconds``, measured after the
    warm-up: decoded, offered and ticked when due, each timed in thread CPU; the load
    generator's share (rendering the packets) counted apart. Left whole: no call added per
    burst to the part measured."""
    from server.protocol.burst import decode_burst

    meter = _Meter(pipeline.stats())
    gather_ns = GATHER_MS * 1_000_000
    warm = round(WARMUP_S * 1000 / GATHER_MS)
    wall0 = time.perf_counter()
    for step in range(round(seconds * 1000 / GATHER_MS)):
        if step == warm:
            meter.restart(pipeline)
        r0 = time.thread_time()
        received.clear()
        _render(fleet, step * gather_ns, gather_ns)
        sim_ns[0] = START_NS + (step + 1) * gather_ns
        meter.generate += time.thread_time() - r0
        if paced:
            _pace(step, wall0)
        t0 = time.thread_time()
        items = decode_burst(received, prefix="fleet")
        t1 = time.thread_time()
        pipeline._handle(items, sim_ns[0])
        t2 = time.thread_time()
        if step % tick_every == tick_every - 1:
            pipeline._tick(sim_ns[0], flush=False)
        t3 = time.thread_time()
        spent = meter.spent
        spent["decode"] += t1 - t0
        spent["offer"] += t2 - t1
        spent["tick"] += t3 - t2
    return meter


def measure(vehicles: int, seconds: float, paced: bool = True) -> dict[str, Any]:
    """Run one fleet of ``vehicles`` for ``seconds`` of sensor time; CPU seconds per stage.

    Uses whichever ``server`` and ``estimator`` packages this interpreter imports (the baseline's
    in a child process). Returns ``{"vehicles", "seconds", "rows", <stage>_s…, "total_s"}``.
    """
    from server.gc_policy import settle
    from server.metrics.latency import LatencyProbe
    from server.settings import Settings
    from server.storage import open_store
    from server.storage.writer import StoreWriter

    received: list[tuple[str, bytes]] = []
    ids = [f"b{i:05d}" for i in range(vehicles)]
    runs, fleet = _replayed_fleet(ids, received)
    sim_ns = [START_NS]

    def clock() -> int:
        return sim_ns[0]

    with tempfile.TemporaryDirectory() as data_dir:
        settings = Settings(storage={"data_dir": data_dir}, viewer={"enabled": False})
        store = open_store(settings.storage)
        latency = LatencyProbe()
        writer = StoreWriter(latency.wrap_store(store), settings.storage).start()
        pipeline = _pipeline(settings, runs, ids, writer, latency, clock)
        settle(settings.ingest.gc_gen0)  # as a server or worker process does once started
        tick_every = settings.ingest.process_interval_ms // GATHER_MS
        try:
            meter = _loop(pipeline, fleet, received, sim_ns, seconds, paced, tick_every)
            writer.flush(timeout=60.0)
            # the load generator's share (rendering the packets) is not the server's
            total = time.process_time() - meter.proc0 - meter.generate
            meter.spent["writer"] = total - (time.thread_time() - meter.thread0 - meter.generate)
        finally:
            writer.close()
            store.close()
    return _result(vehicles, seconds - WARMUP_S, pipeline.stats(), meter, total)


def _result(
    vehicles: int, measured_s: float, stats: dict[str, Any], meter: _Meter, total: float
) -> dict[str, Any]:
    """:func:`measure`'s numbers: rows and CPU seconds per stage and tick phase."""
    stats0 = meter.stats0
    return {
        "vehicles": vehicles,
        "seconds": measured_s,
        "rows": stats["rows"] - stats0["rows"],
        **{f"{k}_s": v for k, v in meter.spent.items()},
        **{f"{k}_s": stats[f"cpu_{k}_s"] - stats0[f"cpu_{k}_s"] for k in TICK_PHASES},
        "total_s": total,
    }


def _child(path: str, vehicles: int, seconds: float) -> dict[str, Any]:
    """:func:`measure` in a fresh interpreter whose packages come from ``path``."""
    from server.tooling.bench import json_from_child, script_of  # the child runs this file

    args = [script_of(path, "pipeline"), "--child"]
    args += ["--vehicles", str(vehicles), "--seconds", str(seconds)]
    return json_from_child(path, args)


def _per_vehicle_second_us(case: dict[str, Any]) -> dict[str, float]:
    """Each stage's and tick phase's CPU in µs a vehicle-second (a baseline whose bench
    did not count the tick's phases has none)."""
    scale = 1e6 / (case["vehicles"] * case["seconds"])
    names = (*STAGES, *TICK_PHASES, "total")
    return {k: case[f"{k}_s"] * scale for k in names if f"{k}_s" in case}


def run(
    sizes: Sequence[int],
    seconds: float,
    *,
    baseline: str | None = None,
    repeats: int = 2,
    json_path: Path | str | None = None,
) -> dict[str, Any]:
    """Measure each size (and the baseline's); print the table; return the numbers."""
    from server.tooling.bench import side_by_side, write_json

    def per_vehicle_second(n: int, path: str) -> dict[str, Any]:
        got = _child(path, vehicles=n, seconds=seconds)
        return {**_per_vehicle_second_us(got), "rows": got["rows"]}

    cases = side_by_side(
        baseline, repeats if baseline else 1, "vehicles", sizes, per_vehicle_second
    )
    result = {"seconds": seconds, "baseline": baseline, "cases": cases}
    print(format_table(result))
    write_json(result, json_path)
    return result


def format_table(result: dict[str, Any]) -> str:
    """The CPU table: µs per vehicle-second by stage, and cores at real time."""
    head = "| vehicles | version | " + " | ".join(STAGES) + " | total | cores at real time |"
    head += " tick: " + " / ".join(TICK_PHASES) + " |"
    lines = [
        f"Server CPU per vehicle-second, µs "
        f"({result['seconds'] - WARMUP_S:g} s of sensor time measured)",
        head,
        "|" + " --- |" * (len(STAGES) + 5),
    ]
    for case in result["cases"]:
        for name in ("before", "after"):
            if name not in case:
                continue
            c = case[name]
            label = f"{name} ({result['baseline']})" if name == "before" else "working tree"
            cells = " | ".join(f"{c[k]:.0f}" for k in STAGES)
            cores = c["total"] * case["vehicles"] / 1e6
            phases = " / ".join(f"{c[k]:.0f}" for k in TICK_PHASES if k in c)
            lines.append(
                f"| {case['vehicles']:,} | {label} | {cells} | {c['total']:.0f} | {cores:.2f} "
                f"| {phases} |"
            )
        if "after_over_before" in case:
            lines.append(
                f"| {case['vehicles']:,} | after/before | | | | | "
                f"{case['after_over_before']:.2f} | | |"
            )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from server.tooling.bench import int_list, revision

    p = argparse.ArgumentParser(
        prog="slipfleet bench pipeline", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--vehicles", type=int_list, default=[300, 1000])
    p.add_argument("--seconds", type=float, default=20.0, help="sensor seconds per run")
    p.add_argument("--baseline", type=revision, default=None, help="git revision to compare with")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--json", default=None)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.vehicles[0], args.seconds)))
        return 0
    run(
        args.vehicles,
        args.seconds,
        baseline=args.baseline,
        repeats=args.repeats,
        json_path=args.json,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
