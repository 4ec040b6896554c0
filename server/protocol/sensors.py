"""The estimators' first streams: GNSS epochs, IMU batches, wheel edges or wheel speeds.

Each stream's payload is encoded here and decoded by its rules (``docs/protocol.md`` §4, §6);
:mod:`server.protocol.streams` declares which function serves which stream. A GNSS epoch
carries the fields of :class:`~estimator.types.GnssSample`, named alike, so the wire struct
(:mod:`server.protocol.wire`) is derived from that class.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from estimator._frozen import builder, copier
from estimator.types import GnssFix, GnssSample, ImuBatch, Wheel, WheelEdges, WheelSpeeds
from server.protocol.base import (
    Body,
    Ctx,
    EncodeError,
    Limits,
    field,
    float_field,
    header,
    int_field,
    pack,
    pack_f8,
    pack_i8,
    stamp,
)
from server.protocol.keys import Stream
from server.protocol.layouts import Edges, Rows, Sampled

__all__ = [
    "IMU",
    "WHEEL_EDGES",
    "WHEEL_MODES",
    "WHEEL_SPEEDS",
    "decode_gnss",
    "decode_wheels",
    "encode_gnss",
    "encode_imu",
    "encode_wheel_edges",
    "encode_wheel_speeds",
    "gnss_checked",
    "gnss_sample",
    "gnss_struct",
    "gnss_within",
]

#: IMU batches: specific force and angular rate, row norms within the limits.
IMU = Sampled(
    rows=(
        Rows("accel_mps2", 3, "max_accel_mps2", norm=True),
        Rows("gyro_radps", 3, "max_gyro_radps", norm=True),
    ),
    build=builder(ImuBatch),
)
#: Wheel speeds (``mode: "speeds"``): ``|omega|`` within the limit.
WHEEL_SPEEDS = Sampled(
    rows=(Rows("omega_radps", 2, "max_wheel_omega_radps"),), build=builder(WheelSpeeds)
)
#: Wheel edges (``mode: "edges"``): one entry per wheel.
WHEEL_EDGES = Edges(key="wheel", members=Wheel, build=builder(WheelEdges))
#: The wheels stream's layout by ``mode``.
WHEEL_MODES: dict[str, Sampled | Edges] = {"edges": WHEEL_EDGES, "speeds": WHEEL_SPEEDS}

_TWO_PI = 2 * math.pi
_HALF_PI = math.pi / 2
_NO_FIX = object()  # "fix" absent: RTK fixed
_FIX_OF: dict[object, GnssFix] = {int(f): f for f in GnssFix}
_FIX_OF[_NO_FIX] = GnssFix.RTK_FIXED
_new_gnss = builder(GnssSample)
_gnss_of_struct = copier(GnssSample)


# ---------------------------------------------------------------------------------------------
# encoding


def encode_gnss(
    sample: GnssSample, seq: int, until_ns: int | None = None, *, boot: int | None = None
) -> bytes:
    """Encode one GNSS epoch for ``<prefix>/<id>/sensors/gnss``."""
    vel = [float(x) for x in sample.vel_enu_mps]
    if len(vel) != 3:
        raise EncodeError("vel_enu_mps must have three components (east, north, up)")
    return pack(
        {
            **header(Stream.GNSS, seq),
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
        boot,
    )


def sample_count(stamp_ns: Any) -> int:
    """Length of a one-dimensional stamp array (EncodeError otherwise)."""
    if np.ndim(stamp_ns) != 1:
        raise EncodeError("stamp_ns must be one-dimensional")
    return int(np.asarray(stamp_ns).shape[0])


def encode_imu(
    batch: ImuBatch, seq: int, until_ns: int | None = None, *, boot: int | None = None
) -> bytes:
    """Encode a batch of ``n`` IMU samples for ``<prefix>/<id>/sensors/imu``."""
    n = sample_count(batch.stamp_ns)
    return pack(
        {
            **header(Stream.IMU, seq),
            "stamp_ns": pack_i8(batch.stamp_ns, n),
            "accel_mps2": pack_f8(batch.accel_mps2, (n, 3), "accel_mps2"),
            "gyro_radps": pack_f8(batch.gyro_radps, (n, 3), "gyro_radps"),
        },
        until_ns,
        boot,
    )


def edge_entries(key: str, runs: Sequence[tuple[int, Any, Any]]) -> list[dict[str, Any]]:
    """The ``edges`` entries of ``(member, stamp_ns, direction or None)`` runs; members without
    an edge are left out."""
    items: list[dict[str, Any]] = []
    for member, stamp_ns, direction in runs:
        n = sample_count(stamp_ns)
        if n == 0:
            continue  # a member without an edge in the window: no entry
        items.append({key: int(member), **edge_arrays(stamp_ns, direction, n)})
    return items


def edge_arrays(stamp_ns: Any, direction: Any, n: int) -> dict[str, bytes]:
    """``stamp_ns`` and, when given, ``direction`` of an edge run of ``n`` edges, packed."""
    out = {"stamp_ns": pack_i8(stamp_ns, n)}
    if direction is not None:
        d = np.asarray(direction)
        if d.shape != (n,):
            raise EncodeError(f"direction must have shape ({n},)")
        out["direction"] = np.ascontiguousarray(d, dtype=np.int8).tobytes()
    return out


def require_until(has_data: bool, until_ns: int | None) -> None:
    """A packet without data is a heartbeat and must carry ``until_ns``."""
    if not has_data and until_ns is None:
        raise EncodeError("a packet without edges must carry until_ns (a heartbeat)")


def encode_wheel_edges(
    edges: Sequence[WheelEdges], seq: int, until_ns: int | None = None, *, boot: int | None = None
) -> bytes:
    """Encode the encoder edges of one or both wheels for ``<prefix>/<id>/sensors/wheels``.

    Wheels without edges are left out; with none at all the packet is a heartbeat (``"edges":
    []``) and needs ``until_ns``: no edge on either wheel up to it.
    """
    items = edge_entries("wheel", [(Wheel(e.wheel), e.stamp_ns, e.direction) for e in edges])
    require_until(bool(items), until_ns)
    return pack({**header(Stream.WHEELS, seq), "mode": "edges", "edges": items}, until_ns, boot)


def encode_wheel_speeds(
    speeds: WheelSpeeds, seq: int, until_ns: int | None = None, *, boot: int | None = None
) -> bytes:
    """Encode ``n`` wheel angular-speed samples for ``<prefix>/<id>/sensors/wheels``."""
    n = sample_count(speeds.stamp_ns)
    return pack(
        {
            **header(Stream.WHEELS, seq),
            "mode": "speeds",
            "stamp_ns": pack_i8(speeds.stamp_ns, n),
            "omega_radps": pack_f8(speeds.omega_radps, (n, 2), "omega_radps"),
        },
        until_ns,
        boot,
    )


# ---------------------------------------------------------------------------------------------
# decoding


def decode_wheels(ctx: Ctx, m: dict[str, Any], lim: Limits) -> Body:
    """The wheels packet of its ``mode``."""
    mode = field(ctx, m, "mode")
    layout = WHEEL_MODES.get(mode) if isinstance(mode, str) else None
    if layout is None:
        raise ctx.fail("wrong_type", f"wheels mode {mode!r} is not 'edges' or 'speeds'")
    return layout.decode(ctx, m, lim)


def decode_gnss(ctx: Ctx, m: dict[str, Any], lim: Limits) -> Body:
    """The GNSS epoch of the map ``m``: the usual packet at once, others field by field."""
    sample = gnss_sample(m, lim)
    if sample is None:
        sample = gnss_checked(ctx, m, lim)
    return (sample,), sample.stamp_ns, sample.stamp_ns


def gnss_sample(m: dict[str, Any], lim: Limits) -> GnssSample | None:
    """The GNSS sample of a map whose fields are floats (``int`` stamp and fix) within their
    limits; None otherwise (:func:`gnss_checked`'s rules then decide).

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
    fix = _FIX_OF.get(fix_raw)
    if fix is None:
        return None
    sample = _new_gnss(
        stamp_ns=t,
        vel_enu_mps=(vel[0], vel[1], vel[2]),
        heading_rad=heading,
        pitch_rad=pitch,
        roll_rad=roll,
        lat_deg=lat,
        lon_deg=lon,
        height_m=h,
        fix=fix,
        vel_std_mps=vel_std,
    )
    return sample if gnss_within(sample, lim) else None


def gnss_struct(p: Any, lim: Limits) -> Body | None:
    """The GNSS epoch of a decoded ``wire.GnssPacket`` (whose fields are the sample's) when
    every value lies within its limits; None: the field-by-field rules decide."""
    sample = _gnss_of_struct(p)
    if not gnss_within(sample, lim):
        return None
    return (sample,), sample.stamp_ns, sample.stamp_ns


def gnss_within(s: GnssSample, lim: Limits) -> bool:
    """Whether each value of ``s`` lies within its limits, one expression for all.

    NaN attitude, position and ``vel_std_mps`` ("not available") pass, as the field-by-field
    rules let them; a NaN or infinite velocity does not (those fixes go the field-by-field way).
    """
    ve, vn, vu = s.vel_enu_mps
    h, vel_std = s.height_m, s.vel_std_mps
    return (
        lim.min_stamp_ns <= s.stamp_ns <= lim.max_stamp_ns
        and ve * ve + vn * vn + vu * vu <= lim.max_speed_mps**2  # False for inf and NaN
        and not abs(s.heading_rad) > _TWO_PI
        and not abs(s.pitch_rad) > _HALF_PI
        and not abs(s.roll_rad) > math.pi
        and not abs(s.lat_deg) > 90
        and not abs(s.lon_deg) > 180
        and not (h < lim.min_height_m or h > lim.max_height_m)
        and not (vel_std < 0 or vel_std > lim.max_speed_mps)
    )


def vector3(ctx: Ctx, m: dict[str, Any], name: str) -> tuple[float, float, float]:
    """A small fixed vector of three numbers: a msgpack array of 3 numbers, or a ``bin`` of 24
    bytes (3 packed little-endian float64), as every other array of the protocol travels."""
    raw = field(ctx, m, name)
    if type(raw) is bytes:
        if len(raw) != 24:
            raise ctx.fail("wrong_shape", f"{name}: {len(raw)} bytes, expected 24 (3 float64)")
        a, b, c = np.frombuffer(raw, dtype="<f8").tolist()
        return a, b, c
    if type(raw) is not list or len(raw) != 3:
        raise ctx.fail("wrong_type", f"{name} must be 3 numbers (array or bin of float64)")
    for x in raw:
        if type(x) is not float and type(x) is not int:
            raise ctx.fail("wrong_type", f"{name} must be 3 numbers (array or bin of float64)")
    return float(raw[0]), float(raw[1]), float(raw[2])


def _velocity(ctx: Ctx, m: dict[str, Any], lim: Limits) -> tuple[float, float, float]:
    """``vel_enu_mps``: three numbers, no ``±inf``, speed within the limit (NaN passes)."""
    ve, vn, vu = vector3(ctx, m, "vel_enu_mps")
    if math.isinf(ve) or math.isinf(vn) or math.isinf(vu):
        raise ctx.fail("non_finite", "vel_enu_mps")
    # NaN (no velocity, e.g. fix NONE) passes: NaN comparisons are False
    if ve * ve + vn * vn + vu * vu > lim.max_speed_mps**2:
        raise ctx.fail("out_of_range", f"speed exceeds {lim.max_speed_mps:g} m/s")
    return ve, vn, vu


def _fix(ctx: Ctx, m: dict[str, Any]) -> GnssFix:
    """``fix`` (RTK fixed when absent)."""
    if "fix" not in m:
        return GnssFix.RTK_FIXED
    fix_raw = int_field(ctx, m, "fix")
    fix = _FIX_OF.get(fix_raw)
    if fix is None:
        raise ctx.fail("wrong_type", f"fix {fix_raw} is not a GnssFix value")
    return fix


def gnss_checked(ctx: Ctx, m: dict[str, Any], lim: Limits) -> GnssSample:
    """The GNSS sample, field by field: the first rule a field breaks is the refusal."""
    t = stamp(ctx, int_field(ctx, m, "stamp_ns"), "stamp_ns", lim)
    vel = _velocity(ctx, m, lim)
    heading = float_field(ctx, m, "heading_rad")
    pitch = float_field(ctx, m, "pitch_rad")
    roll = float_field(ctx, m, "roll_rad")
    if abs(heading) > _TWO_PI or abs(pitch) > _HALF_PI or abs(roll) > math.pi:
        raise ctx.fail("out_of_range", "attitude angle out of range")
    lat = float_field(ctx, m, "lat_deg")
    lon = float_field(ctx, m, "lon_deg")
    h = float_field(ctx, m, "height_m")
    # NaN (position unknown) compares False, so only finite out-of-range values are refused
    if abs(lat) > 90 or abs(lon) > 180 or h < lim.min_height_m or h > lim.max_height_m:
        raise ctx.fail("out_of_range", "position out of range")
    fix = _fix(ctx, m)
    vel_std = float_field(ctx, m, "vel_std_mps") if "vel_std_mps" in m else math.nan
    if vel_std < 0 or vel_std > lim.max_speed_mps:
        raise ctx.fail("out_of_range", "vel_std_mps")
    return GnssSample(
        stamp_ns=t,
        vel_enu_mps=vel,
        heading_rad=heading,
        pitch_rad=pitch,
        roll_rad=roll,
        lat_deg=lat,
        lon_deg=lon,
        height_m=h,
        fix=fix,
        vel_std_mps=vel_std,
    )
