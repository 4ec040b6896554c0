"""Wire protocol (``docs/protocol.md``): key expressions, msgpack payloads, recording files."""

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
from server.protocol.recording import Record, RecordingError, read_recording, write_recording

__all__ = [
    "LIMITS",
    "REASONS",
    "SCHEMA_VERSION",
    "DecodeError",
    "EncodeError",
    "Limits",
    "Packet",
    "ProtocolError",
    "Record",
    "RecordingError",
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
    "read_recording",
    "sensor_key",
    "write_recording",
]
