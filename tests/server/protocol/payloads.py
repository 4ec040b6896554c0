"""Edits of valid msgpack payloads, for the tests of the decoders' refusals."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import msgpack


def set_or_delete(m: dict[str, Any], fields: dict[str, Any]) -> None:
    """Set each of ``fields`` in ``m``, or delete it where its value is None."""
    for k, v in fields.items():
        if v is None:
            m.pop(k, None)
        else:
            m[k] = v


def edited(
    payload: bytes, fields: dict[str, Any], part: Callable[[Any], dict[str, Any]] = lambda m: m
) -> bytes:
    """``payload`` with ``fields`` set or deleted (value None) in ``part`` of its map (default:
    the map itself), packed again."""
    m = msgpack.unpackb(payload, raw=False)
    set_or_delete(part(m), fields)
    return msgpack.packb(m, use_bin_type=True)
