"""The writer with rows of several estimators, and store calls run on its thread."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.types import EstimateBatch
from server.settings import StorageSettings
from server.storage import StorageDataError, StorageError, Store, StoreWriter
from tests.server.storage.conftest import (
    DT_NS,
    T0_NS,
    Backend,
    assert_rows_equal,
    batch_of,
    make_rows,
    make_spec_rows,
)

REF = REFERENCE_SPEED_SPEC


def _settings(**kw: Any) -> StorageSettings:
    return StorageSettings.model_validate(kw)


class RecordingStore:
    """Delegates to a real store; records the estimators of every estimate transaction."""

    def __init__(self, inner: Store) -> None:
        self.inner = inner
        self.transactions: list[list[tuple[str, int]]] = []

    def write_estimates(self, *batches: EstimateBatch) -> int:
        self.transactions.append([(b.estimator, len(b.rows)) for b in batches])
        return self.inner.write_estimates(*batches)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_rows_of_several_estimators_go_in_one_transaction(backend: Backend) -> None:
    inner = backend.open()
    for vid in ("a", "b"):
        inner.upsert_vehicle(vid, {}, now_ns=1)
    store = RecordingStore(inner)
    mdsf = {v: make_spec_rows(MDSF_SPEC, 6, seed=k) for k, v in enumerate("ab")}
    ref = {v: make_spec_rows(REF, 4, seed=k + 7) for k, v in enumerate("ab")}
    writer = StoreWriter(store, _settings())  # not started: both wait for one transaction
    for lo in (0, 3):  # two ticks, each estimator's batch of the tick
        writer.on_estimates(batch_of(MDSF_SPEC, {v: r[lo : lo + 3] for v, r in mdsf.items()}))
        writer.on_estimates(
            batch_of(REF, {v: r[lo // 3 * 2 : lo // 3 * 2 + 2] for v, r in ref.items()})
        )
    writer.submit([("a", make_rows(2, T0_NS + 50 * DT_NS))])  # plain pairs: MDSF rows
    writer.start()
    assert writer.flush(timeout=30)
    writer.close()
    assert store.transactions == [[("mdsf", 14), ("reference_speed", 8)]]
    stats = writer.stats()
    assert stats.rows_written == 22 and stats.transactions == 1
    for v in "ab":
        got = inner.query_series(v, 0, 2**62, estimator="reference_speed")
        assert_rows_equal(got, ref[v])
        assert_rows_equal(inner.query_series(v, 0, T0_NS + 50 * DT_NS), mdsf[v])


def test_a_refused_estimators_rows_are_dropped_alone(backend: Backend) -> None:
    """Rows of an estimator the store does not serve are data it refuses: the other
    estimator's rows of the same transaction are still written."""
    from tests.server.storage.test_estimator_tables import _store_with

    backend.open()
    mdsf_only = _store_with(backend, (MDSF_SPEC,))
    try:
        mdsf_only.migrate()
        mdsf_only.upsert_vehicle("a", {}, now_ns=1)
        writer = StoreWriter(mdsf_only, _settings())
        writer.submit(batch_of(MDSF_SPEC, {"a": make_rows(5)}))
        writer.submit(batch_of(REF, {"a": make_spec_rows(REF, 3)}))
        writer.start()
        assert writer.flush(timeout=30)
        writer.close()
        stats = writer.stats()
        assert stats.rows_written == 5 and stats.rows_dropped_error == 3
        assert "reference_speed" in (stats.last_error or "")
        assert len(mdsf_only.query_series("a", 0, 2**62)) == 5
    finally:
        mdsf_only.close()


def test_submit_refuses_rows_not_of_the_dtype() -> None:
    writer = StoreWriter(None, _settings())  # type: ignore[arg-type]  # never reaches a store
    with pytest.raises(TypeError):
        writer.submit([("a", make_spec_rows(REF, 3))])  # plain pairs are MDSF rows
    with pytest.raises(TypeError):
        EstimateBatch(["a"], [3], make_rows(3), REF)
    assert writer.stats().rows_submitted == 0


# ---------------------------------------------------------------------------- calls


def test_call_runs_on_the_writer_thread_and_returns_or_raises(backend: Backend) -> None:
    store = backend.open()
    with StoreWriter(store, _settings()) as writer:
        name, record = writer.call(
            lambda s: (threading.current_thread().name, s.upsert_vehicle("v1", {"x": 1}, 5))
        )
        assert name == "slipfleet-store-writer"
        assert record == store.get_vehicle("v1")
        token = writer.call(lambda s: s.create_token("t", "viewer", "d" * 64, 7))
        with pytest.raises(StorageDataError):  # a duplicate hash
            writer.call(lambda s: s.create_token("t2", "admin", "d" * 64, 8))

        def broken(s: Store) -> None:
            raise ValueError("not the store's fault")

        with pytest.raises(ValueError, match="not the store's fault"):
            writer.call(broken)
        # the writer goes on as before
        writer.submit([("v1", make_rows(3))])
        assert writer.flush(timeout=30)
        stats = writer.stats()
    assert stats.healthy and stats.rows_written == 3
    assert store.list_tokens() == [token]


@contextlib.contextmanager
def _writer_held(writer: StoreWriter) -> Iterator[None]:
    """Hold ``writer``'s thread inside a call for the block, so what the block hands the writer
    waits; on leaving, let it go and wait for that call to return."""
    release = threading.Event()
    blocker = threading.Thread(target=writer.call, args=(lambda s: release.wait(30),))
    blocker.start()
    time.sleep(0.1)  # the writer thread is inside the call now
    try:
        yield
    finally:
        release.set()
        blocker.join()


def test_call_comes_after_the_registrations_queued_before_it(backend: Backend) -> None:
    store = backend.open()
    got: list[Any] = []
    with StoreWriter(store, _settings()) as writer:
        with _writer_held(writer):  # both below wait
            writer.submit_vehicle("auto", {"kind": "auto"}, now_ns=1)
            reader = threading.Thread(
                target=lambda: got.append(writer.call(lambda s: s.get_vehicle("auto")))
            )
            reader.start()
            time.sleep(0.1)
        reader.join()
    assert got[0] is not None and got[0].config == {"kind": "auto"}


def test_call_is_answered_at_once_during_an_outage(backend: Backend) -> None:
    store = backend.open(fast_fail=True)
    store.upsert_vehicle("v1", {}, now_ns=1)
    writer = StoreWriter(store, _settings(commit_interval_s=0.05), retry_initial_s=30.0).start()
    try:
        with backend.outage():
            writer.submit([("v1", make_rows(10))])
            deadline = time.monotonic() + 20
            while writer.stats().healthy:  # the rows' write failed: a 30 s backoff begins
                assert time.monotonic() < deadline
                time.sleep(0.01)
            started = time.monotonic()
            with pytest.raises(StorageError):
                writer.call(lambda s: s.upsert_vehicle("v2", {}, 2), timeout_s=20.0)
            assert time.monotonic() - started < 10  # not held back by the rows' backoff
        assert writer.call(lambda s: s.upsert_vehicle("v2", {}, 3)).vehicle_id == "v2"
    finally:
        writer.close(timeout=0.1)


def test_a_call_that_times_out_is_dropped(backend: Backend) -> None:
    store = backend.open()
    ran: list[str] = []
    with StoreWriter(store, _settings()) as writer:
        with _writer_held(writer), pytest.raises(StorageError, match="no answer"):
            writer.call(lambda s: ran.append("late"), timeout_s=0.2)
        assert writer.call(lambda s: ran.append("next")) is None
    assert ran == ["next"]


def test_call_needs_a_running_writer(backend: Backend) -> None:
    store = backend.open()
    writer = StoreWriter(store, _settings())
    with pytest.raises(RuntimeError, match="not started"):
        writer.call(lambda s: s.ping())
    writer.start()
    assert writer.call(lambda s: s.ping()) is True
    writer.close()
    with pytest.raises(RuntimeError, match="closed"):
        writer.call(lambda s: s.ping())
