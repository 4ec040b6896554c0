"""The wheel-speed front end as it was before :class:`estimator.wheel_speed.WheelBank`.

Kept unchanged (one tracker = its own arrays, :func:`query_many` lays trackers on one time axis
per call) as the baseline of ``slipfleet bench wheels`` and as the oracle the bank's tests
compare with. Not used by the product.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from estimator.wheel_speed import (
    WheelSpeedConfig,
    WheelSpeedMethod,
    WheelSpeedResult,
    edge_angles,
    stop_bound,
)

__all__ = ["WheelTracker", "omega_at", "query_many"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_NS = 1e-9
_GAP_FACTOR = 3.0


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
