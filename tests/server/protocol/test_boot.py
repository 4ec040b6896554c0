"""The optional header field ``boot`` (the sender's boot id): encoded, decoded alike by the
codec and the burst decoder, refused with a reason when it is not an int in [0, 2**63)."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import pytest

from estimator.types import GnssSample, ImuBatch, OdometerEdges, Wheel, WheelEdges
from server.protocol import (
    DecodeError,
    EncodeError,
    decode,
    encode_gnss,
    encode_imu,
    encode_odometer,
    encode_wheel_edges,
)
from server.protocol.burst import MIN_BATCHED, decode_burst

T0 = 1_763_700_000 * 10**9
MS = 1_000_000
BOOT = 2**63 - 1


def _payloads(boot: int | None) -> dict[str, bytes]:
    """A packet of several streams (a heartbeat among them), each carrying ``boot``."""
    t = T0 + np.arange(10, dtype=np.int64) * 10 * MS
    gnss = GnssSample(T0, (0.0, 1.0, 0.0), 0.0, 0.0, 0.0, 48.0, 11.0, 500.0)
    return {
        "imu": encode_imu(ImuBatch(t, np.zeros((10, 3)), np.zeros((10, 3))), 3, boot=boot),
        "gnss": encode_gnss(gnss, 4, boot=boot),
        "wheels": encode_wheel_edges([WheelEdges(Wheel.LEFT, t)], 5, boot=boot),
        "odometer": encode_odometer(OdometerEdges(np.zeros(0, np.int64)), 6, T0, boot=boot),
    }


@pytest.mark.parametrize("boot", [None, 0, 12345, BOOT])
def test_boot_round_trips_on_every_path(boot: int | None) -> None:
    for stream, payload in _payloads(boot).items():
        key = f"fleet/v1/sensors/{stream}"
        alone = decode(key, payload)
        assert alone.boot == boot
        burst = decode_burst([(key, payload)] * MIN_BATCHED)
        assert all(not isinstance(p, DecodeError) and p.boot == boot for p in burst), stream
        assert (b"boot" in payload) is (boot is not None)


def _with(payload: bytes, value: Any) -> bytes:
    m = msgpack.unpackb(payload)
    m["boot"] = value
    return msgpack.packb(m, use_bin_type=True)


@pytest.mark.parametrize(
    ("value", "reason"),
    [
        (-1, "out_of_range"),
        (2**63, "out_of_range"),
        (2**64 - 1, "out_of_range"),
        (1.0, "wrong_type"),
        ("7", "wrong_type"),
        (None, "wrong_type"),
        (True, "wrong_type"),
    ],
)
def test_bad_boot_is_refused_with_its_reason(value: Any, reason: str) -> None:
    for stream, payload in _payloads(1).items():
        key = f"fleet/v1/sensors/{stream}"
        bad = _with(payload, value)
        with pytest.raises(DecodeError) as exc:
            decode(key, bad)
        assert exc.value.reason == reason and "boot" in exc.value.detail
        # in a burst the bad packet is refused alike, its neighbours are not
        good = (key, payload)
        items = decode_burst([good] * (MIN_BATCHED - 1) + [(key, bad)])
        assert isinstance(items[-1], DecodeError) and items[-1].reason == reason
        assert all(not isinstance(p, DecodeError) and p.boot == 1 for p in items[:-1])


@pytest.mark.parametrize("value", [-1, 2**63, 1.5])
def test_bad_boot_is_not_encoded(value: Any) -> None:
    t = T0 + np.arange(3, dtype=np.int64) * MS
    with pytest.raises(EncodeError, match="boot"):
        encode_imu(ImuBatch(t, np.zeros((3, 3)), np.zeros((3, 3))), 0, boot=value)
