"""Shared fixtures.

PostgreSQL: ``pg_url`` is the URL of a server the tests may create databases on. It is
``$SLIPFLEET_TEST_PG_URL`` when set (CI: start one with ``scripts/pg-test-cluster start``);
otherwise the session starts a throwaway cluster with that script and stops it at the end. If
PostgreSQL cannot start, the tests that need it fail (never skip). ``pg_database_url`` gives each
test a fresh empty database, dropped afterwards.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PG_CLUSTER_SCRIPT = REPO / "scripts" / "pg-test-cluster"
PG_URL_ENV = "SLIPFLEET_TEST_PG_URL"


def start_pg_cluster(cluster_dir: Path, port: int = 0) -> str:
    """Start (creating if needed) a throwaway cluster in ``cluster_dir`` with
    ``scripts/pg-test-cluster``; return its URL. Fails the test if it cannot start."""
    cmd = [sys.executable, str(PG_CLUSTER_SCRIPT), "start", "--dir", str(cluster_dir)]
    if port:
        cmd += ["--port", str(port)]
    started = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    if started.returncode != 0:
        pytest.fail(
            f"could not start a PostgreSQL test cluster (set {PG_URL_ENV} to use an existing "
            f"server):\n{started.stdout}\n{started.stderr}",
            pytrace=False,
        )
    return started.stdout.strip().splitlines()[-1]


def stop_pg_cluster(cluster_dir: Path, *, keep: bool = False) -> None:
    """Stop a cluster started by :func:`start_pg_cluster` (and delete it unless ``keep``)."""
    cmd = [sys.executable, str(PG_CLUSTER_SCRIPT), "stop", "--dir", str(cluster_dir)]
    if keep:
        cmd.append("--keep")
    stopped = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    if stopped.returncode != 0:
        raise RuntimeError(f"could not stop the test cluster: {stopped.stdout}{stopped.stderr}")


@pytest.fixture(scope="session")
def pg_url() -> Iterator[str]:
    """URL of a PostgreSQL server (superuser or CREATEDB role) for this test session."""
    given = os.environ.get(PG_URL_ENV)
    if given:
        yield given
        return
    cluster_dir = Path(tempfile.mkdtemp(prefix="slipfleet-pg-"))
    url = start_pg_cluster(cluster_dir)
    try:
        yield url
    finally:
        stop_pg_cluster(cluster_dir)


@pytest.fixture
def pg_database_url(pg_url: str) -> Iterator[str]:
    """A fresh, empty database on the ``pg_url`` server for one test; dropped afterwards."""
    from server.tooling.pgadmin import create_database, drop_database

    name = f"slipfleet_test_{uuid.uuid4().hex[:12]}"
    url = create_database(pg_url, name)
    try:
        yield url
    finally:
        drop_database(pg_url, name)
