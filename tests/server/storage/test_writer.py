"""The batching writer: batching under load, flush/close, outages, bounded backlog."""

from __future__ import annotations

import itertools
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
import pytest

from estimator.types import EstimateBatch, concat_estimates
from server.settings import StorageSettings
from server.storage import StorageDataError, Store, StoreWriter
from server.storage.writer import COUNTER_VEHICLES_PER_WRITE, MAINTAIN_PAUSE_PER_STEP
from tests.server.storage.conftest import DT_NS, T0_NS, Backend, assert_rows_equal, make_rows


class CountingStore:
    """Delegates to a real store and records the size of every estimate transaction."""

    def __init__(self, inner: Store) -> None:
        self.inner = inner
        self.batches: list[int] = []

    def write_estimates(self, *batches: EstimateBatch) -> int:
        written = self.inner.write_estimates(*batches)
        self.batches.append(sum(len(b.rows) for b in batches))
        return written

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def _wait_for(cond: Callable[[], bool], timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.01)


def _settings(**kw: Any) -> StorageSettings:
    return StorageSettings.model_validate(kw)


def test_batches_at_least_1000_rows_per_transaction_under_load(backend: Backend) -> None:
    """20 vehicles at 250 Hz each (5000 rows/s) in 20 ms ticks for 2 s."""
    inner = backend.open()
    vehicles = [f"v{i:02d}" for i in range(20)]
    for vid in vehicles:
        inner.upsert_vehicle(vid, {}, now_ns=1)
    store = CountingStore(inner)
    settings = _settings(commit_interval_s=0.5, batch_max_rows=5000)
    rows_per_tick = 5
    ticks = 100
    with StoreWriter(store, settings) as writer:
        t_next = time.monotonic()
        for tick in range(ticks):
            start = T0_NS + tick * rows_per_tick * DT_NS
            writer.submit([(vid, make_rows(rows_per_tick, start, seed=tick)) for vid in vehicles])
            t_next += 0.02
            time.sleep(max(t_next - time.monotonic(), 0.0))
    total = ticks * rows_per_tick * len(vehicles)
    stats = writer.stats()
    assert stats.rows_written == total and stats.rows_submitted == total
    assert stats.transactions == len(store.batches) and sum(store.batches) == total
    # the first tick finds the writer idle and is committed at once; every later transaction
    # but the final flush on close carries ≥ 1000 rows
    assert store.batches[0] == rows_per_tick * len(vehicles), store.batches
    assert min(store.batches[1:-1]) >= 1000, store.batches
    assert max(store.batches) <= settings.batch_max_rows
    assert stats.transactions <= total // 1000 + 2
    for vid in vehicles[:3]:
        assert len(inner.query_series(vid, 0, 2**62)) == ticks * rows_per_tick


class TimedStore(CountingStore):
    """Also records when (monotonic s) each estimate transaction started."""

    def __init__(self, inner: Store) -> None:
        super().__init__(inner)
        self.started_s: list[float] = []

    def write_estimates(self, *batches: EstimateBatch) -> int:
        self.started_s.append(time.monotonic())
        return super().write_estimates(*batches)


def test_rows_after_a_pause_commit_at_once_later_ones_wait_the_interval(
    backend: Backend,
) -> None:
    """A burst reaching an idle writer is committed without waiting out the interval; a burst
    arriving right after it waits until an interval after that transaction started."""
    inner = backend.open()
    inner.upsert_vehicle("v1", {}, now_ns=1)
    store = TimedStore(inner)
    interval_s = 1.0
    with StoreWriter(store, _settings(commit_interval_s=interval_s)) as writer:
        submitted_s = time.monotonic()
        writer.submit([("v1", make_rows(3))])
        _wait_for(lambda: writer.stats().rows_written == 3)
        first_done_s = time.monotonic()
        writer.submit([("v1", make_rows(4, T0_NS + 3 * DT_NS, seed=2))])
        _wait_for(lambda: writer.stats().rows_written == 7)
    assert store.batches == [3, 4]
    # the first went out well before an interval had passed (idle writer)
    assert store.started_s[0] - submitted_s < interval_s / 2
    assert first_done_s - submitted_s < interval_s / 2
    # the second waited for the interval, counted from the first transaction's start
    assert store.started_s[1] - store.started_s[0] >= interval_s * 0.99
    assert len(inner.query_series("v1", 0, 2**62)) == 7


class SlowCountersStore(CountingStore):
    """Records the order of writes; each counters write takes ``counters_s``."""

    def __init__(self, inner: Store, counters_s: float) -> None:
        super().__init__(inner)
        self.calls: list[tuple[str, int]] = []
        self.counters_s = counters_s
        self.counters_started = threading.Event()

    def write_counters(self, counters: dict[str, dict[str, int]], now_ns: int) -> None:
        self.calls.append(("counters", len(counters)))
        self.counters_started.set()
        time.sleep(self.counters_s)
        self.inner.write_counters(counters, now_ns)

    def write_estimates(self, *batches: EstimateBatch) -> int:
        self.calls.append(("estimates", sum(len(b.rows) for b in batches)))
        return super().write_estimates(*batches)


def test_fleet_counters_go_in_slices_with_due_estimates_in_between(backend: Backend) -> None:
    inner = backend.open()
    inner.upsert_vehicle("v1", {}, now_ns=1)
    store = SlowCountersStore(inner, counters_s=0.2)
    per_write = COUNTER_VEHICLES_PER_WRITE
    fleet = {f"sim-{v:04d}": {"received": v, "accepted": v} for v in range(3 * per_write - 10)}
    with StoreWriter(store, _settings(commit_interval_s=0.05)) as writer:
        writer.submit_counters(fleet)
        assert store.counters_started.wait(10)  # the first slice is being written
        writer.submit([("v1", make_rows(5))])
        assert writer.flush(timeout=30)
    assert store.calls == [
        ("counters", per_write),
        ("estimates", 5),
        ("counters", per_write),
        ("counters", per_write - 10),
    ]
    for vid in ("sim-0000", f"sim-{per_write:04d}", f"sim-{3 * per_write - 11:04d}"):
        assert inner.get_counters(vid) == fleet[vid]
    assert len(inner.query_series("v1", 0, 2**62)) == 5


class CounterWritesStore(CountingStore):
    """Records what every counters write carries."""

    def __init__(self, inner: Store) -> None:
        super().__init__(inner)
        self.written: list[dict[str, dict[str, int]]] = []

    def write_counters(self, counters: dict[str, dict[str, int]], now_ns: int) -> None:
        self.written.append({vid: dict(named) for vid, named in counters.items()})
        self.inner.write_counters(counters, now_ns)


def test_anchors_are_written_once_and_again_after_the_vehicle_is_forgotten(
    backend: Backend,
) -> None:
    store = backend.open()
    with StoreWriter(store, _settings(commit_interval_s=0.02)) as writer:
        writer.submit_anchors({"v1": (48.0, 11.0, 500.0), "v2": (-33.9, 151.2, 20.0)})
        assert writer.flush(timeout=30)
        assert store.get_anchors() == {"v1": (48.0, 11.0, 500.0), "v2": (-33.9, 151.2, 20.0)}
        writer.submit_anchors({"v1": (1.0, 2.0, 3.0)})  # queued once: not again
        assert writer.flush(timeout=30)
        assert store.get_anchors()["v1"] == (48.0, 11.0, 500.0)
        store.delete_vehicle("v1")  # as the API deletes it, then tells the writer
        writer.forget_vehicle("v1")
        writer.submit_anchors({"v1": (1.0, 2.0, 3.0)})  # the new vehicle of that id
        assert writer.flush(timeout=30)
    assert store.get_anchors() == {"v1": (1.0, 2.0, 3.0), "v2": (-33.9, 151.2, 20.0)}


def test_only_counters_that_changed_are_written_again(backend: Backend) -> None:
    inner = backend.open()
    store = CounterWritesStore(inner)
    with StoreWriter(store, _settings(commit_interval_s=0.02)) as writer:
        writer.submit_counters({"v1": {"received": 5, "late": 0}, "v2": {"received": 1}})
        assert writer.flush(timeout=30)
        writer.submit_counters({"v1": {"received": 9, "late": 0}, "v2": {"received": 1}})
        assert writer.flush(timeout=30)
        writer.submit_counters({"v1": {"received": 9, "late": 0}, "v2": {"received": 1}})
        assert writer.flush(timeout=30)
    assert store.written == [
        {"v1": {"received": 5, "late": 0}, "v2": {"received": 1}},
        {"v1": {"received": 9}},
    ]
    assert inner.get_counters("v1") == {"received": 9, "late": 0}
    assert inner.get_counters("v2") == {"received": 1}


def test_batch_max_rows_splits_a_burst(backend: Backend) -> None:
    inner = backend.open()
    inner.upsert_vehicle("v1", {}, now_ns=1)
    store = CountingStore(inner)
    rows = make_rows(12_000)
    with StoreWriter(store, _settings(batch_max_rows=5000)) as writer:
        assert writer.submit([("v1", rows)]) == 12_000
        assert writer.flush(timeout=60)
    assert store.batches == [5000, 5000, 2000]
    assert_rows_equal(inner.query_series("v1", 0, 2**62), rows)


def test_a_fleets_submits_are_cut_at_batch_max_rows_within_a_vehicle(backend: Backend) -> None:
    """Three submits of four vehicles (3, 5, 2 and 4 rows each, 14 a submit) go out in
    transactions of at most 10 rows, cut within a vehicle's rows where the limit falls; every
    row is stored once, in its vehicle's series."""
    inner = backend.open()
    counts = {"a": 3, "b": 5, "c": 2, "d": 4}
    for vid in counts:
        inner.upsert_vehicle(vid, {}, now_ns=1)
    store = CountingStore(inner)
    ticks = 3
    rows = {vid: make_rows(n * ticks, T0_NS, seed=k) for k, (vid, n) in enumerate(counts.items())}
    with StoreWriter(store, _settings(batch_max_rows=10, commit_interval_s=1.0)) as writer:
        for tick in range(ticks):
            batch = [(vid, rows[vid][tick * n : (tick + 1) * n]) for vid, n in counts.items()]
            assert writer.submit(batch) == 14
        assert writer.flush(timeout=60)
    assert sum(store.batches) == 42 and max(store.batches) <= 10, store.batches
    for vid, expected in rows.items():
        assert_rows_equal(inner.query_series(vid, 0, 2**62), expected)


def test_a_submit_near_a_full_backlog_keeps_the_vehicles_that_fit(backend: Backend) -> None:
    """With 4 rows of room (996 of 1,000 held through an outage), a submit of vehicles with
    3, 2 and 1 rows queues the first and the last (each vehicle's rows whole or not at all,
    in order), and counts 2 dropped."""
    store = backend.open(fast_fail=True)
    for vid in ("a", "b", "c", "d"):
        store.upsert_vehicle(vid, {}, now_ns=1)
    settings = _settings(commit_interval_s=0.05, backlog_max_rows=1000)
    writer = StoreWriter(store, settings, retry_initial_s=0.05, submit_block_s=0.01).start()
    try:
        with backend.outage():
            assert writer.submit([("d", make_rows(996))]) == 996
            _wait_for(lambda: not writer.stats().healthy)
            got = writer.submit([("a", make_rows(3)), ("b", make_rows(2)), ("c", make_rows(1))])
            assert got == 4 and writer.stats().rows_dropped_backlog_full == 2
        assert writer.flush(timeout=60)
    finally:
        writer.close(timeout=30)
    stored = {vid: len(store.query_series(vid, 0, 2**62)) for vid in ("a", "b", "c", "d")}
    assert stored == {"a": 3, "b": 0, "c": 1, "d": 996}


def test_commit_within_interval_at_low_rate(backend: Backend) -> None:
    store = backend.open()
    store.upsert_vehicle("v1", {}, now_ns=1)
    with StoreWriter(store, _settings(commit_interval_s=0.2)) as writer:
        writer.submit([("v1", make_rows(3))])
        t0 = time.monotonic()
        _wait_for(lambda: writer.stats().rows_written == 3, timeout_s=10)
        assert time.monotonic() - t0 < 5.0
        assert writer.stats().last_commit_ns is not None


def test_close_flushes_everything(backend: Backend) -> None:
    store = backend.open()
    store.upsert_vehicle("v1", {}, now_ns=1)
    store.upsert_vehicle("v2", {}, now_ns=1)
    r1, r2 = make_rows(3000, seed=1), make_rows(10, seed=2)
    # a long interval: nothing would be due before close
    writer = StoreWriter(store, _settings(commit_interval_s=1.0, batch_max_rows=100_000)).start()
    writer.submit([("v1", r1[:1000])])
    writer.submit([("v2", r2), ("v1", r1[1000:])])
    writer.submit_counters({"v1": {"packets": 7}})
    writer.close()
    stats = writer.stats()
    assert stats.rows_written == 3010 and stats.backlog_rows == 0 and stats.rows_lost_on_close == 0
    assert_rows_equal(store.query_series("v1", 0, 2**62), r1)
    assert_rows_equal(store.query_series("v2", 0, 2**62), r2)
    assert store.get_counters("v1") == {"packets": 7}
    with pytest.raises(RuntimeError):
        writer.submit([("v1", r1[:1])])
    writer.close()  # idempotent


def test_close_without_start_still_writes(backend: Backend) -> None:
    store = backend.open()
    store.upsert_vehicle("v1", {}, now_ns=1)
    writer = StoreWriter(store, _settings())
    writer.submit([("v1", make_rows(5))])
    writer.close()
    assert len(store.query_series("v1", 0, 2**62)) == 5


def test_flush_and_counters_and_duplicates(backend: Backend) -> None:
    store = backend.open()
    store.upsert_vehicle("v1", {}, now_ns=1)
    rows = make_rows(100)
    with StoreWriter(store, _settings(commit_interval_s=1.0)) as writer:
        writer.on_estimates([("v1", rows), ("ghost", make_rows(4))])
        writer.submit_counters({"v1": {"packets": 1, "bad": 2}})
        writer.submit_counters({"v1": {"packets": 3}})
        assert writer.flush(timeout=30)
        assert store.get_counters("v1") == {"bad": 2, "packets": 3}
        writer.submit([("v1", rows[:50])])  # replay
        assert writer.flush(timeout=30)
        stats = writer.stats()
    assert stats.rows_written == 100
    assert stats.rows_ignored == 4 + 50  # unknown vehicle + replayed rows
    assert stats.healthy and stats.last_error is None


def test_a_vehicle_is_stored_before_the_rows_submitted_after_it(backend: Backend) -> None:
    """The pipeline registers a new vehicle and hands over its first rows right after: the
    writer stores the vehicle first, so none of those rows is refused as of an unknown one."""
    store = backend.open()
    rows = make_rows(40)
    with StoreWriter(store, _settings(commit_interval_s=0.001)) as writer:
        for i in range(20):
            writer.submit_vehicle(f"new{i}", {"kind": "wheeled", "n": i}, now_ns=5)
            writer.submit([(f"new{i}", rows[: 2 * i + 1])])
        assert writer.flush(timeout=30)
        writer.submit_vehicle("new0", {"kind": "wheeled", "n": 99}, now_ns=6)  # a newer config
        assert writer.flush(timeout=30)
        stats = writer.stats()
    assert stats.rows_ignored == 0 and stats.rows_written == sum(2 * i + 1 for i in range(20))
    assert stats.vehicles_stored == 21 and stats.vehicles_dropped_error == 0
    for i in range(20):
        assert_rows_equal(store.query_series(f"new{i}", 0, 2**62), rows[: 2 * i + 1])
    first = store.get_vehicle("new0")
    assert first is not None and first.config == {"kind": "wheeled", "n": 99}


def test_vehicles_wait_out_an_outage_and_a_refused_one_is_counted(backend: Backend) -> None:
    store = backend.open(fast_fail=True)
    writer = StoreWriter(store, _settings(commit_interval_s=0.05), retry_initial_s=0.05).start()
    try:
        with backend.outage():
            writer.submit_vehicle("v1", {}, now_ns=1)
            writer.submit_vehicle("bad", {"not json": {1, 2}}, now_ns=1)  # a set: no JSON
            writer.submit_vehicle("v2", {}, now_ns=1)
            writer.submit([("v1", make_rows(10)), ("v2", make_rows(3))])
            _wait_for(lambda: not writer.stats().healthy)
            assert not writer.flush(timeout=0.3)
        assert writer.flush(timeout=60)
        stats = writer.stats()
    finally:
        writer.close(timeout=30)
    assert stats.healthy and stats.rows_written == 13 and stats.rows_ignored == 0
    assert stats.vehicles_stored == 2 and stats.vehicles_dropped_error == 1
    assert sorted(v.vehicle_id for v in store.list_vehicles()) == ["v1", "v2"]


def test_a_deleted_vehicle_is_not_stored_again(backend: Backend) -> None:
    store = backend.open()
    writer = StoreWriter(store, _settings())  # not started: the registration waits
    writer.submit_vehicle("gone", {}, now_ns=1)
    writer.submit_vehicle("kept", {}, now_ns=1)
    writer.forget_vehicle("gone")
    writer.close()
    assert [v.vehicle_id for v in store.list_vehicles()] == ["kept"]
    with pytest.raises(RuntimeError):
        writer.submit_vehicle("late", {}, now_ns=2)


def test_submit_validates_and_copies(backend: Backend) -> None:
    store = backend.open()
    store.upsert_vehicle("v1", {}, now_ns=1)
    rows = make_rows(10)
    expected = rows.copy()
    with StoreWriter(store, _settings(commit_interval_s=0.5)) as writer:
        with pytest.raises(TypeError):
            writer.submit([("v1", rows), ("v1", np.zeros(3))])
        assert writer.stats().rows_submitted == 0  # nothing of a bad batch is queued
        writer.submit([("v1", rows)])
        rows["vg_mps"] = 0.0  # the caller reuses its buffer
        assert writer.flush(timeout=30)
        # several vehicles in one batch, an empty array and a strided view among them
        store.upsert_vehicle("v2", {}, now_ns=1)
        store.upsert_vehicle("v3", {}, now_ns=1)
        more = make_rows(20, T0_NS + 10 * DT_NS, seed=3)
        other = make_rows(5, seed=4)
        expected_more, expected_other = more[::2].copy(), other.copy()
        empty = make_rows(0)
        assert writer.submit([("v1", more[::2]), ("v2", empty), ("v3", other)]) == 15
        more["vg_mps"] = 0.0
        other["vg_mps"] = 0.0
        assert writer.flush(timeout=30)
    assert_rows_equal(
        store.query_series("v1", 0, 2**62), concat_estimates([expected, expected_more])
    )
    assert len(store.query_series("v2", 0, 2**62)) == 0
    assert_rows_equal(store.query_series("v3", 0, 2**62), expected_other)


def test_survives_outage_with_bounded_backlog_and_catches_up(backend: Backend) -> None:
    store = backend.open(fast_fail=True)
    store.upsert_vehicle("v1", {}, now_ns=1)
    settings = _settings(commit_interval_s=0.05, batch_max_rows=400, backlog_max_rows=1000)
    rows = make_rows(1500)
    writer = StoreWriter(
        store, settings, retry_initial_s=0.05, retry_max_s=0.2, submit_block_s=0.01
    ).start()
    try:
        assert writer.submit([("v1", rows[:200])]) == 200
        assert writer.flush(timeout=30)
        with backend.outage():
            assert writer.submit([("v1", rows[200:700])]) == 500
            _wait_for(lambda: not writer.stats().healthy)
            assert writer.submit([("v1", rows[700:1200])]) == 500  # backlog now full
            assert writer.submit([("v1", rows[1200:1500])]) == 0  # refused and counted
            assert not writer.flush(timeout=0.3)
            stats = writer.stats()
            assert stats.backlog_rows == 1000
            assert stats.rows_dropped_backlog_full == 300
            assert stats.rows_written == 200
            assert stats.consecutive_failures >= 1 and stats.last_error
        assert writer.flush(timeout=60)  # catch-up once the database is back
        stats = writer.stats()
        assert stats.healthy and stats.backlog_rows == 0
        assert stats.rows_written == 1200 and stats.rows_lost_on_close == 0
    finally:
        writer.close(timeout=30)
    assert_rows_equal(store.query_series("v1", 0, 2**62), rows[:1200])


def test_close_during_outage_counts_lost_rows(backend: Backend) -> None:
    store = backend.open(fast_fail=True)
    store.upsert_vehicle("v1", {}, now_ns=1)
    writer = StoreWriter(store, _settings(commit_interval_s=0.05), retry_max_s=0.1).start()
    with backend.outage():
        writer.submit([("v1", make_rows(50))])
        _wait_for(lambda: not writer.stats().healthy)
        t0 = time.monotonic()
        writer.close(timeout=0.5)
        assert time.monotonic() - t0 < 15
    stats = writer.stats()
    assert stats.rows_lost_on_close == 50 and stats.rows_written == 0 and stats.backlog_rows == 0


def test_submit_blocks_briefly_for_room_while_healthy(backend: Backend) -> None:
    store = backend.open()
    store.upsert_vehicle("v1", {}, now_ns=1)
    settings = _settings(commit_interval_s=0.05, batch_max_rows=1000, backlog_max_rows=1000)
    rows = make_rows(5000)
    with StoreWriter(store, settings, submit_block_s=30.0) as writer:
        for i in range(5):  # each waits for the previous batch to be written
            assert writer.submit([("v1", rows[i * 1000 : (i + 1) * 1000])]) == 1000
        assert writer.flush(timeout=60)
        assert writer.stats().rows_dropped_backlog_full == 0
    assert len(store.query_series("v1", 0, 2**62)) == 5000


def test_retention(backend: Backend) -> None:
    store = backend.open()
    store.upsert_vehicle("v1", {}, now_ns=1)
    rows = make_rows(100)
    store.write_estimates([("v1", rows)])
    now_ns = T0_NS + 1 * 86_400 * 10**9 + 60 * DT_NS  # one day after row 60
    writer = StoreWriter(store, _settings(retention_days=1.0), clock_ns=lambda: now_ns)
    with writer:
        _wait_for(lambda: writer.stats().retention_rows_deleted == 60)
    assert_rows_equal(store.query_series("v1", 0, 2**62), rows[60:])


def test_raw_packets_only_when_enabled(backend: Backend) -> None:
    store = backend.open()
    store.upsert_vehicle("v1", {}, now_ns=1)
    packet = ("v1", T0_NS, "fleet/v1/sensors/gnss", b"\x01\x02")
    with StoreWriter(store, _settings(store_raw_packets=False)) as off:
        assert off.submit_raw_packets([packet]) == 0
    with StoreWriter(store, _settings(store_raw_packets=True)) as on:
        assert on.submit_raw_packets([packet]) == 1
        assert on.flush(timeout=30)
        assert on.stats().raw_packets_written == 1
    assert store.query_raw_packets("v1", 0, 2**62) == [packet[1:]]  # type: ignore[attr-defined]


def test_raw_packets_are_bounded_in_bytes(backend: Backend) -> None:
    store = backend.open()
    budget = 2**20
    packets = [("v1", T0_NS + k, "fleet/v1/sensors/imu", bytes([k]) * 2**14) for k in range(100)]
    settings = _settings(store_raw_packets=True, raw_packets_queue_max_bytes=budget)
    with StoreWriter(store, settings) as writer:
        assert writer.submit_raw_packets(packets) == budget // 2**14  # 64 of 16 KiB fit
        assert writer.flush(timeout=30)
        stats = writer.stats()
        assert (stats.raw_packets_written, stats.raw_packets_dropped) == (64, 36)
        assert writer.submit_raw_packets(packets[64:]) == 36  # written: the room is back
        assert writer.flush(timeout=30)
        assert writer.stats().raw_packets_written == 100
    stored = store.query_raw_packets("v1", 0, 2**62)  # type: ignore[attr-defined]
    assert [p[1:] for p in packets] == stored


def test_stored_raw_packets_are_bounded_in_bytes(backend: Backend) -> None:
    """``raw_packets_max_bytes`` bounds the payload bytes in the database: past it packets are
    not stored but counted (the oldest stay), also after a restart (the total is read back)."""
    store = backend.open()
    budget = 2**20
    settings = _settings(store_raw_packets=True, raw_packets_max_bytes=budget)
    packets = [("v1", T0_NS + k, "fleet/v1/sensors/imu", bytes([k]) * 100_000) for k in range(15)]
    with StoreWriter(store, settings) as writer:
        assert writer.submit_raw_packets(packets) == 15  # the queue takes them all
        assert writer.flush(timeout=30)
        stats = writer.stats()
        assert (stats.raw_packets_written, stats.raw_packets_over_budget) == (10, 5)
    assert store.raw_packets_bytes() == 1_000_000  # type: ignore[attr-defined]
    stored = store.query_raw_packets("v1", 0, 2**62)  # type: ignore[attr-defined]
    assert stored == [p[1:] for p in packets[:10]]
    late = [
        ("v1", T0_NS + 20, "fleet/v1/sensors/imu", b"\x01" * 100_000),  # over what is left
        ("v1", T0_NS + 21, "fleet/v1/sensors/imu", b"\x02" * 40_000),  # ignored: after it
    ]
    with StoreWriter(store, settings) as restarted:
        restarted.submit_raw_packets(late)
        assert restarted.flush(timeout=30)
        stats = restarted.stats()
        assert (stats.raw_packets_written, stats.raw_packets_over_budget) == (0, 2)
        restarted.submit_raw_packets(late[1:])  # 40,000 of the 48,576 bytes left fit
        assert restarted.flush(timeout=30)
        assert restarted.stats().raw_packets_written == 1
    assert store.raw_packets_bytes() == 1_040_000  # type: ignore[attr-defined]


def test_producers_on_several_threads(backend: Backend) -> None:
    store = backend.open()
    vehicles = [f"v{i}" for i in range(4)]
    for vid in vehicles:
        store.upsert_vehicle(vid, {}, now_ns=1)
    with StoreWriter(store, _settings(commit_interval_s=0.1)) as writer:

        def produce(vid: str) -> None:
            for k in range(20):
                writer.submit([(vid, make_rows(50, T0_NS + k * 50 * DT_NS, seed=k))])

        threads = [threading.Thread(target=produce, args=(vid,)) for vid in vehicles]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert writer.flush(timeout=60)
    for vid in vehicles:
        got = store.query_series(vid, 0, 2**62, ["vg_mps"])
        assert len(got) == 1000 and np.all(np.diff(got["stamp_ns"]) == DT_NS)


class PoisonStore(CountingStore):
    """Refuses, as the database would refuse bad data, any batch holding vehicle ``poison``."""

    def write_estimates(self, *batches: EstimateBatch) -> int:
        if any(vid == "poison" for b in batches for vid in b.ids):
            raise StorageDataError("value out of range")
        return super().write_estimates(*batches)


def test_rejected_data_is_isolated_per_vehicle_and_counted(backend: Backend) -> None:
    inner = backend.open()
    for vid in ("a", "b", "poison"):
        inner.upsert_vehicle(vid, {}, now_ns=1)
    store = PoisonStore(inner)
    with StoreWriter(store, _settings(commit_interval_s=0.5)) as writer:
        writer.submit([("a", make_rows(10)), ("poison", make_rows(7)), ("b", make_rows(5))])
        assert writer.flush(timeout=30)
        stats = writer.stats()
    assert stats.rows_written == 15 and stats.rows_dropped_error == 7
    assert stats.healthy and stats.backlog_rows == 0
    assert stats.last_error is not None and "out of range" in stats.last_error
    assert len(inner.query_series("a", 0, 2**62)) == 10
    assert len(inner.query_series("poison", 0, 2**62)) == 0


@pytest.mark.postgres
@pytest.mark.slow
def test_writer_survives_postgres_server_restart() -> None:
    """A private cluster (needs the server binaries, like ``pg_url`` without the env URL) is
    stopped under the writer and started again: rows wait in the backlog, then are written."""
    from server.storage.postgres import PostgresStore
    from tests.conftest import start_pg_cluster, stop_pg_cluster

    cluster_dir = Path(tempfile.mkdtemp(prefix="slipfleet-pg-restart-"))
    url = start_pg_cluster(cluster_dir)
    port = urlsplit(url).port or 0
    store = PostgresStore(url, connect_timeout_s=1.0)
    writer: StoreWriter | None = None
    try:
        store.migrate()
        store.upsert_vehicle("v1", {}, now_ns=1)
        settings = _settings(commit_interval_s=0.05, backlog_max_rows=10_000)
        writer = StoreWriter(store, settings, retry_initial_s=0.05, retry_max_s=0.5).start()
        rows = make_rows(700)
        writer.submit([("v1", rows[:200])])
        assert writer.flush(timeout=30)
        stop_pg_cluster(cluster_dir, keep=True)
        assert writer.submit([("v1", rows[200:])]) == 500
        _wait_for(lambda: not writer.stats().healthy)
        assert not store.ping()
        start_pg_cluster(cluster_dir, port=port)
        assert writer.flush(timeout=60)
        assert writer.stats().healthy and writer.stats().rows_written == 700
        assert_rows_equal(store.query_series("v1", 0, 2**62), rows)
    finally:
        if writer is not None:
            writer.close(timeout=5)
        store.close()
        stop_pg_cluster(cluster_dir)


def test_concat_estimates_equals_numpy_concatenate() -> None:
    """The writer's merge of a vehicle's packets: same rows as ``np.concatenate``, also from
    strided views and empty parts."""
    a, b = make_rows(10, seed=1), make_rows(7, seed=2)
    parts = [a, b[::2], make_rows(0), a[3:4]]
    got = concat_estimates(parts)
    assert got.flags.c_contiguous and got.flags.writeable
    assert_rows_equal(got, np.concatenate(parts))


def test_writer_moves_staged_sqlite_rows_while_idle(tmp_path: Path) -> None:
    """Between writes the writer runs the store's upkeep: SQLite's staged rows older than the
    newest second move to their final table, and every row still reads once."""
    from server.storage.sqlite import SqliteStore

    store = SqliteStore(tmp_path / "w.sqlite")
    store.migrate()
    for vid in ("v1", "v2"):
        store.upsert_vehicle(vid, {}, now_ns=1)

    def staged() -> int:
        with store._write() as conn:
            return int(conn.execute("SELECT count(*) FROM estimates_recent").fetchone()[0])

    rows = make_rows(50)  # 5 s at 10 Hz
    with StoreWriter(store, _settings(commit_interval_s=0.02)) as writer:
        writer.submit([("v1", rows), ("v2", rows)])
        assert writer.flush(timeout=30)
        _wait_for(lambda: staged() == 2 * 11)  # the newest second (11 rows) stays staged
    for vid in ("v1", "v2"):
        assert len(store.query_series(vid, 0, 2**62)) == 50
    store.close()


class StepTimedStore(CountingStore):
    """Also records when (monotonic s) each upkeep step started and ended."""

    def __init__(self, inner: Store) -> None:
        super().__init__(inner)
        self.steps: list[tuple[float, float, bool]] = []

    def maintain(self) -> bool:
        started = time.monotonic()
        more = bool(self.inner.maintain())  # type: ignore[attr-defined]
        self.steps.append((started, time.monotonic(), more))
        return more


def test_upkeep_steps_are_paced_by_their_own_duration(tmp_path: Path) -> None:
    """A move round's steps do not run back to back: after a step with more to do, the next
    starts at least MAINTAIN_PAUSE_PER_STEP times that step's duration later, so the round's
    CPU is spread out instead of taken from the pipeline all at once."""
    from server.storage.sqlite import SqliteStore

    store = SqliteStore(tmp_path / "p.sqlite")
    store.migrate()
    ids = [f"v{k:03d}" for k in range(350)]  # 100 vehicles a step: four copy steps, a delete
    for vid in ids:
        store.upsert_vehicle(vid, {}, now_ns=1)
    timed = StepTimedStore(store)
    rows = make_rows(40)  # 4 s at 10 Hz: a round is due
    with StoreWriter(timed, _settings(commit_interval_s=0.02)) as writer:
        writer.submit([(vid, rows) for vid in ids])
        assert writer.flush(timeout=30)
        _wait_for(lambda: sum(more for *_, more in timed.steps) >= 5)
    paced = 0
    for (start, end, more), (next_start, _, _) in itertools.pairwise(timed.steps):
        if more:
            assert next_start - end >= MAINTAIN_PAUSE_PER_STEP * (end - start)
            paced += 1
    assert paced >= 4
    for vid in ids[::50]:
        assert len(store.query_series(vid, 0, 2**62)) == 40
    store.close()
