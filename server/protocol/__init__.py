"""Wire protocol: key expressions and msgpack payloads (``docs/protocol.md``). Pure, no I/O."""

from server.protocol.codec import (
    LIMITS,
    REASONS,
    SCHEMA_VERSION,
    DecodeError,
    EncodeError,
    Limits,
    Packet,
    ProtocolError,
    decode,
    decode_config,
    encode_config,
    encode_gnss,
    encode_imu,
    encode_wheel_edges,
    encode_wheel_speeds,
)
from server.protocol.keys import Stream, config_key, is_valid_vehicle_id, parse_key, sensor_key

__all__ = [
    "LIMITS",
    "REASONS",
    "SCHEMA_VERSION",
    "DecodeError",
    "EncodeError",
    "Limits",
    "Packet",
    "ProtocolError",
    "Stream",
    "config_key",
    "decode",
    "decode_config",
    "encode_config",
    "encode_gnss",
    "encode_imu",
    "encode_wheel_edges",
    "encode_wheel_speeds",
    "is_valid_vehicle_id",
    "parse_key",
    "sensor_key",
]
