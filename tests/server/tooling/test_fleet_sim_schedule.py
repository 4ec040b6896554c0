"""The encoded fleet schedule (load generator): byte for byte the per-packet encoding, due times
and sequence numbers per stream, every packet published once."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

import msgpack
import numpy as np
import pytest

from estimator.sim import simulate
from server.protocol import Stream, decode, sensor_key
from server.tooling import fleet_schedule
from server.tooling.fleet_schedule import (
    MIN_WAKE_NS,
    STREAMS,
    EncodedDrive,
    ScheduledVehicle,
    _Fleet,
    _insert_seq,
    lateness_quantiles,
    publish_schedule,
    render,
)
from server.tooling.fleet_sim import TICK_NS, SimPacket, loop_period_ns, packetize

T0 = 1_763_700_000 * 10**9
SPAN = 100_000_000


@pytest.fixture(scope="module")
def drive() -> tuple[list[SimPacket], EncodedDrive]:
    run = simulate("hard_braking", seed=3, start_ns=T0)  # 34 s: loops are cheap to cover
    packets = packetize(run.sent_in_arrival_order(), run.start_ns)
    return packets, EncodedDrive(packets, run.end_ns - run.start_ns + TICK_NS)


class _Sink:
    """Stands in for the publishers: ``calls[(vehicle, stream)]`` are the payloads put."""

    def __init__(self) -> None:
        self.calls: dict[tuple[int, int], list[bytes]] = defaultdict(list)

    def put(self, v: int, s: int) -> object:
        return lambda payload: self.calls[(v, s)].append(payload)


def _vehicles(sink: _Sink, phases: list[int]) -> list[ScheduledVehicle]:
    return [
        ScheduledVehicle(
            0, ph, 1_000_000_007 * (i + 1), tuple(sink.put(i, s) for s in range(len(STREAMS)))
        )
        for i, ph in enumerate(phases)
    ]


def _render_all(fleet: _Fleet, until_ns: int) -> list[tuple[int, object, bytes, int]]:
    out = []
    for t in range(0, until_ns, SPAN):
        w = render(fleet, t, t + SPAN, loop=True)
        assert w.due_ns == sorted(w.due_ns)
        assert all(t <= d < t + SPAN for d in w.due_ns)
        out += zip(w.due_ns, w.calls, w.payloads, w.stream.tolist(), strict=True)
    return out


def test_rendered_packets_equal_the_per_packet_encoding_over_loops(
    drive: tuple[list[SimPacket], EncodedDrive],
) -> None:
    packets, enc = drive
    sink = _Sink()
    vehicles = _vehicles(sink, [0, 3_000_000, 66_000_000])
    fleet = _Fleet([enc], vehicles)
    rendered = _render_all(fleet, 3 * enc.period_ns)  # three loops: seq passes 127 and 255
    by_stream = {s: [p for p in packets if p.stream is STREAMS[s]] for s in range(3)}
    due_of: dict[tuple[int, int], list[int]] = defaultdict(list)
    for due, call, payload, s in rendered:
        call(payload)  # type: ignore[operator]
        v = next(i for i, veh in enumerate(vehicles) if veh.publishers[s] is call)
        due_of[(v, s)].append(due)
    assert max(len(x) for x in sink.calls.values()) > 256
    checked = 0
    for (v, s), payloads in sink.calls.items():
        mine = by_stream[s]
        for seq, payload in enumerate(payloads):
            loop, i = divmod(seq, len(mine))
            shift = vehicles[v].shift_ns + loop * enc.period_ns
            assert mine[i].until_ns is not None  # the simulator states how far each covers
            assert payload == mine[i].encode(seq, shift), (v, s, seq)
            due = mine[i].arrival_offset_ns + vehicles[v].phase_ns + loop * enc.period_ns
            assert due_of[(v, s)][seq] == due
            checked += 1
    assert checked == len(rendered) > 3 * 3 * len(packets) * 0.99
    # and the server's decoder takes them: stamps, stream and seq where they belong
    payload = sink.calls[(1, 1)][300]
    got = decode(sensor_key("fleet", "sim-0002", STREAMS[1]), payload)
    assert got.seq == 300 and got.stream is STREAMS[1]


@pytest.mark.parametrize(
    "seq", [0, 1, 127, 128, 255, 256, 65_535, 65_536, 2**32 - 1, 2**32, 2**63 - 1]
)
def test_sequence_numbers_are_packed_as_msgpack_packs_them(seq: int) -> None:
    template = bytearray(b"\xaa\x00\xbb" + b"\xcc\x00\xdd")  # two packets, seq byte in the middle
    data, bounds = _insert_seq(
        np.frombuffer(template, np.uint8).copy(),
        np.array([0, 3, 6]),
        np.array([1, 4]),
        np.array([5, seq], np.int64),
    )
    blob = data.tobytes()
    assert blob[bounds[0] : bounds[1]] == b"\xaa" + msgpack.packb(5) + b"\xbb"
    assert blob[bounds[1] : bounds[2]] == b"\xcc" + msgpack.packb(seq) + b"\xdd"


def test_publishing_once_through_puts_every_packet_once_in_order(
    drive: tuple[list[SimPacket], EncodedDrive],
) -> None:
    packets, enc = drive
    sink = _Sink()
    n = 20
    vehicles = _vehicles(sink, [(i * TICK_NS) // n for i in range(n)])
    rounds: list[int] = []
    stats = publish_schedule(
        [enc], vehicles, rate=400.0, loop=False, on_round=lambda s: rounds.append(s.total)
    )
    assert stats.total == n * len(packets) == sum(len(x) for x in sink.calls.values())
    assert stats.packets == [n * sum(p.stream is s for p in packets) for s in STREAMS]
    assert stats.payload_bytes == sum(len(b) for x in sink.calls.values() for b in x)
    assert rounds == sorted(rounds) and rounds[-1] == stats.total
    assert sum(stats.late_packets.values()) == stats.total  # every packet by its lateness
    assert all(ms >= 0 for ms in stats.late_packets)
    for (_, s), payloads in sink.calls.items():
        seqs = [decode(sensor_key("fleet", "x", STREAMS[s]), p).seq for p in payloads]
        assert seqs == list(range(len(seqs)))


class _VirtualTime:
    """Stands in for the ``time`` module of :mod:`server.tooling.fleet_schedule`: its clock
    moves only when the publisher sleeps, so the rounds follow from the publisher's own logic,
    not from how busy the host is (sending takes no time here)."""

    def __init__(self) -> None:
        self.now_ns = 0
        self.sleeps_ns: list[int] = []

    def perf_counter_ns(self) -> int:
        return self.now_ns

    def sleep(self, seconds: float) -> None:
        self.sleeps_ns.append(round(seconds * 1e9))
        self.now_ns += self.sleeps_ns[-1]


class _VirtualStop(threading.Event):
    """A stop event whose ``wait`` sleeps on a :class:`_VirtualTime` (never set)."""

    def __init__(self, clock: _VirtualTime) -> None:
        super().__init__()
        self.clock = clock

    def wait(self, timeout: float | None = None) -> bool:
        assert timeout is not None
        self.clock.sleep(timeout)
        return False


def test_packets_go_out_in_rounds_one_per_wake_up_of_at_least_the_minimum_sleep(
    drive: tuple[list[SimPacket], EncodedDrive], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Thousands of packets a second cost a wake-up every :data:`MIN_WAKE_NS`, not one each:
    every round follows one sleep of at least that, and sends every packet due by then."""
    packets, enc = drive
    clock = _VirtualTime()
    monkeypatch.setattr(fleet_schedule, "time", clock)
    sink = _Sink()
    n = 20
    vehicles = _vehicles(sink, [(i * TICK_NS) // n for i in range(n)])
    rounds: list[int] = []
    rate = 400.0
    stats = publish_schedule(
        [enc],
        vehicles,
        rate=rate,
        loop=False,
        stop=_VirtualStop(clock),
        on_round=lambda s: rounds.append(s.total),
    )
    assert stats.total == n * len(packets) == sum(len(x) for x in sink.calls.values())
    # a round per wake-up, and one at the start for the packets due at once
    assert len(rounds) == len(clock.sleeps_ns) + 1
    assert min(clock.sleeps_ns) >= MIN_WAKE_NS
    last_due_ns = max(p.arrival_offset_ns for p in packets) + max(v.phase_ns for v in vehicles)
    assert len(rounds) <= last_due_ns / rate / MIN_WAKE_NS + 2  # ≈ 22 rounds for 20,440 packets
    assert max(stats.late_packets) <= MIN_WAKE_NS / 1e6  # none waits for a second wake-up


def test_publishing_stops_on_request_and_after_the_duration(
    drive: tuple[list[SimPacket], EncodedDrive],
) -> None:
    _, enc = drive
    sink = _Sink()
    stats = publish_schedule([enc], _vehicles(sink, [0, 50_000_000]), loop=True, duration_s=0.5)
    # 0.5 s of real time: ≈ 30 packets per vehicle-second
    assert 10 <= stats.total <= 45
    stop = threading.Event()
    stop.set()
    assert publish_schedule([enc], _vehicles(_Sink(), [0]), loop=True, stop=stop).total == 0


def test_rate_and_lateness_of_a_real_time_schedule(
    drive: tuple[list[SimPacket], EncodedDrive],
) -> None:
    _, enc = drive
    sink = _Sink()
    n = 200
    phases = [(i * TICK_NS) // n for i in range(n)]
    stats = publish_schedule(
        [enc], _vehicles(sink, phases), loop=True, duration_s=1.5, keep_lateness=True
    )
    due = sum(int(np.searchsorted(enc.arrival_ns, 1_500_000_000 - ph, "right")) for ph in phases)
    assert 0.9 * due <= stats.total <= due
    assert stats.rounds is not None
    late = sorted(ms for _, ms, _ in stats.rounds)
    assert late[len(late) // 2] < 20.0  # half the rounds within 20 ms of due (busy CI hosts)


def test_a_looped_drive_keeps_its_imu_batches_on_the_tick_grid() -> None:
    run = simulate("figure_eight", seed=1, start_ns=T0)  # 68.374 s: a span off the 100 ms grid
    assert (run.end_ns - run.start_ns + TICK_NS) % TICK_NS != 0
    period = loop_period_ns(run.start_ns, run.end_ns)
    assert period % TICK_NS == 0
    assert run.end_ns - run.start_ns + TICK_NS <= period < run.end_ns - run.start_ns + 2 * TICK_NS
    packets = packetize(run.sent_in_arrival_order(), run.start_ns)
    sink = _Sink()
    vehicles = _vehicles(sink, [0])
    fleet = _Fleet([EncodedDrive(packets, period)], vehicles)
    for _, call, payload, _ in _render_all(fleet, 2 * period):
        call(payload)  # type: ignore[operator]
    calls = sink.calls[(0, STREAMS.index(Stream.IMU))]
    imu = [decode(sensor_key("fleet", "sim-0001", Stream.IMU), p) for p in calls]
    per_loop = len([p for p in packets if p.stream is Stream.IMU])
    assert len(imu) == 2 * per_loop
    # the second loop's batches end where the first loop's do, modulo the tick: the server's
    # ticks (put on the end of a vehicle's first IMU batch) stay on every batch end
    first = {p.last_stamp_ns % TICK_NS for p in imu[:per_loop]}
    second = {p.last_stamp_ns % TICK_NS for p in imu[per_loop:]}
    assert second == first


class _StampClock:
    """A stamp clock that remembers its readings (the wall clock, or a fixed value)."""

    def __init__(self, fixed_ns: int | None = None) -> None:
        self.fixed_ns = fixed_ns
        self.readings: list[int] = []

    def __call__(self) -> int:
        self.readings.append(time.time_ns() if self.fixed_ns is None else self.fixed_ns)
        return self.readings[-1]


def test_a_stamp_clock_is_read_once_and_anchors_every_stamp(
    drive: tuple[list[SimPacket], EncodedDrive],
) -> None:
    packets, enc = drive
    sink = _Sink()
    vehicles = _vehicles(sink, [0, 40_000_000])  # shifts relative to the clock's reading
    clock = _StampClock(fixed_ns=T0 + 7 * 10**9)
    publish_schedule([enc], vehicles, rate=400.0, loop=False, stamp_clock_ns=clock)
    assert clock.readings == [T0 + 7 * 10**9]
    for (v, s), payloads in sink.calls.items():
        mine = [p for p in packets if p.stream is STREAMS[s]]
        shift = clock.readings[0] + vehicles[v].shift_ns
        assert payloads == [p.encode(seq, shift) for seq, p in enumerate(mine)]


def test_packets_leave_when_their_stamps_say_they_were_sent(
    drive: tuple[list[SimPacket], EncodedDrive],
) -> None:
    """The load test's latency runs from the stamps: a packet must not go out later than the
    simulated vehicle would send it (its batch complete), by more than the schedule's own
    lateness, however long the fleet's set-up took before the first packet."""
    packets, enc = drive
    n = 300
    phases = [(i * TICK_NS) // n for i in range(n)]
    sent: dict[tuple[int, int], list[int]] = defaultdict(list)

    def put(v: int, s: int) -> object:
        return lambda payload: sent[(v, s)].append(time.time_ns())

    # the same drive as 60 drives: the fleet's arrays take tens of ms to build, as a load
    # test's several scenarios and runs do
    copies = 60
    vehicles = [
        ScheduledVehicle(i % copies, ph, ph - T0, tuple(put(i, s) for s in range(len(STREAMS))))
        for i, ph in enumerate(phases)  # stamps: T0 -> ph
    ]
    clock = _StampClock()
    publish_schedule([enc] * copies, vehicles, loop=True, duration_s=1.0, stamp_clock_ns=clock)
    (anchor_ns,) = clock.readings
    by_stream = {s: [p for p in packets if p.stream is STREAMS[s]] for s in range(3)}
    late_ms = [
        (at - (anchor_ns + phases[v] + by_stream[s][seq].arrival_offset_ns)) / 1e6
        for (v, s), times in sent.items()
        for seq, at in enumerate(times)
    ]
    assert len(late_ms) > 0.8 * 30 * n  # ~30 packets a vehicle-second
    assert min(late_ms) >= 0.0  # never before the vehicle has it
    late_ms.sort()
    assert late_ms[len(late_ms) // 2] < 20.0  # as the rounds' own lateness (busy CI hosts)


def test_lateness_quantiles_count_packets_by_whole_ms() -> None:
    late = {0: 50, 3: 40, 20: 9, 250: 1}  # 100 packets
    assert lateness_quantiles(late, (0.5, 0.9, 0.99, 1.0)) == [0, 3, 20, 250]
    assert lateness_quantiles({}, (0.5, 1.0)) == [None, None]
    assert lateness_quantiles({7: 0}, (0.5,)) == [None]
