"""Simulated crawlers (kind ``tracked``) for the fleet publisher.

:class:`TrackedFleetSim` is a :class:`~server.tooling.fleet_sim.FleetSim` whose runs come from
the crawler simulator (:mod:`estimator.sim.tracked`) instead of the tractor's: every 100 ms
window of a run becomes one wire packet per stream (IMU batch, GNSS epoch, odometer edges,
both sprockets' edges together), sent at the window's end. Edge packets carry ``until_ns``
(the window's end): the edge streams are complete up to it, and a window without an edge (a
stopped crawler) is sent as a heartbeat rather than left out. The vehicle publishes its config
(kind ``tracked``: the tracked estimator by default). Publishing, looping and stamp shifting
are the tractors' (:func:`~server.tooling.fleet_sim.publish_fleets` sends both on one
schedule).

The crawlers drive :func:`demo_route` unless given routes: a one-minute loop through every
motion state with a GNSS outage, so a demo shows states, track slip and dead reckoning.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from estimator.base import Measurement
from estimator.types import GnssSample, ImuBatch, OdometerEdges, SprocketEdges
from server.protocol.keys import Stream
from server.tooling.fleet_sim import FleetSim, SimPacket, _Vehicle

if TYPE_CHECKING:
    from estimator.sim.tracked import Route, TrackedRun

__all__ = ["DEMO_ROUTE_NAME", "TrackedFleetSim", "demo_route", "tracked_packets"]

DEMO_ROUTE_NAME = "crawler_loop"
#: GNSS outage of the demo route: ``(start_s, duration_s)``.
DEMO_OUTAGE_S = (22.0, 40.0)


def demo_route() -> Route:
    """A 76 s loop on firm ground: a stop, a straight at 8 m/s, a left arc, a right
    separated turn, a low-gear straight, a left pivot and a stop, GNSS lost for 40 s from
    22 s (dead-reckoned through the turns; long enough for the long-dead-reckoning alert)."""
    from estimator.sim.tracked.route import FIRM, Route, Segment
    from estimator.tracked.model import MotionState as M

    segments = (
        Segment(M.STOP, 4.0, 0.0),
        Segment(M.STRAIGHT, 14.0, 8.0),
        Segment(M.STRAIGHT, 5.0, 3.0),
        Segment(M.ARC, 7.0, 3.0, left=True),
        Segment(M.STRAIGHT, 10.0, 8.0),
        Segment(M.STRAIGHT, 3.0, 5.0),
        Segment(M.SEPARATED, 9.0, 5.0, left=False, ratio=0.9),
        Segment(M.STRAIGHT, 2.0, 3.0),
        Segment(M.LOW_STRAIGHT, 9.0, 3.0),
        Segment(M.STRAIGHT, 2.0, 1.5),
        Segment(M.PIVOT, 4.0, 1.5, left=True),
        Segment(M.STRAIGHT, 3.0, 0.5),
        Segment(M.STOP, 4.0, 0.0),
    )
    return Route(DEMO_ROUTE_NAME, segments, FIRM, (DEMO_OUTAGE_S,))


def _packet(offset_ns: int, until_ns: int, group: list[Measurement]) -> SimPacket:
    """The wire packet of one window's measurements of one stream."""
    first = group[0]
    if isinstance(first, GnssSample):
        return SimPacket(offset_ns, Stream.GNSS, (first,))
    if isinstance(first, ImuBatch):
        return SimPacket(offset_ns, Stream.IMU, (first,))
    if isinstance(first, OdometerEdges):  # no edge in the window: a heartbeat
        edges = (first,) if len(first.stamp_ns) else ()
        return SimPacket(offset_ns, Stream.ODOMETER, edges, until_ns)
    sides = tuple(m for m in group if isinstance(m, SprocketEdges) and len(m.stamp_ns))
    return SimPacket(offset_ns, Stream.SPROCKETS, sides, until_ns)


def tracked_packets(
    measurements: Sequence[tuple[int, Measurement]], start_ns: int
) -> list[SimPacket]:
    """One wire packet per stream and 100 ms window of a crawler run (``(key_ns, measurement)``
    sorted by key, :class:`~estimator.sim.tracked.TrackedRun`), in arrival order: GNSS, odometer,
    sprockets (both tracks), IMU. Edge packets carry the window's end as ``until_ns``."""
    out = []
    for (key, _), items in itertools.groupby(measurements, key=lambda km: (km[0], type(km[1]))):
        group = [m for _, m in items]
        if isinstance(group[0], ImuBatch) and not len(group[0].stamp_ns):
            continue
        out.append(_packet(key - start_ns, key, group))
    return out


class TrackedFleetSim(FleetSim):
    """Publishes ``n_vehicles`` simulated crawlers.

    Takes :class:`FleetSim`'s arguments (``scenario`` and simulator overrides aside) and
    ``routes``: the distinct runs' routes, vehicle ``i`` driving run ``i % len(routes)``
    (default: :func:`demo_route`), run ``k`` seeded ``seed + k`` at the origin
    :meth:`FleetSim.spread_origin` gives vehicle number ``first_index + k`` (beside the
    tractors, not on top of them).
    """

    def __init__(
        self, session: Any, n_vehicles: int, *, routes: Sequence[Route] = (), **kw: Any
    ) -> None:
        self._routes = list(routes) or [demo_route()]
        kw.setdefault("distinct_runs", len(self._routes))
        super().__init__(session, n_vehicles, **kw)

    def _runs(self) -> list[TrackedRun]:
        from estimator.geo import EnuFrame
        from estimator.sim.tracked import simulate_route

        start_ns = self._clock()
        out = []
        for k in range(self._distinct):
            where = self.spread_origin(self._first - 1 + k)
            frame = EnuFrame(where["origin_lat_deg"], where["origin_lon_deg"], 10.0)
            route = self._routes[k % len(self._routes)]
            out.append(simulate_route(route, self._seed + k, start_ns=start_ns, frame=frame))
        return out

    def _build(self) -> list[_Vehicle]:
        """Simulate the distinct runs and lay the vehicles out over the tick as
        :class:`FleetSim` does; stamps are anchored as publishing starts."""
        return self._lay_out(
            [
                (r.start_ns, tracked_packets(r.measurements, r.start_ns), r.config)
                for r in self._runs()
            ]
        )
