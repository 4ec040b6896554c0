"""One declaration per sensor stream: name → wire struct → measurement → reorder priority.

:data:`STREAMS` holds a frozen :class:`StreamSpec` per :class:`~server.protocol.keys.Stream`;
the codec (:func:`server.protocol.codec.decode`), the burst decoder
(:mod:`server.protocol.burst`) and the reorder buffer (:mod:`server.ingest.reorder`) read it
and name no stream themselves. Adding a stream is a :class:`Stream` member, its measurement
type (:mod:`estimator.types`), its wire struct (:mod:`server.protocol.wire`), its layout or
decoder and encoder, one entry here, and its ``docs/protocol.md`` section.

Stream names are the contract with the estimators: an estimator states the streams it takes
by these names, and a vehicle's packets of other streams are accepted, counted and ordered
but reach no estimator.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import msgspec

from estimator.types import (
    GnssSample,
    ImuBatch,
    OdometerEdges,
    SprocketEdges,
    SteeringAngles,
    WheelEdges,
    WheelSpeeds,
    WheelSpeeds4,
)
from server.protocol import drivetrain, sensors, wire
from server.protocol.base import Body, Ctx, Limits
from server.protocol.keys import Stream
from server.protocol.layouts import Edges, Sampled

__all__ = ["STREAMS", "WIRE_STREAM", "Layout", "StreamSpec", "spec_of"]

#: A payload layout whose arrays the burst decoder checks over many packets at once.
Layout = Sampled | Edges


def _no_batch(p: Any) -> Layout | None:
    """A stream whose packets the burst decoder takes one by one."""
    return None


@dataclass(frozen=True, slots=True)
class StreamSpec:
    """What one sensor stream carries and how it is checked and ordered.

    Attributes
    ----------
    stream : Stream
        The name: the key's last chunk and the payload's ``sensor``.
    wire : type
        The msgspec struct of the stream's valid payloads (the burst decoder's fast path).
    measurements : tuple of type
        The measurement types its packets carry (:mod:`estimator.types`).
    decode : callable ``(ctx, map, limits) -> (measurements, first_ns, last_ns)``
        The per-packet rules on the payload map, header already checked: the first rule
        broken is the refusal (:class:`~server.protocol.base.DecodeError`).
    batch : callable ``(struct) -> Layout or None``
        The layout whose arrays the burst decoder checks for a decoded struct; None: the
        packet is decoded alone (or by ``single``).
    layout : Layout or None
        The one layout of every packet of the stream (``batch`` returns it), so the burst
        decoder needs no call per packet to find it; None: ``batch`` decides per packet.
    single : callable ``(struct, limits) -> (measurements, first_ns, last_ns) or None``
        The burst decoder's check of one decoded struct of a stream without arrays to batch;
        None from it: the per-packet rules decide.
    priority : int
        Order among packets of the same first sample time in the reorder buffer (lower first).
    cumulative : bool
        The stream counts something (edges count wheel angle): data missing while ticks are
        due, or lost, must be told to the estimators that take it
        (:mod:`server.ingest.adapter`), since no edge reads as a slower wheel.
    """

    stream: Stream
    wire: type[msgspec.Struct]
    measurements: tuple[type, ...]
    decode: Callable[[Ctx, dict[str, Any], Limits], Body]
    batch: Callable[[Any], Layout | None] = _no_batch
    single: Callable[[Any, Limits], Body | None] | None = None
    layout: Layout | None = None
    priority: int = 0
    cumulative: bool = False


def _wheels_layout(p: wire.WheelsPacket) -> Layout:
    return sensors.WHEEL_MODES[p.mode]


def _fixed(
    stream: Stream,
    wire_type: type[msgspec.Struct],
    measurement: type,
    layout: Layout,
    priority: int,
    *,
    cumulative: bool = False,
) -> StreamSpec:
    """A stream whose every packet has the one ``layout``: it decodes and batches by it."""
    return StreamSpec(
        stream=stream,
        wire=wire_type,
        measurements=(measurement,),
        decode=layout.decode,
        batch=lambda p: layout,
        layout=layout,
        priority=priority,
        cumulative=cumulative,
    )


_SPECS = (
    StreamSpec(
        stream=Stream.GNSS,
        wire=wire.GnssPacket,
        measurements=(GnssSample,),
        decode=sensors.decode_gnss,
        single=sensors.gnss_struct,
        priority=0,
    ),
    _fixed(Stream.IMU, wire.ImuPacket, ImuBatch, sensors.IMU, priority=1),
    StreamSpec(
        stream=Stream.WHEELS,
        wire=wire.WheelsPacket,
        measurements=(WheelEdges, WheelSpeeds),
        decode=sensors.decode_wheels,
        batch=_wheels_layout,
        priority=2,
        cumulative=True,
    ),
    StreamSpec(
        stream=Stream.ODOMETER,
        wire=wire.OdometerPacket,
        measurements=(OdometerEdges,),
        decode=drivetrain.decode_odometer,
        priority=3,
        cumulative=True,
    ),
    _fixed(
        Stream.SPROCKETS,
        wire.SprocketsPacket,
        SprocketEdges,
        drivetrain.SPROCKETS,
        priority=4,
        cumulative=True,
    ),
    _fixed(Stream.STEERING, wire.SteeringPacket, SteeringAngles, drivetrain.STEERING, priority=5),
    _fixed(
        Stream.WHEEL_SPEEDS4,
        wire.WheelSpeeds4Packet,
        WheelSpeeds4,
        drivetrain.WHEEL_SPEEDS4,
        priority=6,
    ),
)

#: Every stream's declaration, by stream.
STREAMS: Mapping[Stream, StreamSpec] = MappingProxyType({s.stream: s for s in _SPECS})

#: The stream of each wire struct.
WIRE_STREAM: Mapping[type, Stream] = MappingProxyType({s.wire: s.stream for s in _SPECS})


def spec_of(stream: Stream | str) -> StreamSpec:
    """The declaration of ``stream`` (a :class:`Stream` or its name; ValueError if none)."""
    return STREAMS[Stream(stream)]


def _check_complete() -> None:
    """Every stream is declared once, with a distinct priority (import-time invariant)."""
    missing = set(Stream) - set(STREAMS)
    if missing or len(STREAMS) != len(_SPECS):
        raise RuntimeError(f"streams declared not exactly once: missing {sorted(missing)}")
    if len({s.priority for s in _SPECS}) != len(_SPECS):
        raise RuntimeError("two streams share a reorder priority")


_check_complete()
