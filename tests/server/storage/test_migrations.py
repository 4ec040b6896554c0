"""Versioned migrations: idempotent, concurrent-safe, refuse a newer schema."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path
from typing import Any

import pytest

from server.storage import StorageError, open_store
from server.storage.migrations import (
    _VERSION_TABLE,
    MIGRATIONS,
    apply_pending,
    latest_version,
)
from server.storage.sqlite import SqliteStore
from tests.server.storage.conftest import Backend


def test_versions_are_consecutive() -> None:
    assert [m.version for m in MIGRATIONS] == list(range(1, len(MIGRATIONS) + 1))
    for m in MIGRATIONS:
        # a step may be a no-op on one dialect (v3 packs rows for SQLite only), never on both
        assert m.statements("sqlite") or m.statements("postgresql")
    with pytest.raises(ValueError):
        MIGRATIONS[0].statements("oracle")


def test_migrate_twice_keeps_version(backend: Backend) -> None:
    store = backend.open(migrate=False)
    assert store.schema_version() == 0  # type: ignore[attr-defined]
    assert store.migrate() == latest_version()
    store.upsert_vehicle("v1", {"x": 1}, now_ns=1)
    assert store.migrate() == latest_version()
    assert store.schema_version() == latest_version()  # type: ignore[attr-defined]
    assert store.get_vehicle("v1") is not None  # data untouched
    # a second store (another process) sees a migrated database and does nothing
    assert backend.open(migrate=False).migrate() == latest_version()


def test_concurrent_migrations(backend: Backend) -> None:
    """Several servers starting at once: one migrates, the others wait and find it done."""
    stores = [backend.open(migrate=False) for _ in range(4)]
    barrier = threading.Barrier(len(stores))
    results: list[Any] = [None] * len(stores)

    def run(i: int) -> None:
        barrier.wait()
        try:
            results[i] = stores[i].migrate()
        except BaseException as exc:  # surfaced below
            results[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(stores))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == [latest_version()] * len(stores)
    assert stores[0].ping()


def test_open_store_migrates(backend: Backend) -> None:
    store = open_store(backend.settings)
    try:
        assert store.dialect == backend.name
        assert store.schema_version() == latest_version()  # type: ignore[attr-defined]
    finally:
        store.close()


def test_newer_schema_is_refused() -> None:
    executed: list[str] = []

    def execute(sql: str, params: tuple[Any, ...]) -> list[tuple[Any, ...]]:
        executed.append(sql)
        return [(latest_version() + 1,)]

    with pytest.raises(RuntimeError, match="newer"):
        apply_pending(execute, "sqlite")
    assert len(executed) == 2  # version table + version read, no migration statement


def test_newer_schema_refused_by_store(backend: Backend, monkeypatch: pytest.MonkeyPatch) -> None:
    store = backend.open()  # at the latest version
    import server.storage.migrations as mig

    monkeypatch.setattr(mig, "MIGRATIONS", mig.MIGRATIONS[:1])  # an older server
    with pytest.raises(StorageError, match="newer"):
        store.migrate()


def test_raw_packets_survive_the_move_to_vehicle_id_keys(tmp_path: Path) -> None:
    """A version-4 SQLite database with raw packets migrates to version 5 keeping them."""
    path = tmp_path / "v4.sqlite"
    conn = sqlite3.connect(path)
    conn.execute(_VERSION_TABLE["sqlite"])
    for m in MIGRATIONS:
        if m.version > 4:
            break
        for sql in m.statements("sqlite"):
            conn.execute(sql)
        conn.execute(
            "INSERT INTO schema_version (version, description, applied_ns) VALUES (?, ?, 0)",
            (m.version, m.description),
        )
    conn.execute(
        "INSERT INTO vehicles (vkey, vehicle_id, config, created_ns, updated_ns) "
        "VALUES (7, 'old-1', '{}', 1, 1)"
    )
    conn.execute(
        "INSERT INTO raw_packets (vkey, received_ns, key, payload) VALUES (7, 5, 'k', x'0102')"
    )
    conn.commit()
    conn.close()
    store = SqliteStore(path)
    assert store.migrate() == latest_version() >= 5
    assert store.query_raw_packets("old-1", 0, 10) == [(5, "k", b"\x01\x02")]
    store.close()
