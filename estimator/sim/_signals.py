"""Smooth time (or distance) profiles the scenarios are built from.

Every profile is a vectorised function of an array argument (seconds or metres) returning an
array of the same shape. Nothing here draws random numbers except through a
``numpy.random.Generator`` handed in.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from estimator._arrays import FloatArray

Profile = Callable[[FloatArray], FloatArray]

__all__ = [
    "BoundedSines",
    "EasedKnots",
    "Profile",
    "cumtrapz",
    "ou_process",
    "ramp_steps",
    "smooth_window",
]


def _ease(u: FloatArray) -> FloatArray:
    """Cosine ease from 0 to 1 on ``u`` in [0, 1]; zero slope at both ends."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(u, 0.0, 1.0))


@dataclass(frozen=True, slots=True)
class EasedKnots:
    """Piecewise profile through knots ``(x_i, y_i)``, cosine-eased between neighbours.

    The curve is C1 (its slope is zero at every knot), so a speed profile built this way has a
    continuous acceleration that peaks at ``π/2`` times the mean slope of a ramp. Before the first
    knot and after the last the value is held.

    Attributes
    ----------
    x : tuple[float, ...]
        Knot abscissae, non-decreasing (a repeated abscissa makes a step).
    y : tuple[float, ...]
        Knot values.
    """

    x: tuple[float, ...]
    y: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.x) != len(self.y) or len(self.x) == 0:
            raise ValueError("EasedKnots needs as many x as y, at least one")
        if any(b < a for a, b in zip(self.x, self.x[1:], strict=False)):
            raise ValueError("EasedKnots abscissae must be non-decreasing")

    def __call__(self, x: FloatArray) -> FloatArray:
        xa = np.asarray(x, dtype=np.float64)
        kx = np.asarray(self.x)
        ky = np.asarray(self.y)
        if kx.size == 1:
            return np.full_like(xa, ky[0])
        i = np.clip(np.searchsorted(kx, xa, side="right") - 1, 0, kx.size - 2)
        x0, x1 = kx[i], kx[i + 1]
        span = np.where(x1 > x0, x1 - x0, 1.0)
        u = np.where(x1 > x0, (xa - x0) / span, 1.0)
        out = ky[i] + (ky[i + 1] - ky[i]) * _ease(u)
        out = np.where(xa <= kx[0], ky[0], out)
        return np.where(xa >= kx[-1], ky[-1], out)

    @property
    def end(self) -> float:
        """Abscissa of the last knot."""
        return self.x[-1]


@dataclass(frozen=True, slots=True)
class BoundedSines:
    """A zero-mean wobble: a sum of sines scaled so that a chosen quantity stays within ``±bound``.

    With ``bound_on="value"`` the profile itself spans exactly ``±bound`` over ``[0, span]``
    (its largest excursion equals ``bound``); with ``bound_on="rate"`` its time derivative does
    (used for "pitch rate ωx = 0 ± 0.02 rad/s": the pitch angle is the integral of a bounded rate).

    Use :meth:`draw` to make one from a random generator.
    """

    amp: tuple[float, ...]
    freq_hz: tuple[float, ...]
    phase_rad: tuple[float, ...]

    @classmethod
    def draw(
        cls,
        rng: np.random.Generator,
        bound: float,
        span: float,
        f_lo_hz: float,
        f_hi_hz: float,
        n: int = 5,
        bound_on: str = "value",
    ) -> BoundedSines:
        """Draw ``n`` sines with frequencies in ``[f_lo_hz, f_hi_hz]``, scaled to ``bound``."""
        freq = rng.uniform(f_lo_hz, f_hi_hz, n)
        phase = rng.uniform(0.0, 2.0 * np.pi, n)
        weight = rng.uniform(0.5, 1.0, n)
        if bound == 0.0:
            return cls(tuple(0.0 * weight), tuple(freq), tuple(phase))
        if bound_on not in ("value", "rate"):
            raise ValueError("bound_on must be 'value' or 'rate'")

        def shape(x: FloatArray) -> FloatArray:
            arg = 2.0 * np.pi * freq[:, None] * x[None, :] + phase[:, None]
            if bound_on == "value":
                return np.abs((weight[:, None] * np.sin(arg)).sum(axis=0))
            return np.abs((weight[:, None] * 2.0 * np.pi * freq[:, None] * np.cos(arg)).sum(axis=0))

        # coarse pass (20 points per period of the fastest sine: a sampled peak is at most ~1.3 %
        # below the true one), then a fine look around every coarse sample within 3 % of the
        # coarse maximum: the largest excursion is found to better than 0.01 %
        end = max(span, 1e-3)
        grid = np.linspace(0.0, end, max(200, int(span * 20 * f_hi_hz) + 1))
        coarse = shape(grid)
        step = grid[1] - grid[0]
        best = np.flatnonzero(coarse >= 0.97 * coarse.max())[:4000]
        fine = np.clip(
            (grid[best][:, None] + np.linspace(-step, step, 201)[None, :]).ravel(), 0.0, end
        )
        peak = max(float(coarse.max()), float(shape(fine).max()))
        amp = weight * bound / peak
        return cls(tuple(amp), tuple(freq), tuple(phase))

    def __call__(self, x: FloatArray) -> FloatArray:
        xa = np.asarray(x, dtype=np.float64)
        out = np.zeros_like(xa)
        for a, f, p in zip(self.amp, self.freq_hz, self.phase_rad, strict=True):
            out += a * np.sin(2.0 * np.pi * f * xa + p)
        return out


def smooth_window(x: FloatArray, lo: float, hi: float, edge: float) -> FloatArray:
    """1 inside ``[lo, hi]``, 0 outside; cosine edges of width ``edge`` centred on lo and hi."""
    xa = np.asarray(x, dtype=np.float64)
    if edge <= 0:
        return ((xa >= lo) & (xa <= hi)).astype(np.float64)
    rise = _ease((xa - (lo - edge / 2)) / edge)
    fall = 1.0 - _ease((xa - (hi - edge / 2)) / edge)
    return rise * fall


def ramp_steps(x: FloatArray, steps: tuple[tuple[float, float, float], ...]) -> FloatArray:
    """Sum of eased steps: each ``(x0, delta, width)`` rises by ``delta`` from ``x0`` to
    ``x0 + width`` (cosine ease; a width of 0 is a jump at ``x0``)."""
    xa = np.asarray(x, dtype=np.float64)
    out = np.zeros_like(xa)
    for x0, delta, width in steps:
        if width > 0:
            out += delta * _ease((xa - x0) / width)
        else:
            out += delta * (xa >= x0)
    return out


def cumtrapz(y: FloatArray, dx: float) -> FloatArray:
    """Cumulative trapezoidal integral of samples ``y`` spaced ``dx``; starts at 0, same length."""
    out = np.empty_like(y, dtype=np.float64)
    out[0] = 0.0
    np.cumsum(0.5 * (y[1:] + y[:-1]) * dx, out=out[1:])
    return out


def ou_process(
    rng: np.random.Generator, t: FloatArray, sigma: float, tau_s: float, rate_hz: float = 10.0
) -> FloatArray:
    """Stationary Ornstein-Uhlenbeck noise (std ``sigma``, correlation time ``tau_s``) at ``t``.

    Drawn exactly at ``rate_hz`` (AR(1) with ``a = exp(-dt/τ)``) and linearly interpolated onto
    ``t``, so its cost grows with the duration, not with the length of ``t``.
    """
    ta = np.asarray(t, dtype=np.float64)
    if ta.size == 0:
        return np.zeros(0)
    t0, t1 = float(ta[0]), float(ta[-1])
    n = int(np.ceil((t1 - t0) * rate_hz)) + 2
    w = rng.standard_normal(n)
    if sigma == 0.0:
        return np.zeros_like(ta)
    a = float(np.exp(-1.0 / (rate_hz * tau_s)))
    c = float(np.sqrt(1.0 - a * a))
    x = np.empty(n)
    x[0] = w[0]
    for k in range(1, n):
        x[k] = a * x[k - 1] + c * w[k]
    tk = t0 + np.arange(n) / rate_hz
    return sigma * np.interp(ta, tk, x)
