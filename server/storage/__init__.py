"""Storage: the :class:`Store` interface, SQLite and PostgreSQL stores, the batching writer.

Typical use in the app lifespan::

    store = open_store(settings.storage)          # migrated, ready
    writer = StoreWriter(store, settings.storage).start()
    ...
    writer.close()                                 # flushes the backlog
    store.close()
"""

from __future__ import annotations

from server.settings import StorageSettings
from server.storage.base import StorageDataError, StorageError, Store, TokenRecord, VehicleRecord
from server.storage.writer import StoreWriter, WriterStats

__all__ = [
    "StorageDataError",
    "StorageError",
    "Store",
    "StoreWriter",
    "TokenRecord",
    "VehicleRecord",
    "WriterStats",
    "open_store",
]

_PG_SCHEMES = ("postgresql://", "postgres://", "postgresql+psycopg://")


def open_store(settings: StorageSettings, *, migrate: bool = True) -> Store:
    """Open the configured store: PostgreSQL when ``settings.url`` is ``postgresql://…``,
    otherwise SQLite at ``settings.data_dir / settings.sqlite_file``.

    With ``migrate`` (the default) pending schema migrations are applied before returning.

    Raises
    ------
    StorageError
        The database is unreachable or refused the migration.
    ValueError
        ``settings.url`` names something other than PostgreSQL.
    """
    store: Store
    url = settings.url.get_secret_value() if settings.url is not None else ""
    if url:
        if not url.startswith(_PG_SCHEMES):
            raise ValueError("storage.url must be a postgresql:// URL (leave it unset for SQLite)")
        from server.storage.postgres import PostgresStore

        if url.startswith("postgresql+psycopg://"):
            url = "postgresql://" + url.removeprefix("postgresql+psycopg://")
        store = PostgresStore(url)
    else:
        from server.storage.sqlite import SqliteStore

        store = SqliteStore(settings.data_dir / settings.sqlite_file)
    if migrate:
        try:
            store.migrate()
        except BaseException:
            store.close()
            raise
    return store
