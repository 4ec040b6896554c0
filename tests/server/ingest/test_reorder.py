"""Reorder buffer: in-order release, late packets, duplicates, sequence gaps, idle release."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from estimator.types import (
    GnssSample,
    ImuBatch,
    SprocketEdges,
    SteeringAngles,
    TrackSide,
    Wheel,
    WheelEdges,
)
from server.ingest.reorder import (
    SEQ_WINDOW,
    WATERMARK_START_NS,
    ReorderBuffer,
    SeqTracker,
    StreamGap,
    Verdict,
)
from server.protocol import Packet, Stream

MS = 1_000_000
T0 = 1_763_700_000 * 10**9


def imu_packet(seq: int, first_ms: int, n: int = 10, vid: str = "v1") -> Packet:
    t = T0 + (first_ms + np.arange(n)) * MS
    m = ImuBatch(t, np.zeros((n, 3)), np.zeros((n, 3)))
    return Packet(vid, Stream.IMU, seq, 1, (m,), int(t[0]), int(t[-1]))


def wheels_packet(seq: int, first_ms: int) -> Packet:
    t = T0 + (first_ms + np.arange(0, 97, 8)) * MS
    return Packet("v1", Stream.WHEELS, seq, 1, (WheelEdges(Wheel.LEFT, t),), int(t[0]), int(t[-1]))


def gnss_packet(seq: int, at_ms: int) -> Packet:
    t = T0 + at_ms * MS
    g = GnssSample(t, (0.0, 1.0, 0.0), 0.0, 0.0, 0.0, 48.0, 11.0, 500.0)
    return Packet("v1", Stream.GNSS, seq, 1, (g,), t, t)


def _wheel(buf: ReorderBuffer) -> list[tuple[int, int | None, Packet | None]]:
    """``(after_ns, until_ns, before)`` of the gaps taken, every one of the wheels."""
    gaps = buf.take_gaps()
    assert all(g.stream is Stream.WHEELS for g in gaps)
    return [(g.after_ns, g.until_ns, g.before) for g in gaps]


def test_releases_in_first_stamp_order_after_lateness() -> None:
    buf = ReorderBuffer(lateness_ns=50 * MS)
    now = 0
    # IMU 10 ms batches arriving out of order, GNSS in between
    for p in [imu_packet(1, 10), imu_packet(0, 0), gnss_packet(0, 5), imu_packet(3, 30)]:
        assert buf.offer(p, now).verdict is Verdict.ACCEPTED
    # newest = 39 ms -> horizon = -11 ms: nothing yet
    out, released = buf.release(now)
    assert out == [] and released is not None and released == T0 - 11 * MS
    buf.offer(imu_packet(2, 20), now)
    buf.offer(imu_packet(9, 90), now)  # newest 99 -> horizon 49 ms
    out, released = buf.release(now)
    assert [(p.stream, p.seq) for p in out] == [
        (Stream.IMU, 0),
        (Stream.GNSS, 0),
        (Stream.IMU, 1),
        (Stream.IMU, 2),
        (Stream.IMU, 3),
    ]
    assert released == T0 + 49 * MS
    assert buf.pending == 1


def test_late_packet_is_refused_not_fed() -> None:
    buf = ReorderBuffer(lateness_ns=20 * MS)
    buf.offer(imu_packet(0, 0), 0)
    buf.offer(imu_packet(2, 100), 0)
    out, _ = buf.release(0)  # horizon 89 ms
    assert [p.seq for p in out] == [0]
    offer = buf.offer(imu_packet(1, 50), 0)  # older than the released horizon
    assert offer.verdict is Verdict.LATE
    assert offer.lost_delta == -1  # the gap it left is filled, it is late rather than lost
    assert buf.pending == 1


def test_duplicates_by_sequence_number() -> None:
    buf = ReorderBuffer(lateness_ns=10 * MS)
    assert buf.offer(imu_packet(5, 0), 0).verdict is Verdict.ACCEPTED
    assert buf.offer(imu_packet(5, 0), 0).verdict is Verdict.DUPLICATE
    # same seq on another stream is not a duplicate
    assert buf.offer(gnss_packet(5, 3), 0).verdict is Verdict.ACCEPTED
    assert buf.pending == 2


def test_gaps_count_lost_and_refill() -> None:
    buf = ReorderBuffer(lateness_ns=1000 * MS)
    assert buf.offer(imu_packet(0, 0), 0).lost_delta == 0
    assert buf.offer(imu_packet(4, 40), 0).lost_delta == 3
    assert buf.offer(imu_packet(2, 20), 0).lost_delta == -1
    assert buf.offer(imu_packet(2, 20), 0).verdict is Verdict.DUPLICATE


def test_idle_vehicle_releases_tail() -> None:
    buf = ReorderBuffer(lateness_ns=100 * MS, idle_ns=300 * MS)
    buf.offer(imu_packet(0, 0), now_ns=0)
    out, _ = buf.release(now_ns=10 * MS)
    assert out == [] and not buf.drained
    out, released = buf.release(now_ns=300 * MS)
    assert [p.seq for p in out] == [0] and released == T0 + 9 * MS
    assert buf.drained


def test_flush_releases_everything() -> None:
    buf = ReorderBuffer(lateness_ns=10_000 * MS)
    for i in range(5):
        buf.offer(imu_packet(i, 10 * (4 - i)), 0)
    out, released = buf.release(0, flush=True)
    assert [p.seq for p in out] == [4, 3, 2, 1, 0]
    assert released == T0 + 49 * MS


def test_zero_lateness_releases_immediately() -> None:
    buf = ReorderBuffer(lateness_ns=0)
    buf.offer(imu_packet(0, 0), 0)
    out, _ = buf.release(0)
    assert len(out) == 1


def test_seq_restart_after_reboot() -> None:
    tracker = SeqTracker()
    tracker.observe(SEQ_WINDOW * 3)
    dup, lost, restarted = tracker.observe(0)
    assert (dup, lost, restarted) == (False, 0, True)
    assert tracker.observe(1) == (False, 0, False)


def test_negative_lateness_refused() -> None:
    with pytest.raises(ValueError):
        ReorderBuffer(-1)


@settings(max_examples=80, deadline=None)
@given(
    order=st.permutations(list(range(30))),
    lateness_ms=st.integers(0, 200),
    dup_every=st.integers(2, 7),
)
def test_property_released_in_order_and_accounted(
    order: list[int], lateness_ms: int, dup_every: int
) -> None:
    """Whatever the arrival order: released stamps never go back, and every packet is accounted."""
    buf = ReorderBuffer(lateness_ns=lateness_ms * MS)
    released: list[Packet] = []
    counts = {v: 0 for v in Verdict}
    lost = 0
    offered = 0
    for k, i in enumerate(order):
        for _ in range(2 if k % dup_every == 0 else 1):
            offer = buf.offer(imu_packet(i, 10 * i), now_ns=k)
            counts[offer.verdict] += 1
            lost += offer.lost_delta
            offered += 1
        out, _ = buf.release(now_ns=k)
        released.extend(out)
    out, _ = buf.release(now_ns=len(order), flush=True)
    released.extend(out)
    stamps = [p.first_stamp_ns for p in released]
    assert stamps == sorted(stamps)
    assert len(released) == counts[Verdict.ACCEPTED]
    assert offered == sum(counts.values())
    # every sequence number arrived once at least: nothing is lost in the end
    assert lost == 0
    assert counts[Verdict.ACCEPTED] + counts[Verdict.LATE] == 30


@settings(max_examples=100, deadline=None)
@given(
    jitter_ms=st.lists(st.integers(0, 400), min_size=30, max_size=30),
    lateness_ms=st.integers(0, 300),
    watermarks=st.booleans(),
)
def test_property_three_streams_never_feed_behind_an_advance(
    jitter_ms: list[int], lateness_ms: int, watermarks: bool
) -> None:
    """Packets of three streams with random delays: whatever is accepted later starts after the
    time already released (so advancing estimators to it was safe), every packet is accounted,
    and a packet that arrives within the lateness of the newest data is never late (with
    watermarks: unless it is the first of a stream that started after the start-up window,
    which no watermark could wait for)."""
    packets = []
    for k in range(10):
        packets.append((k, imu_packet(k, 100 * k)))  # [100k, 100k + 9] ms
        packets.append((k, gnss_packet(k, 100 * k + 50)))
        packets.append((k, wheels_packet(k, 100 * k + 3)))  # edges in [100k + 3, 100k + 99]
    buf = ReorderBuffer(lateness_ns=lateness_ms * MS, idle_ns=10**18, watermarks=watermarks)
    arrivals = sorted(
        ((p.last_stamp_ns + jitter_ms[i] * MS, i, p) for i, (_, p) in enumerate(packets)),
        key=lambda a: (a[0], a[1]),
    )
    released_before: int | None = None
    newest = None
    accepted = late = 0
    streams_seen: set[Stream] = set()
    for at, _, p in arrivals:
        offer = buf.offer(p, now_ns=at)
        if offer.verdict is Verdict.ACCEPTED:
            accepted += 1
            assert released_before is None or p.first_stamp_ns > released_before
        elif offer.verdict is Verdict.LATE:
            late += 1
            new_stream = watermarks and p.stream not in streams_seen
            assert newest is not None
            assert new_stream or p.first_stamp_ns <= newest - lateness_ms * MS
        streams_seen.add(p.stream)
        newest = p.last_stamp_ns if newest is None else max(newest, p.last_stamp_ns)
        _, released_before = buf.release(now_ns=at)
    assert accepted + late == len(packets)


# -- stream watermarks ---------------------------------------------------------------------------


def three_streams(k: int) -> list[Packet]:
    """The k-th 100 ms of a vehicle: IMU [100k, 100k+9], GNSS at 100k+5, wheels to 100k+99."""
    return [imu_packet(k, 100 * k), gnss_packet(k, 100 * k + 5), wheels_packet(k, 100 * k + 3)]


def test_watermarks_release_what_every_stream_has_delivered() -> None:
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True)
    fixed = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18)
    for k in range(15):
        for p in three_streams(k):
            assert buf.offer(p, 0).verdict is Verdict.ACCEPTED
            fixed.offer(p, 0)
    # streams are complete up to IMU 1409, GNSS 1405, wheels 1499: the horizon is their
    # minimum, not newest - lateness (1199 ms)
    assert buf.release(0)[1] == T0 + 1405 * MS
    assert fixed.release(0)[1] == T0 + 1199 * MS
    assert buf.take_gaps() == ()  # every stream complete: no gap in the wheel data


def test_falling_idle_does_not_overtake_a_stream_the_watermarks_wait_for() -> None:
    """A link stall longer than the idle time: the horizon stays at the lowest watermark (the
    wheels', whose packet is held up), so that packet is fed when it comes, not late."""
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=1000 * MS, watermarks=True)
    for k in range(15):
        for p in three_streams(k):
            buf.offer(p, 0)
    imu, gnss, wheels = three_streams(15)
    buf.offer(imu, 0)
    buf.offer(gnss, 0)
    buf.release(0)
    assert buf.is_idle(5000 * MS)
    _, released = buf.release(5000 * MS)
    assert released == T0 + 1499 * MS  # the wheels' watermark, not the newest sample (1509)
    assert buf.offer(wheels, 5001 * MS).verdict is Verdict.ACCEPTED
    out, released = buf.release(5001 * MS)
    assert [p.stream for p in out] == [Stream.IMU, Stream.WHEELS, Stream.GNSS]
    assert released == T0 + 1505 * MS  # now the GNSS fix's


def test_lost_wheel_packets_open_one_gap_where_the_wheel_data_ends() -> None:
    """Two wheel packets lost: once the fixed window passes the wheels' watermark (the next
    wheel packet has come) the release names the loss once, at the end of the last wheel data,
    and the spans due without wheel data until the missing packets are given up on."""
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True)
    for k in range(15):
        for p in three_streams(k):
            buf.offer(p, 0)
    buf.release(0)
    gaps, wheels_fed = [], []
    for k in range(15, 25):
        imu, gnss, wheels = three_streams(k)
        for p in (imu, gnss) if k in (15, 16) else (imu, gnss, wheels):
            buf.offer(p, 0)
        out, _ = buf.release(0)
        gaps += [(a - T0, u and u - T0, p and p.first_stamp_ns - T0) for a, u, p in _wheel(buf)]
        wheels_fed += [p.seq for p in out if p.stream is Stream.WHEELS and p.seq >= 15]
    assert wheels_fed == list(range(17, 25))
    # each before the first packet released that starts after the wheel data (IMU)
    assert gaps == [
        (1499 * MS, None, 1500 * MS),  # lost: the wheel fits start afresh
        (1499 * MS, 1599 * MS, 1500 * MS),  # ticks due without wheel data
        (1599 * MS, 1699 * MS, 1600 * MS),  # ... until the gap is given up on
    ]


def test_wheel_data_only_later_is_no_gap_but_a_late_wheel_packet_is() -> None:
    """The wheel stream falls behind the fixed window: no edge is known lost (a slow wheel may
    have none), so only the ticks due meanwhile go without wheel speed; its packet then comes,
    late, and is refused: its edges are lost, the fits start afresh from what was released."""
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True)
    for k in range(15):
        for p in three_streams(k):
            buf.offer(p, 0)
    waits = []
    for k in range(15, 20):  # IMU and GNSS go on, the wheels packets are held up
        imu, gnss, _ = three_streams(k)
        buf.offer(imu, 0)
        buf.offer(gnss, 0)
        _, released = buf.release(0)
        waits += [(a - T0, u and u - T0) for a, u, _ in _wheel(buf)]
    assert released == T0 + 1609 * MS  # past the wheels' watermark (1499 ms)
    assert waits == [(1499 * MS, 1509 * MS), (1509 * MS, 1609 * MS)]  # no loss named
    assert buf.offer(wheels_packet(15, 1503), 0).verdict is Verdict.LATE
    out, _ = buf.release(0)
    assert out == [] and buf.take_gaps() == (StreamGap(Stream.WHEELS, T0 + 1609 * MS, None, None),)
    assert buf.take_gaps() == ()  # once


def test_watermarks_wait_the_fixed_window_at_start() -> None:
    """Until the start-up window has passed, streams not heard yet may still come."""
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True)
    for k in range(8):
        buf.offer(imu_packet(k, 100 * k), 0)
    assert buf.release(0)[1] == T0 + 709 * MS - 300 * MS
    assert WATERMARK_START_NS > 709 * MS
    # a GNSS stream appearing now is not late
    assert buf.offer(gnss_packet(0, 500), 0).verdict is Verdict.ACCEPTED


#: a vehicle that sends IMU packets only (the single-stream watermark tests)
IMU_ONLY = (Stream.IMU,)


def warm(buf: ReorderBuffer, n: int = 12) -> int:
    """Feed ``n`` IMU packets (past the start-up window); returns the next sequence number."""
    for k in range(n):
        buf.offer(imu_packet(k, 100 * k), 0)
    return n


def test_watermark_holds_at_a_sequence_gap_until_it_fills() -> None:
    buf = ReorderBuffer(lateness_ns=500 * MS, idle_ns=10**18, watermarks=True, streams=IMU_ONLY)
    n = warm(buf)
    for k in range(n, n + 6):
        if k == n + 3:
            continue  # this IMU packet is delayed in the network
        buf.offer(imu_packet(k, 100 * k), 0)
    # the IMU watermark stays at the last sample before the gap
    assert buf.release(0)[1] == T0 + (100 * (n + 2) + 9) * MS
    assert buf.offer(imu_packet(n + 3, 100 * (n + 3)), 0).verdict is Verdict.ACCEPTED
    out, released = buf.release(0)
    assert released == T0 + (100 * (n + 5) + 9) * MS
    assert [p.seq for p in out] == [n + 3, n + 4, n + 5]


def test_watermark_gives_up_on_a_lost_packet_after_the_window() -> None:
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True, streams=IMU_ONLY)
    n = warm(buf)
    lost = 0
    for k in range(n, n + 10):
        if k == n + 3:
            continue  # lost for good
        lost += buf.offer(imu_packet(k, 100 * k), 0).lost_delta
        buf.release(0)
    assert lost == 1
    # the fixed window passed the packet after the gap: the run resumed after it
    assert buf.release(0)[1] == T0 + (100 * (n + 9) + 9) * MS
    assert buf.offer(imu_packet(n + 3, 100 * (n + 3)), 0).verdict is Verdict.LATE


def test_watermark_follows_a_sequence_restart() -> None:
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True, streams=IMU_ONLY)
    n = warm(buf)
    offer = buf.offer(imu_packet(SEQ_WINDOW * 3, 100 * n), 0)  # counter reset
    assert offer.seq_restart
    buf.offer(imu_packet(SEQ_WINDOW * 3 + 1, 100 * (n + 1)), 0)
    assert buf.release(0)[1] == T0 + (100 * (n + 1) + 9) * MS


def test_watermarks_wait_for_a_stream_not_heard_yet() -> None:
    """A vehicle standing still sends IMU and GNSS but no wheel edges: its horizon keeps to the
    fixed window, so the first wheel packet after it starts moving is not late."""
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True)
    for k in range(20):
        buf.offer(imu_packet(k, 100 * k), 0)
        buf.offer(gnss_packet(k, 100 * k + 5), 0)
    assert buf.release(0)[1] == T0 + (1909 - 300) * MS  # not 1905 (IMU and GNSS marks)
    assert buf.offer(wheels_packet(0, 1700), 0).verdict is Verdict.ACCEPTED
    only_these = ReorderBuffer(
        lateness_ns=300 * MS, idle_ns=10**18, watermarks=True, streams=(Stream.IMU, Stream.GNSS)
    )
    for k in range(20):
        only_these.offer(imu_packet(k, 100 * k), 0)
        only_these.offer(gnss_packet(k, 100 * k + 5), 0)
    assert only_these.release(0)[1] == T0 + 1905 * MS


def test_until_moves_the_watermark_but_not_the_fixed_window() -> None:
    """``until_ns`` (the end of the batch window) lets a stream's watermark run to the end of
    its batch; the fixed window still counts from the newest sample time."""
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True)
    fixed = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18)
    for k in range(15):
        for p in three_streams(k):
            end = T0 + (100 * k + 99) * MS  # every stream complete to the end of the 100 ms
            q = dataclasses.replace(p, until_ns=end)
            assert buf.offer(q, 0).verdict is Verdict.ACCEPTED
            fixed.offer(q, 0)
    assert buf.release(0)[1] == T0 + 1499 * MS  # the windows' end, not the GNSS epoch (1405)
    # newest is the wheels' last edge (1499), not moved by until_ns
    assert fixed.release(0)[1] == T0 + (1499 - 300) * MS


def heartbeat(seq: int, until_ms: int) -> Packet:
    t = T0 + until_ms * MS
    return Packet("v1", Stream.WHEELS, seq, 1, (), t, t, t)


def test_wheel_heartbeats_move_the_watermark_and_are_never_late() -> None:
    """A vehicle standing still: heartbeats say the wheels stream is complete, so the horizon
    follows IMU and GNSS; a heartbeat behind the horizon is not late; none is fed."""
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True)
    for k in range(20):
        buf.offer(imu_packet(k, 100 * k), 0)
        buf.offer(gnss_packet(k, 100 * k + 5), 0)
        assert buf.offer(heartbeat(k, 100 * k + 99), 0).verdict is Verdict.ACCEPTED
    out, released = buf.release(0)
    assert released == T0 + 1905 * MS  # GNSS is the stream behind now
    assert all(p.measurements for p in out) and len(out) == 40
    assert buf.offer(heartbeat(5, 599), 0).verdict is Verdict.DUPLICATE
    behind = buf.offer(heartbeat(20, 1800), 0)  # not a promise broken: nothing to feed
    assert behind.verdict is Verdict.ACCEPTED
    assert buf.offer(wheels_packet(21, 1910), 0).verdict is Verdict.ACCEPTED


@settings(max_examples=60, deadline=None)
@given(
    delay_ms=st.lists(st.integers(0, 60), min_size=3, max_size=3),
    lateness_ms=st.integers(170, 400),  # > one batch (100 ms) + the delay spread
)
def test_property_in_order_streams_are_never_late_and_lag_only_their_spread(
    delay_ms: list[int], lateness_ms: int
) -> None:
    """Each stream in order with its own constant network delay: nothing is ever late, and once
    the start-up window has passed, the horizon trails the arrivals by at most the spread of the
    delays plus one packet, never by the whole window."""
    buf = ReorderBuffer(lateness_ns=lateness_ms * MS, idle_ns=10**18, watermarks=True)
    arrivals = sorted(
        (p.last_stamp_ns + delay_ms[i] * MS, i, p)
        for k in range(30)
        for i, p in enumerate(three_streams(k))
    )
    for at, _, p in arrivals:
        assert buf.offer(p, at).verdict is Verdict.ACCEPTED
        _, released = buf.release(at)
        assert released is not None
        if at - T0 > max(lateness_ms * MS, WATERMARK_START_NS) + 200 * MS:
            assert at - released <= (max(delay_ms) + 100) * MS + 1


@settings(max_examples=80, deadline=None)
@given(
    jitter_ms=st.lists(st.integers(0, 250), min_size=60, max_size=60),
    lateness_ms=st.integers(0, 300),
    watermarks=st.booleans(),
    heartbeats=st.booleans(),
)
# wheels 16 late, heartbeat 17 after wheels 18: it lands behind a gap the fixed window passed
@example(
    jitter_ms=[0] * 50 + [11, 0, 0, 111] + [0] * 6, lateness_ms=60, watermarks=True, heartbeats=True
)
def test_property_may_release_never_holds_back_a_release(
    jitter_ms: list[int], lateness_ms: int, watermarks: bool, heartbeats: bool
) -> None:
    """A buffer released only after packets that set ``may_release`` releases the same packets
    at the same moments, up to the same horizon, as one released after every packet: the
    packets it skips could not have moved the horizon."""
    packets = []
    for k in range(20):
        wheels = (
            heartbeat(k, 100 * k + 99)
            if heartbeats and k % 4 == 1
            else wheels_packet(k, 100 * k + 3)
        )
        packets += [imu_packet(k, 100 * k), gnss_packet(k, 100 * k + 50), wheels]
    arrivals = sorted(
        ((p.last_stamp_ns + jitter_ms[i] * MS, i, p) for i, p in enumerate(packets)),
        key=lambda a: (a[0], a[1]),
    )
    every = ReorderBuffer(lateness_ns=lateness_ms * MS, idle_ns=10**18, watermarks=watermarks)
    gated = ReorderBuffer(lateness_ns=lateness_ms * MS, idle_ns=10**18, watermarks=watermarks)
    for at, _, p in arrivals:
        assert every.offer(p, at).verdict is gated.offer(p, at).verdict
        got_every = every.release(at)
        if gated.may_release:
            assert gated.release(at) == got_every
        else:
            assert got_every[0] == []  # nothing was due
            assert got_every[1] == gated.released_ns  # and the horizon stood still
    assert every.release(0, flush=True) == gated.release(0, flush=True)


def test_packets_behind_a_lagging_stream_do_not_ask_for_a_release() -> None:
    """Wheel packets arrive 250 ms after their last edge: once the watermarks gate, the wheels
    hold the horizon, IMU and GNSS packets wait without a release, and every wheels packet
    asks for one."""
    buf = ReorderBuffer(lateness_ns=400 * MS, idle_ns=10**18, watermarks=True)
    arrivals = sorted(
        (p.last_stamp_ns + (250 if p.stream is Stream.WHEELS else 0) * MS, i, p)
        for k in range(30)
        for i, p in enumerate(three_streams(k))
    )
    asked: dict[Stream, list[bool]] = {s: [] for s in Stream}
    for at, _, p in arrivals:
        assert buf.offer(p, at).verdict is Verdict.ACCEPTED
        if at - T0 > 2 * WATERMARK_START_NS:
            asked[p.stream].append(buf.may_release)
        buf.release(at)
    assert asked[Stream.WHEELS] and all(asked[Stream.WHEELS])
    assert asked[Stream.IMU] and not any(asked[Stream.IMU] + asked[Stream.GNSS])


def test_streams_tied_at_the_lowest_watermark_ask_for_one_release() -> None:
    """Each stream's packets cover up to the same batch end (``until_ns``): the three
    watermarks tie, and only the packet that moves the last of them asks for a release, in
    whichever order the streams arrive."""
    buf = ReorderBuffer(lateness_ns=400 * MS, idle_ns=10**18, watermarks=True)
    orders = [(0, 1, 2), (2, 1, 0), (1, 0, 2), (2, 0, 1)]
    for k in range(40):
        end_ns = T0 + (100 * k + 99) * MS + 1  # past every sample of the batch
        batch = [dataclasses.replace(p, until_ns=end_ns) for p in three_streams(k)]
        asked = []
        for i in orders[k % len(orders)]:
            assert buf.offer(batch[i], 0).verdict is Verdict.ACCEPTED
            asked.append(buf.may_release)
            buf.release(0)
        if k > 2 * WATERMARK_START_NS // (100 * MS):
            assert asked == [False, False, True]
            assert buf.released_ns == end_ns


def sprockets_packet(seq: int, first_ms: int) -> Packet:
    t = T0 + (first_ms + np.arange(0, 97, 8)) * MS
    m = SprocketEdges(TrackSide.TRACK_LEFT, t)
    return Packet("v1", Stream.SPROCKETS, seq, 1, (m,), int(t[0]), int(t[-1]))


def steering_packet(seq: int, first_ms: int) -> Packet:
    t = T0 + (first_ms + np.arange(10) * 10) * MS
    m = SteeringAngles(t, np.zeros(10))
    return Packet("v1", Stream.STEERING, seq, 1, (m,), int(t[0]), int(t[-1]))


def test_lost_data_of_any_cumulative_stream_is_a_gap_of_that_stream() -> None:
    """A crawler sends sprocket edges instead of wheel edges: a lost sprockets packet opens the
    same gaps the wheels would, named for the sprockets."""
    tracked = (Stream.GNSS, Stream.IMU, Stream.SPROCKETS)
    buf = ReorderBuffer(lateness_ns=300 * MS, idle_ns=10**18, watermarks=True, streams=tracked)

    def crawler(k: int) -> list[Packet]:
        return [
            imu_packet(k, 100 * k),
            gnss_packet(k, 100 * k + 5),
            sprockets_packet(k, 100 * k + 3),
        ]

    for k in range(15):
        for p in crawler(k):
            buf.offer(p, 0)
    buf.release(0)
    gaps: list[StreamGap] = []
    for k in range(15, 20):
        imu, gnss, sprockets = crawler(k)
        for p in (imu, gnss) if k == 15 else (imu, gnss, sprockets):
            buf.offer(p, 0)
        buf.release(0)
        gaps += buf.take_gaps()
    assert {g.stream for g in gaps} == {Stream.SPROCKETS}
    lost = [g for g in gaps if g.until_ns is None]
    assert [(g.after_ns - T0, g.before and g.before.first_stamp_ns - T0) for g in lost] == [
        (1499 * MS, 1500 * MS)
    ]


def test_a_stream_that_counts_nothing_has_no_gap_and_is_ordered_by_its_priority() -> None:
    """A late steering packet is refused without a gap (a missing angle reads as nothing);
    packets starting at the same time are released in the streams' declared order."""
    buf = ReorderBuffer(lateness_ns=50 * MS, idle_ns=10**18)
    steering, imu = steering_packet(0, 0), imu_packet(0, 0)
    assert buf.offer(steering, 0).verdict is Verdict.ACCEPTED
    assert buf.offer(imu, 0).verdict is Verdict.ACCEPTED
    assert buf.offer(imu_packet(1, 200), 0).verdict is Verdict.ACCEPTED
    out, _ = buf.release(0)
    assert [p.stream for p in out] == [Stream.IMU, Stream.STEERING]  # priority 1 before 5
    assert buf.offer(steering_packet(1, 100), 0).verdict is Verdict.LATE
    buf.release(0)
    assert buf.take_gaps() == ()
