"""Key expressions of the wire protocol (pure string handling, no Zenoh import).

Every vehicle publishes under ``<prefix>/<vehicle_id>/``::

    <prefix>/<vehicle_id>/sensors/gnss     one GNSS epoch per packet
    <prefix>/<vehicle_id>/sensors/imu      a batch of IMU samples
    <prefix>/<vehicle_id>/sensors/wheels   a batch of wheel edges or wheel speeds
    <prefix>/<vehicle_id>/sensors/<stream> any other stream of :class:`Stream`
    <prefix>/<vehicle_id>/config           optional: the vehicle's configuration (JSON)

``prefix`` is ``ZenohSettings.key_prefix`` (default ``fleet``) and may itself contain ``/``.
A vehicle id is 1-64 characters of ``[A-Za-z0-9_.-]`` starting with a letter or digit, so it is
always exactly one key-expression chunk and never a wildcard.
"""

from __future__ import annotations

import functools
import re
from enum import StrEnum

__all__ = [
    "CONFIG_SUFFIX",
    "SENSORS_CHUNK",
    "Stream",
    "config_key",
    "is_valid_vehicle_id",
    "parse_key",
    "sensor_key",
]

SENSORS_CHUNK = "sensors"
CONFIG_SUFFIX = "config"

_VEHICLE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")


class Stream(StrEnum):
    """A vehicle's sensor stream; the last chunk of its key expression and the ``sensor`` of
    its payloads. What each carries is declared in :mod:`server.protocol.streams`."""

    GNSS = "gnss"
    IMU = "imu"
    WHEELS = "wheels"
    ODOMETER = "odometer"
    SPROCKETS = "sprockets"
    STEERING = "steering"
    WHEEL_SPEEDS4 = "wheel_speeds4"


def is_valid_vehicle_id(vehicle_id: str) -> bool:
    """True when ``vehicle_id`` is usable as one key-expression chunk (see module docstring)."""
    return _VEHICLE_ID.fullmatch(vehicle_id) is not None


def _check(prefix: str, vehicle_id: str) -> None:
    if not is_valid_vehicle_id(vehicle_id):
        raise ValueError(f"invalid vehicle id {vehicle_id!r}")
    if (
        not prefix
        or prefix.startswith("/")
        or prefix.endswith("/")
        or any(c in prefix for c in "*$?#")
    ):
        raise ValueError(f"invalid key prefix {prefix!r}")


def sensor_key(prefix: str, vehicle_id: str, stream: Stream | str) -> str:
    """``<prefix>/<vehicle_id>/sensors/<stream>``."""
    _check(prefix, vehicle_id)
    return f"{prefix}/{vehicle_id}/{SENSORS_CHUNK}/{Stream(stream).value}"


def config_key(prefix: str, vehicle_id: str) -> str:
    """``<prefix>/<vehicle_id>/config``."""
    _check(prefix, vehicle_id)
    return f"{prefix}/{vehicle_id}/{CONFIG_SUFFIX}"


@functools.lru_cache(maxsize=65_536)
def parse_key(key: str, prefix: str) -> tuple[str, Stream | None]:
    """Split a key into ``(vehicle_id, stream)``; ``stream`` is None for the config key.

    Raises ``ValueError`` when ``key`` is not one of the protocol's keys under ``prefix``.
    Results are cached (a fleet repeats the same few keys per vehicle).
    """
    head = prefix + "/"
    if not key.startswith(head):
        raise ValueError(f"key {key!r} is not under prefix {prefix!r}")
    parts = key[len(head) :].split("/")
    if not parts or not is_valid_vehicle_id(parts[0]):
        raise ValueError(f"key {key!r} has no valid vehicle id")
    if len(parts) == 2 and parts[1] == CONFIG_SUFFIX:
        return parts[0], None
    if len(parts) == 3 and parts[1] == SENSORS_CHUNK:
        try:
            return parts[0], Stream(parts[2])
        except ValueError:
            raise ValueError(f"key {key!r}: unknown stream {parts[2]!r}") from None
    raise ValueError(f"key {key!r} is not a sensor or config key")
