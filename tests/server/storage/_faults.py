"""Fault injection for the storage tests: a SQLite database locked by another connection."""

from __future__ import annotations

import contextlib
import sqlite3
from collections.abc import Iterator
from pathlib import Path

__all__ = ["sqlite_write_locked"]


@contextlib.contextmanager
def sqlite_write_locked(path: Path | str) -> Iterator[None]:
    """Hold the write lock of a SQLite database from another connection, as a stuck process
    would: writers time out with "database is locked" until the block exits."""
    conn = sqlite3.connect(path, isolation_level=None)
    try:
        conn.execute("BEGIN EXCLUSIVE")
        yield
        conn.execute("ROLLBACK")
    finally:
        conn.close()
