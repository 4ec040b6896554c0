"""Codec: round trips (hypothesis) and every DecodeError reason."""

from __future__ import annotations

import json
import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.config import (
    ChassisConfig,
    DrivenAxle,
    OdometerConfig,
    TrackedConfig,
    VehicleConfig,
    VehicleGeometry,
    Wheeled4wdSteeredConfig,
    WheeledRearDriveConfig,
)
from estimator.types import GnssFix, GnssSample, ImuBatch, Wheel, WheelEdges, WheelSpeeds
from server.protocol import (
    LIMITS,
    REASONS,
    DecodeError,
    EncodeError,
    Stream,
    decode,
    decode_config,
    encode_config,
    encode_gnss,
    encode_imu,
    encode_wheel_edges,
    encode_wheel_speeds,
    sensor_key,
)
from tests.server.protocol.payloads import edited

T0 = 1_763_700_000 * 10**9  # 2025-11-21, vehicle clock
KEY = {s: sensor_key("fleet", "veh-1", s) for s in Stream}

stamps_start = st.integers(LIMITS.min_stamp_ns, LIMITS.max_stamp_ns - 10**12)


def _imu(n: int, t0: int = T0) -> ImuBatch:
    t = t0 + np.arange(n, dtype=np.int64) * 10_000_000
    acc = np.tile([0.1, 0.5, 9.81], (n, 1))
    gyr = np.tile([0.01, 0.0, -0.2], (n, 1))
    return ImuBatch(t, acc, gyr)


def _gnss(**kw: object) -> GnssSample:
    base: dict[str, object] = {
        "stamp_ns": T0,
        "vel_enu_mps": (1.0, 2.0, 0.0),
        "heading_rad": 0.4,
        "pitch_rad": 0.01,
        "roll_rad": -0.02,
        "lat_deg": 48.1,
        "lon_deg": 11.5,
        "height_m": 520.0,
    }
    base.update(kw)
    return GnssSample(**base)  # type: ignore[arg-type]


def _raw(stream: Stream, **fields: object) -> bytes:
    """A hand-built payload: start from a valid one and override or delete (value None) fields."""
    valid = {
        Stream.GNSS: encode_gnss(_gnss(), 0),
        Stream.IMU: encode_imu(_imu(3), 0),
        Stream.WHEELS: encode_wheel_speeds(
            WheelSpeeds(T0 + np.arange(2, dtype=np.int64), np.ones((2, 2))), 0
        ),
    }[stream]
    return edited(valid, fields)


def _reason(key: str, payload: bytes) -> str:
    with pytest.raises(DecodeError) as info:
        decode(key, payload)
    assert info.value.reason in REASONS
    return info.value.reason


# ------------------------------------------------------------------------- round trips

finite = st.floats(-50, 50, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    t0=stamps_start,
    n=st.integers(1, 40),
    seq=st.integers(0, 2**63 - 1),
    scale=st.floats(-15, 15, allow_nan=False),
)
def test_imu_round_trip(t0: int, n: int, seq: int, scale: float) -> None:
    rng = np.random.default_rng(n)
    t = t0 + np.cumsum(rng.integers(1, 10**8, n))
    acc = rng.uniform(-1, 1, (n, 3)) * scale
    gyr = rng.uniform(-1, 1, (n, 3)) * scale / 2
    p = decode(KEY[Stream.IMU], encode_imu(ImuBatch(t, acc, gyr), seq))
    (m,) = p.measurements
    assert isinstance(m, ImuBatch)
    assert (p.vehicle_id, p.stream, p.seq, p.schema_version) == ("veh-1", Stream.IMU, seq, 1)
    np.testing.assert_array_equal(m.stamp_ns, t)
    np.testing.assert_array_equal(m.accel_mps2, acc)
    np.testing.assert_array_equal(m.gyro_radps, gyr)
    assert m.stamp_ns.dtype == np.int64 and m.accel_mps2.shape == (n, 3)
    assert (p.first_stamp_ns, p.last_stamp_ns) == (int(t[0]), int(t[-1]))


@settings(max_examples=60, deadline=None)
@given(
    t=stamps_start,
    vel=st.tuples(finite, finite, st.floats(-5, 5)),
    heading=st.floats(-6.28, 6.28) | st.just(math.nan),
    lat=st.floats(-90, 90),
    lon=st.floats(-180, 180),
    fix=st.sampled_from(list(GnssFix)),
    std=st.floats(0, 10) | st.just(math.nan),
)
def test_gnss_round_trip(
    t: int,
    vel: tuple[float, float, float],
    heading: float,
    lat: float,
    lon: float,
    fix: GnssFix,
    std: float,
) -> None:
    g = _gnss(stamp_ns=t, vel_enu_mps=vel, heading_rad=heading, lat_deg=lat, lon_deg=lon)
    g = GnssSample(**{**{f: getattr(g, f) for f in g.__slots__}, "fix": fix, "vel_std_mps": std})
    p = decode(KEY[Stream.GNSS], encode_gnss(g, 7))
    (m,) = p.measurements
    assert isinstance(m, GnssSample)
    for f in g.__slots__:
        a, b = getattr(g, f), getattr(m, f)
        assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), f
    assert m.fix is fix
    assert p.first_stamp_ns == p.last_stamp_ns == t


@settings(max_examples=60, deadline=None)
@given(
    t0=stamps_start,
    n_left=st.integers(1, 50),
    n_right=st.integers(0, 50),
    with_direction=st.booleans(),
)
def test_wheel_edges_round_trip(t0: int, n_left: int, n_right: int, with_direction: bool) -> None:
    rng = np.random.default_rng(n_left * 100 + n_right)
    edges = []
    for wheel, n in ((Wheel.LEFT, n_left), (Wheel.RIGHT, n_right)):
        if n == 0:
            continue
        t = t0 + np.cumsum(rng.integers(0, 10**7, n))  # equal neighbours allowed
        d = rng.choice(np.array([-1, 1], dtype=np.int8), n) if with_direction else None
        edges.append(WheelEdges(wheel, t, d))
    p = decode(KEY[Stream.WHEELS], encode_wheel_edges(edges, 3))
    assert len(p.measurements) == len(edges)
    for sent, got in zip(edges, p.measurements, strict=True):
        assert isinstance(got, WheelEdges)
        assert got.wheel is sent.wheel
        np.testing.assert_array_equal(got.stamp_ns, sent.stamp_ns)
        if sent.direction is None:
            assert got.direction is None
        else:
            assert got.direction is not None and got.direction.dtype == np.int8
            np.testing.assert_array_equal(got.direction, sent.direction)
    assert p.first_stamp_ns == min(int(e.stamp_ns[0]) for e in edges)
    assert p.last_stamp_ns == max(int(e.stamp_ns[-1]) for e in edges)


@settings(max_examples=40, deadline=None)
@given(t0=stamps_start, n=st.integers(1, 30), omega=st.floats(-400, 400))
def test_wheel_speeds_round_trip(t0: int, n: int, omega: float) -> None:
    t = t0 + np.arange(n, dtype=np.int64) * 20_000_000
    om = np.column_stack([np.full(n, omega), np.linspace(-omega, omega, n)])
    p = decode(KEY[Stream.WHEELS], encode_wheel_speeds(WheelSpeeds(t, om), 11))
    (m,) = p.measurements
    assert isinstance(m, WheelSpeeds)
    np.testing.assert_array_equal(m.stamp_ns, t)
    np.testing.assert_array_equal(m.omega_radps, om)


def test_decoded_arrays_are_zero_copy_views() -> None:
    p = decode(KEY[Stream.IMU], encode_imu(_imu(8), 0))
    (m,) = p.measurements
    assert isinstance(m, ImuBatch)
    assert not m.accel_mps2.flags.writeable  # a view of the payload, not a copy


@pytest.mark.parametrize(
    "cfg",
    [
        WheeledRearDriveConfig(geometry=VehicleGeometry(track_width_m=2.2), estimators=("mdsf",)),
        TrackedConfig(odometer=OdometerConfig(distance_per_edge_m=0.02)),
        Wheeled4wdSteeredConfig(chassis=ChassisConfig(mass_kg=1800.0, driven_axle=DrivenAxle.REAR)),
    ],
)
def test_config_round_trip(cfg: VehicleConfig) -> None:
    vid, got = decode_config("fleet/veh-1/config", encode_config(cfg))
    assert vid == "veh-1" and got == cfg and type(got) is type(cfg)


@pytest.mark.parametrize(
    ("body", "kind"),
    [
        ({}, WheeledRearDriveConfig),
        ({"kind": "tracked", "sprocket": {"pitch_radius_m": 0.4}}, TrackedConfig),
        ({"kind": "wheeled_4wd_steered", "tyre": {"kz_npm": 50000}}, Wheeled4wdSteeredConfig),
    ],
)
def test_config_of_each_kind_decodes(body: dict[str, Any], kind: type) -> None:
    _, got = decode_config("fleet/veh-1/config", json.dumps(body).encode())
    assert type(got) is kind


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ({"kind": "tracked", "encoder": {}}, "tracked: unknown field(s) ['encoder']"),
        ({"kind": "wheeled_4wd_steered", "tyre": {"kz_npm": 1}}, "tyre.kz_npm must be"),
        ({"noise": {"accel_std_mps2": 1e200}}, "1e-06..10 m/s²"),
    ],
)
def test_config_of_a_wrong_kind_is_refused_naming_the_field(
    body: dict[str, Any], words: str
) -> None:
    with pytest.raises(DecodeError) as info:
        decode_config("fleet/veh-1/config", json.dumps(body).encode())
    assert info.value.reason == "bad_config" and words in str(info.value)


def test_custom_prefix_with_slash() -> None:
    key = sensor_key("site/a", "veh-1", Stream.IMU)
    assert key == "site/a/veh-1/sensors/imu"
    assert decode(key, encode_imu(_imu(2), 0), prefix="site/a").vehicle_id == "veh-1"


# ------------------------------------------------------------------------- refusals


def test_reason_oversize() -> None:
    payload = encode_imu(_imu(400), 0)
    with pytest.raises(DecodeError) as info:
        decode(KEY[Stream.IMU], payload, max_payload_bytes=1024)
    assert info.value.reason == "oversize"
    assert info.value.vehicle_id == "veh-1" and info.value.stream is Stream.IMU


def test_reason_oversize_batch() -> None:
    n = LIMITS.max_batch + 1
    t = np.arange(n, dtype="<i8") + T0
    payload = _raw(Stream.IMU, stamp_ns=t.tobytes())
    with pytest.raises(DecodeError) as info:
        decode(KEY[Stream.IMU], payload, max_payload_bytes=10**7)
    assert info.value.reason == "oversize"


@pytest.mark.parametrize(
    "key",
    [
        "other/veh-1/sensors/imu",
        "fleet/veh-1/sensors/lidar",
        "fleet/veh-1/imu",
        "fleet/-bad/sensors/imu",
        "fleet/veh-1/config",
        "fleet/veh-1/sensors/imu/extra",
    ],
)
def test_reason_bad_key(key: str) -> None:
    assert _reason(key, encode_imu(_imu(2), 0)) == "bad_key"


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"\x93\x01", encode_imu(_imu(2), 0) + b"\x00"])
def test_reason_undecodable(payload: bytes) -> None:
    assert _reason(KEY[Stream.IMU], payload) == "undecodable"


def test_reason_undecodable_not_a_map() -> None:
    assert _reason(KEY[Stream.IMU], msgpack.packb([1, 2, 3])) == "undecodable"


@pytest.mark.parametrize("v", [None, 2, 0, "1", 1.0])
def test_reason_schema_version(v: object) -> None:
    assert _reason(KEY[Stream.IMU], _raw(Stream.IMU, v=v)) == "schema_version"


def test_reason_key_mismatch() -> None:
    assert _reason(KEY[Stream.GNSS], encode_imu(_imu(2), 0)) == "key_mismatch"


@pytest.mark.parametrize(
    ("stream", "field"),
    [
        (Stream.IMU, "seq"),
        (Stream.IMU, "stamp_ns"),
        (Stream.IMU, "gyro_radps"),
        (Stream.IMU, "sensor"),
        (Stream.GNSS, "vel_enu_mps"),
        (Stream.GNSS, "lat_deg"),
        (Stream.WHEELS, "mode"),
        (Stream.WHEELS, "omega_radps"),
    ],
)
def test_reason_missing_field(stream: Stream, field: str) -> None:
    assert _reason(KEY[stream], _raw(stream, **{field: None})) == "missing_field"


@pytest.mark.parametrize(
    ("stream", "fields"),
    [
        (Stream.IMU, {"seq": "1"}),
        (Stream.IMU, {"seq": 1.5}),
        (Stream.IMU, {"stamp_ns": [1, 2, 3]}),
        (Stream.GNSS, {"stamp_ns": 1.0e18}),
        (Stream.GNSS, {"vel_enu_mps": [1.0, 2.0]}),
        (Stream.GNSS, {"heading_rad": "north"}),
        (Stream.GNSS, {"fix": 3}),
        (Stream.WHEELS, {"mode": "pulses"}),
        (Stream.WHEELS, {"mode": "edges", "edges": "x"}),
        (Stream.WHEELS, {"mode": "edges", "edges": [1]}),
    ],
)
def test_reason_wrong_type(stream: Stream, fields: dict[str, object]) -> None:
    assert _reason(KEY[stream], _raw(stream, **fields)) == "wrong_type"


@pytest.mark.parametrize(
    "fields",
    [
        {"stamp_ns": b"\x00" * 12},  # not a multiple of 8 bytes
        {"stamp_ns": b""},  # empty batch
        {"accel_mps2": np.zeros((2, 3)).tobytes()},  # 2 rows for 3 stamps
        {"gyro_radps": np.zeros(10).tobytes()},  # not a multiple of 3 x 8 bytes
    ],
)
def test_reason_wrong_shape(fields: dict[str, object]) -> None:
    assert _reason(KEY[Stream.IMU], _raw(Stream.IMU, **fields)) == "wrong_shape"


def test_reason_wrong_shape_direction() -> None:
    e = WheelEdges(Wheel.LEFT, T0 + np.arange(3, dtype=np.int64))
    m = msgpack.unpackb(encode_wheel_edges([e], 0), raw=False)
    m["edges"][0]["direction"] = np.ones(2, np.int8).tobytes()
    assert _reason(KEY[Stream.WHEELS], msgpack.packb(m)) == "wrong_shape"


@pytest.mark.parametrize(
    ("stream", "payload"),
    [
        (Stream.GNSS, encode_gnss(_gnss(vel_enu_mps=(math.inf, 0.0, 0.0)), 0)),
        (Stream.GNSS, encode_gnss(_gnss(heading_rad=math.inf), 0)),
        (Stream.GNSS, encode_gnss(_gnss(lat_deg=-math.inf), 0)),
        (
            Stream.IMU,
            encode_imu(ImuBatch(T0 + np.arange(2), np.full((2, 3), -np.inf), np.zeros((2, 3))), 0),
        ),
        (
            Stream.WHEELS,
            encode_wheel_speeds(WheelSpeeds(T0 + np.arange(2), np.full((2, 2), np.inf)), 0),
        ),
    ],
)
def test_reason_non_finite(stream: Stream, payload: bytes) -> None:
    assert _reason(KEY[stream], payload) == "non_finite"


def _imu_with(acc: float = 9.81, gyr: float = 0.0) -> bytes:
    a = np.array([[0.0, 0.0, acc]] * 2)
    g = np.array([[0.0, 0.0, gyr]] * 2)
    return encode_imu(ImuBatch(T0 + np.arange(2), a, g), 0)


@pytest.mark.parametrize(
    ("stream", "payload"),
    [
        (Stream.GNSS, encode_gnss(_gnss(vel_enu_mps=(80.0, 80.0, 0.0)), 0)),  # 113 m/s
        (Stream.GNSS, encode_gnss(_gnss(lat_deg=91.0), 0)),
        (Stream.GNSS, encode_gnss(_gnss(height_m=-5000.0), 0)),
        (Stream.GNSS, encode_gnss(_gnss(pitch_rad=2.0), 0)),
        (Stream.GNSS, encode_gnss(_gnss(stamp_ns=10**15), 0)),  # 1970: not a vehicle clock
        (Stream.GNSS, encode_gnss(_gnss(vel_std_mps=-1.0), 0)),
        (Stream.IMU, _imu_with(acc=25 * 9.81)),
        (Stream.IMU, _imu_with(gyr=21.0)),
        (
            Stream.WHEELS,
            encode_wheel_speeds(WheelSpeeds(T0 + np.arange(2), np.full((2, 2), 900.0)), 0),
        ),
        (
            Stream.WHEELS,
            encode_wheel_edges(
                [WheelEdges(Wheel.LEFT, T0 + np.arange(2), np.zeros(2, np.int8))], 0
            ),
        ),
    ],
)
def test_reason_out_of_range(stream: Stream, payload: bytes) -> None:
    assert _reason(KEY[stream], payload) == "out_of_range"


def test_reason_out_of_range_repeated_wheel() -> None:
    e = WheelEdges(Wheel.LEFT, T0 + np.arange(2, dtype=np.int64))
    assert _reason(KEY[Stream.WHEELS], encode_wheel_edges([e, e], 0)) == "out_of_range"


def test_nan_means_not_available_and_passes() -> None:
    g = _gnss(vel_enu_mps=(math.nan, math.nan, math.nan), fix=GnssFix.NONE, lat_deg=math.nan)
    (m,) = decode(KEY[Stream.GNSS], encode_gnss(g, 0)).measurements
    assert isinstance(m, GnssSample) and math.isnan(m.vel_enu_mps[0]) and m.fix is GnssFix.NONE
    acc = np.array([[np.nan, 0.2, 9.8], [0.0, 0.1, 9.8]])
    (b,) = decode(
        KEY[Stream.IMU], encode_imu(ImuBatch(T0 + np.arange(2), acc, acc / 10), 0)
    ).measurements
    assert isinstance(b, ImuBatch) and np.isnan(b.accel_mps2[0, 0])


def test_single_sample_batch_is_fine() -> None:
    assert decode(KEY[Stream.IMU], encode_imu(_imu(1), 0)).first_stamp_ns == T0


def test_reason_non_monotonic() -> None:
    t = np.array([T0, T0 + 5, T0 + 5], dtype=np.int64)  # IMU must strictly increase
    payload = encode_imu(ImuBatch(t, np.zeros((3, 3)), np.zeros((3, 3))), 0)
    assert _reason(KEY[Stream.IMU], payload) == "non_monotonic"
    # edges may repeat a time (two edges in one clock tick) but never go back
    ok = encode_wheel_edges([WheelEdges(Wheel.RIGHT, t)], 0)
    assert decode(KEY[Stream.WHEELS], ok).last_stamp_ns == T0 + 5
    back = encode_wheel_edges([WheelEdges(Wheel.RIGHT, t[::-1].copy())], 0)
    assert _reason(KEY[Stream.WHEELS], back) == "non_monotonic"


@pytest.mark.parametrize(
    "payload",
    [b"{", b"\xff\xfe", b'{"kind": "hovercraft"}', b'{"geometry": {"h0_m": -1}}', b"[]"],
)
def test_config_refusals(payload: bytes) -> None:
    with pytest.raises(DecodeError) as info:
        decode_config("fleet/veh-1/config", payload)
    assert info.value.reason in {"undecodable", "bad_config"}
    with pytest.raises(DecodeError) as info:
        decode_config("fleet/veh-1/sensors/imu", b"{}")
    assert info.value.reason == "bad_key"


def test_every_reason_is_exercised() -> None:
    """REASONS lists exactly what this file checks (keeps the docs' table honest)."""
    checked = {
        "oversize",
        "bad_key",
        "undecodable",
        "schema_version",
        "key_mismatch",
        "missing_field",
        "wrong_type",
        "wrong_shape",
        "non_finite",
        "out_of_range",
        "non_monotonic",
        "bad_config",
    }
    assert set(REASONS) == checked


def test_encode_errors() -> None:
    with pytest.raises(EncodeError):
        encode_imu(_imu(2), -1)
    with pytest.raises(EncodeError):
        encode_imu(ImuBatch(np.arange(3) + T0, np.zeros((2, 3)), np.zeros((3, 3))), 0)
    with pytest.raises(EncodeError):
        floats: Any = np.arange(3.0)  # float seconds are refused: stamps are int ns
        encode_wheel_speeds(WheelSpeeds(floats, np.zeros((3, 2))), 0)


# ------------------------------------------------------------------------- until_ns


@pytest.mark.parametrize("ahead_ns", [0, 1, 97_999_999, LIMITS.max_until_ahead_ns])
def test_until_round_trips_and_is_optional(ahead_ns: int) -> None:
    batch = _imu(10)
    last = int(batch.stamp_ns[-1])
    p = decode(KEY[Stream.IMU], encode_imu(batch, 4, last + ahead_ns))
    assert p.until_ns == last + ahead_ns
    assert p.covers_ns == last + ahead_ns
    plain = decode(KEY[Stream.IMU], encode_imu(batch, 4))
    assert plain.until_ns is None
    assert plain.covers_ns == last
    g = decode(KEY[Stream.GNSS], encode_gnss(_gnss(), 0, T0 + 99_999_999))
    assert g.until_ns == T0 + 99_999_999


@pytest.mark.parametrize(
    ("until", "reason"),
    [
        (T0 + 19_999_999, "out_of_range"),  # before the batch's last sample (T0 + 20 ms)
        (T0 + 20_000_000 + LIMITS.max_until_ahead_ns + 1, "out_of_range"),
        (1.5e18, "wrong_type"),
        ("soon", "wrong_type"),
    ],
)
def test_reason_until_outside_its_range(until: object, reason: str) -> None:
    assert _reason(KEY[Stream.IMU], _raw(Stream.IMU, until_ns=until)) == reason


def test_encode_refuses_a_bad_until() -> None:
    with pytest.raises(EncodeError):
        encode_imu(_imu(2), 0, -1)
    with pytest.raises(EncodeError):
        bad: Any = 1.0e18
        encode_gnss(_gnss(), 0, bad)


def test_wheel_heartbeat_is_edges_without_entries_and_needs_until() -> None:
    """A window without an edge on either wheel: ``"edges": []`` and ``until_ns``."""
    hb = decode(KEY[Stream.WHEELS], encode_wheel_edges([], 9, T0 + 99_999_999))
    assert hb.measurements == () and hb.seq == 9
    assert hb.first_stamp_ns == hb.last_stamp_ns == hb.until_ns == T0 + 99_999_999
    # wheels without edges are left out of a packet that has some
    empty = WheelEdges(Wheel.LEFT, np.zeros(0, dtype=np.int64))
    right = WheelEdges(Wheel.RIGHT, T0 + np.arange(3, dtype=np.int64))
    (only,) = decode(KEY[Stream.WHEELS], encode_wheel_edges([empty, right], 0)).measurements
    assert isinstance(only, WheelEdges) and only.wheel is Wheel.RIGHT
    with pytest.raises(EncodeError):
        encode_wheel_edges([empty], 0)  # nothing to say without until_ns
    no_until = msgpack.unpackb(encode_wheel_edges([], 0, T0), raw=False)
    del no_until["until_ns"]
    assert _reason(KEY[Stream.WHEELS], msgpack.packb(no_until)) == "wrong_type"
    bad = msgpack.unpackb(encode_wheel_edges([], 0, T0), raw=False)
    bad["until_ns"] = 10**15  # 1970: not a vehicle clock
    assert _reason(KEY[Stream.WHEELS], msgpack.packb(bad)) == "out_of_range"


# ------------------------------------------------------------------------- GNSS fast check

_GNSS_FLOATS = ("heading_rad", "pitch_rad", "roll_rad", "lat_deg", "lon_deg", "height_m")
#: values a GNSS field may be given: valid ones, edge cases and wrong types
_ODD = st.sampled_from(
    [
        0,
        1,
        True,
        -1.0,
        2.0,
        4.0,
        7.0,
        95.0,
        200.0,
        -2000.0,
        30_000.0,
        math.nan,
        math.inf,
        -math.inf,
        "1.0",
        None,
        [1.0],
    ]
)


@settings(max_examples=400, deadline=None)
@given(
    changes=st.dictionaries(
        st.sampled_from([*_GNSS_FLOATS, "stamp_ns", "fix", "vel_std_mps", "vel_enu_mps"]),
        _ODD | st.lists(_ODD, min_size=2, max_size=4),
        max_size=3,
    ),
    drop=st.sets(st.sampled_from(["fix", "vel_std_mps", "heading_rad"]), max_size=2),
)
def test_gnss_fast_check_agrees_with_the_field_rules(
    changes: dict[str, Any], drop: set[str]
) -> None:
    """The one-expression check accepts only what the field-by-field rules accept, with the
    same values; what it leaves to them (None) they accept or refuse."""
    from server.protocol.base import Ctx as _Ctx
    from server.protocol.sensors import gnss_checked as _gnss_checked
    from server.protocol.sensors import gnss_sample as _gnss_sample

    m: dict[str, Any] = msgpack.unpackb(encode_gnss(_gnss(vel_std_mps=0.05), 3), raw=False)
    m.update(changes)
    for k in drop:
        m.pop(k, None)
    fast = _gnss_sample(m, LIMITS)
    try:
        checked = _gnss_checked(_Ctx("veh-1", Stream.GNSS), m, LIMITS)
    except DecodeError:
        assert fast is None
        return
    if fast is not None:
        assert type(fast) is GnssSample
        for f in GnssSample.__slots__:
            a, b = getattr(fast, f), getattr(checked, f)
            assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), f
            assert type(a) is type(b), f


def test_gnss_fast_check_takes_the_usual_packet_and_nan_attitude() -> None:
    from server.protocol.sensors import gnss_sample as _gnss_sample

    usual = msgpack.unpackb(encode_gnss(_gnss(vel_std_mps=0.05), 3), raw=False)
    assert _gnss_sample(usual, LIMITS) is not None
    no_attitude = {**usual, "heading_rad": math.nan, "pitch_rad": math.nan, "roll_rad": math.nan}
    assert _gnss_sample(no_attitude, LIMITS) is not None
    assert _gnss_sample({**usual, "heading_rad": math.inf}, LIMITS) is None


@pytest.mark.parametrize(
    ("fields", "reason"),
    [
        ({"v": True}, "schema_version"),  # True == 1, but not an integer version
        ({"v": 1.0}, "schema_version"),
        ({"seq": True}, "wrong_type"),
        ({"seq": -1}, "out_of_range"),
        ({"seq": 2**63}, "out_of_range"),
        ({"sensor": "IMU"}, "key_mismatch"),
        ({"sensor": 1}, "key_mismatch"),
    ],
)
def test_header_values_the_one_expression_check_must_not_take(
    fields: dict[str, object], reason: str
) -> None:
    """The usual header is checked in one expression; values next to valid ones still get
    the field rules' reason."""
    assert _reason(KEY[Stream.IMU], _raw(Stream.IMU, **fields)) == reason


@pytest.mark.parametrize("vel", [(1.0, 2.0, 0.0), (-3.5, 0.25, 0.125), (math.nan,) * 3])
def test_gnss_velocity_as_bin_equals_velocity_as_array(vel: tuple[float, float, float]) -> None:
    """``vel_enu_mps`` may travel as a msgpack array of 3 numbers or, like every other array,
    as a ``bin`` of 3 little-endian float64: both decode to the same sample."""
    as_bin = _raw(Stream.GNSS, vel_enu_mps=np.asarray(vel, dtype="<f8").tobytes())
    as_array = _raw(Stream.GNSS, vel_enu_mps=list(vel))
    got_bin = decode(KEY[Stream.GNSS], as_bin).measurements[0]
    got_array = decode(KEY[Stream.GNSS], as_array).measurements[0]
    assert isinstance(got_bin, GnssSample) and isinstance(got_array, GnssSample)
    np.testing.assert_array_equal(got_bin.vel_enu_mps, vel)
    assert all(type(x) is float for x in got_bin.vel_enu_mps)
    assert repr(got_bin) == repr(got_array)  # NaN fields compare unequal; their text does not


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (np.zeros(2, dtype="<f8").tobytes(), "wrong_shape"),
        (np.zeros(4, dtype="<f8").tobytes(), "wrong_shape"),
        (b"\x00" * 23, "wrong_shape"),
        (np.array([np.inf, 0.0, 0.0], dtype="<f8").tobytes(), "non_finite"),
        (np.array([200.0, 0.0, 0.0], dtype="<f8").tobytes(), "out_of_range"),
    ],
)
def test_gnss_velocity_as_bin_is_checked(raw: bytes, reason: str) -> None:
    assert _reason(KEY[Stream.GNSS], _raw(Stream.GNSS, vel_enu_mps=raw)) == reason
