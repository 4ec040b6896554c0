"""Shared steps of the tests of a migration that appends fields to an estimator's table.

A store stopped one version short of the migration stores rows of the spec as it was (some
final, the later ones still staged on SQLite); the migrated store must read them back with every
old field bit for bit and the appended ones NaN, and then take rows that carry them.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from estimator.spec import EstimatorSpec
from server.storage import Store
from server.storage.migrations import MIGRATIONS, latest_version
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SqliteStore
from tests.server.storage.conftest import DT_NS, T0_NS, Backend, batch_of, make_spec_rows

VEHICLE = "f1"

#: An estimator table's fields as a migration lists them: ``(name, kind)`` in column order.
Fields = tuple[tuple[str, str], ...]


def migration_version(description_start: str) -> int:
    """The version of the migration whose description starts with ``description_start``."""
    return next(m.version for m in MIGRATIONS if m.description.startswith(description_start))


def appended_names(old_fields: Fields, new_fields: Fields) -> tuple[str, ...]:
    """Names of the fields the migration appended: those of ``new_fields`` past ``old_fields``."""
    return tuple(name for name, _ in new_fields[len(old_fields) :])


def spec_before(
    spec: EstimatorSpec, old_fields: Fields, added: tuple[str, ...], **changes: Any
) -> EstimatorSpec:
    """``spec`` as it was before the migration: without the ``added`` fields (what is left must
    be ``old_fields``, asserted), and ``changes`` to its other attributes."""
    fields = tuple(f for f in spec.fields if f.name not in added)
    assert tuple((f.name, f.kind) for f in fields) == old_fields
    return dataclasses.replace(spec, fields=fields, **changes)


def open_store(backend: Backend, specs: tuple[EstimatorSpec, ...]) -> Store:
    """A store of ``backend`` serving ``specs`` (not migrated)."""
    s = backend.settings
    if backend.name == "sqlite":
        return SqliteStore(s.data_dir / s.sqlite_file, specs=specs)
    assert s.url is not None
    return PostgresStore(s.url.get_secret_value(), specs=specs)


def store_before_migration(
    backend: Backend,
    before: EstimatorSpec,
    version: int,
    kind: str,
    monkeypatch: pytest.MonkeyPatch,
) -> np.ndarray:
    """Rows of ``before`` stored for a vehicle of ``kind`` by a store migrated to ``version − 1``
    (on SQLite 30 final, 20 still staged); returns them, (50,) in stamp order."""
    import server.storage.migrations as mig

    final, staged = make_spec_rows(before, 30, seed=4), make_spec_rows(before, 20, seed=5)
    staged["stamp_ns"] += 30 * DT_NS
    old = open_store(backend, (before,))
    try:
        with monkeypatch.context() as m:
            m.setattr(mig, "MIGRATIONS", mig.MIGRATIONS[: version - 1])
            assert old.migrate() == version - 1
        old.upsert_vehicle(VEHICLE, {"kind": kind}, now_ns=1)
        old.write_estimates(batch_of(before, {VEHICLE: final}))
        if isinstance(old, SqliteStore):
            while old.maintain(everything=True):
                pass
        old.write_estimates(batch_of(before, {VEHICLE: staged}))
    finally:
        old.close()
    return np.concatenate([final, staged])


@contextlib.contextmanager
def migrated(
    backend: Backend,
    spec: EstimatorSpec,
    before: EstimatorSpec,
    version: int,
    kind: str,
    monkeypatch: pytest.MonkeyPatch,
) -> Iterator[tuple[Store, np.ndarray]]:
    """Rows of ``before`` stored one version short of ``version``
    (:func:`store_before_migration`), then a store of ``spec`` migrated to the latest version
    (asserted): yields it with those rows. On leaving, a second migrate must find nothing left
    to do; the store is closed."""
    want = store_before_migration(backend, before, version, kind, monkeypatch)
    new = open_store(backend, (spec,))
    try:
        assert new.migrate() == latest_version() >= version
        yield new, want
        assert new.migrate() == latest_version()  # nothing left to do
    finally:
        new.close()


def assert_old_rows_read_back(
    store: Store, spec: EstimatorSpec, want: np.ndarray, added: tuple[str, ...]
) -> None:
    """The migrated ``store`` gives ``want`` back field for field, the ``added`` fields NaN."""
    got = store.query_series(VEHICLE, 0, 2**62, estimator=spec.name)
    assert got.dtype.names == spec.dtype.names and got.shape == want.shape
    for name in want.dtype.names or ():
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    for name in added:
        assert np.isnan(got[name]).all(), name


def assert_new_rows_taken(store: Store, spec: EstimatorSpec, added: tuple[str, ...]) -> None:
    """The migrated table takes rows with the ``added`` fields after the old ones."""
    start_ns = T0_NS + 50 * DT_NS
    placed = make_spec_rows(spec, 10, start_ns, seed=6)
    store.write_estimates(batch_of(spec, {VEHICLE: placed}))
    back = store.query_series(VEHICLE, start_ns, 2**62, estimator=spec.name)
    for name in added:
        np.testing.assert_array_equal(back[name], placed[name], err_msg=name)
