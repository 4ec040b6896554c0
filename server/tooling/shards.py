"""Several server processes sharing a fleet: a router process and one shard per key filter.

The multi-host layout (``deploy/compose.yaml``) on one machine: :class:`RouterProcess` runs
``python -m server.tooling.router``; :func:`sharded_servers` starts one ``slipfleet serve`` process
per vehicle filter as clients of that router, all writing to one PostgreSQL database, so the REST
API of each answers for the whole fleet. Shard ``k`` of :func:`shard_layout` owns the vehicle ids
that start with the ``k``-th letter (``a-…``, ``b-…``): Zenoh delivers each shard only its
share, by key expression (``zenoh.vehicle_filter``). Used by ``slipfleet loadtest --shards N``
and the throughput ladder.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import string
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from server.tooling.ports import free_port
from server.tooling.procs import stop_process
from server.tooling.server_process import ServerProcess

__all__ = ["MAX_SHARDS", "RouterProcess", "shard_layout", "sharded_servers"]

MAX_SHARDS = len(string.ascii_lowercase)


def shard_layout(n: int) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Vehicle filters and vehicle-id formats of ``n`` shards (``n == 1``: one owns all).

    Returns ``(filters, id_formats)``: shard ``k`` subscribes to ``"<letter>-$*"`` and its
    vehicles are named ``"<letter>-{:05d}"``.
    """
    if not 1 <= n <= MAX_SHARDS:
        raise ValueError(f"shards must be between 1 and {MAX_SHARDS}, got {n}")
    if n == 1:
        return ("*",), ("sim-{:05d}",)
    letters = string.ascii_lowercase[:n]
    return tuple(f"{c}-$*" for c in letters), tuple(f"{c}-{{:05d}}" for c in letters)


class RouterProcess:
    """``python -m server.tooling.router`` on a free loopback port (``endpoint``)."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "server.tooling.router", "--listen", self.endpoint],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if "listening" not in line:
            self.stop()
            raise RuntimeError(f"router did not start: {line!r}")

    def stop(self) -> None:
        stop_process(self.proc, 10, kill_wait_s=5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


@contextlib.contextmanager
def sharded_servers(
    storage_url: str, filters: Sequence[str], settings: dict[str, Any] | None = None
) -> Iterator[tuple[RouterProcess, list[ServerProcess]]]:
    """A router process and one server process per vehicle filter (clients of the router),
    all writing to the PostgreSQL database at ``storage_url``; yields ``(router, servers)``.

    ``settings`` (nested dicts, as the TOML file) apply to every shard.
    """
    router = RouterProcess()
    servers: list[ServerProcess] = []
    tmp = Path(tempfile.mkdtemp(prefix="slipfleet-shards-"))
    try:
        for k, vehicle_filter in enumerate(filters):
            s = json.loads(json.dumps(settings or {}))
            s.setdefault("zenoh", {}).update(
                {"connect": [router.endpoint], "vehicle_filter": vehicle_filter}
            )
            server = ServerProcess(s, storage_url, log_path=tmp / f"server-{k}.log")
            server.start()
            servers.append(server)
        yield router, servers
    finally:
        for server in servers:
            server.stop()
        router.stop()
        shutil.rmtree(tmp, ignore_errors=True)
