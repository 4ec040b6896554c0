"""A steered four-wheel vehicle's packets: one per measurement in arrival order, encoded with the
server's stream declarations, and the encoded schedule patches their stamps and sequence
numbers byte for byte as the per-packet encoding does, over loops."""

from __future__ import annotations

import math

import numpy as np

from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4
from server.protocol import Stream, decode, sensor_key
from server.tooling.steered_fleet import demo_drive, steered_packets
from tests.server.tooling.schedule_check import assert_schedule_patches_like_encoding

T0 = 1_763_700_000 * 10**9
MS = 1_000_000


def _measurements(seconds: int) -> list:
    """A run's packets as the four-wheel simulator sends them: per 100 ms an IMU batch of 10,
    wheel speeds and steering of 5 each, and a GNSS epoch."""
    out: list = []
    for k in range(seconds * 10):
        t = T0 + k * 100 * MS
        imu = t + np.arange(10, dtype=np.int64) * 10 * MS
        can = t + np.arange(5, dtype=np.int64) * 20 * MS
        out.append(
            GnssSample(
                stamp_ns=t,
                vel_enu_mps=(1.0, 2.0, 0.0),
                heading_rad=0.1,
                pitch_rad=0.0,
                roll_rad=0.0,
                lat_deg=48.0,
                lon_deg=11.0,
                height_m=500.0,
            )
        )
        out.append(ImuBatch(imu, np.full((10, 3), 0.1 * k), np.full((10, 3), 0.01)))
        out.append(WheelSpeeds4(can, np.full((5, 4), 30.0 + k)))
        out.append(SteeringAngles(can, np.full(5, math.radians(k))))
    return out


def test_packets_arrive_with_their_last_sample_and_decode_as_sent() -> None:
    packets = steered_packets(_measurements(2), T0)
    assert len(packets) == 80 and all(len(p.measurements) == 1 for p in packets)
    offsets = [p.arrival_offset_ns for p in packets]
    assert offsets == sorted(offsets) and offsets[:4] == [0, 80 * MS, 80 * MS, 90 * MS]
    assert {p.stream for p in packets} == {
        Stream.GNSS,
        Stream.IMU,
        Stream.WHEEL_SPEEDS4,
        Stream.STEERING,
    }
    for seq, p in enumerate(packets):
        got = decode(sensor_key("fleet", "sim-0005", p.stream), p.encode(seq))
        assert got.stream is p.stream and got.seq == seq
        (sent,), (back,) = p.measurements, got.measurements
        assert type(back) is type(sent)
        np.testing.assert_array_equal(back.stamp_ns, sent.stamp_ns)
        if isinstance(sent, WheelSpeeds4):
            assert isinstance(back, WheelSpeeds4)
            np.testing.assert_array_equal(back.omega_radps, sent.omega_radps)
        if isinstance(sent, SteeringAngles):
            assert isinstance(back, SteeringAngles)
            np.testing.assert_array_equal(back.angle_rad, sent.angle_rad)


def test_schedule_patches_steered_packets_like_the_per_packet_encoding() -> None:
    packets = steered_packets(_measurements(3), T0)
    streams = {Stream.GNSS, Stream.IMU, Stream.STEERING, Stream.WHEEL_SPEEDS4}  # no wheels
    assert_schedule_patches_like_encoding(packets, T0, streams)


def test_demo_drive_ends_as_it_starts_and_holds_a_wet_patch() -> None:
    drive = demo_drive()
    speed, steer, mu = drive.sample(np.array([0.0, drive.duration_s]))
    assert speed[0] == speed[1] and steer[0] == steer[1] == 0.0 and mu[0] == mu[1] == 0.8
    _, _, mu_mid = drive.sample(np.linspace(0.0, drive.duration_s, 301))
    assert mu_mid.min() == 0.35
