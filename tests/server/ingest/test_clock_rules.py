"""Time rules before the estimators: wall-clock bounds, clock jumps and re-anchoring, far
sequence jumps (``docs/protocol.md`` §6)."""

from __future__ import annotations

import dataclasses

import numpy as np

from server.ingest import Pipeline
from server.ingest.reorder import SEQ_WINDOW, ReorderBuffer, SeqTracker, Verdict
from server.ingest.subscriber import IngestItem
from server.settings import IngestSettings, Settings
from tests.server.ingest.fakes import CapturingSink, RecordingFleet, first_stamp
from tests.server.ingest.test_pipeline import T0, imu
from tests.server.ingest.test_reorder import imu_packet

MS = 1_000_000
S = 1_000 * MS
JUMP = 10 * S


def buffer(reanchor_after: int = 3) -> ReorderBuffer:
    return ReorderBuffer(50 * MS, clock_jump_ns=JUMP, reanchor_after=reanchor_after)


def test_single_wild_stamp_is_refused_and_does_not_move_the_horizon() -> None:
    buf = buffer()
    assert buf.offer(imu_packet(0, 0), 0).verdict is Verdict.ACCEPTED
    wild = imu_packet(1, 3_600_000)  # one hour ahead, 10 ms of wall time later
    assert buf.offer(wild, 10 * MS).verdict is Verdict.CLOCK_JUMP
    assert buf.offer(imu_packet(2, 10), 20 * MS).verdict is Verdict.ACCEPTED
    _, released = buf.release(20 * MS)
    assert released == T0 + 19 * MS - 50 * MS  # newest is still the real data


def test_consistent_jump_forward_reanchors_after_n_packets() -> None:
    buf = buffer(reanchor_after=3)
    buf.offer(imu_packet(0, 0), 0)
    base = 600_000  # the vehicle clock jumped ten minutes ahead
    verdicts = [buf.offer(imu_packet(1 + k, base + 10 * k), k * MS).verdict for k in range(3)]
    assert verdicts == [Verdict.CLOCK_JUMP, Verdict.CLOCK_JUMP, Verdict.REANCHOR]
    buf.release(3 * MS, flush=True)
    buf.reanchor(imu_packet(3, base + 20), 3 * MS)
    assert buf.offer(imu_packet(4, base + 30), 4 * MS).verdict is Verdict.ACCEPTED
    out, released = buf.release(10 * S)  # idle: everything of the new time base
    assert [p.seq for p in out] == [3, 4] and released == T0 + (base + 39) * MS


def test_jump_back_reanchors_instead_of_late_forever() -> None:
    buf = buffer(reanchor_after=3)
    for k in range(5):
        buf.offer(imu_packet(k, 100_000 + 10 * k), k * MS)
    buf.release(5 * MS)
    late = imu_packet(5, 99_950)  # behind the released horizon (99 999 ms)
    assert buf.offer(late, 6 * MS).verdict is Verdict.LATE  # slightly late: ordinary
    back = [buf.offer(imu_packet(6 + k, 10 * k), (7 + k) * MS).verdict for k in range(3)]
    assert back == [Verdict.CLOCK_JUMP, Verdict.CLOCK_JUMP, Verdict.REANCHOR]


def test_scattered_wild_stamps_never_reanchor() -> None:
    buf = buffer(reanchor_after=2)
    buf.offer(imu_packet(0, 0), 0)
    for k in range(1, 20):
        wild = imu_packet(2 * k - 1, 500_000 * (1 + k % 2) + k)  # 8 and 16 min ahead, alternating
        assert buf.offer(wild, k * MS).verdict is Verdict.CLOCK_JUMP
        assert buf.offer(imu_packet(2 * k, 10 * k), k * MS).verdict is Verdict.ACCEPTED


def test_resuming_after_a_quiet_gap_reanchors_at_once() -> None:
    buf = buffer()
    buf.offer(imu_packet(0, 0), 0)
    # 60 s of sensor time after 60 s of silence: a gap, not a jump
    assert buf.offer(imu_packet(1, 60_000), 60 * S).verdict is Verdict.REANCHOR
    # 5 s ahead is within the jump bound: accepted as is
    buf2 = buffer()
    buf2.offer(imu_packet(0, 0), 0)
    assert buf2.offer(imu_packet(1, 5_000), MS).verdict is Verdict.ACCEPTED


def test_far_sequence_jump_forward_is_a_restart_not_a_loss() -> None:
    t = SeqTracker()
    t.observe(5)
    assert t.observe(2**62) == (False, 0, True)  # bounded work, no 2**62 lost packets
    assert t.observe(6) == (False, 0, True)  # and back: another restart
    assert t.observe(6 + SEQ_WINDOW) == (False, SEQ_WINDOW - 1, False)  # a real gap is counted


def _pipeline(fleet: RecordingFleet, sink: CapturingSink) -> Pipeline:
    from server.estimation import EstimatorRegistry

    settings = Settings(
        ingest=IngestSettings(
            lateness_ms=50, process_interval_ms=5, reanchor_after_packets=3, clock_jump_s=10
        )
    )
    return Pipeline(
        settings,
        None,
        EstimatorRegistry(factories={"mdsf": lambda: fleet}),
        [sink],
        wall_clock_ns=lambda: T0,
    )


def test_pipeline_refuses_stamps_outside_the_wall_clock_bounds() -> None:
    fleet, sink = RecordingFleet(), CapturingSink()
    pipe = _pipeline(fleet, sink)
    pipe.start()
    day = 86_400_000
    pipe.submit([imu("a", 0, 0), imu("a", 1, 11 * 60_000), imu("a", 2, -8 * day), imu("a", 3, 10)])
    pipe.stop()
    c = pipe.counters_snapshot()["a"]
    assert c["rejected_clock_skew"] == 2 and c["accepted"] == 2
    assert c["received"] == c["accepted"] + c["late"] + c["duplicate"] + c["rejected"]


def test_pipeline_reanchor_flushes_old_data_and_restarts_the_estimator() -> None:
    fleet, sink = RecordingFleet(), CapturingSink()
    pipe = _pipeline(fleet, sink)
    pipe.start()
    pipe.submit([imu("a", k, 10 * k) for k in range(5)])
    jumped: list[IngestItem] = [
        imu("a", 5 + k, 300_000 + 10 * k) for k in range(6)
    ]  # clock 5 min ahead
    pipe.submit(jumped)
    pipe.stop()
    c = pipe.counters_snapshot()["a"]
    assert c["rejected_clock_jump"] == 2 and c["clock_reanchors"] == 1 and c["accepted"] == 9
    assert c["received"] == c["accepted"] + c["late"] + c["duplicate"] + c["rejected"]
    stamps = [first_stamp(m) for m in fleet.pushed["a"]]
    # everything of the old time base, then the new one from the re-anchoring packet on
    assert stamps == [T0 + 10 * k * MS for k in range(5)] + [
        T0 + (300_000 + 10 * k) * MS for k in range(2, 6)
    ]
    rows = np.concatenate(sink.rows["a"])["stamp_ns"]
    assert int(rows[0]) <= T0 + 49 * MS < int(rows[-1])  # old base advanced to its end first


def test_pipeline_refuses_a_packet_spanning_more_than_a_clock_jump() -> None:
    fleet, sink = RecordingFleet(), CapturingSink()
    pipe = _pipeline(fleet, sink)
    pipe.start()
    wide = imu("a", 0, -60_000, n=2)  # two samples, 1 ms apart ...
    stamps = np.array([T0 - 60 * S, T0], dtype=np.int64)  # ... moved one minute apart
    wide = dataclasses.replace(
        wide,
        measurements=(dataclasses.replace(wide.measurements[0], stamp_ns=stamps),),
        first_stamp_ns=int(stamps[0]),
        last_stamp_ns=int(stamps[1]),
    )
    pipe.submit([wide, imu("a", 1, 0)])
    pipe.stop()
    c = pipe.counters_snapshot()["a"]
    assert c["rejected_clock_jump"] == 1 and c["accepted"] == 1
    assert len(fleet.pushed["a"]) == 1
