"""Batched MDSF engine: every vehicle's filter in slot arrays, stepped in batches.

:class:`MdsfEngine` holds the filter state of many vehicles (``x (cap, n)``, ``P (cap, n, n)``,
``n`` = 4 in paper mode, 8 in product mode; per-vehicle ``F``, ``H``, ``H1``, ``Q``) and steps any
subset of them with a few calls to the pure functions of :mod:`estimator.kalman`. A step runs
named stages (:meth:`MdsfEngine.step`): measurement noise, predict (accelerometer-driven in
product mode), update of the IMU rows, chi-square gates of GNSS speed and distance, update of
GNSS speed, rim speeds and RTK distance, (re)initialisation and divergence reset, the
reference-speed filter (``method.md`` §3), and while GNSS is lost the slip-step test
(:mod:`estimator.mdsf.outage_step`). Each step also returns what it used
(:class:`TickModel`: matrices, masks, NIS) for diagnostics and tests. A state that goes
non-finite or whose speed variance explodes is re-initialised and its row flagged RESET.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
import numpy.typing as npt

from estimator import kalman
from estimator._arrays import BoolArray, FloatArray, IntArray, nan_to_num
from estimator._slots import grow_slot_array
from estimator.config import WheeledRearDriveConfig
from estimator.mdsf.frontend import TickInputs
from estimator.mdsf.model import (
    GRAVITY_MPS2,
    N_OBS_PAPER,
    MdsfConfig,
    MdsfMode,
    MdsfObs,
    MdsfOut,
    MdsfState,
    mdsf_matrices,
)
from estimator.mdsf.outage_step import StepBuf, StepPrior, step_test
from estimator.reference_speed import RefAux, ReferenceSpeedConfig, RefState, reference_step
from estimator.types import EstimateFlag

__all__ = ["Counter", "MdsfEngine", "StepOutput", "TickModel"]

_NS = 1e-9
_SLIP_MIN_SPEED_MPS = 0.5
"""Speed floor of the constant-slip-ratio growth of the rim excess."""
_OUTAGE_SLIP_RATIO_RANGE = (-1.0, 1.0)
"""Range of the slip ratio ``ε = e/V`` an outage's rim excess reverts to: from a locked wheel
(``r·W = 0``) to one turning twice as fast as the ground passes (slip 50 %)."""
_F = EstimateFlag
_RIM = slice(MdsfObs.RIM_LEFT, MdsfObs.RIM_RIGHT + 1)
_RIM_EXCESS = np.array([MdsfState.RIM_EXCESS_LEFT, MdsfState.RIM_EXCESS_RIGHT])
"""The rim-excess states (left, right), for indexing both diagonals at once."""
#: Observation rows of the two update stages (the rows a stage's mask can switch on).
_STAGE1_ROWS = (int(MdsfObs.A1), int(MdsfObs.OMEGA_X), int(MdsfObs.OMEGA_Z))
_STAGE2_ROWS_PAPER = (int(MdsfObs.VG),)
_STAGE2_ROWS_PRODUCT = (
    int(MdsfObs.VG),
    int(MdsfObs.RIM_LEFT),
    int(MdsfObs.RIM_RIGHT),
    int(MdsfObs.DIST),
)
_UNIT_ROWS = {
    int(MdsfObs.A1): int(MdsfState.A1),
    int(MdsfObs.OMEGA_X): int(MdsfState.OMEGA_X),
    int(MdsfObs.OMEGA_Z): int(MdsfState.OMEGA_Z),
    int(MdsfObs.DIST): int(MdsfState.DIST),
}
"""Observation rows that measure one state directly (unit rows of ``H``, both modes; the
distance only in product mode), for :func:`estimator.kalman.update_independent`."""
_DIST_OPEN_VAR_M2 = 1.0e4
"""Variance of the distance state where its origin is arbitrary (start, new chain) [m²]."""


class _TyreStat(IntEnum):
    """Exponentially weighted sums of the online tyre-gain regression (per slot)."""

    W = 0  # weight
    X = 1  # Σw·x, x = low-passed forward specific force / g (traction demand)
    Y = 2  # Σw·y, y = measured rim excess over the filtered wheel speed, per speed (slip ratio)
    XX = 3
    XY = 4


class Counter(IntEnum):
    """Per-vehicle event counters (see :meth:`MdsfFleet.counters`)."""

    TICKS = 0
    GNSS_FUSED = 1
    GNSS_GATED = 2
    GNSS_REACQUIRED = 3
    RESETS = 4
    DEGRADED_TICKS = 5
    SKIPPED_GNSS = 6
    SKIPPED_IMU = 7
    SKIPPED_EDGES = 8
    SKIPPED_WHEEL_SPEEDS = 9
    SKIPPED_LATE = 10
    WAITING_TICKS = 11


_STEP_COUNTERS = np.array(
    [
        Counter.TICKS,
        Counter.GNSS_FUSED,
        Counter.GNSS_GATED,
        Counter.GNSS_REACQUIRED,
        Counter.RESETS,
        Counter.DEGRADED_TICKS,
        Counter.WAITING_TICKS,
    ]
)
"""Counters :meth:`MdsfEngine.step` adds to every tick (ticks, then its events)."""


@dataclass(slots=True)
class StepOutput:
    """Filter outputs of one batched step, shapes ``(k,)``; ``emit`` false before initialisation."""

    emit: BoolArray
    vg: FloatArray
    v1: FloatArray
    v0: FloatArray
    vl: FloatArray
    vr: FloatArray
    vg_std: FloatArray
    vl_std: FloatArray
    vr_std: FloatArray
    accel: FloatArray
    pitch_rate: FloatArray
    yaw_rate: FloatArray
    flags: npt.NDArray[np.int32]
    model: TickModel
    rim: FloatArray | None = None
    """Product mode: filtered rim speeds ``r·W = V_wheel + e`` (left, right), shape (k, 2)."""
    rim_std: FloatArray | None = None
    """Their 1-sigma, shape (k, 2)."""
    rim_ground_cov: FloatArray | None = None
    """Covariance of each filtered rim speed with its wheel's ground speed, shape (k, 2)."""


@dataclass(slots=True)
class TickModel:
    """What one batched step used, for diagnostics and the reference-filter tests.

    Attributes
    ----------
    F, Q : ndarray, shape (k, n, n)
        Transition and process noise of the predict.
    u : ndarray, shape (k, n) or None
        Control term of the predict (product mode).
    z : ndarray, shape (k, m)
        Observation (masked rows hold zeros).
    r : ndarray, shape (k, m)
        Measurement noise variances; ``R`` (k, m, m), their diagonal matrices, is built when
        read.
    mask1, mask2 : ndarray, shape (k, m), bool
        Rows of the first (IMU) and second (GNSS speed, rim speeds) update stage.
    inflated : ndarray, shape (k,), bool
        The covariance was changed between the stages (GNSS re-acquired, a slip jump or an
        outage's bound on the rim excess, :meth:`MdsfEngine._bound_rim_excess`) or after them
        (a slip step found in an outage, :meth:`MdsfEngine._outage_slip_steps`).
    nis : ndarray, shape (k,)
        Normalised innovation squared of both stages (their sum is the joint update's), with
        its degrees of freedom ``dof``; computed when read, from the two ``stages``.
    dof : ndarray, shape (k,), int
    special : ndarray, shape (k,), bool
        The row was (re)initialised, reset after divergence or handed over: not a plain
        Kalman step.
    stages : tuple of kalman.IndependentUpdateResult
        The two update stages.
    """

    F: FloatArray
    Q: FloatArray
    u: FloatArray | None
    z: FloatArray
    r: FloatArray
    mask1: BoolArray
    mask2: BoolArray
    inflated: BoolArray
    dof: IntArray
    special: BoolArray
    stages: tuple[kalman.IndependentUpdateResult, kalman.IndependentUpdateResult]

    @property
    def nis(self) -> FloatArray:
        first, second = self.stages
        return first.nis + second.nis

    @property
    def R(self) -> FloatArray:  # noqa: N802 (the measurement noise matrix, as in kalman)
        return _diagonal(self.r)


@dataclass(slots=True)
class _Updated:
    """What the update stages of a step leave: posterior ``x`` (k, n), ``P`` (k, n, n), the
    rows' ``H`` (k, m, n), stage-1 innovations ``y`` and their variances ``s`` (k, m), and
    which rows were used, gated or opened."""

    x: FloatArray
    P: FloatArray
    H: FloatArray
    y: FloatArray
    s: FloatArray
    use_vg: BoolArray
    gated: BoolArray
    reacq: BoolArray
    inflated: BoolArray
    zupt: BoolArray
    mask1: BoolArray
    mask2: BoolArray
    stages: tuple[kalman.IndependentUpdateResult, kalman.IndependentUpdateResult]


@dataclass(slots=True)
class _Started:
    """Rows (re)initialised at a step (first speed, or after divergence), shapes (k,), the
    mean measured rim speed (NaN: none) and the RESET flags they set."""

    started: BoolArray
    diverged: BoolArray
    rim_mean: FloatArray
    flags: npt.NDArray[np.int32]


def _diagonal(d: FloatArray) -> FloatArray:
    """Stack of diagonal matrices (k, m, m) with diagonals ``d`` (k, m)."""
    k, m = d.shape
    out = np.zeros((k, m, m))
    out.reshape(k, m * m)[:, :: m + 1] = d
    return out


def _step_flags(
    st: _Started, up: _Updated, now_init: BoolArray, degraded: BoolArray
) -> npt.NDArray[np.int32]:
    """A step's flags (k,): the start's RESET flags, then GNSS_OK, DEGRADED, GATED, RESET."""
    return st.flags | (
        np.where(now_init & ~degraded, int(_F.GNSS_OK), 0)
        | np.where(degraded, int(_F.DEGRADED), 0)
        | np.where(up.gated, int(_F.GATED), 0)
        | np.where(up.reacq, int(_F.RESET), 0)
    ).astype(np.int32)


def shrunk_lever_accel(t: TickInputs) -> FloatArray:
    """The tick's ``lever_accel_fwd_mps2`` (``h0·ω̇x``, eq. (3) differentiated) shrunk towards 0
    by two of its std, (k,) [m/s²]; 0 where it is unknown.

    A soft threshold: on a cab without sway the term is the gyro's white noise through
    ``h0/Δt`` (about 0.07 m/s² at 1.2 m), under sway it is metres per second squared.
    """
    if t.lever_accel_fwd_mps2 is None or t.lever_accel_fwd_var is None:
        return np.zeros(t.force_fwd.shape[0])
    lever = nan_to_num(t.lever_accel_fwd_mps2)
    noise = 2.0 * np.sqrt(nan_to_num(t.lever_accel_fwd_var))
    out: FloatArray = np.sign(lever) * np.maximum(np.abs(lever) - noise, 0.0)
    return out


def axle_force_fwd(t: TickInputs) -> FloatArray:
    """The forward specific force the driven tyres must transmit, (k,) [m/s²]; NaN without IMU.

    The IMU's tick-mean forward force ``f1 = a1 + g·sinθ`` plus the lever term (eq. (3)
    differentiated, ``a0 = a1 + h0·ω̇x``, :func:`shrunk_lever_accel`): the traction demand is
    the axle's; a cab swaying about the axle moves the IMU, not the ground under the tyres.
    """
    ok = t.imu_ok & np.isfinite(t.force_fwd)
    out: FloatArray = np.where(ok, t.force_fwd + shrunk_lever_accel(t), np.nan)
    return out


class MdsfEngine:
    """Slot arrays of many vehicles' MDSF filters, stepped in batches.

    State ``x (cap, n)``, covariance ``P (cap, n, n)`` and per-vehicle ``F``, ``H``, ``H1``,
    ``Q`` (``n`` = 4 in paper mode, 8 in product mode; see :class:`~estimator.mdsf.MdsfState`).

    Parameters
    ----------
    config : MdsfConfig
    reference : ReferenceSpeedConfig
        Settings of the reference-speed filter that carries the speed while GNSS is lost.
    capacity : int
        Initial number of slots (grows as needed).
    """

    def __init__(
        self, config: MdsfConfig, reference: ReferenceSpeedConfig | None = None, capacity: int = 16
    ) -> None:
        self.config = config
        self.reference = reference or ReferenceSpeedConfig()
        self.product = config.mode is MdsfMode.PRODUCT
        self.dt_s = config.dt_s
        self.n = config.n_state
        self.m = config.n_obs
        self._free: list[int] = []
        self._cap = 0
        step_half = round(0.5 * config.outage_step_window_s / self.dt_s)
        self._step_ticks = 2 * step_half if self.product and step_half >= 2 else 0
        self._step_prior = StepPrior(
            load_s=config.outage_step_turn_load_s,
            yaw_rad=config.outage_step_yaw_misalign_rad,
            cent_m=config.outage_step_imu_offset_m,
            step=config.outage_step_prior,
            z_min=config.outage_step_z,
            min_step=config.outage_step_min,
        )
        self._alloc(max(capacity, 1))
        # Product mode: the entries of Q the tick's accelerometer variance enters, as (row,
        # column, factor) for one indexed add a step: V1 and a1 through dt, the distance
        # through dt²/2 (method.md §1).
        dt, half = self.dt_s, 0.5 * self.dt_s * self.dt_s
        D, V1, A1 = MdsfState.DIST, MdsfState.V1, MdsfState.A1
        q_accel = (
            (V1, V1, dt * dt),
            (A1, A1, 1.0),
            (V1, A1, dt),
            (A1, V1, dt),
            (D, D, half * half),
            (D, V1, half * dt),
            (V1, D, half * dt),
            (D, A1, half),
            (A1, D, half),
        )
        self._q_accel_rows = np.array([int(r) for r, _, _ in q_accel])
        self._q_accel_cols = np.array([int(c) for _, c, _ in q_accel])
        self._q_accel = np.array([f for _, _, f in q_accel])
        # ... and the rim excesses by ε·dt (MdsfEngine._accel_noise_into_excess): their 2×2
        # block, then their rows against V1, a1, D (the noise's shares there), then the mirror.
        e_l, e_r = (int(e) for e in _RIM_EXCESS)
        shared = (int(V1), int(A1), int(D))
        self._q_excess_shares = np.array([dt, 1.0, half])
        self._q_excess_rows = np.array([e_l, e_l, e_r, e_r, *[e_l] * 3, *[e_r] * 3, *shared * 2])
        self._q_excess_cols = np.array([e_l, e_r, e_l, e_r, *shared * 2, *[e_l] * 3, *[e_r] * 3])

    # -- slots -------------------------------------------------------------------------------
    def _alloc(self, cap: int) -> None:
        old = self._cap

        def grow(name: str, shape: tuple[int, ...], fill: Any) -> None:
            grow_slot_array(self, name, cap, shape, fill)

        n, m = self.n, self.m
        grow("x", (n,), 0.0)
        grow("P", (n, n), 0.0)
        grow("F", (n, n), 0.0)
        grow("H", (m, n), 0.0)
        grow("H1", (len(MdsfOut), n), 0.0)
        grow("v0_row", (n,), 0.0)
        grow("Q_base", (n, n), 0.0)
        grow("initialized", (), False)
        grow("last_fused_ns", (), np.int64(-(2**62)))
        grow("gated_since_ns", (), np.int64(-1))
        grow("gnss_noise_var", (), 0.0)
        grow("force_fast", (), np.nan)
        grow("force_slow", (), np.nan)
        grow("force_model", (), np.nan)
        grow("tyre_stats", (len(_TyreStat),), 0.0)
        grow("rim_innov", (2, 2), 0.0)
        grow("slip_anchor", (2,), 0.0)
        grow("accel_var_fix", (), np.nan)
        grow("leak_var", (), 0.0)
        grow("anchor_stats", (3,), 0.0)
        grow("dist_gated", (), False)
        grow("step_buf", (len(StepBuf), max(self._step_ticks, 1)), 0.0)
        grow("step_count", (), 0)
        grow("step_level", (), 0.0)
        grow("step_inertial", (), 0.0)
        grow("ref_x", (len(RefState),), 0.0)
        grow("ref_P", (len(RefState), len(RefState)), 0.0)
        grow("ref_aux", (len(RefAux),), 0.0)
        grow("counts", (len(Counter),), np.int64(0))
        self._free.extend(range(cap - 1, old - 1, -1))
        self._cap = cap

    x: FloatArray
    P: FloatArray
    F: FloatArray
    H: FloatArray
    H1: FloatArray
    v0_row: FloatArray
    Q_base: FloatArray
    initialized: BoolArray
    last_fused_ns: IntArray
    gated_since_ns: IntArray
    gnss_noise_var: FloatArray
    force_fast: FloatArray
    force_slow: FloatArray
    force_model: FloatArray
    tyre_stats: FloatArray
    rim_innov: FloatArray
    slip_anchor: FloatArray
    accel_var_fix: FloatArray
    leak_var: FloatArray
    anchor_stats: FloatArray
    dist_gated: BoolArray
    step_buf: FloatArray
    step_count: IntArray
    step_level: FloatArray
    step_inertial: FloatArray
    ref_x: FloatArray
    ref_P: FloatArray  # noqa: N815 (covariance, as P)
    ref_aux: FloatArray
    counts: IntArray

    def add(self, vehicle: WheeledRearDriveConfig) -> int:
        """Allocate and initialise a slot for a vehicle; returns the slot index."""
        if not self._free:
            self._alloc(2 * self._cap)
        s = self._free.pop()
        mats = mdsf_matrices(self.config, vehicle)
        self.F[s] = mats.F
        self.H[s] = mats.H
        self.H1[s] = mats.H1
        self.v0_row[s] = mats.v0_row
        self.Q_base[s] = mats.Q_base
        self.initialized[s] = False
        self.last_fused_ns[s] = -(2**62)
        self.gated_since_ns[s] = -1
        self.gnss_noise_var[s] = 0.0
        self.force_fast[s] = np.nan
        self.force_slow[s] = np.nan
        self.force_model[s] = np.nan
        self.tyre_stats[s] = 0.0
        self.rim_innov[s] = 0.0
        self.slip_anchor[s] = 0.0
        self.accel_var_fix[s] = np.nan
        self.leak_var[s] = 0.0
        self.anchor_stats[s] = 0.0
        self.dist_gated[s] = False
        self.step_buf[s] = 0.0
        self.step_count[s] = 0
        self.step_level[s] = 0.0
        self.step_inertial[s] = 0.0
        self.x[s] = 0.0
        self.P[s] = np.eye(self.n)
        self.ref_x[s] = 0.0
        self.ref_P[s] = np.eye(len(RefState))
        self.ref_aux[s] = (0.0, 1.0, 0.0)
        self.counts[s] = 0
        return s

    def release(self, slot: int) -> None:
        """Return a slot to the free list."""
        self.initialized[slot] = False
        self._free.append(slot)

    # -- stepping ----------------------------------------------------------------------------
    def _initial_state(
        self,
        slots: IntArray,
        z: FloatArray,
        imu_ok: BoolArray,
        v1: FloatArray,
        rim_ok: BoolArray,
    ) -> tuple[FloatArray, FloatArray]:
        """State (k, n) and covariance (k, n, n) right after a (re)initialisation at ``v1``."""
        cfg = self.config
        k = slots.shape[0]
        x = np.zeros((k, self.n))
        x[:, MdsfState.V1] = v1
        x[:, MdsfState.A1] = np.where(imu_ok, z[:, MdsfObs.A1], 0.0)
        x[:, MdsfState.OMEGA_X] = np.where(imu_ok, z[:, MdsfObs.OMEGA_X], 0.0)
        x[:, MdsfState.OMEGA_Z] = np.where(imu_ok, z[:, MdsfObs.OMEGA_Z], 0.0)
        p = np.zeros((k, self.n, self.n))
        idx = np.arange(self.n)
        diag = np.zeros((k, self.n))
        diag[:, MdsfState.V1] = cfg.initial_speed_std_mps**2
        diag[:, MdsfState.A1] = 1.0
        diag[:, MdsfState.OMEGA_X] = 0.01
        diag[:, MdsfState.OMEGA_Z] = 0.01
        if self.product:
            diag[:, MdsfState.ACCEL_BIAS] = cfg.accel_bias_std_mps2**2
            h = self.H[slots]
            for obs, st in (
                (MdsfObs.RIM_LEFT, MdsfState.RIM_EXCESS_LEFT),
                (MdsfObs.RIM_RIGHT, MdsfState.RIM_EXCESS_RIGHT),
            ):
                ok = rim_ok[:, obs - MdsfObs.RIM_LEFT]
                v_wheel = np.einsum("ki,ki->k", h[:, obs, : MdsfState.ACCEL_BIAS], x[:, :4])
                x[:, st] = np.where(ok, z[:, obs] - v_wheel, 0.0)
                diag[:, st] = cfg.initial_speed_std_mps**2 + 0.01
            x[:, MdsfState.DIST] = z[:, MdsfObs.DIST]  # origin arbitrary: opened wide
            diag[:, MdsfState.DIST] = _DIST_OPEN_VAR_M2
        p[:, idx, idx] = diag
        return x, p

    def step(
        self, slots: IntArray, t: TickInputs, rim_mps: FloatArray, rim_std_mps: FloatArray
    ) -> StepOutput:
        """Advance the vehicles in ``slots`` by one tick each (batched).

        Stages, in order: observation and its noise, predict, update (IMU rows, then the
        gated GNSS speed, rim speeds and distance, then a zero-velocity update), the online
        fits (GNSS noise, tyre gain), start and divergence reset, the reference-speed filter,
        store, outputs. Equal to one joint Kalman update: the rows' noises are independent.

        Parameters
        ----------
        slots : ndarray, shape (k,), int
            Distinct slot indices.
        t : TickInputs
            One row per slot (``m == k``).
        rim_mps, rim_std_mps : ndarray, shape (k, 2)
            Rim speeds ``r·W`` (left, right) and their std; NaN when unknown.

        Returns
        -------
        StepOutput
        """
        rim_ok = np.isfinite(rim_mps) & np.isfinite(rim_std_mps)
        z = self._observation(t, rim_mps, rim_ok)
        rd = self._noise(slots, t, rim_mps, rim_std_mps, rim_ok)
        x, P, init, broken = self._working_state(slots)
        F, Q, u = self._process(slots, t, z, x, init, rd[:, MdsfObs.A1])
        x_pr, P_pr = kalman.predict(x, P, F, Q, u)
        up = self._update(slots, t, z, rd, x_pr, P_pr, init, rim_mps, rim_ok)
        self._online_fits(slots, t, rd, up, init, rim_mps, rim_ok)
        st = self._start(slots, t, z, init, broken, up, rim_mps, rim_ok)
        if self._step_ticks:
            self._mark_outage_steps(slots, t, z, x, up, st, init, rim_mps, rim_ok, rim_std_mps)
        now_init = init | st.started
        fused, last_fused, degraded = self._gnss_fused(slots, t, up, now_init)
        v0, ref = self._reference(slots, t, z, up, st, rim_ok, degraded)
        self._store(slots, x, P, up, now_init, last_fused, ref)
        if self.product:
            self._set_slip_anchor(slots, up.x, fused)
        self._count(slots, fused, up, st, degraded, now_init)
        flags = _step_flags(st, up, now_init, degraded)
        model = self._tick_model(F, Q, u, z, rd, up, st, degraded)
        return self._outputs(slots, up.x, up.P, up.H, v0, now_init, flags, model)

    def _online_fits(
        self,
        slots: IntArray,
        t: TickInputs,
        rd: FloatArray,
        up: _Updated,
        init: BoolArray,
        rim_mps: FloatArray,
        rim_ok: BoolArray,
    ) -> None:
        """Online fits after the update (product): GNSS noise, then tyre gain (``rd``: (k, m))."""
        if self.product and self.config.gnss_noise_adapt > 0:
            fused = up.use_vg & init
            self._adapt_gnss_noise(slots, fused, up.y[:, MdsfObs.VG], up.s[:, MdsfObs.VG], rd)
        if self.product and self.config.slip_per_demand > 0 and self.config.tyre_gain_tau_s > 0:
            self._learn_tyre_gain(slots, t, up.x, up.H, rim_mps, rim_ok, up.use_vg & init)

    def _mark_outage_steps(
        self,
        slots: IntArray,
        t: TickInputs,
        z: FloatArray,
        x: FloatArray,
        up: _Updated,
        st: _Started,
        init: BoolArray,
        rim_mps: FloatArray,
        rim_ok: BoolArray,
        rim_std_mps: FloatArray,
    ) -> None:
        """Add the outage slip steps found on rows without GNSS to ``up.inflated`` (k,)."""
        lost = self._gnss_lost(slots, t, init) & ~st.started & ~st.diverged
        up.inflated = up.inflated | self._outage_slip_steps(
            slots, t, z, x, up, lost, rim_mps, rim_ok, rim_std_mps
        )

    def _gnss_fused(
        self, slots: IntArray, t: TickInputs, up: _Updated, now_init: BoolArray
    ) -> tuple[BoolArray, IntArray, BoolArray]:
        """Rows whose GNSS speed was fused, each slot's last fused stamp [ns] and the rows
        degraded (no fused GNSS within the timeout), shapes (k,)."""
        fused = up.use_vg & now_init
        last_fused = np.where(fused, t.stamp_ns, self.last_fused_ns[slots])
        degraded = now_init & ((t.stamp_ns - last_fused) > round(self.config.gnss_timeout_s * 1e9))
        return fused, last_fused, degraded

    def _count(
        self,
        slots: IntArray,
        fused: BoolArray,
        up: _Updated,
        st: _Started,
        degraded: BoolArray,
        now_init: BoolArray,
    ) -> None:
        """Add this tick's events to the slots' counters (:data:`_STEP_COUNTERS`; masks (k,))."""
        k = slots.shape[0]
        events = [np.ones(k, dtype=bool), fused, up.gated, up.reacq, st.diverged | up.reacq]
        self.counts[slots[:, None], _STEP_COUNTERS] += np.stack(
            [*events, degraded, ~now_init], axis=1
        )

    def _tick_model(
        self,
        F: FloatArray,
        Q: FloatArray,
        u: FloatArray | None,
        z: FloatArray,
        rd: FloatArray,
        up: _Updated,
        st: _Started,
        degraded: BoolArray,
    ) -> TickModel:
        """The tick's model for the outputs: ``F`` broadcast to (k, n, n), the rest as stepped."""
        k = z.shape[0]
        special = st.started | st.diverged | up.zupt
        if not self.product:
            special = special | degraded
        return TickModel(
            F=np.asarray(np.broadcast_to(F, (k, self.n, self.n))),
            Q=Q,
            u=u,
            z=z,
            r=rd,
            mask1=up.mask1,
            mask2=up.mask2,
            inflated=up.inflated,
            dof=up.stages[0].dof + up.stages[1].dof,
            special=special,
            stages=up.stages,
        )

    # -- stages of a step --------------------------------------------------------------------
    def _observation(self, t: TickInputs, rim_mps: FloatArray, rim_ok: BoolArray) -> FloatArray:
        """Observation ``z`` (k, m) of :class:`MdsfObs`; rows without a value hold 0."""
        k = t.stamp_ns.shape[0]
        z = np.zeros((k, self.m))
        z[:, :N_OBS_PAPER] = np.where(np.isfinite(t.z), t.z, 0.0)
        if self.product:
            z[:, _RIM] = np.where(rim_ok, rim_mps, 0.0)
            z[:, MdsfObs.DIST] = np.where(t.dist_ok, t.dist_m, 0.0)
        return z

    def _noise(
        self,
        slots: IntArray,
        t: TickInputs,
        rim_mps: FloatArray,
        rim_std_mps: FloatArray,
        rim_ok: BoolArray,
    ) -> FloatArray:
        """Measurement noise variances, the diagonal of ``R`` (k, m); unused rows hold 1.

        The GNSS speed's is the receiver's (or configured) variance, raised by the running
        estimate from its innovations (:meth:`_adapt_gnss_noise`). A rim speed's is the wheel
        fit's std scaled by ``wheel_noise_scale``, plus soil texture ``rim_texture_rel·r·W``.
        """
        cfg = self.config
        k = slots.shape[0]
        gyro_var = np.where(t.imu_ok, t.gyro_var, 1.0)
        rd = np.zeros((k, self.m))
        rd[:, MdsfObs.VG] = np.maximum(t.gnss_var, self.gnss_noise_var[slots])
        rd[:, MdsfObs.A1] = np.where(t.imu_ok, t.accel_var, 1.0)
        rd[:, MdsfObs.OMEGA_X] = gyro_var
        rd[:, MdsfObs.OMEGA_Z] = gyro_var
        if self.product:
            rd[:, _RIM] = np.where(
                rim_ok,
                self._rim_fit_var(rim_std_mps, rim_ok)
                + (cfg.rim_texture_rel * np.where(rim_ok, rim_mps, 0.0)) ** 2
                + 1e-6,
                1.0,
            )
            rd[:, MdsfObs.DIST] = np.where(t.dist_ok, t.dist_var, 1.0)
        return rd

    def _rim_fit_var(self, rim_std_mps: FloatArray, rim_ok: BoolArray) -> FloatArray:
        """Each rim speed's variance from the wheel fit alone, ``(wheel_noise_scale·σ)²``
        (k, 2) [m²/s²]; 0 where the rim is unknown. The filter's rim rows add the soil's
        texture to it (:meth:`_noise`); the outage step test weighs a step against it."""
        rim_sd = self.config.wheel_noise_scale * np.where(rim_ok, rim_std_mps, 0.0)
        var: FloatArray = rim_sd**2
        return var

    def _working_state(
        self, slots: IntArray
    ) -> tuple[FloatArray, FloatArray, BoolArray, BoolArray]:
        """Copies of ``x``, ``P`` and ``initialized`` for ``slots`` (rows gathered by an index
        array are copies), with a state that is already non-finite started afresh (it cannot
        be predicted; counted as a reset). Returns ``(x, P, init, broken)``."""
        x = self.x[slots]
        P = self.P[slots]
        init = self.initialized[slots]
        broken = init & ~(np.isfinite(x).all(axis=1) & np.isfinite(P).all(axis=(1, 2)))
        if broken.any():
            x = np.where(broken[:, None], 0.0, x)
            P = np.where(broken[:, None, None], np.eye(self.n), P)
            init &= ~broken
            self.counts[slots, Counter.RESETS] += broken
        return x, P, init, broken

    def _process(
        self,
        slots: IntArray,
        t: TickInputs,
        z: FloatArray,
        x: FloatArray,
        init: BoolArray,
        accel_var: FloatArray,
    ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """Transition ``F`` (k, n, n), process noise ``Q`` (k, n, n) and control ``u`` (k, n)
        of the predict; paper mode: eq. (6), no control."""
        F = self.F[slots]
        Q = self.Q_base[slots]
        if not self.product:
            return F, Q, None
        accel_var = self._leak_into_bias(slots, t, init, accel_var, Q)
        u, a_in = self._accel_control(slots, t, z, x, accel_var, Q)
        self._rim_excess_process(slots, t, x, init, a_in, accel_var, F, Q, u)
        return F, Q, u

    def _leak_into_bias(
        self, slots: IntArray, t: TickInputs, init: BoolArray, accel_var: FloatArray, Q: FloatArray
    ) -> FloatArray:
        """Product mode, GNSS lost: the gravity leak's growth as bias, not white noise (``Q`` in
        place); returns the white accelerometer variance the tick keeps, (k,).

        The front end adds the pitch error's leak ``g·δθ`` to each tick's accelerometer
        variance as white noise, ``g²·P_θθ·c/dt`` (``c = pitch_leak_corr_s``). Through an
        outage ``P_θθ`` grows with the pitch gyro's bias, and ``δθ`` moves over tens of
        seconds: the speed error it makes is ``g·∫δθ``, a drift, not a random walk that lets a
        common rim step pass as a change of speed. So the tick keeps the white variance it had
        at its last fused GNSS speed, ``σ²_fix``, and the rest, ``g²·ΔP_θθ = (σ² − σ²_fix)·dt/c``,
        enters the bias state's variance as it grows: the speed changes only by the integrated
        specific force less a bias whose uncertainty is the last GNSS minutes' plus the tilt's.
        """
        cfg = self.config
        lost = self._gnss_lost(slots, t, init)
        fix = self.accel_var_fix[slots]
        fresh = ~lost | ~np.isfinite(fix)
        self.accel_var_fix[slots] = np.where(fresh & t.imu_ok, accel_var, fix)
        held = ~fresh & t.imu_ok  # a tick without IMU data keeps its placeholder variance
        white = np.where(held, np.minimum(accel_var, fix), accel_var)
        leak = np.where(held, (accel_var - white) * (self.dt_s / cfg.pitch_leak_corr_s), 0.0)
        before = np.where(fresh, 0.0, self.leak_var[slots])
        Q[:, MdsfState.ACCEL_BIAS, MdsfState.ACCEL_BIAS] += np.maximum(leak - before, 0.0)
        self.leak_var[slots] = np.maximum(leak, before)
        return np.asarray(white)

    def _accel_control(
        self,
        slots: IntArray,
        t: TickInputs,
        z: FloatArray,
        x: FloatArray,
        accel_var: FloatArray,
        Q: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """Product mode: the accelerometer drives the speed and the distance (``Q`` in place).

        ``V1' = V1 + dt·(ā − b)``, ``a1' = ā``, ``D' = D + dt·V1 + dt²·(ā − b)/2`` (``ā`` the
        tick's mean acceleration, or the state's where the tick has none), so the tick's
        acceleration noise reaches ``V1``, ``a1`` and ``D`` (one indexed add). A new chain of
        RTK positions, or one after a gated distance, has its own origin: the predicted
        distance is moved onto the measured one and opened, so the chain's offset carries no
        information on the speed. Returns ``(u (k, n), ā (k,))``.
        """
        dt = self.dt_s
        k = slots.shape[0]
        a_in = np.where(t.imu_ok, z[:, MdsfObs.A1], x[:, MdsfState.A1] + x[:, MdsfState.ACCEL_BIAS])
        u = np.zeros((k, self.n))
        u[:, MdsfState.V1] = dt * a_in
        u[:, MdsfState.A1] = a_in
        half = 0.5 * dt * dt
        D, V1 = MdsfState.DIST, MdsfState.V1
        u[:, D] = half * a_in
        Q[:, self._q_accel_rows, self._q_accel_cols] += accel_var[:, None] * self._q_accel
        new_chain = t.dist_ok & (t.dist_restart | self.dist_gated[slots])
        d_pred = x[:, D] + dt * x[:, V1] - half * x[:, MdsfState.ACCEL_BIAS] + half * a_in
        u[:, D] += np.where(new_chain, z[:, MdsfObs.DIST] - d_pred, 0.0)
        Q[:, D, D] += np.where(new_chain, _DIST_OPEN_VAR_M2, 0.0)
        return u, a_in

    def _rim_excess_process(
        self,
        slots: IntArray,
        t: TickInputs,
        x: FloatArray,
        init: BoolArray,
        a_in: FloatArray,
        accel_var: FloatArray,
        F: FloatArray,
        Q: FloatArray,
        u: FloatArray,
    ) -> None:
        """Product mode: how each rim excess ``e = r·W − V`` moves (``F``, ``Q``, ``u`` in place).

        At constant slip ratio it scales with the speed, ``e' = e·(1 + dt·ā/V)``. It wanders
        with soil and load, opens while the traction demand changes
        (:meth:`_demand_change`; without GNSS only ``outage_demand_share`` of it) and where
        rim innovations keep one sign (:meth:`_rim_drift_noise`: a drawbar load, soil, tyre
        pressure the accelerometer cannot see). The tyre model ``Δe ≈ k·V·Δ(f/g)`` enters as
        a control term, ``k`` the traction curve's slope learnt online (:meth:`tyre_gain`); it
        stays on through a GNSS outage.
        """
        cfg = self.config
        dt = self.dt_s
        speed = np.abs(x[:, MdsfState.V1])
        d2 = self._demand_change(slots, t, accel_var)
        lost = self._gnss_lost(slots, t, init)
        d2 = d2 * np.where(lost, cfg.outage_demand_share, 1.0)
        q_e = (cfg.rim_excess_walk_rel_per_sqrt_s * speed) ** 2 * dt + (
            cfg.slip_demand_gain * speed / GRAVITY_MPS2
        ) ** 2 * d2
        q_drift = None
        if cfg.rim_drift_tau_s > 0:
            q_drift = self._rim_drift_noise(slots, lost)
        Q[:, _RIM_EXCESS, _RIM_EXCESS] += q_e[:, None]
        if q_drift is not None:
            Q[:, _RIM_EXCESS, _RIM_EXCESS] += q_drift
        self._slip_ratio_growth(x, a_in, speed, F)
        if cfg.slip_per_demand > 0:
            d_dem = self._model_demand_change(slots, t)
            gain = self.tyre_gain(slots)
            u[:, _RIM_EXCESS] = (gain * speed * d_dem / GRAVITY_MPS2)[:, None]
        if cfg.outage_slip_std > 0 and lost.any():
            self._anchor_slip(slots, lost, speed, F, Q)
        self._accel_noise_into_excess(F, Q, accel_var)

    def _slip_ratio_growth(
        self, x: FloatArray, a_in: FloatArray, speed: FloatArray, F: FloatArray
    ) -> None:
        """The rim excess at constant slip ratio ``ε = e/V``, ``e' = e·(1 + dt·(ā − b)/V)``,
        linearised in ``F`` (k, n, n, in place): ``∂e'/∂e = 1 + dt·ā/V`` and
        ``∂e'/∂b = −ε·dt`` (their product with the state is the growth itself), so the rim
        excess moves with the speed the accelerometer predicts and with the bias the GNSS
        corrects. ``V`` is floored at ``_SLIP_MIN_SPEED_MPS``; a growth outside [0.5, 1.5]
        (a tick's acceleration near the floor's size) is clipped and left uncoupled."""
        dt = self.dt_s
        floor = np.maximum(speed, _SLIP_MIN_SPEED_MPS)
        bias = x[:, MdsfState.ACCEL_BIAS]
        grow = 1.0 + dt * (a_in - bias) / floor
        inside = (grow >= 0.5) & (grow <= 1.5)
        diag = np.where(inside, 1.0 + dt * a_in / floor, np.clip(grow, 0.5, 1.5))
        F[:, _RIM_EXCESS, _RIM_EXCESS] = diag[:, None]
        ratio = x[:, _RIM_EXCESS] / floor[:, None]
        F[:, _RIM_EXCESS, MdsfState.ACCEL_BIAS] = np.where(inside[:, None], -dt * ratio, 0.0)

    def _accel_noise_into_excess(self, F: FloatArray, Q: FloatArray, accel_var: FloatArray) -> None:
        """The tick's accelerometer noise ``w`` moves each rim excess as it moves ``V1``
        (``Q`` (k, n, n) in place): ``e`` grows by ``ε·dt·w`` (minus its bias coupling,
        ``−F[e, b]``), ``V1`` by ``dt·w``, ``a1`` by ``w`` and the distance by ``dt²·w/2``,
        so ``Q += σ²_a·g·gᵀ`` over those rows. A GNSS correction of ``V1`` then corrects the
        excess's share of the same noise: without the cross terms a gravity leak that the
        GNSS takes out of ``V1`` stayed in ``e`` (slip read ``ε·∫δa·dt`` off)."""
        g_e = -F[:, _RIM_EXCESS, MdsfState.ACCEL_BIAS]  # (k, 2)
        k = g_e.shape[0]
        outer = (g_e[:, :, None] * g_e[:, None, :]).reshape(k, 4)
        cross = (g_e[:, :, None] * self._q_excess_shares).reshape(k, 6)
        vals = np.concatenate([outer, cross, cross], axis=1)
        Q[:, self._q_excess_rows, self._q_excess_cols] += accel_var[:, None] * vals

    def _anchor_slip(
        self, slots: IntArray, lost: BoolArray, speed: FloatArray, F: FloatArray, Q: FloatArray
    ) -> None:
        """Product mode, GNSS lost: each rim excess as a mean-reverting process about its last
        GNSS-anchored slip ratio (``F``, ``Q`` (k, n, n) in place).

        ``e' = φ·g·e + (1 − φ)·ε_a·V1``: ``ε_a = ε_0 + k·f/g`` the anchored slip at zero
        demand (:meth:`_set_slip_anchor`) plus the tyre model's slip at this tick's demand,
        held to a rolling wheel's range (``_OUTAGE_SLIP_RATIO_RANGE``, [−1, 1]: an anchor
        fused only while creeping, ``e/V1`` at a few cm/s, can be any size, and with a rim row
        pinning ``V1 + e`` the process would feed the speed's error back ×``|φ − (1 − φ)·ε_a|``
        a tick, above 1 for ``ε_a < −1``),
        ``φ = exp(−dt/outage_slip_tau_s)``, ``g`` the constant-slip growth; the added variance
        ``(1 − φ²)·(outage_slip_std·|V1|)²`` has the tyre's slip range as its stationary
        value. The bias state walks faster (``outage_bias_walk_mps2_per_sqrt_s``: it also
        carries the pitch error's gravity leak). The inertial speed's error grows without
        bound in an outage, the slip's does not: the rims then hold the speed.
        """
        cfg = self.config
        phi = math.exp(-self.dt_s / cfg.outage_slip_tau_s)
        keep = np.where(lost, phi, 1.0)[:, None]
        F[:, _RIM_EXCESS, _RIM_EXCESS] *= keep
        F[:, _RIM_EXCESS, MdsfState.ACCEL_BIAS] *= keep
        target = np.clip(
            self.slip_anchor[slots] + (self._demand_slip(slots) + self.step_level[slots])[:, None],
            *_OUTAGE_SLIP_RATIO_RANGE,
        )
        F[:, _RIM_EXCESS, MdsfState.V1] += (1.0 - keep) * target
        var_max = (cfg.outage_slip_std * np.maximum(speed, _SLIP_MIN_SPEED_MPS)) ** 2
        Q[:, _RIM_EXCESS, _RIM_EXCESS] += np.where(lost, (1.0 - phi * phi) * var_max, 0.0)[:, None]
        q_b = cfg.outage_bias_walk_mps2_per_sqrt_s**2 * self.dt_s
        Q[:, MdsfState.ACCEL_BIAS, MdsfState.ACCEL_BIAS] += np.where(lost, q_b, 0.0)

    def _outage_slip_steps(
        self,
        slots: IntArray,
        t: TickInputs,
        z: FloatArray,
        x_prior: FloatArray,
        up: _Updated,
        lost: BoolArray,
        rim_mps: FloatArray,
        rim_ok: BoolArray,
        rim_std_mps: FloatArray,
    ) -> BoolArray:
        """Product mode, GNSS lost: a slip step found in the window of the rims less the
        inertial speed (:func:`estimator.mdsf.outage_step.step_test`) moves the outage's slip
        level and takes back what the rims pushed into the speed and the bias since it
        (``up.x``, ``up.P`` in place). Returns the rows so changed, (k,).

        Per tick of an outage the window gets ``r = r̄W − ∫ā·dt − Δ_lever − ε_a·V1`` (``ε_a``
        the level :meth:`_anchor_slip` reverts to), ``V1`` and ``ωz``. A step ``δ`` (posterior
        mean, slip ratio) adds ``δ`` to both wheels' anchor, moves ``δ·V1`` from ``V1`` to
        both rim excesses, returns the bias to its value before the step and adds the step's
        variance along that move, ``P += σ²_δ·V1²·ddᵀ`` (``d`` −1 on ``V1``, +1 on each rim
        excess), and the bias's move squared to its variance. The window's ticks after the
        step lose ``δ·V1`` so the step is not found twice. The window also carries the tilt
        track's pitch and roll variance (``t.tilt_var``), the tilt columns' prior, and the
        variance of the rims' mean as the wheel front end gives it (``rim_std_mps``, scaled by
        ``wheel_noise_scale``), against which a step's speed change is weighed.
        """
        count = np.where(lost, self.step_count[slots], 0)
        integral = np.where(lost, self.step_inertial[slots], 0.0)
        a_in = np.where(
            t.imu_ok,
            z[:, MdsfObs.A1],
            x_prior[:, MdsfState.A1] + x_prior[:, MdsfState.ACCEL_BIAS],
        )
        integral = np.where(lost, integral + self.dt_s * a_in, 0.0)
        step_level = np.where(lost, self.step_level[slots], 0.0)
        new = self._step_window_tick(
            slots, t, up, integral, step_level, rim_mps, rim_ok, rim_std_mps
        )
        buf = self.step_buf[slots]
        buf[lost] = np.concatenate([buf[lost, :, 1:], new[lost, :, None]], axis=2)
        count = count + lost
        test = lost & (count >= self._step_ticks)
        found = np.zeros(slots.shape[0], dtype=bool)
        if test.any():
            fit = step_test(buf[test], self.dt_s, self._step_prior)
            rows = np.flatnonzero(test)[fit.found]
            found[rows] = True
            if rows.size:
                step_level[rows] += fit.delta[fit.found]
                self._take_step(rows, fit.delta[fit.found], fit.delta_var[fit.found], buf, up)
        self.step_buf[slots] = buf
        self.step_count[slots] = count
        self.step_level[slots] = step_level
        self.step_inertial[slots] = integral
        return found

    def _step_window_tick(
        self,
        slots: IntArray,
        t: TickInputs,
        up: _Updated,
        integral: FloatArray,
        step_level: FloatArray,
        rim_mps: FloatArray,
        rim_ok: BoolArray,
        rim_std_mps: FloatArray,
    ) -> FloatArray:
        """The tick's column of the step test's window, (k, len(StepBuf)) (channels
        :class:`~estimator.mdsf.outage_step.StepBuf`; ``integral`` the outage's ``∫ā·dt``,
        ``step_level`` the steps taken, each (k,))."""
        x = up.x
        v1 = x[:, MdsfState.V1]
        v_wheel = np.einsum("kmi,ki->km", up.H[:, _RIM, : MdsfState.ACCEL_BIAS], x[:, :4])
        both = rim_ok.all(axis=1)
        model_level = self.slip_anchor[slots].mean(axis=1) + self._demand_slip(slots)
        level = model_level + step_level
        rim_mean = np.where(rim_ok, rim_mps, 0.0).mean(axis=1)
        r = rim_mean - integral - (v_wheel.mean(axis=1) - v1) - level * v1
        k = slots.shape[0]
        tilt_var = t.tilt_var if t.tilt_var is not None else np.full((k, 2), np.nan)
        new = np.empty((k, len(StepBuf)))
        new[:, StepBuf.R] = np.where(both, r, 0.0)
        new[:, StepBuf.V1] = v1
        new[:, StepBuf.YAW] = x[:, MdsfState.OMEGA_Z]
        new[:, StepBuf.OK] = both
        new[:, StepBuf.BIAS] = x[:, MdsfState.ACCEL_BIAS]
        new[:, StepBuf.LEVEL] = model_level
        new[:, StepBuf.PITCH_VAR] = tilt_var[:, 0]
        new[:, StepBuf.ROLL_VAR] = tilt_var[:, 1]
        rim_var = self._rim_fit_var(rim_std_mps, rim_ok)
        new[:, StepBuf.RIM_VAR] = np.where(both, rim_var.sum(axis=1) / 4.0, 0.0)
        return new

    def _take_step(
        self,
        rows: IntArray,
        delta: FloatArray,
        delta_var: FloatArray,
        buf: FloatArray,
        up: _Updated,
    ) -> None:
        """Apply the steps ``delta`` (j,) found on ``rows`` of the step's arrays as
        :meth:`_outage_slip_steps` says (``buf``, ``up.x``, ``up.P`` in place)."""
        half = self._step_ticks // 2
        x = up.x[rows]
        v1 = x[:, MdsfState.V1]
        shift = delta * v1
        x[:, MdsfState.V1] -= shift
        x[:, _RIM_EXCESS] += shift[:, None]
        bias_before = buf[rows, StepBuf.BIAS, half - 1]
        bias_move = x[:, MdsfState.ACCEL_BIAS] - bias_before
        x[:, MdsfState.ACCEL_BIAS] = bias_before
        d = np.zeros((rows.size, self.n))
        d[:, MdsfState.V1] = -1.0
        d[:, _RIM_EXCESS] = 1.0
        P = up.P[rows] + (delta_var * v1 * v1)[:, None, None] * (d[:, :, None] * d[:, None, :])
        P[:, MdsfState.ACCEL_BIAS, MdsfState.ACCEL_BIAS] += bias_move * bias_move
        up.x[rows] = x
        up.P[rows] = P
        after = buf[rows, StepBuf.V1, half:]
        buf[rows, StepBuf.R, half:] -= delta[:, None] * after

    def _update(
        self,
        slots: IntArray,
        t: TickInputs,
        z: FloatArray,
        rd: FloatArray,
        x_pr: FloatArray,
        P_pr: FloatArray,
        init: BoolArray,
        rim_mps: FloatArray,
        rim_ok: BoolArray,
    ) -> _Updated:
        """The update: 1) the IMU rows; 2) GNSS speed, rim speeds and distance, gated against
        the stage-1 posterior so the tests see this tick's measured rates; 3) product mode, a
        zero-velocity update where both wheels stand. Each stage applies its rows one at a
        time (:func:`estimator.kalman.update_independent`)."""
        k, m = slots.shape[0], self.m
        H = self.H[slots]
        mask1 = np.zeros((k, m), dtype=bool)
        mask1[:, MdsfObs.A1] = t.imu_ok & (not self.product)
        mask1[:, MdsfObs.OMEGA_X] = t.imu_ok
        mask1[:, MdsfObs.OMEGA_Z] = t.imu_ok
        res1 = kalman.update_independent(x_pr, P_pr, z, H, rd, mask1, _STAGE1_ROWS, _UNIT_ROWS)
        x_1, P_1 = res1.x, res1.P
        y = z - np.einsum("kmi,ki->km", H, x_1)
        s = kalman.row_variances(H, P_1) + rd
        gated = np.zeros(k, dtype=bool)
        reacq = np.zeros(k, dtype=bool)
        inflated = np.zeros(k, dtype=bool)
        if self.product:
            gated, reacq = self._gate_gnss(slots, t, init, y, s, P_1)
            jumped = self._open_rim_jumps(slots, init, y, s, rim_ok, P_1)
            lost = self._gnss_lost(slots, t, init)
            # A jump on a tick without the gyro row stays open (see _bound_rim_excess).
            blind = jumped & ~t.imu_ok[:, None]
            bounded = self._bound_rim_excess(lost, rim_mps, rim_ok & ~blind, P_1)
            inflated = reacq | jumped.any(axis=1) | bounded
        use_vg = t.gnss_ok & ~gated
        mask2 = np.zeros((k, m), dtype=bool)
        mask2[:, MdsfObs.VG] = use_vg
        if self.product:
            mask2[:, _RIM] = rim_ok
            mask2[:, MdsfObs.DIST] = t.dist_ok & ~self._gate_distance(slots, t, init, y, s)
        stage2 = _STAGE2_ROWS_PRODUCT if self.product else _STAGE2_ROWS_PAPER
        res = kalman.update_independent(x_1, P_1, z, H, rd, mask2, stage2, _UNIT_ROWS)
        zupt = np.zeros(k, dtype=bool)
        x_new, P_new = res.x, res.P
        if self.product and self.config.zupt_speed_mps > 0:
            zupt, x_new, P_new = self._zero_velocity(
                slots, t, z, init, rim_mps, rim_ok, x_new, P_new
            )
        return _Updated(
            x_new, P_new, H, y, s, use_vg, gated, reacq, inflated, zupt, mask1, mask2, (res1, res)
        )

    def _gate_gnss(
        self,
        slots: IntArray,
        t: TickInputs,
        init: BoolArray,
        y: FloatArray,
        s: FloatArray,
        P_1: FloatArray,
    ) -> tuple[BoolArray, BoolArray]:
        """Product mode: chi-square gate of the GNSS speed; after ``reacquire_s`` of
        rejections the speed variance opens to the disagreement (``P_1`` in place) so the
        update follows GNSS. The gate's std has a floor ``hypot(gate_floor_mps,
        gate_floor_rel·|Vg|)`` (``Vg`` predicted): a speed that wandered by a share of itself
        must not lock GNSS out, and a 0.2 m/s outlier must not pass at a creep. The receiver's
        reported accuracy is in ``s`` through ``R``. Returns ``(gated, reacquired)``, (k,)."""
        cfg = self.config
        stamp = t.stamp_ns
        y_vg = y[:, MdsfObs.VG]
        speed = np.abs(nan_to_num(t.z[:, MdsfObs.VG] - y_vg))
        s_gate = s[:, MdsfObs.VG] + cfg.gate_floor_mps**2 + (cfg.gate_floor_rel * speed) ** 2
        gated = t.gnss_ok & init & ~(y_vg * y_vg <= cfg.gate_chi2 * s_gate)
        since = self.gated_since_ns[slots]
        since = np.where(gated & (since < 0), stamp, since)
        reacq = gated & (stamp - since >= round(cfg.reacquire_s * 1e9))
        gated &= ~reacq
        self.gated_since_ns[slots] = np.where(gated, since, -1)
        P_1[:, MdsfState.V1, MdsfState.V1] += np.where(reacq, y_vg * y_vg, 0.0)
        return gated, reacq

    def _open_rim_jumps(
        self,
        slots: IntArray,
        init: BoolArray,
        y: FloatArray,
        s: FloatArray,
        rim_ok: BoolArray,
        P_1: FloatArray,
    ) -> BoolArray:
        """Product mode: a rim speed more than ``slip_jump_sigma`` off its prediction while the
        accelerometer saw no matching acceleration means the slip itself changed (soil, wet
        patch): that rim excess opens by the unexplained part of the innovation (``P_1`` in
        place). Also feeds the running rim innovations. Returns the wheels opened, (k, 2):
        the outage's bound (:meth:`_bound_rim_excess`) leaves them open on a tick without the
        gyro row."""
        cfg = self.config
        y_rim = y[:, _RIM]
        s_rim = s[:, _RIM]
        if cfg.rim_drift_tau_s > 0:
            self._track_rim_innovation(slots, y_rim, s_rim, rim_ok & init[:, None])
        big = rim_ok & init[:, None] & (y_rim * y_rim > cfg.slip_jump_sigma**2 * s_rim)
        P_1[:, _RIM_EXCESS, _RIM_EXCESS] += np.where(big, y_rim * y_rim - s_rim, 0.0)
        return np.asarray(big)

    def _gnss_lost(self, slots: IntArray, t: TickInputs, init: BoolArray) -> BoolArray:
        """Rows whose last fused GNSS speed is older than ``gnss_timeout_s``, (k,)."""
        since_s = (t.stamp_ns - self.last_fused_ns[slots]) * _NS
        return init & (since_s > self.config.gnss_timeout_s)

    def _bound_rim_excess(
        self, lost: BoolArray, rim_mps: FloatArray, rim_ok: BoolArray, P_1: FloatArray
    ) -> BoolArray:
        """Product mode, GNSS lost: each rim excess's std held within the slip range
        ``σ_max = outage_slip_std·|r·W|`` (``P_1`` (k, n, n) in place). Returns the rows
        whose ``P_1`` it changed, (k,).

        ``P ← D·P·D`` with ``D = diag(1, …, c_e, …)``, ``c_e = min(1, σ_max/σ_e)``: the
        variance of ``e`` is brought to the bound and its covariances scaled with it, so ``P``
        stays positive semi-definite and the correlations are kept. A slip's error is bounded
        by its tyre's range while the inertial speed's grows without bound, so a lasting rim
        disagreement then moves ``V1`` (and the bias), not the slip. A wheel whose rim jumped
        on a tick without the gyro row (:meth:`_open_rim_jumps`; ``rim_ok`` false for it) is
        left open: bound, the jump's innovation, many times the bounded ``S``, would be forced
        into ``ωz`` as well, which the rims alone cannot tell from the two excesses'
        difference. With the gyro row ``ωz`` is held and the jump moves ``V1``, as a lasting
        disagreement should.
        """
        share = self.config.outage_slip_std
        rows = lost[:, None] & rim_ok
        if share <= 0 or not rows.any():
            return np.zeros(lost.shape[0], dtype=bool)
        var_max = (share * np.where(rim_ok, rim_mps, 0.0)) ** 2 + 1e-6
        var_e = P_1[:, _RIM_EXCESS, _RIM_EXCESS]
        c = np.where(rows & (var_e > var_max), np.sqrt(var_max / np.maximum(var_e, 1e-30)), 1.0)
        P_1[:, _RIM_EXCESS, :] *= c[:, :, None]
        P_1[:, :, _RIM_EXCESS] *= c[:, None, :]
        return np.asarray((c < 1.0).any(axis=1))

    def _gate_distance(
        self, slots: IntArray, t: TickInputs, init: BoolArray, y: FloatArray, s: FloatArray
    ) -> BoolArray:
        """Product mode: the distance row gated as the speed (a position jump: wrong fix); the
        next fix then starts a new chain. Returns the rows gated, (k,)."""
        cfg = self.config
        y_d = y[:, MdsfObs.DIST]
        s_d = s[:, MdsfObs.DIST] + cfg.gnss_distance_gate_floor_m**2
        d_gated = t.dist_ok & init & ~(y_d * y_d <= cfg.gate_chi2 * s_d)
        self.dist_gated[slots] = np.where(t.dist_ok, d_gated, self.dist_gated[slots])
        return d_gated

    def _zero_velocity(
        self,
        slots: IntArray,
        t: TickInputs,
        z: FloatArray,
        init: BoolArray,
        rim_mps: FloatArray,
        rim_ok: BoolArray,
        x: FloatArray,
        P: FloatArray,
    ) -> tuple[BoolArray, FloatArray, FloatArray]:
        """Product mode: ``V0 = 0`` fused where both rim speeds are at most ``zupt_speed_mps``
        and GNSS, if any, agrees. Returns ``(zupt (k,), x, P)``."""
        k = slots.shape[0]
        zs = self.config.zupt_speed_mps
        zupt = (
            init
            & rim_ok.all(axis=1)
            & (np.abs(np.where(rim_ok, rim_mps, np.inf)) <= zs).all(axis=1)
            & (~t.gnss_ok | (np.abs(z[:, MdsfObs.VG]) <= 2.0 * zs))
        )
        if not zupt.any():
            return zupt, x, P
        resz = kalman.update_independent(
            x,
            P,
            np.zeros((k, 1)),
            self.v0_row[slots][:, None, :],
            np.full((k, 1), (0.5 * zs) ** 2),
            zupt[:, None],
        )
        return zupt, resz.x, resz.P

    def _adapt_gnss_noise(
        self, slots: IntArray, fused: BoolArray, y_vg: FloatArray, s_vg: FloatArray, rd: FloatArray
    ) -> None:
        """Running estimate of the GNSS speed noise from accepted innovations: ``y² − H·P·Hᵀ``
        weighted by ``gnss_noise_adapt`` (in place)."""
        hph = s_vg - rd[:, MdsfObs.VG]
        est = self.gnss_noise_var[slots]
        b = self.config.gnss_noise_adapt
        self.gnss_noise_var[slots] = np.where(fused, (1 - b) * est + b * (y_vg * y_vg - hph), est)

    def _start(
        self,
        slots: IntArray,
        t: TickInputs,
        z: FloatArray,
        init: BoolArray,
        broken: BoolArray,
        up: _Updated,
        rim_mps: FloatArray,
        rim_ok: BoolArray,
    ) -> _Started:
        """(Re)initialise rows (``up.x``, ``up.P`` replaced where so).

        A vehicle starts at its first GNSS speed (``V1`` by eq. (1) less the lever-arm terms);
        without GNSS, after waiting ``gnss_timeout_s`` for it, from the mean rim speed
        (degraded). A state gone non-finite, with a negative variance or a speed variance over
        ``max_speed_var_mps2`` has diverged and restarts at the GNSS speed or the reference
        speed. Both flag RESET.
        """
        cfg = self.config
        H = up.H
        imu = t.imu_ok
        v1_from_gnss = z[:, MdsfObs.VG] - (
            H[:, MdsfObs.VG, MdsfState.OMEGA_X] * np.where(imu, z[:, MdsfObs.OMEGA_X], 0.0)
            + H[:, MdsfObs.VG, MdsfState.OMEGA_Z] * np.where(imu, z[:, MdsfObs.OMEGA_Z], 0.0)
        )
        start = ~init & t.gnss_ok
        n_rim = rim_ok.sum(axis=1)
        rim_mean = np.where(
            n_rim > 0, np.where(rim_ok, rim_mps, 0.0).sum(axis=1) / np.maximum(n_rim, 1), np.nan
        )
        from_wheels = ~init & ~t.gnss_ok & (n_rim > 0)
        start_wheels = from_wheels & (self._wheel_start_allowed(slots) | broken)
        sel = start | start_wheels
        flags = np.zeros(slots.shape[0], dtype=np.int32)
        if sel.any():
            v_start = np.where(start, v1_from_gnss, nan_to_num(rim_mean))
            self._restart_rows(slots, z, imu, v_start, rim_ok, sel, up)
            flags |= np.where(sel, int(_F.RESET), 0).astype(np.int32)
        diag = np.diagonal(up.P, axis1=1, axis2=2)
        diverged = init & (
            ~np.isfinite(up.x).all(axis=1)
            | ~np.isfinite(up.P).all(axis=(1, 2))
            | (diag < 0).any(axis=1)
            | (diag[:, MdsfState.V1] > cfg.max_speed_var_mps2)
        )
        if diverged.any():
            ref_v = self.ref_x[slots, RefState.V]
            v_re = np.where(t.gnss_ok, v1_from_gnss, np.where(np.isfinite(ref_v), ref_v, 0.0))
            self._restart_rows(slots, z, imu, v_re, rim_ok, diverged, up)
            flags |= np.where(diverged, int(_F.RESET), 0).astype(np.int32)
        return _Started(sel, diverged, rim_mean, flags)

    def _restart_rows(
        self,
        slots: IntArray,
        z: FloatArray,
        imu_ok: BoolArray,
        v1: FloatArray,
        rim_ok: BoolArray,
        rows: BoolArray,
        up: _Updated,
    ) -> None:
        """Replace ``up.x``, ``up.P`` of ``rows`` by the initial state at ``v1``."""
        x0, p0 = self._initial_state(slots, z, imu_ok, v1, rim_ok)
        up.x = np.where(rows[:, None], x0, up.x)
        up.P = np.where(rows[:, None, None], p0, up.P)

    def _reference(
        self,
        slots: IntArray,
        t: TickInputs,
        z: FloatArray,
        up: _Updated,
        st: _Started,
        rim_ok: BoolArray,
        degraded: BoolArray,
    ) -> tuple[FloatArray, tuple[FloatArray, FloatArray, FloatArray]]:
        """The reference-speed filter (``method.md`` §3): tracks ``V0`` while GNSS is good,
        carries the speed from the accelerometer and the slip-corrected wheel speed while it
        is lost. Paper mode has no wheel states: while degraded its speed is handed to the
        MDSF state (``up.x``, ``up.P`` in place), so GNSS resumes without a jump. Returns
        ``(V0 (k,), (ref_x, ref_P, ref_aux))``."""
        k = slots.shape[0]
        v0_row = self.v0_row[slots]
        v0 = np.einsum("ki,ki->k", v0_row, up.x)
        v0_var = kalman.row_variances(v0_row[:, None, :], up.P)[:, 0]
        a_ref = z[:, MdsfObs.A1] - (up.x[:, MdsfState.ACCEL_BIAS] if self.product else 0.0)
        rx, rP, raux, _ = reference_step(
            self.ref_x[slots],
            self.ref_P[slots],
            self.ref_aux[slots],
            accel_mps2=np.where(t.imu_ok, a_ref, np.nan),
            dt_s=self.dt_s,
            speed_ref_mps=np.where(degraded, np.nan, v0),
            speed_ref_var=v0_var,
            rim_speed_mps=st.rim_mean,
            config=self.reference,
        )
        restart = st.started | st.diverged
        if restart.any():
            rx = np.where(restart[:, None], np.stack([v0, np.zeros(k)], axis=1), rx)
        if not self.product and degraded.any():
            self._hand_over(up.x, up.P, rx, rP, v0, degraded)
            v0 = np.einsum("ki,ki->k", v0_row, up.x)  # V1 moved, V0 with it (output)
        return v0, (rx, rP, raux)

    def _store(
        self,
        slots: IntArray,
        x: FloatArray,
        P: FloatArray,
        up: _Updated,
        now_init: BoolArray,
        last_fused_ns: IntArray,
        ref: tuple[FloatArray, FloatArray, FloatArray],
    ) -> None:
        """Write the step's state back to the slots: the posterior where the filter runs, the
        prior state ``x``, ``P`` where it still waits for its start."""
        if now_init.all():  # the usual step: every row runs
            self.x[slots], self.P[slots] = up.x, up.P
        else:
            self.x[slots] = np.where(now_init[:, None], up.x, x)
            self.P[slots] = np.where(now_init[:, None, None], up.P, P)
        self.initialized[slots] = now_init
        self.last_fused_ns[slots] = last_fused_ns
        self.ref_x[slots], self.ref_P[slots], self.ref_aux[slots] = ref

    def _set_slip_anchor(self, slots: IntArray, x: FloatArray, fused: BoolArray) -> None:
        """Where GNSS speed was fused, the least-squares slip ratio at zero demand of
        ``e − k·(f/g)·V1 = ε_0·V1`` over the recent drive (forgetting with
        ``outage_anchor_tau_s``), (k, 2): weighted by ``V1²``, so creeping and standing add
        little. An outage's slip reverts to it (:meth:`_anchor_slip`)."""
        lam = math.exp(-self.dt_s / self.config.outage_anchor_tau_s)
        v1 = x[:, MdsfState.V1]
        e0 = x[:, _RIM_EXCESS] - (self._demand_slip(slots) * v1)[:, None]
        stats = self.anchor_stats[slots]
        fresh = np.concatenate([e0 * v1[:, None], (v1 * v1)[:, None]], axis=1)
        stats = np.where(fused[:, None], lam * stats + (1.0 - lam) * fresh, stats)
        self.anchor_stats[slots] = stats
        vv = stats[:, 2:]
        self.slip_anchor[slots] = np.where(vv > 1e-6, stats[:, :2] / np.maximum(vv, 1e-6), 0.0)

    def _demand_slip(self, slots: IntArray) -> FloatArray:
        """The tyre model's slip ratio at the low-passed demand, ``k·f/g`` (k,); 0 without the
        model (``slip_per_demand = 0``) or before any force."""
        if self.config.slip_per_demand <= 0:
            return np.zeros(slots.shape[0])
        f = nan_to_num(self.force_model[slots])
        return np.asarray(self.tyre_gain(slots) * f / GRAVITY_MPS2)

    def _outputs(
        self,
        slots: IntArray,
        x: FloatArray,
        P: FloatArray,
        H: FloatArray,
        v0: FloatArray,
        emit: BoolArray,
        flags: npt.NDArray[np.int32],
        model: TickModel,
    ) -> StepOutput:
        """Outputs ``H1·x`` (eq. (6)) with their std, and in product mode the rim rows of the
        posterior: the wheel fit fused with the accelerometer-driven prediction of ``V`` and
        the rim excess (what the slip is computed from)."""
        H1 = self.H1[slots]
        z1 = np.einsum("koi,ki->ko", H1, x)
        z1_std = np.sqrt(np.maximum(kalman.row_variances(H1, P), 0.0))
        rim_post = rim_std_post = rim_cov = None
        if self.product:
            h_rim = H[:, _RIM]
            h_v = H1[:, (MdsfOut.VL, MdsfOut.VR)]
            rim_post = np.einsum("kmi,ki->km", h_rim, x)
            ph = np.einsum("kij,kmj->kmi", P, h_rim)
            rim_std_post = np.sqrt(np.maximum(np.einsum("kmi,kmi->km", h_rim, ph), 0.0))
            rim_cov = np.einsum("kmi,kmi->km", h_v, ph)
        return StepOutput(
            emit=emit,
            vg=z1[:, MdsfOut.VG],
            v1=x[:, MdsfState.V1],
            v0=v0,
            vl=z1[:, MdsfOut.VL],
            vr=z1[:, MdsfOut.VR],
            vg_std=z1_std[:, MdsfOut.VG],
            vl_std=z1_std[:, MdsfOut.VL],
            vr_std=z1_std[:, MdsfOut.VR],
            accel=x[:, MdsfState.A1],
            pitch_rate=x[:, MdsfState.OMEGA_X],
            yaw_rate=x[:, MdsfState.OMEGA_Z],
            flags=flags,
            model=model,
            rim=rim_post,
            rim_std=rim_std_post,
            rim_ground_cov=rim_cov,
        )

    def _track_rim_innovation(
        self, slots: IntArray, y_rim: FloatArray, s_rim: FloatArray, ok: BoolArray
    ) -> None:
        """Running mean of each rim row's innovation and of its variance (in place).

        ``rim_innov[slot, wheel] = [mean, var_of_mean]``: exponential mean with time constant
        ``rim_drift_tau_s`` of the innovation ``y`` (against the stage-1 posterior), and the
        variance that mean would have if the innovations were white with variance ``S``.
        Wheels without a rim speed this tick keep theirs.
        """
        dt = self.dt_s
        b = dt / (self.config.rim_drift_tau_s + dt)
        st = self.rim_innov[slots]
        mean = np.where(ok, (1 - b) * st[:, :, 0] + b * y_rim, st[:, :, 0])
        var = np.where(ok, (1 - b) ** 2 * st[:, :, 1] + b * b * s_rim, st[:, :, 1])
        st[:, :, 0] = mean
        st[:, :, 1] = var
        self.rim_innov[slots] = st

    def _rim_drift_noise(self, slots: IntArray, gnss_lost: BoolArray | None = None) -> FloatArray:
        """Extra rim-excess process noise per wheel from persistent rim innovations, (k, 2).

        The running mean ``m`` of a rim row's innovation (:meth:`_track_rim_innovation`)
        beyond ``rim_drift_sigma`` of its white-noise spread means the slip moves faster than
        the model lets it; the excess ``m² − σ²·var`` is let into the rim excess over
        ``rim_drift_tau_s`` [(m/s)² per tick].

        That reading needs the speed anchored to the ground. While GNSS is lost
        (``gnss_lost``, shape (k,)) a persistent rim innovation is as much the integrated
        accelerometer error (gravity leaking through the drifting pitch, bias) as a slip
        change, and the rows cannot tell them apart; only the share
        ``outage_rim_drift_share`` of the excess goes to the rim excess, so the slip state
        does not soak up the speed's drift.
        """
        cfg = self.config
        st = self.rim_innov[slots]
        excess = st[:, :, 0] ** 2 - cfg.rim_drift_sigma**2 * st[:, :, 1]
        q = np.maximum(excess, 0.0) * (self.dt_s / cfg.rim_drift_tau_s)
        if gnss_lost is not None:
            q = q * np.where(gnss_lost, cfg.outage_rim_drift_share, 1.0)[:, None]
        return q

    def tyre_gain(self, slots: IntArray) -> FloatArray:
        """Slope of the traction curve ``k = dε/d(f/g)`` in force for each slot, shape (k,).

        ``ε = (r·W − V)/V`` is the slip ratio of the rim excess, ``f`` the low-passed forward
        specific force (acceleration plus slope: what the tyres transmit beyond rolling
        resistance and drawbar, which only shift ``ε``). A weighted least-squares line of ``ε``
        on ``f/g`` over the recent drive (:meth:`_learn_tyre_gain`), shrunk toward the
        configured ``slip_per_demand`` with the weight ``tyre_gain_prior`` (so a drive without
        changes of demand keeps the prior), clipped to ``tyre_gain_range``. Without learning
        (``tyre_gain_tau_s = 0``) the configured value.
        """
        cfg = self.config
        k0 = cfg.slip_per_demand
        if cfg.tyre_gain_tau_s <= 0:
            return np.full(slots.shape[0], k0)
        st = self.tyre_stats[slots]
        w = np.maximum(st[:, _TyreStat.W], 1e-12)
        sxx = st[:, _TyreStat.XX] - st[:, _TyreStat.X] ** 2 / w
        sxy = st[:, _TyreStat.XY] - st[:, _TyreStat.X] * st[:, _TyreStat.Y] / w
        lam = cfg.tyre_gain_prior
        k = (np.maximum(sxy, -1e9) + lam * k0) / (np.maximum(sxx, 0.0) + lam)
        lo, hi = cfg.tyre_gain_range
        return np.asarray(np.clip(k, lo * k0, hi * k0))

    def _learn_tyre_gain(
        self,
        slots: IntArray,
        t: TickInputs,
        x_post: FloatArray,
        H: FloatArray,
        rim_mps: FloatArray,
        rim_ok: BoolArray,
        fused: BoolArray,
    ) -> None:
        """Add this tick's ``(f/g, ε)`` pair to the tyre-gain regression (in place).

        Only ticks with a fused GNSS speed (the speed, hence ``ε``, is referenced to the ground)
        and both rim speeds, while moving faster than ``2·_SLIP_MIN_SPEED_MPS``; ``ε`` is the
        mean of both wheels' measured rim speed over the filtered contact-point speed. Old
        pairs fade with ``tyre_gain_tau_s``.
        """
        cfg = self.config
        v_wheel = np.einsum("kmi,ki->km", H[:, _RIM, : MdsfState.ACCEL_BIAS], x_post[:, :4])
        speed = 0.5 * (v_wheel[:, 0] + v_wheel[:, 1])
        f = self.force_model[slots]
        ok = (
            fused
            & rim_ok.all(axis=1)
            & (speed > 2.0 * _SLIP_MIN_SPEED_MPS)
            & np.isfinite(f)
            & t.imu_ok
        )
        with np.errstate(invalid="ignore", divide="ignore"):
            eps = np.where(
                ok, (np.where(rim_ok, rim_mps, 0.0) - v_wheel).sum(axis=1) / (2.0 * speed), 0.0
            )
        x = np.where(ok, f / GRAVITY_MPS2, 0.0)
        decay = math.exp(-self.dt_s / cfg.tyre_gain_tau_s)
        st = self.tyre_stats[slots]
        w = ok.astype(np.float64)
        st *= np.where(ok, decay, 1.0)[:, None]
        st[:, _TyreStat.W] += w
        st[:, _TyreStat.X] += w * x
        st[:, _TyreStat.Y] += w * eps
        st[:, _TyreStat.XX] += w * x * x
        st[:, _TyreStat.XY] += w * x * eps
        self.tyre_stats[slots] = st

    def _model_demand_change(self, slots: IntArray, t: TickInputs) -> FloatArray:
        """Change of the low-passed forward specific force at the axle over this tick, (k,)
        [m/s²] (:func:`axle_force_fwd`)."""
        dt = self.dt_s
        a = dt / (self.config.slip_model_tau_s + dt)
        f_new = axle_force_fwd(t)
        old = self.force_model[slots]
        fresh = ~np.isfinite(old)
        new = np.where(fresh, f_new, np.where(np.isfinite(f_new), old + a * (f_new - old), old))
        self.force_model[slots] = new
        return np.where(fresh, 0.0, nan_to_num(new - old))

    def _demand_change(self, slots: IntArray, t: TickInputs, accel_var: FloatArray) -> FloatArray:
        """Growth of the squared change of traction demand over this tick, (k,) [(m/s²)²].

        The forward specific force as the IMU reads it (acceleration plus slope) is low-passed fast
        (``force_filter_tau_s``) and slow (5×); their difference ``D`` is the recent change of
        demand. The IMU's, not the axle's that the tyre model's mean follows
        (:func:`axle_force_fwd`): what a swaying cab adds at the IMU (``h0·ω̇x``, ``g·sinθ`` of the
        sway) is not the ground's, but the tick's lever term is not known well enough to take it
        out, so it opens the rim excess's variance. Its variance under white accelerometer noise is
        known, so only the excess over two sigma counts. The slip follows the demand as it changes
        (the tyre settles within a relaxation length, a fraction of a second), so the tyre model's
        error grows while the demand moves, not after: this tick adds ``d(D²) = 2·D·|ΔF|`` with
        ``ΔF`` the fast low-pass's move over the tick, and a whole change ``D`` adds ``D²`` (the rim
        excess then opens by ``slip_demand_gain·|V|·D/g`` in std), so it stops opening once the
        demand has settled, where the wheels can hold the speed again.
        """
        dt = self.dt_s
        tau = self.config.force_filter_tau_s
        a1 = dt / (tau + dt)
        a2 = dt / (5.0 * tau + dt)
        f_new = np.where(t.imu_ok & np.isfinite(t.force_fwd), t.force_fwd, np.nan)
        fast_old = self.force_fast[slots]
        slow = self.force_slow[slots]
        fresh = ~np.isfinite(fast_old)
        fast = np.where(
            fresh,
            f_new,
            np.where(np.isfinite(f_new), fast_old + a1 * (f_new - fast_old), fast_old),
        )
        slow = np.where(
            fresh, f_new, np.where(np.isfinite(f_new), slow + a2 * (f_new - slow), slow)
        )
        self.force_fast[slots] = fast
        self.force_slow[slots] = slow
        var_d = accel_var * (a1 / (2 - a1) + a2 / (2 - a2) - 2 * a1 * a2 / (a1 + a2 - a1 * a2))
        d = nan_to_num(fast - slow)
        excess = np.sqrt(np.maximum(d * d - 4.0 * var_d, 0.0))
        moved = np.where(fresh, 0.0, np.abs(nan_to_num(fast - fast_old)))
        return 2.0 * excess * moved

    @staticmethod
    def _hand_over(
        x: FloatArray, P: FloatArray, rx: FloatArray, rP: FloatArray, v0: FloatArray, sel: BoolArray
    ) -> None:
        """Put the reference speed into ``V1`` (in place) for the rows in ``sel``.

        ``V1`` moves by the difference between the reference speed and ``V0``; its variance
        becomes the reference's and its covariances are scaled down with its std.
        """
        v1_ref = rx[:, RefState.V] - (v0 - x[:, MdsfState.V1])
        x[:, MdsfState.V1] = np.where(sel, v1_ref, x[:, MdsfState.V1])
        pv = rP[:, RefState.V, RefState.V]
        old = np.maximum(P[:, MdsfState.V1, MdsfState.V1], 1e-30)
        scale = np.minimum(np.sqrt(np.maximum(pv, 0.0) / old), 1.0)
        row = P[:, MdsfState.V1, :] * scale[:, None]
        row[:, MdsfState.V1] = pv
        P[:, MdsfState.V1, :] = np.where(sel[:, None], row, P[:, MdsfState.V1, :])
        P[:, :, MdsfState.V1] = np.where(sel[:, None], row, P[:, :, MdsfState.V1])

    def _wheel_start_allowed(self, slots: IntArray) -> BoolArray:
        """A vehicle may start from wheel speeds once it waited ``gnss_timeout_s`` for GNSS."""
        waited = self.counts[slots, Counter.WAITING_TICKS] * self.dt_s
        return np.asarray(waited >= self.config.gnss_timeout_s)
