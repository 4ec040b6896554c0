"""The shapes of valid sensor packets, decoded by msgspec in one C pass.

:func:`server.protocol.codec.decode` unpacks a payload into a dict with msgpack and then checks
each field's presence and type in Python, a few dozen operations per packet. The structs here
state the same field names and msgpack types (``docs/protocol.md`` §3–5), and
:data:`DECODER` checks them while it decodes: a payload that decodes is a map with exactly
these fields, each of its type, ``v`` the schema version and ``seq`` not negative. What is left
to check in Python is values (limits, stamps, lengths of the packed arrays, ``seq`` and
``boot`` below 2**63):
:mod:`server.protocol.burst` does that in batches. The GNSS struct is derived from
:class:`~estimator.types.GnssSample`, whose fields a GNSS payload carries by name; which struct
belongs to which stream is declared in :mod:`server.protocol.streams`.

Anything else raises ``msgspec.ValidationError`` or ``msgspec.DecodeError``, and the caller
decodes that packet with the codec, whose rules give the refusal and its reason (or accept it,
e.g. with an unknown extra field). So these structs decide only which packets take the fast
path, never what a packet means. (Integers where a float goes decode here as floats, as the
codec converts them.)

Two differences from a plain dict decode are on purpose:

* absent optional fields are :data:`UNSET` (or the value the codec gives them: ``fix`` RTK
  fixed, ``vel_std_mps`` NaN), never ``None``: a packet that sends ``nil`` for ``until_ns``
  is not valid and must not decode as one without it;
* unknown fields are refused (``forbid_unknown_fields``): msgpack-python decodes every string
  of a payload and refuses the packet (``undecodable``) for one that is not UTF-8, while a
  decoder may skip an unknown field without reading it; refusing them here leaves that case,
  and every packet with extra fields, to the codec.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Annotated, Literal

import msgspec
from msgspec import UNSET, UnsetType

from estimator.types import GnssSample
from server.protocol.base import SCHEMA_VERSION

__all__ = [
    "DECODER",
    "UNSET",
    "EdgesEntry",
    "GnssPacket",
    "ImuPacket",
    "OdometerPacket",
    "SideEntry",
    "SprocketsPacket",
    "SteeringPacket",
    "WheelSpeeds4Packet",
    "WheelsPacket",
]

_Seq = Annotated[int, msgspec.Meta(ge=0)]  # the upper bound (2**63) is checked by the caller
_Boot = Annotated[int, msgspec.Meta(ge=0)] | UnsetType  # the sender's boot id (optional)
_Version = Literal[SCHEMA_VERSION]  # type: ignore[valid-type]


class _Packet(msgspec.Struct, tag_field="sensor", forbid_unknown_fields=True):
    """The header every sensor packet carries (``sensor`` is the tag)."""

    v: _Version
    seq: _Seq


def _gnss_fields() -> list[tuple[str, object, object]]:
    """``GnssSample``'s fields as struct fields: name, type, default (absent: the sample's)."""
    hints = typing.get_type_hints(GnssSample)
    out: list[tuple[str, object, object]] = []
    for f in dataclasses.fields(GnssSample):
        default = msgspec.NODEFAULT if f.default is dataclasses.MISSING else f.default
        out.append((f.name, hints[f.name], default))
    return [*out, ("until_ns", int | UnsetType, UNSET), ("boot", _Boot, UNSET)]


#: One GNSS epoch: the fields of ``GnssSample`` (``fix`` and ``vel_std_mps`` optional, as there;
#: numbers may come as msgpack ints, decoded to float as the codec does).
GnssPacket = msgspec.defstruct(
    "GnssPacket",
    _gnss_fields(),
    bases=(_Packet,),
    tag="gnss",
    module=__name__,
)


class ImuPacket(_Packet, tag="imu"):
    """An IMU batch: packed little-endian int64 stamps and ``(n, 3)`` float64 rows."""

    stamp_ns: bytes
    accel_mps2: bytes
    gyro_radps: bytes
    until_ns: int | UnsetType = UNSET
    boot: _Boot = UNSET


class EdgesEntry(msgspec.Struct, forbid_unknown_fields=True):
    """One wheel's edges in a wheels packet of mode ``edges``."""

    wheel: int
    stamp_ns: bytes
    direction: bytes | UnsetType = UNSET


class WheelsPacket(_Packet, tag="wheels"):
    """Wheel edges (``edges``) or wheel speeds (``stamp_ns`` and ``omega_radps``)."""

    mode: Literal["edges", "speeds"]
    edges: list[EdgesEntry] | UnsetType = UNSET
    stamp_ns: bytes | UnsetType = UNSET
    omega_radps: bytes | UnsetType = UNSET
    until_ns: int | UnsetType = UNSET
    boot: _Boot = UNSET


class OdometerPacket(_Packet, tag="odometer"):
    """The transmission odometer's edge run (empty: a heartbeat)."""

    stamp_ns: bytes
    direction: bytes | UnsetType = UNSET
    until_ns: int | UnsetType = UNSET
    boot: _Boot = UNSET


class SideEntry(msgspec.Struct, forbid_unknown_fields=True):
    """One track's edges in a sprockets packet."""

    side: int
    stamp_ns: bytes
    direction: bytes | UnsetType = UNSET


class SprocketsPacket(_Packet, tag="sprockets"):
    """Sprocket edges per track (no entry: a heartbeat)."""

    edges: list[SideEntry]
    until_ns: int | UnsetType = UNSET
    boot: _Boot = UNSET


class SteeringPacket(_Packet, tag="steering"):
    """Steering-wheel angles: packed int64 stamps and ``(n,)`` float64 angles."""

    stamp_ns: bytes
    angle_rad: bytes
    until_ns: int | UnsetType = UNSET
    boot: _Boot = UNSET


class WheelSpeeds4Packet(_Packet, tag="wheel_speeds4"):
    """Four wheel speeds: packed int64 stamps and ``(n, 4)`` float64 rows."""

    stamp_ns: bytes
    omega_radps: bytes
    until_ns: int | UnsetType = UNSET
    boot: _Boot = UNSET


#: Decodes a payload into the packet struct of its ``sensor``.
DECODER = msgspec.msgpack.Decoder(
    GnssPacket
    | ImuPacket
    | WheelsPacket
    | OdometerPacket
    | SprocketsPacket
    | SteeringPacket
    | WheelSpeeds4Packet
)
