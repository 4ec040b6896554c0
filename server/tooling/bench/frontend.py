"""Fleet estimator cost: CPU per vehicle-second of sensor data for ``push`` and ``advance``.

``slipfleet bench frontend [--sizes 50,200,1000] [--intervals 50,100,200] [--seconds 20]
[--json PATH]`` or ``python -m server.tooling.bench.frontend``.

Feeds :class:`estimator.mdsf.MdsfFleet` (product mode) the way the server's pipeline does:
``N`` simulated ``field_work`` vehicles, measurements pushed in arrival order, ``advance`` called
every ``interval`` ms of sensor time with a horizon 150 ms behind (the reorder buffer). Only
``SOURCE_RUNS`` distinct runs are simulated; vehicle ``k`` replays run ``k mod SOURCE_RUNS``
(the estimator keeps state per vehicle, so replayed inputs cost the same as fresh ones).

For each fleet size and call interval the table prints the process CPU time spent in ``push``
and in ``advance``, in milliseconds per vehicle-second of sensor data (the first ``WARMUP_S``
seconds, before every vehicle emits, are not counted), and the rows emitted. ``advance`` is
split into the encoder wheel-speed fit (``FleetFrontEnd.fit_wheels``, i.e.
:meth:`estimator.wheel_speed.WheelBank.query`), the filter steps (``MdsfEngine.step``) and the rest
(front end, slip, output rows); the two are timed by wrapping those attributes of the fleet
under test. Target: ``advance`` ≤ 0.3 ms and ``push`` ≤ 0.1 ms per vehicle-second with 1,000
vehicles at 100 ms. Baseline in the same run (``alone ms``): every vehicle in a fleet of its own,
advanced by one call each, as a per-vehicle loop would; ``× batched`` is its cost over the
batched call's.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from estimator.base import Measurement
from estimator.config import WheeledRearDriveConfig
from estimator.mdsf import MdsfFleet
from server.tooling.bench import (
    SOURCE_START_NS,
    field_work_sources,
    int_list,
    push_until,
    write_json,
)

__all__ = ["main", "run"]

SOURCE_RUNS = 8
"""Distinct simulated runs the fleet replays."""
WARMUP_S = 2.0
"""Sensor seconds at the start that are not measured."""
LAG_MS = 150
"""Horizon of each ``advance`` behind the newest arrival (the pipeline's reorder buffer)."""
ALONE_MAX = 50
"""Vehicles run by the per-vehicle baseline (its cost per vehicle does not depend on N)."""


def measure(
    sources: Sequence[tuple[WheeledRearDriveConfig, list[tuple[int, Measurement]]]],
    n_vehicles: int,
    interval_ms: int,
    seconds: float,
) -> dict[str, float]:
    """Run one fleet; returns ``push_ms``, ``advance_ms``, its parts ``wheel_fit_ms``,
    ``engine_ms`` (per vehicle-second of sensor data) and ``rows``."""
    fleet = MdsfFleet()
    spent = {"wheel_fit": 0.0, "engine": 0.0}

    def timed(fn: Callable[..., Any], part: str) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            t0 = time.process_time()
            try:
                return fn(*args)
            finally:
                spent[part] += time.process_time() - t0

        return call

    fleet.front.fit_wheels = timed(fleet.front.fit_wheels, "wheel_fit")
    fleet.engine.step = timed(fleet.engine.step, "engine")  # type: ignore[method-assign]
    ids = [f"v{k:05d}" for k in range(n_vehicles)]
    for k, vid in enumerate(ids):
        fleet.add_vehicle(vid, sources[k % len(sources)][0])
    streams = [sources[k % len(sources)][1] for k in range(n_vehicles)]
    pos = [0] * n_vehicles
    step_ns = interval_ms * 1_000_000
    n_steps = round(seconds * 1000 / interval_ms)
    warm = round(WARMUP_S * 1000 / interval_ms)
    push_s = advance_s = 0.0
    rows = 0
    for s in range(n_steps):
        if s == warm:
            spent["wheel_fit"] = spent["engine"] = 0.0
        now = SOURCE_START_NS + (s + 1) * step_ns
        a = time.process_time()
        push_until(fleet, ids, streams, pos, now)
        b = time.process_time()
        horizon = now - LAG_MS * 1_000_000
        out = fleet.advance(dict.fromkeys(ids, horizon))
        c = time.process_time()
        if s >= warm:
            push_s += b - a
            advance_s += c - b
            rows += sum(r.shape[0] for _, r in out)
    veh_s = n_vehicles * (n_steps - warm) * interval_ms / 1000
    return {
        "push_ms": push_s / veh_s * 1e3,
        "advance_ms": advance_s / veh_s * 1e3,
        "wheel_fit_ms": spent["wheel_fit"] / veh_s * 1e3,
        "engine_ms": spent["engine"] / veh_s * 1e3,
        "rows": float(rows),
    }


def measure_alone(
    sources: Sequence[tuple[WheeledRearDriveConfig, list[tuple[int, Measurement]]]],
    n_vehicles: int,
    interval_ms: int,
    seconds: float,
) -> float:
    """The baseline: each vehicle in an ``MdsfFleet`` of its own, one ``advance`` call per
    vehicle (a per-vehicle loop); ``advance`` ms per vehicle-second of sensor data. The cost
    is linear in the vehicles, so at most ``ALONE_MAX`` of them are run."""
    n = min(n_vehicles, ALONE_MAX)
    fleets = []
    for k in range(n):
        f = MdsfFleet()
        f.add_vehicle("v", sources[k % len(sources)][0])
        fleets.append(f)
    streams = [sources[k % len(sources)][1] for k in range(n)]
    pos = [0] * n
    step_ns = interval_ms * 1_000_000
    n_steps = round(seconds * 1000 / interval_ms)
    warm = round(WARMUP_S * 1000 / interval_ms)
    advance_s = 0.0
    for s in range(n_steps):
        now = SOURCE_START_NS + (s + 1) * step_ns
        for k, f in enumerate(fleets):
            st, i = streams[k], pos[k]
            while i < len(st) and st[i][0] <= now:
                f.push("v", st[i][1])
                i += 1
            pos[k] = i
        horizon = now - LAG_MS * 1_000_000
        b = time.process_time()
        for f in fleets:
            f.advance({"v": horizon})
        if s >= warm:
            advance_s += time.process_time() - b
    return advance_s / (n * (n_steps - warm) * interval_ms / 1000) * 1e3


def run(
    json_path: Path | str | None = None,
    *,
    sizes: Sequence[int] = (50, 200, 1000),
    intervals_ms: Sequence[int] = (50, 100, 200),
    seconds: float = 20.0,
    source_runs: int = SOURCE_RUNS,
) -> dict[str, Any]:
    """Measure every (size, interval) pair, print a table; returns and optionally writes JSON."""
    sources = field_work_sources(seconds, source_runs)
    cases = []
    print(f"MdsfFleet CPU per vehicle-second of sensor data ({seconds:g} s of field_work)")
    print(
        f"{'vehicles':>8} {'interval':>9} {'push ms':>8} {'advance ms':>11} "
        f"{'wheel fit':>10} {'engine':>8} {'rest':>8} {'rows':>9} {'alone ms':>9} "
        f"{'× batched':>9}"
    )
    for n in sizes:
        for iv in intervals_ms:
            r = measure(sources, n, iv, seconds)
            r["alone_advance_ms"] = measure_alone(sources, n, iv, seconds)
            cases.append({"vehicles": n, "interval_ms": iv, **r})
            rest = r["advance_ms"] - r["wheel_fit_ms"] - r["engine_ms"]
            print(
                f"{n:>8} {iv:>6} ms {r['push_ms']:>8.3f} {r['advance_ms']:>11.3f} "
                f"{r['wheel_fit_ms']:>10.3f} {r['engine_ms']:>8.3f} {rest:>8.3f} "
                f"{int(r['rows']):>9} {r['alone_advance_ms']:>9.3f} "
                f"{r['alone_advance_ms'] / r['advance_ms']:>8.1f}x",
                flush=True,
            )
    result = {"seconds": seconds, "cases": cases}
    write_json(result, json_path)
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m server.tooling.bench.frontend [--sizes …] [--intervals …] [--seconds S]
    [--json PATH]``."""
    p = argparse.ArgumentParser(prog="python -m server.tooling.bench.frontend", description=__doc__)
    p.add_argument("--sizes", type=int_list, default=[50, 200, 1000], help="fleet sizes")
    p.add_argument(
        "--intervals", type=int_list, default=[50, 100, 200], help="advance call intervals [ms]"
    )
    p.add_argument("--seconds", type=float, default=20.0, help="sensor seconds per case")
    p.add_argument("--json", type=Path, default=None, help="write the result here")
    args = p.parse_args(argv)
    run(args.json, sizes=args.sizes, intervals_ms=args.intervals, seconds=args.seconds)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
