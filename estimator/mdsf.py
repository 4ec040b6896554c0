"""MDSF: multi-source data structured fusion, ``method.md`` §1 (source 000, eq. (1)-(9)).

Per wheeled vehicle, a linear Kalman filter over the state ``X = [V1, a1, ωx, ωz]`` (forward
speed and forward acceleration at the IMU, pitch rate, yaw rate) turns GNSS velocity, IMU
acceleration and gyro rates into the ground speed of each driven wheel's contact point; with the
wheel's rim speed that gives its slip, eq. (8)(9).

Two modes (:class:`MdsfMode`):

``paper``
    Exactly the source: ``dt = 0.2 s``, ``A``, ``H``, ``H1`` of eq. (6), observation
    ``Z = [Vg, a1, ωx, ωz]`` with ``a1`` the accelerometer's forward reading as it comes
    (gravity included: the source is silent on it), the latest GNSS sample taken as is.

``product``
    What a field needs where the source is silent (each point is tested):

    * **gravity**: the forward specific force carries ``g·sinθ``; ``a_fwd = f_y − g·sinθ`` with
      pitch from the GNSS attitude, integrated ``ωx`` between fixes;
    * **the accelerometer drives the speed** (``u`` of the predict): ``V1(k+1) = V1(k) + dt·ā``
      with ``ā`` the mean gravity-free forward acceleration over ``(t_k, t_k+1]``. Taking ``a1``
      from the previous tick, as eq. (6) does, makes the speed lag by ``dt·a`` (0.2 m/s at
      1 m/s² and 0.2 s); the ``a1`` state then holds the tick's mean acceleration;
    * **GNSS outliers** are gated by the innovation chi-square of the ``Vg`` row and counted;
      a persistent disagreement re-acquires the GNSS speed after ``reacquire_s`` (flag RESET);
    * **time alignment**: every source is put on the filter tick by its own time stamp (GNSS
      speed moved to the tick with the IMU acceleration, IMU averaged over the tick window,
      wheel speed evaluated at the tick);
    * **lever arms**: the forward speed of a body point ``(x, y, z)`` from ``O`` is
      ``V0 + ωz·x − ωx·z``, so with the IMU at ``(x_i, y_i, h0)`` and the antenna at
      ``(x_a, y_a, h0 + h1)`` the observation and output rows become
      ``Vg = V1 − h1·ωx + (x_a − x_i)·ωz`` and ``VL,R = V1 + h0·ωx − (x_i ± b/2)·ωz``; zero
      offsets give the source's ``H`` and ``H1``.

The batched engine (:mod:`estimator.engine`) steps many vehicles with these matrices;
:class:`MdsfFilter` is the per-vehicle reference built on ``filterpy.kalman.KalmanFilter``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum, StrEnum

import numpy as np
import numpy.typing as npt
from filterpy.kalman import KalmanFilter

from estimator.config import ConfigError, VehicleConfig, VehicleGeometry

__all__ = [
    "GRAVITY_MPS2",
    "MdsfConfig",
    "MdsfFilter",
    "MdsfMatrices",
    "MdsfMode",
    "MdsfObs",
    "MdsfOut",
    "MdsfState",
    "gnss_vehicle_speed",
    "mdsf_matrices",
    "observation_matrix",
    "output_matrix",
    "structural_speeds",
    "transition_matrix",
]

FloatArray = npt.NDArray[np.float64]

GRAVITY_MPS2 = 9.80665
"""Standard gravity [m/s²]."""


class MdsfMode(StrEnum):
    """Which MDSF formulation to run."""

    PAPER = "paper"
    PRODUCT = "product"


class MdsfState(IntEnum):
    """Indices of the MDSF state ``X = [V1, a1, ωx, ωz]`` (eq. (6))."""

    V1 = 0
    A1 = 1
    OMEGA_X = 2
    OMEGA_Z = 3


class MdsfObs(IntEnum):
    """Indices of the observation ``Z = [Vg, a1, ωx, ωz]`` (eq. (6))."""

    VG = 0
    A1 = 1
    OMEGA_X = 2
    OMEGA_Z = 3


class MdsfOut(IntEnum):
    """Indices of the output ``Z1 = [Vg, VL, VR]`` (eq. (6))."""

    VG = 0
    VL = 1
    VR = 2


N_STATE = len(MdsfState)
N_OBS = len(MdsfObs)


def _check(name: str, value: float, positive: bool = True) -> None:
    ok = isinstance(value, int | float) and math.isfinite(value) and (value > 0 or not positive)
    if not ok:
        raise ConfigError(
            f"{name} must be a finite number{' > 0' if positive else ''}, got {value!r}"
        )


@dataclass(frozen=True, slots=True)
class MdsfConfig:
    """Settings of the MDSF filter (shared by every vehicle of a fleet).

    Noise figures are 1-sigma; the vehicle's :class:`~estimator.config.NoiseConfig` gives the
    sensor noise, these give the model's.

    Attributes
    ----------
    mode : MdsfMode
        ``paper`` or ``product`` (default).
    tick_s : float
        Filter interval [s]. ``paper`` uses the source's 0.2 s whatever is set here.
    speed_walk_mps_per_sqrt_s : float
        Product mode: random walk of the speed not explained by the accelerometer (pitch error,
        accelerometer bias, scale) [m/s/√s].
    accel_walk_mps2_per_sqrt_s : float
        Paper mode: random walk of ``a1`` (the ``Qa`` of eq. (7) per second) [m/s²/√s].
    rate_walk_radps_per_sqrt_s : float
        Random walk of ``ωx``, ``ωz`` (``Qω`` per second) [rad/s/√s].
    paper_speed_walk_mps_per_sqrt_s : float
        Paper mode ``Qv`` per second [m/s/√s].
    gate_chi2 : float
        Innovation chi-square (1 degree of freedom) above which a GNSS speed is rejected
        (product mode; 10.83 is the 99.9 % point).
    reacquire_s : float
        After GNSS speeds were rejected this long without a break, the next one resets the
        speed (product mode) [s].
    gnss_timeout_s : float
        No fused GNSS speed for this long flags the estimate DEGRADED [s].
    max_speed_var_mps2 : float
        A speed variance above this (or any non-finite value) counts as divergence: reset.
    initial_speed_std_mps : float
        Speed std right after a (re)initialisation.
    pitch_tau_s : float
        Product mode: time constant with which the pitch (integrated ``ωx``) is pulled to the
        GNSS pitch at each fix [s]; the first fix sets it.
    gnss_noise_adapt : float
        Weight of each accepted GNSS innovation in the running estimate of the GNSS speed noise
        (0 turns the adaptation off; the configured noise is always the floor).
    """

    mode: MdsfMode = MdsfMode.PRODUCT
    tick_s: float = 0.05
    speed_walk_mps_per_sqrt_s: float = 0.01
    accel_walk_mps2_per_sqrt_s: float = 1.0
    rate_walk_radps_per_sqrt_s: float = 0.3
    paper_speed_walk_mps_per_sqrt_s: float = 0.05
    gate_chi2: float = 10.83
    reacquire_s: float = 3.0
    gnss_timeout_s: float = 1.0
    max_speed_var_mps2: float = 100.0
    initial_speed_std_mps: float = 0.5
    gnss_noise_adapt: float = 0.02
    pitch_tau_s: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.mode, MdsfMode):
            try:
                object.__setattr__(self, "mode", MdsfMode(self.mode))
            except ValueError as exc:
                raise ConfigError(f"mode must be one of {[m.value for m in MdsfMode]}") from exc
        for name in (
            "tick_s",
            "speed_walk_mps_per_sqrt_s",
            "accel_walk_mps2_per_sqrt_s",
            "rate_walk_radps_per_sqrt_s",
            "paper_speed_walk_mps_per_sqrt_s",
            "gate_chi2",
            "reacquire_s",
            "gnss_timeout_s",
            "max_speed_var_mps2",
            "initial_speed_std_mps",
            "pitch_tau_s",
        ):
            _check(name, getattr(self, name))
        if not 0.001 <= self.tick_s <= 1.0:
            raise ConfigError(f"tick_s must be within 0.001..1 s, got {self.tick_s!r}")
        if not (math.isfinite(self.gnss_noise_adapt) and 0.0 <= self.gnss_noise_adapt < 1.0):
            raise ConfigError("gnss_noise_adapt must be within [0, 1)")

    @property
    def dt_s(self) -> float:
        """The interval actually used: 0.2 s in paper mode, ``tick_s`` in product mode."""
        return 0.2 if self.mode is MdsfMode.PAPER else self.tick_s

    @property
    def tick_ns(self) -> int:
        return round(self.dt_s * 1e9)


def transition_matrix(dt_s: float) -> FloatArray:
    """``A`` of eq. (6): ``V1 += dt·a1``, other states constant; shape (4, 4)."""
    a = np.eye(N_STATE)
    a[MdsfState.V1, MdsfState.A1] = dt_s
    return a


def observation_matrix(h1_m: float, lever_x_m: float = 0.0) -> FloatArray:
    """``H`` of eq. (6), shape (4, 4): ``Vg = V1 − h1·ωx (+ (x_a − x_i)·ωz)``, identity below.

    ``lever_x_m`` is the product mode's horizontal antenna-minus-IMU offset ``x_a − x_i``
    (0 in the source).
    """
    h = np.eye(N_OBS, N_STATE)
    h[MdsfObs.VG, MdsfState.OMEGA_X] = -h1_m
    h[MdsfObs.VG, MdsfState.OMEGA_Z] = lever_x_m
    return h


def output_matrix(
    h0_m: float, h1_m: float, track_width_m: float, antenna_x_m: float = 0.0, imu_x_m: float = 0.0
) -> FloatArray:
    """``H1`` of eq. (6), shape (3, 4): ``Z1 = [Vg, VL, VR] = H1·X`` (eq. (2)-(5)).

    With lateral offsets (product mode) the rows follow ``V_p = V0 + ωz·x − ωx·z``:
    ``Vg = V1 − h1·ωx + (x_a − x_i)·ωz``, ``VL = V1 + h0·ωx − (x_i + b/2)·ωz``,
    ``VR = V1 + h0·ωx − (x_i − b/2)·ωz``.
    """
    half = 0.5 * track_width_m
    h = np.zeros((len(MdsfOut), N_STATE))
    h[MdsfOut.VG] = [1.0, 0.0, -h1_m, antenna_x_m - imu_x_m]
    h[MdsfOut.VL] = [1.0, 0.0, h0_m, -imu_x_m - half]
    h[MdsfOut.VR] = [1.0, 0.0, h0_m, -imu_x_m + half]
    return h


def gnss_vehicle_speed(
    ve_mps: npt.ArrayLike,
    vn_mps: npt.ArrayLike,
    vu_mps: npt.ArrayLike,
    heading_rad: npt.ArrayLike,
    pitch_rad: npt.ArrayLike,
) -> FloatArray:
    """Eq. (1): ``Vg = Ve·sinψ·cosθ + Vn·cosψ·cosθ + Vu·sinθ`` (GNSS velocity on the body Y axis).

    Shapes broadcast; ``ψ`` from north clockwise, ``θ`` nose up.
    """
    psi = np.asarray(heading_rad, dtype=np.float64)
    th = np.asarray(pitch_rad, dtype=np.float64)
    ct = np.cos(th)
    return np.asarray(
        np.asarray(ve_mps) * np.sin(psi) * ct
        + np.asarray(vn_mps) * np.cos(psi) * ct
        + np.asarray(vu_mps) * np.sin(th),
        dtype=np.float64,
    )


def structural_speeds(
    vg_mps: npt.ArrayLike,
    omega_x_radps: npt.ArrayLike,
    omega_z_radps: npt.ArrayLike,
    geometry: VehicleGeometry,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Eq. (2)-(5): ``V1 = Vg + ωx·h1``, ``V0 = V1 + ωx·h0``, ``VL,R = V0 ∓ ωz·b/2``.

    Returns ``(V1, V0, VL, VR)`` with the broadcast shape of the inputs (source geometry: the
    horizontal offsets of ``geometry`` are ignored here).
    """
    vg = np.asarray(vg_mps, dtype=np.float64)
    wx = np.asarray(omega_x_radps, dtype=np.float64)
    wz = np.asarray(omega_z_radps, dtype=np.float64)
    v1 = vg + wx * geometry.h1_m
    v0 = v1 + wx * geometry.h0_m
    half = 0.5 * geometry.track_width_m
    return v1, v0, v0 - wz * half, v0 + wz * half


@dataclass(frozen=True, slots=True)
class MdsfMatrices:
    """Constant matrices of one vehicle's filter.

    Attributes
    ----------
    F : ndarray, shape (4, 4)
        Transition (``A`` in paper mode; product: ``V1`` and ``a1`` driven by ``u``).
    H : ndarray, shape (4, 4)
        Observation matrix (eq. (6), with lever arm in product mode).
    H1 : ndarray, shape (3, 4)
        Output matrix (eq. (6), with lever arms in product mode).
    v0_row : ndarray, shape (4,)
        ``V0 = v0_row·X`` (eq. (3), lever arm in product mode).
    Q_base : ndarray, shape (4, 4)
        Process noise without the accelerometer term (product mode adds ``dt²·var(ā)`` to
        ``V1`` and ``var(ā)`` to ``a1`` per tick).
    dt_s : float
    """

    F: FloatArray
    H: FloatArray
    H1: FloatArray
    v0_row: FloatArray
    Q_base: FloatArray
    dt_s: float


def mdsf_matrices(config: MdsfConfig, vehicle: VehicleConfig) -> MdsfMatrices:
    """Build the matrices of eq. (6)/(7) for one vehicle (see the module docstring per mode)."""
    g = vehicle.geometry
    dt = config.dt_s
    if config.mode is MdsfMode.PAPER:
        F = transition_matrix(dt)
        H = observation_matrix(g.h1_m)
        H1 = output_matrix(g.h0_m, g.h1_m, g.track_width_m)
        v0_row = np.array([1.0, 0.0, g.h0_m, 0.0])
        qv = config.paper_speed_walk_mps_per_sqrt_s**2 * dt
        qa = config.accel_walk_mps2_per_sqrt_s**2 * dt
    else:
        xa, xi = g.antenna_offset_m[0], g.imu_offset_m[0]
        F = np.eye(N_STATE)
        F[MdsfState.A1, MdsfState.A1] = 0.0
        H = observation_matrix(g.h1_m, xa - xi)
        H1 = output_matrix(g.h0_m, g.h1_m, g.track_width_m, xa, xi)
        v0_row = np.array([1.0, 0.0, g.h0_m, -xi])
        qv = config.speed_walk_mps_per_sqrt_s**2 * dt
        qa = 0.0
    qw = config.rate_walk_radps_per_sqrt_s**2 * dt
    Q = np.diag([qv, qa, qw, qw])
    return MdsfMatrices(F=F, H=H, H1=H1, v0_row=v0_row, Q_base=Q, dt_s=dt)


class MdsfFilter:
    """One vehicle's MDSF filter on ``filterpy.kalman.KalmanFilter`` (reference implementation).

    The batched engine must agree with it to rounding (tested). Each :meth:`step` is a predict
    followed by an update with the active observation rows.

    Parameters
    ----------
    config : MdsfConfig
    vehicle : VehicleConfig
    """

    def __init__(self, config: MdsfConfig, vehicle: VehicleConfig) -> None:
        self.config = config
        self.vehicle = vehicle
        self.matrices = mdsf_matrices(config, vehicle)
        kf = KalmanFilter(dim_x=N_STATE, dim_z=N_OBS)
        kf.F = self.matrices.F.copy()
        kf.H = self.matrices.H.copy()
        kf.Q = self.matrices.Q_base.copy()
        kf.B = np.eye(N_STATE)
        self.kf = kf

    def initialize(self, x: FloatArray, P: FloatArray) -> None:
        """Set the state ``x`` (4,) and covariance ``P`` (4, 4)."""
        self.kf.x = np.asarray(x, dtype=np.float64).reshape(N_STATE, 1).copy()
        self.kf.P = np.asarray(P, dtype=np.float64).copy()

    @property
    def x(self) -> FloatArray:
        """State, shape (4,)."""
        return np.asarray(self.kf.x, dtype=np.float64).reshape(N_STATE)

    @property
    def P(self) -> FloatArray:  # noqa: N802 (filterpy's name for the covariance)
        """Covariance, shape (4, 4)."""
        return np.asarray(self.kf.P, dtype=np.float64)

    def step(
        self,
        z: FloatArray,
        R: FloatArray,
        mask: npt.NDArray[np.bool_],
        Q: FloatArray | None = None,
        u: FloatArray | None = None,
    ) -> None:
        """Predict one tick and update with the observation rows where ``mask`` is true.

        Parameters
        ----------
        z : ndarray, shape (4,)
            ``[Vg, a1, ωx, ωz]``.
        R : ndarray, shape (4, 4)
            Measurement noise.
        mask : ndarray, shape (4,), bool
        Q : ndarray, shape (4, 4), optional
            Process noise for this tick (default: the base).
        u : ndarray, shape (4,), optional
            Control term ``B·u`` (product mode: ``[dt·ā, ā, 0, 0]``).
        """
        kf = self.kf
        kf.Q = self.matrices.Q_base if Q is None else np.asarray(Q)
        kf.predict(u=None if u is None else np.asarray(u, dtype=np.float64).reshape(N_STATE, 1))
        rows = np.flatnonzero(mask)
        if rows.size:
            kf.update(
                np.asarray(z, dtype=np.float64)[rows].reshape(-1, 1),
                R=np.asarray(R)[np.ix_(rows, rows)],
                H=self.matrices.H[rows],
            )

    def outputs(self) -> tuple[FloatArray, FloatArray]:
        """``Z1 = H1·X`` (eq. (6)) and its std ``sqrt(diag(H1·P·H1ᵀ))``; shapes (3,), (3,)."""
        H1 = self.matrices.H1
        return H1 @ self.x, np.sqrt(np.diag(H1 @ self.P @ H1.T))
