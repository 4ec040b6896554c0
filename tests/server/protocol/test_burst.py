"""Burst decoding: item for item what the per-packet decoder returns or raises."""

from __future__ import annotations

import random
from typing import Any

import msgpack
import numpy as np
import pytest

from estimator.sim import simulate
from estimator.types import GnssSample, ImuBatch, Wheel, WheelEdges, WheelSpeeds
from server.protocol import (
    DecodeError,
    Packet,
    Stream,
    burst,
    decode,
    encode_imu,
    encode_wheel_edges,
    encode_wheel_speeds,
    sensor_key,
)
from server.protocol.burst import decode_burst
from server.protocol.streams import STREAMS
from server.tooling.fleet_sim import encode_packets, packetize
from tests.server.faults.test_fuzz import MAX_PAYLOAD, PREFIX, Feeder

T0 = 1_763_700_000 * 10**9
STEP_NS = 10_000_000


@pytest.fixture(autouse=True)
def batch_every_burst(monkeypatch: pytest.MonkeyPatch) -> None:
    """The tests here check the batched path, whatever the burst's length."""
    monkeypatch.setattr(burst, "MIN_BATCHED", 1)


Item = Packet | DecodeError


def _decode_one(key: str, payload: bytes, **kw: Any) -> Item:
    try:
        return decode(key, payload, **kw)
    except DecodeError as exc:
        return exc


def _same_value(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.flags.writeable == b.flags.writeable
            and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
        )
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same_value(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float) and a != a:
        return b != b  # NaN: "not available" on both sides
    return type(a) is type(b) and bool(a == b)


def assert_same(expected: Item, got: Item) -> None:
    """``got`` equals ``expected`` field by field (arrays by value, dtype and flags)."""
    assert type(got) is type(expected)
    if isinstance(expected, DecodeError):
        assert isinstance(got, DecodeError)
        fields = ("reason", "detail", "vehicle_id", "stream")
        assert [getattr(got, f) for f in fields] == [getattr(expected, f) for f in fields]
        return
    assert isinstance(got, Packet)
    for name in Packet.__slots__:
        if name != "measurements":
            assert getattr(got, name) == getattr(expected, name), name
    assert len(got.measurements) == len(expected.measurements)
    for x, y in zip(expected.measurements, got.measurements, strict=True):
        assert type(x) is type(y)
        for name in type(x).__slots__:
            assert _same_value(getattr(x, name), getattr(y, name)), name


def assert_burst_matches(received: list[tuple[str, bytes]], **kw: Any) -> list[Item]:
    got = decode_burst(received, **kw)
    assert len(got) == len(received)
    for (key, payload), item in zip(received, got, strict=True):
        assert_same(_decode_one(key, payload, **kw), item)
    return got


def _simulated(vehicles: int = 4, n_packets: int = 600) -> list[tuple[str, bytes]]:
    run = simulate("field_work", seed=3, start_ns=T0, duration_s=20.0)
    enc = encode_packets(packetize(run.sent_in_arrival_order(), run.start_ns)[:n_packets])
    return [
        (sensor_key("fleet", f"veh-{i % vehicles}", stream), payload)
        for i, (stream, payload) in enumerate(enc)
    ]


def _imu_payload(seq: int, t0: int = T0, n: int = 5, **override: Any) -> bytes:
    t = t0 + np.arange(n, dtype=np.int64) * STEP_NS
    acc = np.tile([0.1, 0.5, 9.81], (n, 1))
    gyr = np.tile([0.01, 0.0, -0.2], (n, 1))
    for name, (row, value) in override.items():
        (acc if name == "accel" else gyr)[row, 0] = value
    return encode_imu(ImuBatch(t, acc, gyr), seq, until_ns=int(t0 + n * STEP_NS))


def _edges_payload(seq: int, t0: int = T0, direction: int = 1) -> bytes:
    t = t0 + np.arange(4, dtype=np.int64) * STEP_NS
    d = np.array([1, 1, direction, -1], dtype=np.int8)
    return encode_wheel_edges([WheelEdges(Wheel.LEFT, t, d), WheelEdges(Wheel.RIGHT, t + 1)], seq)


def _speeds_payload(seq: int, t0: int = T0, omega: float = 3.0) -> bytes:
    t = t0 + np.arange(3, dtype=np.int64) * STEP_NS
    om = np.full((3, 2), 2.0)
    om[1, 1] = omega
    return encode_wheel_speeds(WheelSpeeds(t, om), seq)


def _with(payload: bytes, **fields: Any) -> bytes:
    m = msgpack.unpackb(payload, raw=False)
    m.update(fields)
    return msgpack.packb(m, use_bin_type=True)


KEY = {s: sensor_key("fleet", "veh-1", s) for s in Stream}


def test_burst_equals_per_packet_decode_on_simulated_packets() -> None:
    received = _simulated()
    got = assert_burst_matches(received)
    assert all(isinstance(item, Packet) for item in got)
    simulated = {Stream.GNSS, Stream.IMU, Stream.WHEELS}  # the streams the simulator sends
    assert {item.stream for item in got if isinstance(item, Packet)} == simulated


def test_burst_equals_per_packet_decode_on_every_array_kind() -> None:
    received = [
        (KEY[Stream.IMU], _imu_payload(0)),
        (KEY[Stream.WHEELS], _edges_payload(0)),
        (KEY[Stream.WHEELS], _speeds_payload(1)),
        (KEY[Stream.IMU], _imu_payload(1, T0 + 10**8, n=1)),
        (KEY[Stream.WHEELS], _speeds_payload(2, T0 + 10**8, omega=float("nan"))),
        (KEY[Stream.IMU], _imu_payload(2, T0 + 2 * 10**8, accel=(2, float("nan")))),
        (KEY[Stream.WHEELS], encode_wheel_edges([], 3, T0 + 3 * 10**8)),  # a heartbeat
    ]
    got = assert_burst_matches(received)
    assert all(isinstance(item, Packet) for item in got)
    beat = got[-1]
    assert isinstance(beat, Packet) and beat.measurements == ()
    assert beat.first_stamp_ns == beat.until_ns == T0 + 3 * 10**8


def test_bad_packets_in_a_burst_are_refused_alone_with_their_reason() -> None:
    inf, t_back = float("inf"), np.array([T0, T0 + 2, T0 + 1], dtype=np.int64).tobytes()
    bad: dict[int, tuple[Stream, bytes, str]] = {
        1: (Stream.IMU, _imu_payload(1, accel=(3, inf)), "non_finite"),
        3: (Stream.IMU, _imu_payload(3, gyro=(0, 50.0)), "out_of_range"),
        4: (Stream.IMU, _with(_imu_payload(4), stamp_ns=t_back), "non_monotonic"),
        6: (Stream.WHEELS, _edges_payload(6, direction=0), "out_of_range"),
        7: (Stream.WHEELS, _speeds_payload(7, omega=-inf), "non_finite"),
        9: (Stream.WHEELS, _speeds_payload(9, omega=600.0), "out_of_range"),
        10: (Stream.IMU, _with(_imu_payload(10), until_ns=T0), "out_of_range"),
        12: (Stream.IMU, _with(_imu_payload(12), accel_mps2=b"\0" * 24), "wrong_shape"),
        13: (
            Stream.IMU,
            _with(_imu_payload(13), stamp_ns=(T0 // 100).to_bytes(8, "little") * 5),
            "out_of_range",
        ),
        15: (Stream.WHEELS, _with(_edges_payload(15), edges=[]), "wrong_type"),
        16: (Stream.IMU, _imu_payload(16, n=0), "wrong_shape"),
    }
    received = []
    for i in range(18):
        t0 = T0 + i * 10**8
        if i in bad:
            stream, payload, _ = bad[i]
        elif i % 3 == 0:
            stream, payload = Stream.WHEELS, _edges_payload(i, t0)
        elif i % 3 == 1:
            stream, payload = Stream.WHEELS, _speeds_payload(i, t0)
        else:
            stream, payload = Stream.IMU, _imu_payload(i, t0)
        received.append((KEY[stream], payload))
    got = assert_burst_matches(received)
    refused = {i: item.reason for i, item in enumerate(got) if isinstance(item, DecodeError)}
    assert refused == {i: reason for i, (_, _, reason) in bad.items()}


def _gnss_payload(seq: int, t0: int = T0, **fields: Any) -> bytes:
    m = {
        "v": 1,
        "sensor": "gnss",
        "seq": seq,
        "stamp_ns": t0,
        "vel_enu_mps": [1.0, 0.5, 0.0],
        "heading_rad": 0.3,
        "pitch_rad": 0.01,
        "roll_rad": -0.02,
        "lat_deg": 52.0,
        "lon_deg": 5.6,
        "height_m": 12.0,
        "fix": 4,
        "vel_std_mps": 0.03,
        **fields,
    }
    return msgpack.packb(m, use_bin_type=True)


def test_packets_beyond_the_usual_shape_are_decoded_as_alone() -> None:
    """Valid packets the fast path leaves to the codec (an extra field, NaN velocity) or takes
    with a conversion (integers where a float goes), and invalid ones it would take if it only
    checked types (``nil`` for an optional field, ``seq`` of 2**63, a sensor that is not the
    key's, a wheels packet in ``speeds`` mode with a stray ``edges`` entry, a heartbeat
    without ``until_ns``), come out as the codec decodes them."""
    nan = float("nan")
    received = [
        (KEY[Stream.GNSS], _gnss_payload(0)),
        (KEY[Stream.GNSS], _gnss_payload(1, T0 + 10**8, vendor_note="rtk")),
        (KEY[Stream.GNSS], _gnss_payload(2, T0 + 2 * 10**8, vel_enu_mps=[1, 0, 0], height_m=3)),
        (KEY[Stream.GNSS], _gnss_payload(3, T0 + 3 * 10**8, vel_enu_mps=[nan, nan, nan])),
        (KEY[Stream.GNSS], _gnss_payload(4, T0 + 4 * 10**8, until_ns=None)),
        (KEY[Stream.GNSS], _gnss_payload(5, T0 + 5 * 10**8, fix=None)),
        (KEY[Stream.IMU], _with(_imu_payload(6), seq=2**63)),
        (KEY[Stream.IMU], _with(_imu_payload(7), sensor="gnss")),
        (KEY[Stream.IMU], _with(_imu_payload(8), until_ns=None)),
        (KEY[Stream.WHEELS], _with(_speeds_payload(9), edges=[{"wheel": 7}])),
        (KEY[Stream.WHEELS], _with(_edges_payload(10), edges=[])),
        (KEY[Stream.WHEELS], _with(_edges_payload(11), mode="pulses")),
    ]
    got = assert_burst_matches(received)
    decoded = [isinstance(item, Packet) for item in got]
    assert decoded == [True, True, True, True] + [False] * 5 + [True, False, False]


@pytest.mark.parametrize("seed", range(8))
def test_burst_equals_per_packet_decode_on_mutated_packets(seed: int) -> None:
    rng = random.Random(seed)
    feeder = Feeder()
    feeder.index = {v: rng.randrange(2000) for v in feeder.index}
    received = feeder.batch(rng, 500, rng.uniform(0.05, 1.0))
    got = assert_burst_matches(received, prefix=PREFIX, max_payload_bytes=MAX_PAYLOAD)
    assert any(isinstance(item, Packet) for item in got)
    assert any(isinstance(item, DecodeError) for item in got)


def test_empty_burst() -> None:
    assert decode_burst([]) == []


def test_gnss_in_a_burst_is_decoded_as_alone() -> None:
    received = [(k, p) for k, p in _simulated(n_packets=60) if k.endswith("gnss")]
    got = assert_burst_matches(received)
    assert all(
        isinstance(item, Packet) and isinstance(item.measurements[0], GnssSample) for item in got
    )


def test_short_bursts_are_decoded_packet_by_packet(monkeypatch: pytest.MonkeyPatch) -> None:
    """Below MIN_BATCHED packets the arrays are not joined (it would cost more than it saves);
    the items are the same either way."""
    monkeypatch.setattr(burst, "MIN_BATCHED", 8)
    joined: list[int] = []
    finish = burst._Groups.finish
    monkeypatch.setattr(
        burst._Groups, "finish", lambda self, *a: (joined.append(1), finish(self, *a))[1]
    )
    received = _simulated(n_packets=20)
    assert_burst_matches(received[:7])
    assert joined == []
    assert_burst_matches(received[:8])
    assert joined == [1]


def test_gnss_velocity_as_bin_in_a_burst_is_decoded_as_alone() -> None:
    """A GNSS packet whose ``vel_enu_mps`` is a ``bin`` of 3 float64 is decoded, in a burst as
    alone, to the sample of the same packet with an array."""
    vel = np.array([1.0, 0.5, 0.0], dtype="<f8").tobytes()
    received = [
        (KEY[Stream.GNSS], _gnss_payload(i, T0 + i * 10**8, vel_enu_mps=vel)) for i in range(12)
    ]
    got = assert_burst_matches(received)
    assert all(isinstance(item, Packet) for item in got)
    sample = got[0].measurements[0]  # type: ignore[union-attr]
    assert isinstance(sample, GnssSample) and sample.vel_enu_mps == (1.0, 0.5, 0.0)


def test_routes_are_the_stream_declarations() -> None:
    """The burst decoder's per-struct routes are taken from the declarations, one per stream,
    and a stream's one layout is what its ``batch`` and ``decode`` go by."""
    assert {route.stream for route in burst._ROUTES.values()} == set(Stream)
    for stream, spec in STREAMS.items():
        assert burst._ROUTES[spec.wire] == (stream, spec.single, spec.layout, spec.batch)
        if spec.layout is not None:
            assert spec.batch(None) is spec.layout
            assert spec.decode == spec.layout.decode


def test_keys_seen_are_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    """The keys a burst met are kept for the next ones, up to a bound: past it they are
    forgotten at the next burst, and packets decode the same either way."""
    monkeypatch.setattr(burst, "_KEYS_HELD", 4)
    monkeypatch.setattr(burst, "_KEYS", {})

    def burst_of(vehicles: range) -> list[tuple[str, bytes]]:
        return [(sensor_key("fleet", f"veh-{i}", Stream.IMU), _imu_payload(i)) for i in vehicles]

    assert_burst_matches(burst_of(range(3)))
    assert len(burst._KEYS["fleet"]) == 3
    assert_burst_matches(burst_of(range(3, 10)))  # a burst is decoded whole...
    assert len(burst._KEYS["fleet"]) == 10
    assert_burst_matches(burst_of(range(10, 12)))  # ...and the next starts afresh
    assert len(burst._KEYS["fleet"]) == 2
    assert_burst_matches(burst_of(range(2)), prefix="other")
    assert isinstance(decode_burst(burst_of(range(2)), prefix="other")[0], DecodeError)
