"""The streams a vehicle's reorder buffer waits for follow its estimators' spec inputs, and a
stream that stops is told (``stalled_<stream>``), not left silent.

A steered four-wheel vehicle sends IMU, GNSS, CAN wheel speeds and steering (no wheel edges)
and a crawler GNSS, IMU, odometer and sprockets: with a buffer waiting for the tractor's
GNSS/IMU/wheels, their rows came out only once the lateness window (here 2 s) had passed.
Real pipeline and reorder buffers; recording estimators of the real specs.
"""

from __future__ import annotations

import numpy as np

from estimator.config import TrackedConfig, Wheeled4wdSteeredConfig
from estimator.friction_spec import FRICTION_SPEC
from estimator.tracked_spec import TRACKED_SPEC
from estimator.types import (
    ImuBatch,
    OdometerEdges,
    SprocketEdges,
    SteeringAngles,
    TrackSide,
    WheelSpeeds4,
)
from server.estimation import EstimatorRegistry
from server.ingest import Pipeline
from server.ingest.adapter import spec_streams
from server.ingest.reorder import DEFAULT_STREAMS, ReorderBuffer
from server.protocol import Packet, Stream
from tests.server.ingest.fakes import RecordingFleet
from tests.server.ingest.test_pipeline import MS, T0, gnss, make

LATENESS_MS = 2_000


def _window(k: int, n: int) -> np.ndarray:
    """``n`` stamps evenly over the 100 ms window ``k`` (its last at the window's end)."""
    return T0 + k * 100 * MS + (np.arange(1, n + 1) * (100 // n)) * MS


def _packet(vid: str, stream: Stream, seq: int, m: object, t: np.ndarray, edges: bool) -> Packet:
    until = int(T0 + (seq + 1) * 100 * MS) if edges else None
    first, last = (int(t[0]), int(t[-1])) if t.size else (until, until)
    ms = (m,) if m is not None else ()
    return Packet(vid, stream, seq, 1, ms, first, last, until)  # type: ignore[arg-type]


def _imu(vid: str, k: int) -> Packet:
    """Window ``k``'s IMU batch: ten samples 10 ms apart."""
    t = _window(k, 10)
    return _packet(vid, Stream.IMU, k, ImuBatch(t, np.zeros((10, 3)), np.zeros((10, 3))), t, False)


def steered(vid: str, k: int) -> list[Packet]:
    """Window ``k`` of a steered vehicle: GNSS, IMU, four wheel speeds, steering."""
    t = _window(k, 5)
    return [
        gnss(vid, k, k * 100 + 100),
        _imu(vid, k),
        _packet(vid, Stream.WHEEL_SPEEDS4, k, WheelSpeeds4(t, np.full((5, 4), 10.0)), t, False),
        _packet(vid, Stream.STEERING, k, SteeringAngles(t, np.zeros(5)), t, False),
    ]


def crawler(vid: str, k: int, sprockets: bool = True) -> list[Packet]:
    """Window ``k`` of a crawler: GNSS, IMU, odometer and (unless not) sprocket edges."""
    t = _window(k, 4)
    out = [
        gnss(vid, k, k * 100 + 100),
        _imu(vid, k),
        _packet(vid, Stream.ODOMETER, k, OdometerEdges(t), t, True),
    ]
    if sprockets:
        out.append(
            _packet(vid, Stream.SPROCKETS, k, SprocketEdges(TrackSide.TRACK_LEFT, t), t, True)
        )
    return out


def _pipeline(clock: list[int]) -> tuple[Pipeline, dict[str, RecordingFleet]]:
    """A pipeline (2 s lateness, a hand-moved monotonic clock: never idle) on recording
    friction and tracked estimators."""
    friction, tracked = RecordingFleet(FRICTION_SPEC), RecordingFleet(TRACKED_SPEC)
    registry = EstimatorRegistry(
        factories={"friction": lambda: friction, "tracked": lambda: tracked}
    )
    pipe, _, _ = make(
        lateness_ms=LATENESS_MS, advance_step_ms=100, clock_ns=lambda: clock[0], registry=registry
    )
    return pipe, {"friction": friction, "tracked": tracked}


def _feed(pipe: Pipeline, clock: list[int], packets: list[Packet]) -> None:
    """Hand ``packets`` to the pipeline thread (the clock moving 1 ms a packet) and let it
    release what it may."""
    for p in packets:
        clock[0] += MS
        pipe._handle([p], clock[0])
    pipe._tick(clock[0], flush=False)


def test_spec_streams_are_the_inputs_of_the_vehicles_estimators() -> None:
    assert set(spec_streams(("mdsf",))) == set(DEFAULT_STREAMS)
    assert set(spec_streams(("friction",))) == {
        Stream.IMU,
        Stream.GNSS,
        Stream.WHEEL_SPEEDS4,
        Stream.STEERING,
    }
    assert set(spec_streams(("tracked",))) == {
        Stream.GNSS,
        Stream.IMU,
        Stream.ODOMETER,
        Stream.SPROCKETS,
    }
    assert spec_streams(()) == DEFAULT_STREAMS


def test_steered_vehicle_and_crawler_rows_come_out_without_waiting_the_lateness_window() -> None:
    clock = [10**12]
    pipe, fleets = _pipeline(clock)
    pipe.register_vehicle("s1", Wheeled4wdSteeredConfig())
    pipe.register_vehicle("c1", TrackedConfig())
    pipe._apply_control()
    seconds = 5  # the watermarks gate from 2 s on (the start-up window: the lateness)
    for k in range(seconds * 10):
        _feed(pipe, clock, steered("s1", k) + crawler("c1", k))
    pipe._tick(clock[0], flush=False)
    newest = int(_window(seconds * 10 - 1, 1)[0])
    for name, vid in (("friction", "s1"), ("tracked", "c1")):
        advanced = fleets[name].until.get(vid)
        assert advanced is not None, f"{vid}'s {name} never advanced"
        assert newest - advanced <= 100 * MS, (vid, (newest - advanced) / MS)
    assert pipe.counters_snapshot()["c1"].keys().isdisjoint({"stalled_sprockets"})


def test_a_stream_that_stops_is_counted_stalled_once_per_stop() -> None:
    clock = [10**12]
    pipe, _ = _pipeline(clock)
    pipe.register_vehicle("c1", TrackedConfig())
    pipe._apply_control()
    for k in range(20):  # 2 s with both edge streams
        _feed(pipe, clock, crawler("c1", k))
    for k in range(20, 90):  # 7 s without sprockets: past the 2 s window
        _feed(pipe, clock, crawler("c1", k, sprockets=False))
    assert pipe.counters_snapshot()["c1"]["stalled_sprockets"] == 1
    buf = pipe._buffers["c1"]
    assert buf.stalled == {Stream.SPROCKETS}


def test_a_stream_never_sent_is_told_stalled_once_the_start_up_window_is_over() -> None:
    buf = ReorderBuffer(
        150 * MS, watermarks=True, streams=spec_streams(("tracked",)), clock_jump_ns=None
    )
    told: list[tuple[int, Stream]] = []
    for k in range(30):
        for p in crawler("c1", k, sprockets=False):
            buf.offer(p, k * 100 * MS)
        buf.release(k * 100 * MS)
        told += [(k, s) for s in buf.take_stalls()]
    assert told == [(10, Stream.SPROCKETS)]  # 1 s (WATERMARK_START_NS) after the first packet
    assert buf.stalled == {Stream.SPROCKETS}


def test_expect_changes_what_the_watermarks_wait_for() -> None:
    buf = ReorderBuffer(1_000 * MS, watermarks=True)  # the tractor's streams by default
    assert buf.expected == DEFAULT_STREAMS
    buf.expect(spec_streams(("friction",)))
    for k in range(30):
        for p in steered("s1", k):
            buf.offer(p, k * 100 * MS)
    packets, released = buf.release(3_000 * MS)
    assert released == int(_window(29, 1)[0]) and len(packets) == 120
    buf.expect(DEFAULT_STREAMS)  # no wheel edges come: back to the fixed window
    for p in steered("s1", 30):
        buf.offer(p, 3_100 * MS)
    assert buf.release(3_100 * MS)[1] == released
