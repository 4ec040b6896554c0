"""The single batching writer thread.

Every estimate row the server keeps goes through one :class:`StoreWriter`: producers (the
pipeline thread) call :meth:`StoreWriter.submit`, which only appends to an in-memory backlog; the
writer thread drains it in transactions of up to ``batch_max_rows`` rows. A transaction starts
``commit_interval_s`` after the previous one started, or as soon as rows arrive when that long
has passed already (the writer was idle): rows that come in bursts (the pipeline hands over one
per estimator call) are committed at once instead of waiting out an interval, and a row waits
at most ``commit_interval_s`` for its transaction to start. The default (0.02 s) is well under
the estimator calls' 50 ms, so each call's rows go out at once even when calls come a little
early or a commit ran late; under a flood transactions start once per interval, each carrying
what arrived in one. Rows of every estimator share the backlog; a transaction carries a batch
per estimator (``Store.write_estimates(*batches)``), so every estimator's rows of a tick are
stored together.

Bounded backlog, no silent loss:

* the backlog holds at most ``backlog_max_rows`` rows (queued + the batch being written);
* when it is full, ``submit`` waits up to ``submit_block_s`` for room (only while the database
  is healthy — during an outage waiting cannot help), then refuses the rows and counts them in
  ``rows_dropped_backlog_full`` (and logs, rate-limited);
* a failed transaction (:class:`StorageError`) keeps its rows and is retried with exponential
  backoff (``retry_initial_s`` doubling up to ``retry_max_s``) — a database outage becomes a
  bounded backlog that is written out when the database is back;
* rows the database rejects as data (:class:`StorageDataError`, or any unexpected exception)
  are retried per vehicle once, then dropped and counted in ``rows_dropped_error``;
* :meth:`StoreWriter.close` writes everything out, retrying until ``close_timeout_s``; what is
  still pending then is counted in ``rows_lost_on_close`` and logged as an error.

Vehicles the pipeline registers itself (auto-registered on a first packet, or a config sent
over Zenoh) are stored by the writer too (:meth:`StoreWriter.submit_vehicle`), before any
estimate transaction that starts after the call: the store keeps only rows of vehicles it knows,
so a vehicle stored by another thread could lose its first rows to the race (it did: 5-49 rows a
1,000-vehicle load test, each a new vehicle's first).

Writes other threads make (REST: vehicle upserts and deletes, tokens) go through the same
thread by :meth:`StoreWriter.call`, which runs ``fn(store)`` there between two writes and hands
back its result or error: one writer, so REST writes and estimate transactions never contend
for the database lock, and a REST upsert never races a queued registration.

Ingest counters (:meth:`StoreWriter.submit_counters`, latest totals win), the vehicles' ENU
anchors (:meth:`StoreWriter.submit_anchors`, each stored once) and, when ``store_raw_packets``
is on, raw packets (:meth:`StoreWriter.submit_raw_packets`, at most ``raw_packets_max_bytes`` of
payload in the database: :class:`_RawBudget`) ride the same thread; counters go
in slices of :data:`COUNTER_VEHICLES_PER_WRITE` vehicles, with the estimate transactions that
fall due in between. With ``retention_days > 0`` the writer also deletes old
estimates every ``retention_interval_s``. A store with a ``maintain()`` method (SQLite: moving
new rows from its staging table, see :meth:`server.storage.sqlite.SqliteStore.maintain`) gets
it called, one short step at a time, whenever no write is due, and paced: after a step with
more to do the next waits :data:`MAINTAIN_PAUSE_PER_STEP` times as long as the step took.

The writer does not own the store: close the writer first, then the store.
"""

from __future__ import annotations

import concurrent.futures
import itertools
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, TypeVar

import numpy as np

from estimator.spec import EstimatorSpec
from estimator.types import EstimateBatch, concat_estimates
from server.settings import StorageSettings
from server.storage._columns import as_batches
from server.storage.base import Anchor, StorageDataError, StorageError, Store

__all__ = ["StoreWriter", "WriterStats"]

log = logging.getLogger(__name__)

T = TypeVar("T")
#: How long :meth:`StoreWriter.call` waits for its answer by default.
CALL_TIMEOUT_S = 10.0

_NS_PER_DAY = 86_400 * 1_000_000_000
_LOG_EVERY_S = 30.0
_RAW_PACKETS_MAX = 100_000
#: Once the stored raw packets fill ``raw_packets_max_bytes``, the database's total is read
#: again at most this often (retention may have made room).
RAW_BUDGET_RECHECK_S = 60.0
#: Vehicles whose counters one write carries at most: a fleet's counters (1,000 vehicles x 11
#: a second) written in one statement held the estimate commits back for tens of ms; in
#: slices, estimates that fall due in between go first.
COUNTER_VEHICLES_PER_WRITE = 100
#: Seconds between calls of the store's ``maintain`` while it has nothing to do, and after a
#: failed one.
MAINTAIN_IDLE_S = 0.25
MAINTAIN_RETRY_S = 5.0
#: Pause after an upkeep step with more to do, as a multiple of that step's wall time (at most
#: ``MAINTAIN_IDLE_S``). SQLite's move round at 1,000 vehicles is ~11 steps of 25-60 ms every
#: ~2 s; run back to back they took ~0.3 s of the machine's CPU within half a second, and the
#: whole fleet's latency, live and stored, rose by 20-40 ms each time. Spread over the round's
#: period the same work leaves the pipeline its share of the cores.
MAINTAIN_PAUSE_PER_STEP = 2.0


@dataclass(frozen=True, slots=True)
class WriterStats:
    """A snapshot of the writer's counters (all totals since the writer was created)."""

    rows_submitted: int
    """Rows accepted into the backlog."""
    rows_written: int
    """Rows the database inserted."""
    rows_ignored: int
    """Rows committed but not inserted: already stored (replays) or vehicle not registered."""
    rows_dropped_backlog_full: int
    """Rows refused by ``submit`` because the backlog was full."""
    rows_dropped_error: int
    """Rows the database rejected as data (not retried)."""
    rows_lost_on_close: int
    """Rows still pending when ``close`` gave up (database unreachable)."""
    transactions: int
    """Committed estimate transactions."""
    backlog_rows: int
    """Rows waiting (queued + being written)."""
    last_commit_ns: int | None
    """Wall-clock time of the last successful estimate commit."""
    last_error: str | None
    """Message of the most recent failure (kept after recovery)."""
    healthy: bool
    """The writer thread runs (or has not been started) and its last write succeeded."""
    consecutive_failures: int
    raw_packets_written: int
    raw_packets_dropped: int
    retention_rows_deleted: int
    vehicles_stored: int = 0
    """Vehicle registrations written (:meth:`StoreWriter.submit_vehicle`)."""
    vehicles_dropped_error: int = 0
    """Vehicle registrations the database rejected as data (not retried)."""
    raw_packets_over_budget: int = 0
    """Raw packets not stored because the stored ones hold ``raw_packets_max_bytes``."""


#: One submit's rows in the backlog: ``(spec, ids, counts, rows)`` as an :class:`EstimateBatch`
#: holds them (a copy), so a tick's rows of a thousand vehicles are one entry, not a thousand.
_Queued = tuple[EstimatorSpec, list[str], list[int], np.ndarray]
#: One aux write: ``(counters, raw packets, anchors, seq)`` (:meth:`StoreWriter._write_aux`).
_Aux = tuple[
    dict[str, dict[str, int]], list[tuple[str, int, str, bytes]], dict[str, Anchor], int | None
]


def _per_vehicle(
    spec: EstimatorSpec, ids: list[str], counts: list[int], rows: np.ndarray
) -> list[_Queued]:
    """The entry ``(spec, ids, counts, rows)`` as one entry per vehicle (views of ``rows``)."""
    bounds = [0, *itertools.accumulate(counts)]
    return [
        (spec, [vid], [n], rows[a:b])
        for vid, n, (a, b) in zip(ids, counts, itertools.pairwise(bounds), strict=True)
    ]


def _split(entry: _Queued, n_rows: int) -> tuple[_Queued, _Queued]:
    """``entry`` cut after its first ``n_rows`` rows (0 < n_rows < its rows): a vehicle the
    cut falls within has its first rows in the head and the rest in the tail."""
    spec, ids, counts, rows = entry
    k, before = 0, 0
    while before + counts[k] <= n_rows:
        before += counts[k]
        k += 1
    head_ids, head_counts = ids[:k], counts[:k]
    tail_ids, tail_counts = ids[k:], counts[k:]
    if before < n_rows:  # the cut falls within vehicle k
        head_ids, head_counts = [*head_ids, ids[k]], [*head_counts, n_rows - before]
        tail_counts = [counts[k] - (n_rows - before), *tail_counts[1:]]
    return (spec, head_ids, head_counts, rows[:n_rows]), (
        spec,
        tail_ids,
        tail_counts,
        rows[n_rows:],
    )


def _joined(spec: EstimatorSpec, entries: list[_Queued]) -> EstimateBatch:
    """One estimator's entries as one batch (a vehicle of two entries is named twice, each
    part in the order submitted: the stores key every row by its vehicle and stamp)."""
    if len(entries) == 1:
        _, ids, counts, rows = entries[0]
        return EstimateBatch(ids, counts, rows, spec)
    return EstimateBatch(
        [vid for e in entries for vid in e[1]],
        [n for e in entries for n in e[2]],
        concat_estimates([e[3] for e in entries]),
        spec,
    )


class StoreWriter:
    """Batching writer thread in front of a :class:`Store`.

    Parameters
    ----------
    store : Store
        Where rows go; used from the writer thread only.
    settings : StorageSettings
        ``batch_max_rows``, ``commit_interval_s``, ``backlog_max_rows``, ``retention_days``,
        ``store_raw_packets``.
    submit_block_s : float
        How long ``submit`` may wait for room in a full backlog while the database is healthy.
    retry_initial_s, retry_max_s : float
        Backoff after a failed transaction: doubles from the first to the second.
    retention_interval_s : float
        How often retention runs when ``retention_days > 0`` (the first run is at start).
    close_timeout_s : float
        Default time ``close`` keeps retrying to write the backlog out.
    clock_ns : callable
        Wall clock in ns since the epoch (retention cut-off, ``last_commit_ns``).
    """

    def __init__(
        self,
        store: Store,
        settings: StorageSettings,
        *,
        submit_block_s: float = 0.05,
        retry_initial_s: float = 0.1,
        retry_max_s: float = 5.0,
        retention_interval_s: float = 3600.0,
        close_timeout_s: float = 30.0,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._store = store
        self._clock_ns = clock_ns
        self._init_limits(
            settings,
            submit_block_s,
            retry_initial_s,
            retry_max_s,
            retention_interval_s,
            close_timeout_s,
        )
        self._init_backlog(store)
        self._init_stats()

    def _init_limits(
        self,
        settings: StorageSettings,
        submit_block_s: float,
        retry_initial_s: float,
        retry_max_s: float,
        retention_interval_s: float,
        close_timeout_s: float,
    ) -> None:
        """The batch, backlog, raw-packet and retention limits and the retry and close times."""
        self._batch_max = int(settings.batch_max_rows)
        self._interval_s = float(settings.commit_interval_s)
        self._backlog_max = int(settings.backlog_max_rows)
        self._retention_ns = int(settings.retention_days * _NS_PER_DAY)
        self._store_raw = bool(settings.store_raw_packets)
        self._raw_max_bytes = int(settings.raw_packets_queue_max_bytes)
        self._raw_budget = _RawBudget(int(settings.raw_packets_max_bytes))
        self._submit_block_s = float(submit_block_s)
        self._retry_initial_s = float(retry_initial_s)
        self._retry_max_s = float(retry_max_s)
        self._retention_interval_s = float(retention_interval_s)
        self._close_timeout_s = float(close_timeout_s)

    def _init_backlog(self, store: Store) -> None:
        """The empty backlog and side queues the writer thread drains, and its schedule."""
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        # backlog: a submit's rows as one entry (or one per vehicle when the backlog was near full)
        self._queue: deque[_Queued] = deque()
        self._queued_rows = 0
        self._inflight: list[EstimateBatch] | None = None
        self._inflight_rows = 0
        self._seq_submitted = 0  # rows accepted so far
        self._seq_done = 0  # rows finished (committed, ignored or dropped as bad data)
        self._counters: dict[str, dict[str, int]] = {}
        # totals already queued (or written): a counter that did not change is not written again
        self._counters_sent: dict[str, dict[str, int]] = {}
        self._raw: list[tuple[str, int, str, bytes]] = []
        self._raw_bytes = 0  # payload bytes in self._raw
        # ENU anchors to store, and the vehicles whose anchor was queued (each is stored once)
        self._anchors: dict[str, Anchor] = {}
        self._anchors_sent: set[str] = set()
        # store calls (StoreWriter.call) waiting for the writer thread, in order
        self._calls: deque[tuple[Callable[[Store], Any], concurrent.futures.Future[Any]]] = deque()
        # vehicle registrations to store before the next estimate transaction (latest wins)
        self._vehicles: dict[str, tuple[dict[str, Any], int]] = {}
        self._vehicles_stored = 0
        self._vehicles_dropped = 0
        self._aux_seq = 0
        self._aux_done = 0
        self._aux_due_at = 0.0
        self._flush_waiters = 0
        self._closing = False
        self._close_deadline = 0.0
        self._retry_at = 0.0
        self._next_retention_at = 0.0
        self._last_txn_start = -float("inf")  # monotonic s the last estimate transaction began
        # the store's own upkeep between writes (SQLite: moving new rows to their final table)
        self._next_maintain_at = 0.0

    def _init_stats(self) -> None:
        """The counters and health :meth:`stats` reports, and the log rate limits, at start."""
        self._rows_submitted = 0
        self._rows_written = 0
        self._rows_ignored = 0
        self._rows_dropped_full = 0
        self._rows_dropped_error = 0
        self._rows_lost_on_close = 0
        self._transactions = 0
        self._last_commit_ns: int | None = None
        self._last_error: str | None = None
        self._healthy = True
        self._failures = 0
        self._raw_written = 0
        self._raw_dropped = 0
        self._retention_deleted = 0
        self._last_drop_log = -_LOG_EVERY_S
        self._last_fail_log = -_LOG_EVERY_S

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> StoreWriter:
        """Start the writer thread (idempotent); return ``self``."""
        with self._cond:
            if self._closing:
                raise RuntimeError("StoreWriter is closed")
            if self._thread is None:
                self._next_retention_at = time.monotonic()
                self._thread = threading.Thread(
                    target=self._run, name="slipfleet-store-writer", daemon=True
                )
                self._thread.start()
        return self

    def __enter__(self) -> StoreWriter:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self, timeout: float | None = None) -> None:
        """Stop accepting rows, write out the backlog (retrying up to ``timeout`` seconds,
        default ``close_timeout_s``), stop the thread. Rows still pending are counted as lost."""
        with self._cond:
            if self._closing:
                thread = self._thread
            else:
                self._closing = True
                wait_s = self._close_timeout_s if timeout is None else float(timeout)
                self._close_deadline = time.monotonic() + max(wait_s, 0.0)
                if self._thread is None and self._pending_locked():
                    self._thread = threading.Thread(
                        target=self._run, name="slipfleet-store-writer", daemon=True
                    )
                    self._thread.start()
                thread = self._thread
                self._cond.notify_all()
        if thread is not None:
            thread.join()
        with self._cond:
            calls, self._calls = self._calls, deque()
        for _, future in calls:
            if future.set_running_or_notify_cancel():
                future.set_exception(RuntimeError("StoreWriter is closed"))
        with self._cond:
            lost = self._queued_rows + self._inflight_rows
            if lost:
                self._rows_lost_on_close += lost
                self._queue.clear()
                self._queued_rows = 0
                self._inflight = None
                self._inflight_rows = 0
                log.error(
                    "store writer closed with %d rows not written (last error: %s)",
                    lost,
                    self._last_error,
                )
            self._cond.notify_all()

    # ------------------------------------------------------------------ producers

    def submit(self, batch: EstimateBatch | Sequence[tuple[str, np.ndarray]]) -> int:
        """Queue one estimator's rows of several vehicles for writing; return the rows accepted.

        A plain ``[(vehicle_id, rows), …]`` is taken as rows of ``"mdsf"``. Never blocks
        longer than ``submit_block_s``. Rows are copied, so the caller may reuse its buffers.
        Rows that do not fit are counted in ``rows_dropped_backlog_full``.

        Raises
        ------
        TypeError
            Rows of a plain list are not 1-d arrays of the estimator's dtype (nothing of the
            batch is queued).
        RuntimeError
            The writer is closed.
        """
        parts = as_batches([batch])
        if not parts:
            with self._cond:
                if self._closing:
                    raise RuntimeError("StoreWriter is closed")
            return 0
        part = parts[0]
        spec, rows, total = part.spec, part.rows.copy(), len(part.rows)
        ids, counts = list(part.ids), list(part.counts)
        if 0 in counts:
            ids = [vid for vid, n in zip(ids, counts, strict=True) if n]
            counts = [n for n in counts if n]
        with self._cond:
            if self._closing:
                raise RuntimeError("StoreWriter is closed")
            if total and self._pending_rows_locked() + total <= self._backlog_max:
                # the common case: room for every row, queued as one entry
                self._queue.append((spec, ids, counts, rows))
                self._queued_rows += total
                self._seq_submitted += total
                self._rows_submitted += total
                self._cond.notify_all()
                return total
        return self._submit_per_vehicle(_per_vehicle(spec, ids, counts, rows))

    def _submit_per_vehicle(self, entries: list[_Queued]) -> int:
        """Queue each vehicle's entry that fits the backlog, waiting up to ``submit_block_s``
        for room; count the others dropped. Returns the rows accepted."""
        accepted = 0
        deadline = time.monotonic() + self._submit_block_s
        with self._cond:
            if self._closing:
                raise RuntimeError("StoreWriter is closed")
            for entry in entries:
                n = len(entry[3])
                while n <= self._backlog_max < self._pending_rows_locked() + n:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0 or not self._healthy:
                        break
                    self._cond.wait(remaining)
                if self._pending_rows_locked() + n > self._backlog_max:
                    self._rows_dropped_full += n
                    now = time.monotonic()
                    if now - self._last_drop_log >= _LOG_EVERY_S:
                        self._last_drop_log = now
                        log.warning(
                            "store writer backlog full (%d rows): %d rows dropped so far",
                            self._backlog_max,
                            self._rows_dropped_full,
                        )
                    continue
                self._queue.append(entry)
                self._queued_rows += n
                self._seq_submitted += n
                self._rows_submitted += n
                accepted += n
            self._cond.notify_all()
        return accepted

    def on_estimates(self, batch: EstimateBatch | Sequence[tuple[str, np.ndarray]]) -> None:
        """Pipeline sink (once per estimator and tick): same as :meth:`submit`."""
        self.submit(batch)

    def submit_vehicle(self, vehicle_id: str, config: dict[str, Any], now_ns: int) -> None:
        """Queue a vehicle's registration (``Store.upsert_vehicle``); it is written before
        any estimate transaction that starts after this call, so rows submitted after it find
        the vehicle stored. A later call for the same vehicle replaces one not yet written."""
        with self._cond:
            if self._closing:
                raise RuntimeError("StoreWriter is closed")
            self._vehicles.pop(vehicle_id, None)
            self._vehicles[vehicle_id] = (dict(config), int(now_ns))
            self._cond.notify_all()

    def forget_vehicle(self, vehicle_id: str) -> None:
        """Drop a registration not yet written (the vehicle was deleted meanwhile); a vehicle
        registered again under that id gets its anchor stored anew."""
        with self._cond:
            self._vehicles.pop(vehicle_id, None)
            self._anchors.pop(vehicle_id, None)
            self._anchors_sent.discard(vehicle_id)

    def submit_anchors(self, anchors: Mapping[str, Anchor]) -> None:
        """Queue the ENU anchors ``{vehicle_id: (lat_deg, lon_deg, height_m)}`` of vehicles
        whose anchor was not queued before (the store keeps the first one anyway)."""
        with self._cond:
            if self._closing:
                raise RuntimeError("StoreWriter is closed")
            new = {vid: a for vid, a in anchors.items() if vid not in self._anchors_sent}
            if new:
                self._anchors_sent.update(new)
                self._anchors.update(new)
                self._aux_touched_locked()

    def submit_counters(self, counters: dict[str, dict[str, int]]) -> None:
        """Queue ingest counter totals ``{vehicle_id: {name: total}}`` (latest totals win).

        Only totals that changed since they were last queued are written: most of a vehicle's
        counters (refusal reasons, restarts) stay put from one second to the next, and a
        1,000-vehicle fleet's full set was ~15,000 upserts a second."""
        with self._cond:
            if self._closing:
                raise RuntimeError("StoreWriter is closed")
            for vid, named in counters.items():
                sent = self._counters_sent.setdefault(str(vid), {})
                changed = {str(k): int(v) for k, v in named.items() if sent.get(str(k)) != v}
                if changed:
                    sent.update(changed)
                    self._counters.setdefault(str(vid), {}).update(changed)
            self._aux_touched_locked()

    def submit_raw_packets(self, packets: Sequence[tuple[str, int, str, bytes]]) -> int:
        """Queue ``(vehicle_id, received_ns, key, payload)`` when ``store_raw_packets`` is on.

        The queue holds at most ``_RAW_PACKETS_MAX`` packets and ``raw_packets_queue_max_bytes``
        payload bytes; packets beyond either are dropped (``raw_packets_dropped``). Returns the
        packets accepted (0 when raw packets are not stored).
        """
        if not self._store_raw or not packets:
            return 0
        with self._cond:
            if self._closing:
                raise RuntimeError("StoreWriter is closed")
            take = self._raw_room_locked(packets)
            self._raw_dropped += len(packets) - len(take)
            self._raw.extend(take)
            if take:
                self._aux_touched_locked()
            return len(take)

    def _raw_room_locked(
        self, packets: Sequence[tuple[str, int, str, bytes]]
    ) -> list[tuple[str, int, str, bytes]]:
        """The leading ``packets`` that fit the raw queue's packet and byte bounds (counted in)."""
        room = max(_RAW_PACKETS_MAX - len(self._raw), 0)
        take: list[tuple[str, int, str, bytes]] = []
        for packet in packets[:room]:
            size = len(packet[3])
            if self._raw_bytes + size > self._raw_max_bytes:
                break
            self._raw_bytes += size
            take.append(packet)
        return take

    def call(self, fn: Callable[[Store], T], timeout_s: float = CALL_TIMEOUT_S) -> T:
        """Run ``fn(store)`` on the writer thread and return its result or raise its error.

        For the writes other threads make (REST: vehicles, tokens), so that every write goes
        through this one thread: a call runs as soon as the write in progress ends, after the
        vehicle registrations queued before it and ahead of queued rows, also while estimate
        writes wait out a database outage (the call gets the outage's error at once).

        Raises
        ------
        StorageError
            No answer within ``timeout_s`` (the call is dropped if it has not started; one that
            has runs to its end).
        RuntimeError
            The writer is closed or not started.
        """
        if threading.current_thread() is self._thread:
            return fn(self._store)
        future: concurrent.futures.Future[T] = concurrent.futures.Future()
        with self._cond:
            if self._closing or self._thread is None:
                raise RuntimeError("StoreWriter is closed or not started")
            self._calls.append((fn, future))
            self._cond.notify_all()
        try:
            return future.result(timeout_s)
        except concurrent.futures.TimeoutError:
            future.cancel()
            raise StorageError(f"store writer gave no answer within {timeout_s:.1f} s") from None

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until everything submitted before this call is committed; False on timeout."""
        with self._cond:
            rows_target, aux_target = self._seq_submitted, self._aux_seq
            self._flush_waiters += 1
            self._cond.notify_all()
            try:
                return self._cond.wait_for(
                    lambda: (
                        self._seq_done >= rows_target
                        and self._aux_done >= aux_target
                        and not self._vehicles
                    ),
                    timeout,
                )
            finally:
                self._flush_waiters -= 1

    def stats(self) -> WriterStats:
        with self._cond:
            alive = self._thread is None or self._thread.is_alive() or self._closing
            return WriterStats(
                rows_submitted=self._rows_submitted,
                rows_written=self._rows_written,
                rows_ignored=self._rows_ignored,
                rows_dropped_backlog_full=self._rows_dropped_full,
                rows_dropped_error=self._rows_dropped_error,
                rows_lost_on_close=self._rows_lost_on_close,
                transactions=self._transactions,
                backlog_rows=self._pending_rows_locked(),
                last_commit_ns=self._last_commit_ns,
                last_error=self._last_error,
                healthy=self._healthy and alive,
                consecutive_failures=self._failures,
                raw_packets_written=self._raw_written,
                raw_packets_dropped=self._raw_dropped,
                raw_packets_over_budget=self._raw_budget.refused,
                retention_rows_deleted=self._retention_deleted,
                vehicles_stored=self._vehicles_stored,
                vehicles_dropped_error=self._vehicles_dropped,
            )

    # ------------------------------------------------------------------ writer thread

    def _pending_rows_locked(self) -> int:
        return self._queued_rows + self._inflight_rows

    def _pending_locked(self) -> bool:
        return bool(
            self._pending_rows_locked()
            or self._aux_done < self._aux_seq
            or self._vehicles
            or self._calls
        )

    def _aux_touched_locked(self) -> None:
        if self._aux_done == self._aux_seq:  # first change since the last write
            self._aux_due_at = time.monotonic() + self._interval_s
        self._aux_seq += 1
        self._cond.notify_all()

    def _take_locked(self) -> list[EstimateBatch]:
        """Pop up to ``batch_max_rows`` rows off the backlog: a batch per estimator, its
        entries joined in the order submitted."""
        taken: dict[str, tuple[EstimatorSpec, list[_Queued]]] = {}
        queue, n = self._queue, 0
        while queue and n < self._batch_max:
            entry = queue[0]
            room = self._batch_max - n
            if len(entry[3]) <= room:
                queue.popleft()
            else:
                entry, queue[0] = _split(entry, room)
            of_spec = taken.get(entry[0].name)
            if of_spec is None:
                taken[entry[0].name] = (entry[0], [entry])
            else:
                of_spec[1].append(entry)
            n += len(entry[3])
        self._queued_rows -= n
        self._inflight_rows = n
        # the rows were checked against their spec when submitted: joined as they are
        return [_joined(spec, entries) for spec, entries in taken.values()]

    def _take_counters_locked(self) -> dict[str, dict[str, int]]:
        """Pop the counters of up to :data:`COUNTER_VEHICLES_PER_WRITE` vehicles."""
        if len(self._counters) <= COUNTER_VEHICLES_PER_WRITE:
            taken, self._counters = self._counters, {}
            return taken
        vids = list(itertools.islice(self._counters, COUNTER_VEHICLES_PER_WRITE))
        return {vid: self._counters.pop(vid) for vid in vids}

    def _next_job_locked(self) -> tuple[str, Any] | None:
        """Wait until something is due; return ``(kind, payload)`` or None to stop."""
        while True:
            now = time.monotonic()
            if self._closing and (not self._pending_locked() or now >= self._close_deadline):
                return None
            if self._calls:  # also during a backoff, after the registrations queued before
                if self._vehicles and now >= self._retry_at:
                    taken, self._vehicles = self._vehicles, {}
                    return "vehicles", taken
                return "call", self._calls.popleft()
            if now < self._retry_at:
                until = self._retry_at
                if self._closing:
                    until = min(until, self._close_deadline)
                self._cond.wait(max(until - now, 0.0))
                continue
            urgent = self._closing or self._flush_waiters > 0
            if self._vehicles:  # before the rows: the store keeps rows of known vehicles only
                taken, self._vehicles = self._vehicles, {}
                return "vehicles", taken
            if self._inflight is not None:
                return "estimates", self._inflight
            if self._queued_rows and (
                self._queued_rows >= self._batch_max
                or urgent
                or now >= self._last_txn_start + self._interval_s
            ):
                self._last_txn_start = now
                self._inflight = self._take_locked()
                return "estimates", self._inflight
            if self._aux_done < self._aux_seq and (urgent or now >= self._aux_due_at):
                return "aux", self._take_aux_locked()
            if self._retention_ns > 0 and not self._closing and now >= self._next_retention_at:
                return "retention", None
            if not self._closing and now >= self._next_maintain_at:
                return "maintain", None
            due = self._next_due_locked()
            self._cond.wait(None if due is None else max(due - now, 0.0))

    def _take_aux_locked(self) -> _Aux:
        """Pop the next aux write: ``(counters, raw, anchors, seq)``; ``seq`` is the aux change
        it completes, None while more slices of counters wait (the aux data counts as written
        once the last slice is)."""
        counters = self._take_counters_locked()
        raw, self._raw, self._raw_bytes = self._raw, [], 0
        anchors, self._anchors = self._anchors, {}
        seq = None if self._counters else self._aux_seq
        return counters, raw, anchors, seq

    def _next_due_locked(self) -> float | None:
        """The monotonic time the next job falls due: the earliest of the next transaction,
        aux write, retention run, store upkeep and the close deadline; None for nothing."""
        deadlines = []
        if self._queued_rows:
            deadlines.append(self._last_txn_start + self._interval_s)
        if self._aux_done < self._aux_seq:
            deadlines.append(self._aux_due_at)
        if self._retention_ns > 0 and not self._closing:
            deadlines.append(self._next_retention_at)
        if not self._closing:
            deadlines.append(self._next_maintain_at)
        if self._closing:
            deadlines.append(self._close_deadline)
        return min(deadlines) if deadlines else None

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    job = self._next_job_locked()
                if job is None:
                    return
                kind, payload = job
                if kind == "estimates":
                    self._write_estimates(payload)
                elif kind == "vehicles":
                    self._write_vehicles(payload)
                elif kind == "aux":
                    self._write_aux(*payload)
                elif kind == "call":
                    self._run_call(*payload)
                elif kind == "maintain":
                    self._run_maintain()
                else:
                    self._run_retention()
        except BaseException:
            log.exception("store writer thread crashed")
            with self._cond:
                self._healthy = False
                self._last_error = "writer thread crashed"
                self._cond.notify_all()
            raise

    def _failed_locked(self, exc: BaseException) -> None:
        """Record a retryable failure and schedule the retry."""
        self._failures += 1
        self._healthy = False
        self._last_error = str(exc) or type(exc).__name__
        delay = min(self._retry_initial_s * 2 ** (self._failures - 1), self._retry_max_s)
        self._retry_at = time.monotonic() + delay
        now = time.monotonic()
        if self._failures == 1 or now - self._last_fail_log >= _LOG_EVERY_S:
            self._last_fail_log = now
            log.warning(
                "store write failed (%d in a row, %d rows waiting), retrying in %.1f s: %s",
                self._failures,
                self._pending_rows_locked(),
                delay,
                self._last_error,
            )
        self._cond.notify_all()

    def _succeeded_locked(self) -> None:
        if self._failures:
            log.info("store writes recovered after %d failures", self._failures)
        self._failures = 0
        self._healthy = True
        self._retry_at = 0.0

    def _write_estimates(self, batches: list[EstimateBatch]) -> None:
        """One transaction of every estimator's rows taken off the backlog."""
        n = sum(len(b.rows) for b in batches)
        written, bad = 0, 0
        try:
            written = self._store.write_estimates(*batches)
        except StorageDataError as exc:
            written, bad = self._write_one_by_one(batches, exc)
        except StorageError as exc:
            with self._cond:
                self._failed_locked(exc)  # keep the batch in flight and retry it
            return
        except Exception as exc:
            written, bad = self._write_one_by_one(batches, exc)
        with self._cond:
            self._rows_written += written
            self._rows_ignored += n - written - bad
            self._rows_dropped_error += bad
            self._transactions += 1
            self._last_commit_ns = self._clock_ns()
            self._seq_done += n
            self._inflight = None
            self._inflight_rows = 0
            self._succeeded_locked()
            self._cond.notify_all()

    def _write_one_by_one(
        self, batches: list[EstimateBatch], first: BaseException
    ) -> tuple[int, int]:
        """After a data error, write each estimator's rows of each vehicle alone; drop only
        the ones refused."""
        log.error("store rejected a batch as data, isolating per vehicle: %s", first)
        written, bad = 0, 0
        for batch in batches:
            for vid, rows in batch:
                try:
                    written += self._store.write_estimates(
                        EstimateBatch([vid], [len(rows)], rows, batch.spec)
                    )
                except Exception as exc:
                    bad += len(rows)
                    log.exception(
                        "dropping %d %s rows of vehicle %s: %s",
                        len(rows),
                        batch.estimator,
                        vid,
                        exc,
                    )
                    with self._cond:
                        self._last_error = str(exc) or type(exc).__name__
        return written, bad

    def _write_vehicles(self, vehicles: dict[str, tuple[dict[str, Any], int]]) -> None:
        """Store registrations in order; on a database outage put back what is left (a newer
        registration of the same vehicle, submitted meanwhile, wins) and retry later."""
        items = list(vehicles.items())
        for i, (vid, (config, now_ns)) in enumerate(items):
            try:
                self._store.upsert_vehicle(vid, config, now_ns)
            except StorageError as exc:
                if not isinstance(exc, StorageDataError):
                    with self._cond:
                        self._vehicles = {**dict(items[i:]), **self._vehicles}
                        self._failed_locked(exc)
                    return
                self._vehicle_refused(vid, exc)
            except Exception as exc:  # as a data error: this vehicle only, the rest go on
                self._vehicle_refused(vid, exc)
            else:
                with self._cond:
                    self._vehicles_stored += 1
        with self._cond:
            self._succeeded_locked()
            self._cond.notify_all()

    def _vehicle_refused(self, vehicle_id: str, exc: Exception) -> None:
        log.error("store refused vehicle %s, not stored: %s", vehicle_id, exc)
        with self._cond:
            self._vehicles_dropped += 1
            self._last_error = str(exc) or type(exc).__name__

    def _write_aux(
        self,
        counters: dict[str, dict[str, int]],
        raw: list[tuple[str, int, str, bytes]],
        anchors: dict[str, Anchor],
        seq: int | None,
    ) -> None:
        """Write counters, anchors and raw packets; ``seq`` (None: more counters of this round
        wait) is the aux change the write completes."""
        try:
            if counters:
                self._store.write_counters(counters, self._clock_ns())
                counters = {}
            if anchors:
                self._store.put_anchors(anchors, self._clock_ns())
                anchors = {}
            if raw:
                raw = self._raw_budget.within(self._store, raw)  # what is put back on failure
                written = self._store.write_raw_packets(raw) if raw else 0
                self._raw_budget.stored(raw[:written])
                with self._cond:
                    self._raw_written += written
                    self._raw_dropped += len(raw) - written
                raw = []
        except StorageDataError as exc:
            self._aux_rejected(exc, (counters, raw, anchors, seq))
            return
        except StorageError as exc:
            self._aux_put_back(exc, (counters, raw, anchors, seq))
            return
        with self._cond:
            if seq is not None:
                self._aux_done = seq
            self._succeeded_locked()
            self._cond.notify_all()

    def _aux_rejected(self, exc: StorageDataError, unwritten: _Aux) -> None:
        """The store refused the data of an aux write: drop what was not written of it (its
        vehicles' next counter totals go in whole) and complete its ``seq``."""
        counters, raw, _, seq = unwritten
        log.error("store rejected counters, anchors or raw packets, dropped: %s", exc)
        with self._cond:
            for vid in counters:
                self._counters_sent.pop(vid, None)
            self._raw_dropped += len(raw)
            self._last_error = str(exc)
            if seq is not None:
                self._aux_done = seq
            self._cond.notify_all()

    def _aux_put_back(self, exc: StorageError, unwritten: _Aux) -> None:
        """The store failed an aux write: put back what was not written of it, to be
        retried (newer counter totals win over these)."""
        counters, raw, anchors, _ = unwritten
        with self._cond:
            for vid, named in counters.items():
                merged = dict(named)
                merged.update(self._counters.get(vid, {}))
                self._counters[vid] = merged
            self._raw[:0] = raw
            self._raw_bytes += sum(len(p[3]) for p in raw)
            self._anchors = {**anchors, **self._anchors}
            self._failed_locked(exc)

    def _run_call(self, fn: Callable[[Store], Any], future: concurrent.futures.Future[Any]) -> None:
        """Answer one :meth:`call` (unless its caller gave up already)."""
        if not future.set_running_or_notify_cancel():
            return
        try:
            result = fn(self._store)
        except Exception as exc:  # the caller's to handle
            future.set_exception(exc)
        else:
            future.set_result(result)

    def _run_maintain(self) -> None:
        """One step of the store's upkeep; while it has more to do the next one after a pause
        of :data:`MAINTAIN_PAUSE_PER_STEP` times this one's duration (writes that fall due go
        first), else after :data:`MAINTAIN_IDLE_S`."""
        started = time.monotonic()
        try:
            more = self._store.maintain()
        except StorageError as exc:
            log.warning("store upkeep failed, retrying in %.0f s: %s", MAINTAIN_RETRY_S, exc)
            more, wait_s = False, MAINTAIN_RETRY_S
        else:
            took_s = time.monotonic() - started
            wait_s = (
                min(MAINTAIN_PAUSE_PER_STEP * took_s, MAINTAIN_IDLE_S) if more else MAINTAIN_IDLE_S
            )
        with self._cond:
            self._next_maintain_at = time.monotonic() + wait_s

    def _run_retention(self) -> None:
        cutoff_ns = self._clock_ns() - self._retention_ns
        try:
            deleted = self._store.delete_older_than(cutoff_ns)
        except StorageError as exc:
            log.warning("retention failed, retrying in a minute: %s", exc)
            with self._cond:
                self._last_error = str(exc)
                self._next_retention_at = time.monotonic() + min(self._retention_interval_s, 60.0)
            return
        with self._cond:
            self._retention_deleted += deleted
            self._next_retention_at = time.monotonic() + self._retention_interval_s
        if deleted:
            log.info("retention deleted %d estimate rows older than %d ns", deleted, cutoff_ns)


class _RawBudget:
    """The bound on the raw packets' payload bytes in the database (writer thread only).

    The stored total is read from the store (``raw_packets_bytes``) before the first write,
    then kept up to date; once full it is read again at most every
    :data:`RAW_BUDGET_RECHECK_S` (retention deletes old packets). Packets that do not fit are
    not stored and are counted in :attr:`refused`: storage stops, the oldest stay.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.refused = 0
        self._stored_bytes: int | None = None
        self._read_at = -math.inf

    def within(
        self, store: Store, raw: list[tuple[str, int, str, bytes]]
    ) -> list[tuple[str, int, str, bytes]]:
        """The leading packets of ``raw`` that fit the budget (the rest counted refused)."""
        now = time.monotonic()
        full = self._stored_bytes is not None and self._stored_bytes >= self.max_bytes
        if self._stored_bytes is None or (full and now - self._read_at >= RAW_BUDGET_RECHECK_S):
            self._stored_bytes = store.raw_packets_bytes()
            self._read_at = now
        room = self.max_bytes - self._stored_bytes
        kept: list[tuple[str, int, str, bytes]] = []
        for packet in raw:
            room -= len(packet[3])
            if room < 0:
                break
            kept.append(packet)
        self.refused += len(raw) - len(kept)
        return kept

    def stored(self, packets: Sequence[tuple[str, int, str, bytes]]) -> None:
        """Count ``packets`` as written."""
        self._stored_bytes = (self._stored_bytes or 0) + sum(len(p[3]) for p in packets)
