"""Drivetrain streams: transmission odometer edges, sprocket edges, steering-wheel angles and
four CAN wheel speeds (``docs/protocol.md`` §4). Encoders here; the decoders are the layouts'
rules, but for the odometer, whose one edge run sits in the payload itself."""

from __future__ import annotations

from typing import Any

from estimator._frozen import builder
from estimator.types import (
    Corner,
    OdometerEdges,
    SprocketEdges,
    SteeringAngles,
    TrackSide,
    WheelSpeeds4,
)
from server.protocol.base import Body, Ctx, Limits, header, pack, pack_f8, pack_i8
from server.protocol.keys import Stream
from server.protocol.layouts import Edges, Rows, Sampled, edge_run, heartbeat_until
from server.protocol.sensors import edge_arrays, edge_entries, require_until, sample_count

__all__ = [
    "SPROCKETS",
    "STEERING",
    "WHEEL_SPEEDS4",
    "decode_odometer",
    "encode_odometer",
    "encode_sprockets",
    "encode_steering",
    "encode_wheel_speeds4",
]

#: Sprocket edges: one entry per track (``side`` 0 left, 1 right).
SPROCKETS = Edges(key="side", members=TrackSide, build=builder(SprocketEdges))
#: Steering-wheel angles: ``|angle_rad|`` within the limit.
STEERING = Sampled(
    rows=(Rows("angle_rad", 1, "max_steering_angle_rad"),), build=builder(SteeringAngles)
)
#: Four wheel speeds, columns in :class:`~estimator.types.Corner` order.
WHEEL_SPEEDS4 = Sampled(
    rows=(Rows("omega_radps", len(Corner), "max_wheel_omega_radps"),),
    build=builder(WheelSpeeds4),
)

_new_odometer = builder(OdometerEdges)


def decode_odometer(ctx: Ctx, m: dict[str, Any], lim: Limits) -> Body:
    """The odometer's edge run, or a heartbeat (``stamp_ns`` empty, with ``until_ns``)."""
    if m.get("stamp_ns") == b"" and "direction" not in m and "until_ns" in m:
        return heartbeat_until(ctx, m, lim)
    t, direction, first_ns, last_ns = edge_run(ctx, m, lim)
    return (_new_odometer(stamp_ns=t, direction=direction),), first_ns, last_ns


def encode_odometer(
    edges: OdometerEdges, seq: int, until_ns: int | None = None, *, boot: int | None = None
) -> bytes:
    """Encode the odometer's edges for ``<prefix>/<id>/sensors/odometer``; without edges the
    packet is a heartbeat and needs ``until_ns``."""
    n = sample_count(edges.stamp_ns)
    require_until(n > 0, until_ns)
    arrays = edge_arrays(edges.stamp_ns, edges.direction if n else None, n)
    return pack({**header(Stream.ODOMETER, seq), **arrays}, until_ns, boot)


def encode_sprockets(
    edges: list[SprocketEdges] | tuple[SprocketEdges, ...],
    seq: int,
    until_ns: int | None = None,
    *,
    boot: int | None = None,
) -> bytes:
    """Encode one or both tracks' sprocket edges for ``<prefix>/<id>/sensors/sprockets``;
    without edges the packet is a heartbeat and needs ``until_ns``."""
    items = edge_entries("side", [(TrackSide(e.side), e.stamp_ns, e.direction) for e in edges])
    require_until(bool(items), until_ns)
    return pack({**header(Stream.SPROCKETS, seq), "edges": items}, until_ns, boot)


def encode_steering(
    angles: SteeringAngles, seq: int, until_ns: int | None = None, *, boot: int | None = None
) -> bytes:
    """Encode ``n`` steering-wheel angles for ``<prefix>/<id>/sensors/steering``."""
    n = sample_count(angles.stamp_ns)
    return pack(
        {
            **header(Stream.STEERING, seq),
            "stamp_ns": pack_i8(angles.stamp_ns, n),
            "angle_rad": pack_f8(angles.angle_rad, (n,), "angle_rad"),
        },
        until_ns,
        boot,
    )


def encode_wheel_speeds4(
    speeds: WheelSpeeds4, seq: int, until_ns: int | None = None, *, boot: int | None = None
) -> bytes:
    """Encode ``n`` samples of four wheel speeds for ``<prefix>/<id>/sensors/wheel_speeds4``."""
    n = sample_count(speeds.stamp_ns)
    return pack(
        {
            **header(Stream.WHEEL_SPEEDS4, seq),
            "stamp_ns": pack_i8(speeds.stamp_ns, n),
            "omega_radps": pack_f8(speeds.omega_radps, (n, len(Corner)), "omega_radps"),
        },
        until_ns,
        boot,
    )
