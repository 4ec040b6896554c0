"""Wheel-speed front end cost: encoder-edge pushes and speed queries for a fleet.

``slipfleet bench wheels [--vehicles 100,1000,3000] [--intervals 50,100] [--json PATH]`` or
``python -m server.tooling.bench.wheels``.

Every vehicle replays the wheel edges of one of a few simulated runs (``field_work``,
``hard_braking``, ``slow_creep``, ``figure_eight``; their own packets, 100 ms per wheel, in
arrival order), the way :class:`estimator.mdsf.MdsfFleet` uses the front end: each packet is
pushed into its wheel's tracker as it arrives, and every call interval (50 or 100 ms of sensor
time) all wheels of all vehicles are asked for their speed at the due ticks (a 50 ms grid, so
one or two ticks per call) in one :func:`~estimator.wheel_speed.query_many`.

Three ways in the same process, on the same packets:

* **query_many**: :class:`estimator.wheel_speed.WheelTracker` / ``query_many`` (one
  :class:`~estimator.wheel_speed.WheelBank` for the fleet, one result object per wheel);
* **WheelBank API**: slots of one bank, one ``WheelBank.query`` for all;
* **baseline**: one call per wheel (each tracker in a bank of its own, ``WheelTracker.query``),
  the way a per-vehicle front end would ask. (The per-tracker implementation the bank replaced
  measured 1.47 ms per vehicle-second at 1,000 vehicles / 100 ms on this machine, 8.4× the
  bank's ``query_many``; its results equal the bank's to 3.3e-12 rad/s.)

The table gives CPU time (this process, ``time.process_time``) per vehicle-second of sensor
data, for the pushes and for the queries (tooth calibration included), after a warm-up. The baseline
is timed over fewer sensor seconds at the larger fleets (its cost is steady).
The product target: push + query ≤ 0.08 ms per vehicle-second at 1,000 vehicles and 100 ms.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from estimator.config import EncoderConfig, WheeledRearDriveConfig
from estimator.sim import simulate
from estimator.types import WheelEdges
from estimator.wheel_speed import (
    WheelBank,
    WheelSpeedConfig,
    WheelSpeedResult,
    WheelTracker,
    query_many,
)
from server.tooling.bench import int_list, write_json

__all__ = ["main", "run"]

START_NS = 1_700_000_000_000_000_000
SCENARIOS = ("field_work", "hard_braking", "slow_creep", "figure_eight")
TICK_NS = 50_000_000
"""Estimate grid: ticks due at a call are those up to the call time minus ``LAG_NS``."""
LAG_NS = 150_000_000
WARMUP_S = 3.0
PHASES_S = (0.0, 4.0, 8.0, 12.0, 16.0)
"""Points of each simulated run a vehicle may start its replay from [s]."""
TARGET_MS = 0.08


@dataclass(frozen=True, slots=True)
class _Packet:
    arrival_ns: int
    wheel: int
    stamp_ns: npt.NDArray[np.int64]
    direction: npt.NDArray[np.int8] | None


def _runs(seconds: float) -> list[list[_Packet]]:
    """Wheel packets of a few simulated vehicles (with and without direction encoders).

    Each run is also replayed from later points (``PHASES_S``), shifted to start at
    ``START_NS``, so the fleet is not all at the same point of its manoeuvres.
    """
    out = []
    for seed, name in enumerate(SCENARIOS, start=1):
        for has_dir in (False, True):
            cfg = WheeledRearDriveConfig(encoder=EncoderConfig(has_direction=has_dir))
            run = simulate(name, seed=seed, start_ns=START_NS, config=cfg)
            wheel = [(arr, m) for arr, m in run.in_arrival_order() if isinstance(m, WheelEdges)]
            for phase_s in PHASES_S:
                shift = round(phase_s * 1e9)
                end = START_NS + round(seconds * 1e9)
                out.append(
                    [
                        _Packet(arr - shift, int(m.wheel), m.stamp_ns - shift, m.direction)
                        for arr, m in wheel
                        if m.stamp_ns[0] >= START_NS + shift and arr - shift <= end
                    ]
                )
    return out


def _measure(
    runs: list[list[_Packet]],
    vehicles: int,
    interval_ms: int,
    seconds: float,
    make: Callable[[], Any],
    many: Callable[[list[Any], npt.NDArray[np.int64]], object],
) -> tuple[float, float]:
    """CPU ms per vehicle-second for (push, query) over ``seconds`` after the warm-up."""
    trackers = [make() for _ in range(2 * vehicles)]
    step = interval_ms * 1_000_000
    ptr = [0] * vehicles
    feeds = [runs[v % len(runs)] for v in range(vehicles)]
    push_cpu = query_cpu = 0.0
    next_tick = START_NS
    now = START_NS
    measured_from = START_NS + round(WARMUP_S * 1e9)
    end = measured_from + round(seconds * 1e9)
    while now < end:
        now += step
        batch = []
        for v in range(vehicles):
            feed, i = feeds[v], ptr[v]
            while i < len(feed) and feed[i].arrival_ns <= now:
                pk = feed[i]
                batch.append((trackers[2 * v + pk.wheel], pk.stamp_ns, pk.direction))
                i += 1
            ptr[v] = i
        due = now - LAG_NS
        ticks = np.arange(next_tick, due + 1, TICK_NS, dtype=np.int64)
        timed = now > measured_from
        c0 = time.process_time()
        for tr, stamps, direction in batch:
            tr.push(stamps, direction)
        c1 = time.process_time()
        if ticks.size:
            many(trackers, ticks)
            next_tick = int(ticks[-1]) + TICK_NS
        c2 = time.process_time()
        if timed:
            push_cpu += c1 - c0
            query_cpu += c2 - c1
    vs = vehicles * seconds
    return push_cpu * 1e3 / vs, query_cpu * 1e3 / vs


class _SlotHandle:
    """A bank slot with the tracker's ``push`` signature (what a fleet front end would hold)."""

    __slots__ = ("push", "slot")

    def __init__(self, bank: WheelBank) -> None:
        self.slot = bank.add()
        self.push = functools.partial(bank.push, self.slot)


def _bank_api(cfg: WheelSpeedConfig) -> tuple[Callable[[], Any], Callable[..., object]]:
    """``make`` and ``many`` for the fleet-level API: one bank, arrays per call."""
    bank = WheelBank(cfg)
    slots: list[npt.NDArray[np.int64]] = []

    def many(handles: list[_SlotHandle], ticks: npt.NDArray[np.int64]) -> object:
        if not slots or slots[0].shape[0] != len(handles):
            slots[:] = [np.array([h.slot for h in handles], dtype=np.int64)]
        return bank.query(slots[0], ticks)

    return (lambda: _SlotHandle(bank)), many


def _run_query_many(
    runs: list[list[_Packet]], n: int, iv: int, seconds: float, cfg: WheelSpeedConfig
) -> tuple[float, float]:
    return _measure(runs, n, iv, seconds, lambda: WheelTracker(cfg), query_many)


def _run_bank_api(
    runs: list[list[_Packet]], n: int, iv: int, seconds: float, cfg: WheelSpeedConfig
) -> tuple[float, float]:
    return _measure(runs, n, iv, seconds, *_bank_api(cfg))


def _best(repeats: int, measure: Callable[[], tuple[float, float]]) -> tuple[float, float]:
    """Least total over ``repeats`` runs (other load on the machine only ever adds)."""
    return min((measure() for _ in range(max(repeats, 1))), key=sum)


def _print_head(repeats: int) -> None:
    """The table's title and column heads."""
    header = (
        f"{'vehicles':>8} {'call ms':>7} | {'push':>7} {'query':>7} {'total':>7} |"
        f" {'push':>7} {'query':>7} {'total':>7} | {'push':>7} {'query':>7} {'total':>7} |"
        f" {'speed-up':>8}"
    )
    print(
        "CPU ms per vehicle-second of sensor data (both wheels), least of "
        f"{repeats} runs for the new code; load average before: {os.getloadavg()[0]:.1f}"
    )
    print(
        f"{'':17}| {'baseline: call per wheel':^23} | {'new: query_many':^23} |"
        f" {'new: WheelBank API':^23} |"
    )
    print(header)
    print("-" * len(header))


def _case(
    runs: list[list[_Packet]],
    n: int,
    iv: int,
    cfg: WheelSpeedConfig,
    seconds: float,
    baseline_seconds: float | None,
    repeats: int,
) -> dict[str, Any]:
    """One table row: ``n`` vehicles called every ``iv`` ms, the new code's two ways (least of
    ``repeats``) and the baseline's unless ``baseline_seconds`` is None; printed."""
    many_ = _best(repeats, functools.partial(_run_query_many, runs, n, iv, seconds, cfg))
    api = _best(repeats, functools.partial(_run_bank_api, runs, n, iv, seconds, cfg))
    row: dict[str, Any] = {
        "vehicles": n,
        "interval_ms": iv,
        "query_many_push_ms": many_[0],
        "query_many_query_ms": many_[1],
        "bank_push_ms": api[0],
        "bank_query_ms": api[1],
    }
    was = (math.nan, math.nan)
    if baseline_seconds is not None:
        secs = seconds if n <= 100 else baseline_seconds
        tracker = functools.partial(WheelTracker, cfg)
        was = _measure(runs, n, iv, secs, tracker, _one_call_per_wheel)
        row |= {"baseline_push_ms": was[0], "baseline_query_ms": was[1]}
    print(
        f"{n:>8} {iv:>7} | {was[0]:>7.4f} {was[1]:>7.4f} {sum(was):>7.4f} |"
        f" {many_[0]:>7.4f} {many_[1]:>7.4f} {sum(many_):>7.4f} |"
        f" {api[0]:>7.4f} {api[1]:>7.4f} {sum(api):>7.4f} |"
        f" {sum(was) / sum(many_):>7.1f}x",
        flush=True,
    )
    return row


def _print_verdicts(rows: list[dict[str, Any]]) -> None:
    """Whether the new code meets ``TARGET_MS`` at 1,000 vehicles called every 100 ms."""
    for r in rows:
        if r["vehicles"] == 1000 and r["interval_ms"] == 100:
            for name in ("query_many", "bank"):
                total = r[f"{name}_push_ms"] + r[f"{name}_query_ms"]
                verdict = "meets" if total <= TARGET_MS else "misses"
                print(
                    f"1,000 vehicles, 100 ms, {name}: {total:.4f} ms per vehicle-second, "
                    f"{verdict} the {TARGET_MS} ms target"
                )


def run(
    json_path: Path | None = None,
    vehicles: Sequence[int] = (100, 1000, 3000),
    intervals_ms: Sequence[int] = (50, 100),
    seconds: float = 10.0,
    baseline_seconds: float = 3.0,
    baseline: bool = True,
    repeats: int = 2,
) -> dict[str, Any]:
    """Measure and print the table; returns the rows (and writes them to ``json_path``)."""
    runs = _runs(WARMUP_S + max(seconds, baseline_seconds) + 1.0)
    cfg = WheelSpeedConfig()
    _print_head(repeats)
    base_s = baseline_seconds if baseline else None
    rows = [
        _case(runs, n, iv, cfg, seconds, base_s, repeats) for n in vehicles for iv in intervals_ms
    ]
    _print_verdicts(rows)
    result = {"rows": rows, "target_ms": TARGET_MS, "load_average": os.getloadavg()[0]}
    write_json(result, json_path)
    return result


def _one_call_per_wheel(
    trackers: list[WheelTracker], query_ns: npt.NDArray[np.int64]
) -> list[WheelSpeedResult]:
    return [t.query(query_ns) for t in trackers]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m server.tooling.bench.wheels [--vehicles 100,1000,3000] [--intervals 50,100]
    [--seconds S] [--baseline-seconds S] [--no-baseline] [--json PATH]``."""
    p = argparse.ArgumentParser(prog="python -m server.tooling.bench.wheels", description=__doc__)
    p.add_argument("--vehicles", type=int_list, default=[100, 1000, 3000])
    p.add_argument("--intervals", type=int_list, default=[50, 100], help="call interval, ms")
    p.add_argument("--seconds", type=float, default=10.0, help="sensor seconds timed (new)")
    p.add_argument(
        "--baseline-seconds",
        type=float,
        default=3.0,
        help="sensor seconds timed for the baseline above 100 vehicles",
    )
    p.add_argument("--no-baseline", action="store_true", help="skip the baseline")
    p.add_argument("--repeats", type=int, default=2, help="runs of the new code (least kept)")
    p.add_argument("--json", type=Path, default=None, help="write the rows here")
    a = p.parse_args(argv)
    run(
        a.json, a.vehicles, a.intervals, a.seconds, a.baseline_seconds, not a.no_baseline, a.repeats
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
