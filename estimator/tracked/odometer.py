"""Odometer correction and side-slip per motion state (``method.md`` §4, source 002 §2-3).

The transmission odometer reads the gearbox output, the fast track's sprocket speed ``v_o``.

Paper (as printed): low straight ``v_y = v_o/1.42`` (Eq. 7, with the issue's reading of the
ratio), arc ``v_y = 0.8688·v_o`` (Eq. 20), separated ``v_y = ρ/(ρ + B/2)·v_o`` (Eq. 23),
straight ``v_y = v_o``; none in pivots and large heading changes; lateral ``v_x = −φ̇·L``
(Eq. 17) in arcs and separated turns. Eq. 17 points toward the turn centre and is several
times the true side-slip: the turning pole moves ahead of the centre and the hull slides
*outward*, ``v_x = φ̇·D`` with ``D = L·|a_y|/(2·μ_t·g)`` (at most ``L/2``).

Product: the fast track's ground speed is ``V + |ω|·B/2`` in every turn (the kinematic identity
Eq. 23 rests on, slip included), and it is ``F_s·v_o`` with a factor ``F_s`` per state learned
while GNSS is good (``K_D`` scale and that state's traction slip together), less the hull's
lag ``τ·a`` behind its tracks while it accelerates, and times ``1 − κ·a``: the traction
force that accelerates the hull adds slip in proportion (``τ`` and ``κ`` learned too, from
the accelerations beside GNSS; ``κ·a`` costs ``κ·a·V``, which grows with speed where the
lag ``τ·a`` does not); in a low-gear
straight ``V = F_low·v_o/1.42`` with ``F_low = F_straight + δ_low`` (same ``K_D``, same
ground: only the traction differs, so a low gear first met in an outage starts from what the
straights taught, not from 1), and in a pivot likewise ``F_pivot = F_straight + δ_pivot``
(``δ_pivot`` starting at minus the driven track's typical pivot slip). In an arc or a
separated turn the fast track slips more the tighter the turn (its thrust makes the
steering moment, whichever lever slows the other track): ``F_turn = F_straight − c·θ`` with
the tightness ``θ = B/ρ_t = 2(1 − q)/(1 + q)`` from the sprocket ratio ``q`` and the turn
slip per unit tightness ``c`` learned from a prior; every arc and separated turn beside
GNSS teaches ``c`` whatever its ``q``, and a turn first met in an outage starts from what
the straights taught. The odometer's
windowed speed is compared with the filter's speed at the window's centre ``V − a·lag``,
not at the tick (Eq. 6's mismatch). Every factor is the ground's mean plus the patch of
ground under the tracks, ``p`` (:class:`~estimator.tracked.model.TrackedState`).
"""

from __future__ import annotations

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.tracked.model import N_STATES, MotionState, TrackedMode
from estimator.tracked.model import TrackedState as S
from estimator.tracked.params import VehicleParams
from estimator.tracked.recognise import turn_radius_m
from estimator.tracked.settings import TrackedEstimatorConfig

__all__ = [
    "FACTOR_OF",
    "lateral_speed",
    "odometer_measurement",
    "paper_ratio",
    "side_creep",
    "turn_tightness",
]

GRAVITY_MPS2 = 9.80665
M = MotionState

#: Filter state holding each motion state's odometer factor, or its offset or turn slip
#: from the straight's (product mode).
FACTOR_OF = {
    M.STRAIGHT: S.F_STRAIGHT,
    M.LOW_STRAIGHT: S.F_LOW,
    M.ARC: S.TURN_SLIP,
    M.SEPARATED: S.TURN_SLIP,
    M.PIVOT: S.F_PIVOT,
}
_FACTOR_INDEX = np.full(len(M), int(S.F_STRAIGHT), dtype=np.int64)
for _state, _index in FACTOR_OF.items():
    _FACTOR_INDEX[int(_state)] = int(_index)
#: States whose factor is held as an offset from ``F_STRAIGHT`` (same ``K_D``, same ground).
_OFFSET = np.zeros(len(M), dtype=bool)
_OFFSET[[int(M.LOW_STRAIGHT), int(M.PIVOT), int(M.ARC), int(M.SEPARATED)]] = True
#: States whose factor is ``F_STRAIGHT − c·θ`` (``c`` the turn slip, ``θ`` the tightness).
_BY_TIGHTNESS = np.zeros(len(M), dtype=bool)
_BY_TIGHTNESS[[int(M.ARC), int(M.SEPARATED)]] = True
_TURNING = np.zeros(len(M), dtype=bool)
_TURNING[[int(M.ARC), int(M.SEPARATED), int(M.PIVOT)]] = True


def lateral_speed(
    mode: TrackedMode,
    state: IntArray,
    speed_mps: FloatArray,
    yaw_rate_radps: FloatArray,
    contact_length_m: FloatArray,
    lateral_resistance: FloatArray,
) -> FloatArray:
    """The hull centre's lateral speed (right +), shape ``(k,)``, as ``mode`` models it."""
    if mode == TrackedMode.PAPER:
        turning = (state == int(M.ARC)) | (state == int(M.SEPARATED))
        return np.where(turning, -yaw_rate_radps * contact_length_m, 0.0)
    if mode != TrackedMode.PRODUCT:
        return np.zeros_like(speed_mps)
    lateral, _ = side_slip(speed_mps, yaw_rate_radps, contact_length_m, lateral_resistance)
    return lateral


def side_slip(
    speed_mps: FloatArray,
    yaw_rate_radps: FloatArray,
    contact_length_m: FloatArray,
    lateral_resistance: FloatArray,
    gain: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """The product's lateral speed ``v_x = ω·D`` and its derivative by ``gain``, each ``(k,)``:
    the turning pole ``D = min(g_s·L·|V·ω|/(2·μ_t·g), L/2)`` ahead of the centre, ``g_s``
    (``gain``, 1 if None) the ground's side-slip over what the configured ``μ_t`` gives."""
    g_s = np.ones_like(speed_mps) if gain is None else gain
    free = contact_length_m * np.abs(speed_mps * yaw_rate_radps)
    free = free / (2.0 * lateral_resistance * GRAVITY_MPS2)
    capped = g_s * free >= 0.5 * contact_length_m
    pole = np.where(capped, 0.5 * contact_length_m, g_s * free)
    return yaw_rate_radps * pole, np.where(capped, 0.0, yaw_rate_radps * free)


def side_creep(
    speed_mps: FloatArray,
    roll_rad: FloatArray,
    roll_band_rad: FloatArray,
    lateral_resistance: FloatArray,
    creep: float,
    gain: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The hull's creep downhill on a side slope and its derivatives by the side-slip gain
    and by the roll, each ``(k,)``: gravity's cross component ``g·sin φ`` against the
    ground's lateral resistance ``μ_t·g`` sets the tracks' slip angle
    ``β = k_c·sin φ/μ_t`` (``creep`` ``k_c``), so the hull moves right (downhill, ``φ``
    right side down +) at ``v_c = g_s·k_c·|V|·sin φ_e/μ_t``. ``g_s`` (``gain``) is the
    ground's side-slip over what the configured ``μ_t`` gives, the same ground as the
    turns'. ``φ_e = sign φ·max(|φ| − b, 0)`` is the roll beyond the band ``b``
    (``roll_band_rad``) that the roll's uncertainty spans: within it the roll cannot be told
    from the lateral accelerometer's bias, and the creep and its derivatives are 0."""
    beyond = np.maximum(np.abs(roll_rad) - roll_band_rad, 0.0)
    phi_e = np.sign(roll_rad) * beyond
    per_gain = creep * np.abs(speed_mps) * np.sin(phi_e) / lateral_resistance
    by_roll = np.where(beyond > 0.0, gain * creep * np.abs(speed_mps) * np.cos(phi_e), 0.0)
    return gain * per_gain, per_gain, by_roll / lateral_resistance


def turn_tightness(sprocket_mps: FloatArray) -> FloatArray:
    """``θ = B/ρ_t = 2(1 − q)/(1 + q)`` ``(k,)`` from the sprocket speeds ``(k, 2)``, ``q`` the
    slow over the fast one (the kinematic turning radius ``ρ_t`` of the sprockets; 0 where
    neither turns)."""
    fast = sprocket_mps.max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(fast > 0.0, sprocket_mps.min(axis=1) / fast, 1.0)
    q = np.clip(np.nan_to_num(q, nan=1.0), 0.0, 1.0)
    return 2.0 * (1.0 - q) / (1.0 + q)


def paper_ratio(state: IntArray, rho_m: FloatArray, p: VehicleParams) -> FloatArray:
    """``v_y / v_o`` of the paper per state (NaN where it gives none): Eq. 7, 20, 23."""
    ratio = np.full(state.shape, np.nan)
    ratio[state == int(M.STRAIGHT)] = 1.0
    ratio[state == int(M.STOP)] = 1.0
    low = state == int(M.LOW_STRAIGHT)
    ratio[low] = 1.0 / p.low_gear_ratio[low]
    arc = state == int(M.ARC)
    ratio[arc] = p.arc_ratio[arc]
    sep = state == int(M.SEPARATED)
    with np.errstate(invalid="ignore"):
        ratio[sep] = (rho_m / (rho_m + 0.5 * p.gauge_m))[sep]
    return ratio


def odometer_measurement(
    cfg: TrackedEstimatorConfig,
    p: VehicleParams,
    x: FloatArray,
    state: IntArray,
    odometer_mps: FloatArray,
    lag_s: FloatArray,
    accel_mps2: FloatArray,
    yaw_rate_radps: FloatArray,
    valid: BoolArray,
    tightness: FloatArray | None = None,
    pull_mps2: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray, FloatArray]:
    """``(innovation (k, 1), H (k, 1, n), R (k, 1, 1), mask (k,), corrected V (k,))``.

    ``corrected V`` is the forward speed the odometer gives in this state (NaN where none);
    ``tightness`` ``(k,)`` is a turn's ``θ`` (:func:`turn_tightness`, 0 if None).
    ``accel_mps2`` is the hull's own acceleration (gravity out): the hull's lag, the window's
    carry and the odometer's std read it; ``pull_mps2`` the drawbar demand per unit mass,
    ``a + g·sin θ`` (the accelerometer's forward specific force; ``accel_mps2`` if None):
    the traction slip reads it (a grade loads the tracks as an acceleration does).
    """
    pull = accel_mps2 if pull_mps2 is None else pull_mps2
    k = x.shape[0]
    H = np.zeros((k, 1, N_STATES))
    v = x[:, S.SPEED]
    std = cfg.odometer_std_mps + cfg.odometer_std_per_mps * np.abs(odometer_mps)
    std = std + cfg.odometer_std_per_mps2 * np.abs(accel_mps2)  # slip while the hull catches up
    if cfg.mode == TrackedMode.PRODUCT:
        theta = np.zeros(k) if tightness is None else tightness
        motion = (lag_s, accel_mps2, yaw_rate_radps, pull)
        h, corrected = _product_row(p, x, state, H, odometer_mps, motion, theta)
        mask = valid & (state != int(M.HEADING_JUMP)) & (state != int(M.STOP))
        std = _pivot_std(cfg, state, odometer_mps, accel_mps2, std)
        innovation = odometer_mps - h
    else:
        corrected = _paper_ratio(cfg, p, state, v, yaw_rate_radps) * odometer_mps
        H[:, 0, S.SPEED] = 1.0
        mask = valid & np.isfinite(corrected)
        innovation = corrected - v
    R = (std**2)[:, None, None]
    innovation = np.where(mask, innovation, 0.0)[:, None]
    return innovation, H, R, mask, np.where(mask, corrected, np.nan)


def _product_row(
    p: VehicleParams,
    x: FloatArray,
    state: IntArray,
    H: FloatArray,
    odometer_mps: FloatArray,
    motion: tuple[FloatArray, FloatArray, FloatArray, FloatArray],
    theta: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Product mode's predicted odometer ``h = gear·(V − a·lag_s + c_lag·a + turn) /
    (F·(1 − c_slip·pull))`` ``(k,)``, its row of ``H`` ``(k, 1, n)`` (filled in place), and
    the odometer's corrected forward speed ``(k,)``; ``motion`` is ``(lag_s, accel_mps2,
    yaw_rate_radps, pull)``, each ``(k,)``, ``theta`` the turn's tightness ``(k,)``."""
    lag_s, accel_mps2, yaw_rate_radps, pull = motion
    track = _track_factor(x, state, theta)
    factor = track[3]
    gear = np.where(state == int(M.LOW_STRAIGHT), p.low_gear_ratio, 1.0)
    turn = np.where(_TURNING[state], 0.5 * p.gauge_m * np.abs(yaw_rate_radps), 0.0)
    lag = x[:, S.ACCEL_LAG] * accel_mps2
    traction = 1.0 - x[:, S.ACCEL_SLIP] * pull
    ground = x[:, S.SPEED] - accel_mps2 * lag_s + lag + turn
    h = gear * ground / (factor * traction)
    _product_jacobian(H, track, h, (gear, traction), accel_mps2, pull)
    corrected = odometer_mps * factor * traction / gear - turn - lag
    return h, corrected


def _track_factor(
    x: FloatArray, state: IntArray, theta: FloatArray
) -> tuple[IntArray, BoolArray, FloatArray, FloatArray]:
    """The state's track factor ``F`` ``(k,)`` from ``x`` ``(k, n)``, with the index of the
    factor state it reads, whether ``F_straight`` is added, and the factor's scale (``−θ`` in
    a turn read by tightness, else 1), each ``(k,)``: ``(f_idx, offset, scale, F)``."""
    f_idx = _FACTOR_INDEX[state]
    rows = np.arange(x.shape[0])
    offset = _OFFSET[state]
    scale = np.where(_BY_TIGHTNESS[state], -theta, 1.0)  # F_turn = F_straight − c·θ
    patch = x[:, S.GROUND_PATCH]
    factor = x[rows, f_idx] * scale + np.where(offset, x[:, S.F_STRAIGHT], 0.0) + patch
    return f_idx, offset, scale, factor


def _product_jacobian(
    H: FloatArray,
    track: tuple[IntArray, BoolArray, FloatArray, FloatArray],
    h: FloatArray,
    drive: tuple[FloatArray, FloatArray],
    accel_mps2: FloatArray,
    pull: FloatArray,
) -> None:
    """``∂h/∂x`` of :func:`_product_row` into ``H`` ``(k, 1, n)`` in place; ``track`` is
    :func:`_track_factor`'s, ``drive`` ``(gear, traction)``, each ``(k,)``."""
    f_idx, offset, scale, factor = track
    gear, traction = drive
    H[:, 0, S.SPEED] = gear / (factor * traction)
    H[:, 0, S.ACCEL_LAG] = gear * accel_mps2 / (factor * traction)
    H[:, 0, S.ACCEL_SLIP] = h * pull / traction
    H[np.arange(H.shape[0]), 0, f_idx] = -h / factor * scale
    H[:, 0, S.F_STRAIGHT] += np.where(offset, -h / factor, 0.0)
    H[:, 0, S.GROUND_PATCH] = -h / factor


def _pivot_std(
    cfg: TrackedEstimatorConfig,
    state: IntArray,
    odometer_mps: FloatArray,
    accel_mps2: FloatArray,
    std: FloatArray,
) -> FloatArray:
    """The odometer's 1-sigma ``(k,)``: ``std`` but in a pivot, where it grows with speed by
    ``pivot_odometer_std_per_mps`` instead."""
    pivot_std = cfg.odometer_std_mps + cfg.pivot_odometer_std_per_mps * np.abs(odometer_mps)
    return np.where(
        state == int(M.PIVOT), pivot_std + cfg.odometer_std_per_mps2 * np.abs(accel_mps2), std
    )


def _paper_ratio(
    cfg: TrackedEstimatorConfig,
    p: VehicleParams,
    state: IntArray,
    v: FloatArray,
    yaw_rate_radps: FloatArray,
) -> FloatArray:
    """The paper modes' odometer-to-hull speed ratio ``(k,)``: 1 for the raw odometer, else
    :func:`paper_ratio` at the turn radius of ``v`` and ``yaw_rate_radps``."""
    if cfg.mode == TrackedMode.RAW_ODOMETER:
        return np.ones(v.shape[0])
    return paper_ratio(state, turn_radius_m(v, yaw_rate_radps), p)
