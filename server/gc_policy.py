"""Garbage-collector settings for a process that ingests a fleet.

CPython frees almost every object of the ingest path (decoded packets, their arrays, the rows)
by reference counting the moment it is done with it; the cyclic collector only finds reference
cycles, and it pays for that by walking the tracked containers. With the interpreter's default
thresholds ``(700, 10, 10)`` it does so hundreds of times a second in a busy pipeline, and every
so often walks the whole heap: reorder buffers and estimator state of hundreds of vehicles, with
pauses of about 0.1 s that reach the end-to-end latency of every vehicle at once.

:func:`settle` is called once a process has built its long-lived state (imports, settings,
registered vehicles): it collects once, moves everything that survives out of the collector's
sight (:func:`gc.freeze`; such objects are still freed by reference counting) and raises the
first threshold (``IngestSettings.gc_gen0``), so the young generation is collected after that
many net allocations instead of 700. The older generations keep their default ratios: a full
collection still comes, less often by the same factor. What it changed, measured, is in
``docs/perf/server.md`` (the settled garbage collector).
"""

from __future__ import annotations

import gc

__all__ = ["settle"]


def settle(gen0: int) -> None:
    """Collect, freeze what survives, and collect young objects every ``gen0`` allocations.

    ``gen0`` of 0 leaves the collector as the interpreter set it (nothing is frozen either).
    """
    if gen0 <= 0:
        return
    gc.collect()
    gc.freeze()
    _, gen1, gen2 = gc.get_threshold()
    gc.set_threshold(gen0, gen1, gen2)
