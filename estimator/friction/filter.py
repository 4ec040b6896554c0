"""The μ filters, batched over vehicles: the source's SCKF-MEE and its variants, and the product's.

All share the measurement model ``z = [a_x, a_y, ṙ]`` of :mod:`.model` over brush forces
(:mod:`.brush`) of per-wheel inputs ``u = [Fz, α, δ, κ]`` (source eq. 19-27). They differ in
state and covariance handling:

* :attr:`FrictionMode.FIXED_CKF`: state ``[μ, c_x×4, c_y×4]`` (:class:`PaperState`), stiffness
  a random walk from its value at the static load; standard SCKF.
* :attr:`FrictionMode.ADAPTIVE_CKF`: the same, stiffness carried with the load,
  ``c_k = c_{k−1} · c(Fz_k)/c(Fz_{k−1})`` with ``c(Fz) = 2a²c_p`` (eq. 16-19) so what the
  update learnt about a tyre stays; standard SCKF.
* :attr:`FrictionMode.PAPER`: the source's filter, ADAPTIVE_CKF with the MEE measurement
  covariance each step (standard step where it is not positive definite).
* :attr:`FrictionMode.PRODUCT`: state ``[ln μ, g_x,front, g_x,rear, g_y,front, g_y,rear,
  v_y]`` (:class:`ProductState`): per-axle factors on the load-adaptive stiffness instead of
  four free stiffnesses each way (three measurements cannot tell eight stiffnesses apart; an
  axle's factor can follow a worn or soft tyre), and the lateral speed as a state: in the
  tyres' linear range a slip-angle error of 10⁻³ rad already moves the lateral force by a
  tenth of what μ does, far below what GNSS or an integrated ``a_y`` give, so ``v_y`` is
  found with μ from the same forces (``v̇_y = a_y − r v_x``, GNSS ``v_y`` a weak measurement).
  Two more rows, one per axle, are the open differential's torque balance
  ``(F_L r_L − F_R r_R)/r̄ = 0`` (:mod:`.axle`; weightless where it does not hold).
  The measurement covariance adds the slips' uncertainty through the model (``R + D Dᵀ``,
  ``D`` the change of ``h`` for a 1-σ change of each wheel's κ and of the tyres' relaxation
  length, which sets the slip angles' lag in a steering ramp); μ's process noise grows
  while the normalised innovations stay large (a change of ground).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from enum import IntEnum, StrEnum

import numpy as np

from estimator._arrays import BoolArray, FloatArray
from estimator.friction.brush import Values, brush_forces, load_adaptive_stiffness_n
from estimator.friction.model import GRAVITY_MPS2, Chassis, body_accelerations
from estimator.friction.sckf import (
    cubature_points,
    mee_measurement_sqrt,
    sckf_predict,
    sckf_update,
    tria,
)

__all__ = [
    "FilterConfig",
    "FilterState",
    "FrictionMode",
    "PaperState",
    "ProductState",
    "TickInputs",
    "TyreArrays",
    "filter_step",
    "initial_state",
    "mu_of",
    "mu_std_of",
    "mu_upper",
    "reported_mu_std",
]

MU_MIN, MU_MAX = 0.05, 1.6
_GRIP_FLOOR = 0.95
"""The product filter keeps μ at or above this share of the measured ``hypot(a_x, a_y)/g``:
the tyres cannot have delivered more grip than the ground has (a projection of the mean)."""


class FrictionMode(StrEnum):
    """Which filter runs (see the module docstring)."""

    FIXED_CKF = "fixed_ckf"
    ADAPTIVE_CKF = "adaptive_ckf"
    PAPER = "paper"
    PRODUCT = "product"


class PaperState(IntEnum):
    """The source's state (eq. 18): μ and each tyre's longitudinal and lateral stiffness [N]."""

    MU = 0
    CX_FL = 1
    CX_FR = 2
    CX_RL = 3
    CX_RR = 4
    CY_FL = 5
    CY_FR = 6
    CY_RL = 7
    CY_RR = 8


class ProductState(IntEnum):
    """The product filter's state: ``ln μ`` and per-axle factors on the load-adaptive stiffness.

    μ is carried as its logarithm: cubature points spread ``√n σ`` around the mean, and in
    ``ln μ`` they stay positive and spread in proportion (a point at a negative μ, clipped,
    would read as a saturated tyre and pull the mean with it).
    """

    LN_MU = 0
    GX_FRONT = 1
    GX_REAR = 2
    GY_FRONT = 3
    GY_REAR = 4
    VY = 5
    """Lateral speed at the CG [m/s]: the slip angles follow from it and the yaw rate."""


@dataclass(frozen=True, slots=True)
class FilterConfig:
    """Noise and start of the μ filters (per tick of ``tick_s``).

    ``mu_walk_per_sqrt_s``: μ's random walk (``ln_mu_walk_per_sqrt_s`` in the product mode);
    ``stiffness_walk_per_sqrt_s``: relative walk of the paper modes' stiffness states;
    ``factor0_rel_std``, ``factor_walk_per_sqrt_s``: the product's stiffness factors;
    ``ln_mu0_std``, ``vy0_std_mps``, ``vy_walk_mps_per_sqrt_s``: the product's ``ln μ`` and
    ``v_y`` (a narrow start: cubature points spread ``√n σ``, and a wide ``v_y`` would put
    them deep in the tyres' saturation where the point mean no longer follows the model);
    ``accel_std_mps2``, ``yaw_accel_std_radps2``: the measurement noise ``R``;
    ``yaw_model_std_radps2``: the product adds it to ``ṙ``'s (in quadrature): the
    differentiated gyro is good to ~0.15 rad/s² a tick, but the yaw moment the model gives is
    off by more (each tyre's lateral force from a slip angle whose relaxation lag is known to
    ×0.5-2, the tyres' ±3 % stiffness spread left and right, toe): weighed as exact it pulled
    ``v_y`` and with it μ;
    ``mee_kernel_sigma``: the MEE kernel width (whitened units); ``nis_gate``: mean
    normalised innovation (per measurement) above which the product filter's μ walk is
    multiplied by ``mu_walk_boost``; ``linear_util``: the product updates ``ln μ`` only while
    the most used tyre (at the prior mean) works at this share of its grip or more, and an
    axle's stiffness factors only while its tyres work below it (their linear range) with
    their largest slip (κ for ``g_x``, α for ``g_y``) ``learn_excite_sigmas`` of its 1-σ or
    more, and ``ln μ`` only while the body's measured ``hypot(a_x, a_y)`` is
    ``learn_mu_min_accel_mps2`` or more and every wheel's κ is known to
    ``learn_mu_max_kappa_std`` (a torque step's one-sample slip, 1e-2 off, would otherwise be
    judged near the limit and learnt from) and the grip in use is known to
    ``learn_mu_util_rel_std`` of itself against the speed's shared error (:func:`_grip_known`),
    the grip in use for both judged at the far end of μ's interval, ``grip_judged_sigmas``
    1-σ above its mean (:func:`mu_upper`) (see :func:`_gain_mask`); ``outlier_sigmas``: a
    product update whose whitened innovation exceeds it in any measurement is skipped
    (gated: a tick where the wheel speeds and the IMU disagree, as when the torque is cut
    and a wheel spins down within one CAN sample); ``central_prediction``: the product's
    innovation taken from ``h`` with the considered states at their mean
    (:func:`_considered_centre`; off: with the tyres known to ±3 % only it did not pay,
    ``docs/perf/friction.md``); ``relaxation_rel_std``: the relative 1-σ of the tyres'
    relaxation length (so of the slip angles' lag behind the kinematic ones), carried into the
    product's measurement covariance (:func:`_input_spread`).
    """

    mode: FrictionMode = FrictionMode.PRODUCT
    tick_s: float = 0.02
    mu0: float = 0.6
    mu0_std: float = 0.35
    stiffness0_rel_std: float = 0.1
    mu_walk_per_sqrt_s: float = 0.03
    stiffness_walk_per_sqrt_s: float = 0.01
    factor0_rel_std: float = 0.1
    factor_walk_per_sqrt_s: float = 0.01
    ln_mu_walk_per_sqrt_s: float = 0.05
    vy0_std_mps: float = 0.05
    ln_mu0_std: float = 0.35
    vy_walk_mps_per_sqrt_s: float = 0.05
    accel_std_mps2: float = 0.2
    yaw_accel_std_radps2: float = 0.5
    yaw_model_std_radps2: float = 0.866
    mee_kernel_sigma: float = 2.0
    nis_gate: float = 9.0
    mu_walk_boost: float = 5.0
    nis_smoothing_s: float = 0.3
    linear_util: float = 0.3
    learn_mu_min_accel_mps2: float = 0.5
    outlier_sigmas: float = 6.0
    learn_excite_sigmas: float = 4.0
    learn_mu_max_kappa_std: float = 3e-3
    learn_mu_util_rel_std: float = 0.1
    grip_judged_sigmas: float = 2.0
    central_prediction: bool = False
    relaxation_rel_std: float = 0.5

    @property
    def n_states(self) -> int:
        return len(ProductState) if self.mode is FrictionMode.PRODUCT else len(PaperState)


@dataclass(frozen=True, slots=True)
class TyreArrays:
    """Tyre numbers per vehicle, ``(B, 1)`` (broadcast over wheels)."""

    kz_npm: FloatArray
    radius_m: FloatArray
    c_px_npm2: FloatArray
    c_py_npm2: FloatArray

    def stiffness(self, fz_n: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Load-adaptive ``(c_x, c_y)`` [N] at loads ``fz_n`` ``(B, 4)``."""
        return (
            load_adaptive_stiffness_n(fz_n, self.kz_npm, self.radius_m, self.c_px_npm2),
            load_adaptive_stiffness_n(fz_n, self.kz_npm, self.radius_m, self.c_py_npm2),
        )


@dataclass(frozen=True, slots=True)
class TickInputs:
    """One tick's inputs per vehicle: per wheel ``(B, 4)`` load, slip angle, steer angle and
    slip with the 1-σ of the last two (κ's each wheel's own; ``kappa_common_std`` ``(B,)`` the
    speed's error, shared by the four κ); ``z`` ``(B, 3)`` the measured ``[a_x, a_y, ṙ]``;
    ``valid`` ``(B,)`` where an update may run (moving, every input known); ``vx_mps``,
    ``yaw_rate_radps`` ``(B,)`` (with ``z``'s ``a_y``) drive the product's ``v_y``,
    ``vy_meas_mps`` (NaN when none) with ``vy_meas_std_mps`` corrects it; ``alpha_lag_rad``
    ``(B, 4)``: the relaxed slip angle minus the kinematic one (the tyre's lag behind a
    changing slip), added to the product's slip angles from ``v_y``; ``radius_m`` ``(B, 4)``
    the wheels' effective radii and ``balance_std_n`` ``(B, 2)`` the 1-σ of each axle's torque
    balance (product only, :mod:`.axle`)."""

    fz_n: FloatArray
    alpha_rad: FloatArray
    delta_rad: FloatArray
    kappa: FloatArray
    kappa_std: FloatArray
    kappa_common_std: FloatArray
    alpha_std_rad: FloatArray
    z: FloatArray
    valid: BoolArray
    vx_mps: FloatArray
    yaw_rate_radps: FloatArray
    vy_meas_mps: FloatArray
    vy_meas_std_mps: FloatArray
    alpha_lag_rad: FloatArray
    radius_m: FloatArray
    balance_std_n: FloatArray


_N_MEASURED = 4
"""The product's measured rows ``[a_x, a_y, ṙ, v_y]``; the axles' torque balances follow."""


@dataclass(slots=True)
class FilterState:
    """Filter state per vehicle: mean ``x`` ``(B, n)``, root ``s`` ``(B, n, n)``, the last
    loads ``(B, 4)``, the smoothed NIS ``(B,)``, and what the last step did."""

    x: FloatArray
    s: FloatArray
    fz_prev_n: FloatArray
    nis: FloatArray
    mee_ok: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    updated: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def take(self, rows: np.ndarray) -> FilterState:
        return FilterState(
            self.x[rows],
            self.s[rows],
            self.fz_prev_n[rows],
            self.nis[rows],
            self.mee_ok[rows] if self.mee_ok.size else self.mee_ok,
            self.updated[rows] if self.updated.size else self.updated,
        )


def initial_state(cfg: FilterConfig, tyres: TyreArrays, fz_n: FloatArray) -> FilterState:
    """The prior: ``μ0 ± mu0_std``; stiffness at ``fz_n`` ± ``stiffness0_rel_std`` (product:
    factors 1 ± ``factor0_rel_std``)."""
    b = fz_n.shape[0]
    if cfg.mode is FrictionMode.PRODUCT:
        x = np.ones((b, len(ProductState)))
        std = np.full((b, len(ProductState)), cfg.factor0_rel_std)
    else:
        cx, cy = tyres.stiffness(fz_n)
        x = np.concatenate([np.ones((b, 1)), cx, cy], axis=1)
        std = x * cfg.stiffness0_rel_std
    if cfg.mode is FrictionMode.PRODUCT:
        x[:, ProductState.VY] = 0.0
        std[:, ProductState.VY] = cfg.vy0_std_mps
    x[:, 0] = math.log(cfg.mu0) if cfg.mode is FrictionMode.PRODUCT else cfg.mu0
    std[:, 0] = cfg.ln_mu0_std if cfg.mode is FrictionMode.PRODUCT else cfg.mu0_std
    s = np.zeros((b, x.shape[1], x.shape[1]))
    idx = np.arange(x.shape[1])
    s[:, idx, idx] = std
    return FilterState(x, s, fz_n.copy(), np.zeros(b))


def mu_of(state_mu: Values, mode: FrictionMode) -> FloatArray:
    """μ from the state's first component (``ln μ`` in the product mode), within bounds."""
    mu = np.exp(state_mu) if mode is FrictionMode.PRODUCT else state_mu
    return np.clip(mu, MU_MIN, MU_MAX)


def mu_std_of(state_mu: Values, std: Values, mode: FrictionMode) -> FloatArray:
    """μ's 1-σ from the state's (first order through ``exp`` in the product mode)."""
    scale = mu_of(state_mu, mode) if mode is FrictionMode.PRODUCT else 1.0
    return np.asarray(scale * np.asarray(std), dtype=np.float64)


def reported_mu_std(mu_reported: Values, mu: Values, std: Values) -> FloatArray:
    """The 1-σ of the reported μ ``(B,)``: ``√(σ² + (μ_rep − μ)²)``, with ``μ`` and ``σ`` the
    filter's posterior mean and 1-σ this tick.

    Against the posterior, the reported value's mean squared error is
    ``E[(μ_rep − μ_true)²] = (μ_rep − μ)² + σ²``. While informed ``μ_rep = μ`` and it is the
    filter's σ; while held (the last informed value) it grows as the filter moves away from
    the held value (a new ground learnt before it is claimed) and with the filter's own σ (the
    μ walk while nothing informs it), so a held μ is not stated surer than the data now allow.
    NaN before the first informed tick (no value reported)."""
    rep = np.asarray(mu_reported, dtype=np.float64)
    return np.asarray(np.hypot(std, rep - np.asarray(mu, dtype=np.float64)), dtype=np.float64)


def mu_upper(x: FloatArray, s: FloatArray, cfg: FilterConfig) -> FloatArray:
    """The far (upper) end of μ's credible interval ``(B, 1)``: the mean ``+ grip_judged_sigmas``
    of the state's first component's 1-σ (rows of the root ``s`` ``(B, n, n)``).

    Where the tyres' grip in use decides whether μ may learn or be claimed, it is judged here,
    not at the mean: at the mean a μ pulled low (by a slip bias) finds every tyre at its limit,
    where the curve is flat in the slips and ``F = μ F_z`` fits the forces exactly, so the
    judgement would confirm the pull. At the upper end the same tyres sit below their limit
    unless the slips themselves put them there."""
    sd = np.sqrt(np.einsum("ij,ij->i", s[:, 0], s[:, 0]))[:, None]
    return mu_of(x[:, :1] + cfg.grip_judged_sigmas * sd, cfg.mode)


def _stiffness_of(
    points: FloatArray, cfg: FilterConfig, tyres: TyreArrays, fz_n: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per-point tyre stiffness ``(B, P, 4)`` each way."""
    if cfg.mode is not FrictionMode.PRODUCT:
        return points[..., PaperState.CX_FL : PaperState.CX_RR + 1], points[..., PaperState.CY_FL :]
    cx, cy = tyres.stiffness(fz_n)
    gx = points[..., [ProductState.GX_FRONT] * 2 + [ProductState.GX_REAR] * 2]
    gy = points[..., [ProductState.GY_FRONT] * 2 + [ProductState.GY_REAR] * 2]
    return gx * cx[:, None, :], gy * cy[:, None, :]


def _measure(
    points: FloatArray,
    cfg: FilterConfig,
    tyres: TyreArrays,
    chassis: Chassis,
    u: TickInputs,
    kappa: FloatArray,
    alpha: FloatArray,
) -> FloatArray:
    """``h``: ``[a_x, a_y, ṙ]`` ``(B, P, 3)`` at state points ``(B, P, n)`` (product: with
    ``v_y`` and the two axles' torque balances, ``(B, P, 6)``); slips are ``(B, P, 4)`` or
    ``(B, 1, 4)``.

    The balances are taken at the points' mean, the same for every point: they carry no
    information on the state (μ and the factors scale both wheels of an axle alike, and the
    tyres' ±3 % spread would otherwise make a steady imbalance that the state absorbs), only
    on the slips' errors, through their correlation with the accelerations in ``R + D Dᵀ``:
    the update reads the accelerations less what the balance says the slips got wrong."""
    fx, fy = _forces(points, cfg, tyres, chassis, u, kappa, alpha)
    acc = body_accelerations(fx, fy, u.delta_rad[:, None, :], chassis)
    if cfg.mode is not FrictionMode.PRODUCT:
        return acc
    vy = np.broadcast_to(points[..., ProductState.VY, None], (*acc.shape[:-1], 1))
    centre = points.mean(axis=1, keepdims=True)
    fx_centre, _ = _forces(centre, cfg, tyres, chassis, u, kappa, alpha)
    balance = np.broadcast_to(_torque_balance(fx_centre, u.radius_m), (*acc.shape[:-1], 2))
    return np.concatenate([acc, vy, balance], axis=-1)


def _forces(
    points: FloatArray,
    cfg: FilterConfig,
    tyres: TyreArrays,
    chassis: Chassis,
    u: TickInputs,
    kappa: FloatArray,
    alpha: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Brush forces ``(Fx, Fy)`` ``(B, P, 4)`` at state points ``(B, P, n)`` (source eq. 19-27;
    the product's slip angles from its ``v_y``)."""
    mu = mu_of(points[..., :1], cfg.mode)
    cx, cy = _stiffness_of(points, cfg, tyres, u.fz_n)
    if cfg.mode is FrictionMode.PRODUCT:
        alpha = _slip_angles(points[..., ProductState.VY], u, chassis)
    return brush_forces(kappa, alpha, u.fz_n[:, None, :], mu, cx, cy)


def _torque_balance(fx_n: FloatArray, radius_m: FloatArray) -> FloatArray:
    """``(F_L r_L − F_R r_R) / r̄`` per axle ``(B, P, 2)`` of forces ``(B, P, 4)``, radii
    ``(B, 4)``: zero where an open differential gives both wheels one torque."""
    r = radius_m[:, None, :]
    moment = fx_n * r
    mean = (r[..., 0::2] + r[..., 1::2]) / 2
    balance: FloatArray = (moment[..., 0::2] - moment[..., 1::2]) / mean
    return balance


def _slip_angles(vy_mps: FloatArray, u: TickInputs, chassis: Chassis) -> FloatArray:
    """α ``(B, P, 4)`` of lateral speeds ``(B, P)`` (source eq. 9-13, rigid body), lagged as
    the front end's relaxation says (``u.alpha_lag_rad``)."""
    r = u.yaw_rate_radps[:, None, None]
    along = u.vx_mps[:, None, None] - chassis.wheel_y_m[:, None, :] * r
    across = vy_mps[..., None] + chassis.wheel_x_m[:, None, :] * r
    d = u.delta_rad[:, None, :]
    v_long = along * np.cos(d) + across * np.sin(d)
    v_lat = -along * np.sin(d) + across * np.cos(d)
    return -np.arctan2(v_lat, np.maximum(np.abs(v_long), 0.5)) + u.alpha_lag_rad[:, None, :]


def _sq_r(cfg: FilterConfig, u: TickInputs) -> FloatArray:
    """Measurement root: accelerations (product: ``ṙ`` with the yaw model's error) and
    (product) the GNSS ``v_y``, weightless when none, and the axles' torque balances."""
    sigma = [cfg.accel_std_mps2, cfg.accel_std_mps2, cfg.yaw_accel_std_radps2]
    b = u.z.shape[0]
    if cfg.mode is not FrictionMode.PRODUCT:
        return np.broadcast_to(np.diag(sigma), (b, 3, 3)).copy()
    sigma[2] = math.hypot(sigma[2], cfg.yaw_model_std_radps2)
    vy_std = np.where(np.isfinite(u.vy_meas_mps), u.vy_meas_std_mps, 1e3)
    diag = np.concatenate(
        [np.broadcast_to(sigma, (b, 3)), vy_std[:, None], u.balance_std_n], axis=1
    )
    m = diag.shape[1]
    out = np.zeros((b, m, m))
    out[:, np.arange(m), np.arange(m)] = diag
    return out


def _measured(cfg: FilterConfig, u: TickInputs) -> FloatArray:
    """``z``: the accelerations, and (product) the GNSS ``v_y`` (0 where none: no weight) and
    the torque balances' 0."""
    if cfg.mode is not FrictionMode.PRODUCT:
        return u.z
    vy = np.nan_to_num(u.vy_meas_mps)[:, None]
    return np.concatenate([u.z, vy, np.zeros_like(u.balance_std_n)], axis=1)


def _input_spread(
    x: FloatArray, cfg: FilterConfig, tyres: TyreArrays, chassis: Chassis, u: TickInputs
) -> FloatArray:
    """``D`` ``(B, m, 5)`` (product ``(B, m, 6)``): the change of ``h`` at the mean for a 1-σ
    change of each wheel's own κ error and of the shared one (the speed's: all four κ at once;
    the slip angles follow from the state). A shared error shifts the driven and the
    free-rolling wheels alike, so it is not read as a driven tyre's slip. The product's sixth
    column is the relaxation length's: the lag of the relaxed slip angles behind the kinematic
    ones (``u.alpha_lag_rad``) is proportional to it while the slip moves (``τ = σ/v`` short
    against the change), and the tyres' own is the config's ×0.75-1.75 at best, so the lag of
    all four wheels scaled by ``1 + relaxation_rel_std``."""
    shifts = np.concatenate(
        [
            np.eye(4)[None] * u.kappa_std[:, :, None],
            np.ones((1, 1, 4)) * u.kappa_common_std[:, None, None],
        ],
        axis=1,
    )
    kappa = u.kappa[:, None, :] + shifts
    mean = x[:, None, :]
    alpha = u.alpha_rad[:, None, :]
    base = _measure(mean, cfg, tyres, chassis, u, u.kappa[:, None, :], alpha)
    d = _measure(mean, cfg, tyres, chassis, u, kappa, alpha) - base
    if cfg.mode is FrictionMode.PRODUCT and cfg.relaxation_rel_std > 0:
        longer = replace(u, alpha_lag_rad=u.alpha_lag_rad * (1 + cfg.relaxation_rel_std))
        lag = _measure(mean, cfg, tyres, chassis, longer, u.kappa[:, None, :], alpha) - base
        d = np.concatenate([d, lag], axis=1)
    return np.swapaxes(d, -1, -2)


def _predict(
    st: FilterState, cfg: FilterConfig, tyres: TyreArrays, u: TickInputs
) -> tuple[FloatArray, FloatArray]:
    """Time update (eq. 22, 28-31): μ and the stiffness states walk; ADAPTIVE/PAPER carry the
    stiffness with the load ratio."""
    b, n = st.x.shape
    sqrt_dt = math.sqrt(cfg.tick_s)
    walk = np.full((b, n), cfg.stiffness_walk_per_sqrt_s * sqrt_dt)
    mu_walk = cfg.mu_walk_per_sqrt_s * sqrt_dt
    if cfg.mode is FrictionMode.PRODUCT:
        walk[:, 1:] = cfg.factor_walk_per_sqrt_s * sqrt_dt
        boost = np.where(st.nis > cfg.nis_gate, cfg.mu_walk_boost, 1.0)
        walk[:, 0] = cfg.ln_mu_walk_per_sqrt_s * sqrt_dt * boost
        walk[:, ProductState.VY] = cfg.vy_walk_mps_per_sqrt_s * sqrt_dt
        scale = np.ones((b, n))
        shift = np.zeros((b, n))
        shift[:, ProductState.VY] = (u.z[:, 1] - u.yaw_rate_radps * u.vx_mps) * cfg.tick_s
    else:
        walk[:, 0] = mu_walk
        walk[:, 1:] *= np.abs(st.x[:, 1:])
        scale = np.ones((b, n))
        if cfg.mode is not FrictionMode.FIXED_CKF:
            cx_new, cy_new = tyres.stiffness(u.fz_n)
            cx_old, cy_old = tyres.stiffness(st.fz_prev_n)
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = np.concatenate([cx_new / cx_old, cy_new / cy_old], axis=1)
            scale[:, 1:] = np.where(np.isfinite(ratio) & (ratio > 0), ratio, 1.0)
        shift = np.zeros((b, n))
    sq_q = np.zeros((b, n, n))
    idx = np.arange(n)
    sq_q[:, idx, idx] = walk
    return sckf_predict(st.x, st.s, lambda p: p * scale[:, None, :] + shift[:, None, :], sq_q)


def filter_step(
    st: FilterState, cfg: FilterConfig, tyres: TyreArrays, chassis: Chassis, u: TickInputs
) -> FilterState:
    """One tick for every vehicle: predict, then (where ``u.valid``) update with ``u.z``
    (product: not where the innovation is an outlier, ``updated`` False there)."""
    x, s = _predict(st, cfg, tyres, u)
    mee_ok = np.zeros(x.shape[0], dtype=bool)
    nis = st.nis.copy()
    updated = u.valid.copy()
    rows = np.flatnonzero(u.valid)
    if rows.size:
        x_up, s_up, mee_ok[rows], white = _update(
            x[rows],
            s[rows],
            cfg,
            _tyres_subset(tyres, rows),
            _chassis_subset(chassis, rows),
            _subset(u, rows),
        )
        keep = np.ones(rows.size, dtype=bool)
        if cfg.mode is FrictionMode.PRODUCT:
            white = white[:, :_N_MEASURED]
            keep = np.abs(white).max(axis=-1) <= cfg.outlier_sigmas
        x[rows[keep]], s[rows[keep]] = x_up[keep], s_up[keep]
        updated[rows[~keep]] = False
        step = min(cfg.tick_s / cfg.nis_smoothing_s, 1.0)
        nis[rows] += step * ((white**2).mean(axis=-1) - nis[rows])
    _bound_mu(x, cfg, u)
    return FilterState(x, s, u.fz_n.copy(), nis, mee_ok, updated)


def _update(
    x: FloatArray,
    s: FloatArray,
    cfg: FilterConfig,
    tyres: TyreArrays,
    chassis: Chassis,
    u: TickInputs,
) -> tuple[FloatArray, FloatArray, BoolArray, FloatArray]:
    """Measurement update of the vehicles in ``u`` (all valid): the new ``(x, S)``, where the
    MEE covariance was used (paper mode) and the whitened innovation ``(B, m)``."""

    def h(points: FloatArray) -> FloatArray:
        return _measure(
            points, cfg, tyres, chassis, u, u.kappa[:, None, :], u.alpha_rad[:, None, :]
        )

    sq_r = _sq_r(cfg, u)
    z = _measured(cfg, u)
    mee_ok = np.zeros(x.shape[0], dtype=bool)
    mask = None
    if cfg.mode is FrictionMode.PRODUCT:
        sq_r = _with_inputs(sq_r, _input_spread(x, cfg, tyres, chassis, u))
        mask = _gain_mask(x, s, cfg, tyres, u)
    elif cfg.mode is FrictionMode.PAPER:
        z_mean = h(cubature_points(x, s)).mean(axis=1)
        mee = mee_measurement_sqrt(z, z_mean, x.shape[1], sq_r, cfg.mee_kernel_sigma)
        sq_r, mee_ok = mee.sq_r, mee.ok
    centre = None
    if mask is not None and cfg.central_prediction:
        centre = _considered_centre(x, s, mask, h)
    up = sckf_update(x, s, z, h, sq_r, mask, centre)
    white = np.asarray(np.linalg.solve(up.s_zz, up.innovation[..., None])[..., 0], np.float64)
    return up.x, up.s, np.asarray(mee_ok, dtype=bool), white


def _gain_mask(
    x: FloatArray, s: FloatArray, cfg: FilterConfig, tyres: TyreArrays, u: TickInputs
) -> FloatArray:
    """Which product states this update may move ``(B, n)`` (1 or 0; the rest are *considered*:
    their uncertainty enters the update, their values stay).

    At one operating point ``F = g·c·s·(1 − λ + λ²/3)`` (``λ ∝ g c s/μ``) ties ``g`` and ``μ``
    along a ridge (at 60 % of the grip 1 % of ``g`` is 5 % of μ), and the inputs' small biases
    walk a joint update along it. The two are learnt where each is told apart: an axle's
    factors in its tyres' linear range (below ``linear_util`` of the grip, where the slope
    ``F/s`` is the stiffness whatever μ is) while its largest slip is ``learn_excite_sigmas``
    of its 1-σ (κ's own and the speed's shared one, which is correlated over seconds and
    would be learnt as stiffness; at the noise, ``F ∝ g·s`` with ``s ≈ 0`` would shrink
    ``g`` towards 0);
    ``ln μ`` above ``linear_util``, from the curvature against the stiffness learnt (below,
    the curvature is smaller than what the inputs' biases fake: μ is held, not pulled), and
    only while the body accelerates by ``learn_mu_min_accel_mps2`` or more. The grip in use
    that decides it is judged at the far end of μ's interval (:func:`mu_upper`), not at
    the mean: a μ pulled low by a slip bias finds every tyre at its limit, where
    ``F = μ F_z`` fits any slip and the curve is flat in the slips, so a gate judged there
    confirms the pull (and the saturated fit shrinks μ's σ). At the far end the tyres are
    non-linear only where the slips themselves are large enough."""
    mu = mu_of(x[:, :1], cfg.mode)
    cx, cy = _stiffness_of(x[:, None, :], cfg, tyres, u.fz_n)
    fx, fy = brush_forces(u.kappa, u.alpha_rad, u.fz_n, mu, cx[:, 0], cy[:, 0])
    used = np.hypot(fx, fy) / np.maximum(mu * u.fz_n, 1.0)
    kappa_std = np.hypot(u.kappa_std, u.kappa_common_std[:, None])
    kappa = np.abs(u.kappa) / np.maximum(kappa_std, 1e-9)
    alpha = np.abs(u.alpha_rad) / np.maximum(u.alpha_std_rad, 1e-9)
    mask = np.ones_like(x)
    for axle, (gx, gy) in (
        (slice(0, 2), (ProductState.GX_FRONT, ProductState.GY_FRONT)),
        (slice(2, 4), (ProductState.GX_REAR, ProductState.GY_REAR)),
    ):
        linear = used[:, axle].max(axis=1) < cfg.linear_util
        mask[:, gx] = linear & (kappa[:, axle].max(axis=1) >= cfg.learn_excite_sigmas)
        mask[:, gy] = linear & (alpha[:, axle].max(axis=1) >= cfg.learn_excite_sigmas)
    mask[:, ProductState.LN_MU] = _mu_may_learn(x, s, cfg, (cx[:, 0], cy[:, 0]), u)
    return mask


def _mu_may_learn(
    x: FloatArray,
    s: FloatArray,
    cfg: FilterConfig,
    stiffness: tuple[FloatArray, FloatArray],
    u: TickInputs,
) -> BoolArray:
    """Where ``ln μ`` may learn ``(B,)`` (see :func:`_gain_mask`): the body pushed, every κ
    known, and at the far end of μ's interval (:func:`mu_upper`) the most used tyre beyond
    ``linear_util`` and its grip in use known against the speed's shared error
    (:func:`_grip_known`)."""
    cx, cy = stiffness
    pushed = np.hypot(u.z[:, 0], u.z[:, 1]) >= cfg.learn_mu_min_accel_mps2
    known = u.kappa_std.max(axis=1) <= cfg.learn_mu_max_kappa_std
    mu_far = mu_upper(x, s, cfg)
    fx, fy = brush_forces(u.kappa, u.alpha_rad, u.fz_n, mu_far, cx, cy)
    used_far = np.hypot(fx, fy) / np.maximum(mu_far * u.fz_n, 1.0)
    known &= _grip_known(used_far, mu_far, cx, cy, u) <= cfg.learn_mu_util_rel_std
    learns: BoolArray = (used_far.max(axis=1) >= cfg.linear_util) & pushed & known
    return learns


def _grip_known(
    used: FloatArray, mu: FloatArray, cx: FloatArray, cy: FloatArray, u: TickInputs
) -> FloatArray:
    """How far the speed's error moves the grip in use ``(B,)``: the largest change of a
    wheel's utilisation ``used`` ``(B, 4)`` (at ``mu`` ``(B, 1)``) when all four κ move by
    their shared 1-σ (``u.kappa_common_std``), relative to the most used wheel's.

    The shared error is the speed filter's, correlated over seconds (GNSS and the
    accelerometer between the rims' readings): ``R + D Dᵀ`` weighs one tick by it, but a
    run of ticks does not average it out, and where it is a large part of the slips in use
    (braking, when the undriven rims are braked too and no longer read the speed) ``ln μ``
    would learn it as grip."""
    shift = u.kappa_common_std[:, None]
    moved = np.zeros_like(used)
    for sign in (1.0, -1.0):
        fx, fy = brush_forces(u.kappa + sign * shift, u.alpha_rad, u.fz_n, mu, cx, cy)
        other = np.hypot(fx, fy) / np.maximum(mu * u.fz_n, 1.0)
        moved = np.maximum(moved, np.abs(other - used))
    rel: FloatArray = moved.max(axis=1) / np.maximum(used.max(axis=1), 1e-9)
    return rel


def _considered_centre(
    x: FloatArray, s: FloatArray, mask: FloatArray, h: Callable[[FloatArray], FloatArray]
) -> FloatArray:
    """The prediction ``(B, m)`` the product's innovation is taken from: the points' mean of
    ``h`` with the *considered* states (``mask`` 0) held at their mean.

    μ is monotone in each stiffness factor, so at the factors' centre the μ that fits is the
    median of those that fit over their spread; the points' mean of ``h`` spread over the
    factors (±24 % at ``√n σ``) instead shifts μ by the curvature of ``h`` (1.2-1.8 % on μ 0.8
    with the tyres known). The factors' spread still enters ``P_zz`` (the points' own)."""
    points = cubature_points(x, s)
    points = np.where(mask[:, None, :] == 0, x[:, None, :], points)
    centre: FloatArray = h(points).mean(axis=1)
    return centre


def _bound_mu(x: FloatArray, cfg: FilterConfig, u: TickInputs) -> None:
    """Keep μ within ``MU_MIN..MU_MAX``; the product's also at or above the grip measured
    (``_GRIP_FLOOR`` of ``hypot(a_x, a_y)/g``: the ground gave at least that)."""
    if cfg.mode is not FrictionMode.PRODUCT:
        x[:, 0] = np.clip(x[:, 0], MU_MIN, MU_MAX)
        return
    grip = _GRIP_FLOOR * np.hypot(u.z[:, 0], u.z[:, 1]) / GRAVITY_MPS2
    floor = np.maximum(np.where(u.valid, grip, 0.0), MU_MIN)
    x[:, 0] = np.log(np.clip(np.exp(x[:, 0]), floor, MU_MAX))


def _with_inputs(sq_r: FloatArray, d: FloatArray) -> FloatArray:
    """Root of ``R + D Dᵀ`` (``D`` ``(B, m, k)``: the inputs' spread through the model)."""
    root: FloatArray = tria(np.concatenate([sq_r, d], axis=-1))
    return root


def _subset(u: TickInputs, rows: np.ndarray) -> TickInputs:
    return TickInputs(**{f.name: getattr(u, f.name)[rows] for f in fields(u)})


def _tyres_subset(t: TyreArrays, rows: np.ndarray) -> TyreArrays:
    return TyreArrays(t.kz_npm[rows], t.radius_m[rows], t.c_px_npm2[rows], t.c_py_npm2[rows])


def _chassis_subset(c: Chassis, rows: np.ndarray) -> Chassis:
    return Chassis(c.mass_kg[rows], c.yaw_inertia_kgm2[rows], c.wheel_x_m[rows], c.wheel_y_m[rows])
