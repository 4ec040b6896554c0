"""Small helpers shared by tests."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from estimator.base import Measurement
from estimator.sim import SimRun, replay, replay_arrivals
from server.tooling.ports import free_port

__all__ = [
    "VEHICLE_CLIENT",
    "free_port",
    "poll_until",
    "replay_drive",
    "replay_in_order",
    "run_vehicle_client",
]

_T = TypeVar("_T")

#: The runnable vehicle client of ``docs/examples``.
VEHICLE_CLIENT = Path(__file__).resolve().parents[1] / "docs" / "examples" / "vehicle_client.py"


def run_vehicle_client(
    endpoint: str, vehicle_id: str, seconds: float
) -> subprocess.CompletedProcess[str]:
    """Run the example vehicle client against ``endpoint`` for ``seconds``; returns its result."""
    return subprocess.run(
        [
            sys.executable,
            str(VEHICLE_CLIENT),
            "--connect",
            endpoint,
            "--vehicle-id",
            vehicle_id,
            "--seconds",
            str(seconds),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def poll_until(
    cond: Callable[[], _T | None], what: str, timeout_s: float = 120.0, poll_s: float = 0.1
) -> _T:
    """``cond()``'s first true value, polled every ``poll_s``; fails the test saying ``what``
    was awaited after ``timeout_s`` (a deadline for what never comes: generous, since a loaded
    host is slow, and no cost when the condition holds early)."""
    deadline = time.monotonic() + timeout_s
    while not (value := cond()):
        assert time.monotonic() < deadline, f"no {what} in {timeout_s:.0f} s"
        time.sleep(poll_s)
    return value


def replay_drive(
    sim: SimRun,
    push: Callable[[Measurement], None],
    advance: Callable[[int], list[np.ndarray]],
) -> np.ndarray:
    """Play a simulated drive into one vehicle as the server's pipeline would (150 ms reorder
    window, advanced every 100 ms): ``push(m)`` takes a measurement, ``advance(until_ns)``
    returns that vehicle's new rows. All rows, concatenated in order."""
    parts: list[np.ndarray] = []
    for chunk, until in replay_arrivals(
        sim.measurements,
        sim.arrival_ns,
        lateness_ns=150_000_000,
        step_ns=100_000_000,
        end_ns=sim.end_ns,
    ):
        for m in chunk:
            push(m)
        parts += advance(until)
    return np.concatenate(parts)


def replay_in_order(
    sim: SimRun,
    push: Callable[[Measurement], None],
    advance: Callable[[int], list[np.ndarray]],
) -> np.ndarray:
    """Play a simulated drive into one vehicle in sample order, advanced every 100 ms (no
    arrival latencies): as :func:`replay_drive`, for tests of the estimator alone."""
    parts: list[np.ndarray] = []
    for chunk, until in replay(sim.measurements, step_ns=100_000_000, end_ns=sim.end_ns):
        for m in chunk:
            push(m)
        parts += advance(until)
    return np.concatenate(parts)
