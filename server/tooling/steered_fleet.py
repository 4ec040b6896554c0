"""Simulated steered four-wheel vehicles (kind ``wheeled_4wd_steered``) for the fleet publisher.

:class:`SteeredFleetSim` is a :class:`~server.tooling.fleet_sim.FleetSim` whose runs come from
:func:`estimator.sim.four_wheel.simulate_four_wheel` instead of the tractor simulator: each
packet of the run (IMU batch, CAN wheel speeds ``wheel_speeds4``, steering-wheel angles
``steering``, GNSS epoch) becomes one wire packet, sent when its last sample is in, and the
vehicle publishes its config (kind ``wheeled_4wd_steered``: the friction estimator by default).
Publishing, looping and stamp shifting are the tractors' (:func:`publish_fleets` sends both on
one schedule).

Simulating is slow (the truth is integrated at 2 ms: a few seconds of CPU per simulated
second), so a fleet simulates ``distinct_runs`` runs at most and shares them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from estimator.base import Measurement
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4
from server.protocol.keys import Stream
from server.tooling.fleet_sim import FleetSim, SimPacket, _Vehicle

if TYPE_CHECKING:
    from estimator.sim.four_wheel import Manoeuvre

__all__ = ["DEMO_DRIVE_NAME", "SteeredFleetSim", "demo_drive", "steered_packets"]

DEMO_DRIVE_NAME = "demo_loop"
_KMH = 1.0 / 3.6

_STREAM_OF: dict[type, Stream] = {
    GnssSample: Stream.GNSS,
    ImuBatch: Stream.IMU,
    WheelSpeeds4: Stream.WHEEL_SPEEDS4,
    SteeringAngles: Stream.STEERING,
}


def demo_drive() -> Manoeuvre:
    """A 30 s loop that shows μ informed, held and changing: 4 s straight at 40 km/h (the
    front end calibrates the radii), accelerating to 60 km/h, a 60° steering-wheel step and
    back on μ 0.8, a straight stretch (μ uninformed: held), a 60° step the other way on a wet
    patch of μ 0.35, then back to 40 km/h and μ 0.8 so the next loop starts where this ends.
    """
    from estimator.sim.four_wheel import LEAD_S, Manoeuvre  # the simulator only when simulating

    t0 = LEAD_S
    speed = ((0.0, 40 * _KMH), (t0, 40 * _KMH), (t0 + 4, 60 * _KMH), (t0 + 21, 60 * _KMH),
             (t0 + 25, 40 * _KMH), (1e4, 40 * _KMH))  # fmt: skip
    deg60 = math.radians(60.0)
    steer = ((0.0, 0.0), (t0 + 5, 0.0), (t0 + 5.3, deg60), (t0 + 8, deg60), (t0 + 8.5, 0.0),
             (t0 + 15, 0.0), (t0 + 15.3, -deg60), (t0 + 18, -deg60), (t0 + 18.5, 0.0),
             (1e4, 0.0))  # fmt: skip
    mu = ((0.0, 0.8), (t0 + 12, 0.8), (t0 + 12.001, 0.35), (t0 + 20, 0.35),
          (t0 + 20.001, 0.8), (1e4, 0.8))  # fmt: skip
    return Manoeuvre(DEMO_DRIVE_NAME, t0 + 26.0, speed, steer, mu, t0, t0 + 12.0)


def _last_stamp_ns(m: Measurement) -> int:
    if isinstance(m, GnssSample):
        return int(m.stamp_ns)
    return int(m.stamp_ns[-1])


def steered_packets(measurements: Sequence[Measurement], start_ns: int) -> list[SimPacket]:
    """One wire packet per measurement of a four-wheel run, arriving when its last sample is in
    (``arrival_offset_ns`` after ``start_ns``), in arrival order."""
    out = [
        SimPacket(_last_stamp_ns(m) - start_ns, _STREAM_OF[type(m)], (m,))
        for m in measurements
        if isinstance(m, GnssSample) or len(m.stamp_ns)
    ]
    out.sort(key=lambda p: p.arrival_offset_ns)  # stable: a packet's streams keep their order
    return out


class SteeredFleetSim(FleetSim):
    """Publishes ``n_vehicles`` simulated steered four-wheel vehicles.

    Takes :class:`FleetSim`'s arguments (``scenario`` and simulator overrides aside) and
    ``manoeuvres``: the distinct runs' manoeuvres, vehicle ``i`` driving run
    ``i % len(manoeuvres)`` (default: :func:`demo_drive`), run ``k`` seeded ``seed + k``.
    """

    def __init__(
        self, session: Any, n_vehicles: int, *, manoeuvres: Sequence[Manoeuvre] = (), **kw: Any
    ) -> None:
        self._manoeuvres = list(manoeuvres) or [demo_drive()]
        kw.setdefault("distinct_runs", len(self._manoeuvres))
        super().__init__(session, n_vehicles, **kw)

    def _build(self) -> list[_Vehicle]:
        """Simulate the distinct runs (one batched integration) and lay the vehicles out
        over the tick as :class:`FleetSim` does; stamps are anchored as publishing starts."""
        from estimator.sim.four_wheel import simulate_four_wheel

        k_runs = range(self._distinct)
        runs = simulate_four_wheel(
            [self._manoeuvres[k % len(self._manoeuvres)] for k in k_runs],
            seeds=[self._seed + k for k in k_runs],
            start_ns=self._clock(),
        )
        return self._lay_out(
            [(r.start_ns, steered_packets(r.measurements, r.start_ns), r.config) for r in runs]
        )
