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
from server.protocol.codec import DecodeError, Packet, decode_config
from server.protocol.keys import CONFIG_SUFFIX, SENSORS_CHUNK, parse_key
from server.settings import IngestSettings, ZenohSettings

__all__ = ["BURST", "ConfigUpdate", "IngestItem", "IngestSubscriber", "RawPacket"]

log = logging.getLogger(__name__)

#: Samples decoded per hand-over to the pipeline, at most.
BURST = 512

CONFIG_CHANNEL_CAPACITY = 256


@dataclass(frozen=True, slots=True)
class ConfigUpdate:
    """A vehicle configuration received on ``<prefix>/<id>/config``."""

    vehicle_id: str
    config: VehicleConfig


IngestItem = Packet | DecodeError

#: ``(vehicle_id, received_ns, key, payload)`` of one packet as it arrived.
RawPacket = tuple[str, int, str, bytes]


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
    raw_sink : callable, optional
        Receives each burst's raw packets as ``(vehicle_id, received_ns, key, payload)``
        (wall-clock receive time; packets whose key names no vehicle are left out), for
        ``StorageSettings.store_raw_packets``.
    """

    def __init__(
        self,
        session: zenoh.Session,
        zenoh_settings: ZenohSettings,
        ingest_settings: IngestSettings,
        take: Callable[[list[tuple[str, bytes]]], None],
        raw_sink: Callable[[list[RawPacket]], object] | None = None,
    ) -> None:
        self._session = session
        self._take = take
        self._max_payload = ingest_settings.max_payload_bytes
        self._zs = zenoh_settings
        self._gather_s = ingest_settings.gather_ms / 1000
        self._raw_sink = raw_sink
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
            received = [(str(first.key_expr), first.payload.to_bytes())]
            try:
                while len(received) < BURST and (sample := sensors.try_recv()) is not None:
                    received.append((str(sample.key_expr), sample.payload.to_bytes()))
            except zenoh.ZError:
                closed = True  # undeclared while the burst gathered: deliver it, then stop
            full = len(received) == BURST  # a backlog: no gathering until it is worked off
            if self._raw_sink is not None:
                self._sink_raw(received)
            self._take(received)

    def _sink_raw(self, received: list[tuple[str, bytes]]) -> None:
        """Hand the burst's packets whose key names a vehicle to the raw sink."""
        assert self._raw_sink is not None
        prefix = self._zs.key_prefix
        now_ns = time.time_ns()
        raw: list[RawPacket] = [
            (vid, now_ns, key, payload)
            for key, payload in received
            if (vid := _vehicle_of(key, prefix)) is not None
        ]
        if raw:
            self._raw_sink(raw)


def _vehicle_of(key: str, prefix: str) -> str | None:
    """The vehicle a sensor key names (None: not a valid sensor key)."""
    try:
        vid, stream = parse_key(key, prefix)
    except ValueError:
        return None
    return vid if stream is not None else None
