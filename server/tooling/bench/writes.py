"""CPU per stored row in the server's write pattern: a fleet's rows a few hundred per commit.

``slipfleet bench writes [--vehicles 1000] [--rows-per-commit 250,500,1000] [--seconds 30]
[--baseline REV] [--repeats 2] [--json PATH]`` or ``python -m server.tooling.bench.writes``.

The store writer commits what the estimator calls handed over since the last commit: at
1,000 vehicles (a row each per 100 ms tick) a few hundred rows, one per vehicle, every few
tens of ms, and calls the store's ``maintain`` (SQLite: moving staged rows on) between
commits. This bench does that on a SQLite file in a temporary directory, without the writer
thread's queue: ``vehicles`` registered vehicles, every 100 ms of sensor time a row each,
written ``rows-per-commit`` rows per ``write_estimates`` with one ``maintain`` step after each.
Reported per case: thread CPU per row of the writes and of the maintain steps (µs), their sum,
and the longest maintain step (wall ms: the estimate commits that wait behind it). The first
``WARMUP_S`` seconds of sensor time are not measured (the first move rounds start after 3 s).

``--baseline REV`` runs the same loop on the ``estimator/`` and ``server/`` packages of git
revision ``REV`` in a child process, alternating with the working tree ``--repeats`` times;
each case keeps its least total. ``after/before`` is the ratio of the totals.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["main", "measure", "run"]

TICK_NS = 100_000_000
"""Sensor time between two rows of a vehicle (the MDSF tick)."""
WARMUP_S = 5.0
"""Sensor seconds at the start that are not measured."""
START_NS = 1_800_000_000_000_000_000
"""Sensor time of the first row."""
_REPO = Path(__file__).resolve().parents[3]


def measure(vehicles: int, rows_per_commit: int, seconds: float) -> dict[str, Any]:
    """Write ``seconds`` of a ``vehicles`` fleet's rows, ``rows_per_commit`` a commit, with a
    ``maintain`` step after each; CPU seconds of writes and maintain steps after the warm-up."""
    # imported here: a baseline child puts another revision's packages first on its path
    from estimator.types import empty_estimates
    from server.settings import Settings
    from server.storage import open_store

    with tempfile.TemporaryDirectory() as data_dir:
        store = open_store(Settings(storage={"data_dir": data_dir}).storage)
        try:
            ids = [f"v{i:05d}" for i in range(vehicles)]
            for vid in ids:
                store.upsert_vehicle(vid, {}, now_ns=1)
            maintain = getattr(store, "maintain", None)
            write_s = maintain_s = longest_s = 0.0
            rows = 0
            warmup_ticks = int(WARMUP_S * 1e9 / TICK_NS)
            for tick in range(warmup_ticks + int(seconds * 1e9 / TICK_NS)):
                fleet = empty_estimates(vehicles)
                fleet["stamp_ns"] = START_NS + tick * TICK_NS
                measured = tick >= warmup_ticks
                for a in range(0, vehicles, rows_per_commit):
                    end = min(vehicles, a + rows_per_commit)
                    batch = [(ids[i], fleet[i : i + 1]) for i in range(a, end)]
                    c0 = time.thread_time()
                    store.write_estimates(batch)
                    c1 = time.thread_time()
                    w0 = time.perf_counter()
                    if maintain is not None:
                        maintain()
                    w1, c2 = time.perf_counter(), time.thread_time()
                    if measured:
                        write_s += c1 - c0
                        maintain_s += c2 - c1
                        longest_s = max(longest_s, w1 - w0)
                        rows += len(batch)
        finally:
            store.close()
    return {
        "vehicles": vehicles,
        "rows_per_commit": rows_per_commit,
        "rows": rows,
        "write_s": write_s,
        "maintain_s": maintain_s,
        "longest_maintain_s": longest_s,
    }


def _child(path: str, vehicles: int, rows_per_commit: int, seconds: float) -> dict[str, Any]:
    """:func:`measure` in a fresh interpreter whose packages come from ``path``."""
    from server.tooling.bench import json_from_child, script_of  # the child runs this file

    args = [script_of(path, "writes"), "--child", "--vehicles", str(vehicles)]
    args += ["--rows-per-commit", str(rows_per_commit), "--seconds", str(seconds)]
    return json_from_child(path, args)


def _per_row_us(got: dict[str, Any]) -> dict[str, float]:
    rows = max(1, got["rows"])
    write, maintain = got["write_s"] / rows * 1e6, got["maintain_s"] / rows * 1e6
    return {
        "write": write,
        "maintain": maintain,
        "total": write + maintain,
        "longest_maintain_ms": got["longest_maintain_s"] * 1e3,
    }


def run(
    vehicles: int,
    rows_per_commit: Sequence[int],
    seconds: float,
    *,
    baseline: str | None = None,
    repeats: int = 2,
    json_path: Path | str | None = None,
) -> dict[str, Any]:
    """Measure each commit size (and the baseline's); print the table; return the numbers."""
    from server.tooling.bench import side_by_side, write_json

    cases = side_by_side(
        baseline,
        repeats,
        "rows_per_commit",
        rows_per_commit,
        lambda per_commit, path: _per_row_us(_child(path, vehicles, per_commit, seconds)),
    )
    result = {"vehicles": vehicles, "seconds": seconds, "baseline": baseline, "cases": cases}
    print(format_table(result))
    write_json(result, json_path)
    return result


def format_table(result: dict[str, Any]) -> str:
    """CPU per row of writes and maintain steps, and the longest maintain step."""
    lines = [
        f"SQLite CPU per row, {result['vehicles']} vehicles at 10 Hz, maintain after every "
        f"commit ({result['seconds']:g} s of sensor time measured)",
        "| rows/commit | version | write µs | maintain µs | total µs | longest maintain ms |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    names = {"before": f"before ({result['baseline']})", "after": "working tree"}
    for case in result["cases"]:
        for key in ("before", "after"):
            if key in case:
                c = case[key]
                lines.append(
                    f"| {case['rows_per_commit']} | {names[key]} | {c['write']:.2f} "
                    f"| {c['maintain']:.2f} | {c['total']:.2f} | {c['longest_maintain_ms']:.1f} |"
                )
        if "after_over_before" in case:
            lines.append(
                f"| {case['rows_per_commit']} | after/before | | | "
                f"{case['after_over_before']:.2f} | |"
            )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m server.tooling.bench.writes [--vehicles N] [--rows-per-commit 250,500]
    [--seconds S] [--baseline REV] [--repeats R] [--json PATH]``."""
    from server.tooling.bench import int_list, revision

    p = argparse.ArgumentParser(prog="python -m server.tooling.bench.writes", description=__doc__)
    p.add_argument("--vehicles", type=int, default=1000)
    p.add_argument("--rows-per-commit", type=int_list, default=[250, 500, 1000])
    p.add_argument("--seconds", type=float, default=30.0, help="sensor seconds measured")
    p.add_argument(
        "--baseline", type=revision, default=None, help="git revision measured side by side"
    )
    p.add_argument("--repeats", type=int, default=2, help="alternating repeats per version")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--json", type=Path, default=None, help="write the result here")
    args = p.parse_args(argv)
    if args.child:
        (per_commit,) = args.rows_per_commit
        print(json.dumps(measure(args.vehicles, per_commit, args.seconds)))
        return 0
    run(
        args.vehicles,
        args.rows_per_commit,
        args.seconds,
        baseline=args.baseline,
        repeats=args.repeats,
        json_path=args.json,
    )
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
