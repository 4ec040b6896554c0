"""The pipeline spread over worker processes: one GIL per share of the fleet.

One server process holds one Python interpreter lock, and decoding, reordering and estimating
are Python work under it: on its own a process falls behind at some hundreds of vehicles while
a second core idles. With ``IngestSettings.workers = N`` (N ≥ 1) the server keeps Zenoh, the
REST API, the sinks (store writer, live hub, alerts) and the vehicles' registrations, and
starts ``N`` worker processes, each running a :class:`~server.ingest.pipeline.Pipeline` (decode,
reorder buffers, estimator registry) for the vehicles it owns::

    Zenoh ─▶ FifoChannel ─▶ route thread ──(key, payload) bursts──▶ worker k: decode, Pipeline
                            (vehicle → owner)                             │ rows, counters
                                                                          ▼
                     sinks ◀── collect thread ◀───────────── result pipes of all workers

* **Ownership.** Vehicle ``v`` belongs to worker ``crc32(v) mod N`` (:func:`owner_of`): stable
  across restarts, no table to share. Packets whose key names no vehicle go to worker 0,
  which refuses them (counted as usual).
* **Route thread** (the subscriber's thread, :class:`~server.ingest.subscriber.IngestSubscriber`,
  whose ``take`` is :meth:`WorkerPool.route`): takes the samples in bursts as in-process ingest
  does, splits each burst by owner and sends each share undecoded down that worker's pipe. A
  worker that falls behind fills its pipe, the send blocks, the Zenoh channel fills, and BLOCK
  congestion control slows the publishers: nothing is dropped silently.
* **Workers** (:func:`_worker_main`, started with ``spawn``: Zenoh's threads do not survive
  ``fork``) decode each share (``decode_burst``) and submit it to their pipeline, whose one sink
  sends every estimator call's rows back as one array with the estimator's name and the
  vehicles' ids and row counts; the server rebuilds the batch with that name's spec
  (:func:`estimator.catalog.spec_of`). Once a second (and when they stop) they send a
  snapshot of their ingest counters, estimator counters, ENU anchors and pipeline stats. With
  ``store_raw_packets`` they also send back the packets their decoder accepted, to be stored raw.
  Vehicles they register themselves (``unknown_vehicle = "auto"``) are reported to the server,
  which stores them.
* **Collect thread**: waits on every worker's result pipe and hands rows to the sinks (one
  thread, as the in-process pipeline thread calls them), snapshots to the merged views below,
  new vehicles to ``on_new_vehicle``.
* **A worker that dies** is started again by the collect thread (:meth:`WorkerPool._restart`)
  with its vehicles registered again, their counters continued from its last snapshot and
  their ENU frames kept; its vehicles' estimators start afresh. Packets routed to it meanwhile
  are counted (``dropped_worker_down``); ``running`` is false until it is back.
* **Control**: :meth:`WorkerPool.register_vehicle`, :meth:`~WorkerPool.remove_vehicle`,
  :meth:`~WorkerPool.restore_counters` and :meth:`~WorkerPool.restore_anchor` go to the owner's
  control pipe; vehicle configs received over Zenoh are decoded here and registered the same
  way.

:class:`WorkerPool` has :class:`~server.ingest.pipeline.Pipeline`'s public interface, so the
runtime uses either. Its snapshots are as of the workers' last report (at most a second old,
as the in-process estimator counters already are).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import threading
import zlib
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection, wait
from typing import Any

import zenoh

from estimator.catalog import spec_of
from estimator.config import VehicleConfig
from estimator.types import EstimateBatch
from server.estimation.registry import EstimatorRegistry
from server.ingest.pipeline import PHASES, STAT_COUNTERS, EstimateSink, Pipeline
from server.ingest.status import StatusPublisher
from server.ingest.subscriber import IngestSubscriber, RawPacket, Refusal
from server.metrics.thread_cpu import thread_cpu_seconds
from server.protocol.keys import parse_key
from server.settings import IngestSettings, Settings, ZenohSettings
from server.storage.base import Anchor

__all__ = ["WorkerPool", "owner_of"]

try:
    import fcntl
except ImportError:  # not POSIX
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

#: How often a worker reports its counters, anchors and stats (seconds).
SNAPSHOT_EVERY_S = 1.0
#: Sensor keys whose owner the route thread remembers (three per vehicle), at most.
OWNER_KEYS = 100_000
#: Buffer of the pipes to and from a worker (Linux's default is 64 KiB, about three bursts):
#: room for ~0.1 s of a worker's packets at 1,000 vehicles, so the route thread does not block
#: each time the worker's receiving thread waits a few milliseconds for the interpreter lock.
PIPE_BYTES = 1 << 20
#: Longest wait for a worker to start (imports, estimator registry) or to stop.
START_TIMEOUT_S = 60.0

# pipeline stats that are not summed over workers
_STATS_MAX = ("last_tick_ms",)
_STATS_ALL = ("running",)
# the workers' pipeline stats before their first report (a second after start at most), so
# that /metrics right after start reads zeros rather than missing keys
_STATS_UNREPORTED: dict[str, int | float] = {
    **dict.fromkeys(STAT_COUNTERS, 0),
    **dict.fromkeys(("queue_bursts", "queue_bytes", "queue_bytes_peak"), 0),
    "last_tick_ms": 0.0,
    **{f"cpu_{phase}_s": 0.0 for phase in PHASES},
}


def _widen(conn: Connection) -> None:
    """Give the pipe under ``conn`` :data:`PIPE_BYTES` of buffer where the OS allows it
    (Linux; elsewhere, or above ``/proc/sys/fs/pipe-max-size``, it keeps its own)."""
    set_size = getattr(fcntl, "F_SETPIPE_SZ", None) if fcntl is not None else None
    if set_size is None:
        return
    try:
        fcntl.fcntl(conn.fileno(), set_size, PIPE_BYTES)
    except OSError as exc:
        log.debug("pipe buffer left as it is: %s", exc)


def owner_of(vehicle_id: str, workers: int) -> int:
    """The worker (0 … ``workers`` − 1) that owns ``vehicle_id``: ``crc32(id) mod workers``."""
    return zlib.crc32(vehicle_id.encode()) % workers


class _Worker:
    """The server's end of one worker process: its pipes and its last snapshot."""

    def __init__(
        self,
        index: int,
        settings: Settings,
        ctx: Any,
        initial: list[tuple[Any, ...]],
        registry_factory: Callable[[], EstimatorRegistry],
        store_raw: bool = False,
    ) -> None:
        self.index = index
        feed_recv, self.feed = ctx.Pipe(duplex=False)
        self.results, results_send = ctx.Pipe(duplex=False)
        for conn in (self.feed, self.results):
            _widen(conn)
        control_recv, self.control = ctx.Pipe(duplex=False)
        self.feed_lock = threading.Lock()
        self.control_lock = threading.Lock()
        self.process = ctx.Process(
            target=_worker_main,
            args=(
                index,
                settings.ingest.model_dump_json(),
                settings.zenoh.key_prefix,
                initial,
                registry_factory,
                feed_recv,
                results_send,
                control_recv,
                store_raw,
            ),
            name=f"slipfleet-worker-{index}",
            daemon=True,
        )
        self.process.start()
        for end in (feed_recv, results_send, control_recv):
            end.close()  # the child holds them now
        self.snapshot: dict[str, Any] = {}
        self.done = threading.Event()

    def send_control(self, message: tuple[Any, ...]) -> None:
        with self.control_lock:
            self.control.send(message)


class WorkerPool:
    """Decode, reorder and estimate in ``settings.ingest.workers`` processes.

    Parameters are those of :class:`~server.ingest.pipeline.Pipeline` but the registry: each
    worker builds its own with ``registry_factory`` (a module-level callable: it is pickled to
    the spawned workers); ``restart_registry_factory``, when given, is asked for a fresh one
    each time a dead worker is started again (the vehicles' state stored since start, e.g. their
    calibrations, instead of the state at start). ``session`` None runs without Zenoh (feed
    with :meth:`route`).
    """

    def __init__(
        self,
        settings: Settings,
        session: zenoh.Session | None,
        sinks: Sequence[EstimateSink] = (),
        on_new_vehicle: Callable[[str, VehicleConfig], None] | None = None,
        *,
        raw_sink: Callable[[list[RawPacket]], object] | None = None,
        registry_factory: Callable[[], EstimatorRegistry] = EstimatorRegistry,
        restart_registry_factory: Callable[[], Callable[[], EstimatorRegistry]] | None = None,
    ) -> None:
        if settings.ingest.workers < 1:
            raise ValueError("WorkerPool needs ingest.workers >= 1")
        self._settings = settings
        self._prefix = settings.zenoh.key_prefix
        self._n = settings.ingest.workers
        self._sinks = list(sinks)
        self._on_new_vehicle = on_new_vehicle
        self._registry_factory = registry_factory
        self._restart_registry_factory = restart_registry_factory
        self._workers: list[_Worker] = []
        self._ctx = mp.get_context("spawn")
        # every registered vehicle's config: what a worker is started (or restarted) with
        self._configs: dict[str, VehicleConfig] = {}
        self._stored_counters: dict[str, dict[str, int]] = {}  # restore_counters before start
        self._stored_anchors: dict[str, Anchor] = {}  # restore_anchor before start
        self._owner_by_key: dict[str, int] = {}  # sensor key -> worker (route thread only)
        self._collector: threading.Thread | None = None
        self._stats = {
            "sink_errors": 0,
            "worker_messages": 0,
            "dropped_worker_down": 0,
            "worker_restarts": 0,
        }
        # raw packets come back from the workers once decoded: only the accepted ones
        self._raw_sink = raw_sink
        self._subscriber = (
            IngestSubscriber(session, settings.zenoh, settings.ingest, self.route, self.refuse)
            if session is not None
            else None
        )
        # each refused vehicle is told on <prefix>/<id>/status (server.ingest.status)
        self._status = (
            StatusPublisher(session, settings.zenoh.key_prefix, self.counters_snapshot)
            if session is not None
            else None
        )
        self._config_thread: threading.Thread | None = None
        self._stopping = threading.Event()

    # ------------------------------------------------------------------ lifecycle

    def add_sink(self, sink: EstimateSink) -> None:
        """Add a sink before :meth:`start`."""
        if self._workers:
            raise RuntimeError("add sinks before start()")
        self._sinks.append(sink)

    def start(self) -> None:
        """Start the workers (and wait until each is ready), the collector, the subscriber."""
        if self._workers:
            raise RuntimeError("already started")
        self._workers = [
            _Worker(
                k,
                self._settings,
                self._ctx,
                self._initial(k, self._stored_counters, self._stored_anchors),
                self._registry_factory,
                self._raw_sink is not None,
            )
            for k in range(self._n)
        ]
        self._stored_counters = {}
        self._stored_anchors = {}
        for w in self._workers:
            if not _ready(w):
                self.stop()
                raise RuntimeError(f"worker {w.index} did not start")
        self._collector = threading.Thread(
            target=self._collect, name="slipfleet-collect", daemon=True
        )
        self._collector.start()
        if self._subscriber is not None:
            self._subscriber.start()
            self._config_thread = threading.Thread(
                target=self._poll_configs, name="slipfleet-configs", daemon=True
            )
            self._config_thread.start()
        if self._status is not None:
            self._status.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop the subscriber, let every worker work off what it has, collect, join."""
        self._stopping.set()
        if self._status is not None:
            self._status.stop()
        if self._subscriber is not None:
            self._subscriber.stop(timeout_s)
        if self._config_thread is not None:
            self._config_thread.join(timeout_s)
        for w in self._workers:
            try:
                with w.feed_lock:
                    w.feed.send(None)  # end of input: the worker flushes and says "done"
            except (OSError, ValueError):
                w.done.set()  # already gone
        if self._collector is not None:
            self._collector.join(START_TIMEOUT_S)
            if self._collector.is_alive():
                log.warning("worker results still coming after %.0f s", START_TIMEOUT_S)
        for w in self._workers:
            w.process.join(timeout_s)
            if w.process.is_alive():
                log.warning("worker %d did not stop; terminating it", w.index)
                w.process.terminate()
                w.process.join(timeout_s)

    # ------------------------------------------------------------------ input

    def route(self, received: list[tuple[str, bytes]]) -> None:
        """Send each packet of a burst, undecoded, to the worker that owns its vehicle."""
        shares: list[list[tuple[str, bytes]]] = [[] for _ in self._workers]
        owners = self._owner_by_key
        for item in received:  # each (key, payload) pair passed on as it is
            owner = owners.get(item[0])
            if owner is None:
                owner = self._owner_of_key(item[0])
            shares[owner].append(item)
        for w, share in zip(self._workers, shares, strict=True):
            if share:
                self._send(w, share, len(share))

    def refuse(self, refused: list[Refusal]) -> None:
        """Send packets the subscriber refused from their length to their owners to count."""
        shares: list[list[Refusal]] = [[] for _ in self._workers]
        for key, reason in refused:
            shares[self._owner_by_key.get(key, self._owner_of_key(key))].append((key, reason))
        for w, share in zip(self._workers, shares, strict=True):
            if share:
                self._send(w, ("refused", share), len(share))

    def _send(self, w: _Worker, message: object, packets: int) -> None:
        try:
            if w.done.is_set():
                raise BrokenPipeError
            with w.feed_lock:
                w.feed.send(message)
        except (OSError, ValueError):
            self._stats["dropped_worker_down"] += packets
            log.error("worker %d is down: dropped %d packets", w.index, packets)

    def _owner_of_key(self, key: str) -> int:
        """The worker for a sensor key (0 for a key that names no vehicle: it is refused
        there and counted); remembered for up to :data:`OWNER_KEYS` keys."""
        try:
            owner = owner_of(parse_key(key, self._prefix)[0], self._n)
        except ValueError:
            return 0
        if len(self._owner_by_key) < OWNER_KEYS:
            self._owner_by_key[key] = owner
        return owner

    def _poll_configs(self) -> None:
        """Vehicle configs received over Zenoh: register with the owner, report them."""
        assert self._subscriber is not None
        while not self._stopping.wait(0.1):
            for update in self._subscriber.poll_configs():
                # the owner reports it back ("new") once its estimators took the config
                self._control(update.vehicle_id, ("add", update.vehicle_id, update.config, True))

    # ------------------------------------------------------------------ control

    def _control(self, vehicle_id: str, message: tuple[Any, ...]) -> None:
        """Send ``message`` to the owner (before start: its start takes ``_configs``)."""
        if self._workers:
            self._workers[owner_of(vehicle_id, self._n)].send_control(message)

    def _initial(
        self, k: int, counters: dict[str, dict[str, int]], anchors: dict[str, Anchor]
    ) -> list[tuple[Any, ...]]:
        """What worker ``k`` starts with: its vehicles' registrations and, of ``counters`` and
        ``anchors``, its vehicles' totals to continue from and ENU frames to go on in."""
        configs = list(self._configs.items())  # a copy: registrations may come meanwhile

        def mine(vid: str) -> bool:
            return owner_of(vid, self._n) == k

        return (
            [("add", vid, c, False) for vid, c in configs if mine(vid)]
            + [("restore", vid, t) for vid, t in counters.items() if mine(vid)]
            + [("anchor", vid, a) for vid, a in anchors.items() if mine(vid)]
        )

    def register_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        """Start or reconfigure a vehicle (in the worker that owns it)."""
        self._configs[vehicle_id] = config
        self._control(vehicle_id, ("add", vehicle_id, config, False))

    def remove_vehicle(self, vehicle_id: str) -> None:
        """Forget a vehicle: estimators, reorder buffer and counters."""
        self._configs.pop(vehicle_id, None)
        self._control(vehicle_id, ("remove", vehicle_id))

    def send_command(self, vehicle_id: str, estimator: str, key: str, on: bool) -> None:
        """Turn an estimator's command on or off for a vehicle (in the worker that owns it)."""
        self._control(vehicle_id, ("command", vehicle_id, estimator, key, on))

    def restore_counters(self, vehicle_id: str, totals: dict[str, int]) -> None:
        """Continue a vehicle's ingest counters from stored totals (call before :meth:`start`)."""
        if self._workers:
            self._control(vehicle_id, ("restore", vehicle_id, dict(totals)))
        else:
            self._stored_counters[vehicle_id] = dict(totals)

    def restore_anchor(self, vehicle_id: str, anchor: Anchor) -> None:
        """Go on in the vehicle's stored ENU frame (in the worker that owns it)."""
        lat, lon, h = anchor
        frame = (float(lat), float(lon), float(h))
        if self._workers:
            self._control(vehicle_id, ("anchor", vehicle_id, frame))
        else:
            self._stored_anchors[vehicle_id] = frame

    # ------------------------------------------------------------------ output

    def _collect(self) -> None:
        """Results of every worker until each has said it is done; a worker that dies
        before is started again (:meth:`_restart`)."""
        left = {w.results: w for w in self._workers}
        while left:
            for ready in wait(list(left), timeout=1.0):
                assert isinstance(ready, Connection)
                w = left[ready]
                try:
                    message = ready.recv()
                except (EOFError, OSError):
                    del left[ready]
                    w.done.set()
                    if not self._stopping.is_set() and (new := self._restart(w)) is not None:
                        left[new.results] = new
                    continue
                self._stats["worker_messages"] += 1
                if self._take(w, message):
                    w.done.set()
                    del left[ready]

    def _restart(self, dead: _Worker) -> _Worker | None:
        """Start a worker in place of ``dead`` with its vehicles registered again, their
        counters continued from its last snapshot (at most a second old) and their ENU frames
        kept. The vehicles' estimators start afresh; packets routed to it meanwhile are
        counted as dropped (and as sequence gaps by the new worker)."""
        dead.process.join(1.0)
        log.error(
            "worker %d exited (code %s): starting it again", dead.index, dead.process.exitcode
        )
        k = dead.index
        initial = self._initial(
            k, dead.snapshot.get("counters", {}), dict(dead.snapshot.get("anchors", {}))
        )
        store_raw = self._raw_sink is not None
        factory = self._registry_factory
        if self._restart_registry_factory is not None:
            try:
                factory = self._restart_registry_factory()
            except Exception:  # the store may be the trouble: start with the state at start
                log.exception("worker %d: fresh registry state unavailable", k)
        new = _Worker(k, self._settings, self._ctx, initial, factory, store_raw)
        if not _ready(new):
            log.error("worker %d did not start again", k)
            new.process.kill()
            return None
        new.snapshot = dead.snapshot  # until its own first report
        self._workers[k] = new
        self._stats["worker_restarts"] += 1
        return new

    def _take(self, w: _Worker, message: tuple[Any, ...]) -> bool:
        """Act on one worker message; True when the worker is done."""
        kind = message[0]
        if kind == "rows":
            name, ids, counts, rows = message[1:]
            batch = EstimateBatch(ids, counts, rows, spec_of(name))
            for sink in self._sinks:
                try:
                    sink.on_estimates(batch)
                except Exception:
                    self._stats["sink_errors"] += 1
                    log.exception("sink %r failed", sink)
        elif kind == "new":
            self._configs[message[1]] = message[2]
            if self._on_new_vehicle is not None:
                try:
                    self._on_new_vehicle(message[1], message[2])
                except Exception:
                    log.exception("on_new_vehicle failed for %s", message[1])
        elif kind == "raw" and self._raw_sink is not None:
            self._raw_sink(message[1])
        elif kind in ("snapshot", "done"):
            w.snapshot = message[1]
        return kind == "done"

    # ------------------------------------------------------------------ views

    def _merged(self, name: str) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for w in self._workers:
            out.update(w.snapshot.get(name, {}))
        return out

    def counters_snapshot(self) -> dict[str, dict[str, int]]:
        """Per-vehicle ingest counters (as of each worker's last report)."""
        return self._merged("counters")

    def restorable_counters(self) -> dict[str, dict[str, int]]:
        """Counters with their sequence numbers, taken together by each worker's pipeline
        (:meth:`Pipeline.restorable_counters`), as of its last report."""
        return self._merged("restorable")

    def estimator_counters_snapshot(self) -> dict[str, dict[str, dict[str, int]]]:
        """``{estimator: {vehicle_id: {event: n}}}`` over every worker."""
        out: dict[str, dict[str, dict[str, int]]] = {}
        for w in self._workers:
            for name, per_vehicle in w.snapshot.get("estimator_counters", {}).items():
                out.setdefault(name, {}).update(per_vehicle)
        return out

    def anchors_snapshot(self) -> dict[str, tuple[float, float, float]]:
        """Each vehicle's ENU anchor."""
        return self._merged("anchors")

    def thread_cpu_snapshot(self) -> dict[str, dict[str, float]]:
        """``{"worker-k": {thread name: CPU seconds}}`` (:mod:`server.metrics.thread_cpu`) of each
        worker process, as of its last report; a restarted worker counts from zero again."""
        return {f"worker-{w.index}": dict(w.snapshot.get("thread_cpu", {})) for w in self._workers}

    def stats(self) -> dict[str, Any]:
        """The workers' pipeline stats summed (``last_tick_ms`` the largest), plus the pool's;
        ``running`` only while every worker and the collector run."""
        merged: dict[str, Any] = {**_STATS_UNREPORTED, **self._stats}
        for w in self._workers:
            for key, value in w.snapshot.get("stats", {}).items():
                if key in _STATS_MAX:
                    merged[key] = max(merged.get(key, 0), value)
                elif key not in _STATS_ALL and isinstance(value, int | float):
                    merged[key] = merged.get(key, 0) + value
        merged["workers"] = len(self._workers)
        merged["running"] = (
            bool(self._workers)
            and all(w.process.is_alive() and not w.done.is_set() for w in self._workers)
            and self._collector is not None
            and self._collector.is_alive()
        )
        return merged


def _ready(w: _Worker) -> bool:
    """Wait for a new worker's "ready" (False: it died or took too long)."""
    try:
        return bool(w.results.poll(START_TIMEOUT_S)) and w.results.recv()[0] == "ready"
    except (EOFError, OSError):
        return False


# ---------------------------------------------------------------------------- worker process


class _Results:
    """A worker's result pipe, shared by its pipeline thread and its snapshot loop."""

    def __init__(self, conn: Connection) -> None:
        self._conn = conn
        self._lock = threading.Lock()

    def send(self, message: tuple[Any, ...]) -> None:
        with self._lock:
            self._conn.send(message)

    def on_estimates(self, batch: EstimateBatch) -> None:
        """Pipeline sink: one estimator call's rows as one array, with the estimator's name
        and the vehicles' ids and row counts."""
        self.send(("rows", batch.estimator, batch.ids, batch.counts, batch.rows))


def _snapshot(pipeline: Any) -> dict[str, Any]:
    return {
        "counters": pipeline.counters_snapshot(),
        "restorable": pipeline.restorable_counters(),
        "estimator_counters": pipeline.estimator_counters_snapshot(),
        "anchors": pipeline.anchors_snapshot(),
        "stats": pipeline.stats(),
        "thread_cpu": thread_cpu_seconds(),
    }


def _apply(pipeline: Any, message: tuple[Any, ...]) -> None:
    """One control message from the server."""
    if message[0] == "add":
        pipeline.register_vehicle(message[1], message[2], notify=message[3])
    elif message[0] == "remove":
        pipeline.remove_vehicle(message[1])
    elif message[0] == "restore":
        pipeline.restore_counters(message[1], message[2])
    elif message[0] == "anchor":
        pipeline.restore_anchor(message[1], message[2])
    elif message[0] == "command":
        pipeline.send_command(*message[1:])


def _worker_main(
    index: int,
    ingest_json: str,
    key_prefix: str,
    initial: list[tuple[Any, ...]],
    registry_factory: Callable[[], EstimatorRegistry],
    feed: Connection,
    results_conn: Connection,
    control: Connection,
    store_raw: bool = False,
) -> None:
    """A worker process: decode what the server routes here and run a pipeline on it
    (``store_raw``: send the packets it accepted back, to be stored raw)."""
    from server.gc_policy import settle

    logging.basicConfig(level=logging.WARNING, format=f"worker {index}: %(levelname)s %(message)s")
    # what a pipeline without a Zenoh session reads; nothing from the environment or files
    settings = Settings.model_construct(
        ingest=IngestSettings.model_validate_json(ingest_json),
        zenoh=ZenohSettings(key_prefix=key_prefix),
    )
    results = _Results(results_conn)
    pipeline = _worker_pipeline(settings, registry_factory, results, store_raw)
    stop = threading.Event()
    for message in initial:  # registrations and stored counters, before the first packet
        _apply(pipeline, message)
    settle(settings.ingest.gc_gen0)
    threading.Thread(
        target=_serve_controls, args=(pipeline, control, stop), name="worker-control", daemon=True
    ).start()
    pipeline.start()
    snapshot_thread = threading.Thread(
        target=_send_snapshots, args=(pipeline, results, stop), name="worker-snapshots", daemon=True
    )
    snapshot_thread.start()
    results.send(("ready",))
    try:
        _feed_pipeline(pipeline, feed)
    finally:
        stop.set()
        pipeline.stop()
        snapshot_thread.join(5.0)
        results.send(("done", _snapshot(pipeline)))


def _worker_pipeline(
    settings: Settings,
    registry_factory: Callable[[], EstimatorRegistry],
    results: _Results,
    store_raw: bool,
) -> Pipeline:
    """A worker's pipeline, without Zenoh: its rows, new vehicles and raw packets go to
    ``results``."""
    return Pipeline(
        settings,
        None,
        registry_factory(),
        sinks=[results],
        on_new_vehicle=lambda vid, config: results.send(("new", vid, config)),
        raw_sink=(lambda raw: results.send(("raw", raw))) if store_raw else None,
    )


def _serve_controls(pipeline: Pipeline, control: Connection, stop: threading.Event) -> None:
    """Apply the server's control messages to ``pipeline`` until ``stop`` or the pipe closes."""
    while not stop.is_set():
        try:
            if not control.poll(0.2):
                continue
            message = control.recv()
        except (EOFError, OSError):
            return
        _apply(pipeline, message)


def _send_snapshots(pipeline: Pipeline, results: _Results, stop: threading.Event) -> None:
    """Send the pipeline's snapshot every :data:`SNAPSHOT_EVERY_S` until ``stop``."""
    while not stop.wait(SNAPSHOT_EVERY_S):
        results.send(("snapshot", _snapshot(pipeline)))


def _feed_pipeline(pipeline: Pipeline, feed: Connection) -> None:
    """Hand the bursts and refusals the server routes here to ``pipeline`` until the feed ends
    (``None`` or a closed pipe)."""
    while True:
        try:
            share = feed.recv()
        except (EOFError, OSError):
            break
        if share is None:
            break
        if isinstance(share, tuple):  # ("refused", [(key, reason), ...])
            pipeline.refuse(share[1])
        else:
            pipeline.submit_raw(share)
