"""Versioned migrations: idempotent, concurrent-safe, refuse a newer schema."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimator.config import TrackedConfig, Wheeled4wdSteeredConfig, vehicle_config_from_dict
from server.storage import StorageError, open_store
from server.storage.migrations import (
    _VERSION_TABLE,
    MDSF_CALIBRATION_FIELDS_V15,
    MIGRATIONS,
    SQLITE_PACKED_FIELDS,
    apply_pending,
    latest_version,
)
from server.storage.sqlite import SqliteStore
from tests.server.storage.conftest import DT_NS, T0_NS, Backend, assert_rows_equal, make_rows


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
            assert isinstance(sql, str)
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


def _version_5_database(path: Path, vehicles: dict[int, np.ndarray]) -> None:
    """A SQLite file at schema version 5 holding ``{vkey: rows}`` the way version 5 stored them:
    every field a column (NaN as NULL) plus the row's packed bytes."""
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("BEGIN")
    assert apply_pending(lambda sql, p: conn.execute(sql, p).fetchall(), "sqlite", target=5) == (
        5,
        [1, 2, 3, 4, 5],
    )
    names = [name for name, _ in SQLITE_PACKED_FIELDS]
    for vkey, rows in vehicles.items():
        conn.execute(
            "INSERT INTO vehicles (vkey, vehicle_id, config, created_ns, updated_ns) "
            "VALUES (?, ?, '{}', 1, 1)",
            (vkey, f"veh-{vkey}"),
        )
        old = _before_v15(rows)
        size = old.dtype.itemsize
        buf = old.tobytes()
        conn.executemany(
            f"INSERT INTO estimates (vkey, {', '.join(names)}, packed) "
            f"VALUES ({vkey}, {', '.join('?' * (len(names) + 1))})",
            [(*v, buf[i * size : (i + 1) * size]) for i, v in enumerate(old.tolist())],
        )
    conn.execute("COMMIT")
    conn.close()


def _before_v15(rows: np.ndarray) -> np.ndarray:
    """``rows`` in MDSF's layout of versions 6-14 (without the calibration fields)."""
    old = np.zeros(rows.shape[0], dtype=[(n, "<" + k) for n, k in SQLITE_PACKED_FIELDS])
    for name, _ in SQLITE_PACKED_FIELDS:
        old[name] = rows[name]
    return old


def _uncalibrated(rows: np.ndarray) -> np.ndarray:
    """``rows`` as stored before version 15 read back after it: calibration fields NaN."""
    out = rows.copy()
    for name, _ in MDSF_CALIBRATION_FIELDS_V15:
        out[name] = np.nan
    return out


def test_sqlite_estimates_are_packed_by_migration_6(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Version 5 rows with packed bytes, without them (written before version 3) and with bytes
    of another size all read back identically after the move to packed-only rows."""
    import server.storage.migrations as mig

    monkeypatch.setattr(mig, "_V6_REPACK_PAGE_ROWS", 7)  # several pages of rows to pack
    path = tmp_path / "v5.sqlite"
    packed, mixed, unpacked = (
        _uncalibrated(make_rows(n, seed=seed)) for n, seed in ((40, 1), (30, 2), (25, 3))
    )
    mixed["vl_mps"][::3] = np.nan  # NULL in the columns of rows that lose their bytes
    _version_5_database(path, {3: packed, 7: mixed, 12: unpacked})
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("UPDATE estimates SET packed = NULL WHERE vkey = 12")
    conn.execute("UPDATE estimates SET packed = NULL WHERE vkey = 7 AND stamp_ns % 3 = 0")
    conn.execute("UPDATE estimates SET packed = x'00ff' WHERE vkey = 7 AND stamp_ns = ?", (T0_NS,))
    assert conn.execute("SELECT count(*) FROM estimates WHERE packed IS NULL").fetchone()[0] > 25
    conn.close()

    store = SqliteStore(path)
    assert store.schema_version() == 5
    assert store.migrate() == latest_version() >= 6
    assert store.table_columns("estimates") == ["vkey", "stamp_ns", "packed"]
    for vkey, rows in ((3, packed), (7, mixed), (12, unpacked)):
        vid = f"veh-{vkey}"
        assert_rows_equal(store.query_series(vid, 0, 2**62), rows)
        latest = store.latest(vid)
        assert latest is not None
        assert_rows_equal(latest.reshape(1), rows[-1:])
    assert set(store.latest_all()) == {"veh-3", "veh-7", "veh-12"}
    # the primary key came along: the same rows again are not duplicated
    again = _uncalibrated(make_rows(26, seed=3))
    assert store.write_estimates([("veh-7", mixed), ("veh-12", again)]) == 1
    assert store.delete_older_than(T0_NS + 10 * DT_NS) == 30
    assert store.delete_vehicle("veh-3")
    assert len(store.query_series("veh-3", 0, 2**62)) == 0
    assert store.migrate() == latest_version()  # nothing left to do
    store.close()


def test_sqlite_migration_8_bounds_the_rows_already_final(tmp_path: Path) -> None:
    """A version-7 file with final and staged rows gets ``estimates_horizon`` at its newest
    final row: replays of those rows are still refused (keeping the stored values), newer rows
    are staged."""
    path = tmp_path / "v7.sqlite"
    rows = {1: _uncalibrated(make_rows(40)), 2: _uncalibrated(make_rows(40, seed=1))}
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("BEGIN")
    assert apply_pending(lambda sql, p: conn.execute(sql, p).fetchall(), "sqlite", target=7)[0] == 7
    for vkey, r in rows.items():
        conn.execute(
            "INSERT INTO vehicles (vkey, vehicle_id, config, created_ns, updated_ns) "
            "VALUES (?, ?, '{}', 1, 1)",
            (vkey, f"v{vkey}"),
        )
        for table, part in (("estimates", r[:30]), ("estimates_recent", r[30:])):
            conn.executemany(
                f"INSERT INTO {table} (vkey, stamp_ns, packed) VALUES (?, ?, ?)",
                [(vkey, int(one["stamp_ns"]), one.tobytes()) for one in _before_v15(part)],
            )
    conn.execute("COMMIT")
    conn.close()
    store = SqliteStore(path)
    assert store.migrate() == latest_version() >= 8
    assert store._read("SELECT newest_ns FROM estimates_horizon") == [
        (int(rows[1]["stamp_ns"][29]),)
    ]
    changed = {f"v{vkey}": r.copy() for vkey, r in rows.items()}
    for r in changed.values():
        r["vg_mps"] += 1.0
    assert store.write_estimates(list(changed.items())) == 0  # final and staged: both refused
    for vkey, r in rows.items():
        assert_rows_equal(store.query_series(f"v{vkey}", 0, 2**62), r)
    newer = make_rows(5, start_ns=T0_NS + 40 * DT_NS, seed=3)
    assert store.write_estimates([("v1", newer)]) == 5
    assert_rows_equal(store.query_series("v1", 0, 2**62), np.concatenate([rows[1], newer]))
    store.close()


def test_sqlite_migration_8_on_an_empty_database(tmp_path: Path) -> None:
    store = SqliteStore(tmp_path / "s.sqlite")
    store.migrate()
    assert store._read("SELECT id, newest_ns FROM estimates_horizon") == [(0, -(2**63))]
    store.close()


_V9_REAR = {  # what version 9's code stored for a rear-drive vehicle
    "kind": "wheeled_rear_drive",
    "geometry": {
        "h0_m": 1.1,
        "h1_m": 1.5,
        "track_width_m": 1.9,
        "wheel_radius_left_m": 0.8,
        "wheel_radius_right_m": 0.9,
        "antenna_offset_m": [0.2, 0.4],
        "imu_offset_m": [0.0, 0.1],
    },
    "encoder": {"teeth_per_rev": 90, "has_direction": True},
    "noise": {
        "gnss_vel_std_mps": 0.04,
        "accel_std_mps2": 0.06,
        "gyro_std_radps": 0.004,
        "accel_bias_walk_mps2": 0.003,
        "gnss_pos_std_m": 0.02,
    },
    "slip": {
        "min_ground_speed_mps": 0.3,
        "band_edges_pct": [10.0, 20.0],
        "alert_threshold_pct": 25.0,
        "alert_hold_s": 4.0,
        "settle_max_change": 0.5,
    },
    "estimators": ["mdsf"],
}


def test_stored_configs_move_to_the_shape_of_their_kind(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Configs stored by version 9 (every kind in the rear-drive shape, or no kind at all) read
    as their kind after version 11, values kept; an invalid one is kept as it was."""
    import server.storage.migrations as mig
    from server.storage._columns import SpecTables

    store = backend.open(migrate=False)
    with monkeypatch.context() as m:
        m.setattr(mig, "MIGRATIONS", mig.MIGRATIONS[:9])
        # a version-9 database has no estimator tables to check yet
        m.setattr(SpecTables, "reload", lambda self: {})
        assert store.migrate() == 9
    old = {
        "rear": _V9_REAR,
        "empty": {},
        "crawler": {**_V9_REAR, "kind": "tracked", "estimators": []},
        "utility": {**_V9_REAR, "kind": "wheeled_4wd_steered"},
        "broken": {"geometry": {"h0_m": -1}},
    }
    for vid, config in old.items():
        store.upsert_vehicle(vid, config, now_ns=1)
    assert store.migrate() == latest_version() >= 11
    new = {vid: store.get_vehicle(vid).config for vid in old}  # type: ignore[union-attr]

    assert new["rear"] == _V9_REAR  # the rear-drive shape did not change
    assert new["empty"] == {"kind": "wheeled_rear_drive"}
    assert new["broken"] == {"kind": "wheeled_rear_drive", "geometry": {"h0_m": -1}}
    crawler = vehicle_config_from_dict(new["crawler"])
    assert isinstance(crawler, TrackedConfig)
    assert crawler.geometry.track_gauge_m == 1.9
    assert crawler.geometry.imu_lever_arm_m == (0.0, 0.1, 1.1)
    assert crawler.geometry.antenna_lever_arm_m == pytest.approx((0.2, 0.4, 2.6))
    assert crawler.noise.accel_std_mps2 == 0.06 and crawler.slip.band_edges_pct == (10.0, 20.0)
    utility = vehicle_config_from_dict(new["utility"])
    assert isinstance(utility, Wheeled4wdSteeredConfig)
    assert utility.chassis.front_track_m == utility.chassis.rear_track_m == 1.9
    assert utility.tyre.unloaded_radius_m == pytest.approx(0.85)
    assert utility.estimators == ("mdsf",)
    assert store.migrate() == latest_version()  # a second run changes nothing
    assert store.get_vehicle("crawler").config == new["crawler"]  # type: ignore[union-attr]


def test_mdsf_rows_gain_the_calibration_fields_in_migration_15(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    """MDSF rows written by version 14 (final and, on SQLite, staged) read back after version
    15 with every earlier field as it was and the calibration fields NaN; new rows keep them."""
    import dataclasses as dc

    import server.storage.migrations as mig
    from estimator.mdsf_spec import MDSF_SPEC
    from server.storage.postgres import PostgresStore
    from tests.server.storage.conftest import batch_of

    def store_of(specs: list[Any]) -> Any:
        s = backend.settings
        if backend.name == "sqlite":
            return SqliteStore(s.data_dir / s.sqlite_file, specs=specs)
        assert s.url is not None
        return PostgresStore(s.url.get_secret_value(), specs=specs)

    n_old = len(SQLITE_PACKED_FIELDS)
    old_spec = dc.replace(MDSF_SPEC, fields=MDSF_SPEC.fields[:n_old], calibrations=())
    rows = _uncalibrated(make_rows(30, seed=4))
    old = store_of([old_spec])
    with monkeypatch.context() as m:
        m.setattr(mig, "MIGRATIONS", mig.MIGRATIONS[:14])
        assert old.migrate() == 14
    old.upsert_vehicle("v1", {}, now_ns=1)
    assert old.write_estimates(batch_of(old_spec, {"v1": _before_v15(rows[:20])})) == 20
    if backend.name == "sqlite":
        old.maintain(everything=True)  # some rows final, the next staged
    assert old.write_estimates(batch_of(old_spec, {"v1": _before_v15(rows[20:])})) == 10
    old.close()

    store = backend.open(migrate=False)
    assert store.migrate() == latest_version() >= 15
    assert_rows_equal(store.query_series("v1", 0, 2**62), rows)
    new = make_rows(5, T0_NS + 100 * DT_NS, seed=5)
    assert store.write_estimates([("v1", new)]) == 5
    assert_rows_equal(store.query_series("v1", T0_NS + 100 * DT_NS, 2**62), new)
