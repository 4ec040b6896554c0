"""Cost of one batched fleet step: CPU per ``advance`` call and per vehicle-tick, for the
MDSF, tracked and friction estimators side by side.

``slipfleet bench advance [--sizes 100,300,1000] [--estimators mdsf,tracked,friction]
[--baseline REV [--interleave]] [--repeats 3] [--seconds 6] [--json PATH]`` or
``python -m server.tooling.bench.advance``.

The server's pipeline calls ``advance`` every ``ingest.estimate_interval_ms`` (50) for every
vehicle, each vehicle's ticks on its own phase (its first IMU batch), so a call steps about
half the fleet. This bench does the same for each estimator (:data:`ESTIMATORS`): ``N``
simulated vehicles of its kind (``N mod SOURCE_RUNS`` replays of a few runs, as
:mod:`server.tooling.bench.frontend`: MDSF ``field_work`` drives, tracked random crawler
routes, friction ``steer_mu08`` runs of the steered four-wheel simulator) with tick phases
spread evenly over the tick, measurements pushed in arrival order, ``advance`` every ``INTERVAL_MS``
of sensor time with a horizon ``LAG_MS`` behind. Only ``advance`` is timed (process CPU time),
after ``WARMUP_S`` seconds of sensor time.

Each estimator keeps its own tick (MDSF and tracked 0.1 s, friction 0.02 s), so its
ticks per call differ; the same fleet sizes are measured for each. Per estimator and size the
table gives the CPU per call [ms] and per vehicle-tick (emitted row) [µs],
and a straight line ``fixed + per_tick × ticks`` through the per-call costs of all sizes.

``--baseline REV`` measures the estimator package of git revision ``REV`` side by side: its
``estimator/`` is extracted to a temporary directory and each version runs in a child process
(the same modules cannot be imported twice under one name, and measurements are checked
with ``isinstance`` against their own package's types); the two alternate, ``--repeats``
times (a revision without one of the estimators cannot be measured for it), and each case
keeps its fastest repeat, so a machine shared with other work slows both alike.
``after/before`` is the ratio of the costs. Each child also hashes every row it emitted: the
table says whether both versions gave the same bytes.

``--interleave`` (with ``--baseline``) runs both versions in this process instead: the
revision's ``estimator/`` is loaded under a private name (:mod:`server.tooling.bench.renamed`),
the same fleet is built for both (this tree's simulated runs, rebuilt alike as each version's
types), and at every step both ``advance`` calls run back to back, before then after or
after then before (Thue-Morse: each order once in every pair of steps, and equally often at
each step of any period of 2, 4, 8… steps, such as the 0.1 s tick's two calls). Each
version's process CPU time (not the thread's: numpy may work on threads of its own) is
summed over its calls after the warm-up and over ``--repeats`` passes, and every call's rows
are compared byte for byte; an estimator the revision lacks is skipped with a line saying
so. Whatever else loads the machine then falls on both versions within milliseconds of each
other, call by call and in either order, rather than on whole child runs seconds apart, so
the ratio is far quieter on a shared machine.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from server.tooling.bench import (
    SOURCE_START_NS,
    extract_revision,
    field_work_sources,
    int_list,
    json_from_child,
    push_until,
    revision,
    write_json,
)
from server.tooling.bench.renamed import renamed_estimator, to_package

__all__ = ["main", "measure", "run"]

SOURCE_RUNS = 8
"""Distinct simulated runs the fleet replays (MDSF)."""
SIMULATED_RUNS = 2
"""At most this many distinct runs for the tracked and friction fleets: their simulators take
seconds per run (a whole crawler route; the four-wheel dynamics), and cost per tick does not
depend on which run a vehicle replays."""
INTERVAL_MS = 50
"""Sensor time between ``advance`` calls (the pipeline's ``estimate_interval_ms``)."""
LAG_MS = 150
"""Horizon of each ``advance`` behind the newest arrival (the pipeline's reorder buffer)."""
WARMUP_S = 2.0
"""Sensor seconds at the start that are not measured."""
_REPO = Path(__file__).resolve().parents[3]


ESTIMATORS = ("mdsf", "tracked", "friction")
"""Estimators the bench knows, in the order it prints them."""


def _mdsf_fleet(package: str = "estimator") -> Any:
    try:
        fleet = importlib.import_module(f"{package}.mdsf").MdsfFleet
    except ImportError:  # a --baseline revision from before the estimator.mdsf package
        fleet = importlib.import_module(f"{package}.engine").MdsfFleet
    return fleet()


def _tracked_sources(seconds: float, runs: int) -> list[tuple[Any, list[Any]]]:
    """Random crawler routes (seeds 1…, at most :data:`SIMULATED_RUNS`), each
    ``(config, (key_ns, m) in order)``."""
    from estimator.sim.tracked import simulate_tracked

    out = []
    for k in range(min(runs, SIMULATED_RUNS)):
        sim = simulate_tracked("random", k + 1, start_ns=SOURCE_START_NS)
        if sim.truth.t_s[-1] < seconds + 1.0:
            raise ValueError(f"random crawler route {k + 1} shorter than {seconds} s")
        out.append((sim.config, sim.measurements))
    return out


def _friction_sources(seconds: float, runs: int) -> list[tuple[Any, list[Any]]]:
    """``steer_mu08`` runs (seeds 1…, at most :data:`SIMULATED_RUNS`), keyed by each packet's
    last stamp."""
    from estimator.sim.four_wheel import NAMED, simulate_four_wheel

    manoeuvre = NAMED["steer_mu08"]
    if manoeuvre.duration_s < seconds + 1.0:
        raise ValueError(f"steer_mu08 runs {manoeuvre.duration_s:.0f} s, less than {seconds} s")
    n = min(runs, SIMULATED_RUNS)
    sims = simulate_four_wheel([manoeuvre] * n, list(range(1, n + 1)), None, SOURCE_START_NS)
    out = []
    for sim in sims:
        keys = [int(np.atleast_1d(m.stamp_ns)[-1]) for m in sim.measurements]
        keyed = sorted(zip(keys, sim.measurements, strict=True), key=lambda km: km[0])
        out.append((sim.config, keyed))
    return out


def _fleet(name: str, package: str = "estimator") -> tuple[Any, int]:
    """A new fleet of estimator ``name`` and its tick in ns, from ``package`` (imported here,
    so a child measuring another revision gets that revision's; or a renamed ``estimator``,
    :mod:`server.tooling.bench.renamed`)."""
    if name == "mdsf":
        mdsf = _mdsf_fleet(package)
        return mdsf, mdsf.config.tick_ns
    if name == "tracked":
        tracked = importlib.import_module(f"{package}.tracked").TrackedFleet()
        return tracked, tracked.config.tick_ns
    if name == "friction":
        friction = importlib.import_module(f"{package}.friction").FrictionFleet()
        return friction, round(friction.config.filter.tick_s * 1e9)
    raise ValueError(f"unknown estimator {name!r}; known: {', '.join(ESTIMATORS)}")


_SOURCES = {
    "mdsf": field_work_sources,
    "tracked": _tracked_sources,
    "friction": _friction_sources,
}


def measure(
    sizes: Sequence[int], seconds: float, source_runs: int = SOURCE_RUNS, estimator: str = "mdsf"
) -> dict[str, Any]:
    """Run one fleet of ``estimator`` (:data:`ESTIMATORS`) per size with the ``estimator``
    package this interpreter imports.

    Returns ``{"cases": [{vehicles, calls, ticks, advance_s}], "digest": sha256 of the rows}``.
    """
    _fleet(estimator)  # an unknown name fails before any simulation
    sources = _SOURCES[estimator](seconds, source_runs)
    digest = hashlib.sha256()
    cases = []
    for n in sizes:
        fleet, tick_ns = _fleet(estimator)
        cases.append(_one_size(fleet, tick_ns, sources, n, seconds, digest))
    return {"cases": cases, "digest": digest.hexdigest()}


def _add_fleet(fleet: Any, tick_ns: int, sources: list[Any], ids: Sequence[str]) -> list[Any]:
    """Vehicles ``ids`` added to ``fleet``, replaying ``sources`` in turn, tick phases spread
    over the tick; each vehicle's ``(arrival_ns, measurement)`` stream."""
    n, source_runs = len(ids), len(sources)
    for k, vid in enumerate(ids):
        fleet.add_vehicle(vid, sources[k % source_runs][0])
        fleet.align_ticks(vid, SOURCE_START_NS + k * tick_ns // n)
    return [sources[k % source_runs][1] for k in range(n)]


def _one_size(
    fleet: Any, tick_ns: int, sources: list[Any], n: int, seconds: float, digest: Any
) -> dict[str, Any]:
    """``n`` vehicles replaying ``sources`` through ``fleet``; the CPU of its ``advance``."""
    ids = [f"v{k:05d}" for k in range(n)]
    streams = _add_fleet(fleet, tick_ns, sources, ids)
    pos = [0] * n
    step_ns = INTERVAL_MS * 1_000_000
    warm = round(WARMUP_S * 1000 / INTERVAL_MS)
    spent = 0.0
    calls = ticks = 0
    for s in range(round(seconds * 1000 / INTERVAL_MS)):
        now = SOURCE_START_NS + (s + 1) * step_ns
        push_until(fleet, ids, streams, pos, now)
        horizon = dict.fromkeys(ids, now - LAG_MS * 1_000_000)
        t0 = time.process_time()
        out = fleet.advance(horizon)
        t1 = time.process_time()
        for vid, rows in out:
            digest.update(vid.encode())
            digest.update(rows.tobytes())
        if s >= warm:
            spent += t1 - t0
            calls += 1
            ticks += sum(r.shape[0] for _, r in out)
    return {"vehicles": n, "calls": calls, "ticks": ticks, "advance_s": spent}


def _same_rows(a: Sequence[tuple[str, Any]], b: Sequence[tuple[str, Any]]) -> bool:
    """Whether two ``advance`` results hold the same vehicles' rows, byte for byte."""
    return len(a) == len(b) and all(
        va == vb and ra.dtype == rb.dtype and ra.tobytes() == rb.tobytes()
        for (va, ra), (vb, rb) in zip(a, b, strict=True)
    )


def _interleaved_size(
    fleets: dict[str, tuple[Any, int]], sources: dict[str, list[Any]], n: int, seconds: float
) -> tuple[dict[str, dict[str, Any]], bool]:
    """``n`` vehicles replaying the same runs through both ``fleets`` (``"before"``,
    ``"after"``), their ``advance`` called in turn at every step, before first where the
    step's number has an even count of one bits (Thue-Morse), after first elsewhere; per
    version the CPU of its calls after the warm-up, and whether every call gave both the
    same rows."""
    ids = [f"v{k:05d}" for k in range(n)]
    streams = {v: _add_fleet(f, tick, sources[v], ids) for v, (f, tick) in fleets.items()}
    pos = {v: [0] * n for v in fleets}
    spent = dict.fromkeys(fleets, 0.0)
    ticks = dict.fromkeys(fleets, 0)
    warm = round(WARMUP_S * 1000 / INTERVAL_MS)
    calls, same = 0, True
    for s in range(round(seconds * 1000 / INTERVAL_MS)):
        now = SOURCE_START_NS + (s + 1) * INTERVAL_MS * 1_000_000
        out = {}
        for v in list(fleets) if s.bit_count() % 2 == 0 else list(reversed(fleets)):
            fleet = fleets[v][0]
            push_until(fleet, ids, streams[v], pos[v], now)
            horizon = dict.fromkeys(ids, now - LAG_MS * 1_000_000)
            t0 = time.process_time()
            out[v] = fleet.advance(horizon)
            t1 = time.process_time()
            if s >= warm:
                spent[v] += t1 - t0
                ticks[v] += sum(r.shape[0] for _, r in out[v])
        calls += s >= warm
        same = same and _same_rows(out["before"], out["after"])
    cases = {
        v: {"vehicles": n, "calls": calls, "ticks": ticks[v], "advance_s": spent[v]} for v in fleets
    }
    return cases, same


def _interleaved_of(
    estimator: str,
    package: str,
    sizes: Sequence[int],
    seconds: float,
    repeats: int,
    source_runs: int,
) -> dict[str, Any] | None:
    """One estimator of ``package`` (the baseline, renamed) and of this tree in one process,
    calls interleaved (:func:`_interleaved_size`), CPU summed over ``repeats`` passes of new
    fleets; None when ``package`` lacks the estimator."""
    try:
        _fleet(estimator, package)
    except ModuleNotFoundError as exc:
        if not (exc.name or "").startswith(package + "."):
            raise
        return None
    sources = _SOURCES[estimator](seconds, source_runs)
    # both rebuilt alike: a run's arrays may be views into the simulator's, their copies not
    versions = {v: to_package(sources, p) for v, p in (("before", package), ("after", "estimator"))}
    cases: dict[str, list[dict[str, Any]]] = {v: [] for v in versions}
    same = True
    for n in sizes:
        total = {v: {"vehicles": n, "calls": 0, "ticks": 0, "advance_s": 0.0} for v in versions}
        for _ in range(repeats):
            fleets = {"before": _fleet(estimator, package), "after": _fleet(estimator)}
            got, same_here = _interleaved_size(fleets, versions, n, seconds)
            same = same and same_here
            for v, c in got.items():
                for key in ("calls", "ticks", "advance_s"):
                    total[v][key] += c[key]
        for v in versions:
            cases[v].append(total[v])
    best = {v: _best([{"cases": c}]) for v, c in cases.items()}
    return {"rows_identical": same, **best}


def _child(
    path: str, sizes: Sequence[int], seconds: float, source_runs: int, estimator: str
) -> dict[str, Any]:
    """:func:`measure` in a fresh interpreter whose ``estimator`` comes from ``path``."""
    args = ["-m", "server.tooling.bench.advance", "--child", "--estimators", estimator]
    args += ["--sizes", ",".join(map(str, sizes)), "--seconds", str(seconds)]
    args += ["--source-runs", str(source_runs)]
    return json_from_child(path, args)


def _line(points: list[tuple[float, float]]) -> tuple[float, float]:
    """Least-squares ``y = a + b·x`` through ``(x, y)`` points; ``(a, b)``."""
    n = len(points)
    mx = sum(x for x, _ in points) / n
    my = sum(y for _, y in points) / n
    sxx = sum((x - mx) ** 2 for x, _ in points)
    b = sum((x - mx) * (y - my) for x, y in points) / sxx if sxx > 0 else 0.0
    return my - b * mx, b


def _best(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per size, the repeat with the least CPU; per-call ms, per-tick µs and the line."""
    cases = []
    for i, first in enumerate(runs[0]["cases"]):
        c = min((r["cases"][i] for r in runs), key=lambda c: c["advance_s"])
        cases.append(
            {
                "vehicles": first["vehicles"],
                "ticks_per_call": c["ticks"] / c["calls"],
                "call_ms": c["advance_s"] / c["calls"] * 1e3,
                "tick_us": c["advance_s"] / max(c["ticks"], 1) * 1e6,
            }
        )
    if len(cases) > 1:
        fixed, per = _line([(c["ticks_per_call"], c["call_ms"]) for c in cases])
    else:
        fixed, per = float("nan"), float("nan")
    return {"cases": cases, "fixed_ms": fixed, "per_tick_us": per * 1e3}


def _versions_of(
    estimator: str,
    versions: dict[str, str],
    sizes: Sequence[int],
    seconds: float,
    repeats: int,
    source_runs: int,
) -> dict[str, Any]:
    """One estimator measured in every version (alternating); the best per version and
    whether every version and repeat gave the same rows."""
    runs: dict[str, list[dict[str, Any]]] = {v: [] for v in versions}
    for rep in range(repeats):
        order = list(versions) if rep % 2 == 0 else list(reversed(versions))
        for v in order:
            runs[v].append(_child(versions[v], sizes, seconds, source_runs, estimator))
    digests = {v: {r["digest"] for r in rs} for v, rs in runs.items()}
    best: dict[str, Any] = {v: _best(r) for v, r in runs.items()}
    return {"rows_identical": len(set().union(*digests.values())) == 1, **best}


def _print_table(estimator: str, result: dict[str, Any], sizes: Sequence[int]) -> None:
    versions = [v for v in ("before", "after") if v in result]
    head = f"{'vehicles':>8} {'ticks/call':>10}"
    for v in versions:
        head += f" {v + ' ms/call':>16} {v + ' µs/tick':>16}"
    if "before" in result:
        head += f" {'after/before':>12}"
    print(f"\n{estimator}\n{head}")
    for i, n in enumerate(sizes):
        a = result["after"]["cases"][i]
        line = f"{n:>8} {a['ticks_per_call']:>10.1f}"
        for v in versions:
            c = result[v]["cases"][i]
            line += f" {c['call_ms']:>16.3f} {c['tick_us']:>16.2f}"
        if "before" in result:
            line += f" {a['call_ms'] / result['before']['cases'][i]['call_ms']:>12.3f}"
        print(line)
    for v in versions:
        b = result[v]
        print(
            f"{v}: fixed {b['fixed_ms']:.3f} ms per call + {b['per_tick_us']:.2f} µs per "
            "vehicle-tick (line through the sizes)"
        )
    if "before" in result:
        print(f"rows identical: {'yes' if result['rows_identical'] else 'NO'}")


def run(
    json_path: Path | str | None = None,
    *,
    sizes: Sequence[int] = (100, 300, 1000),
    estimators: Sequence[str] = ESTIMATORS,
    baseline: str | None = None,
    interleave: bool = False,
    repeats: int = 3,
    seconds: float = 6.0,
    source_runs: int = SOURCE_RUNS,
) -> dict[str, Any]:
    """Measure every estimator, print a table each; returns and optionally writes the numbers
    as JSON (``{"estimators": {name: {"after", ["before"], "rows_identical"}}, …}``; with
    ``interleave``, ``{name: {"skipped": why}}`` for an estimator the baseline lacks)."""
    unknown = sorted(set(estimators) - set(ESTIMATORS))
    if unknown:
        raise ValueError(f"unknown estimators {unknown}; known: {', '.join(ESTIMATORS)}")
    if interleave and baseline is None:
        raise ValueError("--interleave needs --baseline REV (the revision run beside this tree)")
    per: dict[str, Any] = {}
    if interleave:
        assert baseline is not None
        with renamed_estimator(baseline) as package:
            for name in estimators:
                got = _interleaved_of(name, package, sizes, seconds, repeats, source_runs)
                per[name] = got or {"skipped": f"{baseline} has no estimator.{name}; skipped"}
        passes = f"{repeats} pass" + ("es" if repeats != 1 else "")
        how = f"both versions in this process, calls alternating, CPU summed over {passes}"
    else:
        versions = {"after": str(_REPO)}
        with tempfile.TemporaryDirectory() as tmp:
            if baseline is not None:
                extract_revision(baseline, Path(tmp), ("estimator",))
                versions = {"before": tmp, "after": str(_REPO)}
            for name in estimators:
                per[name] = _versions_of(name, versions, sizes, seconds, repeats, source_runs)
        how = f"fastest of {repeats}"
    print(
        f"Fleet.advance every {INTERVAL_MS} ms, tick phases spread, {seconds:g} s of sensor "
        f"time per case, {how}" + (f"; before = {baseline}" if baseline is not None else "")
    )
    for name in estimators:
        if "skipped" in per[name]:
            print(f"\n{name}\n{per[name]['skipped']}")
        else:
            _print_table(name, per[name], sizes)
    result = {
        "seconds": seconds,
        "repeats": repeats,
        "baseline": baseline,
        "interleave": interleave,
        "estimators": per,
    }
    write_json(result, json_path)
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m server.tooling.bench.advance [--sizes …] [--estimators …] [--baseline REV
    [--interleave]] [--repeats R] [--seconds S] [--json PATH]``."""
    p = argparse.ArgumentParser(prog="python -m server.tooling.bench.advance", description=__doc__)
    p.add_argument("--sizes", type=int_list, default=[100, 300, 1000], help="fleet sizes")
    p.add_argument(
        "--estimators",
        default=",".join(ESTIMATORS),
        help="comma-separated, of " + "/".join(ESTIMATORS),
    )
    p.add_argument(
        "--baseline", type=revision, default=None, help="git revision measured side by side"
    )
    p.add_argument(
        "--interleave",
        action="store_true",
        help="with --baseline: both versions in this process, calls alternating",
    )
    p.add_argument(
        "--repeats", type=int, default=3, help="repeats per version (passes with --interleave)"
    )
    p.add_argument("--seconds", type=float, default=6.0, help="sensor seconds per case")
    p.add_argument("--source-runs", type=int, default=SOURCE_RUNS, help=argparse.SUPPRESS)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--json", type=Path, default=None, help="write the result here")
    args = p.parse_args(argv)
    if args.interleave and args.baseline is None:
        raise SystemExit(
            "slipfleet bench advance: --interleave needs --baseline REV (the revision whose "
            "estimators run beside this tree's)"
        )
    estimators = [e for e in args.estimators.split(",") if e]
    if args.child:
        print(json.dumps(measure(args.sizes, args.seconds, args.source_runs, estimators[0])))
        return 0
    run(
        args.json,
        sizes=args.sizes,
        estimators=estimators,
        baseline=args.baseline,
        interleave=args.interleave,
        repeats=args.repeats,
        seconds=args.seconds,
        source_runs=args.source_runs,
    )
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
