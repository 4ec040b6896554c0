"""Decode sensor packets and vehicle configs; the encoders of every stream (pure: no I/O, no
Zenoh). See ``docs/protocol.md``.

:func:`decode` checks a packet's key and header, then hands the payload map to its stream's
rules (:data:`server.protocol.streams.STREAMS`). The shared parts (header, refusals, limits,
:class:`Packet`) are :mod:`server.protocol.base`, re-exported here.
"""

from __future__ import annotations

import json
from typing import Any

import msgpack

from estimator.config import ConfigError, VehicleConfig, vehicle_config_from_dict
from server.protocol.base import (
    LIMITS,
    REASONS,
    SCHEMA_VERSION,
    Ctx,
    DecodeError,
    EncodeError,
    Limits,
    Packet,
    ProtocolError,
    field,
    int_field,
    new_packet,
)
from server.protocol.drivetrain import (
    encode_odometer,
    encode_sprockets,
    encode_steering,
    encode_wheel_speeds4,
)
from server.protocol.keys import Stream, parse_key
from server.protocol.sensors import (
    encode_gnss,
    encode_imu,
    encode_wheel_edges,
    encode_wheel_speeds,
)
from server.protocol.streams import STREAMS

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
    "encode_odometer",
    "encode_sprockets",
    "encode_steering",
    "encode_wheel_edges",
    "encode_wheel_speeds",
    "encode_wheel_speeds4",
]


#: Each stream's per-packet rules (a dict: faster to look up than the read-only mapping).
_RULES = {stream: spec.decode for stream, spec in STREAMS.items()}


def encode_config(config: VehicleConfig) -> bytes:
    """Encode a vehicle configuration for ``<prefix>/<id>/config`` (UTF-8 JSON, REST's body)."""
    return json.dumps(config.to_dict(), separators=(",", ":")).encode()


def _unpack(
    ctx: Ctx, payload: bytes | bytearray | memoryview, max_payload_bytes: int
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
) -> tuple[Ctx, Stream, dict[str, Any], int]:
    """Parse the key and the header every sensor packet carries.

    Returns
    -------
    ctx : Ctx
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
    ctx = Ctx(vehicle_id, stream)
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
    sensor = field(ctx, m, "sensor")
    if sensor != stream:  # a StrEnum equals its value
        raise ctx.fail("key_mismatch", f"payload sensor {sensor!r} on a {stream.value} key")
    seq = int_field(ctx, m, "seq")
    if not 0 <= seq < 2**63:
        raise ctx.fail("out_of_range", "seq must be in [0, 2**63)")
    return ctx, stream, m, seq


def _until(ctx: Ctx, m: dict[str, Any], last_ns: int, lim: Limits) -> int | None:
    """The packet's ``until_ns`` (None when absent), checked against its last sample."""
    if "until_ns" not in m:
        return None
    until_ns = int_field(ctx, m, "until_ns")
    if not last_ns <= until_ns <= last_ns + lim.max_until_ahead_ns:
        raise ctx.fail(
            "out_of_range",
            f"until_ns must lie between the last sample and "
            f"{lim.max_until_ahead_ns / 1e9:g} s after it",
        )
    return until_ns


def _boot(ctx: Ctx, m: dict[str, Any]) -> int | None:
    """The sender's boot id (None when absent): an integer in [0, 2**63)."""
    boot = m.get("boot")
    if boot is None and "boot" not in m:
        return None
    if type(boot) is not int:
        raise ctx.fail("wrong_type", "boot must be an integer")
    if not 0 <= boot < 2**63:
        raise ctx.fail("out_of_range", "boot must be in [0, 2**63)")
    return boot


def _packet(ctx: Ctx, stream: Stream, m: dict[str, Any], seq: int, lim: Limits) -> Packet:
    """Check and build the packet of an opened map (see :func:`_open`).

    Raises
    ------
    DecodeError
        The first rule of ``docs/protocol.md`` §6 the stream's fields break.
    """
    ms, first_ns, last_ns = _RULES[stream](ctx, m, lim)
    until_ns = _until(ctx, m, last_ns, lim)
    boot = _boot(ctx, m)
    assert ctx.vehicle_id is not None
    return new_packet(
        vehicle_id=ctx.vehicle_id,
        stream=stream,
        seq=seq,
        schema_version=SCHEMA_VERSION,
        measurements=ms,
        first_stamp_ns=first_ns,
        last_stamp_ns=last_ns,
        until_ns=until_ns,
        boot=boot,
    )


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
        ``<prefix>/<vehicle_id>/sensors/<stream>``.
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
    ctx = Ctx(vehicle_id, None)
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
