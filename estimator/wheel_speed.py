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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

from estimator.config import ConfigError

__all__ = [
    "DirectWheelSpeed",
    "WheelSpeedConfig",
    "WheelSpeedMethod",
    "WheelSpeedResult",
    "WheelTracker",
    "edge_angles",
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
        Most edges a fit uses (fast wheel), ≥ ``min_edges``.
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
    stop_bound_margin : float
        The standstill bound allows a tooth gap this much wider than nominal
        (``|ω| ≤ (1 + margin)·2π/(Ns·τ)``): real rings have uneven teeth, and a late edge
        after a wide tooth must not cut a steady speed [-].
    """

    teeth_per_rev: int = 120
    window_s: float = 0.3
    min_edges: int = 3
    max_edges: int = 64
    fit_order: int = 2
    frequency_min_count: int = 2000
    stop_timeout_s: float = 2.0
    timing_std_s: float = 2e-5
    stop_bound_margin: float = 0.5
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
        When several wheels share the arrays (:func:`query_many`): index of the first edge of
        each query's wheel; edges before it are not that wheel's.

    Returns
    -------
    WheelSpeedResult
        Arrays of shape ``(m,)``.
    """
    e = np.asarray(stamp_ns, dtype=np.int64)
    pos = np.asarray(angle_rad, dtype=np.float64)
    q = np.asarray(query_ns, dtype=np.int64)
    m = q.shape[0]
    ns = config.teeth_per_rev
    omega = np.full(m, np.nan)
    std = np.full(m, np.nan)
    method = np.full(m, int(WheelSpeedMethod.NONE), dtype=np.int8)
    if m == 0:
        return WheelSpeedResult(omega, std, method)
    last = np.searchsorted(e, q, side="right") - 1  # index of the last edge ≤ t
    seg0 = np.zeros(m, dtype=np.int64) if segment_start is None else np.asarray(segment_start)
    has = last >= seg0
    if e.shape[0] == 0 or not has.any():
        return WheelSpeedResult(omega, std, method)

    w_ns = round(config.window_s * 1e9)
    first_in = np.searchsorted(e, q - w_ns, side="right")
    n_win = np.maximum(last - first_in + 1, 0)
    n_fit = np.clip(n_win, config.min_edges, config.max_edges)
    n_fit = np.minimum(n_fit, last - seg0 + 1)  # cannot use more edges than exist
    # Gather the candidate edges: row j holds edges last, last-1, ...
    kmax = int(n_fit[has].max()) if has.any() else 2
    kmax = max(kmax, 2)
    offs = np.arange(kmax)
    idx = last[:, None] - offs[None, :]
    w = (offs[None, :] < n_fit[:, None]) & (idx >= seg0[:, None]) & has[:, None]
    idx = np.clip(idx, 0, max(e.shape[0] - 1, 0))
    tau_s = (e[idx] - q[:, None]).astype(np.float64) * _NS  # ≤ 0
    # A wheel starting again after a stop: an interval longer than ``stop_timeout_s`` ends
    # the fit (it would average over the standstill); so does an interval far longer than
    # the latest one (a wheel leaving a near-stop).
    gaps = tau_s[:, :-1] - tau_s[:, 1:]  # interval before edge j, j = 0..kmax-2
    latest = np.where(w[:, 1], gaps[:, 0], np.inf)
    cut = (gaps > config.stop_timeout_s) | (gaps > _GAP_FACTOR * latest[:, None]) & (
        offs[None, 1:] > 1
    )
    keep = np.concatenate([np.ones((m, 1), bool), np.cumsum(cut, axis=1) == 0], axis=1)
    w &= keep
    n_fit = w.sum(axis=1)
    fit_ok = has & (n_fit >= 2)
    w &= fit_ok[:, None]
    span = np.where(fit_ok, -tau_s[np.arange(m), np.maximum(n_fit - 1, 0)], 1.0)
    span = np.where(span > 0, span, 1.0)
    u = tau_s / span[:, None]  # in [-1, 0]
    p = pos[idx] - pos[last][:, None]
    wf = w.astype(np.float64)
    quad = fit_ok & (n_fit >= 3) & (config.fit_order >= 2)
    # Normal equations of the weighted fit [1, u, u²] (u² column off for linear fits).
    u2 = u * u * quad[:, None]
    cols = np.stack([np.ones_like(u), u, u2], axis=-1) * wf[..., None]  # (m, k, 3)
    A = np.einsum("mki,mkj->mij", cols, cols)
    b = np.einsum("mki,mk->mi", cols, p)
    lin = ~quad
    A[lin, 2, :] = 0.0
    A[lin, :, 2] = 0.0
    A[lin, 2, 2] = 1.0
    b[lin, 2] = 0.0
    bad = ~fit_ok
    A[bad] = np.eye(3)
    b[bad] = 0.0
    # Degenerate spans (all edges at one instant) give a singular system: regularise lightly.
    A = A + np.eye(3) * 1e-12
    coef = np.linalg.solve(A, b[..., None])[..., 0]
    om_fit = coef[:, 1] / span
    # Uncertainty: residual scatter, floored by the time-stamp jitter, through (AᵀA)⁻¹.
    resid = (p - (cols @ coef[..., None])[..., 0]) * wf
    n_par = np.where(quad, 3, 2)
    dof = np.maximum(n_fit - n_par, 1)
    s2 = (resid**2).sum(axis=1) / dof
    s2 = np.maximum(s2, (om_fit * config.timing_std_s) ** 2 + (2 * np.pi / ns * 1e-3) ** 2)
    a_inv11 = np.linalg.inv(A)[:, 1, 1]
    std_fit = np.sqrt(s2 * np.maximum(a_inv11, 0.0)) / span

    omega = np.where(fit_ok, om_fit, np.nan)
    std = np.where(fit_ok, std_fit, np.nan)
    method = np.where(fit_ok, np.int8(WheelSpeedMethod.PERIOD), method).astype(np.int8)

    # Frequency method when the window is crowded.
    freq = has & (n_win >= config.frequency_min_count)
    if freq.any():
        before = np.where(first_in > seg0, pos[np.maximum(first_in - 1, 0)], angle_before_rad)
        om_f = (pos[np.maximum(last, 0)] - before) / config.window_s
        omega = np.where(freq, om_f, omega)
        std = np.where(freq, 2 * np.pi / (ns * config.window_s) / math.sqrt(3.0), std)
        method = np.where(freq, np.int8(WheelSpeedMethod.FREQUENCY), method).astype(np.int8)

    # Standstill: bound by the time since the last edge, zero after the timeout.
    single = has & ~fit_ok
    last_ns = e[np.maximum(last, 0)]
    bound = stop_bound(last_ns, q, ns) * (1.0 + config.stop_bound_margin)
    # a fit overshooting a stop; no reverse without direction
    omega = np.where(~np.asarray(signed) & (omega < 0), 0.0, omega)
    sign = np.where(omega < 0, -1.0, 1.0)
    # A lone edge after a stop: at most one tooth since the edge before it.
    prev_ns = e[np.maximum(last - 1, 0)]
    lone = np.where(last - 1 >= seg0, stop_bound(prev_ns, last_ns, ns), 0.0)
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
    return WheelSpeedResult(omega, std, method.astype(np.int8))


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

    Parameters
    ----------
    config : WheelSpeedConfig
    """

    def __init__(self, config: WheelSpeedConfig) -> None:
        self.config = config
        self._stamp = np.zeros(0, dtype=np.int64)
        self._angle = np.zeros(0, dtype=np.float64)
        self._angle_before = 0.0
        self._signed = False
        self._delta = np.zeros(config.teeth_per_rev)
        self._cal_from = 0  # index (in the held arrays) of the next edge to calibrate on
        self._cal_upto = np.iinfo(np.int64).min  # last calibration instant
        self.calibrated_edges = 0
        """Edges the tooth calibration has learnt from."""
        self.skipped = 0
        """Edges dropped because they went back in time."""

    @property
    def last_edge_ns(self) -> int | None:
        """Time of the newest edge held, or None."""
        return int(self._stamp[-1]) if self._stamp.size else None

    @property
    def tooth_correction_rad(self) -> FloatArray:
        """Learnt angle correction of each tooth, shape ``(teeth_per_rev,)``, zero mean."""
        return self._delta.copy()

    def push(self, stamp_ns: IntArray, direction: npt.NDArray[np.int8] | None = None) -> None:
        """Append edges (non-decreasing stamps; earlier-than-held ones are skipped and counted)."""
        t = np.asarray(stamp_ns, dtype=np.int64)
        if t.size == 0:
            return
        d = None if direction is None else np.asarray(direction)
        self._signed |= d is not None
        floor = self._stamp[-1] if self._stamp.size else np.iinfo(np.int64).min
        ok = t >= floor
        if t.size > 1:
            ok[1:] &= t[1:] >= t[:-1]
        if not ok.all():
            self.skipped += int((~ok).sum())
            t = t[ok]
            d = None if d is None else d[ok]
        start = float(self._angle[-1]) if self._angle.size else self._angle_before
        ang = edge_angles(t.size, self.config.teeth_per_rev, d, start)
        self._stamp = np.concatenate([self._stamp, t])
        self._angle = np.concatenate([self._angle, ang])

    def _tooth(self, angle: FloatArray) -> npt.NDArray[np.int64]:
        ns = self.config.teeth_per_rev
        return np.mod(np.rint(angle * ns / (2 * np.pi)).astype(np.int64), ns)

    def _corrected(self) -> FloatArray:
        if not self.config.tooth_calibration:
            return self._angle
        return self._angle + self._delta[self._tooth(self._angle)]

    def query(self, query_ns: IntArray) -> WheelSpeedResult:
        """Speed at each time in ``query_ns`` (shape ``(m,)``, non-decreasing); trims history.

        The tooth corrections in force at time ``t`` are those learnt from the edges up to the
        last multiple of ``calibration_period_s`` at or before ``t``, so results do not depend
        on how queries are batched.
        """
        q = np.asarray(query_ns, dtype=np.int64)
        cfg = self.config
        if not cfg.tooth_calibration or q.size == 0:
            res = omega_at(
                self._stamp, self._corrected(), q, cfg, self._angle_before, signed=self._signed
            )
        else:
            period = round(cfg.calibration_period_s * 1e9)
            parts = []
            i = 0
            while i < q.size:
                boundary = (int(q[i]) // period) * period
                if boundary > self._cal_upto:
                    self._calibrate(boundary)
                    self._cal_upto = boundary
                j = int(np.searchsorted(q, boundary + period, side="left"))
                parts.append(
                    omega_at(
                        self._stamp,
                        self._corrected(),
                        q[i:j],
                        cfg,
                        self._angle_before,
                        signed=self._signed,
                    )
                )
                i = j
            res = WheelSpeedResult(
                np.concatenate([r.omega_radps for r in parts]),
                np.concatenate([r.std_radps for r in parts]),
                np.concatenate([r.method for r in parts]).astype(np.int8),
            )
        if q.size and self._stamp.size:
            self._trim(int(q[-1]))
        return res

    def _calibrate(self, t_ns: int) -> None:
        """Learn tooth corrections from edges with a full window of neighbours at or before t."""
        cfg = self.config
        h = cfg.calibration_half_window
        last = int(np.searchsorted(self._stamp, t_ns, side="right")) - 1
        lo = max(self._cal_from, h)
        hi = last - h  # inclusive
        if hi < lo:
            return
        c = np.arange(lo, hi + 1)
        self._cal_from = hi + 1
        offs = np.arange(-h, h + 1)
        idx = c[:, None] + offs[None, :]
        ts = (self._stamp[idx] - self._stamp[c][:, None]).astype(np.float64) * _NS
        ang = self._corrected()
        a = ang[idx] - ang[c][:, None]
        span = ts[:, -1] - ts[:, 0]
        gaps = np.diff(ts, axis=1)
        ok = (span > 0) & (gaps.max(axis=1) < cfg.stop_timeout_s)
        if self._signed:
            steps = np.diff(self._angle[idx], axis=1)
            ok &= np.all(steps > 0, axis=1) | np.all(steps < 0, axis=1)
        if not ok.any():
            return
        ts, a, c, span = ts[ok], a[ok], c[ok], span[ok]
        u = ts / span[:, None]
        # fit with the centre edge left out: its own error must not pull the fit
        w = np.ones_like(u)
        w[:, h] = 0.0
        cols = np.stack([np.ones_like(u), u, u * u], axis=-1) * w[..., None]
        A = np.einsum("mki,mkj->mij", cols, cols) + np.eye(3) * 1e-12
        b = np.einsum("mki,mk->mi", cols, a)
        coef = np.linalg.solve(A, b[..., None])[..., 0]
        resid = -coef[:, 0]  # centre angle (0 by construction) minus the fit at the centre
        pitch = 2 * np.pi / cfg.teeth_per_rev
        good = np.abs(resid) < 0.3 * pitch
        teeth = self._tooth(self._angle[c[good]])
        np.add.at(self._delta, teeth, -cfg.calibration_gain * resid[good])
        self._delta -= self._delta.mean()
        self.calibrated_edges += int(good.sum())

    def _trim(self, t_ns: int) -> None:
        cfg = self.config
        last = int(np.searchsorted(self._stamp, t_ns, side="right")) - 1
        old = int(np.searchsorted(self._stamp, t_ns - round(cfg.window_s * 1e9), side="right")) - 1
        keep_from = max(0, min(last - cfg.max_edges - 1, old - 1))
        if cfg.tooth_calibration:
            keep_from = min(keep_from, max(self._cal_from - cfg.calibration_half_window - 1, 0))
        if keep_from > 0:
            self._angle_before = float(self._angle[keep_from - 1])
            self._stamp = self._stamp[keep_from:]
            self._angle = self._angle[keep_from:]
            self._cal_from -= keep_from


_SEGMENT_NS = 1 << 41
"""Spacing of trackers on the shared time axis of :func:`query_many` (about 37 minutes)."""
_HISTORY_NS = 1 << 40
"""Edges older than this before the first query are clamped (they only say "stopped")."""


def query_many(trackers: list[WheelTracker], query_ns: IntArray) -> list[WheelSpeedResult]:
    """:meth:`WheelTracker.query` of several trackers at the same times, in one vectorised fit.

    Equivalent to querying each tracker on its own (the fit of each query sees only its own
    tracker's edges: trackers are laid out on one time axis, far apart); saves the per-call
    overhead when a fleet front end asks many wheels at once.

    Parameters
    ----------
    trackers : list of WheelTracker
    query_ns : ndarray, shape (m,), int64, non-decreasing

    Returns
    -------
    list of WheelSpeedResult, one per tracker, arrays of shape (m,)
    """
    q = np.asarray(query_ns, dtype=np.int64)
    if not trackers:
        return []
    cfg = trackers[0].config
    if q.size == 0 or any(t.config != cfg for t in trackers):
        return [t.query(q) for t in trackers]
    period = round(cfg.calibration_period_s * 1e9)
    parts: list[list[WheelSpeedResult]] = [[] for _ in trackers]
    i = 0
    while i < q.size:
        if cfg.tooth_calibration:
            boundary = (int(q[i]) // period) * period
            for t in trackers:
                if boundary > t._cal_upto:
                    t._calibrate(boundary)
                    t._cal_upto = boundary
            j = int(np.searchsorted(q, boundary + period, side="left"))
        else:
            j = q.size
        qs = q[i:j]
        base = int(qs[0]) - _HISTORY_NS
        stamps, angles, queries, before, signed, seg = [], [], [], [], [], []
        n_held = 0
        for k, t in enumerate(trackers):
            off = k * _SEGMENT_NS
            seg.append(np.full(qs.size, n_held, dtype=np.int64))
            n_held += t._stamp.size
            stamps.append(np.maximum(t._stamp - base, 0) + off)
            angles.append(t._corrected())
            queries.append(qs - base + off)
            before.append(np.full(qs.size, t._angle_before))
            signed.append(np.full(qs.size, t._signed))
        res = omega_at(
            np.concatenate(stamps),
            np.concatenate(angles),
            np.concatenate(queries),
            cfg,
            np.concatenate(before),
            signed=np.concatenate(signed),
            segment_start=np.concatenate(seg),
        )
        n = qs.size
        for k in range(len(trackers)):
            sl = slice(k * n, (k + 1) * n)
            parts[k].append(
                WheelSpeedResult(res.omega_radps[sl], res.std_radps[sl], res.method[sl])
            )
        i = j
    out = []
    for k, t in enumerate(trackers):
        out.append(
            WheelSpeedResult(
                np.concatenate([r.omega_radps for r in parts[k]]),
                np.concatenate([r.std_radps for r in parts[k]]),
                np.concatenate([r.method for r in parts[k]]).astype(np.int8),
            )
        )
        if t._stamp.size:
            t._trim(int(q[-1]))
    return out


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
