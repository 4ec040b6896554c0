"""Encode and decode the wire payloads (pure: no I/O, no Zenoh). See ``docs/protocol.md``.

A payload is one msgpack map. Every payload carries the header ``v`` (schema version),
``sensor`` (the stream, which must match the key) and ``seq`` (per-stream sequence number);
numeric arrays travel as msgpack *bin* values holding packed little-endian numbers, so decoding
is ``numpy.frombuffer`` and the resulting arrays are read-only views of the payload.

A float that is NaN means "not available" (GNSS velocity without a fix, a dead IMU axis) and is
passed on: the estimators skip and count it. Infinities, impossible magnitudes and timestamps
that go back are refused here.

Exceptions::

    ValueError
     └── ProtocolError           anything this module refuses
          ├── EncodeError        the measurement cannot be put on the wire (shape, dtype, seq)
          └── DecodeError        a received packet is refused; ``.reason`` is one of REASONS

:class:`DecodeError` carries a short machine ``reason`` (used as a counter name), a human
``detail``, and the ``vehicle_id`` / ``stream`` when the key could be parsed.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from estimator._frozen import builder
from estimator.base import Measurement
from estimator.config import ConfigError, VehicleConfig, vehicle_config_from_dict
from estimator.types import GnssFix, GnssSample, ImuBatch, Wheel, WheelEdges, WheelSpeeds
from server.protocol.keys import Stream, parse_key

__all__ = [
    "LIMITS",
    "REASONS",
    "SCHEMA_VERSION",
    "DecodeError",
    "EncodeError",
    "Limits",
    "Packet",
    "ProtocolError",
    "decode",
    "decode_config",
    "encode_config",
    "encode_gnss",
    "encode_imu",
    "encode_wheel_edges",
    "encode_wheel_speeds",
]

SCHEMA_VERSION = 1

#: Every reason a :class:`DecodeError` can carry (counter names).
REASONS: tuple[str, ...] = (
    "oversize",  # payload larger than max_payload_bytes, or a batch longer than max_batch
    "bad_key",  # key is not <prefix>/<vehicle_id>/sensors/<gnss|imu|wheels> (or /config)
    "undecodable",  # not one msgpack map (or not JSON for a config)
    "schema_version",  # 'v' missing or not a supported version
    "key_mismatch",  # 'sensor' in the payload differs from the key's stream
    "missing_field",
    "wrong_type",  # a field has the wrong msgpack type, or an unknown enum value
    "wrong_shape",  # array byte length / lengths disagree, or an empty batch
    "non_finite",  # +-inf anywhere (NaN means "not available" and passes to the estimators)
    "out_of_range",  # physically impossible value
    "non_monotonic",  # timestamps in a batch do not increase
    "bad_config",  # a config payload that VehicleConfig refuses
)


@dataclass(frozen=True, slots=True)
class Limits:
    """Physical plausibility bounds a packet must respect (units in the names)."""

    max_speed_mps: float = 100.0
    max_gyro_radps: float = 20.0  # per-sample norm
    max_accel_mps2: float = 20.0 * 9.80665  # per-sample norm of the specific force
    max_wheel_omega_radps: float = 500.0
    min_stamp_ns: int = 946_684_800 * 10**9  # 2000-01-01T00:00:00Z
    max_stamp_ns: int = 4_102_444_800 * 10**9  # 2100-01-01T00:00:00Z
    max_batch: int = 65_536  # samples or edges in one packet
    max_until_ahead_ns: int = 5_000_000_000  # until_ns at most this far past the last sample
    max_height_m: float = 20_000.0
    min_height_m: float = -1_000.0


LIMITS = Limits()

# packed little-endian arrays are native here: frombuffer views need no conversion
_LITTLE_ENDIAN = sys.byteorder == "little"
_WHEEL = {int(w): w for w in Wheel}
_GNSS_FIX = {int(f): f for f in GnssFix}


class ProtocolError(ValueError):
    """Anything the codec refuses."""


class EncodeError(ProtocolError):
    """A measurement cannot be encoded (wrong shape or dtype, negative sequence number)."""


class DecodeError(ProtocolError):
    """A received packet is refused.

    Attributes
    ----------
    reason : str
        One of :data:`REASONS`.
    detail : str
        Human explanation.
    vehicle_id : str or None
        From the key, when it could be parsed.
    stream : Stream or None
    """

    def __init__(
        self,
        reason: str,
        detail: str = "",
        *,
        vehicle_id: str | None = None,
        stream: Stream | None = None,
    ) -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail
        self.vehicle_id = vehicle_id
        self.stream = stream


@dataclass(frozen=True, slots=True)
class Packet:
    """One decoded sensor packet.

    Attributes
    ----------
    vehicle_id : str
    stream : Stream
    seq : int
        Per-(vehicle, stream) sequence number.
    schema_version : int
    measurements : tuple of Measurement
        One ``GnssSample``, one ``ImuBatch``, one ``WheelSpeeds``, or one ``WheelEdges`` per
        wheel present in the packet.
    first_stamp_ns, last_stamp_ns : int
        Earliest and latest sample time in the packet (vehicle clock).
    until_ns : int or None
        The sender's promise that every sample of this stream stamped at or before it is in
        this packet or an earlier one (the end of the batch window); ``None`` if not given.
        A wheels packet may be a *heartbeat*: no measurements, only ``until_ns`` (no edge on
        either wheel up to it); its first and last stamps are ``until_ns``.
    """

    vehicle_id: str
    stream: Stream
    seq: int
    schema_version: int
    measurements: tuple[Measurement, ...]
    first_stamp_ns: int
    last_stamp_ns: int
    until_ns: int | None = None

    @property
    def covers_ns(self) -> int:
        """Sensor time up to which this stream is complete once this packet is in: ``until_ns``
        when the sender gave it, else the last sample time."""
        return self.last_stamp_ns if self.until_ns is None else self.until_ns


# ---------------------------------------------------------------------------------------------
# encoding


def _seq(seq: int) -> int:
    if not isinstance(seq, int | np.integer) or not 0 <= int(seq) < 2**63:
        raise EncodeError(f"seq must be an int in [0, 2**63), got {seq!r}")
    return int(seq)


def _i8(a: Any, n: int | None = None, name: str = "stamp_ns") -> bytes:
    arr = np.asarray(a)
    if arr.ndim != 1 or (n is not None and arr.shape[0] != n):
        raise EncodeError(f"{name} must have shape ({n if n is not None else 'n'},)")
    if arr.size and arr.dtype.kind not in "iu":
        raise EncodeError(f"{name} must be integers (int64 nanoseconds)")
    return np.ascontiguousarray(arr, dtype="<i8").tobytes()


def _f8(a: Any, shape: tuple[int, int], name: str) -> bytes:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape != shape:
        raise EncodeError(f"{name} must have shape {shape}, got {arr.shape}")
    return np.ascontiguousarray(arr, dtype="<f8").tobytes()


def _pack(obj: dict[str, Any], until_ns: int | None = None) -> bytes:
    if until_ns is not None:
        if not isinstance(until_ns, int | np.integer) or not 0 <= int(until_ns) < 2**63:
            raise EncodeError(f"until_ns must be an int in [0, 2**63), got {until_ns!r}")
        obj["until_ns"] = int(until_ns)
    packed: bytes = msgpack.packb(obj, use_bin_type=True)
    return packed


def encode_gnss(sample: GnssSample, seq: int, until_ns: int | None = None) -> bytes:
    """Encode one GNSS epoch for ``<prefix>/<id>/sensors/gnss``."""
    vel = [float(x) for x in sample.vel_enu_mps]
    if len(vel) != 3:
        raise EncodeError("vel_enu_mps must have three components (east, north, up)")
    return _pack(
        {
            "v": SCHEMA_VERSION,
            "sensor": Stream.GNSS.value,
            "seq": _seq(seq),
            "stamp_ns": int(sample.stamp_ns),
            "vel_enu_mps": vel,
            "heading_rad": float(sample.heading_rad),
            "pitch_rad": float(sample.pitch_rad),
            "roll_rad": float(sample.roll_rad),
            "lat_deg": float(sample.lat_deg),
            "lon_deg": float(sample.lon_deg),
            "height_m": float(sample.height_m),
            "fix": int(sample.fix),
            "vel_std_mps": float(sample.vel_std_mps),
        },
        until_ns,
    )


def encode_imu(batch: ImuBatch, seq: int, until_ns: int | None = None) -> bytes:
    """Encode a batch of ``n`` IMU samples for ``<prefix>/<id>/sensors/imu``."""
    n = int(np.asarray(batch.stamp_ns).shape[0]) if np.ndim(batch.stamp_ns) == 1 else -1
    if n < 0:
        raise EncodeError("stamp_ns must be one-dimensional")
    return _pack(
        {
            "v": SCHEMA_VERSION,
            "sensor": Stream.IMU.value,
            "seq": _seq(seq),
            "stamp_ns": _i8(batch.stamp_ns, n),
            "accel_mps2": _f8(batch.accel_mps2, (n, 3), "accel_mps2"),
            "gyro_radps": _f8(batch.gyro_radps, (n, 3), "gyro_radps"),
        },
        until_ns,
    )


def encode_wheel_edges(edges: Sequence[WheelEdges], seq: int, until_ns: int | None = None) -> bytes:
    """Encode the encoder edges of one or both wheels for ``<prefix>/<id>/sensors/wheels``.

    Wheels without edges are left out; with none at all the packet is a heartbeat (``"edges":
    []``) and needs ``until_ns``: no edge on either wheel up to it.
    """
    items: list[dict[str, Any]] = []
    for e in edges:
        n = int(np.asarray(e.stamp_ns).shape[0]) if np.ndim(e.stamp_ns) == 1 else -1
        if n < 0:
            raise EncodeError("stamp_ns must be one-dimensional")
        if n == 0:
            continue  # a wheel without an edge in the window: no entry
        item: dict[str, Any] = {"wheel": int(Wheel(e.wheel)), "stamp_ns": _i8(e.stamp_ns, n)}
        if e.direction is not None:
            d = np.asarray(e.direction)
            if d.shape != (n,):
                raise EncodeError(f"direction must have shape ({n},)")
            item["direction"] = np.ascontiguousarray(d, dtype=np.int8).tobytes()
        items.append(item)
    if not items and until_ns is None:
        raise EncodeError("a wheels packet without edges must carry until_ns (a heartbeat)")
    return _pack(
        {
            "v": SCHEMA_VERSION,
            "sensor": Stream.WHEELS.value,
            "seq": _seq(seq),
            "mode": "edges",
            "edges": items,
        },
        until_ns,
    )


def encode_wheel_speeds(speeds: WheelSpeeds, seq: int, until_ns: int | None = None) -> bytes:
    """Encode ``n`` wheel angular-speed samples for ``<prefix>/<id>/sensors/wheels``."""
    n = int(np.asarray(speeds.stamp_ns).shape[0]) if np.ndim(speeds.stamp_ns) == 1 else -1
    if n < 0:
        raise EncodeError("stamp_ns must be one-dimensional")
    return _pack(
        {
            "v": SCHEMA_VERSION,
            "sensor": Stream.WHEELS.value,
            "seq": _seq(seq),
            "mode": "speeds",
            "stamp_ns": _i8(speeds.stamp_ns, n),
            "omega_radps": _f8(speeds.omega_radps, (n, 2), "omega_radps"),
        },
        until_ns,
    )


def encode_config(config: VehicleConfig) -> bytes:
    """Encode a vehicle configuration for ``<prefix>/<id>/config`` (UTF-8 JSON, REST's body)."""
    return json.dumps(config.to_dict(), separators=(",", ":")).encode()


# ---------------------------------------------------------------------------------------------
# decoding


class _Ctx:
    """Raise helpers bound to the packet's vehicle and stream."""

    __slots__ = ("stream", "vehicle_id")

    def __init__(self, vehicle_id: str | None, stream: Stream | None) -> None:
        self.vehicle_id = vehicle_id
        self.stream = stream

    def fail(self, reason: str, detail: str) -> DecodeError:
        return DecodeError(reason, detail, vehicle_id=self.vehicle_id, stream=self.stream)


def _field(ctx: _Ctx, m: dict[str, Any], name: str) -> Any:
    try:
        return m[name]
    except KeyError:
        raise ctx.fail("missing_field", name) from None


_MISSING = object()


def _int(ctx: _Ctx, m: dict[str, Any], name: str) -> int:
    v = m.get(name, _MISSING)
    if type(v) is int:  # the common case first: one lookup, one check
        return v
    if v is _MISSING:
        raise ctx.fail("missing_field", name)
    raise ctx.fail("wrong_type", f"{name} must be an integer")


def _float(ctx: _Ctx, m: dict[str, Any], name: str) -> float:
    """A required number; NaN ("not available") passes, ``±inf`` is refused."""
    v = m.get(name, _MISSING)
    if type(v) is float:
        f = v
    elif type(v) is int:
        f = float(v)
    elif v is _MISSING:
        raise ctx.fail("missing_field", name)
    else:
        raise ctx.fail("wrong_type", f"{name} must be a number")
    if math.isinf(f):
        raise ctx.fail("non_finite", name)
    return f


def _stamp(ctx: _Ctx, v: int, name: str, lim: Limits) -> int:
    if not lim.min_stamp_ns <= v <= lim.max_stamp_ns:
        raise ctx.fail("out_of_range", f"{name} {v} is outside years 2000..2100")
    return v


def _array(
    ctx: _Ctx, m: dict[str, Any], name: str, dtype: str, width: int, lim: Limits
) -> np.ndarray:
    raw = _field(ctx, m, name)
    if type(raw) is not bytes:
        raise ctx.fail("wrong_type", f"{name} must be binary (packed little-endian {dtype})")
    item = np.dtype(dtype).itemsize * width
    if len(raw) % item:
        raise ctx.fail("wrong_shape", f"{name}: {len(raw)} bytes is not a multiple of {item}")
    n = len(raw) // item
    if n > lim.max_batch:
        raise ctx.fail("oversize", f"{name}: {n} samples > {lim.max_batch}")
    arr = np.frombuffer(raw, dtype=dtype)
    return arr.reshape(n, width) if width > 1 else arr


def _stamps(
    ctx: _Ctx, m: dict[str, Any], lim: Limits, *, strict: bool, name: str = "stamp_ns"
) -> tuple[np.ndarray, int, int]:
    """A batch's sample times and its first and last one (ns)."""
    t = _array(ctx, m, name, "<i8", 1, lim)
    if t.shape[0] == 0:
        raise ctx.fail("wrong_shape", f"{name}: empty batch")
    first_ns = _stamp(ctx, int(t[0]), name, lim)
    last_ns = _stamp(ctx, int(t[-1]), name, lim)
    if t.shape[0] > 1:
        ok = (t[1:] > t[:-1]).all() if strict else (t[1:] >= t[:-1]).all()
        if not ok:
            raise ctx.fail(
                "non_monotonic", f"{name} must {'increase' if strict else 'not decrease'}"
            )
    return (t if _LITTLE_ENDIAN else t.astype(np.int64)), first_ns, last_ns


def _finite_rows(ctx: _Ctx, a: np.ndarray, name: str, n: int, bound: float) -> np.ndarray:
    if a.shape[0] != n:
        raise ctx.fail("wrong_shape", f"{name} has {a.shape[0]} rows for {n} timestamps")
    norm2 = np.einsum("ij,ij->i", a, a)
    if not (norm2 <= bound * bound).all():  # fast path fails on NaN, inf or too large
        if np.isinf(a).any():
            raise ctx.fail("non_finite", name)
        if (norm2 > bound * bound).any():  # NaN rows compare False: "not available" passes
            raise ctx.fail("out_of_range", f"{name} norm exceeds {bound:g}")
    return a if _LITTLE_ENDIAN else a.astype(np.float64)


#: What a stream's decoder returns: the packet's measurements, its first and last sample time.
_Body = tuple[tuple[Measurement, ...], int, int]


def _velocity(ctx: _Ctx, m: dict[str, Any], lim: Limits) -> tuple[float, float, float]:
    """``vel_enu_mps``: three numbers, no ``±inf``, speed within the limit (NaN passes)."""
    vel = _field(ctx, m, "vel_enu_mps")
    if type(vel) is not list or len(vel) != 3:
        raise ctx.fail("wrong_type", "vel_enu_mps must be an array of 3 numbers")
    for x in vel:
        if type(x) is not float and type(x) is not int:
            raise ctx.fail("wrong_type", "vel_enu_mps must be an array of 3 numbers")
    ve, vn, vu = float(vel[0]), float(vel[1]), float(vel[2])
    if math.isinf(ve) or math.isinf(vn) or math.isinf(vu):
        raise ctx.fail("non_finite", "vel_enu_mps")
    # NaN (no velocity, e.g. fix NONE) passes: NaN comparisons are False
    if ve * ve + vn * vn + vu * vu > lim.max_speed_mps**2:
        raise ctx.fail("out_of_range", f"speed exceeds {lim.max_speed_mps:g} m/s")
    return ve, vn, vu


def _fix(ctx: _Ctx, m: dict[str, Any]) -> GnssFix:
    """``fix`` (RTK fixed when absent)."""
    if "fix" not in m:
        return GnssFix.RTK_FIXED
    fix_raw = _int(ctx, m, "fix")
    fix = _GNSS_FIX.get(fix_raw)
    if fix is None:
        raise ctx.fail("wrong_type", f"fix {fix_raw} is not a GnssFix value")
    return fix


_TWO_PI = 2 * math.pi
_HALF_PI = math.pi / 2
_NO_FIX = object()  # "fix" absent: RTK fixed
_FIX_OF: dict[object, GnssFix] = {int(f): f for f in GnssFix}
_FIX_OF[_NO_FIX] = GnssFix.RTK_FIXED
_new_gnss = builder(GnssSample)
_new_packet = builder(Packet)


def _gnss_sample(m: dict[str, Any], lim: Limits) -> GnssSample | None:
    """The GNSS sample of a map whose fields are floats (``int`` stamp and fix) within their
    limits; None otherwise (:func:`_decode_gnss`'s rules then decide).

    The receivers' usual packet, checked in one expression instead of a call per field (the
    check per field, with its reason, is for the others). Velocities with a NaN (no fix) and
    integers where a float goes are valid but go the long way, which accepts them.
    """
    get = m.get
    t = get("stamp_ns")
    vel = get("vel_enu_mps")
    heading, pitch, roll = get("heading_rad"), get("pitch_rad"), get("roll_rad")
    lat, lon, h = get("lat_deg"), get("lon_deg"), get("height_m")
    fix_raw = get("fix", _NO_FIX)
    vel_std = get("vel_std_mps", math.nan)
    if not (
        type(t) is int
        and type(vel) is list
        and len(vel) == 3
        and type(vel[0]) is float
        and type(vel[1]) is float
        and type(vel[2]) is float
        and type(heading) is float
        and type(pitch) is float
        and type(roll) is float
        and type(lat) is float
        and type(lon) is float
        and type(h) is float
        and (type(fix_raw) is int or fix_raw is _NO_FIX)
        and type(vel_std) is float
    ):
        return None
    return _gnss_within(
        t, vel, heading, pitch, roll, lat, lon, h, _FIX_OF.get(fix_raw), vel_std, lim
    )


def _gnss_within(
    t: int,
    vel: Sequence[float],
    heading: float,
    pitch: float,
    roll: float,
    lat: float,
    lon: float,
    h: float,
    fix: GnssFix | None,
    vel_std: float,
    lim: Limits,
) -> GnssSample | None:
    """The GNSS sample of these values (``vel_std`` NaN when not given) when each lies within
    its limits, one expression for all; None when one does not, or ``fix`` is None (unknown).

    NaN attitude, position and ``vel_std`` ("not available") pass, as the field-by-field rules
    let them; a NaN or infinite velocity does not (those fixes go the field-by-field way).
    """
    ve, vn, vu = vel
    if not (
        fix is not None
        and lim.min_stamp_ns <= t <= lim.max_stamp_ns
        and ve * ve + vn * vn + vu * vu <= lim.max_speed_mps**2  # False for inf and NaN
        and not abs(heading) > _TWO_PI
        and not abs(pitch) > _HALF_PI
        and not abs(roll) > math.pi
        and not abs(lat) > 90
        and not abs(lon) > 180
        and not (h < lim.min_height_m or h > lim.max_height_m)
        and not (vel_std < 0 or vel_std > lim.max_speed_mps)
    ):
        return None
    return _new_gnss(t, (ve, vn, vu), heading, pitch, roll, lat, lon, h, fix, vel_std)


def _decode_gnss(ctx: _Ctx, m: dict[str, Any], lim: Limits) -> _Body:
    sample = _gnss_sample(m, lim)
    if sample is None:
        sample = _gnss_checked(ctx, m, lim)
    return (sample,), sample.stamp_ns, sample.stamp_ns


def _gnss_checked(ctx: _Ctx, m: dict[str, Any], lim: Limits) -> GnssSample:
    """The GNSS sample, field by field: the first rule a field breaks is the refusal."""
    t = _stamp(ctx, _int(ctx, m, "stamp_ns"), "stamp_ns", lim)
    vel = _velocity(ctx, m, lim)
    heading = _float(ctx, m, "heading_rad")
    pitch = _float(ctx, m, "pitch_rad")
    roll = _float(ctx, m, "roll_rad")
    if abs(heading) > 2 * math.pi or abs(pitch) > math.pi / 2 or abs(roll) > math.pi:
        raise ctx.fail("out_of_range", "attitude angle out of range")
    lat = _float(ctx, m, "lat_deg")
    lon = _float(ctx, m, "lon_deg")
    h = _float(ctx, m, "height_m")
    # NaN (position unknown) compares False, so only finite out-of-range values are refused
    if abs(lat) > 90 or abs(lon) > 180 or h < lim.min_height_m or h > lim.max_height_m:
        raise ctx.fail("out_of_range", "position out of range")
    fix = _fix(ctx, m)
    vel_std = _float(ctx, m, "vel_std_mps") if "vel_std_mps" in m else math.nan
    if vel_std < 0 or vel_std > lim.max_speed_mps:
        raise ctx.fail("out_of_range", "vel_std_mps")
    return GnssSample(t, vel, heading, pitch, roll, lat, lon, h, fix, vel_std)


def _decode_imu(ctx: _Ctx, m: dict[str, Any], lim: Limits) -> _Body:
    t, first_ns, last_ns = _stamps(ctx, m, lim, strict=True)
    n = t.shape[0]
    acc = _finite_rows(
        ctx, _array(ctx, m, "accel_mps2", "<f8", 3, lim), "accel_mps2", n, lim.max_accel_mps2
    )
    gyr = _finite_rows(
        ctx, _array(ctx, m, "gyro_radps", "<f8", 3, lim), "gyro_radps", n, lim.max_gyro_radps
    )
    return (ImuBatch(t, acc, gyr),), first_ns, last_ns


def _decode_edges(ctx: _Ctx, m: dict[str, Any], lim: Limits) -> _Body:
    items = _field(ctx, m, "edges")
    if isinstance(items, list) and not items and "until_ns" in m:
        # a heartbeat: no edge on either wheel up to until_ns, which is its span
        until_ns = _stamp(ctx, _int(ctx, m, "until_ns"), "until_ns", lim)
        return (), until_ns, until_ns
    if not isinstance(items, list) or not 1 <= len(items) <= len(Wheel):
        raise ctx.fail(
            "wrong_type", "edges must be an array of 1 or 2 wheel entries (0 with until_ns)"
        )
    out: list[Measurement] = []
    seen: set[int] = set()
    first_ns, last_ns = 2**63 - 1, -(2**63)
    for item in items:
        if not isinstance(item, dict):
            raise ctx.fail("wrong_type", "each edges entry must be a map")
        w = _int(ctx, item, "wheel")
        if w not in (0, 1) or w in seen:
            raise ctx.fail("out_of_range", f"wheel {w} is not 0 (left) or 1 (right), or repeated")
        seen.add(w)
        t, lo_ns, hi_ns = _stamps(ctx, item, lim, strict=False)
        first_ns, last_ns = min(first_ns, lo_ns), max(last_ns, hi_ns)
        direction = None
        if "direction" in item:
            d = _array(ctx, item, "direction", "i1", 1, lim)
            if d.shape[0] != t.shape[0]:
                raise ctx.fail("wrong_shape", "direction and stamp_ns lengths differ")
            if not (np.abs(d.astype(np.int16)) == 1).all():
                raise ctx.fail("out_of_range", "direction must be +1 or -1")
            direction = d
        out.append(WheelEdges(_WHEEL[w], t, direction))
    return tuple(out), first_ns, last_ns


def _decode_speeds(ctx: _Ctx, m: dict[str, Any], lim: Limits) -> _Body:
    t, first_ns, last_ns = _stamps(ctx, m, lim, strict=True)
    om = _array(ctx, m, "omega_radps", "<f8", 2, lim)
    if om.shape[0] != t.shape[0]:
        raise ctx.fail("wrong_shape", "omega_radps and stamp_ns lengths differ")
    if np.isinf(om).any():
        raise ctx.fail("non_finite", "omega_radps")
    if (np.abs(om) > lim.max_wheel_omega_radps).any():
        raise ctx.fail("out_of_range", f"|omega_radps| exceeds {lim.max_wheel_omega_radps:g}")
    return (WheelSpeeds(t, om if _LITTLE_ENDIAN else om.astype(np.float64)),), first_ns, last_ns


def _unpack(
    ctx: _Ctx, payload: bytes | bytearray | memoryview, max_payload_bytes: int
) -> dict[str, Any]:
    if len(payload) > max_payload_bytes:
        raise ctx.fail("oversize", f"{len(payload)} bytes > {max_payload_bytes}")
    try:
        m = msgpack.unpackb(payload, raw=False, use_list=True, strict_map_key=True)
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise ctx.fail("undecodable", type(exc).__name__) from None
    if not isinstance(m, dict):
        raise ctx.fail("undecodable", "payload is not a map")
    return m


def _open(
    key: str, payload: bytes | bytearray | memoryview, prefix: str, max_payload_bytes: int
) -> tuple[_Ctx, Stream, dict[str, Any], int]:
    """Parse the key and the header every sensor packet carries.

    Returns
    -------
    ctx : _Ctx
        Raise helpers bound to the key's vehicle and stream.
    stream : Stream
    m : dict
        The unpacked msgpack map, header checked (``v``, ``sensor``, ``seq``).
    seq : int

    Raises
    ------
    DecodeError
        ``bad_key``, ``oversize``, ``undecodable``, ``schema_version``, ``key_mismatch``,
        ``missing_field``, ``wrong_type`` or ``out_of_range`` (of ``seq``).
    """
    try:
        vehicle_id, stream = parse_key(key, prefix)
    except ValueError as exc:
        raise DecodeError("bad_key", str(exc)) from None
    ctx = _Ctx(vehicle_id, stream)
    if stream is None:
        raise ctx.fail("bad_key", "a config key carries no sensor packet")
    m = _unpack(ctx, payload, max_payload_bytes)
    seq = m.get("seq")
    if (
        type(seq) is int
        and 0 <= seq < 2**63
        and m.get("v") == SCHEMA_VERSION
        and type(m["v"]) is int
        and m.get("sensor") == stream  # a StrEnum equals its value
    ):
        return ctx, stream, m, seq  # the usual header, checked without a call per field
    version = m.get("v")
    if type(version) is not int or version != SCHEMA_VERSION:
        raise ctx.fail("schema_version", f"unsupported schema version {version!r}")
    sensor = _field(ctx, m, "sensor")
    if sensor != stream:  # a StrEnum equals its value
        raise ctx.fail("key_mismatch", f"payload sensor {sensor!r} on a {stream.value} key")
    seq = _int(ctx, m, "seq")
    if not 0 <= seq < 2**63:
        raise ctx.fail("out_of_range", "seq must be in [0, 2**63)")
    return ctx, stream, m, seq


def _until(ctx: _Ctx, m: dict[str, Any], last_ns: int, lim: Limits) -> int | None:
    """The packet's ``until_ns`` (None when absent), checked against its last sample."""
    if "until_ns" not in m:
        return None
    until_ns = _int(ctx, m, "until_ns")
    if not last_ns <= until_ns <= last_ns + lim.max_until_ahead_ns:
        raise ctx.fail(
            "out_of_range",
            f"until_ns must lie between the last sample and "
            f"{lim.max_until_ahead_ns / 1e9:g} s after it",
        )
    return until_ns


def _packet(ctx: _Ctx, stream: Stream, m: dict[str, Any], seq: int, lim: Limits) -> Packet:
    """Check and build the packet of an opened map (see :func:`_open`).

    Raises
    ------
    DecodeError
        The first rule of ``docs/protocol.md`` §6 the stream's fields break.
    """
    body: _Body
    if stream is Stream.GNSS:
        body = _decode_gnss(ctx, m, lim)
    elif stream is Stream.IMU:
        body = _decode_imu(ctx, m, lim)
    else:
        mode = _field(ctx, m, "mode")
        if mode == "edges":
            body = _decode_edges(ctx, m, lim)
        elif mode == "speeds":
            body = _decode_speeds(ctx, m, lim)
        else:
            raise ctx.fail("wrong_type", f"wheels mode {mode!r} is not 'edges' or 'speeds'")
    ms, first_ns, last_ns = body
    until_ns = _until(ctx, m, last_ns, lim)
    assert ctx.vehicle_id is not None
    return _new_packet(ctx.vehicle_id, stream, seq, SCHEMA_VERSION, ms, first_ns, last_ns, until_ns)


def decode(
    key: str,
    payload: bytes | bytearray | memoryview,
    *,
    prefix: str = "fleet",
    max_payload_bytes: int = 256 * 1024,
    limits: Limits = LIMITS,
) -> Packet:
    """Decode one sensor packet received on ``key``.

    Parameters
    ----------
    key : str
        ``<prefix>/<vehicle_id>/sensors/<gnss|imu|wheels>``.
    payload : bytes
        The msgpack payload.
    prefix : str
        The server's key prefix.
    max_payload_bytes : int
        Larger payloads are refused (``oversize``) before parsing.

    Raises
    ------
    DecodeError
        With ``reason`` from :data:`REASONS`.
    """
    ctx, stream, m, seq = _open(key, payload, prefix, max_payload_bytes)
    return _packet(ctx, stream, m, seq, limits)


def decode_config(
    key: str,
    payload: bytes | bytearray | memoryview,
    *,
    prefix: str = "fleet",
    max_payload_bytes: int = 256 * 1024,
) -> tuple[str, VehicleConfig]:
    """Decode a ``<prefix>/<vehicle_id>/config`` payload (UTF-8 JSON of a config of any kind).

    Raises :class:`DecodeError` (``bad_key``, ``oversize``, ``undecodable``, ``bad_config``
    with :func:`vehicle_config_from_dict`'s reason: kind, field, range and unit).
    """
    try:
        vehicle_id, stream = parse_key(key, prefix)
    except ValueError as exc:
        raise DecodeError("bad_key", str(exc)) from None
    ctx = _Ctx(vehicle_id, None)
    if stream is not None:
        raise ctx.fail("bad_key", "not a config key")
    if len(payload) > max_payload_bytes:
        raise ctx.fail("oversize", f"{len(payload)} bytes > {max_payload_bytes}")
    try:
        data = json.loads(bytes(payload).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ctx.fail("undecodable", type(exc).__name__) from None
    try:
        return vehicle_id, vehicle_config_from_dict(data)
    except (ConfigError, TypeError, ValueError) as exc:
        raise ctx.fail("bad_config", str(exc)) from None
