"""Storage faults while vehicles stream: PostgreSQL stopped and started again, SQLite disk full.

During the fault the writer keeps rows in its bounded in-memory backlog, ``/api/v1/health``
answers 503 naming ``storage``, and when the database is back the backlog is written out: the
stored estimates equal those of a server that never failed.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from server.tooling.pgadmin import create_database
from tests.conftest import start_pg_cluster, stop_pg_cluster
from tests.server.faults._harness import (
    Publisher,
    ServerProcess,
    reference_rows,
    series_stamps,
    wait_until,
)
from tests.support import free_port

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

OUTAGE_S = 6.0
_BACKLOG = re.compile(r"^slipfleet_writer_backlog_rows (\S+)$", re.M)


def _backlog_rows(client: httpx.Client) -> int:
    m = _BACKLOG.search(client.get("/api/v1/metrics").text)
    assert m is not None, "backlog gauge in /api/v1/metrics"
    return int(float(m.group(1)))


def _storage_alert_open(client: httpx.Client) -> bool:
    r = client.get("/api/v1/alerts", params={"state": "open"})
    r.raise_for_status()
    return any(a["kind"] == "storage_down" and a["vehicle_id"] == "" for a in r.json()["alerts"])


def _health(client: httpx.Client) -> tuple[int, dict[str, bool]]:
    r = client.get("/api/v1/health")
    return r.status_code, r.json().get("checks", {})


class _Watch:
    """Polls health and the writer backlog while a fault lasts."""

    def __init__(self, client: httpx.Client) -> None:
        self.client = client
        self.peak = 0
        self.first_503: float | None = None

    def poll(self, t0: float) -> tuple[int, dict[str, bool]]:
        self.peak = max(self.peak, _backlog_rows(self.client))
        code, checks = _health(self.client)
        if code == 503 and self.first_503 is None:
            self.first_503 = time.monotonic() - t0
        return code, checks


def _stored(server: ServerProcess, pub: Publisher) -> dict[str, np.ndarray]:
    start, end = pub.start_ns - 10**9, pub.start_ns + int((pub.duration_s + 60) * 1e9)
    with server.client() as client:
        return {vid: series_stamps(client, vid, start, end) for vid in pub.vehicle_ids}


def _wait_complete(server: ServerProcess, pub: Publisher, ref: dict[str, np.ndarray]) -> None:
    def complete() -> bool:
        stored = _stored(server, pub)
        return all(s.size == ref[v].size for v, s in stored.items())

    wait_until(complete, 90, "every estimate stored", poll_s=0.5)


@pytest.mark.postgres
def test_postgres_outage_backlog_and_catch_up(tmp_path: Path) -> None:
    cluster = Path(tempfile.mkdtemp(prefix="slipfleet-pg-outage-"))  # readable by postgres
    port = free_port()
    admin_url = start_pg_cluster(cluster, port)
    try:
        url = create_database(admin_url, f"slipfleet_outage_{uuid.uuid4().hex[:8]}")
        server = ServerProcess(tmp_path, storage_url=url)
        pub = Publisher(server.zenoh_listen, n_vehicles=2, duration_s=50.0, rate=2.0)
        ref = reference_rows(pub)
        server.start()
        try:
            server.wait_ready()
            pub.start()
            time.sleep(5.0)
            with server.client() as client:
                watch = _Watch(client)
                t_down = time.monotonic()
                stop_pg_cluster(cluster, keep=True)
                stopped_s = time.monotonic() - t_down
                while time.monotonic() - t_down < OUTAGE_S:
                    code, checks = watch.poll(t_down)
                    time.sleep(0.2)
                assert code == 503 and checks.get("storage") is False, (code, checks)
                assert _storage_alert_open(client), "an open storage_down alert"
                t_up = time.monotonic()
                start_pg_cluster(cluster, port)
                started_s = time.monotonic() - t_up

                def caught_up() -> bool:
                    code, _ = watch.poll(t_down)
                    return code == 200 and _backlog_rows(client) == 0

                recovery_s = wait_until(caught_up, 60, "health 200 and an empty backlog")
                wait_until(lambda: not _storage_alert_open(client), 10, "storage alert closed")
            pub.wait_done(120)
            _wait_complete(server, pub, ref)
            stored = _stored(server, pub)
        finally:
            server.stop()
    finally:
        stop_pg_cluster(cluster)
    print(
        f"\nPostgreSQL outage: stopped in {stopped_s:.1f} s, down {OUTAGE_S:.0f} s, health 503 "
        f"after {watch.first_503:.2f} s; restarted in {started_s:.1f} s, health 200 and backlog "
        f"written {recovery_s:.2f} s after it was up; backlog peak {watch.peak} rows"
    )
    assert watch.peak > 0, "rows waited in the backlog"
    for vid in pub.vehicle_ids:
        assert np.array_equal(stored[vid], ref[vid]["stamp_ns"]), f"{vid}: rows lost or doubled"


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    """A 16 MB tmpfs (needs root; fails, not skips, where it cannot be mounted)."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(mnt)], check=True)
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_sqlite_disk_full_backlog_and_catch_up(tmp_path: Path, tiny_disk: Path) -> None:
    server = ServerProcess(tmp_path, extra_env={"SLIPFLEET_STORAGE__DATA_DIR": str(tiny_disk)})
    pub = Publisher(server.zenoh_listen, n_vehicles=2, duration_s=50.0, rate=2.0)
    ref = reference_rows(pub)
    server.start()
    ballast = tiny_disk / "ballast"
    try:
        server.wait_ready()
        pub.start()
        time.sleep(4.0)
        with server.client() as client:
            watch = _Watch(client)
            t_full = time.monotonic()
            # fill the disk: the database cannot grow any more
            used_b = shutil.disk_usage(tiny_disk).used
            try:
                with open(ballast, "wb") as f:
                    while True:
                        f.write(b"\0" * 65536)
                        f.flush()
            except OSError:
                pass
            free_b = shutil.disk_usage(tiny_disk).free

            def refused() -> bool:
                code, checks = watch.poll(t_full)
                return code == 503 and checks.get("storage") is False

            detect_s = wait_until(refused, 30, "health 503 on a full disk", poll_s=0.2)
            while time.monotonic() - t_full < OUTAGE_S:
                watch.poll(t_full)
                time.sleep(0.2)
            t_free = time.monotonic()
            ballast.unlink()

            def caught_up() -> bool:
                code, _ = watch.poll(t_full)
                return code == 200 and _backlog_rows(client) == 0

            recovery_s = wait_until(caught_up, 60, "health 200 and an empty backlog")
        pub.wait_done(120)
        _wait_complete(server, pub, ref)
        stored = _stored(server, pub)
    finally:
        server.stop()
    print(
        f"\nSQLite disk full ({used_b} bytes used by the store, {free_b} left): health 503 after "
        f"{detect_s:.2f} s, full for {t_free - t_full:.1f} s; health 200 and backlog written "
        f"{recovery_s:.2f} s after space was freed; backlog peak {watch.peak} rows"
    )
    for vid in pub.vehicle_ids:
        assert np.array_equal(stored[vid], ref[vid]["stamp_ns"]), f"{vid}: rows lost or doubled"
