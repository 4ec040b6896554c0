"""What a vehicle's estimators are handed of its released packets.

The reorder buffer is generic over the streams (:mod:`server.protocol.streams`): it releases
packets in sensor-time order and reports, per cumulative stream, data missing after a time
(:class:`~server.ingest.reorder.StreamGap`). This module turns that into what an estimator
takes: the measurements of the streams it reads (by stream name), and for wheel data missing
an :class:`estimator.types.WheelGap`, told before the first data fed after the gap.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Sequence

from estimator.base import Measurement
from estimator.catalog import SPECS
from estimator.types import WheelGap
from server.ingest.reorder import DEFAULT_STREAMS, StreamGap
from server.protocol.base import Packet
from server.protocol.keys import Stream

__all__ = ["ESTIMATOR_STREAMS", "fed", "spec_streams", "wheel_gaps"]

#: The streams some estimator of the catalog reads (its spec's ``inputs``); the registry hands
#: each measurement on only to the estimators whose spec names its stream. Packets of other
#: streams are accepted, counted and ordered, and reach no estimator.
ESTIMATOR_STREAMS: frozenset[Stream] = frozenset(
    Stream(name) for spec in SPECS.values() for name in spec.inputs
)


def spec_streams(estimators: Sequence[str]) -> tuple[Stream, ...]:
    """The streams a vehicle running ``estimators`` is expected to send, for its reorder
    buffer to wait for: every stream their specs' ``inputs`` name (a tractor's GNSS, IMU and
    wheel edges; a crawler's GNSS, IMU, odometer and sprockets), :data:`DEFAULT_STREAMS` for
    a vehicle that runs none."""
    names = {name for e in estimators for name in SPECS[e].inputs}
    return tuple(Stream(n) for n in sorted(names)) if names else DEFAULT_STREAMS


def fed(packet: Packet, streams: Collection[Stream] = ESTIMATOR_STREAMS) -> tuple[Measurement, ...]:
    """The measurements of ``packet`` for estimators that read ``streams`` (none if its
    stream is not one of them)."""
    return packet.measurements if packet.stream in streams else ()


def wheel_gaps(gaps: Iterable[StreamGap]) -> list[tuple[WheelGap, Packet | None]]:
    """The wheel-data notices of ``gaps``, each with the packet it goes before (None: after
    the release's packets), in order.

    Wheel edges count wheel angle: with the wheel data behind the ticks due (``until_ns``
    given) those ticks get no wheel speed; with it lost (``until_ns`` None) the wheels' fits
    start afresh (:class:`~estimator.types.WheelGap`). Gaps of other cumulative streams have
    no notice yet: no estimator reads them.
    """
    return [
        (WheelGap(after_ns=g.after_ns, until_ns=g.until_ns), g.before)
        for g in gaps
        if g.stream is Stream.WHEELS
    ]
