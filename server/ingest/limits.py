"""Byte limits of ingest: what one vehicle may send per second, and what may wait undecoded.

Packet counts alone do not bound memory: a bounded queue of 256 KiB payloads holds gigabytes.
Two limits bound it in bytes:

* :class:`ByteRate` — each vehicle's payload bytes per second, a token bucket of
  ``rate_bps`` refilled continuously and holding at most ``burst_bytes``: a packet that finds
  too few tokens is refused (counted ``rejected_over_rate``), not queued. One vehicle flooding
  its own key cannot take the fleet's share.
* :class:`ByteBudget` — the undecoded bytes waiting for the pipeline, all vehicles together:
  a burst that would pass ``max_bytes`` waits (backpressure, as the packet-count bound of the
  queue), except the first one, so a single burst larger than the budget still moves.

Both are thread-safe where they must be: :class:`ByteRate` is used by the ingest thread only,
:class:`ByteBudget` by the ingest thread (acquire) and the pipeline thread (release).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

from server.protocol.base import DecodeError
from server.protocol.keys import parse_key

__all__ = ["MAX_RATE_VEHICLES", "ByteBudget", "ByteRate", "refusal_errors"]

#: Vehicles whose byte-rate buckets are kept; beyond it the oldest half is dropped (a bucket
#: left out starts full again: random ids cannot grow memory, at worst a burst passes).
MAX_RATE_VEHICLES = 50_000


class ByteRate:
    """Per-vehicle token buckets over payload bytes (``rate_bps`` 0: no limit).

    A bucket holds ``min(burst_bytes, tokens + rate_bps · Δt)``; :meth:`allow` takes ``n``
    tokens when there are that many and answers True, else leaves the bucket and answers False.
    """

    def __init__(
        self,
        rate_bps: int,
        burst_bytes: int,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self._rate_per_ns = rate_bps / 1e9
        self._burst = float(max(burst_bytes, rate_bps))
        self._clock = clock_ns
        # vehicle -> [tokens, stamp ns], updated in place (no tuple made per packet)
        self._buckets: dict[str, list[float]] = {}

    @property
    def enabled(self) -> bool:
        """False when no rate is set (every packet allowed)."""
        return self._rate_per_ns > 0

    def allow(self, vehicle_id: str, n_bytes: int) -> bool:
        """Take ``n_bytes`` from ``vehicle_id``'s bucket if it holds them."""
        if self._rate_per_ns <= 0:
            return True
        now = self._clock()
        bucket = self._buckets.get(vehicle_id)
        if bucket is None:
            if len(self._buckets) >= MAX_RATE_VEHICLES:
                for old in list(self._buckets)[: MAX_RATE_VEHICLES // 2]:
                    del self._buckets[old]
            bucket = self._buckets[vehicle_id] = [self._burst, now]
        tokens = bucket[0] + (now - bucket[1]) * self._rate_per_ns
        if tokens > self._burst:
            tokens = self._burst
        allowed = tokens >= n_bytes
        bucket[0] = tokens - n_bytes if allowed else tokens
        bucket[1] = now
        return allowed


class ByteBudget:
    """Bytes in flight between two threads, at most ``max_bytes`` (see module docstring)."""

    def __init__(self, max_bytes: int) -> None:
        self._max = max_bytes
        self._held = 0
        self._peak = 0
        self._cond = threading.Condition()

    @property
    def held(self) -> int:
        """Bytes acquired and not yet released."""
        return self._held

    @property
    def peak(self) -> int:
        """The most bytes ever held at once."""
        return self._peak

    def acquire(self, n_bytes: int, timeout_s: float) -> bool:
        """Wait until ``n_bytes`` fit (or nothing is held) and take them; False when they did
        not fit within ``timeout_s`` (nothing taken: the caller decides whether to wait on)."""
        with self._cond:
            fits = self._cond.wait_for(
                lambda: self._held == 0 or self._held + n_bytes <= self._max, timeout_s
            )
            if not fits:
                return False
            self._held += n_bytes
            self._peak = max(self._peak, self._held)
            return True

    def release(self, n_bytes: int) -> None:
        """Give back bytes taken by :meth:`acquire`."""
        with self._cond:
            self._held = max(0, self._held - n_bytes)
            self._cond.notify_all()


def refusal_errors(refused: Sequence[tuple[str, str]], prefix: str) -> list[DecodeError]:
    """``(key, reason)`` refusals as the codec's refusals, with the vehicle and stream the key
    names (None where it names none), for the ingest counters."""
    out: list[DecodeError] = []
    for key, reason in refused:
        try:
            vehicle_id, stream = parse_key(key, prefix)
        except ValueError:
            vehicle_id, stream = None, None
        out.append(DecodeError(reason, key, vehicle_id=vehicle_id, stream=stream))
    return out
