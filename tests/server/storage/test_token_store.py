"""Access-token methods of the Store, on SQLite and PostgreSQL alike; the database keeps hashes."""

from __future__ import annotations

import sqlite3
from typing import Any

import psycopg
import pytest

from server.storage import StorageDataError, Store, TokenRecord
from server.tokens import Role, hash_token, issue_token
from tests.server.storage.conftest import Backend


def _raw_rows(backend: Backend) -> list[tuple[Any, ...]]:
    """Every api_tokens row, read past the store."""
    sql = "SELECT id, name, role, token_sha256 FROM api_tokens ORDER BY id"
    if backend.name == "sqlite":
        path = backend.settings.data_dir / backend.settings.sqlite_file
        with sqlite3.connect(path) as conn:
            return conn.execute(sql).fetchall()
    assert backend.settings.url is not None
    with psycopg.connect(backend.settings.url.get_secret_value()) as conn:
        return conn.execute(sql).fetchall()


def test_create_get_list(store: Store) -> None:
    a = store.create_token("alice", "admin", "a" * 64, 100)
    b = store.create_token("grafana", "viewer", "b" * 64, 200)
    assert a == TokenRecord(a.id, "alice", "admin", 100, None, None)
    assert b.id > a.id
    assert store.get_token("a" * 64) == a
    assert store.get_token("c" * 64) is None
    assert store.list_tokens() == [a, b]
    assert not a.revoked


def test_duplicate_hash_and_unknown_role_are_refused(store: Store) -> None:
    store.create_token("one", "viewer", "d" * 64, 1)
    with pytest.raises(StorageDataError):
        store.create_token("two", "viewer", "d" * 64, 2)
    with pytest.raises(StorageDataError):
        store.create_token("root", "root", "e" * 64, 3)
    assert [t.name for t in store.list_tokens()] == ["one"]


def test_touch_and_revoke(store: Store) -> None:
    t = store.create_token("op", "operator", "f" * 64, 10)
    store.touch_token(t.id, 20)
    got = store.get_token("f" * 64)
    assert got is not None and got.last_used_ns == 20
    revoked = store.revoke_token(t.id, 30)
    assert revoked is not None and revoked.revoked_ns == 30 and revoked.revoked
    again = store.revoke_token(t.id, 40)  # keeps the first time
    assert again is not None and again.revoked_ns == 30
    assert store.revoke_token(t.id + 1000, 50) is None
    got = store.get_token("f" * 64)
    assert got is not None and got.revoked_ns == 30  # still found: the caller refuses it


def test_database_holds_only_the_hash(store: Store, backend: Backend) -> None:
    token, record = issue_token(store, "dash", Role.VIEWER, 5)
    rows = _raw_rows(backend)
    assert rows == [(record.id, "dash", "viewer", hash_token(token))]
    assert token not in repr(rows)
    assert store.get_token(hash_token(token)) == record


def test_tokens_survive_reopening(backend: Backend) -> None:
    first = backend.open()
    token, record = issue_token(first, "keep", Role.ADMIN, 7)
    first.close()
    assert backend.open().get_token(hash_token(token)) == record


def test_expiry_is_stored_and_read_back(store: Store) -> None:
    never = store.create_token("forever", "viewer", "1" * 64, 100)
    soon = store.create_token("shift", "operator", "2" * 64, 100, expires_ns=100 + 8 * 3600 * 10**9)
    assert never.expires_ns is None and soon.expires_ns == 100 + 8 * 3600 * 10**9
    got = store.get_token("2" * 64)
    assert got == soon
    assert got.valid_at(soon.expires_ns - 1) and not got.valid_at(soon.expires_ns)
    assert never.valid_at(2**62) and not never.expired(2**62)
    assert [t.expires_ns for t in store.list_tokens()] == [None, soon.expires_ns]
    revoked = store.revoke_token(soon.id, 200)
    assert revoked is not None and revoked.expires_ns == soon.expires_ns
    assert not revoked.valid_at(300)  # revoked before it expired


def test_issue_token_sets_the_expiry_from_a_lifetime(store: Store) -> None:
    _, record = issue_token(store, "temp", Role.VIEWER, 1_000, expires_in_ns=5_000)
    assert record.expires_ns == 6_000
    for bad in (0, -1, 11 * 366 * 86_400 * 10**9):
        with pytest.raises(ValueError):
            issue_token(store, "bad", Role.VIEWER, 1_000, expires_in_ns=bad)
    assert [t.name for t in store.list_tokens()] == ["temp"]
