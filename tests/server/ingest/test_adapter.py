"""The adapter: what estimators are handed of released packets and stream gaps."""

from __future__ import annotations

import numpy as np

from estimator.catalog import SPECS
from estimator.types import ImuBatch, SteeringAngles, WheelGap
from server.ingest.adapter import ESTIMATOR_STREAMS, fed, wheel_gaps
from server.ingest.reorder import StreamGap
from server.protocol import Packet, Stream

T0 = 1_763_700_000 * 10**9


def _packet(stream: Stream, m: object) -> Packet:
    return Packet("v1", stream, 0, 1, (m,), T0, T0 + 9)  # type: ignore[arg-type]


def test_estimators_are_fed_only_the_streams_they_read() -> None:
    t = T0 + np.arange(10, dtype=np.int64)
    imu = _packet(Stream.IMU, ImuBatch(t, np.zeros((10, 3)), np.zeros((10, 3))))
    steering = _packet(Stream.STEERING, SteeringAngles(t, np.zeros(10)))
    assert fed(imu) == imu.measurements and fed(steering) == steering.measurements
    assert fed(steering, {Stream.IMU}) == ()
    # every stream an estimator of the catalog names, and only those
    assert {Stream(n) for s in SPECS.values() for n in s.inputs} == ESTIMATOR_STREAMS
    assert {Stream.STEERING, Stream.WHEEL_SPEEDS4, Stream.ODOMETER, Stream.SPROCKETS} <= (
        ESTIMATOR_STREAMS
    )


def test_wheel_gaps_become_wheel_gap_notices_before_their_packet() -> None:
    before = _packet(Stream.IMU, None)
    gaps = [
        StreamGap(Stream.WHEELS, T0, None, before),
        StreamGap(Stream.SPROCKETS, T0, T0 + 5, None),  # nobody reads sprockets yet
        StreamGap(Stream.WHEELS, T0, T0 + 7, None),
    ]
    assert wheel_gaps(gaps) == [
        (WheelGap(after_ns=T0, until_ns=None), before),
        (WheelGap(after_ns=T0, until_ns=T0 + 7), None),
    ]
