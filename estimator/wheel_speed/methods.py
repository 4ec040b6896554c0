"""Wheel angular speed from encoder edges: the period and frequency methods (``method.md`` §2).

A toothed ring with ``Ns`` teeth gives one rising edge every ``2π/Ns`` of wheel rotation.

* **Period method, k-tooth average** (source 001): over ``k`` tooth intervals
  ``t_k = t(i+k) − t(i)``, ``ω = 2π·k/(Ns·t_k)`` (:func:`omega_k_tooth`).
* **Frequency method**: count the edges in a fixed window ``W``, ``ω = 2π·n/(Ns·W)``; its error is
  ±1 count, so it is only good when the window holds many edges (:func:`omega_frequency`).

A k-tooth average is the speed at the *middle* of its span, which lies in the past of the time the
estimate is stamped with; under an angular acceleration ``α`` that is a bias of
``α·(t − t_mid)``. :func:`omega_at` removes it by fitting the wheel angle of the last ``k`` edges
with a quadratic in time and evaluating the derivative *at the query time*; with at most one edge
interval of extrapolation the fit is exact under constant acceleration and unbiased to first
order otherwise. Its slope (linear fit, ``fit_order=1``) is the least-squares form of the k-tooth
average and is what the period method reduces to when too few edges are there for the quadratic.

``k`` follows the speed: the fit takes the edges of the last ``window_s`` (at least
``min_edges``, at most ``max_edges``), so a slow wheel uses a few long periods and a fast wheel
many short ones. The frequency method takes over only when the window holds at least
``frequency_min_count`` edges (a very high edge rate). Every result says which method it used.

Standstill: a wheel that stops gives no more edges, so the last speed must not be held. If no
edge came for ``τ = t − t_last``, the wheel is slower than one tooth per ``τ``:
``|ω| ≤ 2π/(Ns·τ)``, and after ``stop_timeout_s`` it is taken as stopped (``ω = 0``).

Direction: a quadrature encoder gives ``±1`` per edge; the wheel angle then steps back on reverse
edges and the fitted slope is signed. Without direction every edge counts forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

from estimator._arrays import FloatArray, IntArray
from estimator.config import ConfigError

__all__ = [
    "WheelSpeedConfig",
    "WheelSpeedMethod",
    "WheelSpeedResult",
    "edge_angles",
    "omega_at",
    "omega_frequency",
    "omega_k_tooth",
    "stop_bound",
]

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
    return _omega_in_windows(e, pos, q, last, seg0, has, config, angle_before_rad, signed)


def _omega_in_windows(
    e: IntArray,
    pos: FloatArray,
    q: IntArray,
    last: IntArray,
    seg0: IntArray,
    has: npt.NDArray[np.bool_],
    config: WheelSpeedConfig,
    angle_before_rad: float | FloatArray,
    signed: bool | npt.NDArray[np.bool_],
) -> WheelSpeedResult:
    """Gather each query's window of edges (``last``: its last edge) and fit it (``omega_at``)."""
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
        freq_omega = _count_speed(pos, first_in, seg0, last_c, angle_before_rad, config)
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


def _count_speed(
    pos: FloatArray,
    first_in: IntArray,
    seg0: IntArray,
    last_c: IntArray,
    angle_before_rad: float | FloatArray,
    config: WheelSpeedConfig,
) -> FloatArray:
    """Angle turned over the window divided by the window (the frequency method's ``ω``)."""
    before = np.where(first_in > seg0, pos[np.maximum(first_in - 1, 0)], angle_before_rad)
    return (pos[last_c] - before) / config.window_s


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
    omega, std, method, fit_ok = _fit_window(tau_s, p, w, has, config, angle_var_rad2)
    ns = config.teeth_per_rev
    # Frequency method when the window is crowded.
    if freq_omega is not None:
        omega = np.where(freq, freq_omega, omega)
        std = np.where(freq, 2 * np.pi / (ns * config.window_s) / math.sqrt(3.0), std)
        method = np.where(freq, np.int8(WheelSpeedMethod.FREQUENCY), method)
    return _bound_at_standstill(
        WheelSpeedResult(omega, std, method),
        q,
        has & ~fit_ok,
        has,
        last_ns,
        np.where(has_prev, stop_bound(prev_ns, last_ns, ns), 0.0),
        config,
        signed,
    )


def _fit_window(
    tau_s: FloatArray,
    p: FloatArray,
    w: npt.NDArray[np.bool_],
    has: npt.NDArray[np.bool_],
    config: WheelSpeedConfig,
    angle_var_rad2: float | FloatArray,
) -> tuple[FloatArray, FloatArray, npt.NDArray[np.int8], npt.NDArray[np.bool_]]:
    """Weighted fit of the wheel angle to ``[1, u, u²]`` over each query's window.

    ``u = tau / span`` in [-1, 0]; ω = c₁ / span, its std from the residual scatter (floored by
    the ring's angle noise and the stamp jitter) through ``(AᵀA)⁻¹``. Returns ω, its std and
    the method, shape (m,) each (NaN and ``NONE`` where no fit), and which rows were fitted.
    """
    m = tau_s.shape[0]
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
    # With three edges a quadratic leaves no residual at all; the floor keeps such a fit from
    # claiming the jitter's precision.
    resid = (p - (coef[0][:, None] + coef[1][:, None] * u + coef[2][:, None] * u2)) * wf
    n_par = np.where(quad, 3, 2)
    dof = np.maximum(n_fit - n_par, 1)
    s2 = _row_dot(resid, resid) / dof
    s2 = np.maximum(s2, (om_fit * config.timing_std_s) ** 2 + angle_var_rad2)
    std_fit = np.sqrt(s2 * np.maximum(a_inv11, 0.0)) / span
    omega = np.where(fit_ok, om_fit, np.nan)
    std = np.where(fit_ok, std_fit, np.nan)
    method = np.where(fit_ok, np.int8(WheelSpeedMethod.PERIOD), np.int8(WheelSpeedMethod.NONE))
    return omega, std, method, fit_ok


def _bound_at_standstill(
    fitted: WheelSpeedResult,
    q: IntArray,
    single: npt.NDArray[np.bool_],
    has: npt.NDArray[np.bool_],
    last_ns: IntArray,
    lone: FloatArray,
    config: WheelSpeedConfig,
    signed: bool | npt.NDArray[np.bool_],
) -> WheelSpeedResult:
    """Bound ω by the time since the last edge (at most one tooth since), zero after the timeout.

    ``single`` rows hold one edge and no fit: their speed is at most ``lone`` (one tooth since the
    edge before), shape (m,). Capped and lone speeds lie between 0 and the bound: std = bound / 2.
    """
    ns = config.teeth_per_rev
    omega, std, method = fitted.omega_radps, fitted.std_radps, fitted.method
    bound = stop_bound(last_ns, q, ns) * (1.0 + config.stop_bound_margin)
    # a fit overshooting a stop; no reverse without direction
    omega = np.where(~np.asarray(signed) & (omega < 0), 0.0, omega)
    sign = np.where(omega < 0, -1.0, 1.0)
    mag = np.where(single, np.minimum(lone, bound), np.abs(omega))
    capped = mag > bound
    mag = np.minimum(mag, bound)
    stopped = has & ((q - last_ns) * _NS > config.stop_timeout_s)
    mag = np.where(stopped, 0.0, mag)
    omega = np.where(has, sign * mag, np.nan)
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
    :func:`numpy.linalg.solve`.

    Returns
    -------
    coef : ndarray, shape (3, m)
        ``c0, c1, c2``.
    a_inv11 : ndarray, shape (m,)
        ``(A⁻¹)₁₁``, the variance factor of ``c1``.
    """
    s00, s01, s02, s11, s12, s22, b0, b1, b2 = _weighted_sums(u, u2, wf, p, quad, fit_ok)
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
        _solve_ill_rows(np.flatnonzero(ill), u, u2, wf, p, ~quad, ~fit_ok, coef, a_inv11)
    return coef, a_inv11


def _weighted_sums(
    u: FloatArray,
    u2: FloatArray,
    wf: FloatArray,
    p: FloatArray,
    quad: npt.NDArray[np.bool_],
    fit_ok: npt.NDArray[np.bool_],
) -> tuple[FloatArray, ...]:
    """``(s00, s01, s02, s11, s12, s22, b0, b1, b2)`` of ``A``, ``b``; linear and bad rows set."""
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
    s22 = np.where(~quad, 1.0, s22)  # u2 is 0 on linear rows: s02 = s12 = b2 = 0 already
    bad = ~fit_ok
    if bad.any():
        s00, s11, s22 = (np.where(bad, 1.0, s) for s in (s00, s11, s22))
        s01, s02, s12, b0, b1, b2 = (np.where(bad, 0.0, s) for s in (s01, s02, s12, b0, b1, b2))
    return s00, s01, s02, s11, s12, s22, b0, b1, b2


def _solve_ill_rows(
    r: IntArray,
    u: FloatArray,
    u2: FloatArray,
    wf: FloatArray,
    p: FloatArray,
    lin: npt.NDArray[np.bool_],
    bad: npt.NDArray[np.bool_],
    coef: FloatArray,
    a_inv11: FloatArray,
) -> None:
    """Rows ``r`` of :func:`_solve_quadratic_fit` by LU, written into ``coef`` and ``a_inv11``."""
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
