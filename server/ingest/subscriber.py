"""Zenoh subscribers and the ingest thread.

Two subscriptions under ``<prefix>/<vehicle_filter>/``:

* ``sensors/**`` into a bounded :class:`zenoh.handlers.FifoChannel` of
  ``ZenohSettings.channel_capacity`` samples. Zenoh's threads only enqueue; the ingest thread
  takes samples in bursts (up to :data:`BURST`; after the first sample of a burst it waits
  ``IngestSettings.gather_ms`` for more, unless a backlog fills whole bursts) and hands each
  burst's ``(key, payload)`` list to ``take``, on this thread: the in-process pipeline queues
  it for its own thread, which decodes it together with the pure codec
  (:func:`server.protocol.burst.decode_burst`: one numpy pass per stream for the array checks);
  the worker pool sends each vehicle's packets to its worker, which does the same. When they
  fall behind, ``take`` blocks, the channel fills, and Zenoh's BLOCK
  congestion control slows the publishers: nothing is dropped silently.
* Before a sample's payload is copied out of Zenoh its length is read (``len`` of the
  ``ZBytes``, no copy): one over ``IngestSettings.max_payload_bytes`` is refused as
  ``oversize``, one its vehicle has no byte rate left for (:class:`~server.ingest.limits.ByteRate`)
  as ``over_rate``. Refused packets go to ``refuse`` as ``(key, reason)`` to be counted; raw
  packets are stored later, once the decoder accepted them (the pipeline's ``raw_sink``).
* ``config`` into a small FIFO that the pipeline thread polls with :meth:`poll_configs`
  (configs are rare; polling is one non-blocking ``try_recv``).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from estimator.config import VehicleConfig
from server.ingest.limits import ByteRate
from server.protocol.codec import DecodeError, Packet, decode_config
from server.protocol.keys import CONFIG_SUFFIX, SENSORS_CHUNK
from server.settings import IngestSettings, ZenohSettings

__all__ = ["BURST", "ConfigUpdate", "IngestItem", "IngestSubscriber", "RawPacket", "Refusal"]

log = logging.getLogger(__name__)

#: Samples decoded per hand-over to the pipeline, at most.
BURST = 512

CONFIG_CHANNEL_CAPACITY = 256

#: Keys whose byte-rate bucket the ingest thread keeps (:meth:`IngestSubscriber._rate_key`).
RATE_KEYS_HELD = 65_536


@dataclass(frozen=True, slots=True)
class ConfigUpdate:
    """A vehicle configuration received on ``<prefix>/<id>/config``."""

    vehicle_id: str
    config: VehicleConfig


IngestItem = Packet | DecodeError

#: ``(vehicle_id, received_ns, key, payload)`` of one packet as it arrived.
RawPacket = tuple[str, int, str, bytes]

#: ``(key, reason)`` of a packet refused before its payload was copied: ``oversize`` or
#: ``over_rate``.
Refusal = tuple[str, str]


class IngestSubscriber:
    """Declares the subscribers and runs the ingest thread.

    Parameters
    ----------
    session : zenoh.Session
    zenoh_settings, ingest_settings
        Prefix, vehicle filter, channel capacity; payload size limit.
    take : callable
        Receives each burst's ``(key, payload)`` packets as they arrived; may block
        (backpressure).
    refuse : callable, optional
        Receives the packets refused from their length, as :data:`Refusal` pairs, to count
        them (without it they are dropped uncounted).
    """

    def __init__(
        self,
        session: zenoh.Session,
        zenoh_settings: ZenohSettings,
        ingest_settings: IngestSettings,
        take: Callable[[list[tuple[str, bytes]]], None],
        refuse: Callable[[list[Refusal]], object] | None = None,
    ) -> None:
        self._session = session
        self._take = take
        self._refuse = refuse
        self._max_payload = ingest_settings.max_payload_bytes
        self._rate = ByteRate(
            ingest_settings.vehicle_max_bytes_per_s, ingest_settings.vehicle_burst_bytes
        )
        self._rate_on = self._rate.enabled
        self._rate_keys: dict[str, str] = {}  # key -> its byte-rate bucket (_rate_key)
        self._zs = zenoh_settings
        self._gather_s = ingest_settings.gather_ms / 1000
        self._thread: threading.Thread | None = None
        self._sensors: zenoh.Subscriber[zenoh.Handler[zenoh.Sample]] | None = None
        self._config: zenoh.Subscriber[zenoh.Handler[zenoh.Sample]] | None = None
        self._stopping = threading.Event()

    @property
    def sensors_key(self) -> str:
        """The sensor subscription's key expression."""
        base = zenoh.KeyExpr(self._zs.key_prefix).join(self._zs.vehicle_filter)
        return str(base.join(SENSORS_CHUNK).join("**"))

    @property
    def config_key(self) -> str:
        """The config subscription's key expression."""
        return str(
            zenoh.KeyExpr(self._zs.key_prefix).join(self._zs.vehicle_filter).join(CONFIG_SUFFIX)
        )

    def start(self) -> None:
        """Declare the subscribers and start the ingest thread."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._sensors = self._session.declare_subscriber(
            self.sensors_key, zenoh.handlers.FifoChannel(self._zs.channel_capacity)
        )
        self._config = self._session.declare_subscriber(
            self.config_key, zenoh.handlers.FifoChannel(CONFIG_CHANNEL_CAPACITY)
        )
        self._thread = threading.Thread(target=self._run, name="slipfleet-ingest", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Undeclare the subscribers (wakes the thread) and join it."""
        self._stopping.set()
        for sub in (self._sensors, self._config):
            if sub is not None:
                # a closed session has undeclared it already
                with contextlib.suppress(zenoh.ZError):
                    sub.undeclare()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("ingest thread did not stop within %.1f s", timeout_s)

    def poll_configs(self) -> list[ConfigUpdate]:
        """Configs received since the last call (refused ones are logged and skipped)."""
        out: list[ConfigUpdate] = []
        if self._config is None or self._stopping.is_set():
            return out
        handler = self._config.handler
        while (sample := handler.try_recv()) is not None:
            try:
                vid, cfg = decode_config(
                    str(sample.key_expr),
                    sample.payload.to_bytes(),
                    prefix=self._zs.key_prefix,
                    max_payload_bytes=self._max_payload,
                )
            except DecodeError as exc:
                log.warning("refused vehicle config on %s: %s", sample.key_expr, exc)
                continue
            out.append(ConfigUpdate(vid, cfg))
        return out

    def _run(self) -> None:
        assert self._sensors is not None
        sensors = self._sensors.handler
        full = False
        closed = False
        while not closed:
            try:
                first = sensors.recv()
            except zenoh.ZError:
                return  # channel closed: subscriber undeclared
            if not full and self._gather_s > 0:
                # let a burst gather: the decoder's cost per packet falls with the burst size,
                # and the pipeline releases packets only at its ticks anyway
                time.sleep(self._gather_s)
            received: list[tuple[str, bytes]] = []
            refused: list[Refusal] = []
            self._admit(first, received, refused)
            taken = 1
            try:
                while taken < BURST and (sample := sensors.try_recv()) is not None:
                    self._admit(sample, received, refused)
                    taken += 1
            except zenoh.ZError:
                closed = True  # undeclared while the burst gathered: deliver it, then stop
            full = taken == BURST  # a backlog: no gathering until it is worked off
            if refused and self._refuse is not None:
                self._refuse(refused)
            if not received:
                continue
            self._take(received)

    def _admit(
        self, sample: zenoh.Sample, received: list[tuple[str, bytes]], refused: list[Refusal]
    ) -> None:
        """Copy ``sample`` into ``received``, or refuse it from its length alone."""
        key = str(sample.key_expr)
        payload = sample.payload
        size = len(payload)  # ZBytes' length: nothing copied yet
        if size > self._max_payload:
            refused.append((key, "oversize"))
        elif self._rate_on and not self._rate.allow(self._rate_key(key), size):
            refused.append((key, "over_rate"))
        else:
            received.append((key, payload.to_bytes()))

    def _rate_key(self, key: str) -> str:
        """The byte-rate bucket of a key: its vehicle chunk (the whole key if it has none).
        Kept per key (a fleet repeats its vehicles' few keys; emptied past
        :data:`RATE_KEYS_HELD`, so random keys cannot grow memory)."""
        bucket = self._rate_keys.get(key)
        if bucket is None:
            if len(self._rate_keys) >= RATE_KEYS_HELD:
                self._rate_keys.clear()
            rest = key[len(self._zs.key_prefix) + 1 :]
            bucket = self._rate_keys[key] = rest.split("/", 1)[0] or key
        return bucket
