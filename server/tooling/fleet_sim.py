"""Publish simulated vehicles over Zenoh, and record or replay Zenoh traffic.

:class:`FleetSim` turns :func:`estimator.sim.simulate` runs into the wire protocol
(``docs/protocol.md``) and publishes them the way live vehicles would: each packet when its
sensor time is due (a batch: its last sample's time; real time, or faster by ``rate``), sensor
stamps shifted to *now*, sequence numbers per stream, vehicle ids ``sim-0001``, ``sim-0002``,
...; vehicles are spread over the 100 ms packet tick so they do not all publish at once.
Simulating is the slow part (≈0.4 s per 5-minute vehicle), so ``distinct_runs`` runs are
simulated and shared round-robin by the vehicles, each with its own time phase (and the run's
own origin, :meth:`FleetSim.spread_origin`): 3,000 vehicles of a load test play 2 drives per
scenario, not 3,000.

Publishing goes through :mod:`server.tooling.fleet_schedule`: each distinct run is encoded once, and
only stamps and sequence numbers are patched per vehicle and loop, in bulk per 100 ms window;
one thread sends every vehicle's packets from one merged schedule (a few µs of CPU a packet,
:func:`publish_fleets` for several fleets at once). The payloads are byte for byte what
:func:`encode_packet` makes of the shifted measurements.

A vehicle's published config names the estimators it runs: empty (its kind's defaults) unless
an :class:`EstimatorMix` gives every k-th vehicle others (a mixed fleet: ``sim-0004`` runs
``mdsf`` and ``reference_speed``, the others ``mdsf`` only).

:func:`record` writes what a session receives to a recording file and :func:`replay` publishes
one (format: :mod:`server.protocol.recording`).

Publishers use congestion control BLOCK and reliable transport: a slow router slows the
simulator down instead of dropping packets.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import math
import secrets
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import zenoh

from estimator.base import Measurement
from estimator.config import VehicleConfig
from estimator.types import (
    GnssSample,
    ImuBatch,
    OdometerEdges,
    SprocketEdges,
    SteeringAngles,
    WheelEdges,
    WheelSpeeds,
    WheelSpeeds4,
)
from server.protocol.codec import (
    DecodeError,
    decode,
    encode_config,
    encode_gnss,
    encode_imu,
    encode_odometer,
    encode_sprockets,
    encode_steering,
    encode_wheel_edges,
    encode_wheel_speeds,
    encode_wheel_speeds4,
)
from server.protocol.keys import Stream, config_key, parse_key, sensor_key
from server.protocol.recording import RecordingWriter, read_recording
from server.tooling.estimator_mix import EstimatorMix

if TYPE_CHECKING:
    from estimator.sim import SimRun
from server.tooling.fleet_schedule import (
    STREAMS,
    EncodedDrive,
    ScheduledVehicle,
    ScheduleStats,
    publish_schedule,
)

__all__ = [
    "VEHICLE_ID_FORMAT",
    "EstimatorMix",
    "FleetSim",
    "RunPlan",
    "SimPacket",
    "SimStats",
    "encode_packet",
    "encode_packets",
    "packetize",
    "publish_fleets",
    "record",
    "renamed_key",
    "replay",
    "shift_measurement",
    "vehicle_of_key",
]

log = logging.getLogger(__name__)

VEHICLE_ID_FORMAT = "sim-{:04d}"
TICK_NS = 100_000_000
#: Origin of the first simulated run (a field in the Netherlands) and the spacing of the others.
SIM_ORIGIN_DEG = (52.0, 5.6)
SIM_ORIGIN_SPACING_M = 250.0


def loop_period_ns(start_ns: int, end_ns: int) -> int:
    """Sensor time of one loop of a drive spanning ``start_ns … end_ns``: the span and a tick,
    rounded up to whole ticks, so that a looped vehicle's batches keep their phase like a
    vehicle streaming on (the server puts a vehicle's ticks on the end of its first IMU batch;
    a loop of a fractional tick would move every batch of the next loop off its ticks, and each
    tick would wait for one more batch)."""
    return -(-(end_ns - start_ns + TICK_NS) // TICK_NS) * TICK_NS


@dataclass(frozen=True, slots=True)
class SimPacket:
    """One packet of a simulated run: when it arrives (ns after the run start) and what it holds."""

    arrival_offset_ns: int
    stream: Stream
    measurements: tuple[Measurement, ...]
    #: the packet's ``until_ns`` (absolute, shifted with the stamps), None: not sent
    until_ns: int | None = None

    def encode(self, seq: int, shift_ns: int = 0, boot: int | None = None) -> bytes:
        """The packet on the wire as sequence number ``seq``, its stamps and ``until_ns`` moved
        by ``shift_ns`` (a later loop of the drive, another vehicle's phase), sent with the
        sender's ``boot`` id when given."""
        ms = self.measurements
        if shift_ns:
            ms = tuple(shift_measurement(m, shift_ns) for m in ms)
        until = None if self.until_ns is None else self.until_ns + shift_ns
        return encode_packet(self.stream, ms, seq, until, boot)


@dataclass(slots=True)
class SimStats:
    """What a publisher sent."""

    packets: Counter[str] = field(default_factory=Counter)
    payload_bytes: int = 0
    configs: int = 0
    loops: int = 0
    max_behind_ms: float = 0.0
    wall_s: float = 0.0
    #: sending rounds (``keep_lateness``): (perf_counter ns, ms late, packets)
    send_rounds: list[tuple[int, float, int]] = field(default_factory=list)
    #: packets by lateness (``ScheduleStats.late_packets``), updated as they are sent
    late_packets: dict[int, int] = field(default_factory=dict)

    @property
    def total_packets(self) -> int:
        return sum(self.packets.values())


def _stream_of(m: Measurement) -> Stream:
    if isinstance(m, GnssSample):
        return Stream.GNSS
    if isinstance(m, ImuBatch):
        return Stream.IMU
    return Stream.WHEELS


def packetize(
    sent: Sequence[tuple[int, Measurement, int | None]], start_ns: int
) -> list[SimPacket]:
    """Group ``(arrival_ns, measurement, until_ns)`` triples (arrival order) into wire packets.

    Wheel edges of both wheels arriving at the same time share one packet (its ``until_ns``
    the later of the two); empty batches (no samples) are dropped unless they carry an
    ``until_ns`` (a wheel heartbeat: encoded with no edges).
    """
    out: list[SimPacket] = []
    for arrival, m, until in sent:
        if not isinstance(m, GnssSample) and len(m.stamp_ns) == 0 and until is None:
            continue  # nothing measured and no window end to tell
        stream = _stream_of(m)
        last = out[-1] if out else None
        if (
            isinstance(m, WheelEdges)
            and last is not None
            and last.stream is Stream.WHEELS
            and last.arrival_offset_ns == arrival - start_ns
            and len(last.measurements) == 1
            and isinstance(last.measurements[0], WheelEdges)
            and last.measurements[0].wheel != m.wheel
        ):
            both = (*last.measurements, m)
            merged = until if last.until_ns is None or until is None else max(until, last.until_ns)
            out[-1] = SimPacket(last.arrival_offset_ns, stream, both, merged)
            continue
        out.append(SimPacket(arrival - start_ns, stream, (m,), until))
    return out


def shift_measurement(m: Measurement, dt_ns: int) -> Measurement:
    """The same measurement with every timestamp moved by ``dt_ns``."""
    if isinstance(m, GnssSample):
        return dataclasses.replace(m, stamp_ns=int(m.stamp_ns) + dt_ns)
    return dataclasses.replace(m, stamp_ns=m.stamp_ns + dt_ns)


def encode_packet(
    stream: Stream,
    measurements: tuple[Measurement, ...],
    seq: int,
    until_ns: int | None = None,
    boot: int | None = None,
) -> bytes:
    """Encode one packet's measurements (as :func:`packetize` grouped them); a wheels,
    odometer or sprockets packet without edges is a heartbeat (needs ``until_ns``); ``boot``:
    the sender's boot id (None: not sent)."""
    if not measurements and stream is Stream.WHEELS:
        return encode_wheel_edges([], seq, until_ns, boot=boot)
    if not measurements and stream is Stream.ODOMETER:
        return encode_odometer(OdometerEdges(np.zeros(0, np.int64)), seq, until_ns, boot=boot)
    if stream is Stream.SPROCKETS:
        sides = [m for m in measurements if isinstance(m, SprocketEdges)]
        return encode_sprockets(sides, seq, until_ns, boot=boot)
    first = measurements[0]
    if stream is Stream.GNSS and isinstance(first, GnssSample):
        return encode_gnss(first, seq, until_ns, boot=boot)
    if stream is Stream.IMU and isinstance(first, ImuBatch):
        return encode_imu(first, seq, until_ns, boot=boot)
    if isinstance(first, WheelSpeeds):
        return encode_wheel_speeds(first, seq, until_ns, boot=boot)
    if isinstance(first, SteeringAngles):
        return encode_steering(first, seq, until_ns, boot=boot)
    if isinstance(first, WheelSpeeds4):
        return encode_wheel_speeds4(first, seq, until_ns, boot=boot)
    if isinstance(first, OdometerEdges):
        return encode_odometer(first, seq, until_ns, boot=boot)
    edges = [m for m in measurements if isinstance(m, WheelEdges)]
    if len(edges) != len(measurements):
        raise ValueError(f"cannot encode {[type(m).__name__ for m in measurements]} on {stream}")
    return encode_wheel_edges(edges, seq, until_ns, boot=boot)


def encode_packets(
    packets: Sequence[SimPacket], boot: int | None = None
) -> list[tuple[str, bytes]]:
    """``(stream name, payload)`` of ``packets`` in order, each stream's ``seq`` from 0, sent
    with the boot id ``boot`` when given."""
    seq: Counter[str] = Counter()
    out = []
    for p in packets:
        name = p.stream.value
        out.append((name, p.encode(seq[name], boot=boot)))
        seq[name] += 1
    return out


def _never_sent(payload: bytes) -> None:
    """The publisher slot of a stream the vehicle's drive has no packet of."""
    raise AssertionError("a packet on a stream its drive does not hold")


def _publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )


@dataclass(slots=True)
class _Vehicle:
    vehicle_id: str
    packets: list[SimPacket]
    period_ns: int  # sensor-time length of one loop
    phase_ns: int
    shift_ns: int  # run stamps -> published stamps, first loop (anchored as publishing starts)
    config: VehicleConfig
    index: int = 0
    loop: int = 0
    seq: dict[Stream, int] = field(default_factory=lambda: dict.fromkeys(Stream, 0))


@dataclass(frozen=True, slots=True)
class RunPlan:
    """One distinct simulated run of a fleet: its scenario and the scenario parameters that
    differ from the defaults (``estimator.sim.SCENARIOS[scenario].defaults`` names them)."""

    scenario: str
    overrides: Mapping[str, float] = field(default_factory=dict)


class FleetSim:
    """Publishes ``n_vehicles`` simulated vehicles on ``session``.

    Parameters
    ----------
    session : zenoh.Session or sequence of zenoh.Session
        Client session(s) connected to the server's router; vehicle ``i`` publishes on
        ``session[i % len(session)]`` (several sessions load the router like separate vehicles).
    n_vehicles : int
    scenario : str
        An :func:`estimator.sim.scenario_names` entry.
    prefix : str
        Key prefix (``ZenohSettings.key_prefix``).
    seed : int
        Run ``k`` is simulated with ``seed + k``.
    rate : float
        Publish ``rate`` times faster than real time (stamps still advance with sensor time).
    loop : bool
        Start over (stamps continuing) when a run ends; otherwise stop after one run.
    distinct_runs : int
        How many different runs to simulate and share among the vehicles.
    first_index : int
        Number of the first vehicle id (``sim-0001`` by default).
    publish_config : bool
        Publish each vehicle's config on ``<prefix>/<id>/config`` before its data.
    clock_ns : callable
        UTC clock for the stamp shift (injectable for tests).
    estimator_mix : EstimatorMix, optional
        Which vehicles' configs name other estimators than their kind's defaults.
    plans : sequence of RunPlan, optional
        The distinct runs, each its own scenario and parameters (vehicle ``i`` drives run
        ``i % len(plans)``); given, they replace ``scenario`` and ``distinct_runs``.
    """

    def __init__(
        self,
        session: zenoh.Session | Sequence[zenoh.Session],
        n_vehicles: int,
        *,
        scenario: str = "field_work",
        prefix: str = "fleet",
        seed: int = 0,
        rate: float = 1.0,
        loop: bool = False,
        distinct_runs: int = 8,
        first_index: int = 1,
        publish_config: bool = True,
        clock_ns: Callable[[], int] = time.time_ns,
        estimator_mix: EstimatorMix | None = None,
        plans: Sequence[RunPlan] = (),
        **sim_overrides: object,
    ) -> None:
        if n_vehicles < 1 or rate <= 0 or distinct_runs < 1:
            raise ValueError("n_vehicles >= 1, rate > 0 and distinct_runs >= 1 are required")
        self._sessions = list(session) if isinstance(session, Sequence) else [session]
        if not self._sessions:
            raise ValueError("at least one session is needed")
        self._n = n_vehicles
        self._prefix = prefix
        self._seed = seed
        self._rate = rate
        self._loop = loop
        self._plans = list(plans) or [RunPlan(scenario)] * distinct_runs
        self._distinct = min(len(self._plans), n_vehicles)
        self._first = first_index
        self._publish_config = publish_config
        self._clock = clock_ns
        self._mix = estimator_mix
        self._overrides = sim_overrides
        self._stop = threading.Event()
        self._boot: int | None = None  # picked as each run starts (its vehicles send it)
        self._thread: threading.Thread | None = None
        self.stats = SimStats()

    @property
    def vehicle_ids(self) -> list[str]:
        return [VEHICLE_ID_FORMAT.format(self._first + i) for i in range(self._n)]

    def estimators_of(self, index: int) -> tuple[str, ...]:
        """The ``estimators`` vehicle ``index`` (0-based in this fleet) publishes in its config."""
        return () if self._mix is None else self._mix.names_for(self._first + index)

    @staticmethod
    def spread_origin(k: int) -> dict[str, float]:
        """Run ``k`` starts 250 m east of run ``k - 1`` (unless an origin is given), so the
        vehicles of a demo or load test do not drive on top of each other."""
        lat0, lon0 = SIM_ORIGIN_DEG
        return {
            "origin_lat_deg": lat0,
            "origin_lon_deg": lon0
            + k * SIM_ORIGIN_SPACING_M / (111_320.0 * math.cos(math.radians(lat0))),
        }

    def simulate_runs(self, start_ns: int) -> list[SimRun]:
        """The fleet's distinct runs, simulated from ``start_ns`` (vehicle ``i`` drives run
        ``i % len(runs)``), each at its own origin (:meth:`spread_origin`)."""
        from estimator.sim import simulate  # the simulator loads only when simulating

        return [
            simulate(
                plan.scenario,
                seed=self._seed + k,
                start_ns=start_ns,
                **{**self.spread_origin(k), **self._overrides, **plan.overrides},  # type: ignore[arg-type]
            )
            for k, plan in enumerate(self._plans[: self._distinct])
        ]

    def _build(self) -> list[_Vehicle]:
        """Simulate the distinct runs and lay the vehicles out; stamps are anchored later.

        ``shift_ns`` is left relative (run stamps -> phase); :meth:`run` adds the clock reading
        taken just before publishing starts, so simulating (≈0.4 s a run) adds no latency.
        """
        runs = self.simulate_runs(self._clock())
        packetized = [packetize(run.sent_in_arrival_order(), run.start_ns) for run in runs]
        vehicles = []
        for i, vid in enumerate(self.vehicle_ids):
            run = runs[i % self._distinct]
            packets = packetized[i % self._distinct]  # shared, read-only
            period = loop_period_ns(run.start_ns, run.end_ns)
            phase = (i * TICK_NS) // self._n
            # the vehicle registers its simulated sensors' noise figures, as an integrator would
            config = dataclasses.replace(
                run.config, noise=run.sensor_noise, estimators=self.estimators_of(i)
            )
            vehicles.append(_Vehicle(vid, packets, period, phase, phase - run.start_ns, config))
        return vehicles

    def _lay_out(
        self, drives: Sequence[tuple[int, list[SimPacket], VehicleConfig]]
    ) -> list[_Vehicle]:
        """The vehicles over distinct drives ``(start_ns, packets, config)`` (vehicle ``i``
        drives ``i % len(drives)``, looping after its last packet), spread over the tick, each
        with its config naming the estimators :meth:`estimators_of` gives it."""
        vehicles = []
        for i, vid in enumerate(self.vehicle_ids):
            start_ns, packets, config = drives[i % len(drives)]
            period = loop_period_ns(start_ns, start_ns + packets[-1].arrival_offset_ns)
            phase = (i * TICK_NS) // self._n
            config = dataclasses.replace(config, estimators=self.estimators_of(i))
            vehicles.append(_Vehicle(vid, packets, period, phase, phase - start_ns, config))
        return vehicles

    def run(self, duration_s: float | None = None) -> SimStats:
        """Publish until the runs end (no loop), ``duration_s`` passes, or :meth:`stop`.

        A session closed after :meth:`stop` (its caller's wait for this thread ran out while
        simulating) ends the run like the stop itself.
        """
        try:
            return publish_fleets([self], duration_s, stop=self._stop, stats=self.stats)
        except zenoh.ZError:
            if self._stop.is_set():
                return self.stats
            raise

    def _declare(
        self, drive_of: dict[int, int], drives: list[EncodedDrive], stop: threading.Event
    ) -> tuple[list[_Vehicle], list[ScheduledVehicle], list[zenoh.Publisher]]:
        """Simulate, encode each distinct drive once, declare publishers, publish configs.

        The vehicles' stamp shifts are still relative (the clock reading is added by
        :func:`~server.tooling.fleet_schedule.publish_schedule` as publishing starts).
        Declaring ends early once ``stop`` is set: a caller stops the fleet before it closes
        the sessions, and simulating may outlast its wait for this thread.
        """
        vehicles = self._build()
        # a run starts every vehicle's sequence numbers at 0: a new boot id tells the server
        # (a second run on the same server is not a replay of the first)
        self._boot = secrets.randbits(63)
        scheduled: list[ScheduledVehicle] = []
        declared: list[zenoh.Publisher] = []
        for i, v in enumerate(vehicles):
            if stop.is_set():
                break
            d = drive_of.get(id(v.packets))
            if d is None:
                d = drive_of[id(v.packets)] = len(drives)
                drives.append(EncodedDrive(v.packets, v.period_ns, self._boot))
            session = self._sessions[i % len(self._sessions)]
            used = {p.stream for p in v.packets}  # a tractor sends no steering, ...
            pubs = {s: _publisher(session, sensor_key(self._prefix, v.vehicle_id, s)) for s in used}
            declared.extend(pubs.values())
            puts = tuple(pubs[s].put if s in pubs else _never_sent for s in STREAMS)
            scheduled.append(ScheduledVehicle(d, v.phase_ns, v.shift_ns, puts))
            if self._publish_config:
                session.put(
                    config_key(self._prefix, v.vehicle_id),
                    encode_config(v.config),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
                self.stats.configs += 1
        return vehicles, scheduled, declared

    def start(self, duration_s: float | None = None) -> None:
        """Run in a background thread."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._thread = threading.Thread(
            target=self.run, args=(duration_s,), name="slipfleet-fleet-sim", daemon=True
        )
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop publishing and join the background thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)


def publish_fleets(
    sims: Sequence[FleetSim],
    duration_s: float | None = None,
    *,
    stop: threading.Event | None = None,
    stats: SimStats | None = None,
    keep_lateness: bool = False,
    ready: threading.Event | None = None,
    go: threading.Event | None = None,
) -> SimStats:
    """Publish several :class:`FleetSim` fleets from one thread, on one merged schedule.

    They must share ``rate`` and ``loop``. Every distinct drive is encoded once
    (:class:`server.tooling.fleet_schedule.EncodedDrive`) and payloads are built per 100 ms window
    in bulk; the sending loop costs one ``put`` per packet. ``stats`` (a fresh :class:`SimStats`
    by default; every fleet's ``stats`` becomes this one) is updated after every sending
    round, so another thread can follow the progress; with ``keep_lateness`` every round is
    kept in ``stats.send_rounds``. ``ready`` is set once everything is simulated, encoded and
    declared; publishing then waits for ``go`` (if given), so several processes
    can start together.
    """
    rate, loop, clock = _shared_timing(sims)
    stats = stats if stats is not None else SimStats()
    for s in STREAMS:  # every key present before another thread starts summing the counts
        stats.packets.setdefault(s.value, 0)
    stop = stop if stop is not None else sims[0]._stop
    drives, prepared = _declare_fleets(sims, stats, stop)
    if ready is not None:
        ready.set()
    if go is not None:
        go.wait()
    if stop.is_set():  # stopped while simulating: the sessions may be closed already
        _undeclare(prepared)
        return stats
    # the stamps' time base ("now") is read by publish_schedule once its set-up is done
    scheduled = [v for _, vehicles, _ in prepared for v in vehicles]
    progress = functools.partial(_copy_progress, stats)
    wall0 = time.perf_counter_ns()
    try:
        done = publish_schedule(
            drives,
            scheduled,
            rate=rate,
            loop=loop,
            duration_s=duration_s,
            stop=stop,
            on_round=progress,
            keep_lateness=keep_lateness,
            stamp_clock_ns=clock,
        )
        progress(done)
        stats.loops = done.loops
        if done.rounds is not None:
            stats.send_rounds = done.rounds
    finally:
        _undeclare(prepared)
        stats.wall_s = (time.perf_counter_ns() - wall0) / 1e9
    return stats


def _declare_fleets(
    sims: Sequence[FleetSim], stats: SimStats, stop: threading.Event
) -> tuple[
    list[EncodedDrive], list[tuple[list[_Vehicle], list[ScheduledVehicle], list[zenoh.Publisher]]]
]:
    """Simulate and declare every fleet (each distinct drive encoded once), each counting in
    ``stats``: the drives and each fleet's vehicles and publishers."""
    drives: list[EncodedDrive] = []
    drive_of: dict[int, int] = {}
    prepared = []
    for sim in sims:
        sim.stats = stats
        prepared.append(sim._declare(drive_of, drives, stop))
    return drives, prepared


def _shared_timing(sims: Sequence[FleetSim]) -> tuple[float, bool, Callable[[], int]]:
    """The ``(rate, loop, clock)`` every fleet shares; ValueError when none or they differ."""
    if not sims:
        raise ValueError("no fleets to publish")
    rate, loop, clock = sims[0]._rate, sims[0]._loop, sims[0]._clock
    if any(s._rate != rate or s._loop != loop or s._clock is not clock for s in sims):
        raise ValueError("fleets published together must share rate, loop and clock")
    return rate, loop, clock


def _copy_progress(stats: SimStats, s: ScheduleStats) -> None:
    """Copy a schedule's counts so far into ``stats`` (packets by stream name)."""
    for stream, n in zip(STREAMS, s.packets, strict=True):
        stats.packets[stream.value] = n
    stats.payload_bytes = s.payload_bytes
    stats.max_behind_ms = s.max_behind_ms
    stats.late_packets = s.late_packets


def _undeclare(prepared: Sequence[tuple[object, object, list[zenoh.Publisher]]]) -> None:
    """Undeclare every publisher; one whose session is closed already went with it."""
    for _, _, declared in prepared:
        for pub in declared:
            with contextlib.suppress(zenoh.ZError):
                pub.undeclare()


def _prefix_of(key: str) -> str:
    parts = key.split("/")
    return "/".join(parts[:-3]) if parts[-2] == "sensors" else "/".join(parts[:-2])


def _is_vehicle_traffic(key: str) -> bool:
    parts = key.split("/")
    return len(parts) >= 3 and (parts[-2] == "sensors" or parts[-1] == "config")


def _vehicle_index(parts: Sequence[str]) -> int:
    return -3 if parts[-2] == "sensors" else -2


def vehicle_of_key(key: str) -> str:
    """The vehicle id of ``key`` (a sensor or config key of the protocol)."""
    parts = key.split("/")
    return parts[_vehicle_index(parts)]


def renamed_key(key: str, vehicle_id: str) -> str:
    """``key`` (a sensor or config key of the protocol) with its vehicle id replaced."""
    parts = key.split("/")
    parts[_vehicle_index(parts)] = vehicle_id
    return "/".join(parts)


def replay(
    path: str | Path,
    session: zenoh.Session,
    rate: float = 1.0,
    *,
    shift_to_now: bool = True,
    shift_ns: int | None = None,
    vehicle_as: str | None = None,
    stop: threading.Event | None = None,
    clock_ns: Callable[[], int] = time.time_ns,
) -> SimStats:
    """Publish a recording with its original pacing (``rate`` times faster).

    With ``shift_to_now`` (default) sensor packets are decoded, their stamps moved so the first
    record lands *now*, and re-encoded: the server treats them as fresh data; ``shift_ns`` moves
    them by that much instead. Without a shift the payloads go out byte for byte (the server's
    store ignores rows it already has). Packets that do not decode are published unchanged.
    ``vehicle_as`` publishes every record under that vehicle id (a recording of one vehicle
    replayed beside the vehicle itself).
    """
    if rate <= 0:
        raise ValueError("rate must be > 0")
    stats = SimStats()
    pubs: dict[str, zenoh.Publisher] = {}
    wall0 = time.perf_counter_ns()
    first_stamp: int | None = None
    shift = 0
    try:
        for rec in read_recording(path):
            if stop is not None and stop.is_set():
                break
            if first_stamp is None:
                first_stamp = rec.stamp_ns
                to_now = clock_ns() - first_stamp if shift_to_now else 0
                shift = to_now if shift_ns is None else shift_ns
            _wait_due(int((rec.stamp_ns - first_stamp) / rate), wall0, stop)
            key = rec.key if vehicle_as is None else renamed_key(rec.key, vehicle_as)
            stream, payload = _replayed(key, rec.payload, shift)
            pub = pubs.get(key)
            if pub is None:
                pub = pubs[key] = _publisher(session, key)
            pub.put(payload)
            if stream is None:
                stats.configs += 1
            else:
                stats.packets[stream.value] += 1
            stats.payload_bytes += len(payload)
    finally:
        for pub in pubs.values():
            pub.undeclare()
        stats.wall_s = (time.perf_counter_ns() - wall0) / 1e9
    return stats


def _wait_due(due_ns: int, wall0_ns: int, stop: threading.Event | None) -> None:
    """Sleep until ``due_ns`` after ``wall0_ns`` (``perf_counter_ns``), or until ``stop``."""
    while (ahead := due_ns - (time.perf_counter_ns() - wall0_ns)) > 0:
        if stop is not None and stop.wait(ahead / 1e9):
            break
        if stop is None:
            time.sleep(ahead / 1e9)


def _replayed(key: str, payload: bytes, shift_ns: int) -> tuple[Stream | None, bytes]:
    """A recorded record's stream (None: not a sensor key) and payload, re-encoded with its
    stamps moved by ``shift_ns`` when it is a sensor packet that decodes."""
    stream: Stream | None = None
    try:
        _, stream = parse_key(key, _prefix_of(key))
    except (ValueError, IndexError):
        stream = None
    if shift_ns != 0 and stream is not None:
        try:
            pkt = decode(key, payload, prefix=_prefix_of(key), max_payload_bytes=1 << 30)
            again = SimPacket(0, pkt.stream, pkt.measurements, pkt.until_ns)
            payload = again.encode(pkt.seq, shift_ns, pkt.boot)  # as recorded
        except DecodeError:
            pass  # replay what was recorded: the server will count the refusal
    return stream, payload


def record(
    path: str | Path,
    session: zenoh.Session,
    key_expr: str = "fleet/**",
    *,
    duration_s: float | None = None,
    stop: threading.Event | None = None,
    max_records: int | None = None,
    clock_ns: Callable[[], int] = time.time_ns,
    on_ready: Callable[[], None] | None = None,
) -> int:
    """Write every sample ``session`` receives on ``key_expr`` to ``path``; return the count.

    Only what a server takes in is kept: sensor packets and configs (``<prefix>/<id>/sensors/…``,
    ``<prefix>/<id>/config``), not what servers publish back (alerts, status). Stops after
    ``duration_s`` (counted from when the subscriber is declared) or when ``stop`` is set
    (keeping what had already arrived), or after ``max_records``. ``on_ready`` is called once
    the subscriber is declared: what is published from then on is recorded.
    """
    sub = session.declare_subscriber(key_expr, zenoh.handlers.FifoChannel(65_536))
    if on_ready is not None:
        on_ready()
    end = None if duration_s is None else time.monotonic() + duration_s
    handler = sub.handler
    try:
        with open(path, "wb") as fh:
            writer = RecordingWriter(fh)
            stopping = False
            while max_records is None or writer.records < max_records:
                if not stopping:
                    stopping = (stop is not None and stop.is_set()) or (
                        end is not None and time.monotonic() >= end
                    )
                sample = handler.try_recv()
                if sample is None:
                    if stopping:
                        break  # stopped and drained what had already arrived
                    time.sleep(0.002)
                    continue
                key = str(sample.key_expr)
                if _is_vehicle_traffic(key):
                    writer.write(key, clock_ns(), sample.payload.to_bytes())
            return writer.records
    finally:
        sub.undeclare()
