"""The migration that appends the tracked row's online calibration (the gyro's noise measured
standing): rows stored before it (SQLite: final and still staged) read back with every old field
bit for bit and no measurement (NaN, which a restart does not restore), and the table then takes
rows with one, on both backends."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.spec import EstimatorSpec
from estimator.tracked_spec import TRACKED_SPEC
from server.estimation.calibration import stored_calibrations
from server.storage import Store
from server.storage.migrations import (
    MIGRATIONS,
    TRACKED_FIELDS_V13,
    TRACKED_FIELDS_V17,
    latest_version,
)
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SqliteStore
from tests.server.storage.conftest import DT_NS, T0_NS, Backend, batch_of, make_spec_rows

_ADDED = tuple(name for name, _ in TRACKED_FIELDS_V17[len(TRACKED_FIELDS_V13) :])
_VERSION = next(
    m.version for m in MIGRATIONS if m.description.startswith("tracked rows carry the gyro's noise")
)


def _spec_before() -> EstimatorSpec:
    """The tracked spec as it was before the calibration: version 13's fields, none."""
    fields = tuple(f for f in TRACKED_SPEC.fields if f.name not in _ADDED)
    assert tuple((f.name, f.kind) for f in fields) == TRACKED_FIELDS_V13
    return dataclasses.replace(TRACKED_SPEC, fields=fields, calibrations=())


def _open(backend: Backend, specs: tuple[EstimatorSpec, ...]) -> Store:
    s = backend.settings
    store: Store
    if backend.name == "sqlite":
        store = SqliteStore(s.data_dir / s.sqlite_file, specs=specs)
    else:
        assert s.url is not None
        store = PostgresStore(s.url.get_secret_value(), specs=specs)
    return store


def test_rows_stored_before_read_back_without_a_calibration(
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
        old.upsert_vehicle("f1", {"kind": "tracked"}, now_ns=1)
        old.write_estimates(batch_of(before, {"f1": final}))
        if isinstance(old, SqliteStore):  # some rows final, the later ones still staged
            while old.maintain(everything=True):
                pass
        old.write_estimates(batch_of(before, {"f1": staged}))
    finally:
        old.close()

    new = _open(backend, (TRACKED_SPEC,))
    try:
        assert new.migrate() == latest_version() >= _VERSION
        got = new.query_series("f1", 0, 2**62, estimator="tracked")
        want = np.concatenate([final, staged])
        assert got.dtype.names == TRACKED_SPEC.dtype.names and got.shape == want.shape
        for name in want.dtype.names or ():
            np.testing.assert_array_equal(got[name], want[name], err_msg=name)
        for name in _ADDED:
            assert np.isnan(got[name]).all(), name
        assert stored_calibrations(new) == {}  # nothing measured: nothing to restore
        # the converted table takes rows with a measurement, after and beside the old ones
        placed = make_spec_rows(TRACKED_SPEC, 10, T0_NS + 50 * DT_NS, seed=6)
        new.write_estimates(batch_of(TRACKED_SPEC, {"f1": placed}))
        back = new.query_series("f1", T0_NS + 50 * DT_NS, 2**62, estimator="tracked")
        for name in _ADDED:
            np.testing.assert_array_equal(back[name], placed[name], err_msg=name)
        assert set(stored_calibrations(new)) == {("f1", "tracked")}
        assert new.migrate() == latest_version()  # nothing left to do
    finally:
        new.close()
