"""The pipeline thread: reorder, estimate, hand rows to sinks.

::

    Zenoh threads ─▶ FifoChannel ─▶ ingest thread ─▶ bounded queue ─▶ pipeline thread
                                    (bursts, undecoded)                 │ decode_burst
                                                                        │ reorder buffers
                                                                        │ registry.push
                                                                        │ registry.advance
                                                                        ▼
                                                          sinks.on_estimates(batch)

The pipeline thread owns the estimator registry, every reorder buffer and the counters' writes,
so none of them needs a lock. Every ``IngestSettings.process_interval_ms`` (longer when a tick
takes more than a third of that: see :data:`TICK_DUTY`) it releases the
packets whose time has come, pushes them to the vehicle's estimators, advances them to the
released horizon (each time it crosses a step of ``advance_step_ms`` on the vehicle's tick grid;
with the MDSF tick as the step, as soon as a tick is due) and hands each estimator's rows (one
:class:`~estimator.types.EstimateBatch` per estimator and call, read through its ``spec``) to
each sink's ``on_estimates``. Sinks run on this thread: they must only enqueue (the storage
writer and live hub do).

An estimator that raises costs only the vehicle it raised for (the registry guards every call,
see :mod:`server.estimation.registry`): counted in that vehicle's ``estimator_errors`` and
logged at most once per :data:`ERROR_LOG_EVERY_NS` per vehicle and estimator. A config that an
estimator refuses is not applied (the vehicle keeps its old one; counted ``configs_refused``).

Vehicles are registered with :meth:`Pipeline.register_vehicle` (REST, startup), by a config on
``<prefix>/<id>/config``, or, with ``unknown_vehicle = "auto"``, on their first packet with a
default :class:`VehicleConfig`. The last two call ``on_new_vehicle(vehicle_id, config)`` on the
pipeline thread so the server can store the vehicle (keep it short: enqueue).

Before a decoded packet reaches a reorder buffer it must lie within the server's wall clock
(``IngestSettings.max_future_s`` ahead, ``max_past_s`` behind), else it is refused
``clock_skew``; a packet whose samples span more than ``clock_jump_s`` is refused
``clock_jump``. The reorder buffer refuses ``clock_jump`` packets and asks for a re-anchor
(``docs/protocol.md`` §6): the vehicle's pending packets are fed and its estimators advanced to
the end of the old time base, then restarted with the same config, and the packet starts the
new one (counted ``clock_reanchors``).

Tick alignment: a vehicle's ticks are put on the last sample time of its first IMU batch
(``registry.align_ticks``, before its first push), so with batches as long as the tick (or a
whole fraction of it) every tick falls on a batch end and is computed as soon as that batch
(and the other streams' data covering it, ``until_ns``) has arrived, instead of waiting for
the next batch: up to one batch length less latency. The phase is fixed at the vehicle's first
push (the default grid if no IMU batch had come by then), and advance steps use the same one.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import zenoh

from estimator.config import VehicleConfig, WheeledRearDriveConfig
from estimator.types import EstimateBatch, WheelGap
from server.estimation.registry import (
    ConfigRefusedError,
    EstimatorRegistry,
    UnknownEstimatorError,
)
from server.ingest.adapter import fed, spec_streams, wheel_gaps
from server.ingest.counters import IngestCounters
from server.ingest.limits import ByteBudget, refusal_errors
from server.ingest.reorder import ReorderBuffer, StreamGap, Verdict
from server.ingest.status import StatusPublisher
from server.ingest.subscriber import (
    ConfigUpdate,
    IngestItem,
    IngestSubscriber,
    RawPacket,
    Refusal,
)
from server.protocol.burst import decode_burst
from server.protocol.codec import DecodeError, Packet
from server.protocol.keys import Stream
from server.settings import Settings, UnknownVehiclePolicy
from server.storage.base import Anchor

__all__ = ["PIPELINE_REASONS", "STAT_COUNTERS", "EstimateSink", "Pipeline"]

#: The counters of :meth:`Pipeline.stats` (besides its gauges: queue, last tick, CPU by phase).
STAT_COUNTERS = (
    "ticks",
    "rows",
    "sink_errors",
    "estimator_errors",
    "pipeline_errors",
    "dropped_not_running",
)


@dataclass(frozen=True, slots=True)
class _Command:
    """An operator's switch of an estimator's command for one vehicle."""

    estimator: str
    key: str
    on: bool


#: What a control step carries: a config, an ENU frame, a command or nothing.
_ControlArg = VehicleConfig | Anchor | _Command | None

log = logging.getLogger(__name__)

#: Counter-name prefix of a stream's highest sequence number (``seq_high_imu`` …).
SEQ_HIGH = "seq_high_"
#: Stored name of the boot id the ``seq_high_<stream>`` numbers were seen with (not a counter:
#: kept with them for a restart, never reported).
SEQ_BOOT = "seq_boot"

#: Parts of the pipeline thread's work whose CPU time it adds up (``stats()["cpu_<phase>_s"]``,
#: ``slipfleet_pipeline_cpu_seconds_total{phase}``): decoding bursts, offering packets to the
#: reorder buffers, releasing them to the estimators' buffers, estimator calls, handing rows to
#: the sinks (in a worker: the pipe to the server). The rest of the thread's time (control
#: messages, counter snapshots) is not counted in any of them.
PHASES = ("decode", "reorder", "release", "estimate", "deliver")

#: How often the pipeline thread copies the estimators' event counters and ENU anchors for
#: other threads.
ESTIMATOR_COUNTERS_EVERY_NS = 1_000_000_000

#: A vehicle's failing estimator is logged at most once per this long (later failures are
#: counted, and their number given in the next line).
ERROR_LOG_EVERY_NS = 10_000_000_000

#: Bursts (each up to ``subscriber.BURST`` = 512 packets) waiting for the pipeline, at most:
#: about 32 k packets (~50 MB) behind the Zenoh channel before backpressure reaches it.
QUEUE_BURSTS = 64
#: Undecoded bursts waiting one after another are decoded as one, up to this many packets: a
#: pipeline that fell behind catches up with larger bursts, which cost less per packet.
COALESCE_PACKETS = 1024
#: A pipeline tick (release, estimate, deliver) may take at most 1/TICK_DUTY of the wall time:
#: when ticks get slower than ``process_interval_ms / TICK_DUTY`` they are spaced further apart.
#: (3 spaced a 17 ms tick 50 ms apart: at 400 vehicles an estimator call came every ~70 ms
#: instead of 50 and rows reached the sinks later, while most of the tick's cost, per vehicle
#: tick, does not shrink with fewer calls.)
TICK_DUTY = 1.5
#: ... but ticks are never spaced further apart than this (live values lag by up to this).
MAX_TICK_GAP_NS = 100_000_000
#: Wall time between two looks for active vehicles that fell idle (a tail no watermark holds
#: is released); otherwise a tick visits only the vehicles that received packets.
IDLE_SWEEP_NS = 100_000_000
#: Unregistered vehicle ids that get counters of their own; refusals of further unregistered
#: ids are counted under ``counters.NO_VEHICLE`` ("").
MAX_UNREGISTERED_COUNTED = 1000
#: The span ``ingest.max_registrations_per_min`` counts self-registrations over.
REGISTRATION_WINDOW_NS = 60_000_000_000

_NONE_ACCEPTED = (0, 0)  # (packets, lost_delta) of a vehicle before its first accepted one

#: Refusal reasons the pipeline adds to the codec's (``rejected_<reason>`` counters).
PIPELINE_REASONS: tuple[str, ...] = (
    "clock_skew",  # stamps outside [wall clock - max_past_s, wall clock + max_future_s]
    "clock_jump",  # sensor time jumped within the stream (not confirmed yet) or within a packet
    "unknown_vehicle",  # no config and unknown_vehicle = "reject"
    "over_rate",  # the vehicle's payload bytes per second (ingest.vehicle_max_bytes_per_s)
    "registration_cap",  # auto-registration's cap (ingest.max_vehicles, per-minute rate)
)


class _Raw:
    """An undecoded burst in the pipeline's queue: ``[(key, payload), ...]``."""

    __slots__ = ("nbytes", "received")

    def __init__(self, received: list[tuple[str, bytes]], nbytes: int | None = None) -> None:
        self.received = received
        self.nbytes = sum(len(p) for _, p in received) if nbytes is None else nbytes

    def __len__(self) -> int:
        return len(self.received)


#: What the pipeline's queue holds: (monotonic receive time ns, decoded burst or undecoded
#: _Raw); None stops the thread.
_QueueItem = tuple[int, list[IngestItem] | _Raw] | None


@runtime_checkable
class EstimateSink(Protocol):
    """Receives estimate rows on the pipeline thread; must not block for long.

    Called once per estimator and estimator call with that estimator's
    :class:`~estimator.types.EstimateBatch` (``batch.spec`` says what the rows are; ``rows`` are
    every vehicle's joined once); every estimator a vehicle runs reaches every sink.
    """

    def on_estimates(self, batch: EstimateBatch) -> None: ...


class Pipeline:
    """Reorder buffers + estimator registry + sinks on one thread, fed by the Zenoh subscriber.

    Parameters
    ----------
    settings : Settings
        Uses ``settings.zenoh`` (prefix, filter, channel) and ``settings.ingest``.
    session : zenoh.Session or None
        Where to subscribe; None runs without Zenoh (feed with :meth:`submit`, for tests/replay).
    registry : EstimatorRegistry
        Owned by the pipeline thread once started.
    sinks : sequence of EstimateSink
    on_new_vehicle : callable(vehicle_id, config), optional
        Called for vehicles registered by the pipeline itself (auto or Zenoh config).
    raw_sink : callable, optional
        Receives the raw packets the decoder accepted, byte for byte as they arrived
        (``StorageSettings.store_raw_packets``), on the pipeline thread as each burst is
        decoded.
    clock_ns : callable, optional
        Monotonic clock in ns (for the reorder buffers' idle release); injectable for tests.
    wall_clock_ns : callable, optional
        UTC clock in ns since the epoch (the ``clock_skew`` bounds); injectable for tests.
    """

    def __init__(
        self,
        settings: Settings,
        session: zenoh.Session | None,
        registry: EstimatorRegistry,
        sinks: Sequence[EstimateSink] = (),
        on_new_vehicle: Callable[[str, VehicleConfig], None] | None = None,
        *,
        raw_sink: Callable[[list[RawPacket]], object] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        wall_clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._settings = settings
        self._ingest = settings.ingest
        self._registry = registry
        registry.on_error = self._estimator_failed
        # (vehicle, estimator) -> (clock ns before which it is not logged again, failures since)
        self._error_log: dict[tuple[str, str], tuple[int, int]] = {}
        self._sinks = list(sinks)
        self._on_new_vehicle = on_new_vehicle
        self._clock = clock_ns
        self._wall_clock = wall_clock_ns
        self._init_windows(settings)
        self._init_queues(settings)
        self._init_vehicle_state()
        # raw packets are stored once decoded, and only those the decoder accepted
        self._raw_sink = raw_sink
        self._init_zenoh(settings, session)
        self._thread: threading.Thread | None = None
        self._stats = dict.fromkeys(STAT_COUNTERS, 0)
        self._stopping = threading.Event()
        self._last_tick_s = 0.0
        self._cpu_s = dict.fromkeys(PHASES, 0.0)  # thread CPU by phase (PHASES)

    def _init_windows(self, settings: Settings) -> None:
        """The stamp bounds, lateness and tick intervals of ``settings.ingest``, in ns."""
        self._max_future_ns = round(settings.ingest.max_future_s * 1e9)
        self._max_past_ns = round(settings.ingest.max_past_s * 1e9)
        self._clock_jump_ns = round(settings.ingest.clock_jump_s * 1e9)
        self._lateness_ns = settings.ingest.lateness_ms * 1_000_000
        self._interval_ns = settings.ingest.process_interval_ms * 1_000_000
        self._advance_step_ns = settings.ingest.advance_step_ms * 1_000_000
        self._estimate_interval_ns = settings.ingest.estimate_interval_ms * 1_000_000

    def _init_queues(self, settings: Settings) -> None:
        """The bounded burst queue into the pipeline thread and its control queue, empty."""
        self._queue: queue.Queue[_QueueItem] = queue.Queue(maxsize=QUEUE_BURSTS)
        self._queued_bytes = ByteBudget(settings.ingest.queue_max_bytes)  # undecoded _Raw
        self._held: deque[_QueueItem] = deque()  # taken off the queue early (pipeline thread)
        # (op, vehicle_id, config | anchor | None, notify), op "add", "anchor" or "remove"
        self._control: deque[tuple[str, str, _ControlArg, bool]] = deque()

    def _init_vehicle_state(self) -> None:
        """The per-vehicle state and counters the pipeline thread keeps, empty."""
        # each vehicle's ENU frame origin, kept across re-registrations (a new config starts a
        # fresh estimator, which would otherwise anchor anew): restored ones and learnt ones
        self._frames: dict[str, Anchor] = {}
        self._counters = IngestCounters()
        self._estimator_counters: dict[str, dict[str, dict[str, int]]] = {}
        self._anchors: dict[str, tuple[float, float, float]] = {}
        self._seq_high: dict[str, dict[str, int]] = {}  # copied by the pipeline thread
        self._counted: dict[str, dict[str, int]] = {}  # the counters, copied with _seq_high
        self._seq_boot: dict[str, int] = {}  # copied with _seq_high: each buffer's boot id
        # from a previous run, until the first packet: highest numbers and their boot id
        self._resume_seq: dict[str, tuple[dict[str, int], int | None]] = {}
        self._buffers: dict[str, ReorderBuffer] = {}
        self._configs: dict[str, VehicleConfig] = {}
        self._active: set[str] = set()  # vehicles with data not yet released/advanced
        self._arrived: set[str] = set()  # vehicles with packets accepted since the last tick
        self._next_sweep_ns = 0
        self._advanced_ns: dict[str, int] = {}
        # vehicle -> last sample of its first IMU batch (what its ticks are to be put on), and
        # vehicle -> the phase its estimators' ticks got at their first push since they last
        # (re)started: the anchor if one was known by then, else 0 (the default grid)
        self._tick_anchor_ns: dict[str, int] = {}
        self._tick_phase_ns: dict[str, int] = {}
        self._due: dict[str, int] = {}  # vehicle -> sensor time to advance to at the next call
        self._next_estimate_ns = 0
        self._unregistered_counted: set[str] = set()
        self._registered_ns: deque[int] = deque()  # self-registrations of the last minute

    def _init_zenoh(self, settings: Settings, session: zenoh.Session | None) -> None:
        """The Zenoh subscriber and status publisher (None each without a session)."""
        self._subscriber = (
            IngestSubscriber(session, settings.zenoh, settings.ingest, self.submit_raw, self.refuse)
            if session is not None
            else None
        )
        # each refused vehicle is told on <prefix>/<id>/status (server.ingest.status)
        self._status = (
            StatusPublisher(session, settings.zenoh.key_prefix, self._counters.snapshot)
            if session is not None
            else None
        )

    # ------------------------------------------------------------------ public, any thread

    def add_sink(self, sink: EstimateSink) -> None:
        """Add a sink before :meth:`start`."""
        if self._thread is not None:
            raise RuntimeError("add sinks before start()")
        self._sinks.append(sink)

    def start(self) -> None:
        """Start the pipeline thread, then the subscriber."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._thread = threading.Thread(target=self._run, name="slipfleet-pipeline", daemon=True)
        self._thread.start()
        if self._subscriber is not None:
            try:
                self._subscriber.start()
            except Exception:  # e.g. an invalid vehicle filter: do not leave the thread behind
                self._subscriber = None
                self.stop()
                raise
        if self._status is not None:
            self._status.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop the subscriber, process what was received, flush every buffer, join."""
        if self._status is not None:
            self._status.stop()
        if self._subscriber is not None:
            self._subscriber.stop(timeout_s)
        if self._thread is None:
            return
        self._stopping.set()
        try:
            self._queue.put(None, timeout=timeout_s)
        except queue.Full:
            log.warning("pipeline queue stayed full for %.1f s while stopping", timeout_s)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning("pipeline thread did not stop within %.1f s", timeout_s)

    def submit(self, items: list[IngestItem]) -> None:
        """Queue decoded packets/refusals for the pipeline; blocks while the queue is full.

        If the pipeline thread is not running (never started, stopped, or crashed) the items
        are dropped and counted in ``stats()["dropped_not_running"]`` instead of blocking the
        caller (Zenoh's backpressure) forever.
        """
        self._put(items)

    def submit_raw(self, received: list[tuple[str, bytes]]) -> None:
        """Queue a burst of undecoded ``(key, payload)`` packets, decoded together
        (``decode_burst``) on the pipeline thread; blocks while the queue is full.

        The subscriber's ``take``. Decoding where the packets are then handled, instead of on
        the thread that receives them, keeps the two from taking turns on the interpreter lock
        for every burst.
        """
        raw = _Raw(received)
        if raw and self._wait_for_bytes(raw.nbytes):
            self._put(raw)
        elif raw:
            self._dropped_not_running(len(raw))

    def refuse(self, refused: list[Refusal]) -> None:
        """Count packets the subscriber refused before copying them (``(key, reason)``)."""
        items: list[IngestItem] = [*refusal_errors(refused, self._settings.zenoh.key_prefix)]
        self._put(items)

    def _running(self) -> bool:
        return self._thread is not None and self._thread.is_alive() and not self._stopping.is_set()

    def _wait_for_bytes(self, nbytes: int) -> bool:
        """Hold ``nbytes`` of the undecoded-bytes budget, waiting while it is spent (False:
        the pipeline stopped meanwhile)."""
        while self._running():
            if self._queued_bytes.acquire(nbytes, timeout_s=0.5):
                return True
        return False

    def _put(self, items: list[IngestItem] | _Raw) -> None:
        if not items:
            return
        received_ns = self._clock()
        while self._running():
            try:
                self._queue.put((received_ns, items), timeout=0.5)
                return
            except queue.Full:
                continue
        self._dropped_not_running(len(items))

    def _dropped_not_running(self, n: int) -> None:
        self._stats["dropped_not_running"] += n
        log.error("pipeline not running: dropped %d ingest items", n)

    def _decoded(self, items: list[IngestItem] | _Raw) -> list[IngestItem]:
        if not isinstance(items, _Raw):
            return items
        try:
            decoded = decode_burst(
                items.received,
                prefix=self._settings.zenoh.key_prefix,
                max_payload_bytes=self._ingest.max_payload_bytes,
            )
        finally:
            self._queued_bytes.release(items.nbytes)
        if self._raw_sink is not None:
            self._sink_accepted(items.received, decoded)
        return decoded

    def _sink_accepted(self, received: list[tuple[str, bytes]], decoded: list[IngestItem]) -> None:
        """Hand the packets of a burst that the decoder accepted to the raw sink, stamped now
        (UTC ns): a malformed or refused payload is never stored raw."""
        assert self._raw_sink is not None
        now_ns = time.time_ns()
        raw: list[RawPacket] = [
            (item.vehicle_id, now_ns, key, payload)
            for (key, payload), item in zip(received, decoded, strict=True)
            if isinstance(item, Packet)
        ]
        if raw:
            self._raw_sink(raw)

    def register_vehicle(
        self, vehicle_id: str, config: VehicleConfig, *, notify: bool = False
    ) -> None:
        """Start or reconfigure a vehicle (applied on the pipeline thread).

        Validate first with ``registry.names_for(config)`` to report unknown estimators.
        ``notify``: call ``on_new_vehicle`` once registered (a config that came over Zenoh to
        a worker pool's server, see :mod:`server.ingest.workers`).
        """
        self._control.append(("add", vehicle_id, config, notify))

    def remove_vehicle(self, vehicle_id: str) -> None:
        """Forget a vehicle: estimators, reorder buffer, counters and its ENU frame."""
        self._control.append(("remove", vehicle_id, None, False))

    def send_command(self, vehicle_id: str, estimator: str, key: str, on: bool) -> None:
        """Turn an estimator's command on or off for a vehicle (applied on the pipeline
        thread, between two steps; a failure is counted as an estimator error)."""
        self._control.append(("command", vehicle_id, _Command(estimator, key, on), False))

    def restore_anchor(self, vehicle_id: str, anchor: Anchor) -> None:
        """Go on in the ENU frame the vehicle's stored estimates were given in (its stored
        anchor), from now on and after any re-registration (applied on the pipeline thread,
        after the registrations asked for before it)."""
        self._control.append(("anchor", vehicle_id, anchor, False))

    def restore_counters(self, vehicle_id: str, totals: dict[str, int]) -> None:
        """Continue a vehicle's ingest counters from stored totals (call before :meth:`start`);
        its sequence tracking resumes after the stored ``seq_high_<stream>`` numbers, under the
        stored boot id (``seq_boot``) when there is one."""
        self._counters.restore(vehicle_id, totals)
        highest = {
            k.removeprefix(SEQ_HIGH): int(v) for k, v in totals.items() if k.startswith(SEQ_HIGH)
        }
        boot = totals.get(SEQ_BOOT)
        if highest or boot is not None:
            self._resume_seq[vehicle_id] = (highest, None if boot is None else int(boot))

    def estimator_counters_snapshot(self) -> dict[str, dict[str, dict[str, int]]]:
        """The estimators' event counters (resets, gated GNSS, …) as of the last second:
        ``{estimator: {vehicle_id: {event: n}}}`` (see ``EstimatorRegistry.counters``)."""
        return self._estimator_counters

    def anchors_snapshot(self) -> dict[str, tuple[float, float, float]]:
        """Each vehicle's ENU anchor ``(lat_deg, lon_deg, height_m)`` as of the last second."""
        return self._anchors

    def counters_snapshot(self) -> dict[str, dict[str, int]]:
        """Per-vehicle ingest counters (see :mod:`server.ingest.counters`), as they are now,
        plus each stream's highest sequence number as of the last second
        (``seq_high_<stream>``). To store for a restart use :meth:`restorable_counters`."""
        snap = self._counters.snapshot()
        for vid, highest in self._seq_high.items():
            if vid in snap:
                snap[vid].update({f"{SEQ_HIGH}{stream}": n for stream, n in highest.items()})
        return snap

    def restorable_counters(self) -> dict[str, dict[str, int]]:
        """The counters and each stream's highest sequence number (``seq_high_<stream>``, and
        the boot id they were seen with, ``seq_boot``) as of the last second, taken together on
        the pipeline thread, for :meth:`restore_counters`
        after a restart: it counts the packets sent after those sequence numbers as lost, so
        counters newer than them would count the packets in between twice (received and lost;
        after a SIGKILL, received + lost exceeded sent by the last second's packets)."""
        snap = {vid: dict(counts) for vid, counts in self._counted.items()}
        for vid, highest in self._seq_high.items():
            if vid in snap:
                snap[vid].update({f"{SEQ_HIGH}{stream}": n for stream, n in highest.items()})
        for vid, boot in self._seq_boot.items():
            if vid in snap:
                snap[vid][SEQ_BOOT] = boot
        return snap

    def stats(self) -> dict[str, Any]:
        """Pipeline health: queue depth, ticks, rows emitted, errors, last tick duration."""
        return {
            **self._stats,
            "queue_bursts": self._queue.qsize(),
            "queue_capacity": QUEUE_BURSTS,
            "queue_bytes": self._queued_bytes.held,
            "queue_bytes_peak": self._queued_bytes.peak,
            "last_tick_ms": round(self._last_tick_s * 1000, 3),
            "running": self._thread is not None and self._thread.is_alive(),
            **{f"cpu_{phase}_s": seconds for phase, seconds in self._cpu_s.items()},
        }

    # ------------------------------------------------------------------ pipeline thread

    def _run(self) -> None:
        next_tick = self._clock() + self._interval_ns
        next_counters = self._clock()
        received_ns = self._clock()
        while True:
            self._apply_control()
            timeout_s = max(0.0, (next_tick - self._clock()) / 1e9)
            try:
                got = self._next_item(timeout_s)
            except queue.Empty:
                got = (self._clock(), [])
            if got is None:
                break
            received_ns, items = got
            if isinstance(items, _Raw):
                received_ns, items = self._coalesce(received_ns, items)
            try:
                self._apply_configs()
                if items:
                    self._decode_and_handle(items, received_ns)
                now = self._clock()
                if now >= next_tick:
                    # While bursts wait in the queue, "now" for the idle release is the receive
                    # time of the burst just handled: a backlog must not look like silence.
                    backlog = not self._queue.empty() or self._held
                    self._tick(received_ns if backlog else now, flush=False)
                    # A tick costs a fixed part per estimator call plus a part per vehicle: as
                    # the fleet grows, ticks come less often (each at most 1/TICK_DUTY of the
                    # time) and batch more vehicles per call, instead of falling behind.
                    spent = self._clock() - now
                    next_tick = self._next_tick_ns(next_tick, now, spent)
                if now >= next_counters:
                    self._refresh_snapshots()
                    next_counters = now + ESTIMATOR_COUNTERS_EVERY_NS
            except Exception:  # a bug here must not stall ingest (Zenoh would block on us)
                self._stats["pipeline_errors"] += 1
                log.exception("pipeline step failed")
                next_tick = self._clock() + self._interval_ns
        self._shut_down()

    def _decode_and_handle(self, items: list[IngestItem] | _Raw, received_ns: int) -> None:
        """Decode a burst and offer its packets to the reorder buffers, timing both."""
        c0 = time.thread_time()
        decoded = self._decoded(items)
        c1 = time.thread_time()
        self._handle(decoded, received_ns)
        self._cpu_s["decode"] += c1 - c0
        self._cpu_s["reorder"] += time.thread_time() - c1

    def _shut_down(self) -> None:
        """Handle everything still queued, then release every buffer."""
        self._apply_control()
        self._apply_configs()
        while True:
            try:
                rest = self._next_item(None)
            except queue.Empty:
                break
            if rest:
                self._handle(self._decoded(rest[1]), rest[0])
        self._tick(self._clock(), flush=True)
        self._refresh_snapshots()  # the final counters include vehicles seen since the last one

    def _refresh_snapshots(self) -> None:
        """Copy the estimators' counters and anchors and the buffers' highest sequence
        numbers for the snapshot readers (other threads read these copies, never the live
        state)."""
        self._estimator_counters = self._registry.counters()
        self._anchors = self._registry.anchors()
        self._frames.update(self._anchors)
        self._seq_high = {v: b.seq_highest() for v, b in self._buffers.items()}
        self._seq_boot = {v: b.boot for v, b in self._buffers.items() if b.boot is not None}
        self._counted = self._counters.snapshot()

    def _next_item(self, timeout_s: float | None) -> _QueueItem:
        """The next queue item (one taken early by :meth:`_coalesce` first); waits up to
        ``timeout_s`` (None: not at all) before raising ``queue.Empty``."""
        if self._held:
            return self._held.popleft()
        if timeout_s is None:
            return self._queue.get_nowait()
        return self._queue.get(timeout=timeout_s)

    def _coalesce(self, received_ns: int, raw: _Raw) -> tuple[int, _Raw]:
        """``raw`` joined with the undecoded bursts queued right behind it, up to
        :data:`COALESCE_PACKETS`; returns the receive time of the last one joined and the
        joined burst. An item that cannot be joined is held for the next turn."""
        parts = [raw.received]
        n = len(raw)
        nbytes = raw.nbytes
        while n < COALESCE_PACKETS and not self._held:
            try:
                nxt = self._queue.get_nowait()
            except queue.Empty:
                break
            if nxt is None or not isinstance(nxt[1], _Raw):
                self._held.append(nxt)  # the stop mark or decoded items: after this burst
                break
            received_ns = nxt[0]
            parts.append(nxt[1].received)
            n += len(nxt[1])
            nbytes += nxt[1].nbytes
        if len(parts) == 1:
            return received_ns, raw
        return received_ns, _Raw([p for part in parts for p in part], nbytes)

    def _next_tick_ns(self, scheduled_ns: int, now: int, spent_ns: int) -> int:
        """When the tick after the one ``scheduled_ns`` (started at ``now``, ``spent_ns`` long)
        is due: one ``process_interval_ms`` later, but no later than the next estimator call
        (so calls come every ``estimate_interval_ms``, not at the first tick after it), and no
        sooner than the tick's duty (:data:`TICK_DUTY`) allows."""
        nearest = now + self._interval_ns // 4
        due = max(scheduled_ns + self._interval_ns, nearest)
        if self._next_estimate_ns > now:
            due = max(min(due, self._next_estimate_ns), nearest)
        return max(due, now + min(int(TICK_DUTY * spent_ns), MAX_TICK_GAP_NS))

    def _apply_control(self) -> None:
        while self._control:
            op, vid, arg, notify = self._control.popleft()
            try:
                self._control_step(op, vid, arg, notify)
            except Exception:  # a bug here must not end the thread nor drop later steps
                self._stats["pipeline_errors"] += 1
                log.exception("control step %s failed for %s", op, vid)

    def _control_step(self, op: str, vid: str, arg: _ControlArg, notify: bool) -> None:
        if op == "add" and isinstance(arg, VehicleConfig):
            self._add(vid, arg, notify=notify)
        elif op == "command" and isinstance(arg, _Command):
            self._registry.command(vid, arg.estimator, arg.key, arg.on)
        elif op == "anchor" and isinstance(arg, tuple):
            self._frames[vid] = arg
            if vid in self._configs:
                self._set_anchor(vid, arg)
        elif op == "remove":
            self._frames.pop(vid, None)
            self._registry.remove_vehicle(vid)
            self._buffers.pop(vid, None)
            self._configs.pop(vid, None)
            self._active.discard(vid)
            self._arrived.discard(vid)
            self._advanced_ns.pop(vid, None)
            self._tick_anchor_ns.pop(vid, None)
            self._tick_phase_ns.pop(vid, None)
            self._due.pop(vid, None)
            self._unregistered_counted.discard(vid)
            self._counters.forget(vid)
            for key in [k for k in self._error_log if k[0] == vid]:
                del self._error_log[key]

    def _apply_configs(self) -> None:
        if self._subscriber is None:
            return
        update: ConfigUpdate
        for update in self._subscriber.poll_configs():
            vid = update.vehicle_id
            if vid in self._configs or len(self._configs) < self._ingest.max_vehicles:
                self._add(vid, update.config, notify=True)
            else:
                log.warning("refused the config of new vehicle %s: ingest.max_vehicles", vid)

    def _frame_of(self, vehicle_id: str) -> Anchor | None:
        """The vehicle's ENU frame origin to keep: restored, or learnt (also within the last
        second, before the snapshot took it)."""
        frame = self._frames.get(vehicle_id)
        if frame is None:
            frame = self._registry.anchor(vehicle_id)
            if frame is not None:
                self._frames[vehicle_id] = frame
        return frame

    def _start_estimators(self, vehicle_id: str, config: VehicleConfig) -> bool:
        """(Re)start the vehicle's estimators with ``config``: a fresh state and tick grid, in
        the ENU frame the vehicle had (restored or learnt). False when the config names an
        unknown estimator or an estimator refuses it: the vehicle keeps what it had (a refusal
        is counted ``configs_refused``)."""
        frame = self._frame_of(vehicle_id)
        try:
            self._registry.add_vehicle(vehicle_id, config)
        except UnknownEstimatorError as exc:
            log.warning("vehicle %s not registered: %s", vehicle_id, exc)
            return False
        except ConfigRefusedError as exc:
            self._counters.config_refused(self._counter_id(vehicle_id))
            log.error("config of %s refused, the old one kept: %s", vehicle_id, exc)
            return False
        self._tick_phase_ns.pop(vehicle_id, None)
        if frame is not None:
            self._set_anchor(vehicle_id, frame)
        return True

    def _add(self, vehicle_id: str, config: VehicleConfig, *, notify: bool) -> bool:
        if not self._start_estimators(vehicle_id, config):
            return False
        self._configs[vehicle_id] = config
        buf = self._buffers.get(vehicle_id)
        if buf is not None:  # its estimators may read other streams now
            buf.expect(spec_streams(self._registry.estimators_of(vehicle_id)))
        if notify and self._on_new_vehicle is not None:
            try:
                self._on_new_vehicle(vehicle_id, config)
            except Exception:  # a failing callback must not stop ingest
                log.exception("on_new_vehicle failed for %s", vehicle_id)
        return True

    def _set_anchor(self, vehicle_id: str, anchor: Anchor) -> None:
        try:
            self._registry.set_anchor(vehicle_id, anchor)
        except ValueError as exc:  # a stored anchor that is no position: anchor anew
            log.error("anchor of %s not used: %s", vehicle_id, exc)
            self._frames.pop(vehicle_id, None)

    def _handle(self, items: list[IngestItem], now: int) -> None:
        # accepted packets are counted once per vehicle and burst: (packets, lost_delta)
        accepted: dict[str, tuple[int, int]] = {}
        try:
            self._offer_all(items, now, accepted)
        finally:
            self._counters.accepted_many(accepted)

    def _offer_all(
        self, items: list[IngestItem], now: int, accepted: dict[str, tuple[int, int]]
    ) -> None:
        """Count refusals, offer each packet to its vehicle's reorder buffer; the accepted
        ones are added up in ``accepted``."""
        counters = self._counters
        accepted_verdict, imu = Verdict.ACCEPTED, Stream.IMU  # enum members: ~70 ns a lookup
        wall = self._wall_clock()
        earliest, latest = wall - self._max_past_ns, wall + self._max_future_ns
        for item in items:
            if isinstance(item, DecodeError):
                counters.rejected(self._counter_id(item.vehicle_id), item.reason)
                continue
            vid = item.vehicle_id
            if item.first_stamp_ns < earliest or item.last_stamp_ns > latest:
                counters.rejected(self._counter_id(vid), "clock_skew")
                continue
            if item.last_stamp_ns - item.first_stamp_ns > self._clock_jump_ns:
                # one batch spanning more than a clock jump is a jump inside the packet; the
                # estimators would step through every tick of the span
                counters.rejected(self._counter_id(vid), "clock_jump")
                continue
            buf = self._buffers.get(vid)
            if buf is None:
                if not self._admit(item):
                    continue
                buf = self._buffers[vid] = self._new_buffer(vid)
                buf.resume_seq(*self._resume_seq.pop(vid, ({}, None)))
            offer = buf.offer(item, now)
            if offer.seq_restart:
                counters.seq_restart(vid)
            if offer.verdict is accepted_verdict:
                n, lost = accepted.get(vid, _NONE_ACCEPTED)
                accepted[vid] = (n + 1, lost + offer.lost_delta)
                self._active.add(vid)
                if buf.may_release:
                    self._arrived.add(vid)
                if item.stream is imu and vid not in self._tick_anchor_ns:
                    self._tick_anchor_ns[vid] = item.last_stamp_ns
            elif offer.verdict is Verdict.LATE:
                counters.late(vid, offer.lost_delta)
            elif offer.verdict is Verdict.DUPLICATE:
                counters.duplicate(vid)
            elif offer.verdict is Verdict.CLOCK_JUMP:
                counters.rejected(vid, "clock_jump", offer.lost_delta)
            else:
                self._reanchor(vid, buf, item, now)
                counters.clock_reanchor(vid)
                counters.accepted(vid, offer.lost_delta)
                self._active.add(vid)
                self._arrived.add(vid)

    def _new_buffer(self, vid: str) -> ReorderBuffer:
        return ReorderBuffer(
            self._lateness_ns,
            clock_jump_ns=self._clock_jump_ns,
            reanchor_after=self._ingest.reanchor_after_packets,
            watermarks=self._ingest.stream_watermarks,
            streams=spec_streams(self._registry.estimators_of(vid)),
        )

    def _reanchor(self, vid: str, buf: ReorderBuffer, packet: Packet, now: int) -> None:
        """End ``vid``'s old time base (feed, advance, deliver), restart its estimators with the
        same config, and start the new time base with ``packet``."""
        registry = self._registry
        packets, released = buf.release(now, flush=True)
        gaps = buf.take_gaps()
        if packets or gaps:
            self._push(vid, packets, gaps)
        self._due.pop(vid, None)  # advanced right here, to the end of the old time base
        if released is not None and released != self._advanced_ns.get(vid):
            self._deliver(registry.advance({vid: released}))
        self._advanced_ns.pop(vid, None)
        config = self._configs.get(vid)
        if config is not None and registry.has_vehicle(vid):
            self._start_estimators(vid, config)  # same config: a fresh state, the same frame
        self._tick_phase_ns.pop(vid, None)
        self._tick_anchor_ns.pop(vid, None)
        if packet.stream is Stream.IMU:
            self._tick_anchor_ns[vid] = packet.last_stamp_ns
        log.info("vehicle %s: clock re-anchored at %d ns", vid, packet.first_stamp_ns)
        buf.reanchor(packet, now)

    def _push(
        self,
        vid: str,
        packets: list[Packet],
        gaps: Sequence[StreamGap] = (),
    ) -> None:
        """Feed ``packets`` (released, in sensor-time order) to ``vid``'s estimators; ``gaps``
        (:meth:`ReorderBuffer.take_gaps`) says where data is missing (:mod:`.adapter`)."""
        if vid not in self._tick_phase_ns:
            self._tick_phase_ns[vid] = self._align(vid)
        push_all = self._registry.push_all
        notices = wheel_gaps(gaps) if gaps else ()
        before: dict[int, list[WheelGap]] = {}  # id(packet) -> notices before it
        for gap, p in notices:
            if p is not None:
                before.setdefault(id(p), []).append(gap)
        for packet in packets:
            if before and id(packet) in before:
                for gap in before[id(packet)]:
                    self._wheel_gap(vid, gap)
            measurements = fed(packet)
            if measurements:  # guarded per estimator by the registry
                push_all(vid, packet.stream, measurements)
        for gap, p in notices:
            if p is None:  # no packet after the gap in this release
                self._wheel_gap(vid, gap)

    def _wheel_gap(self, vid: str, gap: WheelGap) -> None:
        """Tell ``vid``'s estimators that its wheel data after ``gap.after_ns`` is missing:
        due without it up to ``gap.until_ns``, or lost (None): then the ticks up to
        ``after_ns`` are computed first, with the edges before the loss (everything they need
        is fed), and the estimators start the wheels' fits afresh."""
        registry = self._registry
        after_ns = gap.after_ns
        if gap.until_ns is None:
            self._counters.wheel_gap(vid)
            last = self._advanced_ns.get(vid)
            if last is None or after_ns > last:
                self._deliver(registry.advance({vid: after_ns}))
                self._advanced_ns[vid] = after_ns
        registry.push(vid, gap)

    def _admit(self, packet: Packet) -> bool:
        """First packet of a vehicle without a buffer: known, auto-registered, or refused."""
        vid = packet.vehicle_id
        if self._registry.has_vehicle(vid):
            return True
        if self._ingest.unknown_vehicle is not UnknownVehiclePolicy.AUTO_REGISTER:
            self._counters.rejected(self._counter_id(vid), "unknown_vehicle")
            return False
        if not self._may_register(vid):
            self._counters.rejected(self._counter_id(vid), "registration_cap")
            return False
        if self._add(vid, WheeledRearDriveConfig(), notify=True):
            return True
        self._counters.rejected(self._counter_id(vid), "unknown_vehicle")
        return False

    def _may_register(self, vehicle_id: str) -> bool:
        """Whether a vehicle the server does not know may register itself by its first
        packet: fewer than ``ingest.max_vehicles`` run and fewer than
        ``ingest.max_registrations_per_min`` did so in the last minute (the registration is
        then counted). A vehicle publishing its config registers as REST does, within
        ``ingest.max_vehicles`` only."""
        now = self._clock()
        window = self._registered_ns
        while window and now - window[0] >= REGISTRATION_WINDOW_NS:
            window.popleft()
        if len(window) >= self._ingest.max_registrations_per_min:
            return False
        if len(self._configs) >= self._ingest.max_vehicles:
            return False
        window.append(now)
        return True

    def _counter_id(self, vehicle_id: str | None) -> str | None:
        """Counter bucket of a refused packet: its vehicle, unless that vehicle is unregistered
        and too many unregistered ids are counted already (random ids must not grow memory)."""
        if vehicle_id is None or self._registry.has_vehicle(vehicle_id):
            return vehicle_id
        if vehicle_id in self._unregistered_counted:
            return vehicle_id
        if len(self._unregistered_counted) < MAX_UNREGISTERED_COUNTED:
            self._unregistered_counted.add(vehicle_id)
            return vehicle_id
        return None

    def _align(self, vid: str) -> int:
        """Put ``vid``'s ticks on its anchor (before its first push); returns the phase its
        estimators use, 0 (the default grid) when no IMU batch had come before that push."""
        anchor = self._tick_anchor_ns.get(vid)
        if anchor is None:
            return 0
        self._registry.align_ticks(vid, anchor)
        return anchor

    def _tick(self, now: int, *, flush: bool) -> None:
        t0 = time.perf_counter()
        c0 = time.thread_time()
        until: dict[str, int] = {}
        drained: list[str] = []
        for vid in self._to_visit(now, flush):
            released, done = self._release(vid, now, flush)
            if released is not None:
                until[vid] = released
            if done:
                drained.append(vid)
        self._active.difference_update(drained)
        c1 = time.thread_time()
        self._cpu_s["release"] += c1 - c0
        # One estimator call per estimate interval for every vehicle with a tick due: a call
        # has a fixed cost, so fewer, larger calls hold more vehicles.
        self._due.update(until)
        if self._due and (flush or now >= self._next_estimate_ns):
            self._estimate_due(now, c1)
        self._stats["ticks"] += 1
        self._last_tick_s = time.perf_counter() - t0

    def _to_visit(self, now: int, flush: bool) -> set[str]:
        """The vehicles whose horizon may have moved. It moves when their packets arrive, or
        when they fall idle: the vehicles that received something that may move it
        (ReorderBuffer.may_release), and once per IDLE_SWEEP_NS the ones that fell idle; at a
        flush every active vehicle."""
        visit: set[str] = self._arrived & self._active
        if flush:
            visit = self._active
        elif now >= self._next_sweep_ns:
            visit |= {vid for vid in self._active if self._buffers[vid].is_idle(now)}
            self._next_sweep_ns = now + IDLE_SWEEP_NS
        self._arrived = set()
        return visit

    def _release(self, vid: str, now: int, flush: bool) -> tuple[int | None, bool]:
        """Release ``vid``'s packets up to its horizon and push them to its estimators.

        Returns the horizon its ticks are due to (None: none due) and whether its buffer is
        drained up to the horizon it has advanced to. A horizon is due when it crosses a step
        of its tick grid, at a flush, or when the vehicle is idle.
        """
        buf = self._buffers[vid]
        packets, released = buf.release(now, flush=flush)
        gaps = buf.take_gaps()
        for stream in buf.take_stalls():
            self._counters.stream_stalled(vid, stream.value)
        if (packets or gaps) and self._registry.has_vehicle(vid):
            self._push(vid, packets, gaps)
        if released is None:
            return None, False
        due = None
        step, last = self._advance_step_ns, self._advanced_ns.get(vid)
        if last is None or (
            released != last
            and (
                (released - (phase := self._tick_phase_ns.get(vid, 0))) // step
                > (last - phase) // step
                or flush
                or buf.is_idle(now)
            )
        ):
            due = last = self._advanced_ns[vid] = released
        return due, released == last and buf.drained

    def _estimate_due(self, now: int, c1: float) -> None:
        """One estimator call for every vehicle with a tick due, its batches to the sinks
        (``c1``: the thread time the release ended at)."""
        due, self._due = self._due, {}
        self._next_estimate_ns = now + self._estimate_interval_ns
        batches = self._registry.advance(due)
        c2 = time.thread_time()
        self._deliver(batches)
        self._cpu_s["estimate"] += c2 - c1
        self._cpu_s["deliver"] += time.thread_time() - c2

    def _deliver(self, batches: list[EstimateBatch]) -> None:
        """Hand each estimator's batch to every sink."""
        for batch in batches:
            self._stats["rows"] += batch.rows.shape[0]
            for sink in self._sinks:
                try:
                    sink.on_estimates(batch)
                except Exception:  # one faulty sink must not stop the others or ingest
                    self._stats["sink_errors"] += 1
                    log.exception("sink %r failed", sink)

    def _estimator_failed(self, vid: str, estimator: str, operation: str, exc: Exception) -> None:
        """The registry's ``on_error``: count the failure for ``vid``; log it unless this
        vehicle's estimator was logged less than :data:`ERROR_LOG_EVERY_NS` ago."""
        self._stats["estimator_errors"] += 1
        self._counters.estimator_error(self._counter_id(vid))
        now = self._clock()
        key = (vid, estimator)
        quiet_until, unlogged = self._error_log.get(key, (now, 0))
        if now < quiet_until:
            self._error_log[key] = (quiet_until, unlogged + 1)
            return
        self._error_log[key] = (now + ERROR_LOG_EVERY_NS, 0)
        log.error(
            "estimator %s: %s failed for vehicle %s (%d more failures since the last line)",
            estimator,
            operation,
            vid,
            unlogged,
            exc_info=exc,
        )
