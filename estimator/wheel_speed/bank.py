"""Wheel angular speed from encoder rising edges (``method.md`` §2) and from direct (CAN) speeds.

A toothed ring with ``Ns`` teeth gives one rising edge every ``2π/Ns`` of wheel rotation.

* **Period method, k-tooth average** (source 001): over ``k`` tooth intervals
  ``t_k = t(i+k) − t(i)``, ``ω = 2π·k/(Ns·t_k)`` (:func:`omega_k_tooth`).
* **Frequency method**: count the edges in a fixed window ``W``, ``ω = 2π·n/(Ns·W)``; its error is
  ±1 count, so it is only good when the window holds many edges (:func:`omega_frequency`).

A k-tooth average is the speed at the *middle* of its span, which lies in the past of the time the
estimate is stamped with. Under an angular acceleration ``α`` that is a bias of ``α·(t − t_mid)``:
at 1 rad/s² and a 0.2 s span, ≈0.1 rad/s, 3 % of a tractor's wheel speed. :func:`omega_at`
removes it by fitting the wheel angle of the last ``k`` edges with a quadratic in time and
evaluating the derivative *at the query time*; with at most one edge interval of extrapolation
the fit is exact under constant acceleration and unbiased to first order otherwise. Its slope
(linear fit, ``fit_order=1``) is the least-squares form of the k-tooth average and is what the
period method reduces to when too few edges are there for the quadratic.

``k`` follows the speed: the fit takes the edges of the last ``window_s`` (at least
``min_edges``, at most ``max_edges``), so a slow wheel uses a few long periods and a fast wheel
many short ones. The frequency method takes over only when the window holds at least
``frequency_min_count`` edges (a very high edge rate). Every result says which method it used.

Standstill: a wheel that stops gives no more edges, so the last speed must not be held. If no
edge came for ``τ = t − t_last``, the wheel is slower than one tooth per ``τ``:
``|ω| ≤ 2π/(Ns·τ)``, and after ``stop_timeout_s`` it is taken as stopped (``ω = 0``).

Direction: a quadrature encoder gives ``±1`` per edge; the wheel angle then steps back on reverse
edges and the fitted slope is signed. Without direction every edge counts forward.

Many wheels: a :class:`WheelBank` keeps the edges of thousands of wheels in shared arrays (one
ring per wheel), queues pushes and answers a query of any set of wheels, tooth calibration
included, in a fixed number of numpy calls. :class:`WheelTracker` is one slot of a bank and
:func:`query_many` queries trackers through their bank; a fleet front end can hold slot indices
and call :meth:`WheelBank.push` / :meth:`WheelBank.query` directly (arrays, no per-wheel
objects).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import sliding_window_view

from estimator._arrays import as_stamps
from estimator._slots import grow_slot_array
from estimator.config import ConfigError

__all__ = [
    "DirectWheelSpeed",
    "WheelBank",
    "WheelSpeedConfig",
    "WheelSpeedMethod",
    "WheelSpeedResult",
    "WheelTracker",
    "edge_angles",
    "gather_bank",
    "omega_at",
    "omega_frequency",
    "omega_k_tooth",
    "query_many",
    "stop_bound",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_NS = 1e-9
_GAP_FACTOR = 3.0
"""An interval this many times longer than the latest one ends the fit (a wheel restarting)."""


class WheelSpeedMethod(IntEnum):
    """How a wheel speed value was obtained."""

    NONE = 0
    """No information (no edge or sample yet)."""
    PERIOD = 1
    """k-tooth period method (least-squares fit on edge times), or its standstill bound."""
    FREQUENCY = 2
    """Edge count over a fixed window."""
    DIRECT = 3
    """Given directly (CAN)."""


@dataclass(frozen=True, slots=True)
class WheelSpeedConfig:
    """Wheel-speed front end settings.

    Attributes
    ----------
    teeth_per_rev : int
        ``Ns``, rising edges per wheel revolution.
    window_s : float
        Time span of edges the period fit aims to cover [s] (default 0.3 s).
    min_edges : int
        Fewest edges a fit uses, even if they span more than ``window_s`` (slow wheel), ≥ 2.
    max_edges : int
        Most edges a fit uses (fast wheel), ≥ ``min_edges`` (default 16). A fast wheel's fit
        is then shorter than ``window_s``: with 16 edges its noise is already a few hundredths
        of a percent, while the quadratic's error under a changing acceleration (jerk: braking
        onset, a wheel catching grip) grows with the square of the span — about 1.5 % at
        3.8 m/s under 4 m/s³ over the full 0.3 s.
    fit_order : int
        1: linear fit of wheel angle (k-tooth average, centred in the past);
        2: quadratic fit evaluated at the query time (latency-compensated, default).
    frequency_min_count : int
        Use the frequency method when the window holds at least this many edges.
    stop_timeout_s : float
        No edge for this long [s] means the wheel is stopped (``ω = 0``).
    timing_std_s : float
        1-sigma jitter of an edge time stamp [s], floor of the reported speed std.
    tooth_calibration : bool
        Learn and remove the ring's tooth-spacing pattern (:class:`WheelTracker`).
    calibration_gain : float
        Share of each residual a tooth correction takes (0..1].
    calibration_half_window : int
        Neighbours on each side of an edge in the calibration fit.
    calibration_period_s : float
        The tooth corrections are updated on this fixed time grid [s].
    angle_noise_rel : float
        Prior 1-sigma angle error of one edge, as a fraction of the tooth pitch: a ring's
        tooth spacing before calibration (default 0.01, one percent). A fit's residual scatter
        is floored by it, so a fit through few edges (a slow wheel, a restart) whose residuals
        happen to be small does not report an error below what the ring gives. With tooth
        calibration the floor follows the calibration residuals instead
        (:meth:`WheelBank._calibrate`), shrinking as the pattern is learnt.
    stop_bound_margin : float
        The standstill bound allows a tooth gap this much wider than nominal
        (``|ω| ≤ (1 + margin)·2π/(Ns·τ)``): real rings have uneven teeth, and a late edge
        after a wide tooth must not cut a steady speed [-].
    """

    teeth_per_rev: int = 120
    window_s: float = 0.3
    min_edges: int = 3
    max_edges: int = 16
    fit_order: int = 2
    frequency_min_count: int = 2000
    stop_timeout_s: float = 2.0
    timing_std_s: float = 2e-5
    stop_bound_margin: float = 0.5
    angle_noise_rel: float = 0.01
    tooth_calibration: bool = True
    calibration_gain: float = 0.4
    calibration_half_window: int = 6
    calibration_period_s: float = 0.5

    def __post_init__(self) -> None:
        if not isinstance(self.teeth_per_rev, int) or not 1 <= self.teeth_per_rev <= 100_000:
            raise ConfigError(
                f"teeth_per_rev must be an int in 1..100000, got {self.teeth_per_rev!r}"
            )
        for name in ("window_s", "stop_timeout_s", "timing_std_s", "calibration_period_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {value!r}")
        if not isinstance(self.min_edges, int) or self.min_edges < 2:
            raise ConfigError(f"min_edges must be an int >= 2, got {self.min_edges!r}")
        if not isinstance(self.max_edges, int) or self.max_edges < self.min_edges:
            raise ConfigError(f"max_edges must be an int >= min_edges, got {self.max_edges!r}")
        if not (math.isfinite(self.angle_noise_rel) and 0 <= self.angle_noise_rel < 0.5):
            raise ConfigError("angle_noise_rel must be within [0, 0.5)")
        if not (math.isfinite(self.stop_bound_margin) and self.stop_bound_margin >= 0):
            raise ConfigError("stop_bound_margin must be a finite number >= 0")
        if not (math.isfinite(self.calibration_gain) and 0 < self.calibration_gain <= 1):
            raise ConfigError("calibration_gain must be within (0, 1]")
        if not isinstance(self.calibration_half_window, int) or self.calibration_half_window < 2:
            raise ConfigError("calibration_half_window must be an int >= 2")
        if self.fit_order not in (1, 2):
            raise ConfigError(f"fit_order must be 1 or 2, got {self.fit_order!r}")
        if not isinstance(self.frequency_min_count, int) or self.frequency_min_count < 2:
            raise ConfigError("frequency_min_count must be an int >= 2")


@dataclass(frozen=True, slots=True)
class WheelSpeedResult:
    """Wheel speeds at query times.

    Attributes
    ----------
    omega_radps : ndarray, shape (m,)
        Signed angular speed (forward positive); NaN when unknown.
    std_radps : ndarray, shape (m,)
        1-sigma uncertainty.
    method : ndarray, shape (m,), int8
        :class:`WheelSpeedMethod` per value.
    """

    omega_radps: FloatArray
    std_radps: FloatArray
    method: npt.NDArray[np.int8]


def omega_k_tooth(stamp_ns: IntArray, k: int, teeth_per_rev: int) -> FloatArray:
    """k-tooth period method, ``method.md`` §2: ``ω = 2π·k/(Ns·t_k)``.

    Parameters
    ----------
    stamp_ns : ndarray, shape (n,), int64
        Rising-edge times.
    k : int
        Tooth intervals averaged (``k = 1`` is the plain period method).
    teeth_per_rev : int
        ``Ns``.

    Returns
    -------
    ndarray, shape (n − k,)
        Speed over each span ``[t(i), t(i+k)]`` [rad/s], forward.
    """
    t = np.asarray(stamp_ns, dtype=np.int64)
    t_k = (t[k:] - t[:-k]).astype(np.float64) * _NS
    with np.errstate(divide="ignore"):
        return 2.0 * np.pi * k / (teeth_per_rev * t_k)


def omega_frequency(
    stamp_ns: IntArray, query_ns: IntArray, window_s: float, teeth_per_rev: int
) -> FloatArray:
    """Frequency method, ``method.md`` §2: edges counted in ``(t − W, t]``, ``ω = 2π·n/(Ns·W)``.

    Parameters
    ----------
    stamp_ns : ndarray, shape (n,), int64
        Rising-edge times, non-decreasing.
    query_ns : ndarray, shape (m,), int64
        Window end times.
    window_s : float
        ``W`` [s].
    teeth_per_rev : int
        ``Ns``.

    Returns
    -------
    ndarray, shape (m,)
        Speed [rad/s], forward.
    """
    t = np.asarray(stamp_ns, dtype=np.int64)
    q = np.asarray(query_ns, dtype=np.int64)
    w_ns = round(window_s * 1e9)
    count = np.searchsorted(t, q, side="right") - np.searchsorted(t, q - w_ns, side="right")
    return np.asarray(2.0 * np.pi * count / (teeth_per_rev * window_s), dtype=np.float64)


def stop_bound(last_edge_ns: IntArray, query_ns: IntArray, teeth_per_rev: int) -> FloatArray:
    """Upper bound on ``|ω|`` when no edge came since ``t_last``: ``2π/(Ns·(t − t_last))``.

    Returns ``inf`` at ``t == t_last``. Shapes broadcast.
    """
    tau = (np.asarray(query_ns, np.int64) - np.asarray(last_edge_ns, np.int64)).astype(np.float64)
    with np.errstate(divide="ignore"):
        return 2.0 * np.pi / (teeth_per_rev * tau * _NS)


def edge_angles(
    n: int,
    teeth_per_rev: int,
    direction: npt.NDArray[np.int8] | None = None,
    start_rad: float = 0.0,
) -> FloatArray:
    """Cumulative wheel angle at each edge: ``start + Σ dir·2π/Ns``; shape ``(n,)``."""
    step = 2.0 * np.pi / teeth_per_rev
    if direction is None:
        return start_rad + step * np.arange(1, n + 1, dtype=np.float64)
    d = np.where(np.asarray(direction) < 0, -1.0, 1.0)
    return start_rad + step * np.cumsum(d)


def omega_at(
    stamp_ns: IntArray,
    angle_rad: FloatArray,
    query_ns: IntArray,
    config: WheelSpeedConfig,
    angle_before_rad: float | FloatArray = 0.0,
    signed: bool | npt.NDArray[np.bool_] = False,
    segment_start: IntArray | None = None,
) -> WheelSpeedResult:
    """Causal wheel speed at each query time from the edges at or before it.

    Implements ``method.md`` §2 with speed-adaptive ``k`` and latency compensation (module
    docstring). For each query ``t``: the edges in ``(t − window_s, t]`` (at least ``min_edges``,
    at most ``max_edges`` of the latest ones at or before ``t``) are fitted with
    ``angle(τ) = c0 + c1·τ + c2·τ²`` (``τ = edge time − t``); ``ω(t) = c1``. The standstill bound
    (with ``stop_bound_margin``) and timeout are then applied.

    Parameters
    ----------
    stamp_ns : ndarray, shape (n,), int64
        Edge times, non-decreasing.
    angle_rad : ndarray, shape (n,)
        Wheel angle at each edge (:func:`edge_angles`).
    query_ns : ndarray, shape (m,), int64
        Query times, any order.
    config : WheelSpeedConfig
    angle_before_rad : float or ndarray, shape (m,)
        Wheel angle before the first edge given (for the frequency count).
    signed : bool or ndarray, shape (m,), bool
        The angles carry direction (quadrature encoder); otherwise a negative fitted speed
        (a fit overshooting a stop) is clamped to zero.
    segment_start : ndarray, shape (m,), int, optional
        When several wheels share the arrays: index of the first edge of each query's wheel;
        edges before it are not that wheel's.

    Returns
    -------
    WheelSpeedResult
        Arrays of shape ``(m,)``.
    """
    e = np.asarray(stamp_ns, dtype=np.int64)
    pos = np.asarray(angle_rad, dtype=np.float64)
    q = np.asarray(query_ns, dtype=np.int64)
    m = q.shape[0]
    if m == 0:
        return _unknown(0)
    last = np.searchsorted(e, q, side="right") - 1  # index of the last edge ≤ t
    seg0 = np.zeros(m, dtype=np.int64) if segment_start is None else np.asarray(segment_start)
    has = last >= seg0
    if e.shape[0] == 0 or not has.any():
        return _unknown(m)
    w_ns = round(config.window_s * 1e9)
    first_in = np.searchsorted(e, q - w_ns, side="right")
    n_win = np.maximum(last - first_in + 1, 0)
    w, offs = _fit_mask(last, seg0, n_win, has, config)
    idx = np.clip(last[:, None] - offs[None, :], 0, e.shape[0] - 1)
    last_c = np.maximum(last, 0)
    tau_s = (e[idx] - q[:, None]).astype(np.float64) * _NS
    p = pos[idx] - pos[last_c][:, None]
    freq = has & (n_win >= config.frequency_min_count)
    freq_omega = None
    if freq.any():
        before = np.where(first_in > seg0, pos[np.maximum(first_in - 1, 0)], angle_before_rad)
        freq_omega = (pos[last_c] - before) / config.window_s
    prior_var = (config.angle_noise_rel * 2.0 * np.pi / config.teeth_per_rev) ** 2
    return _speed_from_window(
        q,
        tau_s,
        p,
        w,
        has,
        freq,
        freq_omega,
        e[last_c],
        e[np.maximum(last - 1, 0)],
        last - 1 >= seg0,
        config,
        signed,
        prior_var,
    )


def _unknown(m: int) -> WheelSpeedResult:
    return WheelSpeedResult(
        np.full(m, np.nan), np.full(m, np.nan), np.full(m, int(WheelSpeedMethod.NONE), np.int8)
    )


def _fit_mask(
    last: IntArray,
    seg0: IntArray,
    n_win: IntArray,
    has: npt.NDArray[np.bool_],
    config: WheelSpeedConfig,
) -> tuple[npt.NDArray[np.bool_], IntArray]:
    """Which of the edges ``last, last − 1, …`` a query may fit: mask ``(m, kmax)`` and offsets.

    ``k`` = edges in the window, clipped to ``[min_edges, max_edges]`` and to the edges held
    (``last − seg0 + 1``); ``kmax`` is the largest ``k`` over the queries (at least 2).
    """
    n_fit = np.clip(n_win, config.min_edges, config.max_edges)
    n_fit = np.minimum(n_fit, last - seg0 + 1)  # cannot use more edges than exist
    kmax = max(int(n_fit[has].max()) if has.any() else 2, 2)
    offs = np.arange(kmax)
    w = (offs[None, :] < n_fit[:, None]) & (offs[None, :] <= (last - seg0)[:, None]) & has[:, None]
    return w, offs


def _speed_from_window(
    q: IntArray,
    tau_s: FloatArray,
    p: FloatArray,
    w: npt.NDArray[np.bool_],
    has: npt.NDArray[np.bool_],
    freq: npt.NDArray[np.bool_],
    freq_omega: FloatArray | None,
    last_ns: IntArray,
    prev_ns: IntArray,
    has_prev: npt.NDArray[np.bool_],
    config: WheelSpeedConfig,
    signed: bool | npt.NDArray[np.bool_],
    angle_var_rad2: float | FloatArray,
) -> WheelSpeedResult:
    """Fit, frequency override and standstill bound of :func:`omega_at` on gathered edges.

    Parameters
    ----------
    q : ndarray, shape (m,), int64
        Query times.
    tau_s : ndarray, shape (m, kmax)
        Time of edge ``last − j`` minus the query time [s] (column ``j``).
    p : ndarray, shape (m, kmax)
        Corrected wheel angle of edge ``last − j`` minus that of edge ``last`` [rad].
    w : ndarray, shape (m, kmax), bool
        The edges the query may fit (:func:`_fit_mask`); entries outside are finite but unused.
    has : ndarray, shape (m,), bool
        The query has an edge at or before it.
    freq, freq_omega : ndarray, shape (m,)
        Queries taken by the frequency method and their speed (None when none is).
    last_ns, prev_ns : ndarray, shape (m,), int64
        Time of the last edge at or before the query and of the one before it.
    has_prev : ndarray, shape (m,), bool
        The edge before the last one is held.
    angle_var_rad2 : float or ndarray, shape (m,)
        Variance of one edge's angle error [rad²]: the floor of the fit's residual variance
        (``angle_noise_rel`` of the pitch, or what the tooth calibration measured).
    """
    m = tau_s.shape[0]
    ns = config.teeth_per_rev
    # A wheel starting again after a stop: an interval longer than ``stop_timeout_s`` ends
    # the fit (it would average over the standstill); so does an interval far longer than
    # the latest one (a wheel leaving a near-stop).
    gaps = tau_s[:, :-1] - tau_s[:, 1:]  # interval before edge j, j = 0..kmax-2
    latest = np.where(w[:, 1], gaps[:, 0], np.inf)
    cut = gaps > _GAP_FACTOR * latest[:, None]
    cut[:, 0] = False  # (the latest interval itself)
    cut |= gaps > config.stop_timeout_s
    w = w.copy()
    w[:, 1:] &= np.cumsum(cut, axis=1) == 0
    n_fit = np.count_nonzero(w, axis=1)
    fit_ok = has & (n_fit >= 2)
    w &= fit_ok[:, None]
    span = np.where(fit_ok, -tau_s[np.arange(m), np.maximum(n_fit - 1, 0)], 1.0)
    span = np.where(span > 0, span, 1.0)
    u = tau_s / span[:, None]  # in [-1, 0]
    wf = w.astype(np.float64)
    quad = fit_ok & (n_fit >= 3) & (config.fit_order >= 2)
    # Weighted fit of [1, u, u²] (u² column off for linear fits).
    u2 = u * u
    if not quad.all():
        u2[~quad] = 0.0
    coef, a_inv11 = _solve_quadratic_fit(u, u2, wf, p, quad, fit_ok)
    om_fit = coef[1] / span
    # Uncertainty: residual scatter, floored by the ring's angle noise and the time-stamp
    # jitter, through (AᵀA)⁻¹. With three edges a quadratic leaves no residual at all; the
    # floor keeps such a fit from claiming the jitter's precision.
    resid = (p - (coef[0][:, None] + coef[1][:, None] * u + coef[2][:, None] * u2)) * wf
    n_par = np.where(quad, 3, 2)
    dof = np.maximum(n_fit - n_par, 1)
    s2 = _row_dot(resid, resid) / dof
    s2 = np.maximum(s2, (om_fit * config.timing_std_s) ** 2 + angle_var_rad2)
    std_fit = np.sqrt(s2 * np.maximum(a_inv11, 0.0)) / span

    omega = np.where(fit_ok, om_fit, np.nan)
    std = np.where(fit_ok, std_fit, np.nan)
    method = np.where(fit_ok, np.int8(WheelSpeedMethod.PERIOD), np.int8(WheelSpeedMethod.NONE))

    # Frequency method when the window is crowded.
    if freq_omega is not None:
        omega = np.where(freq, freq_omega, omega)
        std = np.where(freq, 2 * np.pi / (ns * config.window_s) / math.sqrt(3.0), std)
        method = np.where(freq, np.int8(WheelSpeedMethod.FREQUENCY), method)

    # Standstill: bound by the time since the last edge, zero after the timeout.
    single = has & ~fit_ok
    bound = stop_bound(last_ns, q, ns) * (1.0 + config.stop_bound_margin)
    # a fit overshooting a stop; no reverse without direction
    omega = np.where(~np.asarray(signed) & (omega < 0), 0.0, omega)
    sign = np.where(omega < 0, -1.0, 1.0)
    # A lone edge after a stop: at most one tooth since the edge before it.
    lone = np.where(has_prev, stop_bound(prev_ns, last_ns, ns), 0.0)
    mag = np.where(single, np.minimum(lone, bound), np.abs(omega))
    capped = mag > bound
    mag = np.minimum(mag, bound)
    stopped = has & ((q - last_ns) * _NS > config.stop_timeout_s)
    mag = np.where(stopped, 0.0, mag)
    omega = np.where(has, sign * mag, np.nan)
    # Capped or lone: the speed lies between 0 and the bound.
    std = np.where(capped | single, 0.5 * bound, std)
    std = np.where(stopped, 2 * np.pi / (ns * config.stop_timeout_s), std)
    method = np.where((capped | single | stopped) & has, np.int8(WheelSpeedMethod.PERIOD), method)
    return WheelSpeedResult(omega, std, method.astype(np.int8, copy=False))


def _row_sum(x: FloatArray) -> FloatArray:
    """Sum of each row of ``(m, k)`` (faster than ``sum(axis=1)`` for short rows)."""
    return np.einsum("ij->i", x)


def _row_dot(x: FloatArray, y: FloatArray) -> FloatArray:
    """``Σ_j x_ij·y_ij`` per row of ``(m, k)``."""
    return np.einsum("ij,ij->i", x, y)


_WELL_POSED = 1e-5
"""Below this ``det(A)/(A00·A11·A22)`` a normal-equation system is solved by LU, not cofactors.

A healthy quadratic fit on edges spread over ``[−1, 0]`` has a ratio near 1e-3; below 1e-5 (a
fit over a stop, edges bunched at one end: about 0.5 % of fits on simulated fleets) cofactors
and LU differ by up to 1e-7 in the reported std, so those rows take LU.
"""


def _solve_quadratic_fit(
    u: FloatArray,
    u2: FloatArray,
    wf: FloatArray,
    p: FloatArray,
    quad: npt.NDArray[np.bool_],
    fit_ok: npt.NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray]:
    """Normal equations ``A·c = b`` of the weighted least-squares fit ``p ≈ c0 + c1·u + c2·u2``.

    Each row (shape ``(m, k)`` inputs) is one fit; ``quad`` off: linear (``c2 = 0``); ``fit_ok``
    off: ``c = 0``. ``A`` is regularised by ``1e-12·I`` (degenerate spans). Solved in closed
    form (cofactors of the symmetric 3×3 ``A``); near-singular rows go through
    :func:`numpy.linalg.solve` as before.

    Returns
    -------
    coef : ndarray, shape (3, m)
        ``c0, c1, c2``.
    a_inv11 : ndarray, shape (m,)
        ``(A⁻¹)₁₁``, the variance factor of ``c1``.
    """
    wu = wf * u
    wu2 = wf * u2
    s00 = _row_sum(wf)
    s01 = _row_sum(wu)
    s02 = _row_sum(wu2)
    s11 = _row_dot(wu, u)
    s12 = _row_dot(wu, u2)
    s22 = _row_dot(wu2, u2)
    b0 = _row_dot(wf, p)
    b1 = _row_dot(wu, p)
    b2 = _row_dot(wu2, p)
    lin = ~quad
    s22 = np.where(lin, 1.0, s22)  # u2 is 0 on linear rows: s02 = s12 = b2 = 0 already
    bad = ~fit_ok
    if bad.any():
        s00, s11, s22 = (np.where(bad, 1.0, s) for s in (s00, s11, s22))
        s01, s02, s12, b0, b1, b2 = (np.where(bad, 0.0, s) for s in (s01, s02, s12, b0, b1, b2))
    s00 = s00 + 1e-12
    s11 = s11 + 1e-12
    s22 = s22 + 1e-12
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    c11 = s00 * s22 - s02 * s02
    c12 = s01 * s02 - s00 * s12
    c22 = s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / det
        coef = np.stack(
            [
                (c00 * b0 + c01 * b1 + c02 * b2) * inv_det,
                (c01 * b0 + c11 * b1 + c12 * b2) * inv_det,
                (c02 * b0 + c12 * b1 + c22 * b2) * inv_det,
            ]
        )
        a_inv11 = c11 * inv_det
        ill = ~(np.abs(det) > _WELL_POSED * np.abs(s00 * s11 * s22))
    if ill.any():
        r = np.flatnonzero(ill)
        cols = np.stack([np.ones_like(u[r]), u[r], u2[r]], axis=-1) * wf[r][..., None]
        A = np.einsum("mki,mkj->mij", cols, cols)
        b = np.einsum("mki,mk->mi", cols, p[r])
        A[lin[r], 2, :] = 0.0
        A[lin[r], :, 2] = 0.0
        A[lin[r], 2, 2] = 1.0
        b[lin[r], 2] = 0.0
        A[bad[r]] = np.eye(3)
        b[bad[r]] = 0.0
        A = A + np.eye(3) * 1e-12
        coef[:, r] = np.linalg.solve(A, b[..., None])[..., 0].T
        a_inv11[r] = np.linalg.inv(A)[:, 1, 1]
    return coef, a_inv11


def _quadratic_intercept(u: FloatArray, a: FloatArray, n: int) -> FloatArray:
    """``c0`` of the least-squares fit ``a ≈ c0 + c1·u + c2·u²``, one fit per row of ``(M, k)``.

    ``n`` points per row count (columns where both ``u`` and ``a`` are 0 add nothing else).
    Normal equations from the power sums of ``u`` (regularised by ``1e-12·I`` like
    :func:`_solve_quadratic_fit`, which takes the near-singular rows).
    """
    u2 = u * u
    s00 = np.full(u.shape[0], float(n)) + 1e-12
    s01 = _row_sum(u)
    s02 = _row_sum(u2)
    s11 = s02 + 1e-12
    s12 = _row_dot(u2, u)
    s22 = _row_dot(u2, u2) + 1e-12
    b0 = _row_sum(a)
    b1 = _row_dot(u, a)
    b2 = _row_dot(u2, a)
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    det = s00 * c00 + s01 * c01 + s02 * c02
    with np.errstate(divide="ignore", invalid="ignore"):
        c0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
        ill = ~(np.abs(det) > _WELL_POSED * np.abs(s00 * s11 * s22))
    if ill.any():
        r = np.flatnonzero(ill)
        yes = np.ones(r.shape[0], dtype=bool)
        wf = (u[r] != 0.0) | (a[r] != 0.0)
        c0[r] = _solve_quadratic_fit(u[r], u2[r], wf.astype(np.float64), a[r], yes, yes)[0][0]
    return c0


_SPLIT_MIN_ROWS = 256
"""Fewer fit rows than this are fitted as one group (:func:`_split_by_width`)."""


def _split_by_width(k: IntArray) -> list[IntArray]:
    """Rows ``0 … m−1`` in one or two groups so that ``Σ rows·(widest k in group)`` is least.

    Returns ``[arange(m)]`` when splitting saves less than a quarter.
    """
    m = k.shape[0]
    kmax = max(int(k.max()), 2)
    if m < _SPLIT_MIN_ROWS or kmax <= 8:
        return [np.arange(m)]
    n_le = np.cumsum(np.bincount(k, minlength=kmax + 1))  # rows with k ≤ j
    width = np.maximum(np.arange(kmax + 1), 2)
    cost = n_le * width + (m - n_le) * kmax
    j = int(np.argmin(cost))
    if cost[j] > 0.75 * m * kmax:
        return [np.arange(m)]
    narrow = k <= j
    return [np.flatnonzero(narrow), np.flatnonzero(~narrow)]


def _tooth(angle_rad: FloatArray, teeth_per_rev: int) -> IntArray:
    """Tooth number ``0 … Ns−1`` of the edge at each cumulative angle."""
    ns = teeth_per_rev
    return np.mod(np.rint(angle_rad * ns / (2 * np.pi)).astype(np.int64), ns)


_ARENA = (
    ("_stamp", np.int64),
    ("_angle", np.float64),
    ("_dslot", np.int64),
    ("_corr", np.float64),
)
"""The per-edge arrays of a :class:`WheelBank` (attribute name, dtype)."""

_MIN_SEGMENT = 64
"""Smallest per-wheel ring (edges); rings are powers of two."""


class WheelBank:
    """Encoder edges of many wheels in shared arrays: pushes are queued, queries vectorised.

    Each wheel is a *slot* (:meth:`add` returns its index). Its held edges live in a ring, a
    power-of-two segment of two flat arrays (times, cumulative angles) shared by all slots;
    a ring that fills up moves to a larger one at the end, and the arrays are compacted when
    half of them is abandoned rings. Per-slot state (ring place, calibration, trimming) is in
    arrays indexed by slot, so a query of any set of slots costs a fixed number of numpy
    calls, whatever the number of wheels.

    :meth:`push` only checks time order (skipped edges are counted at once, as
    :class:`WheelTracker` promises) and queues the batch; the queue is written into the rings,
    angles included, by the next query (or any read of held state) in one pass.

    A wheel's results do not depend on which bank holds it or how queries are batched: the
    same edges are held and trimmed, the same tooth calibration runs at the same grid instants.

    Parameters
    ----------
    config : WheelSpeedConfig
        Shared by every slot.
    """

    # per-slot state, grown by _alloc_slots
    _base: IntArray
    _mask: IntArray
    _head: IntArray
    _count: IntArray
    _last_angle: FloatArray
    _angle_before: FloatArray
    _signed: npt.NDArray[np.bool_]
    _cal_from: IntArray
    _cal_upto: IntArray
    _calibrated: IntArray
    _angle_var: FloatArray
    _delta: FloatArray

    def __init__(self, config: WheelSpeedConfig) -> None:
        self.config = config
        self._step_rad = 2.0 * np.pi / config.teeth_per_rev
        self._w_ns = round(config.window_s * 1e9)
        self._period_ns = round(config.calibration_period_s * 1e9)
        self._prior_var = (config.angle_noise_rel * self._step_rad) ** 2
        self._slots = 0  # high-water mark
        self._free: list[int] = []
        self._alloc_slots(16)
        self._stamp = np.zeros(0, dtype=np.int64)  # the rings
        self._angle = np.zeros(0, dtype=np.float64)
        self._dslot = np.zeros(0, dtype=np.int64)  # index of the edge's tooth in _delta.flat
        self._corr = np.zeros(0, dtype=np.float64)  # angle with the tooth correction in force
        self._used = 0  # arena elements handed out
        self._abandoned = 0  # arena elements of rings that moved
        self.compactions = 0
        """Times the rings were copied into fresh arrays (diagnostics)."""
        # push queue (Python lists: a push costs a few list appends)
        self._q_slot: list[int] = []
        self._q_stamp: list[IntArray] = []
        self._q_dir: list[tuple[int, npt.NDArray[np.int8]]] = []  # (batch number, directions)
        self._q_len: list[int] = []
        self._floor_ns: list[int] = []  # newest accepted stamp per slot (time-order check)
        self._removed: list[int] = []  # slots removed, to clear at the next flush
        self.skipped: list[int] = []
        """Per slot: edges dropped because they went back in time."""

    # --- slots ---------------------------------------------------------------------------
    def _alloc_slots(self, n: int) -> None:
        i64 = np.int64
        grow_slot_array(self, "_base", n, (), i64(0))  # ring start in the arena
        grow_slot_array(self, "_mask", n, (), i64(0))  # ring size − 1 (0: no ring yet)
        grow_slot_array(self, "_head", n, (), i64(0))  # edge number of the oldest held edge
        grow_slot_array(self, "_count", n, (), i64(0))  # edges ever accepted
        grow_slot_array(self, "_last_angle", n, (), 0.0)  # angle of the newest edge
        grow_slot_array(self, "_angle_before", n, (), 0.0)  # before the oldest held
        grow_slot_array(self, "_signed", n, (), False)
        grow_slot_array(self, "_cal_from", n, (), i64(0))  # next edge number to calibrate on
        grow_slot_array(self, "_cal_upto", n, (), i64(np.iinfo(np.int64).min))  # last instant
        grow_slot_array(self, "_calibrated", n, (), i64(0))
        grow_slot_array(self, "_angle_var", n, (), self._prior_var)  # edge angle noise [rad²]
        grow_slot_array(self, "_delta", n, (self.config.teeth_per_rev,), 0.0)

    def add(self) -> int:
        """A new, empty wheel; returns its slot index."""
        if self._removed:
            self._flush()
        if self._free:
            slot = self._free.pop()
        else:
            slot = self._slots
            self._slots += 1
            if slot >= self._base.shape[0]:
                self._alloc_slots(2 * self._base.shape[0])
            self._floor_ns.append(0)
            self.skipped.append(0)
        self._floor_ns[slot] = np.iinfo(np.int64).min
        self.skipped[slot] = 0
        for arr, value in (
            (self._base, 0),
            (self._mask, 0),
            (self._head, 0),
            (self._count, 0),
            (self._last_angle, 0.0),
            (self._angle_before, 0.0),
            (self._signed, False),
            (self._cal_from, 0),
            (self._cal_upto, np.iinfo(np.int64).min),
            (self._calibrated, 0),
            (self._angle_var, self._prior_var),
            (self._delta, 0.0),
        ):
            arr[slot] = value
        return slot

    def remove(self, slot: int) -> None:
        """Forget a wheel; its index may be handed out again by :meth:`add`.

        Only noted here (a tracker's finalizer may call this at any allocation, even in the
        middle of another call on the bank); the slot is cleared by the next flush.
        """
        self._removed.append(slot)

    def _clear_removed(self) -> None:
        removed, self._removed = self._removed, []
        for slot in removed:
            self._clear(slot)

    def _clear(self, slot: int) -> None:
        self._abandoned += int(self._mask[slot]) + 1 if self._mask[slot] else 0
        self._mask[slot] = self._base[slot] = 0  # no ring: reads of it land on index 0
        self._head[slot] = self._count[slot] = 0
        self._free.append(slot)

    # --- push ----------------------------------------------------------------------------
    def push(
        self, slot: int, stamp_ns: IntArray, direction: npt.NDArray[np.int8] | None = None
    ) -> int:
        """Queue edges of ``slot`` (see :meth:`WheelTracker.push`); back-in-time ones skipped.

        An edge is kept when it is not earlier than any edge before it (held or in the batch).
        Returns how many of these edges were skipped (also added to ``skipped[slot]``).
        """
        t = as_stamps(stamp_ns)
        tl = t.tolist()
        n = len(tl)
        if n == 0:
            return 0
        if direction is not None:
            self._signed[slot] = True
        floor = self._floor_ns[slot]
        skipped = 0
        if tl[0] < floor or (n > 1 and tl != sorted(tl)):
            prev = np.maximum.accumulate(np.concatenate([[floor], t[:-1]]))
            ok = t >= prev
            kept = int(ok.sum())
            skipped = n - kept
            self.skipped[slot] += skipped
            if kept == 0:
                return skipped
            t = t[ok]
            direction = None if direction is None else np.asarray(direction).reshape(-1)[ok]
            n = kept
            tl = t.tolist()
        self._floor_ns[slot] = tl[-1]
        if direction is not None:
            d = np.asarray(direction).reshape(-1)
            if d.shape[0] != n:
                raise ValueError(f"{d.shape[0]} directions for {n} edges")
            self._q_dir.append((len(self._q_slot), d))
        self._q_slot.append(slot)
        self._q_stamp.append(t)
        self._q_len.append(n)
        return skipped

    def _flush(self) -> None:
        """Write the queued batches into the rings, with their cumulative angles."""
        if not self._q_slot:
            if self._removed:
                self._clear_removed()
            return
        slots = np.array(self._q_slot, dtype=np.int64)
        lens = np.array(self._q_len, dtype=np.int64)
        # usually every slot has one batch queued: no chaining of batches within a slot
        one_each = len(set(self._q_slot)) == len(self._q_slot)
        t = np.concatenate(self._q_stamp)
        d_sum = None
        if self._q_dir:
            with_dir = np.zeros(slots.shape[0], dtype=bool)
            with_dir[[i for i, _ in self._q_dir]] = True
            d_all = np.ones(t.shape[0], dtype=np.int8)
            d_all[np.repeat(with_dir, lens)] = np.concatenate([d for _, d in self._q_dir])
            d_sum = np.cumsum(np.where(d_all < 0, -1, 1))
        self._q_slot, self._q_stamp, self._q_dir, self._q_len = [], [], [], []
        n_edges = t.shape[0]
        ends = np.cumsum(lens)
        starts = ends - lens
        in_batch = np.arange(n_edges) - np.repeat(starts, lens)  # edge index within its batch
        # Edge count within its batch (signed with direction): the angle is start + step·k,
        # as edge_angles computes it batch by batch.
        if d_sum is None:
            k = in_batch + 1
            total = lens
        else:
            before = np.concatenate([[0], d_sum])[starts]
            k = d_sum - np.repeat(before, lens)
            total = d_sum[ends - 1] - before
        step = self._step_rad
        cur = self._last_angle
        if one_each:
            start = cur[slots]
            cur[slots] = start + step * total.astype(np.float64)
            earlier = np.zeros_like(lens)
            by_slot = np.argsort(slots)
            touched, new_per_slot = slots[by_slot], lens[by_slot]
        else:
            # Batches of one slot, in push order: their start angles chain batch after batch,
            # and their edges follow the edges of the slot's earlier batches (``earlier``).
            order = np.argsort(slots, kind="stable")
            s_sorted = slots[order]
            first = np.flatnonzero(np.concatenate([[True], s_sorted[1:] != s_sorted[:-1]]))
            group = np.repeat(first, np.diff(np.concatenate([first, [slots.shape[0]]])))
            rank = np.empty_like(slots)
            rank[order] = np.arange(slots.shape[0]) - group
            start = np.empty(slots.shape[0])
            for r in range(int(rank.max()) + 1):
                b = np.flatnonzero(rank == r)
                start[b] = cur[slots[b]]
                cur[slots[b]] = start[b] + step * total[b].astype(np.float64)
            before_sorted = np.cumsum(lens[order]) - lens[order]
            earlier = np.empty_like(lens)
            earlier[order] = before_sorted - before_sorted[group]
            per_slot = np.bincount(slots, weights=lens, minlength=self._slots).astype(np.int64)
            touched = np.flatnonzero(per_slot)
            new_per_slot = per_slot[touched]
        angle = np.repeat(start, lens) + step * k.astype(np.float64)
        # Edge numbers: each slot's new edges follow its held ones, in push order.
        e_slot = np.repeat(slots, lens)
        number = self._count[e_slot] + np.repeat(earlier, lens) + in_batch
        self._fit_rings(touched, new_per_slot)
        self._count[touched] += new_per_slot
        at = self._base[e_slot] + (number & self._mask[e_slot])
        self._stamp[at] = t
        self._angle[at] = angle
        ns = self.config.teeth_per_rev
        dslot = e_slot * ns + _tooth(angle, ns)
        self._dslot[at] = dslot
        self._corr[at] = angle + self._delta.reshape(-1)[dslot]
        if self._removed:
            self._clear_removed()

    # --- rings ---------------------------------------------------------------------------
    def _fit_rings(self, slots: IntArray, extra: IntArray) -> None:
        """Move slots whose held edges plus ``extra`` new ones outgrow their ring.

        First compacts the arena when more of it is abandoned rings than live ones.
        """
        if self._abandoned > (1 << 16):
            live = int((self._mask[: self._slots] + (self._mask[: self._slots] > 0)).sum())
            if self._abandoned > live:
                self._compact()
        held = self._count[slots] - self._head[slots] + extra
        small = held > self._mask[slots] + (self._mask[slots] > 0)
        if not small.any():
            return
        grow = slots[small]
        size = np.maximum(
            _MIN_SEGMENT, 1 << np.ceil(np.log2(np.maximum(2 * held[small], 1))).astype(np.int64)
        )
        self._move(grow, size)

    def _move(self, slots: IntArray, size: IntArray) -> None:
        """Give ``slots`` new rings of ``size`` edges at the arena end, copying held edges."""
        need = self._used + int(size.sum())
        if need > self._stamp.shape[0]:
            cap = max(need, 2 * self._stamp.shape[0], 1 << 12)
            for name, dtype in _ARENA:
                new = np.zeros(cap, dtype=dtype)
                new[: self._used] = getattr(self, name)[: self._used]
                setattr(self, name, new)
        new_base = self._used + np.cumsum(size) - size
        self._used = need
        held = self._count[slots] - self._head[slots]
        had = self._mask[slots] > 0
        n = int(held[had].sum())
        if n:
            hs, hh = slots[had], held[had]
            rel = np.arange(n) - np.repeat(np.cumsum(hh) - hh, hh)
            number = np.repeat(self._head[hs], hh) + rel
            src = np.repeat(self._base[hs], hh) + (number & np.repeat(self._mask[hs], hh))
            dst = np.repeat(new_base[had], hh) + (number & np.repeat(size[had] - 1, hh))
            for name, _ in _ARENA:
                arr = getattr(self, name)
                arr[dst] = arr[src]
        self._abandoned += int((self._mask[slots] + had).sum())
        self._base[slots] = new_base
        self._mask[slots] = size - 1

    def _compact(self) -> None:
        """Copy every live ring into fresh arrays (abandoned rings dropped, rings resized)."""
        slots = np.flatnonzero(self._mask[: self._slots] > 0)
        held = self._count[slots] - self._head[slots]
        size = np.maximum(
            _MIN_SEGMENT, 1 << np.ceil(np.log2(np.maximum(2 * held, 1))).astype(np.int64)
        )
        old = {name: getattr(self, name) for name, _ in _ARENA}
        old_base, old_mask = self._base[slots].copy(), self._mask[slots].copy()
        cap = max(int(size.sum()) * 2, 1 << 12)
        for name, dtype in _ARENA:
            setattr(self, name, np.zeros(cap, dtype=dtype))
        new_base = np.cumsum(size) - size
        n = int(held.sum())
        if n:
            rel = np.arange(n) - np.repeat(np.cumsum(held) - held, held)
            number = np.repeat(self._head[slots], held) + rel
            src = np.repeat(old_base, held) + (number & np.repeat(old_mask, held))
            dst = np.repeat(new_base, held) + (number & np.repeat(size - 1, held))
            for name, _ in _ARENA:
                getattr(self, name)[dst] = old[name][src]
        self._base[slots] = new_base
        self._mask[slots] = size - 1
        self._used = int(size.sum())
        self._abandoned = 0
        self.compactions += 1

    def _at(self, slot: IntArray | np.int64, number: IntArray) -> IntArray:
        """Arena index of edge ``number`` of ``slot`` (shapes broadcast)."""
        return self._base[slot] + (number & self._mask[slot])

    def _search(self, slot: IntArray, lo: IntArray, hi: IntArray, value: IntArray) -> IntArray:
        """First edge number in ``[lo, hi)`` with a time after ``value`` (``hi`` if none).

        Bisection of every row at once (held times are non-decreasing), as many halvings as
        the widest range needs; a row whose range is already empty stays where it is.
        ``slot``, ``lo``, ``hi`` have shape ``(n,)``; ``value`` shape ``(n,)`` or ``(s, n)``
        (``s`` searches of the same rows in one pass; the result has ``value``'s shape).
        """
        base = self._base[slot]
        mask = self._mask[slot]
        width = int((hi - lo).max()) if lo.size else 0
        lo = np.broadcast_to(lo, value.shape)
        hi = np.broadcast_to(hi, value.shape)
        if width <= 0:
            return lo.copy()
        for _ in range(width.bit_length()):
            mid = (lo + hi) >> 1
            after = self._stamp[base + (mid & mask)] > value
            lo = np.where(after, lo, np.minimum(mid + 1, hi))
            hi = np.where(after, mid, hi)
        return lo

    # --- query ---------------------------------------------------------------------------
    def query(self, slots: IntArray, query_ns: IntArray) -> WheelSpeedResult:
        """Speeds of ``slots`` at the times ``query_ns``; trims their history.

        Same rules as :meth:`WheelTracker.query` (times not earlier than the slot's previous
        query; tooth corrections of the last calibration instant at or before each time).

        Parameters
        ----------
        slots : ndarray, shape (n,), int
            Slot indices (a slot may repeat when the times are shared).
        query_ns : ndarray, shape (m,) or (n, m), int64, non-decreasing along m
            The same times for every slot, or each slot's own (vehicles whose ticks lie on
            grids of different phase); then the slots must be distinct.

        Returns
        -------
        WheelSpeedResult
            Arrays of shape ``(n, m)``: row ``i`` is slot ``slots[i]``.
        """
        s = np.asarray(slots, dtype=np.int64).reshape(-1)
        q2 = np.asarray(query_ns, dtype=np.int64)
        n = s.shape[0]
        # one row per distinct slot for the calibration (a repeated slot shares its times)
        uniq, first = np.unique(s, return_index=True) if n > 1 else (s, np.zeros(1, np.int64))
        if q2.ndim == 2:
            if q2.shape[0] != n:
                raise ValueError(f"query_ns has {q2.shape[0]} rows for {n} slots")
            if uniq.shape[0] != n:
                raise ValueError("slots must be distinct when each has its own times")
        else:
            q2 = np.broadcast_to(q2.reshape(1, -1), (n, q2.size))
        m = q2.shape[1]
        self._flush()
        if n == 0 or m == 0:
            r = _unknown(n * m)
            return WheelSpeedResult(
                r.omega_radps.reshape(n, m), r.std_radps.reshape(n, m), r.method.reshape(n, m)
            )
        cfg = self.config
        omega = np.empty((n, m))
        std = np.empty((n, m))
        method = np.empty((n, m), dtype=np.int8)
        period = self._period_ns
        i = 0
        tail: tuple[IntArray, IntArray] | None = None
        while i < m:
            due = None
            if cfg.tooth_calibration:
                # each row calibrates on its own grid boundaries; a chunk of columns ends where
                # any row reaches its next boundary (other rows are not due there)
                boundary = (q2[first, i] // period) * period
                due = boundary > self._cal_upto[uniq]
                if not due.any():
                    due = None
                j = int((q2[first] < (boundary + period)[:, None]).sum(axis=1).min())
            else:
                j = m
            # The edges each fit and calibration needs, found in one bisection over the held
            # edges (a calibration moves no edge): the first after each query time, after it
            # − window_s (at or before the former) and, when a calibration is due, after the
            # slot's grid boundary.
            nq = j - i
            rs = np.repeat(s, nq)
            q = q2[:, i:j].reshape(-1)
            times = [q, q - self._w_ns]
            if due is not None:
                times.append(np.repeat((q2[:, i] // period) * period, nq))
            after = self._search(rs, self._head[rs], self._count[rs], np.stack(times))
            if due is not None:
                self._calibrate(uniq[due], after[2][first[due] * nq] - 1)
                self._cal_upto[uniq[due]] = boundary[due]
            res, tail = self._fit(rs, q, nq, after[0], after[1])
            omega[:, i:j] = res.omega_radps.reshape(n, j - i)
            std[:, i:j] = res.std_radps.reshape(n, j - i)
            method[:, i:j] = res.method.reshape(n, j - i)
            i = j
        assert tail is not None
        self._trim(s, *tail)
        return WheelSpeedResult(omega, std, method)

    def _corrected(self, at: IntArray) -> FloatArray:
        """Angles of the edges at arena indices ``at``, with their slot's tooth corrections."""
        return self._corr[at]

    def _recorrect(self, slots: IntArray) -> None:
        """Refresh the corrected angles of the held edges of ``slots`` (their corrections moved)."""
        held = self._count[slots] - self._head[slots]
        n = int(held.sum())
        if n == 0:
            return
        number = np.repeat(self._head[slots] - (np.cumsum(held) - held), held) + np.arange(n)
        at = self._at(np.repeat(slots, held), number)
        self._corr[at] = self._angle[at] + self._delta.reshape(-1)[self._dslot[at]]

    def _fit(
        self, rs: IntArray, q: IntArray, nq: int, end: IntArray, first_in: IntArray
    ) -> tuple[WheelSpeedResult, tuple[IntArray, IntArray]]:
        """:func:`omega_at` of slot ``rs[r]`` at time ``q[r]`` for every row ``r`` (shape
        ``(n·nq,)``: ``nq`` times of each slot in turn).

        ``end`` and ``first_in`` are each row's first edge after ``q`` and after
        ``q − window_s`` (edge numbers, :meth:`_search`). Also returns, per slot, the last edge
        at or before its last time and the first edge after that time − ``window_s``, for
        trimming.
        """
        cfg = self.config
        head = self._head[rs]
        last = end - 1
        tail = (last[nq - 1 :: nq], first_in[nq - 1 :: nq])
        has = last >= head
        if not has.any():
            return _unknown(rs.shape[0]), tail
        n_win = np.maximum(last - first_in + 1, 0)
        # Rows are fitted in (at most) two groups by how many edges they may use, so slow
        # wheels do not pay for the columns of the fastest one.
        groups = None
        if rs.shape[0] >= _SPLIT_MIN_ROWS:
            k = np.minimum(np.clip(n_win, cfg.min_edges, cfg.max_edges), end - head)
            groups = _split_by_width(np.where(has, k, 0))
        if groups is None or len(groups) == 1:
            res = self._fit_rows(rs, q, head, last, first_in, n_win, has)
            return res, tail
        m = rs.shape[0]
        omega, std = np.empty(m), np.empty(m)
        method = np.empty(m, dtype=np.int8)
        for g in groups:
            r = self._fit_rows(rs[g], q[g], head[g], last[g], first_in[g], n_win[g], has[g])
            omega[g], std[g], method[g] = r.omega_radps, r.std_radps, r.method
        return WheelSpeedResult(omega, std, method), tail

    def _fit_rows(
        self,
        rs: IntArray,
        q: IntArray,
        head: IntArray,
        last: IntArray,
        first_in: IntArray,
        n_win: IntArray,
        has: npt.NDArray[np.bool_],
    ) -> WheelSpeedResult:
        """Gather each row's edges and fit them (:func:`_speed_from_window`)."""
        cfg = self.config
        if not has.any():
            return _unknown(rs.shape[0])
        w, offs = _fit_mask(last, head, n_win, has, cfg)
        last_c = np.maximum(last, head)
        number = np.maximum(last_c[:, None] - offs[None, :], head[:, None])
        at = self._at(rs[:, None], number)
        stamp = self._stamp[at]  # column 0: the last edge, 1: the one before it (or head)
        tau_s = (stamp - q[:, None]).astype(np.float64) * _NS
        pos = self._corrected(at)
        p = pos - pos[:, :1]
        freq = has & (n_win >= cfg.frequency_min_count)
        freq_omega = None
        if freq.any():
            prior = self._corrected(self._at(rs, np.maximum(first_in - 1, head)))
            before = np.where(first_in > head, prior, self._angle_before[rs])
            freq_omega = (pos[:, 0] - before) / cfg.window_s
        return _speed_from_window(
            q,
            tau_s,
            p,
            w,
            has,
            freq,
            freq_omega,
            stamp[:, 0],
            stamp[:, 1],
            last - 1 >= head,
            cfg,
            self._signed[rs],
            self._angle_var[rs],
        )

    def _trim(self, s: IntArray, last: IntArray, first_in: IntArray) -> None:
        """Drop edges no later query can use."""
        cfg = self.config
        head = self._head[s]
        rel_last = last - head
        rel_old = first_in - 1 - head
        keep = np.maximum(0, np.minimum(rel_last - cfg.max_edges - 1, rel_old - 1))
        if cfg.tooth_calibration:
            keep = np.minimum(
                keep, np.maximum(self._cal_from[s] - head - cfg.calibration_half_window - 1, 0)
            )
        cut = (keep > 0) & (self._count[s] > head)
        if not cut.any():
            return
        cs, new_head = s[cut], head[cut] + keep[cut]
        self._angle_before[cs] = self._angle[self._at(cs, new_head - 1)]
        self._head[cs] = new_head

    def _calibrate(self, slots: IntArray, last: IntArray) -> None:
        """Learn tooth corrections of ``slots`` (distinct, ascending) from edges with a full
        window at or before their calibration instant ``t_ns``; ``last`` is the number of each
        slot's last edge at or before it (``head − 1`` if none).

        For each slot: the edges not yet used that have ``calibration_half_window`` (``h``)
        neighbours on both sides at or before ``t_ns``; per edge, a quadratic fit of its ``2h``
        neighbours' angles against time (corrected with the slot's current corrections, the
        edge itself left out), and the tooth's correction moves by ``calibration_gain`` of the
        edge's residual; corrections are then made zero-mean again. The edges of a slot are
        read once as one run ``lo − h … hi + h``; the windows are rows ``(M, 2h)`` over it.
        """
        cfg = self.config
        h = cfg.calibration_half_window
        head = self._head[slots]
        lo = np.maximum(self._cal_from[slots], head + h)
        hi = last - h
        go = hi >= lo
        if not go.any():
            return
        slots, lo, hi = slots[go], lo[go], hi[go]
        self._cal_from[slots] = hi + 1
        n_c = hi - lo + 1  # centres per slot
        run_len = n_c + 2 * h
        run_first = np.cumsum(run_len) - run_len
        run_slot = np.repeat(slots, run_len)
        n_run = int(run_len.sum())
        number = np.repeat(lo - h - run_first, run_len) + np.arange(n_run)
        at = self._at(run_slot, number)
        stamp = self._stamp[at]
        raw = self._angle[at]
        ang = self._corr[at]
        # window rows: centre index in the run arrays, neighbours −h … −1, 1 … h
        m = int(n_c.sum())
        row_slot = np.repeat(slots, n_c)
        centre = np.repeat(run_first + h - (np.cumsum(n_c) - n_c), n_c) + np.arange(m)
        # no interval ≥ stop_timeout_s inside the window; with direction, one way only
        gap_ns = np.diff(stamp)
        long_gap = np.concatenate([[0], np.cumsum(gap_ns * _NS >= cfg.stop_timeout_s)])
        ok = long_gap[centre + h] == long_gap[centre - h]
        ok &= stamp[centre + h] > stamp[centre - h]  # span > 0
        signed = self._signed[row_slot]
        if signed.any():
            step = np.diff(raw)
            up = np.concatenate([[0], np.cumsum(step > 0)])
            down = np.concatenate([[0], np.cumsum(step < 0)])
            n_up = up[centre + h] - up[centre - h]
            n_down = down[centre + h] - down[centre - h]
            ok &= (n_up == 2 * h) | (n_down == 2 * h) | ~signed
        any_ok = np.zeros(self._slots, dtype=bool)
        any_ok[row_slot[ok]] = True
        if not ok.any():
            return
        centre, row_slot = centre[ok], row_slot[ok]
        # Windows as rows (M, 2h + 1) of the run; the centre column is exactly 0 in both time
        # and angle, so it adds nothing to the fit: the centre edge is left out (its own error
        # must not pull the fit).
        t_run = (stamp - stamp[0]).astype(np.float64) * _NS
        win_t = sliding_window_view(t_run, 2 * h + 1)[centre - h]
        win_a = sliding_window_view(ang, 2 * h + 1)[centre - h]
        ts = win_t - win_t[:, h : h + 1]
        u = ts / (ts[:, -1] - ts[:, 0])[:, None]
        a = win_a - win_a[:, h : h + 1]
        c0 = _quadratic_intercept(u, a, 2 * h)
        resid = -c0  # centre angle (0 by construction) minus the fit at the centre
        pitch = 2 * np.pi / cfg.teeth_per_rev
        good = np.abs(resid) < 0.3 * pitch
        flat = self._delta.reshape(-1)
        np.add.at(flat, self._dslot[at[centre[good]]], -cfg.calibration_gain * resid[good])
        upd = np.flatnonzero(any_ok)
        self._delta[upd] -= (_row_sum(self._delta[upd]) / cfg.teeth_per_rev)[:, None]
        self._recorrect(upd)
        np.add.at(self._calibrated, row_slot[good], 1)
        self._learn_angle_noise(row_slot[good], resid[good])

    def _learn_angle_noise(self, row_slot: IntArray, resid: FloatArray) -> None:
        """Move each slot's edge angle variance toward its calibration residuals (in place).

        ``resid`` are this calibration's residuals (before their correction), ``row_slot``
        their slots (non-decreasing). The residual of an edge against its neighbours' fit is
        the error a fit would see with the corrections then in force; its mean square over the
        ``M`` new residuals of a slot enters an exponential mean with a memory of one revolution
        (``teeth_per_rev`` edges): ``v ← (1 − β)·v + β·mean(r²)``, ``β = 1 − (1 − 1/Ns)^M``.
        (The residual also carries the neighbours' fit error, a few percent of its variance
        with the default window: the floor errs on the safe side.)
        """
        if resid.shape[0] == 0:
            return
        # row_slot is non-decreasing (from _calibrate): its runs are the slots
        new = np.ones(row_slot.shape[0], dtype=bool)
        new[1:] = row_slot[1:] != row_slot[:-1]
        slots = row_slot[new]
        run = np.cumsum(new) - 1
        n = np.bincount(run)
        mean_sq = np.bincount(run, weights=resid * resid) / n
        beta = 1.0 - (1.0 - 1.0 / self.config.teeth_per_rev) ** n
        self._angle_var[slots] += beta * (mean_sq - self._angle_var[slots])

    # --- per-slot views ------------------------------------------------------------------
    def held_stamp_ns(self, slot: int) -> IntArray:
        """Times of the edges ``slot`` holds, shape ``(n,)`` (pending pushes included)."""
        self._flush()
        number = np.arange(self._head[slot], self._count[slot])
        if number.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        return self._stamp[self._at(np.int64(slot), number)]

    def tooth_correction_rad(self, slot: int) -> FloatArray:
        """Learnt angle correction per tooth of ``slot``, shape ``(teeth_per_rev,)``."""
        self._flush()
        return self._delta[slot].copy()

    def calibrated_edges(self, slot: int) -> int:
        """Edges the tooth calibration of ``slot`` has learnt from."""
        return int(self._calibrated[slot])

    def angle_noise_rad(self, slot: int) -> float:
        """1-sigma angle error of one edge of ``slot`` that its fits are floored by [rad]."""
        self._flush()
        return math.sqrt(float(self._angle_var[slot]))


class WheelTracker:
    """Streaming, causal speed of one wheel from its encoder edges.

    Push :class:`~estimator.types.WheelEdges` batches in time order with :meth:`push`; ask
    :meth:`query` for the speed at times not earlier than the previous query. Keeps only the
    edges a later query can need.

    Tooth calibration: real rings have unevenly spaced teeth (a fixed pattern, a percent of
    the pitch), which puts a fixed error on every edge's angle and, through the fit, a
    speed error that repeats every turn. The tracker learns the pattern: each edge with
    ``calibration_half_window`` edges on both sides (already received) is compared with a
    local quadratic fit of its neighbours, and the tooth's angle correction moves by
    ``calibration_gain`` of the residual (corrections kept zero-mean), on a fixed time grid.
    Tooth ``j`` is the edge count modulo ``teeth_per_rev``. Only past edges are used, so
    speeds stay causal.

    A tracker is a slot of a :class:`WheelBank`: its own bank unless one is given. The first
    :func:`query_many` over trackers of several banks (same config) moves them into one, so
    later calls fit them all in one pass.

    Parameters
    ----------
    config : WheelSpeedConfig
    bank : WheelBank, optional
        Bank to hold the edges (its config must equal ``config``).
    """

    def __init__(self, config: WheelSpeedConfig, bank: WheelBank | None = None) -> None:
        if bank is not None and bank.config != config:
            raise ConfigError("a WheelTracker's bank must have the tracker's config")
        self.config = config
        self._bank = bank if bank is not None else WheelBank(config)
        self._slot = self._bank.add()
        self._finalizer = weakref.finalize(self, WheelBank.remove, self._bank, self._slot)

    @property
    def skipped(self) -> int:
        """Edges dropped because they went back in time."""
        return self._bank.skipped[self._slot]

    @property
    def calibrated_edges(self) -> int:
        """Edges the tooth calibration has learnt from."""
        return self._bank.calibrated_edges(self._slot)

    @property
    def angle_noise_rad(self) -> float:
        """1-sigma angle error of one edge: the prior ``angle_noise_rel`` of the pitch, then
        what the tooth calibration measures."""
        return self._bank.angle_noise_rad(self._slot)

    @property
    def last_edge_ns(self) -> int | None:
        """Time of the newest edge held, or None."""
        stamp = self._bank.held_stamp_ns(self._slot)
        return int(stamp[-1]) if stamp.size else None

    @property
    def held_stamp_ns(self) -> IntArray:
        """Times of the edges held, shape ``(n,)``."""
        return self._bank.held_stamp_ns(self._slot)

    @property
    def tooth_correction_rad(self) -> FloatArray:
        """Learnt angle correction of each tooth, shape ``(teeth_per_rev,)``, zero mean."""
        return self._bank.tooth_correction_rad(self._slot)

    def push(self, stamp_ns: IntArray, direction: npt.NDArray[np.int8] | None = None) -> int:
        """Append edges (non-decreasing stamps; earlier-than-held ones are skipped and counted);
        returns how many of these were skipped."""
        return self._bank.push(self._slot, stamp_ns, direction)

    def query(self, query_ns: IntArray) -> WheelSpeedResult:
        """Speed at each time in ``query_ns`` (shape ``(m,)``, non-decreasing); trims history.

        The tooth corrections in force at time ``t`` are those learnt from the edges up to the
        last multiple of ``calibration_period_s`` at or before ``t``, so results do not depend
        on how queries are batched.
        """
        r = self._bank.query(np.array([self._slot]), query_ns)
        return WheelSpeedResult(r.omega_radps[0], r.std_radps[0], r.method[0])

    def _move_to(self, bank: WheelBank) -> None:
        """Carry this wheel's state (held edges, calibration, counters) into ``bank``."""
        old, slot = self._bank, self._slot
        old._flush()
        bank._flush()
        new = bank.add()
        stamp = old.held_stamp_ns(slot)
        n = stamp.shape[0]
        if n:
            angle = old._angle[
                old._at(np.int64(slot), np.arange(old._head[slot], old._count[slot]))
            ]
            bank._fit_rings(np.array([new]), np.array([n]))
            bank._count[new] = n
            at = bank._at(np.int64(new), np.arange(n))
            bank._stamp[at] = stamp
            bank._angle[at] = angle
            ns = self.config.teeth_per_rev
            bank._dslot[at] = new * ns + _tooth(angle, ns)
            bank._corr[at] = old._corr[
                old._at(np.int64(slot), np.arange(old._head[slot], old._count[slot]))
            ]
        shift = int(old._head[slot])
        bank._cal_from[new] = old._cal_from[slot] - shift
        for name in (
            "_last_angle",
            "_angle_before",
            "_signed",
            "_cal_upto",
            "_calibrated",
            "_angle_var",
            "_delta",
        ):
            getattr(bank, name)[new] = getattr(old, name)[slot]
        bank._floor_ns[new] = old._floor_ns[slot]
        bank.skipped[new] = old.skipped[slot]
        self._finalizer.detach()
        old.remove(slot)
        self._bank, self._slot = bank, new
        self._finalizer = weakref.finalize(self, WheelBank.remove, bank, new)


def query_many(trackers: list[WheelTracker], query_ns: IntArray) -> list[WheelSpeedResult]:
    """:meth:`WheelTracker.query` of several trackers, in one vectorised fit.

    Equivalent to querying each tracker on its own. Trackers of one config that sit in
    different banks are first moved into one (the biggest), once (:func:`gather_bank`); from
    then on a call costs a fixed number of numpy calls plus a Python attribute read per tracker.

    Parameters
    ----------
    trackers : list of WheelTracker
        Distinct trackers.
    query_ns : ndarray, shape (m,) or (len(trackers), m), int64, non-decreasing along m
        The same times for every tracker, or each tracker's own.

    Returns
    -------
    list of WheelSpeedResult, one per tracker, arrays of shape (m,)
    """
    q = np.asarray(query_ns, dtype=np.int64)
    if not trackers:
        return []
    held = gather_bank(trackers)
    if held is None:
        rows = q if q.ndim == 2 else np.broadcast_to(q, (len(trackers), q.shape[0]))
        return [t.query(r) for t, r in zip(trackers, rows, strict=True)]
    bank, slots = held
    r = bank.query(slots, q)
    return list(map(_result_row, r.omega_radps, r.std_radps, r.method))


def gather_bank(trackers: list[WheelTracker]) -> tuple[WheelBank, IntArray] | None:
    """The bank that holds every one of ``trackers`` (not empty) and their slots in it.

    Trackers spread over several banks are moved into the biggest of them first. Only this
    function (also through :func:`query_many`) moves trackers, so a caller may keep the answer
    and query the bank directly (:meth:`WheelBank.query`, one row per slot) as long as it
    takes the answer of every later call for the trackers of that call. None when the
    trackers' configs differ (they cannot share a bank).
    """
    bank = trackers[0]._bank
    if not all(t._bank is bank for t in trackers):
        cfg = trackers[0].config
        if any(t.config != cfg for t in trackers):
            return None
        banks = {id(t._bank): t._bank for t in trackers}
        bank = max(banks.values(), key=lambda b: b._slots - len(b._free))
        for t in trackers:
            if t._bank is not bank:
                t._move_to(bank)
    slots = np.fromiter((t._slot for t in trackers), dtype=np.int64, count=len(trackers))
    return bank, slots


_set_omega = WheelSpeedResult.__dict__["omega_radps"].__set__
_set_std = WheelSpeedResult.__dict__["std_radps"].__set__
_set_method = WheelSpeedResult.__dict__["method"].__set__


def _result_row(
    omega: FloatArray, std: FloatArray, method: npt.NDArray[np.int8]
) -> WheelSpeedResult:
    """``WheelSpeedResult(omega, std, method)`` without the frozen dataclass's ``__init__``.

    That ``__init__`` sets each field through ``object.__setattr__``, about 1 µs a result: as
    much as the whole fit of a wheel when :func:`query_many` answers thousands. The slot
    descriptors store the same three fields directly.
    """
    r = object.__new__(WheelSpeedResult)
    _set_omega(r, omega)
    _set_std(r, std)
    _set_method(r, method)
    return r


class DirectWheelSpeed:
    """Wheel speeds given directly (CAN :class:`~estimator.types.WheelSpeeds`), both wheels.

    The value at ``t`` is the latest finite sample at or before ``t`` (causal hold), unknown
    (NaN) once older than ``stale_s``.

    Parameters
    ----------
    stale_s : float
        Age after which a held sample is no longer used [s].
    std_radps : float
        1-sigma noise reported with the values.
    """

    def __init__(self, stale_s: float = 0.5, std_radps: float = 0.02) -> None:
        self.stale_ns = round(stale_s * 1e9)
        self.std_radps = std_radps
        self._stamp = np.zeros(0, dtype=np.int64)
        self._omega = np.zeros((0, 2), dtype=np.float64)
        self.skipped = 0
        """Samples dropped (non-finite or back in time)."""

    @property
    def has_data(self) -> bool:
        return bool(self._stamp.size)

    def push(self, stamp_ns: IntArray, omega_radps: FloatArray) -> None:
        """Append samples; shapes ``(n,)`` and ``(n, 2)``."""
        t = np.asarray(stamp_ns, dtype=np.int64)
        om = np.asarray(omega_radps, dtype=np.float64).reshape(-1, 2)
        if t.size == 0 or om.shape[0] != t.size:
            self.skipped += int(t.size)
            return
        floor = self._stamp[-1] if self._stamp.size else np.iinfo(np.int64).min
        ok = np.isfinite(om).all(axis=1) & (t >= floor)
        if t.size > 1:
            ok[1:] &= t[1:] >= t[:-1]
        self.skipped += int((~ok).sum())
        self._stamp = np.concatenate([self._stamp, t[ok]])
        self._omega = np.concatenate([self._omega, om[ok]])

    def query(self, query_ns: IntArray) -> tuple[FloatArray, FloatArray]:
        """Speeds at each query time: ``omega (m, 2)`` and ``std (m, 2)``; NaN when unknown."""
        q = np.asarray(query_ns, dtype=np.int64)
        i = np.searchsorted(self._stamp, q, side="right") - 1
        ok = (
            (i >= 0) & (q - self._stamp[np.maximum(i, 0)] <= self.stale_ns)
            if self._stamp.size
            else (np.zeros(q.size, dtype=bool))
        )
        om = np.full((q.size, 2), np.nan)
        if self._stamp.size:
            om[ok] = self._omega[i[ok]]
            keep = (
                max(0, int(np.searchsorted(self._stamp, q[-1], side="right")) - 2) if q.size else 0
            )
            if keep > 0:
                self._stamp = self._stamp[keep:]
                self._omega = self._omega[keep:]
        std = np.where(np.isfinite(om), self.std_radps, np.nan)
        return om, std
