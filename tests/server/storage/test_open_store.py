"""open_store: backend selection from StorageSettings."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.settings import StorageSettings
from server.storage import open_store
from server.storage.migrations import latest_version
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SqliteStore


def test_sqlite_by_default_in_data_dir(tmp_path: Path) -> None:
    settings = StorageSettings.model_validate({"data_dir": tmp_path / "d", "sqlite_file": "x.db"})
    store = open_store(settings)
    try:
        assert isinstance(store, SqliteStore) and store.dialect == "sqlite"
        assert (tmp_path / "d" / "x.db").is_file()
        assert store.schema_version() == latest_version()
    finally:
        store.close()


def test_without_migrate(tmp_path: Path) -> None:
    store = open_store(StorageSettings.model_validate({"data_dir": tmp_path}), migrate=False)
    try:
        assert store.schema_version() == 0  # type: ignore[attr-defined]
    finally:
        store.close()


def test_rejects_other_urls(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="postgresql"):
        open_store(StorageSettings.model_validate({"url": "mysql://x@y/z"}))


@pytest.mark.postgres
def test_postgres_by_url(pg_database_url: str) -> None:
    store = open_store(StorageSettings.model_validate({"url": pg_database_url}))
    try:
        assert isinstance(store, PostgresStore) and store.dialect == "postgresql"
        assert store.ping() and store.schema_version() == latest_version()
    finally:
        store.close()


@pytest.mark.postgres
def test_postgres_unreachable_raises_storage_error(pg_url: str) -> None:
    from server.storage import StorageError
    from server.tooling.pgadmin import database_url

    url = database_url(pg_url, "slipfleet_does_not_exist")
    with pytest.raises(StorageError):
        open_store(StorageSettings.model_validate({"url": url}))
