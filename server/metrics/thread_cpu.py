"""CPU time of this process's threads, by thread name: where a server's cores go.

``/metrics`` exposes it as ``slipfleet_thread_cpu_seconds_total{process, thread}`` (the server
process and each ingest worker), and ``slipfleet loadtest`` turns two scrapes into cores per
thread over its window, so a load test says which thread is busy instead of leaving it to a
profiler.

Per OS thread, user + system seconds (psutil). A thread that Python started is named by its
``threading`` name (matched on its native id: ``slipfleet-pipeline``, ``slipfleet-store-writer``
…); any other thread (Zenoh's runtime, which names its threads ``rx-0``, ``acc-0`` …) by its OS
name with a trailing ``-<n>`` dropped and ``os:`` in front, so a pool's threads add up under one
name (``os:rx``). Threads of the same name add up. A thread that has ended is no longer counted:
a name's total can fall, as a Prometheus counter does when its process restarts.
"""

from __future__ import annotations

import re
import threading
from pathlib import Path

import psutil

__all__ = ["thread_cpu_seconds"]

_POOL_INDEX = re.compile(r"-\d+$")


def thread_cpu_seconds() -> dict[str, float]:
    """``{thread name: CPU seconds}`` of this process's live threads (see the module docstring).

    Returns an empty dict where the platform does not list a process's threads.
    """
    try:
        threads = psutil.Process().threads()
    except (psutil.Error, NotImplementedError):
        return {}
    python_names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for t in threads:
        name = python_names.get(t.id)
        if name is None:
            name = "os:" + _POOL_INDEX.sub("", _os_name(t.id))
        out[name] = out.get(name, 0.0) + t.user_time + t.system_time
    return out


def _os_name(tid: int) -> str:
    """The OS name of thread ``tid`` of this process (Linux), else ``"thread"``."""
    try:
        return Path(f"/proc/self/task/{tid}/comm").read_text().strip() or "thread"
    except OSError:
        return "thread"
