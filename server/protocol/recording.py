"""Recording file format for ``slipfleet replay PATH`` (``docs/protocol.md``, "Recordings").

A recording is the Zenoh traffic as it arrived, so replaying it exercises the whole ingest path::

    file    = magic record*
    magic   = b"SLIPREC" 0x01                        8 bytes, version 1
    record  = key_len:u32 payload_len:u32 stamp_ns:i64 key payload      little-endian
      key      UTF-8 key expression, e.g. fleet/sim-0001/sensors/imu   (key_len bytes)
      payload  the payload exactly as published                          (payload_len bytes)
      stamp_ns when the recorder received it (UTC ns); replay keeps the gaps between records

Records are in ``stamp_ns`` order. A truncated last record (a recorder killed mid-write) is
ignored on reading. Pure file I/O, no Zenoh.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

__all__ = [
    "MAGIC",
    "Record",
    "RecordingError",
    "RecordingWriter",
    "read_recording",
    "write_recording",
]

MAGIC = b"SLIPREC\x01"
_HEADER = struct.Struct("<IIq")
MAX_KEY_BYTES = 4096
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024


class RecordingError(ValueError):
    """Not a recording, or a corrupt one."""


@dataclass(frozen=True, slots=True)
class Record:
    """One recorded sample."""

    key: str
    stamp_ns: int
    payload: bytes


class RecordingWriter:
    """Append records to an open binary file (writes the magic first)."""

    def __init__(self, fh: BinaryIO) -> None:
        self._fh = fh
        fh.write(MAGIC)
        self.records = 0

    def write(self, key: str, stamp_ns: int, payload: bytes) -> None:
        k = key.encode()
        if len(k) > MAX_KEY_BYTES or len(payload) > MAX_PAYLOAD_BYTES:
            raise RecordingError("key or payload too large for a recording")
        self._fh.write(_HEADER.pack(len(k), len(payload), stamp_ns))
        self._fh.write(k)
        self._fh.write(payload)
        self.records += 1


def write_recording(path: str | Path, records: Iterable[Record]) -> int:
    """Write ``records`` to ``path``; return how many."""
    with open(path, "wb") as fh:
        writer = RecordingWriter(fh)
        for r in records:
            writer.write(r.key, r.stamp_ns, r.payload)
        return writer.records


def read_recording(path: str | Path) -> Iterator[Record]:
    """Yield the records of ``path`` in file order (raises RecordingError if not a recording)."""
    with open(path, "rb") as fh:
        if fh.read(len(MAGIC)) != MAGIC:
            raise RecordingError(f"{path} is not a slipfleet recording (version 1)")
        while True:
            head = fh.read(_HEADER.size)
            if len(head) < _HEADER.size:
                return
            key_len, payload_len, stamp_ns = _HEADER.unpack(head)
            if key_len > MAX_KEY_BYTES or payload_len > MAX_PAYLOAD_BYTES:
                raise RecordingError(f"{path}: corrupt record header")
            body = fh.read(key_len + payload_len)
            if len(body) < key_len + payload_len:
                return
            try:
                key = body[:key_len].decode()
            except UnicodeDecodeError as exc:
                raise RecordingError(f"{path}: corrupt record key") from exc
            yield Record(key, stamp_ns, body[key_len:])
