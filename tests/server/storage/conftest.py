"""Fixtures running every storage test against both backends.

``backend`` is parametrized: ``sqlite`` (a real file in ``tmp_path``) and ``postgresql`` (a fresh
database on the ``pg_url`` server, marked ``postgres``). Each test gets its own database.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest

from estimator.spec import EstimatorSpec
from estimator.types import ESTIMATE_FIELDS, EstimateBatch, empty_estimates
from server.settings import StorageSettings
from server.storage import Store
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SqliteStore
from server.tooling.pgadmin import set_connections_allowed
from tests.server.storage._faults import sqlite_write_locked

T0_NS = 1_763_700_000_000_000_000  # 2025-11-21, a realistic epoch in ns
DT_NS = 100_000_000  # 10 Hz


def make_rows(n: int, start_ns: int = T0_NS, *, seed: int = 0, dt_ns: int = DT_NS) -> np.ndarray:
    """``n`` estimate rows at ``dt_ns`` spacing with random values, NaNs and infinities."""
    rng = np.random.default_rng(seed)
    rows = empty_estimates(n)
    rows["stamp_ns"] = start_ns + np.arange(n, dtype=np.int64) * dt_ns
    for name, kind in ESTIMATE_FIELDS[1:]:
        if kind == "f8":
            rows[name] = rng.normal(0.0, 10.0, n)
        else:
            rows[name] = rng.integers(0, 1 << 9, n)
    if n:
        rows["slip_left_pct"][::5] = np.nan  # not valid
        rows["slip_right_std_pct"][::7] = np.nan
        rows["vg_mps"][0] = np.inf
        rows["accel_mps2"][-1] = -np.inf
        rows["east_m"][n // 2] = 1e-300
    return rows


def make_spec_rows(
    spec: EstimatorSpec, n: int, start_ns: int = T0_NS, *, seed: int = 0, dt_ns: int = DT_NS
) -> np.ndarray:
    """``n`` rows of ``spec``'s dtype at ``dt_ns`` spacing: random values, a NaN and an
    infinity in its second field, random flags."""
    rng = np.random.default_rng(seed)
    rows = spec.empty_rows(n)
    rows["stamp_ns"] = start_ns + np.arange(n, dtype=np.int64) * dt_ns
    for f in spec.fields[1:]:
        if f.kind == "f8":
            rows[f.name] = rng.normal(0.0, 10.0, n)
        else:
            rows[f.name] = rng.integers(0, 1 << 9, n)
    if n > 1:
        second = next(f.name for f in spec.fields[1:] if f.kind == "f8")
        rows[second][0], rows[second][1] = np.nan, -np.inf
    return rows


def batch_of(spec: EstimatorSpec, rows: dict[str, np.ndarray]) -> EstimateBatch:
    """One estimator's rows of several vehicles, ``{vehicle_id: rows}``."""
    return EstimateBatch.of(list(rows.items()), spec)


def assert_rows_equal(got: np.ndarray, want: np.ndarray) -> None:
    """Field-by-field equality with NaN == NaN; dtype names must match."""
    assert got.dtype.names == want.dtype.names
    assert got.shape == want.shape
    for name in want.dtype.names or ():
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


@dataclass
class Backend:
    """One database for one test, and ways to open stores on it and to break it."""

    name: str
    settings: StorageSettings
    _make: Callable[[bool], Store]
    _outage: Callable[[], contextlib.AbstractContextManager[None]]
    _opened: list[Store] = field(default_factory=list)

    def open(self, *, fast_fail: bool = False, migrate: bool = True) -> Store:
        """A store on this test's database (closed at teardown); ``fast_fail`` shortens the
        lock and connect timeouts for outage tests."""
        store = self._make(fast_fail)
        self._opened.append(store)
        if migrate:
            store.migrate()
        return store

    def outage(self) -> contextlib.AbstractContextManager[None]:
        """While active the database refuses writes (SQLite: another process holds the write
        lock; PostgreSQL: the database refuses connections and its sessions are ended)."""
        return self._outage()

    def close_all(self) -> None:
        for store in self._opened:
            store.close()


def _sqlite_backend(tmp_path: Path) -> Backend:
    data_dir = tmp_path / "data"
    settings = StorageSettings.model_validate({"data_dir": data_dir})
    path = data_dir / settings.sqlite_file

    def make(fast_fail: bool) -> Store:
        return SqliteStore(path, busy_timeout_s=0.1 if fast_fail else 5.0)

    return Backend("sqlite", settings, make, lambda: sqlite_write_locked(path))


def _postgres_backend(admin_url: str, url: str) -> Backend:
    dbname = urlsplit(url).path.lstrip("/")
    settings = StorageSettings.model_validate({"url": url})

    def make(fast_fail: bool) -> Store:
        return PostgresStore(url, connect_timeout_s=1.0 if fast_fail else 5.0)

    @contextlib.contextmanager
    def outage() -> Iterator[None]:
        set_connections_allowed(admin_url, dbname, False)
        try:
            yield
        finally:
            set_connections_allowed(admin_url, dbname, True)

    return Backend("postgresql", settings, make, outage)


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def backend(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Backend]:
    if request.param == "sqlite":
        b = _sqlite_backend(tmp_path)
    else:
        admin_url = request.getfixturevalue("pg_url")
        b = _postgres_backend(admin_url, request.getfixturevalue("pg_database_url"))
    try:
        yield b
    finally:
        b.close_all()


@pytest.fixture
def store(backend: Backend) -> Store:
    """A migrated store on a fresh database."""
    return backend.open()
