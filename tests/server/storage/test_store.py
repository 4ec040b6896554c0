"""The Store contract, on SQLite and PostgreSQL alike."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from estimator.types import ESTIMATE_DTYPE, ESTIMATE_FIELDS
from server.storage import StorageDataError, Store, VehicleRecord
from server.storage.migrations import MDSF_FIELDS_V15
from server.storage.sqlite import SqliteStore
from tests.server.storage.conftest import DT_NS, T0_NS, Backend, assert_rows_equal, make_rows

CONFIG = {"kind": "tractor", "wheel_radius_m": 0.8, "teeth_per_rev": 60, "nested": {"a": [1, 2]}}


def _register(store: Store, *vehicle_ids: str) -> None:
    for vid in vehicle_ids:
        store.upsert_vehicle(vid, CONFIG, now_ns=T0_NS)


def test_dialect_and_ping(store: Store, backend: Backend) -> None:
    assert store.dialect == backend.name
    assert store.ping()


# ---------------------------------------------------------------------------- vehicles


def test_each_backend_has_every_call_of_the_store_interface(store: Store) -> None:
    """The writer and the API call the interface's methods directly (no ``getattr`` for an
    optional one), so a backend must have them all."""
    declared = {n for n, v in vars(Store).items() if callable(v) and not n.startswith("_")}
    assert {"maintain", "write_raw_packets", "raw_packets_bytes"} <= declared
    missing = sorted(n for n in declared if not callable(getattr(store, n, None)))
    assert missing == []
    assert store.maintain() in (True, False)


def test_upsert_vehicle_keeps_created_and_updates_config(store: Store) -> None:
    first = store.upsert_vehicle("tractor-1", CONFIG, now_ns=100)
    assert first == VehicleRecord("tractor-1", CONFIG, created_ns=100, updated_ns=100)
    changed = {**CONFIG, "wheel_radius_m": 0.9}
    second = store.upsert_vehicle("tractor-1", changed, now_ns=250)
    assert second == VehicleRecord("tractor-1", changed, created_ns=100, updated_ns=250)
    assert store.get_vehicle("tractor-1") == second
    assert store.get_vehicle("nope") is None


def test_list_vehicles_sorted(store: Store) -> None:
    assert store.list_vehicles() == []
    for vid in ("b", "a", "c"):
        store.upsert_vehicle(vid, {"id": vid}, now_ns=1)
    assert [v.vehicle_id for v in store.list_vehicles()] == ["a", "b", "c"]
    assert store.list_vehicles()[0].config == {"id": "a"}


# ---------------------------------------------------------------------------- estimates


def test_round_trip_all_fields_with_nan_and_inf(store: Store) -> None:
    _register(store, "v1")
    rows = make_rows(500)
    assert np.isnan(rows["slip_left_pct"]).any() and np.isinf(rows["vg_mps"]).any()
    assert store.write_estimates([("v1", rows)]) == 500
    got = store.query_series("v1", T0_NS, T0_NS + 500 * DT_NS)
    assert got.dtype == ESTIMATE_DTYPE
    assert_rows_equal(got, rows)


def test_write_is_idempotent(store: Store) -> None:
    _register(store, "v1")
    rows = make_rows(300)
    assert store.write_estimates([("v1", rows[:200])]) == 200
    # replay with overlap: only the 100 new rows are inserted, stored values unchanged
    replay = rows.copy()
    replay["vg_mps"] = -1.0
    assert store.write_estimates([("v1", replay)]) == 100
    got = store.query_series("v1", 0, 2**62)
    assert_rows_equal(got[:200], rows[:200])
    assert_rows_equal(got[200:], replay[200:])
    # duplicates inside one batch
    assert store.write_estimates([("v1", rows[:10]), ("v1", rows[:10])]) == 0


def test_write_several_vehicles_in_one_batch_and_unknown_vehicle(store: Store) -> None:
    _register(store, "a", "b")
    ra, rb = make_rows(50, seed=1), make_rows(70, seed=2)
    written = store.write_estimates([("a", ra), ("ghost", make_rows(5)), ("b", rb)])
    assert written == 120  # rows of the unregistered vehicle are not written
    assert_rows_equal(store.query_series("a", 0, 2**62), ra)
    assert_rows_equal(store.query_series("b", 0, 2**62), rb)
    assert len(store.query_series("ghost", 0, 2**62)) == 0
    assert store.write_estimates([]) == 0
    assert store.write_estimates([("a", make_rows(0))]) == 0


def test_write_rejects_wrong_dtype(store: Store) -> None:
    _register(store, "v1")
    with pytest.raises(TypeError):
        store.write_estimates([("v1", np.zeros(3))])


def test_series_range_is_half_open_and_ordered(store: Store) -> None:
    _register(store, "v1", "v2")
    rows = make_rows(1000)
    shuffled = rows[np.random.default_rng(3).permutation(len(rows))]
    store.write_estimates([("v1", shuffled), ("v2", make_rows(1000, seed=9))])
    start, end = T0_NS + 100 * DT_NS, T0_NS + 250 * DT_NS
    got = store.query_series("v1", start, end)
    assert_rows_equal(got, rows[100:250])  # start included, end excluded, sorted, v1 only
    assert len(store.query_series("v1", end, start)) == 0
    assert len(store.query_series("v1", T0_NS + 10**15, T0_NS + 10**16)) == 0


def test_series_field_subset(store: Store) -> None:
    _register(store, "v1")
    rows = make_rows(100)
    store.write_estimates([("v1", rows)])
    got = store.query_series("v1", 0, 2**62, ["slip_right_pct", "flags", "slip_left_pct"])
    assert got.dtype.names == ("stamp_ns", "slip_right_pct", "flags", "slip_left_pct")
    assert got.dtype["flags"] == np.dtype("i4") and got.dtype["stamp_ns"] == np.dtype("i8")
    for name in got.dtype.names or ():
        np.testing.assert_array_equal(got[name], rows[name])
    only_time = store.query_series("v1", 0, 2**62, ["stamp_ns"])
    assert only_time.dtype.names == ("stamp_ns",)
    with pytest.raises(ValueError):
        store.query_series("v1", 0, 2**62, ["stamp_ns", "speed; DROP TABLE estimates"])


def test_series_empty_for_unknown_vehicle(store: Store) -> None:
    got = store.query_series("nobody", 0, 2**62)
    assert got.dtype == ESTIMATE_DTYPE and got.shape == (0,)


def test_latest_and_latest_all(store: Store) -> None:
    _register(store, "a", "b", "empty")
    ra, rb = make_rows(30, seed=1), make_rows(40, start_ns=T0_NS + 5 * DT_NS, seed=2)
    ra["slip_left_pct"][-1] = np.nan  # NaN survives the single-row path too
    store.write_estimates([("a", ra), ("b", rb)])
    la = store.latest("a")
    assert la is not None and la.shape == () and la.dtype == ESTIMATE_DTYPE
    assert_rows_equal(la.reshape(1), ra[-1:])
    assert store.latest("empty") is None
    assert store.latest("nobody") is None
    everything = store.latest_all()
    assert set(everything) == {"a", "b"}
    assert_rows_equal(everything["b"].reshape(1), rb[-1:])


def test_delete_vehicle_cascades(store: Store) -> None:
    _register(store, "gone", "kept")
    store.write_estimates([("gone", make_rows(100)), ("kept", make_rows(10))])
    store.write_counters({"gone": {"packets": 5}, "kept": {"packets": 6}}, now_ns=1)
    assert store.delete_vehicle("gone") is True
    assert store.get_vehicle("gone") is None
    assert len(store.query_series("gone", 0, 2**62)) == 0
    assert store.get_counters("gone") == {}
    assert store.latest("gone") is None
    assert set(store.latest_all()) == {"kept"}
    assert len(store.query_series("kept", 0, 2**62)) == 10
    assert store.get_counters("kept") == {"packets": 6}
    assert store.delete_vehicle("gone") is False
    # re-registering starts empty
    _register(store, "gone")
    assert len(store.query_series("gone", 0, 2**62)) == 0


def test_delete_older_than(store: Store) -> None:
    _register(store, "a", "b")
    store.write_estimates([("a", make_rows(100)), ("b", make_rows(50, seed=1))])
    cutoff = T0_NS + 30 * DT_NS
    assert store.delete_older_than(cutoff) == 30 + 30
    assert store.query_series("a", 0, 2**62)["stamp_ns"][0] == cutoff
    assert len(store.query_series("b", 0, 2**62)) == 20
    assert store.delete_older_than(cutoff) == 0


# ---------------------------------------------------------------------------- counters


def test_counters_upsert(store: Store) -> None:
    assert store.get_counters("v1") == {}
    store.write_counters({"v1": {"packets": 10, "decode_errors": 1}, "v2": {"packets": 3}}, 1)
    store.write_counters({"v1": {"packets": 25}}, 2)
    assert store.get_counters("v1") == {"decode_errors": 1, "packets": 25}
    assert store.get_counters("v2") == {"packets": 3}
    store.write_counters({}, 3)  # nothing to do
    # counters of a vehicle that was never registered (rejected traffic) are kept
    store.write_counters({"unknown-7": {"rejected_unknown_vehicle": 4}}, 4)
    assert store.get_counters("unknown-7") == {"rejected_unknown_vehicle": 4}


def test_counters_of_a_fleet_in_one_write(store: Store) -> None:
    """A fleet's counters as the server flushes them (every vehicle, several names each, totals
    past 32 bits), twice: the second write replaces every total."""
    names = ("received", "accepted", "late", "seq_high_imu")
    fleet = {
        f"sim-{v:04d}": {name: v * 10 + k + 2**40 for k, name in enumerate(names)}
        for v in range(300)
    }
    store.write_counters(fleet, 1)
    store.write_counters({vid: {n: t + 1 for n, t in c.items()} for vid, c in fleet.items()}, 2)
    for vid in ("sim-0000", "sim-0150", "sim-0299"):
        assert store.get_counters(vid) == {n: t + 1 for n, t in fleet[vid].items()}


# ---------------------------------------------------------------------------- ENU anchors


def test_anchors_are_stored_once_and_deleted_with_their_vehicle(store: Store) -> None:
    _register(store, "v1")
    _register(store, "v2")
    assert store.get_anchors() == {}
    a1 = (52.520008123456789, 13.404954987654321, 34.125)
    assert store.put_anchors({"v1": a1, "v2": (-33.9, 151.2, -2.5)}, 1) == 2
    # a second anchor for v1 does not move its frame: the first one stays
    assert store.put_anchors({"v1": (0.0, 0.0, 0.0), "v3": (1.0, 2.0, 3.0)}, 2) == 1
    assert store.put_anchors({}, 3) == 0
    got = store.get_anchors()
    assert got == {"v1": a1, "v2": (-33.9, 151.2, -2.5), "v3": (1.0, 2.0, 3.0)}  # bit-exact
    assert store.get_anchors("v2") == {"v2": (-33.9, 151.2, -2.5)}
    assert store.get_anchors("nobody") == {}
    assert store.delete_vehicle("v1")
    assert "v1" not in store.get_anchors()
    assert store.put_anchors({"v1": (5.0, 6.0, 7.0)}, 4) == 1  # a new vehicle of that name


# ---------------------------------------------------------------------------- raw packets


def test_raw_packets(store: Store) -> None:
    _register(store, "v1")
    packets = [("v1", T0_NS + i, f"fleet/v1/sensors/imu/{i}", bytes([i, 0, 255])) for i in range(5)]
    # packets of a vehicle not (yet) registered are kept too: they arrive before registration
    assert store.write_raw_packets([*packets, ("ghost", T0_NS, "k", b"x")]) == 6  # type: ignore[attr-defined]
    assert store.raw_packets_bytes() == 5 * 3 + 1  # type: ignore[attr-defined]
    got = store.query_raw_packets("v1", T0_NS + 1, T0_NS + 4)  # type: ignore[attr-defined]
    assert got == [(t, k, p) for _, t, k, p in packets[1:4]]
    assert store.query_raw_packets("ghost", 0, 2**62) == [(T0_NS, "k", b"x")]  # type: ignore[attr-defined]
    store.delete_vehicle("ghost")  # never registered: its raw packets go all the same
    assert store.query_raw_packets("ghost", 0, 2**62) == []  # type: ignore[attr-defined]
    store.delete_older_than(T0_NS + 2)
    assert len(store.query_raw_packets("v1", 0, 2**62)) == 3  # type: ignore[attr-defined]
    store.delete_vehicle("v1")
    assert store.query_raw_packets("v1", 0, 2**62) == []  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------- concurrency


def test_reads_from_other_threads_while_writing(store: Store) -> None:
    _register(store, "v1")
    errors: list[BaseException] = []
    stop = threading.Event()

    def reader() -> None:
        try:
            while not stop.is_set():
                got = store.query_series("v1", 0, 2**62, ["vg_mps"])
                assert np.all(np.diff(got["stamp_ns"]) > 0)
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=reader) for _ in range(2)]
    for t in threads:
        t.start()
    for i in range(10):
        store.write_estimates([("v1", make_rows(200, start_ns=T0_NS + i * 200 * DT_NS))])
    stop.set()
    for t in threads:
        t.join()
    assert not errors
    assert len(store.query_series("v1", 0, 2**62)) == 2000


def test_estimate_columns_match_estimate_fields(store: Store) -> None:
    """A change to ESTIMATE_FIELDS must come with a new migration."""
    columns = store.table_columns("estimates")  # type: ignore[attr-defined]
    if store.dialect == "sqlite":  # rows only packed, in the layout frozen with migration 15
        assert columns == ["vkey", "stamp_ns", "packed"]
        packed = np.dtype([(name, "<" + kind) for name, kind in MDSF_FIELDS_V15])
        assert packed == ESTIMATE_DTYPE and packed.itemsize == ESTIMATE_DTYPE.itemsize
    else:
        assert columns == ["vkey", *(name for name, _ in ESTIMATE_FIELDS)]


def test_sqlite_read_spanning_several_pages(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A range longer than one read statement's page comes back whole, in order, as one
    snapshot; a page boundary inside the range and at its end are both covered."""
    import server.storage.sqlite as sqlite_module

    monkeypatch.setattr(sqlite_module, "_READ_PAGE_ROWS", 7)
    store = SqliteStore(tmp_path / "s.sqlite")
    store.migrate()
    store.upsert_vehicle("v1", {}, now_ns=1)
    store.upsert_vehicle("v2", {}, now_ns=1)
    rows = make_rows(50)
    store.write_estimates([("v2", make_rows(30, seed=4)), ("v1", rows)])
    assert_rows_equal(store.query_series("v1", 0, 2**62), rows)
    assert_rows_equal(store.query_series("v1", T0_NS + 3 * DT_NS, T0_NS + 17 * DT_NS), rows[3:17])
    assert_rows_equal(store.query_series("v1", T0_NS + 7 * DT_NS, T0_NS + 21 * DT_NS), rows[7:21])
    got = store.query_series("v1", 0, 2**62)
    got["vg_mps"] = 0.0  # the caller owns the array
    store.close()


def _move_all(store: SqliteStore) -> None:
    """Move every staged row to ``estimates`` (what the writer does over time)."""
    while store.maintain(everything=True):
        pass


def _count(store: SqliteStore, table: str) -> int:
    with store._write() as conn:
        return int(conn.execute(f"SELECT count(*) FROM {table}").fetchone()[0])


@pytest.mark.parametrize("table", ["estimates", "estimates_recent"])
def test_sqlite_refuses_rows_of_another_layout(tmp_path: Path, table: str) -> None:
    """A stored row that is not ESTIMATE_DTYPE's size (a layout change without its migration)
    is an error, never garbage, in the staging table as in the final one."""
    store = SqliteStore(tmp_path / "s.sqlite")
    store.migrate()
    store.upsert_vehicle("v1", {}, now_ns=1)
    store.write_estimates([("v1", make_rows(5))])
    if table == "estimates":
        _move_all(store)
    assert _count(store, table) == 5
    with store._write() as conn:
        conn.execute(f"UPDATE {table} SET packed = x'0102' WHERE stamp_ns = ?", (T0_NS,))
    with pytest.raises(StorageDataError, match=f"not {ESTIMATE_DTYPE.itemsize}-byte"):
        store.query_series("v1", 0, 2**62)
    assert len(store.query_series("v1", T0_NS + 1, 2**62)) == 4  # the other rows still read
    with store._write() as conn:
        conn.execute(
            f"UPDATE {table} SET packed = x'0102' WHERE stamp_ns = ?", (T0_NS + 4 * DT_NS,)
        )
    with pytest.raises(StorageDataError):
        store.latest("v1")
    store.close()


def _moving_one_vehicle_a_step(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> tuple[SqliteStore, list[str]]:
    """A migrated SQLite store with three vehicles whose move rounds copy one a transaction."""
    monkeypatch.setattr("server.storage.sqlite._MOVE_VEHICLES", 1)
    store = SqliteStore(tmp_path / "s.sqlite")
    store.migrate()
    ids = ["v1", "v2", "v3"]
    for vid in ids:
        store.upsert_vehicle(vid, {}, now_ns=1)
    return store, ids


def test_sqlite_new_rows_are_staged_then_moved_and_read_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """New rows land in the time-ordered staging table; maintain() moves the ones older than
    the newest second once the staged rows span three seconds, a few vehicles a transaction;
    reads see every row exactly once, before, during and after a move."""
    store, ids = _moving_one_vehicle_a_step(tmp_path, monkeypatch)
    rows = {vid: make_rows(50, seed=k) for k, vid in enumerate(ids)}  # 5 s at 10 Hz
    assert store.write_estimates([(vid, r[:20]) for vid, r in rows.items()]) == 60
    assert not store.maintain()  # 1.9 s staged: nothing to move yet
    assert store.write_estimates([(vid, r[20:]) for vid, r in rows.items()]) == 90
    assert _count(store, "estimates_recent") == 150 and _count(store, "estimates") == 0
    assert store.maintain()  # v1's rows older than the newest second: copied
    # the newest row is at 4.9 s: the 39 rows of v1 before 3.9 s are copied
    assert _count(store, "estimates") == 39
    for vid in ids:  # v1's moved rows are in both tables now: read once
        assert_rows_equal(store.query_series(vid, 0, 2**62), rows[vid])
    while store.maintain():
        pass
    assert _count(store, "estimates") == 117 and _count(store, "estimates_recent") == 33
    for vid in ids:
        assert_rows_equal(store.query_series(vid, 0, 2**62), rows[vid])
        assert_rows_equal(
            store.query_series(vid, T0_NS + 35 * DT_NS, T0_NS + 45 * DT_NS), rows[vid][35:45]
        )  # a range across both tables
        assert store.latest(vid)["stamp_ns"] == rows[vid]["stamp_ns"][-1]
    assert {vid: int(r["stamp_ns"]) for vid, r in store.latest_all().items()} == {
        vid: int(r["stamp_ns"][-1]) for vid, r in rows.items()
    }
    # a replay of rows already moved, or still staged, is not stored twice
    assert store.write_estimates([("v1", rows["v1"])]) == 0
    store.close()


def test_sqlite_a_replay_keeps_the_stored_rows_wherever_they_are(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Rows written again with other values (a replay) are refused and leave the stored ones,
    whether those are final, staged, or copied in a move round that has not ended; a replay
    older than the final rows' stamp bound is checked against them too."""
    monkeypatch.setattr("server.storage.sqlite._MOVE_VEHICLES", 1)
    store = SqliteStore(tmp_path / "s.sqlite")
    store.migrate()
    for vid in ("v1", "v2"):
        store.upsert_vehicle(vid, {}, now_ns=1)
    rows = {"v1": make_rows(50), "v2": make_rows(50, seed=1)}
    store.write_estimates([(vid, r[:40]) for vid, r in rows.items()])
    _move_all(store)  # the first 40 of each final, the bound at the 40th
    newest = store._read("SELECT newest_ns FROM estimates_horizon")[0][0]
    assert newest == int(rows["v1"]["stamp_ns"][39])
    store.write_estimates([(vid, r[40:]) for vid, r in rows.items()])  # staged, above it
    store.write_estimates([("v1", make_rows(50, start_ns=T0_NS + 50 * DT_NS, seed=2))])
    assert store.maintain()  # a round: v1 copied, still staged too

    def replay() -> int:
        changed = {vid: r.copy() for vid, r in rows.items()}
        for r in changed.values():
            r["vg_mps"] += 1.0
        return store.write_estimates(list(changed.items()))

    assert replay() == 0
    for vid, r in rows.items():
        assert_rows_equal(store.query_series(vid, 0, T0_NS + 50 * DT_NS), r)
    while store.maintain():
        pass
    assert replay() == 0
    for vid, r in rows.items():
        assert_rows_equal(store.query_series(vid, 0, T0_NS + 50 * DT_NS), r)
        assert_rows_equal(store.latest(vid).reshape(1), store.query_series(vid, 0, 2**62)[-1:])
    store.close()


def test_sqlite_rows_are_read_once_at_every_step_of_a_move(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every read path sees each row once after every step of a move round, one vehicle a
    step, with rows written between the steps."""
    store, ids = _moving_one_vehicle_a_step(tmp_path, monkeypatch)
    rows = {vid: make_rows(80, seed=k) for k, vid in enumerate(ids)}
    store.write_estimates([(vid, r[:40]) for vid, r in rows.items()])
    done = dict.fromkeys(ids, 40)
    more = True
    while more:
        more = store.maintain()
        for vid in ids:  # a row of each vehicle between the steps
            if done[vid] < 80:
                store.write_estimates([(vid, rows[vid][done[vid] : done[vid] + 1])])
                done[vid] += 1
        for vid in ids:
            want = rows[vid][: done[vid]]
            assert_rows_equal(store.query_series(vid, 0, 2**62), want)
            assert int(store.latest(vid)["stamp_ns"]) == int(want["stamp_ns"][-1])
        assert {v: int(r["stamp_ns"]) for v, r in store.latest_all().items()} == {
            vid: int(rows[vid]["stamp_ns"][done[vid] - 1]) for vid in ids
        }
    assert _count(store, "estimates") > 0
    store.close()


def test_sqlite_deletes_reach_staged_rows(tmp_path: Path) -> None:
    store = SqliteStore(tmp_path / "s.sqlite")
    store.migrate()
    for vid in ("v1", "v2"):
        store.upsert_vehicle(vid, {}, now_ns=1)
    store.write_estimates([("v1", make_rows(40)), ("v2", make_rows(40))])
    while store.maintain():  # the older 29 of each moved, the newest 11 still staged
        pass
    assert _count(store, "estimates") == 58 and _count(store, "estimates_recent") == 22
    assert store.delete_older_than(T0_NS + 35 * DT_NS) == 2 * 35
    assert len(store.query_series("v1", 0, 2**62)) == 5
    assert store.delete_vehicle("v1")
    assert len(store.query_series("v2", 0, 2**62)) == 5
    assert _count(store, "estimates_recent") == 5 and _count(store, "estimates") == 0
    store.close()


def test_sqlite_rows_arriving_during_a_move_are_never_lost(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A vehicle already copied in a move round that then sends rows older than the round's
    cutoff (data it buffered while offline) keeps them: only copied rows leave the staging
    table."""
    monkeypatch.setattr("server.storage.sqlite._MOVE_VEHICLES", 1)
    store = SqliteStore(tmp_path / "s.sqlite")
    store.migrate()
    for vid in ("v1", "v2"):
        store.upsert_vehicle(vid, {}, now_ns=1)
    late = make_rows(10, start_ns=T0_NS - 3600 * 10**9, seed=5)  # an hour older
    store.write_estimates([("v1", make_rows(50)), ("v2", make_rows(50, seed=1))])
    assert store.maintain()  # v1 copied
    store.write_estimates([("v1", late)])  # v1 again, below the cutoff, after its copy
    while store.maintain():
        pass
    assert len(store.query_series("v1", 0, 2**62)) == 60
    assert_rows_equal(store.query_series("v1", 0, T0_NS), late)
    _move_all(store)
    assert len(store.query_series("v1", 0, 2**62)) == 60 and _count(store, "estimates_recent") == 0
    store.close()
