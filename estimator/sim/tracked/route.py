"""Routes of the simulated crawler: manoeuvres in order, the ground they cross, GNSS outages.

A route is a list of :class:`Segment` (a motion state held for a duration at a gearbox speed);
:func:`named_route` gives the fixed scenarios, :func:`random_route` draws one from the stated
distributions (:data:`RANDOM_RANGES`). Pure: every draw from the generator handed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from estimator.sim.tracked.terrain import FLAT, Terrain, hill_terrain
from estimator.tracked.model import MotionState

__all__ = [
    "CLOCK_KEYS",
    "CONFIG_NAMES_DATASHEET_SHARE",
    "FIRM",
    "MANOEUVRES",
    "RANDOM_RANGES",
    "SOFT",
    "Ground",
    "Route",
    "Segment",
    "named_route",
    "random_route",
    "route_names",
]

M = MotionState


@dataclass(frozen=True, slots=True)
class Segment:
    """One manoeuvre: the steering levers of ``state`` held for ``duration_s``.

    ``speed_mps`` is the target gearbox output speed (the speed of a track in direct drive);
    ``left`` turns left (else right); ``ratio`` is the slow sprocket's speed over the fast
    one's in a separated turn (between the low gear's 1/1.42 and 1).
    """

    state: MotionState
    duration_s: float
    speed_mps: float
    left: bool = True
    ratio: float = 0.9


@dataclass(frozen=True, slots=True)
class Ground:
    """How the tracks slip on one ground (fractions; slip ``s = (Vs − v)/max(Vs, v)``).

    Traction slip of a driven track ``rolling_slip + accel_slip_per_g·a/g ± turn_slip·B/ρ_t``
    (``a`` the drawbar demand, the hull's own acceleration plus ``g·sin θ``; + on the fast
    side, − on the slow side, ``ρ_t`` the kinematic turning radius); a braked
    track in a pivot is dragged at ``brake_drag`` of the fast track's ground speed; the
    turning pole moves ``L·|a_y|/(2·lateral_resistance·g)`` ahead of the centre; slip wanders
    by an Ornstein-Uhlenbeck texture of ``texture_std`` and varies by ``patch_std`` (relative)
    from one patch of ground to the next (every ``patch_m`` metres).
    """

    name: str
    rolling_slip: float
    accel_slip_per_g: float
    turn_slip: float
    brake_drag: float
    lateral_resistance: float
    texture_std: float
    patch_std: float = 0.15
    patch_m: float = 150.0


FIRM = Ground("firm", 0.015, 0.3, 0.10, 0.2, 0.7, 0.003)
SOFT = Ground("soft", 0.045, 0.6, 0.16, 0.12, 0.45, 0.006)


@dataclass(frozen=True, slots=True)
class Route:
    """Segments, ground, GNSS outages ``(start_s, duration_s)``, initial heading and the
    terrain's slopes (:mod:`~estimator.sim.tracked.terrain`; level by default)."""

    name: str
    segments: tuple[Segment, ...]
    ground: Ground
    outages_s: tuple[tuple[float, float], ...]
    heading0_rad: float = 0.3
    terrain: Terrain = FLAT

    @property
    def duration_s(self) -> float:
        return float(sum(s.duration_s for s in self.segments))


def _leg(straight_mps: float, turn: Segment, seconds: float) -> list[Segment]:
    """A straight at ``straight_mps`` for ``seconds``, a slow-down and the turn."""
    slow = max(1.0, (straight_mps - turn.speed_mps) / 1.2 + 1.0)
    return [
        Segment(M.STRAIGHT, seconds, straight_mps),
        Segment(M.STRAIGHT, slow, turn.speed_mps),
        turn,
    ]


def _base_route() -> list[Segment]:
    """The named long route (≈ 11 min): straights at 10-12 m/s, arcs and separated turns
    both ways, low-gear straights, pivots, a fast pivot (large heading change) and stops."""
    out = [Segment(M.STOP, 5.0, 0.0)]
    out += _leg(11.0, Segment(M.ARC, 8.0, 3.0, left=True), 50.0)
    out += _leg(12.0, Segment(M.SEPARATED, 12.0, 5.0, left=False, ratio=0.9), 40.0)
    out += _leg(10.0, Segment(M.LOW_STRAIGHT, 20.0, 3.0), 30.0)
    out += [Segment(M.STRAIGHT, 4.0, 1.5), Segment(M.PIVOT, 5.0, 1.5, left=True)]
    out += [Segment(M.STRAIGHT, 3.0, 0.5), Segment(M.STOP, 6.0, 0.0)]
    out += _leg(11.0, Segment(M.SEPARATED, 10.0, 6.0, left=True, ratio=0.94), 45.0)
    out += _leg(12.0, Segment(M.ARC, 7.0, 3.0, left=False), 35.0)
    out += _leg(11.0, Segment(M.LOW_STRAIGHT, 15.0, 4.0), 40.0)
    out += [Segment(M.STRAIGHT, 3.0, 4.0), Segment(M.PIVOT, 2.0, 4.0, left=False)]
    out += _leg(12.0, Segment(M.SEPARATED, 15.0, 5.0, left=False, ratio=0.82), 50.0)
    out += _leg(10.0, Segment(M.PIVOT, 4.0, 1.5, left=False), 30.0)
    out += [Segment(M.STRAIGHT, 3.0, 0.5), Segment(M.STOP, 5.0, 0.0)]
    out += _leg(11.0, Segment(M.ARC, 6.0, 3.5, left=True), 40.0)
    out += [
        Segment(M.STRAIGHT, 40.0, 10.0),
        Segment(M.STRAIGHT, 8.0, 0.5),
        Segment(M.STOP, 5.0, 0.0),
    ]
    return out


#: GNSS outage of the named routes: 4 minutes from 150 s (the route covers > 1 km in it).
NAMED_OUTAGE_S = (150.0, 240.0)


def route_names() -> tuple[str, ...]:
    return ("route_firm", "route_soft", "route_firm_hill")


def named_route(name: str) -> Route:
    """``route_firm`` or ``route_soft``: the long route on level firm or soft ground;
    ``route_firm_hill``: the same on firm ground over hills (grades ±10 %, cross grades ±5 %,
    :func:`~estimator.sim.tracked.terrain.hill_terrain`)."""
    grounds = {"route_firm": FIRM, "route_soft": SOFT, "route_firm_hill": FIRM}
    if name not in grounds:
        raise KeyError(f"unknown tracked scenario {name!r}; known: {list(grounds)}")
    terrain = hill_terrain() if name == "route_firm_hill" else FLAT
    return Route(name, tuple(_base_route()), grounds[name], (NAMED_OUTAGE_S,), terrain=terrain)


#: Manoeuvres of random routes: (probability, duration s, gearbox speed m/s), uniform draws.
#: HEADING_JUMP is a fast pivot (the heading turns faster than ``δφ_max`` a tick).
MANOEUVRES: dict[MotionState, tuple[float, tuple[float, float], tuple[float, float]]] = {
    M.STRAIGHT: (0.34, (15.0, 60.0), (6.0, 12.0)),
    M.LOW_STRAIGHT: (0.12, (10.0, 30.0), (2.0, 4.5)),
    M.ARC: (0.14, (4.0, 12.0), (2.0, 4.0)),
    M.SEPARATED: (0.16, (6.0, 20.0), (3.0, 7.0)),
    M.PIVOT: (0.1, (2.0, 6.0), (1.0, 2.0)),
    M.STOP: (0.08, (3.0, 10.0), (0.0, 0.0)),
    M.HEADING_JUMP: (0.06, (1.5, 3.0), (3.3, 4.0)),
}

#: Other ranges random routes draw from (uniform): ground figures (:class:`Ground`), the
#: separated turn's sprocket ratio, the route's duration and its outage's (s), and the
#: gyro's grade (its noise and bias walk over the data sheet's: from the ADIS16470 itself to
#: a consumer part, :class:`~estimator.sim.tracked.sensors.CrawlerSensors`), the receiver's
#: vertical over horizontal velocity noise, and the streams' clocks (:data:`CLOCK_KEYS`):
#: the receiver's offset from the IMU's clock ±100 ms (a real drive measured 65 ms), the
#: odometer's and the sprockets' ±20 ms, the receiver's epoch jitter 1σ 1-4 ms.
RANDOM_RANGES: dict[str, tuple[float, float]] = {
    "separated_ratio": (0.78, 0.96),
    "rolling_slip": (0.01, 0.06),
    "accel_slip_per_g": (0.2, 0.8),
    "turn_slip": (0.05, 0.18),
    "brake_drag": (0.1, 0.3),
    "lateral_resistance": (0.35, 0.8),
    "texture_std": (0.002, 0.008),
    "duration_s": (600.0, 900.0),
    "outage_s": (180.0, 300.0),
    "gyro_grade": (1.0, 2.0),
    "gnss_up_vel_std_ratio": (1.5, 2.0),
    "gnss_clock_offset_s": (-0.1, 0.1),
    "odometer_clock_offset_s": (-0.02, 0.02),
    "sprocket_clock_offset_s": (-0.02, 0.02),
    "gnss_epoch_jitter_s": (0.001, 0.004),
}
#: The clock figures of ``RANDOM_RANGES`` (each a field of ``CrawlerSensors``), drawn in
#: this order by a generator of their own.
CLOCK_KEYS = (
    "gnss_clock_offset_s",
    "odometer_clock_offset_s",
    "sprocket_clock_offset_s",
    "gnss_epoch_jitter_s",
)
#: Share of random routes whose vehicle config names the gyro's data-sheet part (the
#: ADIS16470's typical figures) while the unit fitted is drawn over ``gyro_grade`` all the
#: same: a unit worse than its data sheet (unit-to-unit spread, temperature, vibration), as
#: fleets have. The other routes' configs give the unit's own figures (the part times its
#: grade). Drawn independently of the grade.
CONFIG_NAMES_DATASHEET_SHARE = 0.5
_GROUND_KEYS = (
    "rolling_slip",
    "accel_slip_per_g",
    "turn_slip",
    "brake_drag",
    "lateral_resistance",
    "texture_std",
)


def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def _random_ground(rng: np.random.Generator) -> Ground:
    values = {k: _u(rng, RANDOM_RANGES[k]) for k in _GROUND_KEYS}
    return Ground("random", **values)


def _random_segment(rng: np.random.Generator) -> Segment:
    states = list(MANOEUVRES)
    probs = np.array([MANOEUVRES[s][0] for s in states])
    state = states[int(rng.choice(len(states), p=probs / probs.sum()))]
    _, dur, speed = MANOEUVRES[state]
    left = bool(rng.random() < 0.5)
    ratio = _u(rng, RANDOM_RANGES["separated_ratio"])
    seg = Segment(state, _u(rng, dur), _u(rng, speed), left, ratio)
    if state == M.HEADING_JUMP:
        seg = replace(seg, state=M.PIVOT)
    return seg


def random_route(rng: np.random.Generator) -> Route:
    """A random route: manoeuvres drawn from :data:`RANDOM_RANGES`, each entered from a
    straight slow-down (stops from 0.5 m/s), on a random ground, with one outage."""
    total = _u(rng, RANDOM_RANGES["duration_s"])
    segs = [Segment(M.STOP, 3.0, 0.0), Segment(M.STRAIGHT, 30.0, _u(rng, (6.0, 12.0)))]
    speed = segs[-1].speed_mps
    while sum(s.duration_s for s in segs) < total:
        seg = _random_segment(rng)
        target = 0.5 if seg.state == M.STOP else seg.speed_mps
        if abs(speed - target) > 0.3:
            segs.append(Segment(M.STRAIGHT, abs(speed - target) / 1.2 + 1.5, target))
        segs.append(seg)
        speed = seg.speed_mps
    segs.append(Segment(M.STRAIGHT, speed / 1.2 + 1.5, 0.5))
    segs.append(Segment(M.STOP, 4.0, 0.0))
    length = _u(rng, RANDOM_RANGES["outage_s"])
    start = _u(rng, (120.0, max(121.0, total - length - 30.0)))
    return Route(
        "random",
        tuple(segs),
        _random_ground(rng),
        ((start, length),),
        heading0_rad=_u(rng, (-math.pi, math.pi)),
    )
