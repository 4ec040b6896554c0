"""What the simulated driver is asked to do: speed, steering-wheel angle and road μ over time.

A :class:`Manoeuvre` is three piecewise-linear profiles (knots in seconds) sampled on the
simulator's grid. The named ones are the issue's (``method.md`` §5 claims): accelerating
30 → 80 km/h in 6 s, a 60° steering-wheel step at 60 km/h, each on μ 0.8, 0.3 and a step
1.0 → 0.4 mid-manoeuvre; one tyre with kz 50,000 N/m; straight constant-speed driving (μ
unobservable); a farm-track drive with gentle manoeuvres. Every manoeuvre starts with
``LEAD_S`` of straight steady driving (the front end's radius calibration needs it), and its
scored segment starts at ``t0_s``.

:func:`random_manoeuvre` draws one from stated distributions (see its docstring).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LEAD_S", "NAMED", "Manoeuvre", "named_manoeuvre", "random_manoeuvre"]

LEAD_S = 4.0
"""Straight steady driving before every manoeuvre [s]."""

_KMH = 1.0 / 3.6


@dataclass(frozen=True, slots=True)
class Manoeuvre:
    """Profiles over ``0..duration_s``: knots ``(t_s, value)`` interpolated linearly.

    ``mu_knots`` steps are written as two knots at (nearly) the same time. ``damaged_wheel``
    (0..3, Corner order) has its vertical stiffness set to ``damaged_kz_npm``; ``t0_s`` is
    where the scored segment starts and ``mu_step_s`` where μ steps (NaN: no step).
    """

    name: str
    duration_s: float
    speed_knots: tuple[tuple[float, float], ...]
    steer_knots: tuple[tuple[float, float], ...]
    mu_knots: tuple[tuple[float, float], ...]
    t0_s: float = LEAD_S
    mu_step_s: float = math.nan
    damaged_wheel: int = -1
    damaged_kz_npm: float = 50_000.0

    def sample(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Target speed [m/s], steering-wheel angle [rad] and μ at times ``t_s``."""
        speed, steer, mu = (
            np.interp(t_s, [k[0] for k in knots], [k[1] for k in knots])
            for knots in (self.speed_knots, self.steer_knots, self.mu_knots)
        )
        return speed, steer, mu


def _mu(mu: float | tuple[float, float], step_s: float) -> tuple[tuple[float, float], ...]:
    if isinstance(mu, tuple):
        return ((0.0, mu[0]), (step_s, mu[0]), (step_s + 1e-3, mu[1]), (1e4, mu[1]))
    return ((0.0, mu), (1e4, mu))


def _accelerate(name: str, mu: float | tuple[float, float], damaged: int = -1) -> Manoeuvre:
    t0 = LEAD_S
    speed = ((0.0, 30 * _KMH), (t0, 30 * _KMH), (t0 + 6.0, 80 * _KMH), (t0 + 10.0, 80 * _KMH))
    return Manoeuvre(
        name,
        t0 + 10.0,
        speed,
        ((0.0, 0.0), (1e4, 0.0)),
        _mu(mu, t0 + 3.0),
        t0,
        t0 + 3.0 if isinstance(mu, tuple) else math.nan,
        damaged,
    )


def _steer(name: str, mu: float | tuple[float, float]) -> Manoeuvre:
    t0 = LEAD_S
    steer = ((0.0, 0.0), (t0, 0.0), (t0 + 0.3, math.radians(60.0)), (1e4, math.radians(60.0)))
    return Manoeuvre(
        name,
        t0 + 6.0,
        ((0.0, 60 * _KMH), (1e4, 60 * _KMH)),
        steer,
        _mu(mu, t0 + 3.0),
        t0,
        t0 + 3.0 if isinstance(mu, tuple) else math.nan,
    )


def _constant() -> Manoeuvre:
    return Manoeuvre(
        "constant_speed",
        LEAD_S + 16.0,
        ((0.0, 50 * _KMH), (1e4, 50 * _KMH)),
        ((0.0, 0.0), (1e4, 0.0)),
        _mu(0.8, 0.0),
    )


def _farm_track() -> Manoeuvre:
    t = np.arange(0.0, LEAD_S + 20.0 + 0.25, 0.25)
    steer = np.where(t < LEAD_S, 0.0, math.radians(30.0) * np.sin(2 * math.pi * 0.2 * (t - LEAD_S)))
    speed = 25 * _KMH + np.where(t < LEAD_S, 0.0, 1.5 * np.sin(2 * math.pi * 0.07 * (t - LEAD_S)))
    return Manoeuvre(
        "farm_track",
        LEAD_S + 20.0,
        tuple(zip(t, speed, strict=True)),
        tuple(zip(t, steer, strict=True)),
        _mu(0.5, 0.0),
    )


NAMED: dict[str, Manoeuvre] = {
    m.name: m
    for m in (
        _accelerate("accelerate_mu08", 0.8),
        _accelerate("accelerate_mu03", 0.3),
        _accelerate("accelerate_step", (1.0, 0.4)),
        _steer("steer_mu08", 0.8),
        _steer("steer_mu03", 0.3),
        _steer("steer_step", (1.0, 0.4)),
        _accelerate("damaged_tyre", 0.8, damaged=2),
        _constant(),
        _farm_track(),
    )
}


def named_manoeuvre(name: str) -> Manoeuvre:
    """The manoeuvre ``name`` (``KeyError`` listing the known ones)."""
    try:
        return NAMED[name]
    except KeyError:
        raise KeyError(f"unknown manoeuvre {name!r}; known: {sorted(NAMED)}") from None


def random_manoeuvre(rng: np.random.Generator, index: int = 0) -> Manoeuvre:
    """A random 16 s manoeuvre after the lead-in, from these distributions (uniform):

    * initial speed 20-90 km/h; four 4 s phases, each a speed change of −25..+25 km/h
      (kept within 10-110 km/h) and a steering-wheel target of −90..90° reached in 0.2-2 s,
      with probability 0.3 of straight ahead;
    * μ 0.2-1.1, with probability 0.3 a step to 0.2-1.1 at a random phase boundary.
    """
    v = rng.uniform(20.0, 90.0) * _KMH
    speed, steer = [(0.0, v), (LEAD_S, v)], [(0.0, 0.0), (LEAD_S, 0.0)]
    for k in range(4):
        t = LEAD_S + 4.0 * k
        v = float(np.clip(v + rng.uniform(-25.0, 25.0) * _KMH, 10 * _KMH, 110 * _KMH))
        speed.append((t + 4.0, v))
        target = 0.0 if rng.random() < 0.3 else math.radians(rng.uniform(-90.0, 90.0))
        steer += [(t + rng.uniform(0.2, 2.0), target), (t + 4.0, target)]
    mu0 = float(rng.uniform(0.2, 1.1))
    step = rng.random() < 0.3
    step_s = LEAD_S + 4.0 * float(rng.integers(1, 4))
    mu: float | tuple[float, float] = (mu0, float(rng.uniform(0.2, 1.1))) if step else mu0
    return Manoeuvre(
        f"random_{index}",
        LEAD_S + 16.0,
        tuple(speed),
        tuple(steer),
        _mu(mu, step_s),
        LEAD_S,
        step_s if step else math.nan,
    )
