"""Rows of several estimators in one store: a table set per spec, on SQLite and PostgreSQL."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from estimator.catalog import SPECS
from estimator.friction_spec import FRICTION_SPEC
from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.spec import EstimatorSpec, FieldSpec
from estimator.tracked_spec import TRACKED_SPEC
from server.storage import StorageDataError, StorageError, Store
from server.storage._columns import spec_fields
from server.storage.migrations import (
    FRICTION_FIELDS_V19,
    MDSF_FIELDS_V15,
    REFERENCE_SPEED_FIELDS_V10,
    TRACKED_FIELDS_V20,
    estimator_table_steps,
)
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SqliteStore
from tests.server.storage.conftest import (
    DT_NS,
    T0_NS,
    Backend,
    assert_rows_equal,
    batch_of,
    make_spec_rows,
)

REF = REFERENCE_SPEED_SPEC


def _register(store: Store, *vehicle_ids: str) -> None:
    for vid in vehicle_ids:
        store.upsert_vehicle(vid, {"kind": "wheeled_rear_drive"}, now_ns=T0_NS)


def _both(store: Store, vid: str, n_mdsf: int, n_ref: int, start_ns: int = T0_NS) -> tuple:
    mdsf = make_spec_rows(MDSF_SPEC, n_mdsf, start_ns, seed=1)
    ref = make_spec_rows(REF, n_ref, start_ns + DT_NS // 2, seed=2)
    written = store.write_estimates(batch_of(MDSF_SPEC, {vid: mdsf}), batch_of(REF, {vid: ref}))
    assert written == n_mdsf + n_ref
    return mdsf, ref


def test_frozen_field_lists_match_the_specs() -> None:
    """A spec change must come with a migration that converts its table."""
    assert spec_fields(MDSF_SPEC) == MDSF_FIELDS_V15
    assert spec_fields(REF) == REFERENCE_SPEED_FIELDS_V10
    assert spec_fields(FRICTION_SPEC) == FRICTION_FIELDS_V19
    assert spec_fields(TRACKED_SPEC) == TRACKED_FIELDS_V20


def test_every_catalog_spec_has_its_tables(store: Store) -> None:
    assert set(SPECS) == {"mdsf", "reference_speed", "friction", "tracked"}
    _register(store, "v1")
    for spec in SPECS.values():
        assert store.query_series("v1", 0, 2**62, estimator=spec.name).dtype == spec.dtype
        rows = make_spec_rows(spec, 30, T0_NS, seed=3)
        assert store.write_estimates(batch_of(spec, {"v1": rows})) == 30
        assert_rows_equal(store.query_series("v1", 0, 2**62, estimator=spec.name), rows)


def test_two_estimators_of_one_vehicle_round_trip(store: Store) -> None:
    _register(store, "v1", "v2")
    mdsf, ref = _both(store, "v1", 120, 80)
    got_ref = store.query_series("v1", 0, 2**62, estimator="reference_speed")
    assert got_ref.dtype == REF.dtype
    assert_rows_equal(got_ref, ref)
    assert_rows_equal(store.query_series("v1", 0, 2**62, estimator="mdsf"), mdsf)
    assert_rows_equal(store.query_series("v1", 0, 2**62), mdsf)  # the default: MDSF
    # a field subset of the other estimator, a range, another vehicle empty
    part = store.query_series(
        "v1", T0_NS, T0_NS + 10 * DT_NS, ["flags", "speed_mps"], estimator="reference_speed"
    )
    assert part.dtype.names == ("stamp_ns", "flags", "speed_mps")
    np.testing.assert_array_equal(part["speed_mps"], ref["speed_mps"][:10])
    assert len(store.query_series("v2", 0, 2**62, estimator="reference_speed")) == 0
    # the replay of both is ignored, per estimator
    assert store.write_estimates(batch_of(REF, {"v1": ref}), batch_of(MDSF_SPEC, {"v1": mdsf})) == 0
    # the same stamps under another estimator are other rows
    same = make_spec_rows(REF, 5, T0_NS, seed=3)
    assert store.write_estimates(batch_of(REF, {"v2": same})) == 5
    assert store.estimators_with_rows("v1") == ["mdsf", "reference_speed"]
    assert store.estimators_with_rows("v2") == ["reference_speed"]
    assert store.estimators_with_rows("nobody") == []


def test_unknown_estimator_and_field_are_refused(store: Store) -> None:
    _register(store, "v1")
    with pytest.raises(ValueError, match="wheel_torque"):
        store.query_series("v1", 0, 2**62, estimator="wheel_torque")
    with pytest.raises(ValueError, match="wheel_torque"):
        store.latest("v1", estimator="wheel_torque")
    with pytest.raises(ValueError, match="vg_mps"):
        store.query_series("v1", 0, 2**62, ["vg_mps"], estimator="reference_speed")


def test_latest_and_latest_all_per_estimator(store: Store) -> None:
    _register(store, "a", "b")
    mdsf_a, ref_a = _both(store, "a", 30, 20)
    ref_b = make_spec_rows(REF, 7, T0_NS + 100 * DT_NS, seed=5)
    store.write_estimates(batch_of(REF, {"b": ref_b}))
    got = store.latest("a", estimator="reference_speed")
    assert got is not None and got.shape == () and got.dtype == REF.dtype
    assert_rows_equal(got.reshape(1), ref_a[-1:])
    mdsf_latest = store.latest("a")
    assert mdsf_latest is not None
    assert_rows_equal(mdsf_latest.reshape(1), mdsf_a[-1:])
    assert store.latest("b") is None  # no MDSF rows
    ref_all = store.latest_all(estimator="reference_speed")
    assert set(ref_all) == {"a", "b"}
    assert_rows_equal(ref_all["b"].reshape(1), ref_b[-1:])
    assert set(store.latest_all(estimator="mdsf")) == {"a"}


def test_retention_reaches_every_estimator(store: Store) -> None:
    _register(store, "a", "b")
    _both(store, "a", 100, 100)
    _both(store, "b", 50, 10)
    cutoff = T0_NS + 30 * DT_NS
    # MDSF rows at T0 + k·DT, reference rows half a tick later: 30 + 30 of a, 30 + 10 of b
    assert store.delete_older_than(cutoff) == 30 + 30 + 30 + 10
    for vid, left_mdsf, left_ref in (("a", 70, 70), ("b", 20, 0)):
        assert len(store.query_series(vid, 0, 2**62)) == left_mdsf
        assert len(store.query_series(vid, 0, 2**62, estimator="reference_speed")) == left_ref
    assert store.delete_older_than(cutoff) == 0


def test_delete_vehicle_removes_every_estimators_rows(store: Store) -> None:
    _register(store, "gone", "kept")
    _both(store, "gone", 40, 40)
    _, kept_ref = _both(store, "kept", 5, 6)
    assert store.delete_vehicle("gone")
    for spec in SPECS.values():
        assert len(store.query_series("gone", 0, 2**62, estimator=spec.name)) == 0
        assert store.latest("gone", estimator=spec.name) is None
    assert store.estimators_with_rows("gone") == []
    _register(store, "gone")  # registered again: starts empty
    assert store.estimators_with_rows("gone") == []
    assert_rows_equal(store.query_series("kept", 0, 2**62, estimator="reference_speed"), kept_ref)


def _changed_reference_spec() -> EstimatorSpec:
    """The reference speed with one more field: what a spec change without migration is."""
    extra = FieldSpec("slope_rad", "f8", "rad", "slope")
    return dataclasses.replace(REF, fields=(*REF.fields[:-1], extra, REF.fields[-1]))


def _store_with(backend: Backend, specs: tuple[EstimatorSpec, ...]) -> Store:
    if backend.name == "sqlite":
        return SqliteStore(backend.settings.data_dir / backend.settings.sqlite_file, specs=specs)
    url = backend.settings.url
    assert url is not None
    return PostgresStore(url.get_secret_value(), specs=specs)


def test_a_spec_its_table_no_longer_fits_is_refused(backend: Backend) -> None:
    backend.open()  # migrated by today's specs
    changed = _store_with(backend, (MDSF_SPEC, _changed_reference_spec()))
    try:
        with pytest.raises(StorageError, match=r"'reference_speed'.*no longer match"):
            changed.migrate()
        with pytest.raises(StorageError, match="'reference_speed'"):
            changed.query_series("v1", 0, 2**62)  # refused on first use too, not only at start
    finally:
        changed.close()


def test_a_spec_without_a_table_is_refused(backend: Backend) -> None:
    backend.open()
    new = dataclasses.replace(REF, name="wheel_torque", title="no migration made its table")
    store = _store_with(backend, (MDSF_SPEC, new))
    try:
        with pytest.raises(StorageError, match="'wheel_torque' has no table"):
            store.migrate()
    finally:
        store.close()


def test_rows_of_a_spec_the_store_does_not_serve_are_refused_as_data(backend: Backend) -> None:
    store = _store_with(backend, (MDSF_SPEC,))  # serves MDSF only
    try:
        store.migrate()
        _register(store, "v1")
        with pytest.raises(StorageDataError, match="reference_speed"):
            store.write_estimates(batch_of(REF, {"v1": make_spec_rows(REF, 3)}))
        # rows of a spec it does not serve are still deleted with the vehicle and by retention
        other = backend.open()
        assert other.write_estimates(batch_of(REF, {"v1": make_spec_rows(REF, 3)})) == 3
        assert store.delete_older_than(T0_NS + 2 * DT_NS) == 2
        assert store.delete_vehicle("v1")
        assert len(other.query_series("v1", 0, 2**62, estimator="reference_speed")) == 0
    finally:
        store.close()


def test_table_steps_refuse_names_that_are_not_identifiers() -> None:
    with pytest.raises(ValueError, match="identifier"):
        estimator_table_steps(
            "x; DROP TABLE vehicles", "estimates_x", (("stamp_ns", "i8"),), "sqlite"
        )
    with pytest.raises(ValueError, match="stamp_ns"):
        estimator_table_steps("x", "estimates_x", (("speed_mps", "f8"),), "sqlite")


def test_sqlite_each_estimator_is_staged_and_moved_on_its_own(tmp_path: Path) -> None:
    """Rows of both estimators stage, move in rounds of their own, and read back once."""
    store = SqliteStore(tmp_path / "s.sqlite")
    store.migrate()
    _register(store, "a", "b")
    mdsf = {v: make_spec_rows(MDSF_SPEC, 60, seed=k) for k, v in enumerate("ab")}
    ref = {v: make_spec_rows(REF, 60, seed=k + 5) for k, v in enumerate("ab")}
    for lo in range(0, 60, 10):  # a second at a time, as a server commits
        store.write_estimates(
            batch_of(MDSF_SPEC, {v: r[lo : lo + 10] for v, r in mdsf.items()}),
            batch_of(REF, {v: r[lo : lo + 10] for v, r in ref.items()}),
        )
        while store.maintain():
            for v in "ab":  # read once at every step
                assert_rows_equal(store.query_series(v, 0, 2**62), mdsf[v][: lo + 10])
                got = store.query_series(v, 0, 2**62, estimator="reference_speed")
                assert_rows_equal(got, ref[v][: lo + 10])
    conn = sqlite3.connect(tmp_path / "s.sqlite")
    final = {
        t: conn.execute(f"SELECT count(*) FROM {t}").fetchone()[0]
        for t in ("estimates", "estimates_recent", "estimates_reference_speed",
                  "estimates_reference_speed_recent")
    }  # fmt: skip
    conn.close()
    # rows older than a second behind the newest were moved, per estimator
    assert final["estimates"] > 0 and final["estimates_reference_speed"] > 0
    assert final["estimates"] + final["estimates_recent"] == 120
    assert final["estimates_reference_speed"] + final["estimates_reference_speed_recent"] == 120
    store.close()
