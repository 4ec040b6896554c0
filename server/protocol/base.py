"""What every sensor stream shares: the header, the refusals, the limits, the decoded packet,
and the field rules a stream's payload is checked by (pure: no I/O). See ``docs/protocol.md``.

A payload is one msgpack map carrying the header ``v`` (schema version), ``sensor`` (the
stream, which must match the key) and ``seq`` (per-stream sequence number); numeric arrays
travel as msgpack *bin* values holding packed little-endian numbers, so decoding is
``numpy.frombuffer`` and the resulting arrays are read-only views of the payload.

A float that is NaN means "not available" (GNSS velocity without a fix, a dead IMU axis) and is
passed on: the estimators skip and count it. Infinities, impossible magnitudes and timestamps
that go back are refused.

Exceptions::

    ValueError
     └── ProtocolError           anything the protocol refuses
          ├── EncodeError        the measurement cannot be put on the wire (shape, dtype, seq)
          └── DecodeError        a received packet is refused; ``.reason`` is one of REASONS

:class:`DecodeError` carries a short machine ``reason`` (used as a counter name), a human
``detail``, and the ``vehicle_id`` / ``stream`` when the key could be parsed.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from estimator._frozen import builder
from estimator.base import Measurement
from server.protocol.keys import Stream

__all__ = [
    "LIMITS",
    "LITTLE_ENDIAN",
    "REASONS",
    "SCHEMA_VERSION",
    "Body",
    "Ctx",
    "DecodeError",
    "EncodeError",
    "Limits",
    "Packet",
    "ProtocolError",
    "array",
    "field",
    "float_field",
    "header",
    "int_field",
    "new_packet",
    "pack",
    "pack_f8",
    "pack_i8",
    "stamp",
    "stamps",
]

SCHEMA_VERSION = 1

#: Every reason a :class:`DecodeError` can carry (counter names).
REASONS: tuple[str, ...] = (
    "oversize",  # payload larger than max_payload_bytes, or a batch longer than max_batch
    "bad_key",  # key is not <prefix>/<vehicle_id>/sensors/<stream> (or /config)
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

#: Packed little-endian arrays are native here: ``frombuffer`` views need no conversion.
LITTLE_ENDIAN = sys.byteorder == "little"


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
    max_steering_angle_rad: float = 6 * math.pi  # three turns of the steering wheel each way


LIMITS = Limits()


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
        The stream's measurements (``server.protocol.streams``): e.g. one ``GnssSample``, one
        ``ImuBatch``, or one ``WheelEdges`` per wheel present in the packet.
    first_stamp_ns, last_stamp_ns : int
        Earliest and latest sample time in the packet (vehicle clock).
    until_ns : int or None
        The sender's promise that every sample of this stream stamped at or before it is in
        this packet or an earlier one (the end of the batch window); ``None`` if not given.
        A packet of an edge stream may be a *heartbeat*: no measurements, only ``until_ns``
        (no edge up to it); its first and last stamps are ``until_ns``.
    boot : int or None
        The sender's boot id (picked once per start of the sender; ``docs/protocol.md`` §5):
        a new one starts the vehicle's sequence tracking afresh. ``None`` if not given.
    """

    vehicle_id: str
    stream: Stream
    seq: int
    schema_version: int
    measurements: tuple[Measurement, ...]
    first_stamp_ns: int
    last_stamp_ns: int
    until_ns: int | None = None
    boot: int | None = None

    @property
    def covers_ns(self) -> int:
        """Sensor time up to which this stream is complete once this packet is in: ``until_ns``
        when the sender gave it, else the last sample time."""
        return self.last_stamp_ns if self.until_ns is None else self.until_ns


#: Builds a :class:`Packet` from every field, by keyword, without the frozen ``__init__``.
new_packet = builder(Packet)

#: What a stream's decoder returns: the packet's measurements, its first and last sample time.
Body = tuple[tuple[Measurement, ...], int, int]


# ---------------------------------------------------------------------------------------------
# encoding


def header(stream: Stream, seq: int) -> dict[str, Any]:
    """The header fields of a packet of ``stream`` numbered ``seq`` (checked)."""
    if not isinstance(seq, int | np.integer) or not 0 <= int(seq) < 2**63:
        raise EncodeError(f"seq must be an int in [0, 2**63), got {seq!r}")
    return {"v": SCHEMA_VERSION, "sensor": stream.value, "seq": int(seq)}


def pack_i8(a: Any, n: int | None = None, name: str = "stamp_ns") -> bytes:
    """Packed int64 of the ``(n,)`` integer array ``a``."""
    arr = np.asarray(a)
    if arr.ndim != 1 or (n is not None and arr.shape[0] != n):
        raise EncodeError(f"{name} must have shape ({n if n is not None else 'n'},)")
    if arr.size and arr.dtype.kind not in "iu":
        raise EncodeError(f"{name} must be integers (int64 nanoseconds)")
    return np.ascontiguousarray(arr, dtype="<i8").tobytes()


def pack_f8(a: Any, shape: tuple[int, ...], name: str) -> bytes:
    """Packed float64 of ``a``, which must have ``shape``."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape != shape:
        raise EncodeError(f"{name} must have shape {shape}, got {arr.shape}")
    return np.ascontiguousarray(arr, dtype="<f8").tobytes()


def pack(obj: dict[str, Any], until_ns: int | None = None, boot: int | None = None) -> bytes:
    """The msgpack payload of ``obj`` (header included), with ``until_ns`` and the sender's
    ``boot`` id when given (both last: the fleet simulator finds the stamps before them)."""
    if until_ns is not None:
        if not isinstance(until_ns, int | np.integer) or not 0 <= int(until_ns) < 2**63:
            raise EncodeError(f"until_ns must be an int in [0, 2**63), got {until_ns!r}")
        obj["until_ns"] = int(until_ns)
    if boot is not None:
        if not isinstance(boot, int | np.integer) or not 0 <= int(boot) < 2**63:
            raise EncodeError(f"boot must be an int in [0, 2**63), got {boot!r}")
        obj["boot"] = int(boot)
    packed: bytes = msgpack.packb(obj, use_bin_type=True)
    return packed


# ---------------------------------------------------------------------------------------------
# field rules of the per-packet decoders


class Ctx:
    """Raise helpers bound to the packet's vehicle and stream."""

    __slots__ = ("stream", "vehicle_id")

    def __init__(self, vehicle_id: str | None, stream: Stream | None) -> None:
        self.vehicle_id = vehicle_id
        self.stream = stream

    def fail(self, reason: str, detail: str) -> DecodeError:
        return DecodeError(reason, detail, vehicle_id=self.vehicle_id, stream=self.stream)


def field(ctx: Ctx, m: dict[str, Any], name: str) -> Any:
    """A required field of any type (``missing_field`` when absent)."""
    try:
        return m[name]
    except KeyError:
        raise ctx.fail("missing_field", name) from None


_MISSING = object()


def int_field(ctx: Ctx, m: dict[str, Any], name: str) -> int:
    """A required integer."""
    v = m.get(name, _MISSING)
    if type(v) is int:  # the common case first: one lookup, one check
        return v
    if v is _MISSING:
        raise ctx.fail("missing_field", name)
    raise ctx.fail("wrong_type", f"{name} must be an integer")


def float_field(ctx: Ctx, m: dict[str, Any], name: str) -> float:
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


def stamp(ctx: Ctx, v: int, name: str, lim: Limits) -> int:
    """``v`` when it lies within the limits' years."""
    if not lim.min_stamp_ns <= v <= lim.max_stamp_ns:
        raise ctx.fail("out_of_range", f"{name} {v} is outside years 2000..2100")
    return v


def array(
    ctx: Ctx, m: dict[str, Any], name: str, dtype: str, width: int, lim: Limits
) -> np.ndarray:
    """The packed array ``name``: shape ``(n,)`` for ``width`` 1, else ``(n, width)``."""
    raw = field(ctx, m, name)
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


def stamps(
    ctx: Ctx, m: dict[str, Any], lim: Limits, *, strict: bool, name: str = "stamp_ns"
) -> tuple[np.ndarray, int, int]:
    """A batch's sample times and its first and last one (ns): not empty, within the limits,
    increasing (``strict``) or not decreasing."""
    t = array(ctx, m, name, "<i8", 1, lim)
    if t.shape[0] == 0:
        raise ctx.fail("wrong_shape", f"{name}: empty batch")
    first_ns = stamp(ctx, int(t[0]), name, lim)
    last_ns = stamp(ctx, int(t[-1]), name, lim)
    if t.shape[0] > 1:
        ok = (t[1:] > t[:-1]).all() if strict else (t[1:] >= t[:-1]).all()
        if not ok:
            raise ctx.fail(
                "non_monotonic", f"{name} must {'increase' if strict else 'not decrease'}"
            )
    return (t if LITTLE_ENDIAN else t.astype(np.int64)), first_ns, last_ns
