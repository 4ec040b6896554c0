"""Batched MDSF engine and the fleet estimator the server drives (``name = "mdsf"``).

Two layers:

:class:`MdsfEngine`
    Holds every vehicle's filter state in slot arrays (``x (cap, n)``, ``P (cap, n, n)`` with
    ``n`` = 4 in paper mode, 7 in product mode; per-vehicle ``F``, ``H``, ``H1``, ``Q``) and
    steps any subset of vehicles with a few calls to the pure functions of
    :mod:`estimator.kalman`: predict (accelerometer-driven in product mode), update of the IMU
    rows, chi-square gate of the GNSS speed, update of GNSS and rim speeds, divergence reset,
    reference-speed filter (§3). Each step also returns what it used (:class:`TickModel`:
    matrices, masks, NIS) for diagnostics and tests.

:class:`MdsfFleet`
    Implements :class:`estimator.base.FleetEstimator`. Each vehicle has a front end
    (:class:`_FrontEnd`) that buffers its measurements and, on :meth:`MdsfFleet.advance`, turns
    them into per-tick filter inputs with vectorised numpy calls per vehicle and advance (no
    Python work per tick): IMU averaged over each tick window (gravity removed with the
    pitch, gyro biases learnt against the GNSS attitude), GNSS speed by eq. (1) moved to the
    tick by its time stamp. The wheel speeds of all vehicles that share the ticks are fitted
    in one call (:func:`estimator.wheel_speed.query_many`). The engine then steps round by
    round: round ``r`` is the ``r``-th due tick of every vehicle that has one, all in one
    batched call. Slip, positions and attitude are computed for all rows at once afterwards.

Ticks sit on a fleet-wide grid (multiples of ``tick_ns`` since the epoch), so rows of different
vehicles share time stamps, and a row at ``t`` uses only measurements stamped at or before
``t`` (rows do not depend on how data was batched; tested). A vehicle's first row is the first
tick with a usable GNSS speed (or, after ``gnss_timeout_s`` without GNSS, with wheel speeds,
flagged DEGRADED). Nothing here raises on NaN/inf: bad parts are skipped and counted
(:meth:`MdsfFleet.counters`); a filter whose state goes non-finite or whose speed variance
explodes is re-initialised and the row flagged RESET.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
import numpy.typing as npt

from estimator import kalman
from estimator.base import Measurement
from estimator.config import VehicleConfig
from estimator.geo import EnuFrame
from estimator.mdsf import (
    GRAVITY_MPS2,
    N_OBS_PAPER,
    MdsfConfig,
    MdsfMode,
    MdsfObs,
    MdsfOut,
    MdsfState,
    gnss_vehicle_speed,
    mdsf_matrices,
)
from estimator.reference_speed import RefAux, ReferenceSpeedConfig, RefState, reference_step
from estimator.slip import slip_pct
from estimator.types import (
    ESTIMATE_DTYPE,
    EstimateFlag,
    GnssFix,
    GnssSample,
    ImuBatch,
    Wheel,
    WheelEdges,
    WheelSpeeds,
    empty_estimates,
)
from estimator.wheel_speed import (
    DirectWheelSpeed,
    WheelSpeedConfig,
    WheelSpeedMethod,
    WheelSpeedResult,
    WheelTracker,
    query_many,
)

__all__ = ["Counter", "MdsfEngine", "MdsfFleet", "StepOutput", "TickInputs", "TickModel"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

_NS = 1e-9
_SLIP_MIN_SPEED_MPS = 0.5
"""Speed floor of the constant-slip-ratio growth of the rim excess."""
_F = EstimateFlag


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


@dataclass(slots=True)
class TickInputs:
    """One vehicle's inputs for ``m`` consecutive ticks (rows), built by its front end.

    Attributes
    ----------
    stamp_ns : ndarray, shape (m,), int64
    z : ndarray, shape (m, 4)
        ``[Vg, a1, ωx, ωz]`` (eq. (6) observation); Vg aligned to the tick in product mode.
    gnss_ok : ndarray, shape (m,), bool
        A GNSS speed is in ``z[:, VG]``.
    gnss_var : ndarray, shape (m,)
        Its variance [(m/s)²].
    imu_ok : ndarray, shape (m,), bool
        The tick window held IMU samples.
    accel_var, gyro_var : ndarray, shape (m,)
        Variance of the tick-mean acceleration and rates.
    force_fwd : ndarray, shape (m,)
        Tick-mean forward specific force as measured (gravity included) [m/s²]: the traction
        demand the tyres see.
    omega : ndarray, shape (m, 2)
        Wheel angular speeds (left, right) at the tick [rad/s]; NaN when unknown.
    omega_std : ndarray, shape (m, 2)
    wheel_flags : ndarray, shape (m,), int32
        ``WHEEL_PERIOD_METHOD`` / ``WHEEL_DIRECT`` bits.
    enu : ndarray, shape (m, 3)
        Antenna position in the vehicle's ENU frame (NaN before the first fix).
    attitude : ndarray, shape (m, 3)
        Heading, pitch, roll [rad].
    """

    stamp_ns: IntArray
    z: FloatArray
    gnss_ok: BoolArray
    gnss_var: FloatArray
    imu_ok: BoolArray
    accel_var: FloatArray
    gyro_var: FloatArray
    force_fwd: FloatArray
    omega: FloatArray
    omega_std: FloatArray
    wheel_flags: npt.NDArray[np.int32]
    enu: FloatArray
    attitude: FloatArray

    @property
    def m(self) -> int:
        return int(self.stamp_ns.shape[0])


_TICK_FIELDS = TickInputs.__slots__


def _concat_inputs(items: list[TickInputs]) -> TickInputs:
    return TickInputs(*(np.concatenate([getattr(t, f) for t in items]) for f in _TICK_FIELDS))


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
        its degrees of freedom ``dof``.
    dof : ndarray, shape (k,), int
    special : ndarray, shape (k,), bool
        The row was (re)initialised, reset after divergence or handed over: not a plain
        Kalman step.
    """

    F: FloatArray
    Q: FloatArray
    u: FloatArray | None
    z: FloatArray
    R: FloatArray
    mask1: BoolArray
    mask2: BoolArray
    inflated: BoolArray
    nis: FloatArray
    dof: IntArray
    special: BoolArray


class MdsfEngine:
    """Slot arrays of many vehicles' MDSF filters, stepped in batches.

    State ``x (cap, n)``, covariance ``P (cap, n, n)`` and per-vehicle ``F``, ``H``, ``H1``,
    ``Q`` (``n`` = 4 in paper mode, 7 in product mode; see :class:`~estimator.mdsf.MdsfState`).

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

    # -- slots -------------------------------------------------------------------------------
    def _alloc(self, cap: int) -> None:
        old = self._cap

        def grow(name: str, shape: tuple[int, ...], fill: Any) -> None:
            a = getattr(self, name, None)
            dtype = np.asarray(fill).dtype if a is None else a.dtype
            new = np.full((cap, *shape), fill, dtype=dtype)
            if a is not None:
                new[:old] = a
            setattr(self, name, new)

        n, m = self.n, self.m
        grow("x", (n,), 0.0)
        grow("P", (n, n), 0.0)
        grow("F", (n, n), 0.0)
        grow("H", (m, n), 0.0)
        grow("H1", (len(MdsfOut), n), 0.0)
        grow("v0_row", (n,), 0.0)
        grow("Q_base", (n, n), 0.0)
        grow("accel_bias_walk", (), 0.0)
        grow("initialized", (), False)
        grow("last_fused_ns", (), np.int64(-(2**62)))
        grow("gated_since_ns", (), np.int64(-1))
        grow("gnss_noise_var", (), 0.0)
        grow("force_fast", (), np.nan)
        grow("force_slow", (), np.nan)
        grow("force_model", (), np.nan)
        grow("tyre_stats", (len(_TyreStat),), 0.0)
        grow("rim_innov", (2, 2), 0.0)
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
    accel_bias_walk: FloatArray
    initialized: BoolArray
    last_fused_ns: IntArray
    gated_since_ns: IntArray
    gnss_noise_var: FloatArray
    force_fast: FloatArray
    force_slow: FloatArray
    force_model: FloatArray
    tyre_stats: FloatArray
    rim_innov: FloatArray
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
            z[:, MdsfObs.RIM_LEFT :] = np.where(rim_ok, rim_mps, 0.0)
        H = self.H[slots]
        x = self.x[slots]
        P = self.P[slots]
        init = self.initialized[slots].copy()
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
            rd[:, MdsfObs.RIM_LEFT :] = np.where(
                rim_ok,
                (cfg.wheel_noise_scale * rim_std_mps) ** 2
                + (cfg.rim_texture_rel * np.where(rim_ok, rim_mps, 0.0)) ** 2
                + 1e-6,
                1.0,
            )
        R = np.zeros((k, m, m))
        R[:, np.arange(m), np.arange(m)] = rd

        # -- predict ------------------------------------------------------------------------
        Q = self.Q_base[slots].copy()
        u: FloatArray | None = None
        if self.product:
            a_in = np.where(
                t.imu_ok, z[:, MdsfObs.A1], x[:, MdsfState.A1] + x[:, MdsfState.ACCEL_BIAS]
            )
            u = np.zeros((k, n))
            u[:, MdsfState.V1] = dt * a_in
            u[:, MdsfState.A1] = a_in
            Q[:, MdsfState.V1, MdsfState.V1] += dt * dt * accel_var
            Q[:, MdsfState.A1, MdsfState.A1] += accel_var
            Q[:, MdsfState.V1, MdsfState.A1] += dt * accel_var
            Q[:, MdsfState.A1, MdsfState.V1] += dt * accel_var
            # Rim excess e = r·W − V: at constant slip ratio it scales with the speed,
            # e' = e·(1 + dt·ā/V); on top, slip wanders with soil and load and moves when the
            # traction demand (forward specific force) changes: variance ∝ |Δf|.
            speed = np.abs(x[:, MdsfState.V1])
            d2 = self._demand_change(slots, t, accel_var)
            q_e = (cfg.rim_excess_walk_rel_per_sqrt_s * speed) ** 2 * dt + (
                cfg.slip_demand_gain * speed / GRAVITY_MPS2
            ) ** 2 * d2 * (dt / cfg.force_filter_tau_s)
            F = self.F[slots].copy()
            grow = 1.0 + dt * (a_in - x[:, MdsfState.ACCEL_BIAS]) / np.maximum(
                speed, _SLIP_MIN_SPEED_MPS
            )
            # Slip changes the accelerometer cannot see (a drawbar load set down or lifted,
            # soil, tyre pressure) show as rim innovations that keep one sign: their running
            # mean beyond what white innovations explain opens that wheel's rim excess.
            q_drift = self._rim_drift_noise(slots) if cfg.rim_drift_tau_s > 0 else None
            for j, st in enumerate((MdsfState.RIM_EXCESS_LEFT, MdsfState.RIM_EXCESS_RIGHT)):
                Q[:, st, st] += q_e
                if q_drift is not None:
                    Q[:, st, st] += q_drift[:, j]
                F[:, st, st] = np.clip(grow, 0.5, 1.5)
            if cfg.slip_per_demand > 0:
                # Tyre model: slip follows the traction demand, ds ≈ k·d(f/g); the expected
                # change of the rim excess enters as a control term (the filter corrects k's
                # error through the rim, GNSS and accelerometer rows). k is the local slope of
                # the traction curve, learnt online (:meth:`tyre_gain`); the model stays on in
                # a GNSS outage, where it carries the slip's response to speed changes (a
                # demand that rises and falls back leaves no net change).
                d_dem = self._model_demand_change(slots, t)
                gain = self.tyre_gain(slots)
                for st in (MdsfState.RIM_EXCESS_LEFT, MdsfState.RIM_EXCESS_RIGHT):
                    u[:, st] = gain * speed * d_dem / GRAVITY_MPS2
        else:
            F = self.F[slots]
        x_pr, P_pr = kalman.predict(x, P, F, Q, u)

        # -- update in two stages (equal to one joint update: the rows' noises are independent)
        # 1) the IMU rows, 2) GNSS speed and rim speeds, gated against the stage-1 posterior so
        #    the tests see this tick's measured rates.
        mask1 = np.zeros((k, m), dtype=bool)
        mask1[:, MdsfObs.A1] = t.imu_ok & (not self.product)
        mask1[:, MdsfObs.OMEGA_X] = t.imu_ok
        mask1[:, MdsfObs.OMEGA_Z] = t.imu_ok
        res1 = kalman.update(x_pr, P_pr, z, H, R, mask1)
        x_1, P_1 = res1.x, res1.P
        y_all = z - np.einsum("kmi,ki->km", H, x_1)
        s_all = np.einsum("kmi,kij,kmj->km", H, P_1, H) + rd
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
            y_rim = y_all[:, MdsfObs.RIM_LEFT :]
            s_rim = s_all[:, MdsfObs.RIM_LEFT :]
            if cfg.rim_drift_tau_s > 0:
                self._track_rim_innovation(slots, y_rim, s_rim, rim_use & init[:, None])
            big = rim_use & init[:, None] & (y_rim * y_rim > cfg.slip_jump_sigma**2 * s_rim)
            extra = np.where(big, y_rim * y_rim - s_rim, 0.0)
            for j, st in enumerate((MdsfState.RIM_EXCESS_LEFT, MdsfState.RIM_EXCESS_RIGHT)):
                P_1[:, st, st] += extra[:, j]
            inflated |= big.any(axis=1)
        use_vg = gnss_ok & ~gated
        mask2 = np.zeros((k, m), dtype=bool)
        mask2[:, MdsfObs.VG] = use_vg
        if self.product:
            mask2[:, MdsfObs.RIM_LEFT :] = rim_use
        res = kalman.update(x_1, P_1, z, H, R, mask2)
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
                rz = np.full((k, 1, 1), (0.5 * zs) ** 2)
                resz = kalman.update(
                    x_new,
                    P_new,
                    np.zeros((k, 1)),
                    self.v0_row[slots][:, None, :],
                    rz,
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
        v_start = np.where(start, v1_from_gnss, np.nan_to_num(rim_mean))
        sel = start | start_wheels
        if sel.any():
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
        v0_var = np.einsum("ki,kij,kj->k", v0_row, P_new, v0_row)
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
        rx = np.where(restart[:, None], np.stack([v0, np.zeros(k)], axis=1), rx)
        if not self.product and degraded.any():
            # Paper mode has no wheel states: hand the reference speed to the MDSF state, so
            # GNSS resumes from it without a jump.
            self._hand_over(x_new, P_new, rx, rP, v0, degraded)

        # -- store --------------------------------------------------------------------------------
        self.x[slots] = np.where(now_init[:, None], x_new, x)
        self.P[slots] = np.where(now_init[:, None, None], P_new, P)
        self.initialized[slots] = now_init
        self.last_fused_ns[slots] = last_fused
        self.ref_x[slots] = rx
        self.ref_P[slots] = rP
        self.ref_aux[slots] = raux
        cnt = self.counts
        cnt[slots, Counter.TICKS] += 1
        cnt[slots, Counter.GNSS_FUSED] += fused
        cnt[slots, Counter.GNSS_GATED] += gated
        cnt[slots, Counter.GNSS_REACQUIRED] += reacq
        cnt[slots, Counter.RESETS] += diverged | reacq
        cnt[slots, Counter.DEGRADED_TICKS] += degraded
        cnt[slots, Counter.WAITING_TICKS] += ~now_init

        # -- outputs -------------------------------------------------------------------------
        H1 = self.H1[slots]
        z1 = np.einsum("koi,ki->ko", H1, x_new)
        z1_var = np.einsum("koi,kij,koj->ko", H1, P_new, H1)
        z1_std = np.sqrt(np.maximum(z1_var, 0.0))
        flags |= np.where(now_init & ~degraded, int(_F.GNSS_OK), 0).astype(np.int32)
        flags |= np.where(degraded, int(_F.DEGRADED), 0).astype(np.int32)
        flags |= np.where(gated, int(_F.GATED), 0).astype(np.int32)
        flags |= np.where(reacq, int(_F.RESET), 0).astype(np.int32)
        return StepOutput(
            emit=now_init,
            vg=z1[:, MdsfOut.VG],
            v1=x_new[:, MdsfState.V1],
            v0=np.einsum("ki,ki->k", v0_row, x_new),
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
                nis=res1.nis + res.nis,
                dof=res1.dof + res.dof,
                special=sel
                | diverged
                | zupt
                | (degraded if not self.product else np.zeros(k, bool)),
            ),
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

    def _rim_drift_noise(self, slots: IntArray) -> FloatArray:
        """Extra rim-excess process noise per wheel from persistent rim innovations, (k, 2).

        The running mean ``m`` of a rim row's innovation (:meth:`_track_rim_innovation`)
        beyond ``rim_drift_sigma`` of its white-noise spread means the slip moves faster than
        the model lets it; the excess ``m² − σ²·var`` is let into the rim excess over
        ``rim_drift_tau_s`` [(m/s)² per tick].
        """
        cfg = self.config
        st = self.rim_innov[slots]
        excess = st[:, :, 0] ** 2 - cfg.rim_drift_sigma**2 * st[:, :, 1]
        return np.maximum(excess, 0.0) * (self.dt_s / cfg.rim_drift_tau_s)

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
        v_wheel = np.einsum(
            "kmi,ki->km", h[:, MdsfObs.RIM_LEFT :, : MdsfState.ACCEL_BIAS], x_post[:, :4]
        )
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
        return np.where(fresh, 0.0, np.nan_to_num(new - old))

    def _demand_change(self, slots: IntArray, t: TickInputs, accel_var: FloatArray) -> FloatArray:
        """Squared recent change of traction demand beyond accelerometer noise, (k,) [(m/s²)²].

        The forward specific force (acceleration plus slope) is low-passed fast
        (``force_filter_tau_s``) and slow (5×); their difference is the recent change of
        demand. Its variance under white accelerometer noise is known, so only the excess over
        two sigma counts.
        """
        dt = self.dt_s
        tau = self.config.force_filter_tau_s
        a1 = dt / (tau + dt)
        a2 = dt / (5.0 * tau + dt)
        f_new = np.where(t.imu_ok & np.isfinite(t.force_fwd), t.force_fwd, np.nan)
        fast = self.force_fast[slots]
        slow = self.force_slow[slots]
        fresh = ~np.isfinite(fast)
        fast = np.where(
            fresh, f_new, np.where(np.isfinite(f_new), fast + a1 * (f_new - fast), fast)
        )
        slow = np.where(
            fresh, f_new, np.where(np.isfinite(f_new), slow + a2 * (f_new - slow), slow)
        )
        self.force_fast[slots] = fast
        self.force_slow[slots] = slow
        var_d = accel_var * (a1 / (2 - a1) + a2 / (2 - a2) - 2 * a1 * a2 / (a1 + a2 - a1 * a2))
        d = np.nan_to_num(fast - slow)
        return np.maximum(d * d - 4.0 * var_d, 0.0)

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
# Front end: one per vehicle
# ---------------------------------------------------------------------------------------------


def _log_at(log: list[tuple[int, float]], T: IntArray, before: float) -> FloatArray:
    """Value of a time-stamped log in force at each time in ``T`` (``before`` if none yet)."""
    if not log:
        return np.full(T.shape[0], before)
    st_ = np.array([a for a, _ in log], dtype=np.int64)
    va = np.array([b for _, b in log])
    i = np.searchsorted(st_, T, side="right") - 1
    return np.where(i >= 0, va[np.maximum(i, 0)], before)


def _cummean(values: FloatArray, lo: IntArray, hi: IntArray) -> FloatArray:
    """Mean of ``values[lo:hi]`` per window (shape (m, ...)); NaN for empty windows."""
    c = np.concatenate([np.zeros((1, *values.shape[1:])), np.cumsum(values, axis=0)])
    n = (hi - lo).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (c[hi] - c[lo]) / n.reshape(-1, *([1] * (values.ndim - 1)))
    return np.asarray(out)


class _FrontEnd:
    """Buffers one vehicle's measurements and turns them into :class:`TickInputs`."""

    def __init__(self, vehicle: VehicleConfig, config: MdsfConfig, wheel: WheelSpeedConfig) -> None:
        self.vehicle = vehicle
        self.config = config
        self.product = config.mode is MdsfMode.PRODUCT
        self.tick_ns = config.tick_ns
        wcfg = dataclasses.replace(wheel, teeth_per_rev=vehicle.encoder.teeth_per_rev)
        self.trackers = (WheelTracker(wcfg), WheelTracker(wcfg))
        self.direct = DirectWheelSpeed(std_radps=0.01)
        self.has_edges = False
        self.next_tick_ns: int | None = None
        self.done_ns: int | None = None  # last tick emitted
        self.gnss: list[GnssSample] = []
        self.imu_t: list[IntArray] = []
        self.imu_f: list[FloatArray] = []
        self.imu_w: list[FloatArray] = []
        self.frame: EnuFrame | None = None
        self.pitch_rad = 0.0
        self.pitch_known = False
        self.pitch_gyro_bias = 0.0
        self.pitch_fix_ns = 0
        self.pitch_fixes = 1
        self.pitch_var = config.pitch_std_rad**2 * 100.0  # unknown before the first fix
        self.pitch_var_log: list[tuple[int, float]] = []
        self._pitch_var_before = self.pitch_var
        self.pitch_bias_log: list[tuple[int, float]] = []
        self._pitch_bias_before = 0.0
        self.yaw_rad = math.nan
        self.yaw_gyro_bias = 0.0
        self.yaw_fix_ns = 0
        self._yaw_bias_before = 0.0
        self.last_yaw_ns: int | None = None
        self.last_imu_ns: int | None = None
        self.last_imu_ns_used: int | None = None
        # Latest GNSS solution held for outputs: stamp, e, n, u, ve, vn, vu, heading, pitch, roll
        self.hold = np.full(10, np.nan)
        self.counts: dict[str, int] = {}
        n = vehicle.noise
        self.gnss_var_cfg = n.gnss_vel_std_mps**2
        self.accel_var_cfg = n.accel_std_mps2**2
        self.gyro_var_cfg = n.gyro_std_radps**2
        self.imu_fwd_m = vehicle.geometry.imu_offset_m[1]

    def _count(self, name: str, n: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + n

    def _see(self, stamp_ns: int) -> None:
        if self.next_tick_ns is None:
            tn = self.tick_ns
            self.next_tick_ns = -(-int(stamp_ns) // tn) * tn

    def _late(self, stamp_ns: int) -> bool:
        return self.done_ns is not None and stamp_ns <= self.done_ns

    def push(self, m: Measurement) -> None:
        if isinstance(m, GnssSample):
            if not isinstance(m.stamp_ns, int | np.integer):
                self._count("skipped_gnss")
                return
            if self._late(int(m.stamp_ns)):
                self._count("skipped_late")
                return
            self._see(int(m.stamp_ns))
            self.gnss.append(m)
        elif isinstance(m, ImuBatch):
            t = np.asarray(m.stamp_ns, dtype=np.int64).reshape(-1)
            f = np.asarray(m.accel_mps2, dtype=np.float64).reshape(-1, 3)
            w = np.asarray(m.gyro_radps, dtype=np.float64).reshape(-1, 3)
            if f.shape[0] != t.shape[0] or w.shape[0] != t.shape[0]:
                self._count("skipped_imu", int(t.shape[0]))
                return
            ok: BoolArray = np.isfinite(f[:, 1]) & np.isfinite(w[:, 0]) & np.isfinite(w[:, 2])
            floor = self.last_imu_ns if self.last_imu_ns is not None else np.iinfo(np.int64).min
            if self.done_ns is not None:
                floor = max(floor, self.done_ns)
            ok &= t > floor
            if t.shape[0] > 1:
                ok[1:] &= t[1:] > t[:-1]
            if not ok.all():
                self._count("skipped_imu", int((~ok).sum()))
                t, f, w = t[ok], f[ok], w[ok]
            if t.shape[0] == 0:
                return
            self._see(int(t[0]))
            self.last_imu_ns = int(t[-1])
            self.imu_t.append(t)
            self.imu_f.append(f)
            self.imu_w.append(w)
        elif isinstance(m, WheelEdges):
            t = np.asarray(m.stamp_ns, dtype=np.int64).reshape(-1)
            if t.shape[0] == 0:
                return
            try:
                tracker = self.trackers[int(m.wheel)]
            except (IndexError, ValueError):
                self._count("skipped_edges", int(t.shape[0]))
                return
            d = None if m.direction is None else np.asarray(m.direction).reshape(-1)
            if d is not None and d.shape[0] != t.shape[0]:
                d = None
            if not self.vehicle.encoder.has_direction:
                d = None
            before = tracker.skipped
            tracker.push(t, d)
            self._count("skipped_edges", tracker.skipped - before)
            self.has_edges = True
            self._see(int(t[0]))
        elif isinstance(m, WheelSpeeds):
            t = np.asarray(m.stamp_ns, dtype=np.int64).reshape(-1)
            before = self.direct.skipped
            self.direct.push(t, m.omega_radps)
            self._count("skipped_wheel_speeds", self.direct.skipped - before)
            if t.shape[0]:
                self._see(int(t[0]))

    # -- tick assembly ---------------------------------------------------------------------
    def assemble(self, until_ns: int) -> TickInputs | None:
        if self.next_tick_ns is None or until_ns < self.next_tick_ns:
            return None
        tn = self.tick_ns
        m = (int(until_ns) - self.next_tick_ns) // tn + 1
        ticks = self.next_tick_ns + tn * np.arange(m, dtype=np.int64)
        t_end = int(ticks[-1])
        self.next_tick_ns = t_end + tn
        self.done_ns = t_end
        # IMU samples up to the last tick.
        if self.imu_t:
            T = np.concatenate(self.imu_t)
            Fs = np.concatenate(self.imu_f)
            Ws = np.concatenate(self.imu_w)
        else:
            T = np.zeros(0, dtype=np.int64)
            Fs = np.zeros((0, 3))
            Ws = np.zeros((0, 3))
        n_use = int(np.searchsorted(T, t_end, side="right"))
        rest = (T[n_use:], Fs[n_use:], Ws[n_use:])
        T, Fs, Ws = T[:n_use], Fs[:n_use], Ws[:n_use]
        self.imu_t = [rest[0]] if rest[0].size else []
        self.imu_f = [rest[1]] if rest[0].size else []
        self.imu_w = [rest[2]] if rest[0].size else []

        # GNSS samples up to the last tick.
        n_g = 0
        while n_g < len(self.gnss) and self.gnss[n_g].stamp_ns <= t_end:
            n_g += 1
        gs = self.gnss[:n_g]
        del self.gnss[:n_g]
        g = self._gnss_arrays(gs)

        # Pitch per IMU sample (product: GNSS pitch blended with integrated ωx) and forward accel.
        theta = self._pitch_track(T, Ws[:, 0], g)
        if self.product:
            # Gyro biases learnt against the GNSS attitude, in force at each sample.
            bx = _log_at(self.pitch_bias_log, T, self._pitch_bias_before)
            if self.pitch_bias_log:
                self._pitch_bias_before = self.pitch_bias_log[-1][1]
            self.pitch_bias_log.clear()
            bz = self._yaw_track(T, Ws[:, 2], theta, g)
            Ws = Ws.copy()
            Ws[:, 0] -= bx
            Ws[:, 2] -= bz
        if self.product:
            a_fwd = Fs[:, 1] - GRAVITY_MPS2 * np.sin(theta)
            if self.imu_fwd_m != 0.0:
                a_fwd = a_fwd + (Ws[:, 0] ** 2 + Ws[:, 2] ** 2) * self.imu_fwd_m
        else:
            a_fwd = Fs[:, 1]
        hi = np.searchsorted(T, ticks, side="right")
        lo = np.searchsorted(T, ticks - tn, side="right")
        n_imu = hi - lo
        imu_ok = n_imu > 0
        vals = np.stack([a_fwd, Ws[:, 0], Ws[:, 2], Fs[:, 1]], axis=1)
        means = _cummean(vals, lo, hi) if T.size else np.full((m, 4), np.nan)
        nf = np.maximum(n_imu, 1).astype(np.float64)
        accel_var = self.accel_var_cfg / nf
        if self.product:
            # Gravity leaks through the pitch error: g·δθ. Its variance per fix (tracked in
            # _pitch_track) is spread as white noise with the same low-frequency power
            # (correlation ``pitch_tau_s``).
            pv = self._pitch_var_at(ticks)
            accel_var = accel_var + (GRAVITY_MPS2**2) * pv * (
                self.config.pitch_tau_s / self.config.dt_s
            )
        gyro_var = self.gyro_var_cfg / nf
        theta_tick = np.where(imu_ok, theta[np.maximum(hi - 1, 0)] if T.size else np.nan, np.nan)

        z = np.full((m, N_OBS_PAPER), np.nan)
        z[:, MdsfObs.A1] = means[:, 0]
        z[:, MdsfObs.OMEGA_X] = means[:, 1]
        z[:, MdsfObs.OMEGA_Z] = means[:, 2]

        # GNSS speed per tick: eq. (1), moved to the tick (product) and averaged, or the latest.
        gnss_ok = np.zeros(m, dtype=bool)
        gnss_var = np.full(m, self.gnss_var_cfg)
        enu = np.full((m, 3), np.nan)
        att = np.full((m, 3), np.nan)
        if g is not None:
            gt, vg, var, vel_ok = g["stamp"], g["vg"], g["var"], g["vel_ok"]
            j = np.searchsorted(ticks, gt, side="left")  # tick whose window holds the sample
            inside = (j < m) & vel_ok
            if self.product:
                a_t = np.nan_to_num(z[np.minimum(j, m - 1), MdsfObs.A1])
                vg_al = vg + a_t * (ticks[np.minimum(j, m - 1)] - gt) * _NS
                cnt = np.bincount(j[inside], minlength=m)[:m]
                s_vg = np.bincount(j[inside], weights=vg_al[inside], minlength=m)[:m]
                s_var = np.bincount(j[inside], weights=var[inside], minlength=m)[:m]
                has = cnt > 0
                z[has, MdsfObs.VG] = s_vg[has] / cnt[has]
                gnss_var[has] = s_var[has] / cnt[has] ** 2
                gnss_ok = has
            else:
                jj = j[inside]
                z[jj, MdsfObs.VG] = vg[inside]  # later samples overwrite: the latest wins
                gnss_var[jj] = var[inside]
                gnss_ok[jj] = True
        enu, att = self._hold_outputs(ticks, g, z[:, MdsfObs.OMEGA_Z], theta_tick)

        # Wheel speeds at the ticks: from the encoders (filled by the fleet, batched over
        # vehicles, see ``wheels_from``) or from direct (CAN) speeds.
        omega = np.full((m, 2), np.nan)
        omega_std = np.full((m, 2), np.nan)
        wflags = np.zeros(m, dtype=np.int32)
        if not self.uses_encoders:
            omega, omega_std = self.direct.query(ticks)
            wflags |= int(_F.WHEEL_DIRECT)

        return TickInputs(
            stamp_ns=ticks,
            z=z,
            gnss_ok=gnss_ok,
            gnss_var=gnss_var,
            imu_ok=imu_ok,
            accel_var=accel_var,
            gyro_var=gyro_var,
            force_fwd=means[:, 3],
            omega=omega,
            omega_std=omega_std,
            wheel_flags=wflags,
            enu=enu,
            attitude=att,
        )

    @property
    def uses_encoders(self) -> bool:
        """Wheel speeds come from encoder edges (else from direct speeds, when there are any)."""
        return self.has_edges or not self.direct.has_data

    def wheels_from(self, t: TickInputs, both: list[WheelSpeedResult]) -> None:
        """Fill ``t``'s wheel columns from the trackers' results (left, right), in place."""
        period = np.ones(t.m, dtype=bool)
        lone_std = 2 * np.pi / (self.vehicle.encoder.teeth_per_rev * 2.0)
        for w in Wheel:
            r = both[w]
            none = r.method == WheelSpeedMethod.NONE
            t.omega[:, w] = np.where(none, 0.0, r.omega_radps)
            t.omega_std[:, w] = np.where(none, lone_std, r.std_radps)
            period &= r.method != WheelSpeedMethod.FREQUENCY
        t.wheel_flags |= np.where(period, int(_F.WHEEL_PERIOD_METHOD), 0).astype(np.int32)

    def _gnss_arrays(self, gs: list[GnssSample]) -> dict[str, np.ndarray] | None:
        if not gs:
            return None
        n = len(gs)
        stamp = np.fromiter((s.stamp_ns for s in gs), dtype=np.int64, count=n)
        num = np.array(
            [
                (
                    *s.vel_enu_mps,
                    s.heading_rad,
                    s.pitch_rad,
                    s.roll_rad,
                    s.lat_deg,
                    s.lon_deg,
                    s.height_m,
                    s.vel_std_mps,
                    float(int(s.fix)),
                )
                for s in gs
            ],
            dtype=np.float64,
        ).reshape(n, 11)
        ve, vn, vu = num[:, 0], num[:, 1], num[:, 2]
        fix_ok = num[:, 10] != float(GnssFix.NONE)
        vel_ok = (
            np.isfinite(num[:, :3]).all(axis=1) & fix_ok & (np.abs(num[:, :3]) < 200).all(axis=1)
        )
        self._count("skipped_gnss", int((~vel_ok).sum()))
        heading_raw = num[:, 3]
        heading = np.where(np.isfinite(num[:, 3]), num[:, 3], np.arctan2(ve, vn))
        pitch_g = num[:, 4]
        pos_ok = np.isfinite(num[:, 6:9]).all(axis=1) & fix_ok
        return {
            "stamp": stamp,
            "ve": ve,
            "vn": vn,
            "vu": vu,
            "heading": heading,
            "heading_raw": heading_raw,
            "pitch": pitch_g,
            "roll": num[:, 5],
            "lat": num[:, 6],
            "lon": num[:, 7],
            "h": num[:, 8],
            "pos_ok": pos_ok,
            "vel_ok": vel_ok,
            "var": np.where(
                np.isfinite(num[:, 9]) & (num[:, 9] > 0), num[:, 9] ** 2, self.gnss_var_cfg
            ),
            "vg": np.zeros(n),  # filled by _pitch_track (needs the pitch at each sample)
        }

    def _pitch_track(
        self, T: IntArray, wx: FloatArray, g: dict[str, np.ndarray] | None
    ) -> FloatArray:
        """Pitch at each IMU sample: ``ωx − b_x`` integrated, corrected at each GNSS fix.

        A complementary filter: at each fix with a pitch the tracked pitch moves toward it with
        time constant ``pitch_tau_s`` and the pitch-gyro bias ``b_x`` with ``gyro_bias_tau_s``
        (product mode; paper mode takes the GNSS pitch as it is). Also fills ``g["vg"]`` with
        eq. (1), using the GNSS pitch or the tracked pitch if the receiver gives none.
        Returns shape ``(len(T),)``.
        """
        n = T.shape[0]
        theta = np.empty(n)
        prev = self.last_imu_ns_used
        if n:
            dts = np.empty(n)
            dts[1:] = np.diff(T) * _NS
            dts[0] = (T[0] - prev) * _NS if prev is not None else 0.0
            dts = np.clip(dts, 0.0, 0.1)
            cum_w = np.cumsum(wx * dts)
            cum_t = np.cumsum(dts)
            self.last_imu_ns_used = int(T[-1])
        else:
            cum_w = cum_t = np.zeros(0)
        th0 = self.pitch_rad
        base_w = base_t = 0.0
        start = 0
        tau = self.config.pitch_tau_s

        def integrate(lo: int, hi: int) -> None:
            # pitch over samples lo..hi-1 with the bias known at the segment start
            bias = self.pitch_gyro_bias
            theta[lo:hi] = th0 + (cum_w[lo:hi] - base_w) - bias * (cum_t[lo:hi] - base_t)

        if g is not None:
            for i in range(g["stamp"].shape[0]):
                tg = int(g["stamp"][i])
                j = int(np.searchsorted(T, tg, side="right"))
                if j > start:
                    integrate(start, j)
                    th0 = float(theta[j - 1])
                    base_w, base_t = float(cum_w[j - 1]), float(cum_t[j - 1])
                    start = j
                p = float(g["pitch"][i])
                sp2 = self.config.pitch_std_rad**2
                if math.isfinite(p):
                    if not self.pitch_known or not self.product:
                        th0 = p
                        self.pitch_var = sp2
                    else:
                        gap = min(max((tg - self.pitch_fix_ns) * _NS, 0.0), 1.0)
                        err = p - th0
                        # running mean over the first fixes, then the complementary filter
                        self.pitch_fixes += 1
                        gain = max(1.0 / self.pitch_fixes, 1.0 - math.exp(-gap / tau))
                        th0 += gain * err
                        self.pitch_var = (1 - gain) ** 2 * self.pitch_var + gain**2 * sp2
                        self.pitch_gyro_bias -= gap / (tau * self.config.gyro_bias_tau_s) * err
                    self.pitch_known = True
                    self.pitch_fix_ns = tg
                self.pitch_var_log.append((tg, self.pitch_var))
                self.pitch_bias_log.append((tg, self.pitch_gyro_bias))
                pitch_used = p if math.isfinite(p) else th0
                if g["vel_ok"][i]:
                    g["vg"][i] = gnss_vehicle_speed(
                        g["ve"][i], g["vn"][i], g["vu"][i], g["heading"][i], pitch_used
                    )
        if n > start:
            integrate(start, n)
            th0 = float(theta[-1])
        self.pitch_rad = th0
        return theta

    def _yaw_track(
        self, T: IntArray, wz: FloatArray, theta: FloatArray, g: dict[str, np.ndarray] | None
    ) -> FloatArray:
        """Yaw-gyro bias in force at each IMU sample, learnt against the GNSS heading.

        Heading is integrated from the yaw rate (``ψ̇ = −(ωz − b_z)/cos θ``) and pulled to each
        GNSS heading with ``pitch_tau_s``; the bias integrates the disagreement with
        ``gyro_bias_tau_s``, as for the pitch. Returns shape ``(len(T),)``.
        """
        n = T.shape[0]
        out = np.full(n, self.yaw_gyro_bias)
        prev = self.last_yaw_ns
        dts = np.empty(n)
        if n:
            dts[1:] = np.diff(T) * _NS
            dts[0] = (T[0] - prev) * _NS if prev is not None else 0.0
            dts = np.clip(dts, 0.0, 0.1)
            self.last_yaw_ns = int(T[-1])
        rate = -wz / np.maximum(np.cos(theta), 0.5)
        cum_r = np.cumsum(rate * dts)
        cum_t = np.cumsum(dts / np.maximum(np.cos(theta), 0.5))
        base_r = base_t = 0.0
        start = 0
        tau = self.config.pitch_tau_s
        psi = self.yaw_rad
        heads = g["heading_raw"] if g is not None else np.zeros(0)
        stamps = g["stamp"] if g is not None else np.zeros(0, dtype=np.int64)
        for i in range(heads.shape[0]):
            h = float(heads[i])
            if not math.isfinite(h):
                continue
            tg = int(stamps[i])
            j = int(np.searchsorted(T, tg, side="right"))
            bias = self.yaw_gyro_bias
            if j > start:
                out[start:j] = bias
                if math.isfinite(psi):
                    psi += (cum_r[j - 1] - base_r) + bias * (cum_t[j - 1] - base_t)
                base_r, base_t = float(cum_r[j - 1]), float(cum_t[j - 1])
                start = j
            elif n == 0 and math.isfinite(psi) and prev is not None and tg > prev:
                pass  # no rate samples since the last batch: the heading is held
            if math.isfinite(psi):
                gap = min(max((tg - self.yaw_fix_ns) * _NS, 0.0), 1.0)
                err = math.remainder(h - psi, 2 * math.pi)
                psi += (1.0 - math.exp(-gap / tau)) * err
                # ψ̇ = −(ωz − b)/cosθ: a heading that falls behind means b is too small
                self.yaw_gyro_bias += gap / (tau * self.config.gyro_bias_tau_s) * err
            else:
                psi = h
            self.yaw_fix_ns = tg
        out[start:] = self.yaw_gyro_bias
        if math.isfinite(psi) and n > start:
            psi += (cum_r[-1] - base_r) + self.yaw_gyro_bias * (cum_t[-1] - base_t)
        self.yaw_rad = psi
        return out

    def _pitch_var_at(self, ticks: IntArray) -> FloatArray:
        """Pitch variance in force at each tick (latest fix at or before it); shape (m,)."""
        log = self.pitch_var_log
        if not log:
            return np.full(ticks.shape[0], self.pitch_var)
        st_ = np.array([a for a, _ in log], dtype=np.int64)
        va = np.array([b for _, b in log])
        i = np.searchsorted(st_, ticks, side="right") - 1
        out = np.where(i >= 0, va[np.maximum(i, 0)], self._pitch_var_before)
        self._pitch_var_before = float(va[-1])
        log.clear()
        return out

    def _hold_outputs(
        self,
        ticks: IntArray,
        g: dict[str, np.ndarray] | None,
        wz: FloatArray,
        theta_tick: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """Position (ENU, moved to the tick with the GNSS velocity) and attitude per tick."""
        if g is not None:
            ok = g["pos_ok"]
            if self.frame is None and ok.any():
                i0 = int(np.flatnonzero(ok)[0])
                self.frame = EnuFrame(float(g["lat"][i0]), float(g["lon"][i0]), float(g["h"][i0]))
            e = np.full(ok.shape[0], np.nan)
            nn = np.full(ok.shape[0], np.nan)
            u = np.full(ok.shape[0], np.nan)
            if self.frame is not None and ok.any():
                e[ok], nn[ok], u[ok] = self.frame.to_enu(g["lat"][ok], g["lon"][ok], g["h"][ok])
            rows = np.stack(
                [
                    g["stamp"].astype(np.float64),
                    e,
                    nn,
                    u,
                    g["ve"],
                    g["vn"],
                    g["vu"],
                    g["heading"],
                    g["pitch"],
                    g["roll"],
                ],
                axis=1,
            )
        else:
            rows = np.zeros((0, 10))
        # For each tick: the latest GNSS row at or before it (rows are time ordered) or the hold.
        allrows = np.vstack([self.hold[None, :], rows])
        stamps = allrows[:, 0]
        idx = (
            np.searchsorted(
                np.where(np.isnan(stamps), -np.inf, stamps), ticks.astype(np.float64), side="right"
            )
            - 1
        )
        idx = np.maximum(idx, 0)
        sel = allrows[idx]
        age = (ticks - np.nan_to_num(sel[:, 0], nan=0.0)) * _NS
        age = np.where(np.isfinite(sel[:, 0]), age, 0.0)
        vel = np.nan_to_num(sel[:, 4:7])
        enu = sel[:, 1:4] + (vel * age[:, None] if self.product else 0.0)
        heading = sel[:, 7] - (np.nan_to_num(wz) * age if self.product else 0.0)
        heading = np.mod(heading, 2 * np.pi)
        pitch = (
            np.where(np.isfinite(theta_tick), theta_tick, sel[:, 8]) if self.product else sel[:, 8]
        )
        att = np.stack([heading, pitch, sel[:, 9]], axis=1)
        if rows.shape[0]:
            # Keep the latest row with a finite position as the hold (velocity/attitude too).
            self.hold = rows[-1].copy()
            okp = np.isfinite(rows[:, 1])
            if okp.any() and not okp[-1]:
                self.hold[1:4] = rows[np.flatnonzero(okp)[-1], 1:4]
        return enu, att


# ---------------------------------------------------------------------------------------------
# Fleet estimator
# ---------------------------------------------------------------------------------------------


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
    ) -> None:
        self.config = config or MdsfConfig()
        self.wheel = wheel or WheelSpeedConfig()
        self.engine = MdsfEngine(self.config, reference)
        self._slot: dict[str, int] = {}
        self._fe: dict[str, _FrontEnd] = {}
        self._cfg: dict[str, VehicleConfig] = {}

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        """Start estimating ``vehicle_id`` (replaces its config and state if already there)."""
        self.remove_vehicle(vehicle_id)
        self._slot[vehicle_id] = self.engine.add(config)
        self._fe[vehicle_id] = _FrontEnd(config, self.config, self.wheel)
        self._cfg[vehicle_id] = config

    def remove_vehicle(self, vehicle_id: str) -> None:
        """Forget ``vehicle_id`` (no error if unknown)."""
        slot = self._slot.pop(vehicle_id, None)
        if slot is not None:
            self.engine.release(slot)
        self._fe.pop(vehicle_id, None)
        self._cfg.pop(vehicle_id, None)

    def vehicle_ids(self) -> list[str]:
        return list(self._slot)

    def push(self, vehicle_id: str, measurement: Measurement) -> None:
        """Buffer one measurement (sensor-time order per vehicle); ``KeyError`` if unknown."""
        self._fe[vehicle_id].push(measurement)

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the vehicle's local ENU frame (its first GNSS
        fix), to which ``east_m``/``north_m``/``up_m`` of its rows refer; None before that fix."""
        fe = self._fe.get(vehicle_id)
        frame = fe.frame if fe is not None else None
        if frame is None:
            return None
        return (frame.lat0_deg, frame.lon0_deg, frame.h0_m)

    def counters(self, vehicle_id: str) -> dict[str, int]:
        """Event counters of one vehicle: ticks, GNSS fused/gated/re-acquired, resets,
        degraded ticks, skipped (non-finite or out-of-order) GNSS/IMU/edges/wheel speeds."""
        slot = self._slot[vehicle_id]
        out = {c.name.lower(): int(self.engine.counts[slot, c]) for c in Counter}
        for k, v in self._fe[vehicle_id].counts.items():
            out[k] = out.get(k, 0) + v
        return out

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        """Emit every due tick (``stamp_ns <= until_ns[id]``), vehicles stepped together."""
        items: list[tuple[str, TickInputs]] = []
        for vid, until in until_ns.items():
            fe = self._fe.get(vid)
            if fe is None:
                continue
            ti = fe.assemble(int(until))
            if ti is not None and ti.m > 0:
                items.append((vid, ti))
        if not items:
            return []
        # Encoder wheel speeds: one vectorised fit for every wheel that shares the ticks.
        groups: dict[tuple[WheelSpeedConfig, int, int], list[tuple[_FrontEnd, TickInputs]]] = {}
        for vid, ti in items:
            fe = self._fe[vid]
            if fe.uses_encoders:
                key = (fe.trackers[0].config, int(ti.stamp_ns[0]), ti.m)
                groups.setdefault(key, []).append((fe, ti))
        for members in groups.values():
            trackers = [tr for fe, _ in members for tr in fe.trackers]
            fitted = query_many(trackers, members[0][1].stamp_ns)
            for i, (fe, ti) in enumerate(members):
                fe.wheels_from(ti, fitted[2 * i : 2 * i + 2])
        items.sort(key=lambda it: -it[1].m)
        lengths = np.array([ti.m for _, ti in items], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        slots = np.array([self._slot[vid] for vid, _ in items], dtype=np.int64)
        flat = _concat_inputs([ti for _, ti in items])
        total = int(lengths.sum())
        radius = np.empty((total, 2))
        min_speed = np.empty(total)
        for (vid, _), off, ln in zip(items, offsets, lengths, strict=True):
            geo = self._cfg[vid].geometry
            radius[off : off + ln] = (geo.wheel_radius_left_m, geo.wheel_radius_right_m)
            min_speed[off : off + ln] = self._cfg[vid].slip.min_ground_speed_mps
        rim = flat.omega * radius
        rim_std = flat.omega_std * radius
        out = empty_estimates(total)
        emit = np.zeros(total, dtype=bool)
        cols = (
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
        res: dict[str, FloatArray] = {c: np.full(total, np.nan) for c in cols}
        flags = np.zeros(total, dtype=np.int32)
        for r in range(int(lengths[0])):
            c = int(np.count_nonzero(lengths > r))
            fi = offsets[:c] + r
            tin = TickInputs(*(getattr(flat, f)[fi] for f in _TICK_FIELDS))
            so = self.engine.step(slots[:c], tin, rim[fi], rim_std[fi])
            emit[fi] = so.emit
            for name in cols:
                res[name][fi] = getattr(so, name)
            flags[fi] = so.flags
        # Slip for all rows at once (eq. (8)(9)).
        sl = slip_pct(rim[:, 0], res["vl"], min_speed, rim_std[:, 0], res["vl_std"])
        sr = slip_pct(rim[:, 1], res["vr"], min_speed, rim_std[:, 1], res["vr_std"])
        flags |= np.where(sl.valid, int(_F.SLIP_LEFT_VALID), 0).astype(np.int32)
        flags |= np.where(sr.valid, int(_F.SLIP_RIGHT_VALID), 0).astype(np.int32)
        flags |= np.where(sl.standstill & sr.standstill, int(_F.STANDSTILL), 0).astype(np.int32)
        flags |= flat.wheel_flags
        out["stamp_ns"] = flat.stamp_ns
        out["vg_mps"] = res["vg"]
        out["v1_mps"] = res["v1"]
        out["v0_mps"] = res["v0"]
        out["vl_mps"] = res["vl"]
        out["vr_mps"] = res["vr"]
        out["rim_left_mps"] = rim[:, 0]
        out["rim_right_mps"] = rim[:, 1]
        out["omega_left_radps"] = flat.omega[:, 0]
        out["omega_right_radps"] = flat.omega[:, 1]
        out["slip_left_pct"] = sl.slip_pct
        out["slip_right_pct"] = sr.slip_pct
        out["vg_std_mps"] = res["vg_std"]
        out["vl_std_mps"] = res["vl_std"]
        out["vr_std_mps"] = res["vr_std"]
        out["slip_left_std_pct"] = sl.std_pct
        out["slip_right_std_pct"] = sr.std_pct
        out["accel_mps2"] = res["accel"]
        out["pitch_rate_radps"] = res["pitch_rate"]
        out["yaw_rate_radps"] = res["yaw_rate"]
        out["east_m"] = flat.enu[:, 0]
        out["north_m"] = flat.enu[:, 1]
        out["up_m"] = flat.enu[:, 2]
        out["heading_rad"] = flat.attitude[:, 0]
        out["pitch_rad"] = flat.attitude[:, 1]
        out["roll_rad"] = flat.attitude[:, 2]
        out["flags"] = flags
        result: list[tuple[str, np.ndarray]] = []
        for (vid, _), off, ln in zip(items, offsets, lengths, strict=True):
            rows = out[off : off + ln][emit[off : off + ln]]
            if rows.shape[0]:
                result.append((vid, rows))
        return result
