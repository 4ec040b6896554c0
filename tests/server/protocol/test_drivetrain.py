"""The drivetrain streams (odometer, sprockets, steering, wheel_speeds4): round trips, every
refusal with its reason, and the burst decoder agreeing with the codec on them."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from estimator.types import (
    Corner,
    OdometerEdges,
    SprocketEdges,
    SteeringAngles,
    TrackSide,
    WheelSpeeds4,
)
from server.protocol import (
    LIMITS,
    STREAMS,
    DecodeError,
    EncodeError,
    Packet,
    Stream,
    burst,
    decode,
    encode_odometer,
    encode_sprockets,
    encode_steering,
    encode_wheel_speeds4,
    sensor_key,
    spec_of,
)
from server.protocol.burst import decode_burst
from server.protocol.wire import DECODER
from tests.server.protocol.payloads import edited
from tests.server.protocol.test_burst import assert_burst_matches

T0 = 1_763_700_000 * 10**9
STEP_NS = 10_000_000
KEY = {s: sensor_key("fleet", "veh-1", s) for s in Stream}
NEW = (Stream.ODOMETER, Stream.SPROCKETS, Stream.STEERING, Stream.WHEEL_SPEEDS4)


def _t(n: int = 5, t0: int = T0) -> np.ndarray:
    return t0 + np.arange(n, dtype=np.int64) * STEP_NS


def _valid(stream: Stream, seq: int = 0, t0: int = T0) -> bytes:
    t = _t(5, t0)
    if stream is Stream.ODOMETER:
        return encode_odometer(OdometerEdges(t, np.array([1, 1, -1, 1, 1], np.int8)), seq)
    if stream is Stream.SPROCKETS:
        edges = [
            SprocketEdges(TrackSide.TRACK_LEFT, t),
            SprocketEdges(TrackSide.TRACK_RIGHT, t + 3),
        ]
        return encode_sprockets(edges, seq, until_ns=int(t[-1]) + 4)
    if stream is Stream.STEERING:
        return encode_steering(SteeringAngles(t, np.linspace(-1.0, 1.0, 5)), seq)
    return encode_wheel_speeds4(WheelSpeeds4(t, np.arange(20.0).reshape(5, 4) - 8), seq)


def _with(payload: bytes, **fields: Any) -> bytes:
    """``payload`` with fields replaced, or deleted (value None)."""
    return edited(payload, fields)


def _entry(payload: bytes, **fields: Any) -> bytes:
    """A sprockets payload whose first entry has fields replaced or deleted."""
    return edited(payload, fields, lambda m: m["edges"][0])


def _i8(*values: int) -> bytes:
    return np.array(values, dtype="<i8").tobytes()


def _f8(a: Any) -> bytes:
    return np.ascontiguousarray(a, dtype="<f8").tobytes()


def _reason(stream: Stream, payload: bytes) -> str:
    with pytest.raises(DecodeError) as info:
        decode(KEY[stream], payload)
    assert info.value.stream is stream and info.value.vehicle_id == "veh-1"
    return info.value.reason


# ------------------------------------------------------------------------- round trips


def test_odometer_round_trip_with_and_without_direction() -> None:
    t = _t(6)
    for direction in (np.array([1, 1, 1, -1, -1, 1], np.int8), None):
        p = decode(KEY[Stream.ODOMETER], encode_odometer(OdometerEdges(t, direction), 7))
        (m,) = p.measurements
        assert isinstance(m, OdometerEdges) and (p.stream, p.seq) == (Stream.ODOMETER, 7)
        np.testing.assert_array_equal(m.stamp_ns, t)
        if direction is None:
            assert m.direction is None
        else:
            np.testing.assert_array_equal(m.direction, direction)
        assert (p.first_stamp_ns, p.last_stamp_ns) == (int(t[0]), int(t[-1]))


def test_odometer_edges_may_share_a_stamp() -> None:
    t = np.array([T0, T0, T0 + 5], dtype=np.int64)
    (m,) = decode(KEY[Stream.ODOMETER], encode_odometer(OdometerEdges(t), 0)).measurements
    assert isinstance(m, OdometerEdges)
    np.testing.assert_array_equal(m.stamp_ns, t)


def test_sprockets_round_trip_per_track() -> None:
    p = decode(KEY[Stream.SPROCKETS], _valid(Stream.SPROCKETS))
    assert [type(m) for m in p.measurements] == [SprocketEdges, SprocketEdges]
    left, right = p.measurements
    assert isinstance(left, SprocketEdges) and isinstance(right, SprocketEdges)
    assert (left.side, right.side) == (TrackSide.TRACK_LEFT, TrackSide.TRACK_RIGHT)
    assert type(left.side) is TrackSide
    np.testing.assert_array_equal(right.stamp_ns, _t() + 3)
    assert (p.first_stamp_ns, p.last_stamp_ns, p.until_ns) == (
        T0,
        int(_t()[-1]) + 3,
        int(_t()[-1]) + 4,
    )


def test_steering_round_trip_keeps_nan_as_not_available() -> None:
    angle = np.array([0.1, np.nan, -0.3, 18.0, -18.0])
    p = decode(KEY[Stream.STEERING], encode_steering(SteeringAngles(_t(), angle), 3))
    (m,) = p.measurements
    assert isinstance(m, SteeringAngles) and m.angle_rad.shape == (5,)
    np.testing.assert_array_equal(m.angle_rad, angle)


def test_wheel_speeds4_round_trip_in_corner_order() -> None:
    omega = np.arange(20.0).reshape(5, 4)
    p = decode(KEY[Stream.WHEEL_SPEEDS4], encode_wheel_speeds4(WheelSpeeds4(_t(), omega), 1))
    (m,) = p.measurements
    assert isinstance(m, WheelSpeeds4) and m.omega_radps.shape == (5, len(Corner))
    assert m.omega_radps[2, Corner.REAR_LEFT] == 10.0


@pytest.mark.parametrize("stream", [Stream.ODOMETER, Stream.SPROCKETS])
def test_edge_streams_send_heartbeats(stream: Stream) -> None:
    until = T0 + 99 * STEP_NS
    payload = (
        encode_odometer(OdometerEdges(np.zeros(0, np.int64)), 4, until_ns=until)
        if stream is Stream.ODOMETER
        else encode_sprockets([], 4, until_ns=until)
    )
    p = decode(KEY[stream], payload)
    assert p.measurements == () and p.first_stamp_ns == p.last_stamp_ns == p.until_ns == until


def test_encoders_refuse_what_cannot_go_on_the_wire() -> None:
    t = _t()
    with pytest.raises(EncodeError):
        encode_odometer(OdometerEdges(np.zeros(0, np.int64)), 0)  # a heartbeat needs until_ns
    with pytest.raises(EncodeError):
        encode_sprockets([], 0)
    with pytest.raises(EncodeError):
        encode_odometer(OdometerEdges(t, np.ones(4, np.int8)), 0)
    with pytest.raises(EncodeError):
        encode_steering(SteeringAngles(t, np.zeros((5, 1))), 0)
    with pytest.raises(EncodeError):
        encode_wheel_speeds4(WheelSpeeds4(t, np.zeros((5, 2))), 0)
    with pytest.raises(EncodeError):
        encode_steering(SteeringAngles(t.astype(float), np.zeros(5)), 0)
    with pytest.raises(EncodeError):
        encode_wheel_speeds4(WheelSpeeds4(t, np.zeros((5, 4))), -1)


# ------------------------------------------------------------------------- refusals

BACK = _i8(T0, T0 + 2, T0 + 1)  # edges going backwards
SAME = _i8(T0, T0, T0 + 1)  # samples must strictly increase
ANCIENT = _i8(T0 // 100, T0 // 100 + 1, T0 // 100 + 2)
INF, NAN = float("inf"), float("nan")
# (stream, how the valid payload is changed, reason)
REFUSALS: list[tuple[Stream, dict[str, Any], str]] = [
    (Stream.ODOMETER, {"stamp_ns": None}, "missing_field"),
    (Stream.ODOMETER, {"stamp_ns": [1, 2]}, "wrong_type"),
    (Stream.ODOMETER, {"stamp_ns": b"\0" * 12}, "wrong_shape"),
    (Stream.ODOMETER, {"stamp_ns": b""}, "wrong_shape"),  # empty, and no until_ns
    (Stream.ODOMETER, {"stamp_ns": BACK, "direction": None}, "non_monotonic"),
    (Stream.ODOMETER, {"stamp_ns": ANCIENT, "direction": None}, "out_of_range"),
    (Stream.ODOMETER, {"direction": b"\x01\x00\x01\x01\x01"}, "out_of_range"),
    (Stream.ODOMETER, {"direction": b"\x01\x01"}, "wrong_shape"),
    (Stream.ODOMETER, {"direction": 1}, "wrong_type"),
    (Stream.ODOMETER, {"stamp_ns": b"\0" * 8 * (LIMITS.max_batch + 1)}, "oversize"),
    (Stream.SPROCKETS, {"edges": None}, "missing_field"),
    (Stream.SPROCKETS, {"edges": [], "until_ns": None}, "wrong_type"),  # not a heartbeat
    (Stream.SPROCKETS, {"edges": "left"}, "wrong_type"),
    (Stream.SPROCKETS, {"edges": [1]}, "wrong_type"),
    (Stream.STEERING, {"angle_rad": None}, "missing_field"),
    (Stream.STEERING, {"angle_rad": 0.5}, "wrong_type"),
    (Stream.STEERING, {"angle_rad": _f8([0.1] * 4)}, "wrong_shape"),
    (Stream.STEERING, {"angle_rad": _f8([0.1, INF, 0.1, 0.1, 0.1])}, "non_finite"),
    (Stream.STEERING, {"angle_rad": _f8([0.1, 0.1, 0.1, 0.1, 19.0])}, "out_of_range"),
    (Stream.STEERING, {"stamp_ns": SAME, "angle_rad": _f8([0.0] * 3)}, "non_monotonic"),
    (Stream.WHEEL_SPEEDS4, {"omega_radps": _f8(np.ones((5, 2)))}, "wrong_shape"),
    (Stream.WHEEL_SPEEDS4, {"omega_radps": _f8(np.ones(19))}, "wrong_shape"),
    (Stream.WHEEL_SPEEDS4, {"omega_radps": _f8(np.full((5, 4), -INF))}, "non_finite"),
    (Stream.WHEEL_SPEEDS4, {"omega_radps": _f8(np.full((5, 4), 501.0))}, "out_of_range"),
    (
        Stream.WHEEL_SPEEDS4,
        {"stamp_ns": BACK, "omega_radps": _f8(np.ones((3, 4)))},
        "non_monotonic",
    ),
    (Stream.WHEEL_SPEEDS4, {"until_ns": T0}, "out_of_range"),  # before its last sample
    (Stream.WHEEL_SPEEDS4, {"sensor": "steering"}, "key_mismatch"),
]
ENTRY_REFUSALS: list[tuple[dict[str, Any], str]] = [
    ({"side": None}, "missing_field"),
    ({"side": "left"}, "wrong_type"),
    ({"side": 2}, "out_of_range"),
    ({"side": 1}, "out_of_range"),  # both entries the right track
    ({"stamp_ns": BACK}, "non_monotonic"),
    ({"direction": b"\x01\x01\x01\x01\x02"}, "out_of_range"),
    ({"direction": b"\x01"}, "wrong_shape"),
]


@pytest.mark.parametrize(("stream", "fields", "reason"), REFUSALS)
def test_each_refusal_has_its_reason(stream: Stream, fields: dict[str, Any], reason: str) -> None:
    assert _reason(stream, _with(_valid(stream), **fields)) == reason


@pytest.mark.parametrize(("fields", "reason"), ENTRY_REFUSALS)
def test_each_sprocket_entry_refusal_has_its_reason(fields: dict[str, Any], reason: str) -> None:
    assert _reason(Stream.SPROCKETS, _entry(_valid(Stream.SPROCKETS), **fields)) == reason


def test_nan_speeds_and_angles_pass_as_not_available() -> None:
    omega = np.ones((5, 4))
    omega[2, Corner.FRONT_RIGHT] = NAN
    payload = _with(_valid(Stream.WHEEL_SPEEDS4), omega_radps=_f8(omega))
    (m,) = decode(KEY[Stream.WHEEL_SPEEDS4], payload).measurements
    assert isinstance(m, WheelSpeeds4) and np.isnan(m.omega_radps[2, 1])


# ------------------------------------------------------------------------- burst and registry


def test_burst_decodes_the_new_streams_as_the_codec_does(monkeypatch: pytest.MonkeyPatch) -> None:
    """Valid packets of each new stream, heartbeats, and every refusal above, in one burst."""
    monkeypatch.setattr(burst, "MIN_BATCHED", 1)
    received = [(KEY[s], _valid(s, seq, T0 + seq * 10**8)) for seq in range(3) for s in NEW]
    received += [
        (KEY[Stream.SPROCKETS], encode_sprockets([], 9, until_ns=T0 + 10**9)),
        (KEY[Stream.ODOMETER], encode_odometer(OdometerEdges(_t(0)), 9, until_ns=T0 + 10**9)),
    ]
    received += [(KEY[s], _with(_valid(s, 20), **f)) for s, f, _ in REFUSALS]
    received += [
        (KEY[Stream.SPROCKETS], _entry(_valid(Stream.SPROCKETS, 30), **f))
        for f, _ in ENTRY_REFUSALS
    ]
    got = assert_burst_matches(received)
    assert sum(isinstance(item, Packet) for item in got) == 3 * len(NEW) + 2
    reasons = [reason for *_, reason in REFUSALS] + [reason for _, reason in ENTRY_REFUSALS]
    assert [item.reason for item in got if isinstance(item, DecodeError)] == reasons
    assert len(decode_burst(received)) == len(received)


def test_every_stream_is_declared_once_with_its_wire_struct() -> None:
    assert set(STREAMS) == set(Stream)
    assert len({spec.priority for spec in STREAMS.values()}) == len(Stream)
    for stream in Stream:
        spec = spec_of(stream.value)
        assert spec.stream is stream and spec_of(stream) is spec
        payload = _valid(stream) if stream in NEW else None
        if payload is not None:  # the fast path's struct is the stream's
            assert type(DECODER.decode(payload)) is spec.wire
            assert {type(m) for m in decode(KEY[stream], payload).measurements} <= set(
                spec.measurements
            )
    cumulative = {s for s, spec in STREAMS.items() if spec.cumulative}
    assert cumulative == {Stream.WHEELS, Stream.ODOMETER, Stream.SPROCKETS}
