"""Ground that is not flat: a grade and a cross grade along the route.

A :class:`Terrain` gives the grade (rise over run along the hull's heading, uphill +) and the
cross grade (fall to the hull's right over run, right side down +) as functions of the
along-ground distance the hull has driven, each a smooth (cosine) interpolation between knots
laid every few tens of metres. The hull's pitch is ``θ = atan(grade)``, its roll
``φ = atan(cross)``. :data:`FLAT` is level ground (the named routes' default);
:func:`random_terrain` draws one from :data:`TERRAIN_RANGES`; :func:`hill_terrain` is the
named hilly route's. Pure: every draw from the generator handed in.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from estimator._arrays import FloatArray

__all__ = ["FLAT", "TERRAIN_RANGES", "Terrain", "hill_terrain", "random_terrain"]


@dataclass(frozen=True, slots=True)
class Terrain:
    """Knots ``(distance_m, value)`` of the grade and the cross grade (fractions, rise over
    run); empty knots mean level ground along that axis."""

    grade_at_m: tuple[float, ...] = ()
    grade: tuple[float, ...] = ()
    cross_at_m: tuple[float, ...] = ()
    cross: tuple[float, ...] = ()

    @property
    def flat(self) -> bool:
        return not any(self.grade) and not any(self.cross)

    def grade_of(self, distance_m: FloatArray) -> FloatArray:
        """Grade at each along-ground distance, shape of ``distance_m``."""
        return _smooth(self.grade_at_m, self.grade, distance_m)

    def grade_at(self, distance_m: float) -> float:
        """:meth:`grade_of` at one distance, in plain floats (for step-by-step integration)."""
        at, value = self.grade_at_m, self.grade
        if not at:
            return 0.0
        k = min(max(bisect.bisect_right(at, distance_m) - 1, 0), len(at) - 1)
        k1 = min(k + 1, len(at) - 1)
        u = min(max((distance_m - at[k]) / max(at[k1] - at[k], 1e-9), 0.0), 1.0)
        return value[k] + (value[k1] - value[k]) * (0.5 - 0.5 * math.cos(math.pi * u))

    def cross_of(self, distance_m: FloatArray) -> FloatArray:
        """Cross grade at each along-ground distance, shape of ``distance_m``."""
        return _smooth(self.cross_at_m, self.cross, distance_m)


FLAT = Terrain()

#: Random routes' terrain (uniform draws, a generator of its own per route): the route's
#: largest grade, the spacing of the grade's knots (m), each knot's grade uniform within
#: ± the largest; the same for the cross grade.
TERRAIN_RANGES: dict[str, tuple[float, float]] = {
    "grade_max": (0.05, 0.15),
    "grade_spacing_m": (20.0, 80.0),
    "cross_max": (0.0, 0.10),
    "cross_spacing_m": (30.0, 120.0),
}


def _smooth(at_m: tuple[float, ...], value: tuple[float, ...], d: FloatArray) -> FloatArray:
    """Cosine interpolation between knots (flat slopes at each knot, so the pitch rate is
    continuous); held beyond the last knot; 0 without knots."""
    d = np.asarray(d, dtype=np.float64)
    if not at_m:
        return np.zeros(d.shape)
    x, y = np.asarray(at_m), np.asarray(value)
    k = np.clip(np.searchsorted(x, d, side="right") - 1, 0, x.size - 1)
    k1 = np.minimum(k + 1, x.size - 1)
    span = np.maximum(x[k1] - x[k], 1e-9)
    u = np.clip((d - x[k]) / span, 0.0, 1.0)
    w = 0.5 - 0.5 * np.cos(math.pi * u)
    return np.asarray(y[k] + (y[k1] - y[k]) * w)


def _knots(
    rng: np.random.Generator, length_m: float, spacing: tuple[float, float], top: float
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    at = [0.0]
    while at[-1] < length_m:
        at.append(at[-1] + float(rng.uniform(*spacing)))
    values = [0.0] + [float(rng.uniform(-top, top)) for _ in at[1:]]
    return tuple(at), tuple(values)


def random_terrain(rng: np.random.Generator, length_m: float = 20_000.0) -> Terrain:
    """A terrain drawn from :data:`TERRAIN_RANGES` over ``length_m`` of route (level at the
    start, where the route begins standing)."""
    r = TERRAIN_RANGES
    grade_top = float(rng.uniform(*r["grade_max"]))
    cross_top = float(rng.uniform(*r["cross_max"]))
    g_at, g = _knots(rng, length_m, r["grade_spacing_m"], grade_top)
    c_at, c = _knots(rng, length_m, r["cross_spacing_m"], cross_top)
    return Terrain(g_at, g, c_at, c)


def hill_terrain(length_m: float = 20_000.0) -> Terrain:
    """The named hilly route's terrain: grades alternating +10 % / −10 % every 150 m (ramps
    of 60 m between), and a cross grade alternating ±5 % every 220 m."""
    g_at: list[float] = [0.0, 40.0]
    g: list[float] = [0.0, 0.0]
    sign = 1.0
    while g_at[-1] < length_m:
        g_at += [g_at[-1] + 60.0, g_at[-1] + 150.0]
        g += [0.10 * sign, 0.10 * sign]
        sign = -sign
    c_at = [0.0] + [60.0 + 220.0 * k for k in range(int(length_m // 220.0) + 2)]
    c = [0.0] + [0.05 * (1 if k % 2 == 0 else -1) for k in range(len(c_at) - 1)]
    return Terrain(tuple(g_at), tuple(g), tuple(c_at), tuple(c))
