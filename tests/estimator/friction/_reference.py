"""The per-vehicle :class:`FrontEnd` ticked on the fleet's grid: the reference the batched
sensor reads and front end are held to."""

from __future__ import annotations

import dataclasses
from typing import Any

from estimator.base import Measurement
from estimator.friction.frontend import FrontEnd
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

TICK_NS = 20_000_000


@dataclasses.dataclass
class Reference:
    """One vehicle: its ticks ``first IMU sample + k·TICK_NS`` (or from ``next_ns``), each
    recorded by :meth:`record` (here the front end's whole tick)."""

    front: FrontEnd
    next_ns: int | None
    ticks: dict[int, Any] = dataclasses.field(default_factory=dict)

    def push(self, m: Measurement) -> None:
        if isinstance(m, ImuBatch):
            self.front.push_imu(m)
        elif isinstance(m, WheelSpeeds4):
            self.front.push_wheels(m)
        elif isinstance(m, SteeringAngles):
            self.front.push_steering(m)
        elif isinstance(m, GnssSample):
            self.front.push_gnss(m)

    def advance(self, until_ns: int) -> None:
        last = self.front.imu_until_ns()
        if last is None:
            return
        if self.next_ns is None:
            self.next_ns = int(self.front.imu[0][0][0]) + TICK_NS
        while self.next_ns <= min(until_ns, last):
            self.record(self.next_ns)
            self.next_ns += TICK_NS

    def record(self, t_ns: int) -> None:
        tick = self.front.tick(t_ns)
        if tick is not None:
            self.ticks[t_ns] = tick
