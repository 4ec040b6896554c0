"""What a GNSS clock offset moves a fix's speed and the RTK distance by, per vehicle slot.

A fix stamped ``t_s`` describes the antenna at ``t_s − δ`` (``δ`` the GNSS clock offset,
:class:`~estimator.mdsf.calibration.CalibrationBank`); the front end has moved it to the
tick as if it described ``t_s``. :class:`GnssClockShift` keeps the body rates of the last
ticks and the filter's speed rate at ``O`` per slot and turns them into that shift; the
vehicle's geometry (heights and lateral offsets of the IMU and the antenna) is read from the
front end's slot arrays (:class:`SlotGeometry`), not kept here.

Per tick the fleet calls, in order: :meth:`GnssClockShift.record_rates` (the tick's rates),
:meth:`GnssClockShift.fix_rates` (the rates at the fix's instants, interpolation weights
computed once for all slots), :meth:`GnssClockShift.record_sway` (the running powers of the
sway part), then the pure :meth:`GnssClockShift.shift_mps` and
:meth:`GnssClockShift.mast_shift_m`, and after the filter's step
:meth:`GnssClockShift.record_speed`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator._slots import grow_slot_array
from estimator.mdsf.model import MdsfConfig

__all__ = ["FixRates", "GnssClockShift", "SlotGeometry"]

_SHIFT_TICKS = 5
"""Ticks of body rates :class:`GnssClockShift` keeps (the newest and four before it: a GNSS
offset of up to ±0.1 s and a fix up to a tick before its tick stay inside)."""
_AXLE_RATE_TAU_S = 0.3
"""Time constant of the low-pass on the filter's speed rate at ``O`` [s]."""
_LEVER_POWER_TAU_S = 5.0
"""Time constant of the running powers of the shift's sway part and of its noise, whose
ratio sets how much of that part is applied (:meth:`GnssClockShift.shift_mps`) [s]."""

_SLOPE_AT_NEWEST = np.array([-11.0, 18.0, -9.0, 2.0]) / 6.0
"""Slope of the cubic through the newest four ticks at the newest, per tick back (nodes
newest first); it grows towards the past, so a tick ahead is minus it."""
_BEND_AT_NEWEST = np.array([2.0, -5.0, 4.0, -1.0])
"""Second difference of the cubic through the newest four ticks at the newest, per tick²."""
_SLOT_ARRAYS: tuple[tuple[str, tuple[int, ...], object], ...] = (
    ("rates", (_SHIFT_TICKS, 2), np.nan),
    ("rate_var", (_SHIFT_TICKS,), 0.0),
    ("stamp_ns", (), np.int64(0)),
    ("v0_prev", (), np.nan),
    ("a0", (), 0.0),
    ("lever_power", (), 0.0),
    ("noise_power", (), 0.0),
)
""":class:`GnssClockShift`'s slot arrays: name, shape per slot and a fresh slot's value."""


class SlotGeometry(Protocol):
    """Per-slot geometry arrays (slots,) [m] the shift reads (the MDSF front end holds them,
    :class:`~estimator.mdsf.frontend.FleetFrontEnd`)."""

    imu_up_m: FloatArray  # the IMU's height over O, h0
    h1_m: FloatArray  # the antenna's height over the IMU, h1
    ant_lat_m: FloatArray  # the antenna's lateral offset from O, x_a
    imu_lat_m: FloatArray  # the IMU's lateral offset from O, x_i


def _cubic_weights(u: FloatArray) -> FloatArray:
    """Lagrange weights (k, 4) of the nodes 0, 1, 2, 3 at ``u`` (k,) (in node spacings)."""
    u1, u2, u3 = u - 1.0, u - 2.0, u - 3.0
    return np.stack(
        [-u1 * u2 * u3 / 6.0, u * u2 * u3 / 2.0, -u * u1 * u3 / 2.0, u * u1 * u2 / 6.0], axis=1
    )


def _node_weights(u: FloatArray) -> FloatArray:
    """Weights (k, _SHIFT_TICKS) of the kept ticks (newest first) that give the rates ``u``
    (k,) ticks before the newest: within the history the cubic through the four ticks
    around ``u``; ahead of the newest (``u < 0``) the newest plus ``u`` times the cubic's
    slope there (:data:`_SLOPE_AT_NEWEST`). Rows are placed by slices: most ``u`` lie within
    the newest tick, whose cubic starts at the newest node, and none ahead of it."""
    u = np.clip(u, None, _SHIFT_TICKS - 1.0)
    first = np.clip(np.floor(u) - 1.0, 0.0, _SHIFT_TICKS - 4.0)
    cubic = _cubic_weights(np.maximum(u, 0.0) - first)
    w = np.zeros((u.shape[0], _SHIFT_TICKS))
    w[:, :4] = cubic
    for start in range(1, _SHIFT_TICKS - 3):
        rows = np.flatnonzero(first == start)
        if rows.shape[0]:
            block = np.zeros((rows.shape[0], _SHIFT_TICKS))
            block[:, start : start + 4] = cubic[rows]
            w[rows] = block
    ahead = np.flatnonzero(u < 0.0)
    if ahead.shape[0]:
        line = np.zeros((ahead.shape[0], _SHIFT_TICKS))
        line[:, :4] = u[ahead, None] * _SLOPE_AT_NEWEST[None, :]
        line[:, 0] += 1.0
        w[ahead] = line
    return w


def _rates_at(w: FloatArray, nodes: FloatArray, holes: BoolArray | None) -> FloatArray:
    """Body rates (k, 2) from node weights ``w`` (k, _SHIFT_TICKS) and the kept rates
    ``nodes`` (k, _SHIFT_TICKS, 2; NaN as 0), NaN where a node it weighs is a hole
    (``holes``, same shape: no IMU at that tick; None: there are none). The cubic's error
    within the history is neglected (~5 % of a 2 Hz sway's amplitude)."""
    values = np.einsum("kj,kjc->kc", w, nodes)
    if holes is None:
        return values
    missing = ((w != 0.0)[:, :, None] & holes).any(axis=1)
    return np.where(missing, np.nan, values)


@dataclass(slots=True)
class FixRates:
    """A tick's body rates at the instants its fixes describe, for slots (k,).

    ``age_s`` the fix's age before the newest tick (clipped to ``[0, dt]``) and ``offset_s``
    the applied offset ``δ``, (k,); ``nodes`` the kept rates ``[ωx, ωz]`` newest first
    (k, _SHIFT_TICKS, 2); the rates ``[ωx, ωz]`` (k, 2) at the fix (``at_fix``, ``age_s``
    back), at the instant it describes (``was``, ``age_s + δ``) and midway (``mid``,
    ``age_s + δ/2``); the sway part ``ΔL`` (k,), its noise ``N`` (k,) and the antenna's
    height ``h0 + h1`` and lateral offset ``x_a`` (k,) they were taken with.
    """

    age_s: FloatArray
    offset_s: FloatArray
    nodes: FloatArray
    at_fix: FloatArray
    was: FloatArray
    mid: FloatArray
    lever_mps: FloatArray
    noise_var: FloatArray
    up_m: FloatArray
    lat_m: FloatArray


class GnssClockShift:
    """What a GNSS clock offset ``δ`` moves a fix's speed by, per vehicle slot.

    A fix stamped ``t_s`` describes the antenna at ``t_s − δ``; the front end has moved it to
    the tick as if it described ``t_s``. The antenna's forward speed is
    ``V_a = V0 + x_a·ωz − (h0 + h1)·ωx`` (``O`` the rear axle's ground point, the antenna at
    lateral ``x_a`` and height ``h0 + h1``), so the fix is short of the speed at ``t_s`` by

        ``ΔV_a = δ·ā0 + g·ΔL``,
        ``ΔL = x_a·(ωz(t_s) − ωz(t_s − δ)) − (h0 + h1)·(ωx(t_s) − ωx(t_s − δ))``

    with ``ā0`` the rate of the filter's own speed at ``O`` (GNSS-anchored, low-passed: the
    axle does not sway) and the body rates of the last ticks interpolated (cubic, on the
    tick grid) at both instants: a swaying cab's mast moves the antenna by metres per second
    within ``δ`` where the IMU's acceleration, at another height, says otherwise. ``ΔL``
    carries the tick rates' noise through the interpolation, ``N = (h²+x_a²)·Σ_j Δw_j²·σ_j²``
    (``Δw`` the two instants' node weights; ahead of the newest tick the slope's weights
    amplify it ~3×): ``g = 1 − N̄/M̄`` (running means of ``N`` and ``ΔL²``, at least 0) applies
    as much of ``ΔL`` as stands above its noise (a Wiener gain), so a slow sway on a tall
    mast at a crawl is not corrected by noise larger than itself.
    """

    def __init__(self, config: MdsfConfig) -> None:
        self.dt_s = config.dt_s
        self.tick_ns = config.tick_ns
        self.alpha = config.dt_s / (_AXLE_RATE_TAU_S + config.dt_s)
        self.beta = config.dt_s / (_LEVER_POWER_TAU_S + config.dt_s)
        cap = 0
        self.rates = np.zeros((cap, _SHIFT_TICKS, 2))  # ωx, ωz of the newest ticks first
        self.rate_var = np.zeros((cap, _SHIFT_TICKS))  # each tick's rate variance [rad²/s²]
        self.stamp_ns = np.zeros(cap, dtype=np.int64)  # the newest tick's stamp
        self.v0_prev = np.zeros(cap)  # the last emitted tick's speed at O [m/s] (NaN: none)
        self.a0 = np.zeros(cap)  # its low-passed rate [m/s²]
        self.lever_power = np.zeros(cap)  # running mean of ΔL² [m²/s²]
        self.noise_power = np.zeros(cap)  # running mean of N [m²/s²]

    def add(self, slot: int) -> None:
        """Start ``slot`` with no history."""
        if slot >= self.stamp_ns.shape[0]:
            cap = max(2 * self.stamp_ns.shape[0], slot + 1)
            for name, shape, fill in _SLOT_ARRAYS:
                grow_slot_array(self, name, cap, shape, fill)
        for name, _, fill in _SLOT_ARRAYS:
            getattr(self, name)[slot] = fill

    # -- state updates of a tick -------------------------------------------------------------
    def record_rates(
        self,
        slots: IntArray,
        stamp_ns: IntArray,
        rates_radps: FloatArray,
        rate_var: FloatArray | None = None,
    ) -> None:
        """A tick's body rates ``[ωx, ωz]`` (k, 2; NaN: no IMU) and their noise variance
        (k,; None: noiseless) become the newest; a tick that does not follow the last one on
        the grid starts the history anew."""
        var = np.zeros(slots.shape[0]) if rate_var is None else np.nan_to_num(rate_var)
        broken = np.flatnonzero((stamp_ns - self.stamp_ns[slots]) != self.tick_ns)
        for kept, newest in ((self.rates, rates_radps), (self.rate_var, var)):
            old = kept[slots]
            new = np.empty_like(old)
            new[:, 0] = newest
            new[:, 1:] = old[:, :-1]
            kept[slots] = new
        self.rates[slots[broken], 1:] = np.nan
        self.stamp_ns[slots] = stamp_ns

    def record_sway(self, slots: IntArray, fix: FixRates) -> None:
        """Step the running powers of the tick's ``ΔL`` and its noise ``N`` (``fix``) where
        both are known: ``M̄ ← M̄ + β·(ΔL² − M̄)``, ``N̄ ← N̄ + β·(N − N̄)``."""
        lever, noise = fix.lever_mps, fix.noise_var
        known = np.isfinite(lever) & np.isfinite(noise)
        m, n = self.lever_power[slots], self.noise_power[slots]
        m = np.where(known, m + self.beta * (np.nan_to_num(lever) ** 2 - m), m)
        n = np.where(known, n + self.beta * (np.nan_to_num(noise) - n), n)
        self.lever_power[slots], self.noise_power[slots] = m, n

    def record_speed(self, slots: IntArray, v0_mps: FloatArray, emit: BoolArray) -> None:
        """The filter's speed at ``O`` after a tick (k,): its rate, low-passed,
        ``ā0 ← ā0 + α·((V0 − V0_prev)/dt − ā0)``; kept through ticks without a row."""
        ok = emit & np.isfinite(v0_mps)
        rate = (v0_mps - self.v0_prev[slots]) / self.dt_s
        a0 = self.a0[slots]
        step = ok & np.isfinite(rate)
        self.a0[slots] = np.where(step, a0 + self.alpha * (rate - a0), a0)
        self.v0_prev[slots] = np.where(ok, v0_mps, np.nan)

    # -- pure reads --------------------------------------------------------------------------
    def fix_rates(
        self, slots: IntArray, offset_s: FloatArray, age_s: FloatArray, geometry: SlotGeometry
    ) -> FixRates:
        """The rates at the instants of fixes ``age_s`` (k,; NaN or inf: at the tick) before
        the newest tick under the offset ``offset_s`` (k,), with the sway part ``ΔL`` and its
        noise ``N`` (class docstring). The node weights (:func:`_node_weights`) of all three
        instants come from one call; a slot without offset has all three at the fix, taken
        once."""
        age = np.clip(np.nan_to_num(age_s, nan=0.0, posinf=0.0), 0.0, self.dt_s)
        moved = np.flatnonzero(offset_s != 0.0)
        k, j = age.shape[0], moved.shape[0]
        off = offset_s[moved]
        u = np.concatenate([age, age[moved] + off, age[moved] + 0.5 * off]) / self.dt_s
        weights = _node_weights(u)
        nodes = self.rates[slots]
        holes = np.isnan(nodes)  # a history not full yet, a tick without IMU
        clean, gaps = (np.nan_to_num(nodes), holes) if holes.any() else (nodes, None)
        at_fix = _rates_at(weights[:k], clean, gaps)
        was, mid, spread = at_fix.copy(), at_fix.copy(), np.zeros(k)
        if j:
            w_fix, w_was = weights[moved], weights[k : k + j]
            some = None if gaps is None else gaps[moved]
            was[moved] = _rates_at(w_was, clean[moved], some)
            mid[moved] = _rates_at(weights[k + j :], clean[moved], some)
            var = self.rate_var[slots[moved]]
            spread[moved] = np.einsum("kj,kj->k", (w_fix - w_was) ** 2, var)
        d_wx, d_wz = (at_fix - was).T
        up = geometry.imu_up_m[slots] + geometry.h1_m[slots]
        lat = geometry.ant_lat_m[slots]
        return FixRates(
            age_s=age,
            offset_s=offset_s,
            nodes=nodes,
            at_fix=at_fix,
            was=was,
            mid=mid,
            lever_mps=lat * d_wz - up * d_wx,
            noise_var=(up * up + lat * lat) * spread,
            up_m=up,
            lat_m=lat,
        )

    def shift_mps(
        self, slots: IntArray, fix: FixRates, offset_std_s: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """``ΔV_a`` (class docstring) of the fixes of ``fix`` (after :meth:`record_sway`), and
        its error variance (k,): the offset's std ``offset_std_s`` (k,) times the antenna's
        acceleration, the rates' guess after the newest tick and what the gain leaves of
        ``ΔL`` and its noise. The rates' part 0 where they are unknown."""
        up, lat, lever = fix.up_m, fix.lat_m, fix.lever_mps
        gain, lever_var = self._lever_gain(slots, fix.noise_var)
        guess = self._guess_var(fix)
        # the antenna's acceleration at the newest tick (the slope is per tick back)
        slope = np.einsum("j,kjc->kc", _SLOPE_AT_NEWEST, fix.nodes[:, :4]) / -self.dt_s
        a0 = self.a0[slots]
        accel = a0 + lat * slope[:, 1] - up * slope[:, 0]
        var = up * up * guess[:, 0] + lat * lat * guess[:, 1] + lever_var
        var = var + (offset_std_s * accel) ** 2
        known = np.isfinite(lever) & np.isfinite(var)
        shift = fix.offset_s * a0 + np.where(known, gain * lever, 0.0)
        far = (offset_std_s * a0) ** 2
        return shift, np.where(known, var, far)

    def _lever_gain(self, slots: IntArray, noise: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The gain ``g = 1 − N̄/M̄`` (0 without power) from the running powers and the
        variance of what it leaves of a tick's ``ΔL`` of noise ``noise`` (k,),
        ``(1 − g)²·S + g²·N`` with ``S = M̄ − N̄`` the sway's own power, (k,)."""
        m, n = self.lever_power[slots], self.noise_power[slots]
        with np.errstate(invalid="ignore", divide="ignore"):
            gain = np.where(m > 0.0, np.clip(1.0 - n / m, 0.0, 1.0), 0.0)
        signal = np.maximum(m - n, 0.0)
        return gain, (1.0 - gain) ** 2 * signal + gain * gain * noise

    def _guess_var(self, fix: FixRates) -> FloatArray:
        """Variance (k, 2) of carrying the rates ``−(age + δ)`` ahead of the newest tick on
        the cubic's slope: the curvature's share ``(|ω̈|·h²/2)²`` (0 within the history)."""
        ahead = np.minimum((fix.age_s + fix.offset_s) / self.dt_s, 0.0)[:, None]
        bend = np.einsum("j,kjc->kc", _BEND_AT_NEWEST, fix.nodes[:, :4])
        return (0.5 * np.abs(bend) * ahead * ahead) ** 2

    def imu_speed_step_mps(self, slots: IntArray, geometry: SlotGeometry) -> FloatArray:
        """The IMU point's speed change over the newest tick (k,),
        ``ā0·dt + x_i·Δωz − h0·Δωx``: the filter's GNSS-anchored rate at ``O`` and the body
        rates' change between the last two ticks (0 where unknown). Summed over a chain of
        RTK positions it is ``V1(t) − V1(t0)`` without the accelerometer's bias and gravity
        leak, which ``∫a1·dt`` would carry into the distance's clock correction."""
        d_wx, d_wz = (self.rates[slots, 0] - self.rates[slots, 1]).T
        lever = geometry.imu_lat_m[slots] * d_wz - geometry.imu_up_m[slots] * d_wx
        return self.a0[slots] * self.dt_s + np.where(np.isfinite(lever), lever, 0.0)

    @staticmethod
    def mast_shift_m(
        slots: IntArray, fix: FixRates, applied: BoolArray, geometry: SlotGeometry
    ) -> FloatArray:
        """What the offset makes of the RTK distance's lever arm where ``applied`` (k,; 0
        elsewhere): the front end moves a fix's antenna position to the IMU by ``h1·θ`` with
        the pitch at the stamp ``t_s``, where the position is the antenna's at ``t_s − δ``;
        the difference is ``−h1·∫ωx`` over ``[t_s − δ, t_s]`` (Simpson's rule on the rates
        of ``fix``; 0 where they are unknown)."""
        rate = np.where(applied, fix.offset_s, 0.0)
        turned = rate * (fix.at_fix[:, 0] + fix.was[:, 0] + 4.0 * fix.mid[:, 0]) / 6.0
        return np.where(np.isfinite(turned), -geometry.h1_m[slots] * turned, 0.0)
