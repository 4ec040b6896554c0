"""MDSF: multi-source data structured fusion, ``method.md`` §1 (source 000, eq. (1)-(9)).

Per wheeled vehicle, a linear Kalman filter over the state ``X = [V1, a1, ωx, ωz]`` (forward
speed and forward acceleration at the IMU, pitch rate, yaw rate) turns GNSS velocity, IMU
acceleration and gyro rates into the ground speed of each driven wheel's contact point; with the
wheel's rim speed that gives its slip, eq. (8)(9).

Two modes (:class:`MdsfMode`):

``paper``
    Exactly the source: ``dt = 0.2 s``, ``A``, ``H``, ``H1`` of eq. (6), observation
    ``Z = [Vg, a1, ωx, ωz]`` with ``a1`` the accelerometer's forward reading as it comes
    (gravity included: the source is silent on it), the latest GNSS sample taken as is, the
    standard recursion of eq. (7). While GNSS is lost the reference-speed filter of §3 carries
    the speed (:mod:`estimator.reference_speed`).

``product``
    What a field needs where the source is silent (each point is tested). The state grows to
    ``[V1, a1, ωx, ωz, b_a, e_L, e_R, D]`` (:class:`MdsfState`); outputs are still ``H1·X``:

    * **gravity**: the forward specific force carries ``g·sinθ``; ``a_fwd = f_y − g·sinθ`` with
      the pitch from the GNSS attitude and the integrated pitch rate in a Kalman filter with
      the pitch-gyro bias (learnt against the GNSS pitch, and from the gyro itself while the
      vehicle stands), the yaw-gyro bias learnt against the GNSS heading; the pitch error's
      gravity leak is part of the accelerometer noise;
    * **the accelerometer drives the speed** (``u`` of the predict): ``V1(k+1) = V1(k) +
      dt·(ā − b_a)`` with ``ā`` the mean forward acceleration over ``(t_k, t_k+1]``. Taking
      ``a1`` from the previous tick, as eq. (6) does, makes the speed lag by ``dt·a`` (0.2 m/s
      at 1 m/s² and 0.2 s); ``a1`` holds the tick's mean acceleration, ``b_a`` the
      accelerometer bias;
    * **wheel speeds as measurements**: each rim speed is ``r·W = V_wheel + e_wheel`` with the
      *rim excess* ``e`` (slip in m/s) a state: it scales with the speed at constant slip
      ratio, follows the traction demand through a tyre model whose gain (the traction curve's
      local slope) is learnt online while GNSS is fused (``slip_per_demand`` its prior), wanders
      slowly, opens when the demand changes beyond the accelerometer noise and when a rim
      speed jumps away from its prediction (wet patch). Wheel and accelerometer then carry
      the fast part of the speed, GNSS the slow part; slip is
      ``(r·W − V)/max(r·W, V)`` with ``V = H1·X`` and ``r·W = V + e`` the *filtered* rim
      speed (the wheel fit weighed by its std against the prediction, so a slow wheel's
      few-edge fit does not pass its noise straight into the slip; the rows' rim speed and
      ``ω`` are that filtered value);
    * **RTK positions as distance**: the source uses only the GNSS velocity, whose noise (5 %
      in its own scenarios) leaks into the wheel speeds; an RTK receiver's position is good to
      centimetres. Eq. (1) applied to the displacement between consecutive fixes gives the
      distance travelled along the body's forward axis; its sum is fused as a measurement of
      the distance state ``D`` (``D' = D + dt·V1``), so over a few seconds the speed is pinned
      to about ``σ_pos/T`` instead of averaging the Doppler noise. Chains break at gaps
      (outage, RTK float); each new chain has its own origin, which carries no speed
      information;
    * **GNSS outliers** are gated by the innovation chi-square of the ``Vg`` row (with a floor)
      and counted; a persistent disagreement re-acquires the GNSS speed after ``reacquire_s``
      (flag RESET);
    * **time alignment**: every source is put on the filter tick by its own time stamp (GNSS
      speed moved to the tick with the IMU acceleration and the lever-arm rates, acceleration
      averaged over the tick window, body rates fitted over it and taken at the tick, wheel
      speed fitted and evaluated at the tick, see :mod:`estimator.wheel_speed`);
    * **lever arms**: the forward speed of a body point ``(x, y, z)`` from ``O`` is
      ``V0 + ωz·x − ωx·z``, so with the IMU at ``(x_i, y_i, h0)`` and the antenna at
      ``(x_a, y_a, h0 + h1)`` the observation and output rows become
      ``Vg = V1 − h1·ωx + (x_a − x_i)·ωz`` and ``VL,R = V1 + h0·ωx − (x_i ± b/2)·ωz``; zero
      offsets give the source's ``H`` and ``H1``;
    * **default tick 0.1 s** (10 Hz), faster than the source's 0.2 s: a longer tick lags in
      transients, a shorter one fuses wheel-speed fits whose windows overlap more (correlated
      errors); the measurements are in ``docs/perf/estimator.md``.

The batched engine (:mod:`estimator.mdsf.engine`) steps many vehicles with these matrices;
:class:`MdsfFilter` is the per-vehicle reference built on ``filterpy.kalman.KalmanFilter``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import IntEnum, StrEnum

import numpy as np
import numpy.typing as npt
from filterpy.kalman import KalmanFilter

from estimator._arrays import FloatArray
from estimator.config import ConfigError, VehicleGeometry, WheeledRearDriveConfig

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

GRAVITY_MPS2 = 9.80665
"""Standard gravity [m/s²]."""


class MdsfMode(StrEnum):
    """Which MDSF formulation to run."""

    PAPER = "paper"
    PRODUCT = "product"


class MdsfState(IntEnum):
    """Indices of the MDSF state.

    The source's state ``X = [V1, a1, ωx, ωz]`` (eq. (6)) is the first four; ``paper`` mode uses
    exactly those. ``product`` mode adds the accelerometer bias, per driven wheel the rim
    speed's excess over the contact point's ground speed (``r·W − V``, the slip in m/s), and the
    distance the IMU point travelled along the body's forward axis (``D' = V1``, the integral
    of eq. (2); its origin is arbitrary, re-set with each chain of RTK positions).
    """

    V1 = 0
    A1 = 1
    OMEGA_X = 2
    OMEGA_Z = 3
    ACCEL_BIAS = 4
    RIM_EXCESS_LEFT = 5
    RIM_EXCESS_RIGHT = 6
    DIST = 7


class MdsfObs(IntEnum):
    """Indices of the observation: the source's ``Z = [Vg, a1, ωx, ωz]`` (eq. (6)), and in
    product mode the two rim speeds ``r·W`` (left, right) and the along-track distance from
    the RTK positions."""

    VG = 0
    A1 = 1
    OMEGA_X = 2
    OMEGA_Z = 3
    RIM_LEFT = 4
    RIM_RIGHT = 5
    DIST = 6


class MdsfOut(IntEnum):
    """Indices of the output ``Z1 = [Vg, VL, VR]`` (eq. (6))."""

    VG = 0
    VL = 1
    VR = 2


N_STATE_PAPER = 4
N_OBS_PAPER = 4
N_STATE_PRODUCT = len(MdsfState)
N_OBS_PRODUCT = len(MdsfObs)


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
        Filter interval [s] (product mode; default 0.1 s). ``paper`` uses the source's 0.2 s.
    speed_walk_mps_per_sqrt_s : float
        Product mode: random walk of the speed not explained by the accelerometer (pitch error,
        scale) [m/s/√s].
    accel_bias_std_mps2 : float
        Product mode: prior std of the accelerometer bias [m/s²].
    accel_bias_extra_walk_mps2_per_sqrt_s : float
        Product mode: random walk of the bias state on top of the sensor's own
        (``NoiseConfig.accel_bias_walk_mps2``): the state also takes up gravity leaking through
        a pitch error (``g·δθ``), which drifts while the pitch is only integrated [m/s²/√s].
    rim_excess_walk_mps_per_sqrt_s : float
        Product mode: random walk of each wheel's rim-speed excess ``r·W − V`` (slip in m/s)
        at standstill [m/s/√s].
    rim_excess_walk_rel_per_sqrt_s : float
        Its part proportional to the speed (slip changes with soil and load) [1/√s].
    slip_demand_gain : float
        Product mode: slip change per change of traction demand (``ds/d(f/g)``, about the tyre
        curve's slope); while the demand changes the rim-excess variance grows by
        ``(gain·|V|/g)²·2·D·|Δf|`` per tick, ``f`` the low-passed forward specific force
        (acceleration plus slope, what the tyres must transmit) and ``D`` its recent change, so
        a change ``D`` opens the rim excess by ``gain·|V|·D/g`` in std [-].
    slip_per_demand : float
        Product mode: tyre model, rim-excess change per speed and per change of traction
        demand, ``Δe ≈ k·V·Δ(f/g)`` (about the inverse slope of the traction curve over the
        driven axle's load share, times ``1/(1−s)²``); drives the predict, the rows correct
        its error. The slope depends on the soil and on how far up the curve the tyre works
        (it steepens toward saturation), so ``k`` is learnt online per vehicle
        (``tyre_gain_tau_s``); this value is the prior it starts from and is shrunk toward
        (1.0: about the slope at moderate demand on medium soil). The model also runs through
        GNSS outages. 0 turns it off [-].
    tyre_gain_tau_s : float
        Product mode: memory of the online fit of the tyre model's gain (the traction curve's
        local slope ``dε/d(f/g)``, ``ε`` the measured rim excess per speed while GNSS is fused);
        0 keeps ``slip_per_demand`` fixed [s].
    tyre_gain_prior : float
        Weight of ``slip_per_demand`` in that fit, as a spread of demand ``Σ(Δf/g)²`` the data
        must show before it outweighs the prior (about 1 s of ±0.1 g swings at 10 Hz) [-].
    tyre_gain_range : tuple of float
        Bounds of the learnt gain as factors of ``slip_per_demand`` [-].
    slip_model_tau_s : float
        Time constant of the demand low-pass the tyre model follows [s].
    slip_jump_sigma : float
        Product mode: a rim speed more than this many sigma off its prediction opens the rim
        excess by the unexplained innovation (the slip jumped: wet patch, soil change) [-].
        Lower opens on white noise alone (each time loosening the speed), higher misses jumps
        of a few sigma (a slow wheel in a wet patch); see ``docs/perf/estimator.md``.
    rim_drift_tau_s : float
        Product mode: time constant of the running mean of each rim row's innovation; a mean
        beyond ``rim_drift_sigma`` of its white-noise spread opens that wheel's rim excess
        (slip moving with what the accelerometer cannot see: drawbar, soil); 0 turns it off [s].
    rim_drift_sigma : float
        Threshold of that test, in standard deviations of the running mean [-].
    outage_rim_drift_share : float
        Share of that extra noise kept while GNSS is lost (no fused GNSS speed for more than
        ``gnss_timeout_s``): without a ground reference a persistent rim innovation is as
        likely the accelerometer-driven speed drifting (pitch error, bias) as the slip moving,
        so only this part opens the rim excess; 1 keeps it all, 0 closes it [-].
    outage_demand_share : float
        Share of the demand-driven rim-excess noise (``slip_demand_gain``) kept while GNSS is
        lost. The tyre model's control term already moves the rim excess by the slip change it
        expects; the opened variance lets the rows put the rest there. With GNSS that is
        cheap (the speed stays pinned); without it, an opened rim excess soaks up the
        accelerometer-driven speed's drift instead, while none at all leaves the tyre model's
        own error uncorrected over a long outage. The default (0.03, about a sixth in std)
        lets the tyre model carry nearly all of the slip's response to demand; the jump and
        drift tests still open the rim excess (``docs/perf/estimator.md``) [-].
    outage_slip_std : float
        Product mode, GNSS lost: bound on each rim excess's prior std as a share of its rim
        speed, ``σ_e ≤ outage_slip_std·|r·W|`` (the tyre model's slip range about the last
        anchored slip). The inertial speed's error grows without bound through an outage
        while a pulling tyre's slip stays within a few pp, so a rim disagreement beyond this
        moves the speed and the accelerometer bias, not the slip; 0 turns it off [-].
    outage_slip_tau_s : float
        Product mode, GNSS lost: time constant with which each rim excess reverts to its
        last GNSS-anchored slip ratio times the speed, ``e' = φ·e + (1 − φ)·ε_a·V1``,
        ``φ = exp(−dt/τ)``, with the stationary std ``outage_slip_std·|V1|`` [s].
    outage_anchor_tau_s : float
        Memory of the slip an outage reverts to: a least-squares slip ratio over the drive
        with GNSS, forgotten with this time constant [s].
    outage_bias_walk_mps2_per_sqrt_s : float
        Product mode, GNSS lost: extra random walk of the accelerometer-bias state, which then
        also carries what the leak's growth (``MdsfEngine._leak_into_bias``) leaves out, such
        as sway the tilt track does not follow; the rims, their slip held by
        ``outage_slip_std``, observe it; 0 leaves the bias the sensor's walk and the leak's
        growth [m/s²/√s].
    outage_step_window_s : float
        Product mode, GNSS lost: length of the window over which a slip step is tested
        (:mod:`estimator.mdsf.outage_step`; the step at its middle, so found half a window
        late); 0 turns the test off [s].
    outage_step_z : float
        Posterior mean of a step over its posterior std above which it is taken [-].
    outage_step_min : float
        Smallest step taken (slip ratio) [-].
    outage_step_prior : float
        Prior 1-sigma of a step (slip ratio): the estimate is shrunk toward 0 by it [-].
    outage_step_turn_load_s : float
        Prior 1-sigma of the mean slip's change per lateral acceleration ``V1·|ωz|`` [s].
    outage_step_yaw_misalign_rad : float
        Prior 1-sigma of the IMU's yaw misalignment, which leaks ``V1·ωz`` into ``ā`` [rad].
    outage_step_imu_offset_m : float
        Prior 1-sigma of the IMU's forward offset, which adds ``ωz²·y`` to ``ā`` [m].
    zupt_speed_mps : float
        Product mode: both rim speeds at or below this (and GNSS, if any, below twice it) mean
        the vehicle stands: ``V0 = 0`` is fused (zero-velocity update); 0 turns it off [m/s].
    force_filter_tau_s : float
        Time constant of that low-pass [s].
    rim_texture_rel : float
        Product mode: short-term scatter of a rim speed around the contact point's speed plus
        its mean excess, relative to the speed (soil texture, lugs; treated as measurement
        noise of the rim-speed rows) [-].
    wheel_noise_scale : float
        Product mode: factor on the wheel-speed front end's std (its errors are correlated from
        tick to tick: the fit windows overlap and the tooth pattern repeats every turn).
    accel_walk_mps2_per_sqrt_s : float
        Paper mode: random walk of ``a1`` (the ``Qa`` of eq. (7) per second) [m/s²/√s].
    paper_speed_walk_mps_per_sqrt_s : float
        Paper mode ``Qv`` per second [m/s/√s].
    rate_walk_radps_per_sqrt_s : float
        Random walk of ``ωx``, ``ωz`` (``Qω`` per second) [rad/s/√s].
    gate_chi2 : float
        Innovation chi-square (1 degree of freedom) above which a GNSS speed is rejected
        (product mode; 10.83 is the 99.9 % point).
    gate_floor_mps : float
        Floor added to the innovation std of the GNSS gate at standstill: innovations below
        ``gate_floor·√gate_chi2`` are never rejected [m/s].
    gate_floor_rel : float
        Its part proportional to the speed, ``floor = hypot(gate_floor_mps, rel·|V1|)``: a
        speed wandering by a share of itself must not lock GNSS out at speed, and a 0.2 m/s
        outlier must not pass at a creep (the receiver's reported std enters the gate through
        ``R``) [-].
    reacquire_s : float
        After GNSS speeds were rejected this long without a break, the next one resets the
        speed (product mode) [s].
    gnss_timeout_s : float
        No fused GNSS speed for this long flags the estimate DEGRADED [s].
    max_speed_var_mps2 : float
        A speed variance above this (or any non-finite value) counts as divergence: reset.
    initial_speed_std_mps : float
        Speed std right after a (re)initialisation.
    attitude_tau_s : float
        Product mode: time constant of the heading track's pull to the GNSS heading
        (:func:`estimator.tilt.yaw_fix_update`), and the correlation time taken for the
        roll's error where the yaw rate carries it into the pitch rate, and the pitch's into
        the roll rate [s]. Pitch and roll have no time constant: each is a Kalman filter with
        its gyro's bias (:func:`estimator.tilt.pitch_kf_update`).
    pitch_leak_corr_s : float
        Product mode: correlation time taken for the pitch filter's error where its gravity
        leak (``g·δθ``) is added to the accelerometer noise as white noise,
        ``g²·P_θθ·pitch_leak_corr_s/dt`` per tick [s]. An assumption, not derived from the
        filter (``docs/perf/estimator.md``). While GNSS is lost the leak's growth goes to the
        accelerometer-bias state instead (a drift, not white noise: ``MdsfEngine._leak_into_bias``).
    gyro_bias_tau_s : float
        Product mode: time constant with which the yaw-gyro bias is learnt against the GNSS
        heading [s].
    pitch_std_rad : float
        Product mode: 1-sigma noise of the receiver's pitch (receivers do not report it); sets
        how much gravity leaks into the forward acceleration through the pitch error [rad].
    gyro_bias_std_radps : float
        Product mode: prior std of the pitch gyro's bias (MEMS turn-on bias, a few mrad/s)
        in the pitch filter (:func:`estimator.tilt.pitch_kf_update`) [rad/s].
    gyro_bias_walk_radps_per_sqrt_s : float
        Product mode: random walk of that bias (in-run drift) [rad/s/√s].
    standstill_speed_mps : float
        Product mode: a GNSS fix whose horizontal speed is below this, after one that was too,
        closes an interval the vehicle stood through: the pitch gyro's mean reading over it is
        a measurement of its bias (zero angular rate). 0 turns it off [m/s].
    standstill_rate_floor_radps : float
        Product mode: noise floor of that measurement (engine vibration, a vehicle creeping
        below the speed threshold) [rad/s].
    gnss_vertical_vel_factor : float
        Product mode: the receiver's vertical velocity noise over its horizontal one (typically
        1.5–2, the satellites being above); sets the noise of the pitch taken from the GNSS
        velocity's elevation where the receiver gives no attitude (one antenna) [-].
    velocity_pitch_floor_rad : float
        Product mode: noise floor of that velocity pitch: the body pitching on its tyres
        against its path [rad].
    accel_roll_floor_rad : float
        Product mode: noise floor of the roll taken from the lateral accelerometer where the
        receiver gives no roll (body sway, side slip, the sensor's bias) [rad].
    gnss_noise_adapt : float
        Weight of each accepted GNSS innovation in the running estimate of the GNSS speed noise
        (0 turns the adaptation off; the receiver's or configured noise is always the floor).
    gnss_distance_gap_s : float
        Product mode: RTK-fixed positions at most this far apart chain into an along-track
        distance (eq. (1) applied to the displacement), fused as a measurement of the distance
        state: centimetre position noise over seconds pins the speed far tighter than the
        Doppler speed's percent noise. A longer gap (outage, float spell) starts a new chain,
        because the straight projection over the gap would miss the turns; 0 turns the
        distance off [s].
    gnss_distance_gate_floor_m : float
        Floor added to the innovation std of the distance gate (as ``gate_floor_mps`` for the
        speed): a distance more than ``√gate_chi2`` times off its prediction (a wrong fix, a
        position jump) is not fused and the next fix starts a new chain [m].
    wheel_clock_accel_tau_s : float
        Product mode: time constant of the low-pass on the rate of each wheel's filtered ground
        speed, the acceleration ``a_w`` by which the wheel clock offset moves the rims
        (``r·W + δ_w·a_w``) and against which it is learnt. Not the accelerometer's force:
        vibration, body sway and leftover gravity are in that force, not in the rims [s].
    valid_slip_std_max_pct : float
        Product mode: a slip whose 1-sigma exceeds this (or is unknown) is not valid: no
        value, no valid flag (paper mode keeps the source's rule). The default is the tyre
        model's own slip range, ``outage_slip_std`` (4 %): a slip known worse than the tyre
        alone would say (its 2-sigma band ±8 pp spans a working tyre's 5-15 %) tells a user
        nothing to act on, while an outage's slip, held near its anchor within that range,
        stays a reading (a very large value turns the rule off) [percentage points].
    course_tau_s : float
        Product mode, a receiver without heading (one antenna): time constant of the course's
        pull to the GNSS velocity's direction less the antenna's lever-arm velocity; between
        fixes the course is the yaw rate integrated (``frontend._TiltTrack._course_update``).
        The antenna's own course swings with a swaying mast and reverses when the mast's
        ``h1·ωx`` outruns the speed [s].
    gnss_clock_lowpass_tau_s : float
        Product mode: time constant of each of the two first-order low-passes the GNSS clock
        filter runs its speed and acceleration through (``calibration.CalibrationBank.
        observe_gnss``). ``Vg = V − δ_g·a`` is linear, so it holds for the low-passed signals;
        a cab swaying at 0.3-3 Hz on a tall mast moves the antenna by metres per second
        squared the slow driving accelerations do not, and the low-passes take that out [s].
    gnss_clock_apply_std_s : float
        Product mode: the GNSS clock offset moves the fixes only once its std is below this
        bound, by a weight that rises from 0 there to full at half of it, times the shrinkage
        ``δ²/(δ² + σ²)`` (``calibration.CalibrationBank.gnss_offset_s``): an estimate still
        learning, or one no larger than its std, moves them little [s].
    """

    mode: MdsfMode = MdsfMode.PRODUCT
    tick_s: float = 0.1
    speed_walk_mps_per_sqrt_s: float = 0.01
    accel_bias_std_mps2: float = 0.1
    accel_bias_extra_walk_mps2_per_sqrt_s: float = 0.003
    rim_excess_walk_mps_per_sqrt_s: float = 0.005
    rim_excess_walk_rel_per_sqrt_s: float = 0.002
    slip_demand_gain: float = 0.75
    slip_per_demand: float = 1.0
    slip_model_tau_s: float = 0.3
    tyre_gain_tau_s: float = 60.0
    tyre_gain_prior: float = 0.1
    tyre_gain_range: tuple[float, float] = (0.2, 3.0)
    slip_jump_sigma: float = 3.5
    rim_drift_tau_s: float = 1.0
    rim_drift_sigma: float = 2.0
    outage_rim_drift_share: float = 0.3
    outage_demand_share: float = 0.03
    outage_slip_std: float = 0.04
    outage_slip_tau_s: float = 1.0
    outage_anchor_tau_s: float = 20.0
    outage_bias_walk_mps2_per_sqrt_s: float = 0.02
    outage_step_window_s: float = 6.0
    outage_step_z: float = 6.0
    outage_step_min: float = 0.015
    outage_step_prior: float = 0.05
    outage_step_turn_load_s: float = 0.05
    outage_step_yaw_misalign_rad: float = 0.05
    outage_step_imu_offset_m: float = 2.0
    zupt_speed_mps: float = 0.0
    force_filter_tau_s: float = 0.3
    rim_texture_rel: float = 0.003
    wheel_noise_scale: float = 1.0
    accel_walk_mps2_per_sqrt_s: float = 1.0
    paper_speed_walk_mps_per_sqrt_s: float = 0.05
    rate_walk_radps_per_sqrt_s: float = 0.3
    gate_chi2: float = 10.83
    gate_floor_mps: float = 0.02
    gate_floor_rel: float = 0.03
    reacquire_s: float = 3.0
    gnss_timeout_s: float = 1.0
    max_speed_var_mps2: float = 100.0
    initial_speed_std_mps: float = 0.5
    attitude_tau_s: float = 1.0
    pitch_leak_corr_s: float = 1.0
    pitch_std_rad: float = 0.005
    gyro_bias_tau_s: float = 5.0
    gyro_bias_std_radps: float = 0.005
    gyro_bias_walk_radps_per_sqrt_s: float = 1e-4
    standstill_speed_mps: float = 0.05
    standstill_rate_floor_radps: float = 5e-4
    gnss_vertical_vel_factor: float = 1.5
    velocity_pitch_floor_rad: float = 0.002
    accel_roll_floor_rad: float = 0.05
    gnss_noise_adapt: float = 0.02
    gnss_distance_gap_s: float = 1.0
    gnss_distance_gate_floor_m: float = 0.1
    wheel_clock_accel_tau_s: float = 0.3
    valid_slip_std_max_pct: float = 4.0
    course_tau_s: float = 1.0
    gnss_clock_lowpass_tau_s: float = 0.2
    gnss_clock_apply_std_s: float = 0.03

    def __post_init__(self) -> None:
        if not isinstance(self.mode, MdsfMode):
            try:
                object.__setattr__(self, "mode", MdsfMode(self.mode))
            except ValueError as exc:
                raise ConfigError(f"mode must be one of {[m.value for m in MdsfMode]}") from exc
        for f in dataclasses.fields(self):
            if f.name in (
                "mode",
                "gnss_noise_adapt",
                "slip_demand_gain",
                "zupt_speed_mps",
                "outage_step_window_s",
                "slip_per_demand",
                "tyre_gain_tau_s",
                "tyre_gain_range",
                "rim_drift_tau_s",
                "outage_rim_drift_share",
                "outage_demand_share",
                "outage_slip_std",
                "outage_bias_walk_mps2_per_sqrt_s",
                "gnss_distance_gap_s",
                "standstill_speed_mps",
            ):
                continue
            _check(f.name, getattr(self, f.name))
        lo, hi = self.tyre_gain_range
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= 1.0 <= hi):
            raise ConfigError("tyre_gain_range must be (lo, hi) with 0 < lo <= 1 <= hi")
        for name in (
            "slip_demand_gain",
            "zupt_speed_mps",
            "outage_step_window_s",
            "slip_per_demand",
            "tyre_gain_tau_s",
            "rim_drift_tau_s",
            "outage_slip_std",
            "outage_bias_walk_mps2_per_sqrt_s",
            "gnss_distance_gap_s",
            "standstill_speed_mps",
        ):
            _check(name, getattr(self, name), positive=False)
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0")
        if not 0.001 <= self.tick_s <= 1.0:
            raise ConfigError(f"tick_s must be within 0.001..1 s, got {self.tick_s!r}")
        for name in ("outage_rim_drift_share", "outage_demand_share"):
            share = getattr(self, name)
            ok = isinstance(share, int | float) and math.isfinite(share) and 0.0 <= share <= 1.0
            if not ok:
                raise ConfigError(f"{name} must be within [0, 1]")
        if not (math.isfinite(self.gnss_noise_adapt) and 0.0 <= self.gnss_noise_adapt < 1.0):
            raise ConfigError("gnss_noise_adapt must be within [0, 1)")

    @property
    def dt_s(self) -> float:
        """The interval actually used: 0.2 s in paper mode, ``tick_s`` in product mode."""
        return 0.2 if self.mode is MdsfMode.PAPER else self.tick_s

    @property
    def tick_ns(self) -> int:
        return round(self.dt_s * 1e9)

    @property
    def n_state(self) -> int:
        """State dimension: 4 (paper, eq. (6)) or 8 (product)."""
        return N_STATE_PAPER if self.mode is MdsfMode.PAPER else N_STATE_PRODUCT

    @property
    def n_obs(self) -> int:
        """Observation dimension: 4 (paper) or 7 (product)."""
        return N_OBS_PAPER if self.mode is MdsfMode.PAPER else N_OBS_PRODUCT


def transition_matrix(dt_s: float) -> FloatArray:
    """``A`` of eq. (6): ``V1 += dt·a1``, other states constant; shape (4, 4)."""
    a = np.eye(N_STATE_PAPER)
    a[MdsfState.V1, MdsfState.A1] = dt_s
    return a


def observation_matrix(h1_m: float) -> FloatArray:
    """``H`` of eq. (6), shape (4, 4): ``Vg = V1 − h1·ωx``, identity below."""
    h = np.eye(N_OBS_PAPER, N_STATE_PAPER)
    h[MdsfObs.VG, MdsfState.OMEGA_X] = -h1_m
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
    h = np.zeros((len(MdsfOut), N_STATE_PAPER))
    h[MdsfOut.VG] = [1.0, 0.0, -h1_m, antenna_x_m - imu_x_m]
    h[MdsfOut.VL] = [1.0, 0.0, h0_m, -imu_x_m - half]
    h[MdsfOut.VR] = [1.0, 0.0, h0_m, -imu_x_m + half]
    return h


def product_transition(dt_s: float) -> FloatArray:
    """Product-mode transition, shape (8, 8), with the control
    ``u = [dt·ā, ā, 0, 0, 0, 0, 0, dt²·ā/2]``:

    ``V1' = V1 + dt·(ā − b)``, ``a1' = ā − b`` (the tick's mean acceleration),
    ``D' = D + dt·V1 + dt²·(ā − b)/2`` (the distance integrates eq. (2)'s ``V1``), ``ωx, ωz,
    b`` and the rim excesses constant (random walks).
    """
    f = np.eye(N_STATE_PRODUCT)
    f[MdsfState.V1, MdsfState.ACCEL_BIAS] = -dt_s
    f[MdsfState.A1, MdsfState.A1] = 0.0
    f[MdsfState.A1, MdsfState.ACCEL_BIAS] = -1.0
    f[MdsfState.DIST, MdsfState.V1] = dt_s
    f[MdsfState.DIST, MdsfState.ACCEL_BIAS] = -0.5 * dt_s * dt_s
    return f


def product_observation(geometry: VehicleGeometry) -> FloatArray:
    """Product-mode observation matrix, shape (7, 8).

    Rows: ``Vg = V1 − h1·ωx + (x_a − x_i)·ωz`` (eq. (2) with lever arm), ``a1`` (unused: the
    accelerometer drives the predict), ``ωx``, ``ωz``, each rim speed
    ``r·W = V_wheel + e_wheel`` with ``V_wheel`` from eq. (4)/(5) (lever arms included), and
    the along-track distance ``D`` (the front end moves the antenna's to the IMU point).
    """
    g = geometry
    xa, xi = g.antenna_offset_m[0], g.imu_offset_m[0]
    h1 = output_matrix(g.h0_m, g.h1_m, g.track_width_m, xa, xi)
    h = np.zeros((N_OBS_PRODUCT, N_STATE_PRODUCT))
    h[MdsfObs.VG, :N_STATE_PAPER] = h1[MdsfOut.VG]
    h[MdsfObs.A1, MdsfState.A1] = 1.0
    h[MdsfObs.OMEGA_X, MdsfState.OMEGA_X] = 1.0
    h[MdsfObs.OMEGA_Z, MdsfState.OMEGA_Z] = 1.0
    h[MdsfObs.RIM_LEFT, :N_STATE_PAPER] = h1[MdsfOut.VL]
    h[MdsfObs.RIM_LEFT, MdsfState.RIM_EXCESS_LEFT] = 1.0
    h[MdsfObs.RIM_RIGHT, :N_STATE_PAPER] = h1[MdsfOut.VR]
    h[MdsfObs.RIM_RIGHT, MdsfState.RIM_EXCESS_RIGHT] = 1.0
    h[MdsfObs.DIST, MdsfState.DIST] = 1.0
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
    """Constant matrices of one vehicle's filter (``n`` = 4 paper, 8 product; ``m`` = 4, 7).

    Attributes
    ----------
    F : ndarray, shape (n, n)
        Transition (``A`` of eq. (6) in paper mode; :func:`product_transition`).
    H : ndarray, shape (m, n)
        Observation matrix (eq. (6); :func:`product_observation`).
    H1 : ndarray, shape (3, n)
        Output matrix (eq. (6), with lever arms in product mode).
    v0_row : ndarray, shape (n,)
        ``V0 = v0_row·X`` (eq. (3), lever arm in product mode).
    Q_base : ndarray, shape (n, n)
        Process noise without the per-tick terms (product mode adds the accelerometer noise to
        ``V1``/``a1`` and the adaptive rim-excess noise).
    dt_s : float
    """

    F: FloatArray
    H: FloatArray
    H1: FloatArray
    v0_row: FloatArray
    Q_base: FloatArray
    dt_s: float


def mdsf_matrices(config: MdsfConfig, vehicle: WheeledRearDriveConfig) -> MdsfMatrices:
    """Build the matrices of eq. (6)/(7) for one vehicle (see the module docstring per mode)."""
    g = vehicle.geometry
    dt = config.dt_s
    qw = config.rate_walk_radps_per_sqrt_s**2 * dt
    if config.mode is MdsfMode.PAPER:
        F = transition_matrix(dt)
        H = observation_matrix(g.h1_m)
        H1 = output_matrix(g.h0_m, g.h1_m, g.track_width_m)
        v0_row = np.array([1.0, 0.0, g.h0_m, 0.0])
        qv = config.paper_speed_walk_mps_per_sqrt_s**2 * dt
        qa = config.accel_walk_mps2_per_sqrt_s**2 * dt
        Q = np.diag([qv, qa, qw, qw])
    else:
        xa, xi = g.antenna_offset_m[0], g.imu_offset_m[0]
        F = product_transition(dt)
        H = product_observation(g)
        H1 = np.zeros((len(MdsfOut), N_STATE_PRODUCT))
        H1[:, :N_STATE_PAPER] = output_matrix(g.h0_m, g.h1_m, g.track_width_m, xa, xi)
        v0_row = np.zeros(N_STATE_PRODUCT)
        v0_row[:N_STATE_PAPER] = [1.0, 0.0, g.h0_m, -xi]
        qv = config.speed_walk_mps_per_sqrt_s**2 * dt
        qb = (
            vehicle.noise.accel_bias_walk_mps2**2 + config.accel_bias_extra_walk_mps2_per_sqrt_s**2
        ) * dt
        qe = config.rim_excess_walk_mps_per_sqrt_s**2 * dt
        Q = np.diag([qv, 0.0, qw, qw, qb, qe, qe, 0.0])
    return MdsfMatrices(F=F, H=H, H1=H1, v0_row=v0_row, Q_base=Q, dt_s=dt)


class MdsfFilter:
    """One vehicle's MDSF filter on ``filterpy.kalman.KalmanFilter`` (reference implementation).

    The batched engine must agree with it to rounding (tested). Each :meth:`step` is a predict
    followed by an update with the active observation rows.

    Parameters
    ----------
    config : MdsfConfig
    vehicle : WheeledRearDriveConfig
    """

    def __init__(self, config: MdsfConfig, vehicle: WheeledRearDriveConfig) -> None:
        self.config = config
        self.vehicle = vehicle
        self.matrices = mdsf_matrices(config, vehicle)
        self.n = config.n_state
        kf = KalmanFilter(dim_x=self.n, dim_z=config.n_obs)
        kf.F = self.matrices.F.copy()
        kf.H = self.matrices.H.copy()
        kf.Q = self.matrices.Q_base.copy()
        kf.B = np.eye(self.n)
        self.kf = kf

    def initialize(self, x: FloatArray, P: FloatArray) -> None:
        """Set the state ``x`` (n,) and covariance ``P`` (n, n)."""
        self.kf.x = np.asarray(x, dtype=np.float64).reshape(self.n, 1).copy()
        self.kf.P = np.asarray(P, dtype=np.float64).copy()

    @property
    def x(self) -> FloatArray:
        """State, shape (n,)."""
        return np.asarray(self.kf.x, dtype=np.float64).reshape(self.n)

    @property
    def P(self) -> FloatArray:  # noqa: N802 (filterpy's name for the covariance)
        """Covariance, shape (n, n)."""
        return np.asarray(self.kf.P, dtype=np.float64)

    def predict(
        self, Q: FloatArray | None = None, u: FloatArray | None = None, F: FloatArray | None = None
    ) -> None:
        """Time update, eq. (7): ``x = F·x + u``, ``P = F·P·Fᵀ + Q``.

        Parameters
        ----------
        Q : ndarray, shape (n, n), optional
            Process noise for this tick (default: the base).
        u : ndarray, shape (n,), optional
            Control term ``B·u`` (product mode: ``[dt·ā, ā, 0, …]``).
        F : ndarray, shape (n, n), optional
            Transition for this tick (default: the constant one; product mode scales the rim
            excess with the speed change).
        """
        kf = self.kf
        kf.F = self.matrices.F if F is None else np.asarray(F, dtype=np.float64)
        kf.Q = self.matrices.Q_base if Q is None else np.asarray(Q, dtype=np.float64)
        kf.predict(u=None if u is None else np.asarray(u, dtype=np.float64).reshape(self.n, 1))

    def update(self, z: FloatArray, R: FloatArray, mask: npt.NDArray[np.bool_]) -> None:
        """Measurement update, eq. (7), with the observation rows where ``mask`` is true.

        Parameters
        ----------
        z : ndarray, shape (m,)
            Observation (:class:`MdsfObs`).
        R : ndarray, shape (m, m)
            Measurement noise.
        mask : ndarray, shape (m,), bool
        """
        rows = np.flatnonzero(mask)
        if rows.size:
            self.kf.update(
                np.asarray(z, dtype=np.float64)[rows].reshape(-1, 1),
                R=np.asarray(R, dtype=np.float64)[np.ix_(rows, rows)],
                H=self.matrices.H[rows],
            )

    def step(
        self,
        z: FloatArray,
        R: FloatArray,
        mask: npt.NDArray[np.bool_],
        Q: FloatArray | None = None,
        u: FloatArray | None = None,
    ) -> None:
        """One tick: :meth:`predict` then :meth:`update` with the rows where ``mask`` is true."""
        self.predict(Q, u)
        self.update(z, R, mask)

    def outputs(self) -> tuple[FloatArray, FloatArray]:
        """``Z1 = H1·X`` (eq. (6)) and its std ``sqrt(diag(H1·P·H1ᵀ))``; shapes (3,), (3,)."""
        H1 = self.matrices.H1
        return H1 @ self.x, np.sqrt(np.diag(H1 @ self.P @ H1.T))
