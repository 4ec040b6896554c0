"""Batched MDSF engine and the fleet estimator the server drives (``name = "mdsf"``).

Two layers:

:class:`MdsfEngine`
    Holds every vehicle's filter state in slot arrays (``x (cap, n)``, ``P (cap, n, n)`` with
    ``n`` = 4 in paper mode, 8 in product mode; per-vehicle ``F``, ``H``, ``H1``, ``Q``) and
    steps any subset of vehicles with a few calls to the pure functions of
    :mod:`estimator.kalman`: predict (accelerometer-driven in product mode), update of the IMU
    rows, chi-square gate of the GNSS speed and distance, update of GNSS speed, rim speeds and
    RTK distance, divergence reset, reference-speed filter (§3). Each step also returns what it
    used (:class:`TickModel`: matrices, masks, NIS) for diagnostics and tests.

:class:`MdsfFleet`
    Implements :class:`estimator.base.FleetEstimator`. One fleet front end
    (:class:`estimator.mdsf.frontend.FleetFrontEnd`, state in arrays by engine slot) buffers every
    vehicle's measurements and, on :meth:`MdsfFleet.advance`, turns those of all due vehicles
    into per-tick filter inputs with a number of numpy calls that does not grow with the fleet:
    IMU averaged over each tick window (gravity removed with the pitch, gyro biases learnt
    against the GNSS attitude), GNSS speed by eq. (1) moved to the tick by its time stamp,
    along-track distance from the RTK positions, wheel speeds of all vehicles that share the
    ticks fitted in one call (:meth:`estimator.wheel_speed.WheelBank.query`). The engine steps
    round by round: round ``r`` is the ``r``-th due tick of every vehicle that has one, all in
    one batched call.
    Slip, positions and attitude are computed for all rows at once afterwards.

Ticks sit on a grid of ``tick_ns``: multiples of it since the epoch by default, or moved by
:meth:`MdsfFleet.align_ticks` (the server puts a vehicle's ticks on the end of its first IMU
batch, so a tick is computed as soon as the batch holding it arrives). A row at ``t`` uses only
measurements stamped at or before ``t`` (rows do not depend on how data was batched, nor on the
other vehicles of a call; tested). A vehicle's first row is the first
tick with a usable GNSS speed (or, after ``gnss_timeout_s`` without GNSS, with wheel speeds,
flagged DEGRADED). Nothing here raises on NaN/inf: bad parts are skipped and counted
(:meth:`MdsfFleet.counters`); a filter whose state goes non-finite or whose speed variance
explodes is re-initialised and the row flagged RESET.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
import numpy.typing as npt

from estimator import kalman
from estimator._arrays import nan_to_num
from estimator._slots import grow_slot_array
from estimator.base import Pushed
from estimator.config import VehicleConfig
from estimator.dead_reckoning import DeadReckoning, DeadReckoningConfig
from estimator.mdsf.frontend import FleetFrontEnd, FleetTicks, TickInputs
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
from estimator.reference_speed import RefAux, ReferenceSpeedConfig, RefState, reference_step
from estimator.slip import fit_span_s, slip_pct, unsettled
from estimator.types import ESTIMATE_DTYPE, EstimateFlag, empty_estimates
from estimator.wheel_speed import WheelSpeedConfig

__all__ = ["Counter", "MdsfEngine", "MdsfFleet", "StepOutput", "TickInputs", "TickModel"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

_NS = 1e-9
_SLIP_MIN_SPEED_MPS = 0.5
"""Speed floor of the constant-slip-ratio growth of the rim excess."""
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


# counters(): each counter's key and column, in declaration order
_COUNTER_KEYS = tuple(c.name.lower() for c in Counter)
_COUNTER_COLUMNS = np.array(list(Counter), dtype=np.intp)

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
_TICK_FIELDS = TickInputs.__slots__
_STEP_COLS = (
    "vg",
    "v1",
    "v0",
    "vl",
    "vr",
    "vg_std",
    "vl_std",
    "vr_std",
    "accel",
    "pitch_rate",
    "yaw_rate",
)
"""Per-row outputs of :class:`StepOutput` that go into the estimate rows."""


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
    R : ndarray, shape (k, m, m)
        Measurement noise.
    mask1, mask2 : ndarray, shape (k, m), bool
        Rows of the first (IMU) and second (GNSS speed, rim speeds) update stage.
    inflated : ndarray, shape (k,), bool
        The covariance was changed between the stages (GNSS re-acquired or a slip jump).
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
    R: FloatArray
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
        grow("dist_gated", (), False)
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
    dist_gated: BoolArray
    ref_x: FloatArray
    ref_P: FloatArray  # noqa: N815 (covariance, as P)
    ref_aux: FloatArray
    counts: IntArray

    def add(self, vehicle: VehicleConfig) -> int:
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
        self.dist_gated[s] = False
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
        cfg = self.config
        k = slots.shape[0]
        n, m = self.n, self.m
        dt = self.dt_s
        stamp = t.stamp_ns
        rim_ok = np.isfinite(rim_mps) & np.isfinite(rim_std_mps)
        z = np.zeros((k, m))
        z[:, :N_OBS_PAPER] = np.where(np.isfinite(t.z), t.z, 0.0)
        if self.product:
            z[:, _RIM] = np.where(rim_ok, rim_mps, 0.0)
            z[:, MdsfObs.DIST] = np.where(t.dist_ok, t.dist_m, 0.0)
        # rows gathered by an index array are copies: the working state of this step
        H = self.H[slots]
        x = self.x[slots]
        P = self.P[slots]
        init = self.initialized[slots]
        flags = np.zeros(k, dtype=np.int32)
        # A state that is already broken (non-finite) cannot be predicted: start it afresh.
        broken = init & ~(np.isfinite(x).all(axis=1) & np.isfinite(P).all(axis=(1, 2)))
        if broken.any():
            x = np.where(broken[:, None], 0.0, x)
            P = np.where(broken[:, None, None], np.eye(n), P)
            init &= ~broken
            self.counts[slots, Counter.RESETS] += broken
        gnss_ok = t.gnss_ok.copy()

        # Adaptive GNSS noise: receiver/config value is the floor, innovations can raise it.
        r_gnss = np.maximum(t.gnss_var, self.gnss_noise_var[slots])
        accel_var = np.where(t.imu_ok, t.accel_var, 1.0)
        gyro_var = np.where(t.imu_ok, t.gyro_var, 1.0)
        rd = np.zeros((k, m))
        rd[:, MdsfObs.VG] = r_gnss
        rd[:, MdsfObs.A1] = accel_var
        rd[:, MdsfObs.OMEGA_X] = gyro_var
        rd[:, MdsfObs.OMEGA_Z] = gyro_var
        if self.product:
            rd[:, _RIM] = np.where(
                rim_ok,
                (cfg.wheel_noise_scale * rim_std_mps) ** 2
                + (cfg.rim_texture_rel * np.where(rim_ok, rim_mps, 0.0)) ** 2
                + 1e-6,
                1.0,
            )
            rd[:, MdsfObs.DIST] = np.where(t.dist_ok, t.dist_var, 1.0)
        R = np.zeros((k, m, m))
        R.reshape(k, m * m)[:, :: m + 1] = rd  # the diagonals

        # -- predict ------------------------------------------------------------------------
        Q = self.Q_base[slots]
        u: FloatArray | None = None
        if self.product:
            a_in = np.where(
                t.imu_ok, z[:, MdsfObs.A1], x[:, MdsfState.A1] + x[:, MdsfState.ACCEL_BIAS]
            )
            u = np.zeros((k, n))
            u[:, MdsfState.V1] = dt * a_in
            u[:, MdsfState.A1] = a_in
            # The acceleration noise drives V1 and a1; the distance integrates the speed:
            # D' = D + dt·V1 + dt²·(ā − b)/2, so the tick's acceleration noise reaches it
            # through dt²/2 (correlated with V1 and a1). One indexed add: (row, column, factor).
            half = 0.5 * dt * dt
            D, V1 = MdsfState.DIST, MdsfState.V1
            u[:, D] = half * a_in
            Q[:, self._q_accel_rows, self._q_accel_cols] += accel_var[:, None] * self._q_accel
            # A new chain of RTK positions (or one after a gated distance) has its own origin:
            # the predicted distance is moved onto the measured one and opened, so the chain's
            # offset carries no information on the speed.
            new_chain = t.dist_ok & (t.dist_restart | self.dist_gated[slots])
            d_pred = x[:, D] + dt * x[:, V1] - half * x[:, MdsfState.ACCEL_BIAS] + half * a_in
            u[:, D] += np.where(new_chain, z[:, MdsfObs.DIST] - d_pred, 0.0)
            Q[:, D, D] += np.where(new_chain, _DIST_OPEN_VAR_M2, 0.0)
            # Rim excess e = r·W − V: at constant slip ratio it scales with the speed,
            # e' = e·(1 + dt·ā/V); on top, slip wanders with soil and load and moves when the
            # traction demand (forward specific force) changes, while it changes: a change D of
            # demand adds (gain·V·D/g)² in all (:meth:`_demand_change`).
            speed = np.abs(x[:, MdsfState.V1])
            d2 = self._demand_change(slots, t, accel_var)
            # Without GNSS only ``outage_demand_share`` of it (the tyre model carries the rest).
            lost = init & ((stamp - self.last_fused_ns[slots]) * _NS > cfg.gnss_timeout_s)
            d2 = d2 * np.where(lost, cfg.outage_demand_share, 1.0)
            q_e = (cfg.rim_excess_walk_rel_per_sqrt_s * speed) ** 2 * dt + (
                cfg.slip_demand_gain * speed / GRAVITY_MPS2
            ) ** 2 * d2
            F = self.F[slots]
            grow = 1.0 + dt * (a_in - x[:, MdsfState.ACCEL_BIAS]) / np.maximum(
                speed, _SLIP_MIN_SPEED_MPS
            )
            # Slip changes the accelerometer cannot see (a drawbar load set down or lifted,
            # soil, tyre pressure) show as rim innovations that keep one sign: their running
            # mean beyond what white innovations explain opens that wheel's rim excess.
            q_drift = None
            if cfg.rim_drift_tau_s > 0:
                q_drift = self._rim_drift_noise(slots, lost)
            Q[:, _RIM_EXCESS, _RIM_EXCESS] += q_e[:, None]
            if q_drift is not None:
                Q[:, _RIM_EXCESS, _RIM_EXCESS] += q_drift
            F[:, _RIM_EXCESS, _RIM_EXCESS] = np.clip(grow, 0.5, 1.5)[:, None]
            if cfg.slip_per_demand > 0:
                # Tyre model: slip follows the traction demand, ds ≈ k·d(f/g); the expected
                # change of the rim excess enters as a control term (the filter corrects k's
                # error through the rim, GNSS and accelerometer rows). k is the local slope of
                # the traction curve, learnt online (:meth:`tyre_gain`); the model stays on in
                # a GNSS outage, where it carries the slip's response to speed changes (a
                # demand that rises and falls back leaves no net change).
                d_dem = self._model_demand_change(slots, t)
                gain = self.tyre_gain(slots)
                u[:, _RIM_EXCESS] = (gain * speed * d_dem / GRAVITY_MPS2)[:, None]
        else:
            F = self.F[slots]
        x_pr, P_pr = kalman.predict(x, P, F, Q, u)

        # -- update in two stages (equal to one joint update: the rows' noises are independent,
        #    so each stage also applies its rows one at a time, kalman.update_independent)
        # 1) the IMU rows, 2) GNSS speed and rim speeds, gated against the stage-1 posterior so
        #    the tests see this tick's measured rates.
        mask1 = np.zeros((k, m), dtype=bool)
        mask1[:, MdsfObs.A1] = t.imu_ok & (not self.product)
        mask1[:, MdsfObs.OMEGA_X] = t.imu_ok
        mask1[:, MdsfObs.OMEGA_Z] = t.imu_ok
        res1 = kalman.update_independent(x_pr, P_pr, z, H, rd, mask1, _STAGE1_ROWS)
        x_1, P_1 = res1.x, res1.P
        y_all = z - np.einsum("kmi,ki->km", H, x_1)
        s_all = kalman.row_variances(H, P_1) + rd
        y_vg = y_all[:, MdsfObs.VG]
        gated = np.zeros(k, dtype=bool)
        reacq = np.zeros(k, dtype=bool)
        rim_use = rim_ok
        inflated = np.zeros(k, dtype=bool)
        if self.product:
            # The gate has a floor: a speed that wandered by a few cm/s while the receiver
            # reports mm/s (standing, creeping) must not lock the GNSS out.
            s_gate = s_all[:, MdsfObs.VG] + cfg.gate_floor_mps**2
            gated = gnss_ok & init & ~(y_vg * y_vg <= cfg.gate_chi2 * s_gate)
            since = self.gated_since_ns[slots]
            since = np.where(gated & (since < 0), stamp, since)
            reacq = gated & (stamp - since >= round(cfg.reacquire_s * 1e9))
            gated &= ~reacq
            since = np.where(gated, since, -1)
            self.gated_since_ns[slots] = since
            # Re-acquire: open the speed variance to the disagreement so the update follows GNSS.
            P_1[:, MdsfState.V1, MdsfState.V1] += np.where(reacq, y_vg * y_vg, 0.0)
            inflated |= reacq
            # A rim speed far off its prediction while the accelerometer saw no matching
            # acceleration means the slip itself changed (soil, wet patch): open the rim
            # excess by the unexplained part of the innovation before the update.
            y_rim = y_all[:, _RIM]
            s_rim = s_all[:, _RIM]
            if cfg.rim_drift_tau_s > 0:
                self._track_rim_innovation(slots, y_rim, s_rim, rim_use & init[:, None])
            big = rim_use & init[:, None] & (y_rim * y_rim > cfg.slip_jump_sigma**2 * s_rim)
            extra = np.where(big, y_rim * y_rim - s_rim, 0.0)
            P_1[:, _RIM_EXCESS, _RIM_EXCESS] += extra
            inflated |= big.any(axis=1)
        use_vg = gnss_ok & ~gated
        mask2 = np.zeros((k, m), dtype=bool)
        mask2[:, MdsfObs.VG] = use_vg
        if self.product:
            mask2[:, _RIM] = rim_use
            # The distance row is gated like the speed (a position jump: wrong fix); the next
            # fix then starts a new chain.
            y_d = y_all[:, MdsfObs.DIST]
            s_d = s_all[:, MdsfObs.DIST] + cfg.gnss_distance_gate_floor_m**2
            d_gated = t.dist_ok & init & ~(y_d * y_d <= cfg.gate_chi2 * s_d)
            self.dist_gated[slots] = np.where(t.dist_ok, d_gated, self.dist_gated[slots])
            mask2[:, MdsfObs.DIST] = t.dist_ok & ~d_gated
        stage2 = _STAGE2_ROWS_PRODUCT if self.product else _STAGE2_ROWS_PAPER
        res = kalman.update_independent(x_1, P_1, z, H, rd, mask2, stage2)
        x_new, P_new = res.x, res.P
        zupt = np.zeros(k, dtype=bool)
        if self.product and cfg.zupt_speed_mps > 0:
            # Zero-velocity update: both wheels stand and GNSS (if any) agrees.
            zs = cfg.zupt_speed_mps
            zupt = (
                init
                & rim_ok.all(axis=1)
                & (np.abs(np.where(rim_ok, rim_mps, np.inf)) <= zs).all(axis=1)
                & (~gnss_ok | (np.abs(z[:, MdsfObs.VG]) <= 2.0 * zs))
            )
            if zupt.any():
                resz = kalman.update_independent(
                    x_new,
                    P_new,
                    np.zeros((k, 1)),
                    self.v0_row[slots][:, None, :],
                    np.full((k, 1), (0.5 * zs) ** 2),
                    zupt[:, None],
                )
                x_new, P_new = resz.x, resz.P

        # Running estimate of the GNSS speed noise from accepted innovations.
        if self.product and cfg.gnss_noise_adapt > 0:
            hph = s_all[:, MdsfObs.VG] - r_gnss
            est = self.gnss_noise_var[slots]
            b = cfg.gnss_noise_adapt
            est = np.where(use_vg & init, (1 - b) * est + b * (y_vg * y_vg - hph), est)
            self.gnss_noise_var[slots] = est

        if self.product and cfg.slip_per_demand > 0 and cfg.tyre_gain_tau_s > 0:
            self._learn_tyre_gain(slots, t, x_new, rim_mps, rim_ok, use_vg & init)

        # -- initialise vehicles that get their first GNSS speed --------------------------
        v1_from_gnss = z[:, MdsfObs.VG] - (
            H[:, MdsfObs.VG, MdsfState.OMEGA_X] * np.where(t.imu_ok, z[:, MdsfObs.OMEGA_X], 0.0)
            + H[:, MdsfObs.VG, MdsfState.OMEGA_Z] * np.where(t.imu_ok, z[:, MdsfObs.OMEGA_Z], 0.0)
        )
        start = ~init & gnss_ok
        # Without GNSS a vehicle can start from its wheels (reference speed, degraded).
        n_rim = rim_ok.sum(axis=1)
        rim_mean = np.where(
            n_rim > 0, np.where(rim_ok, rim_mps, 0.0).sum(axis=1) / np.maximum(n_rim, 1), np.nan
        )
        start_wheels = ~init & ~gnss_ok & (n_rim > 0) & (self._wheel_start_allowed(slots) | broken)
        sel = start | start_wheels
        if sel.any():
            v_start = np.where(start, v1_from_gnss, nan_to_num(rim_mean))
            x0, p0 = self._initial_state(slots, z, t.imu_ok, v_start, rim_ok)
            x_new = np.where(sel[:, None], x0, x_new)
            P_new = np.where(sel[:, None, None], p0, P_new)
            flags |= np.where(sel, int(_F.RESET), 0).astype(np.int32)

        # -- divergence check -----------------------------------------------------------------
        diag = np.diagonal(P_new, axis1=1, axis2=2)
        diverged = init & (
            ~np.isfinite(x_new).all(axis=1)
            | ~np.isfinite(P_new).all(axis=(1, 2))
            | (diag < 0).any(axis=1)
            | (diag[:, MdsfState.V1] > cfg.max_speed_var_mps2)
        )
        if diverged.any():
            ref_v = self.ref_x[slots, RefState.V]
            v_re = np.where(gnss_ok, v1_from_gnss, np.where(np.isfinite(ref_v), ref_v, 0.0))
            x0, p0 = self._initial_state(slots, z, t.imu_ok, v_re, rim_ok)
            x_new = np.where(diverged[:, None], x0, x_new)
            P_new = np.where(diverged[:, None, None], p0, P_new)
            flags |= np.where(diverged, int(_F.RESET), 0).astype(np.int32)

        now_init = init | sel
        fused = use_vg & now_init
        last_fused = np.where(fused, stamp, self.last_fused_ns[slots])
        degraded = now_init & ((stamp - last_fused) > round(cfg.gnss_timeout_s * 1e9))

        # -- reference-speed filter (method.md §3): tracks V0 while GNSS is good, carries the
        # speed from accelerometer + slip-corrected wheel speed while it is lost.
        v0_row = self.v0_row[slots]
        v0 = np.einsum("ki,ki->k", v0_row, x_new)
        v0_var = kalman.row_variances(v0_row[:, None, :], P_new)[:, 0]
        a_ref = z[:, MdsfObs.A1] - (x_new[:, MdsfState.ACCEL_BIAS] if self.product else 0.0)
        rx, rP, raux, _ = reference_step(
            self.ref_x[slots],
            self.ref_P[slots],
            self.ref_aux[slots],
            accel_mps2=np.where(t.imu_ok, a_ref, np.nan),
            dt_s=dt,
            speed_ref_mps=np.where(degraded, np.nan, v0),
            speed_ref_var=v0_var,
            rim_speed_mps=rim_mean,
            config=self.reference,
        )
        restart = sel | diverged
        if restart.any():
            rx = np.where(restart[:, None], np.stack([v0, np.zeros(k)], axis=1), rx)
        if not self.product and degraded.any():
            # Paper mode has no wheel states: hand the reference speed to the MDSF state, so
            # GNSS resumes from it without a jump.
            self._hand_over(x_new, P_new, rx, rP, v0, degraded)
            v0 = np.einsum("ki,ki->k", v0_row, x_new)  # V1 moved, V0 with it (output)

        # -- store --------------------------------------------------------------------------------
        self.x[slots] = np.where(now_init[:, None], x_new, x)
        self.P[slots] = np.where(now_init[:, None, None], P_new, P)
        self.initialized[slots] = now_init
        self.last_fused_ns[slots] = last_fused
        self.ref_x[slots] = rx
        self.ref_P[slots] = rP
        self.ref_aux[slots] = raux
        # one indexed add of the tick's events (columns _STEP_COUNTERS)
        self.counts[slots[:, None], _STEP_COUNTERS] += np.stack(
            [np.ones(k, dtype=bool), fused, gated, reacq, diverged | reacq, degraded, ~now_init],
            axis=1,
        )

        # -- outputs -------------------------------------------------------------------------
        H1 = self.H1[slots]
        z1 = np.einsum("koi,ki->ko", H1, x_new)
        z1_var = kalman.row_variances(H1, P_new)
        z1_std = np.sqrt(np.maximum(z1_var, 0.0))
        flags |= (
            np.where(now_init & ~degraded, int(_F.GNSS_OK), 0)
            | np.where(degraded, int(_F.DEGRADED), 0)
            | np.where(gated, int(_F.GATED), 0)
            | np.where(reacq, int(_F.RESET), 0)
        ).astype(np.int32)
        rim_post = rim_std_post = rim_cov = None
        if self.product:
            # The rim rows of the posterior: the wheel fit fused with the accelerometer-driven
            # prediction of V and the rim excess (what the slip is computed from).
            h_rim = H[:, _RIM]
            h_v = H1[:, (MdsfOut.VL, MdsfOut.VR)]
            rim_post = np.einsum("kmi,ki->km", h_rim, x_new)
            ph = np.einsum("kij,kmj->kmi", P_new, h_rim)
            rim_std_post = np.sqrt(np.maximum(np.einsum("kmi,kmi->km", h_rim, ph), 0.0))
            rim_cov = np.einsum("kmi,kmi->km", h_v, ph)
        return StepOutput(
            emit=now_init,
            vg=z1[:, MdsfOut.VG],
            v1=x_new[:, MdsfState.V1],
            v0=v0,
            vl=z1[:, MdsfOut.VL],
            vr=z1[:, MdsfOut.VR],
            vg_std=z1_std[:, MdsfOut.VG],
            vl_std=z1_std[:, MdsfOut.VL],
            vr_std=z1_std[:, MdsfOut.VR],
            accel=x_new[:, MdsfState.A1],
            pitch_rate=x_new[:, MdsfState.OMEGA_X],
            yaw_rate=x_new[:, MdsfState.OMEGA_Z],
            flags=flags,
            model=TickModel(
                F=np.asarray(np.broadcast_to(F, (k, n, n))),
                Q=Q,
                u=u,
                z=z,
                R=R,
                mask1=mask1,
                mask2=mask2,
                inflated=inflated,
                dof=res1.dof + res.dof,
                special=sel
                | diverged
                | zupt
                | (degraded if not self.product else np.zeros(k, bool)),
                stages=(res1, res),
            ),
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
        h = self.H[slots]
        v_wheel = np.einsum("kmi,ki->km", h[:, _RIM, : MdsfState.ACCEL_BIAS], x_post[:, :4])
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
        """Change of the low-passed forward specific force over this tick, (k,) [m/s²]."""
        dt = self.dt_s
        a = dt / (self.config.slip_model_tau_s + dt)
        f_new = np.where(t.imu_ok & np.isfinite(t.force_fwd), t.force_fwd, np.nan)
        old = self.force_model[slots]
        fresh = ~np.isfinite(old)
        new = np.where(fresh, f_new, np.where(np.isfinite(f_new), old + a * (f_new - old), old))
        self.force_model[slots] = new
        return np.where(fresh, 0.0, nan_to_num(new - old))

    def _demand_change(self, slots: IntArray, t: TickInputs, accel_var: FloatArray) -> FloatArray:
        """Growth of the squared change of traction demand over this tick, (k,) [(m/s²)²].

        The forward specific force (acceleration plus slope) is low-passed fast
        (``force_filter_tau_s``) and slow (5×); their difference ``D`` is the recent change of
        demand. Its variance under white accelerometer noise is known, so only the excess over
        two sigma counts. The slip follows the demand as it changes (the tyre settles within a
        relaxation length, a fraction of a second), so the tyre model's error grows while the
        demand moves, not after: this tick adds ``d(D²) = 2·D·|ΔF|`` with ``ΔF`` the fast
        low-pass's move over the tick, and a whole change ``D`` adds ``D²`` (the rim excess
        then opens by ``slip_demand_gain·|V|·D/g`` in std). Using ``D²`` itself per tick, as
        before, kept the rim excess opening for the slow low-pass's memory (≈1.5 s) after the
        demand had settled, while the wheels could have held the speed.
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


# ---------------------------------------------------------------------------------------------
# Fleet estimator
# ---------------------------------------------------------------------------------------------


def _rounds(lengths: IntArray, offsets: IntArray) -> Iterator[tuple[int, IntArray]]:
    """Round ``r`` of a call's ticks: the ``r``-th tick of every vehicle that has one, as
    ``(c, rows)`` (the first ``c`` vehicles: ``lengths`` decrease), for steps that must see a
    vehicle's ticks in order."""
    for r in range(int(lengths[0]) if lengths.shape[0] else 0):
        c = int(np.count_nonzero(lengths > r))
        yield c, offsets[:c] + r


def _filtered_rims(
    so: StepOutput, rim: FloatArray, rim_std: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rim speeds (k, 2), their std and covariance with the wheel's ground speed for the slip:
    the filtered ones where the step has them (product mode, emitted rows, measured rim
    speed), else the measured ones with no covariance."""
    if so.rim is None or so.rim_std is None or so.rim_ground_cov is None:
        return rim, rim_std, np.zeros(rim.shape)
    use = (so.emit & np.isfinite(so.rim).all(axis=1))[:, None] & np.isfinite(rim)
    return (
        np.where(use, so.rim, rim),
        np.where(use, so.rim_std, rim_std),
        np.where(use, so.rim_ground_cov, 0.0),
    )


class MdsfFleet:
    """MDSF for a fleet of wheeled vehicles; implements :class:`estimator.base.FleetEstimator`.

    Parameters
    ----------
    config : MdsfConfig, optional
        Filter settings (default: product mode).
    wheel : WheelSpeedConfig, optional
        Wheel-speed front-end settings (``teeth_per_rev`` comes from each vehicle's encoder).
    reference : ReferenceSpeedConfig, optional
        Settings of the speed filter used while GNSS is lost.
    dead_reckoning : DeadReckoningConfig, optional
        How the position is carried while GNSS gives none (:mod:`estimator.dead_reckoning`).

    Examples
    --------
    >>> fleet = MdsfFleet()
    >>> fleet.add_vehicle("t1", VehicleConfig())          # doctest: +SKIP
    >>> fleet.push("t1", imu_batch); fleet.push("t1", gnss_sample)   # doctest: +SKIP
    >>> for vid, rows in fleet.advance({"t1": now_ns}): ...          # doctest: +SKIP
    """

    name = "mdsf"
    output_dtype = ESTIMATE_DTYPE

    def __init__(
        self,
        config: MdsfConfig | None = None,
        wheel: WheelSpeedConfig | None = None,
        reference: ReferenceSpeedConfig | None = None,
        dead_reckoning: DeadReckoningConfig | None = None,
    ) -> None:
        self.config = config or MdsfConfig()
        self.wheel = wheel or WheelSpeedConfig()
        self.engine = MdsfEngine(self.config, reference)
        self.front = FleetFrontEnd(self.config, self.wheel)
        self.carry = DeadReckoning(dead_reckoning or DeadReckoningConfig(), self.config.dt_s)
        self._slot: dict[str, int] = {}
        # per slot: wheel radii and rim travel per encoder tooth (left, right) [m], the slip's
        # minimum ground speed [m/s] and settling limit (SlipConfig)
        self._radius_m = np.zeros((0, 2))
        self._tooth_arc_m = np.zeros((0, 2))
        self._min_speed_mps = np.zeros(0)
        self._settle_max_change = np.zeros(0)

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        """Start estimating ``vehicle_id`` (replaces its config and state if already there)."""
        self.remove_vehicle(vehicle_id)
        slot = self.engine.add(config)
        self._slot[vehicle_id] = slot
        self.front.add(slot, config)
        self.carry.add(slot, config.geometry.antenna_offset_m)
        if slot >= self._min_speed_mps.shape[0]:
            cap = max(2 * self._min_speed_mps.shape[0], slot + 1)
            grow_slot_array(self, "_radius_m", cap, (2,), 0.0)
            grow_slot_array(self, "_tooth_arc_m", cap, (2,), 0.0)
            grow_slot_array(self, "_min_speed_mps", cap, (), 0.0)
            grow_slot_array(self, "_settle_max_change", cap, (), 0.0)
        geo = config.geometry
        self._radius_m[slot] = (geo.wheel_radius_left_m, geo.wheel_radius_right_m)
        teeth = config.encoder.teeth_per_rev
        self._tooth_arc_m[slot] = self._radius_m[slot] * (2.0 * np.pi / teeth)
        self._min_speed_mps[slot] = config.slip.min_ground_speed_mps
        self._settle_max_change[slot] = config.slip.settle_max_change

    def remove_vehicle(self, vehicle_id: str) -> None:
        """Forget ``vehicle_id`` (no error if unknown)."""
        slot = self._slot.pop(vehicle_id, None)
        if slot is not None:
            self.engine.release(slot)
            self.front.release(slot)

    def vehicle_ids(self) -> list[str]:
        return list(self._slot)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        """Buffer one measurement (sensor-time order per vehicle); ``KeyError`` if unknown."""
        self.front.push(self._slot[vehicle_id], measurement)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        """Ticks of ``vehicle_id`` fall on ``stamp_ns + k·tick`` (call before its first push;
        see :meth:`estimator.mdsf.frontend.FleetFrontEnd.align_ticks`); ``KeyError`` if unknown."""
        self.front.align_ticks(self._slot[vehicle_id], stamp_ns)

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the vehicle's local ENU frame (its first GNSS
        fix), to which ``east_m``/``north_m``/``up_m`` of its rows refer; None before that fix."""
        slot = self._slot.get(vehicle_id)
        return None if slot is None else self.front.anchor(slot)

    def set_anchor(self, vehicle_id: str, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Give the vehicle's ENU frame this origin (e.g. the anchor its stored estimates were
        given in before a restart) instead of its next first fix; ``KeyError`` if unknown,
        ``ValueError`` if not a geodetic position. Later fixes do not move it."""
        self.front.set_anchor(self._slot[vehicle_id], lat_deg, lon_deg, height_m)

    def counters(self, vehicle_id: str) -> dict[str, int]:
        """Event counters of one vehicle: ticks, GNSS fused/gated/re-acquired, resets,
        degraded ticks, skipped (non-finite or out-of-order) GNSS/IMU/edges/wheel speeds."""
        slot = self._slot[vehicle_id]
        out = dict(
            zip(_COUNTER_KEYS, self.engine.counts[slot, _COUNTER_COLUMNS].tolist(), strict=True)
        )
        for k, v in self.front.counts(slot).items():
            out[k] = out.get(k, 0) + v
        return out

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        """Emit every due tick (``stamp_ns <= until_ns[id]``), vehicles stepped together."""
        ids = [vid for vid in until_ns if vid in self._slot]
        if not ids:
            return []
        slots = np.fromiter(map(self._slot.__getitem__, ids), dtype=np.int64, count=len(ids))
        until = np.fromiter(map(until_ns.__getitem__, ids), dtype=np.int64, count=len(ids))
        due = self.front.assemble(slots, until)
        if due is None:
            return []
        lengths, offsets, flat = due.lengths, due.offsets, due.inputs
        total = flat.m
        row_slot = np.repeat(due.slots, lengths)
        radius = self._radius_m[row_slot]
        min_speed = self._min_speed_mps[row_slot]
        rim = flat.omega * radius
        rim_std = flat.omega_std * radius
        # Slip from the filtered rim speeds where the filter has them (product mode), so the
        # wheel fit's noise is weighed against the accelerometer; the measured ones otherwise.
        rounds = int(lengths[0])
        if rounds == 1:
            # one tick per vehicle (the usual call): the step's rows are the call's rows, its
            # outputs are used as they are
            so = self.engine.step(due.slots, flat, rim, rim_std)
            emit, flags = so.emit, so.flags
            res = {name: getattr(so, name) for name in _STEP_COLS}
            rim, rim_std, rim_cov = _filtered_rims(so, rim, rim_std)
        else:
            emit = np.zeros(total, dtype=bool)
            flags = np.zeros(total, dtype=np.int32)
            res = {c: np.full(total, np.nan) for c in _STEP_COLS}
            rim_cov = np.zeros((total, 2))
        for c, fi in _rounds(lengths, offsets) if rounds > 1 else ():
            tin = TickInputs(*(getattr(flat, f)[fi] for f in _TICK_FIELDS))
            so = self.engine.step(due.slots[:c], tin, rim[fi], rim_std[fi])
            emit[fi] = so.emit
            for name in _STEP_COLS:
                res[name][fi] = getattr(so, name)
            flags[fi] = so.flags
            rim[fi], rim_std[fi], rim_cov[fi] = _filtered_rims(so, rim[fi], rim_std[fi])
        # Slip for all rows and both wheels at once (eq. (8)(9); element-wise: columns left, right).
        ground = np.stack([res["vl"], res["vr"]], axis=1)
        sp = slip_pct(
            rim,
            ground,
            min_speed[:, None],
            rim_std,
            np.stack([res["vl_std"], res["vr_std"]], axis=1),
            rim_cov,
        )
        # starting / stopping faster than the wheel fit follows: no slip value (SETTLING)
        fitted = (flat.wheel_flags & int(_F.WHEEL_DIRECT)) == 0
        span = np.where(
            fitted[:, None],
            fit_span_s(ground, self._tooth_arc_m[row_slot], self.wheel.min_edges),
            0.0,
        )
        settling = sp.valid & unsettled(
            ground, res["accel"][:, None], span, self._settle_max_change[row_slot][:, None]
        )
        valid = sp.valid & ~settling
        enu, heading, carried = self._carry(due, res)
        slip_out = np.where(valid, sp.slip_pct, np.nan)
        slip_std_out = np.where(valid, sp.std_pct, np.nan)
        flags = (
            flags
            | (
                np.where(valid[:, 0], int(_F.SLIP_LEFT_VALID), 0)
                | np.where(valid[:, 1], int(_F.SLIP_RIGHT_VALID), 0)
                | np.where(sp.standstill.all(axis=1), int(_F.STANDSTILL), 0)
                | np.where(settling.any(axis=1), int(_F.SETTLING), 0)
                | np.where(carried, int(_F.DEAD_RECKONED), 0)
            ).astype(np.int32)
            | flat.wheel_flags
        )
        out = empty_estimates(total)
        out["stamp_ns"] = flat.stamp_ns
        out["vg_mps"] = res["vg"]
        out["v1_mps"] = res["v1"]
        out["v0_mps"] = res["v0"]
        out["vl_mps"] = res["vl"]
        out["vr_mps"] = res["vr"]
        out["rim_left_mps"] = rim[:, 0]
        out["rim_right_mps"] = rim[:, 1]
        out["omega_left_radps"] = rim[:, 0] / radius[:, 0]
        out["omega_right_radps"] = rim[:, 1] / radius[:, 1]
        out["slip_left_pct"] = slip_out[:, 0]
        out["slip_right_pct"] = slip_out[:, 1]
        out["vg_std_mps"] = res["vg_std"]
        out["vl_std_mps"] = res["vl_std"]
        out["vr_std_mps"] = res["vr_std"]
        out["slip_left_std_pct"] = slip_std_out[:, 0]
        out["slip_right_std_pct"] = slip_std_out[:, 1]
        out["accel_mps2"] = res["accel"]
        out["pitch_rate_radps"] = res["pitch_rate"]
        out["yaw_rate_radps"] = res["yaw_rate"]
        out["east_m"] = enu[:, 0]
        out["north_m"] = enu[:, 1]
        out["up_m"] = enu[:, 2]
        out["heading_rad"] = heading
        out["pitch_rad"] = flat.attitude[:, 1]
        out["roll_rad"] = flat.attitude[:, 2]
        out["flags"] = flags
        # Emitted rows, split by vehicle (in the order of ``due``).
        kept = out if emit.all() else out[emit]
        ends = np.cumsum(np.add.reduceat(emit, offsets))
        return [
            (ids[i], kept[a:b])
            for i, a, b in zip(
                due.index.tolist(), [0, *ends[:-1].tolist()], ends.tolist(), strict=True
            )
            if b > a
        ]

    def _carry(
        self, due: FleetTicks, res: dict[str, FloatArray]
    ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """Positions and headings of the call's ticks with GNSS outages dead-reckoned, and which
        ticks were (a vehicle's ticks in order: one round per tick, as the filter's steps)."""
        flat, lengths, offsets = due.inputs, due.lengths, due.offsets
        enu, heading = flat.enu, flat.attitude[:, 0]
        carried = np.zeros(flat.m, dtype=bool)
        copied = False
        for c, fi in _rounds(lengths, offsets):
            e, h, k = self.carry.step(
                due.slots[:c],
                flat.enu[fi],
                flat.fix_age_s[fi],
                flat.attitude[fi, 0],
                res["v0"][fi],
                res["yaw_rate"][fi],
                flat.attitude[fi, 1],
            )
            if k.any():  # outputs copied only when some tick is carried (rare)
                if not copied:
                    enu, heading, copied = enu.copy(), heading.copy(), True
                enu[fi], heading[fi], carried[fi] = e, h, k
        return enu, heading, carried
