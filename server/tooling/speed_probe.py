"""How fast this machine runs Python at the moment: a fixed loop, timed.

Shared machines drift: on the 2-core VM the same pipeline bench took 1,254 µs per
vehicle-second one hour and 1,733 the next, and a ten-million-step loop 0.70–0.89 s minutes
apart. A load test near the machine's limit passes or fails on that drift, so its report
carries this probe, taken before the load starts and after it ends, to compare runs by.
"""

from __future__ import annotations

import time

__all__ = ["PROBE_STEPS", "probe_s"]

#: Loop steps of one probe (0.055-0.097 s here, depending on the hour: the load-test runs of
#: 2026-11-26).
PROBE_STEPS = 2_000_000


def probe_s(steps: int = PROBE_STEPS, repeats: int = 3) -> float:
    """Least wall time, in seconds, of ``repeats`` runs of a pure-Python loop of ``steps``
    additions (the interpreter's speed on one core, as other work on the machine leaves it)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        total = 0
        for i in range(steps):
            total += i
        best = min(best, time.perf_counter() - t0)
    return best
