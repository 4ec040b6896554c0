"""The migration that appends the friction row's position: rows stored before it (SQLite: final
and still staged) read back with every old field bit for bit and no position (NaN), and the
table then takes rows with one, on both backends."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.friction_spec import FRICTION_SPEC
from estimator.spec import EstimatorSpec
from server.storage import Store
from server.storage.migrations import (
    FRICTION_FIELDS_V12,
    FRICTION_FIELDS_V16,
    MIGRATIONS,
    latest_version,
)
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SqliteStore
from tests.server.storage.conftest import DT_NS, T0_NS, Backend, batch_of, make_spec_rows

_ADDED = tuple(name for name, _ in FRICTION_FIELDS_V16[len(FRICTION_FIELDS_V12) :])
_VERSION = next(
    m.version for m in MIGRATIONS if m.description.endswith("friction estimator's position")
)


def _spec_before() -> EstimatorSpec:
    """The friction spec as it was before the position: version 12's fields, no position."""
    fields = tuple(f for f in FRICTION_SPEC.fields if f.name not in _ADDED)
    assert tuple((f.name, f.kind) for f in fields) == FRICTION_FIELDS_V12
    return dataclasses.replace(
        FRICTION_SPEC, fields=fields, position=None, degraded_flags=("HELD",)
    )


def _open(backend: Backend, specs: tuple[EstimatorSpec, ...]) -> Store:
    s = backend.settings
    store: Store
    if backend.name == "sqlite":
        store = SqliteStore(s.data_dir / s.sqlite_file, specs=specs)
    else:
        assert s.url is not None
        store = PostgresStore(s.url.get_secret_value(), specs=specs)
    return store


def test_rows_stored_before_read_back_without_a_position(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    import server.storage.migrations as mig

    before = _spec_before()
    final, staged = make_spec_rows(before, 30, seed=4), make_spec_rows(before, 20, seed=5)
    staged["stamp_ns"] += 30 * DT_NS
    old = _open(backend, (before,))
    try:
        with monkeypatch.context() as m:
            m.setattr(mig, "MIGRATIONS", mig.MIGRATIONS[: _VERSION - 1])
            assert old.migrate() == _VERSION - 1
        old.upsert_vehicle("f1", {"kind": "wheeled_4wd_steered"}, now_ns=1)
        old.write_estimates(batch_of(before, {"f1": final}))
        if isinstance(old, SqliteStore):  # some rows final, the later ones still staged
            while old.maintain(everything=True):
                pass
        old.write_estimates(batch_of(before, {"f1": staged}))
    finally:
        old.close()

    new = _open(backend, (FRICTION_SPEC,))
    try:
        assert new.migrate() == latest_version() >= _VERSION
        got = new.query_series("f1", 0, 2**62, estimator="friction")
        want = np.concatenate([final, staged])
        assert got.dtype.names == FRICTION_SPEC.dtype.names and got.shape == want.shape
        for name in want.dtype.names or ():
            np.testing.assert_array_equal(got[name], want[name], err_msg=name)
        for name in _ADDED:
            assert np.isnan(got[name]).all(), name
        # the converted table takes rows with a position, after and beside the old ones
        placed = make_spec_rows(FRICTION_SPEC, 10, T0_NS + 50 * DT_NS, seed=6)
        new.write_estimates(batch_of(FRICTION_SPEC, {"f1": placed}))
        back = new.query_series("f1", T0_NS + 50 * DT_NS, 2**62, estimator="friction")
        for name in _ADDED:
            np.testing.assert_array_equal(back[name], placed[name], err_msg=name)
        assert new.migrate() == latest_version()  # nothing left to do
    finally:
        new.close()
