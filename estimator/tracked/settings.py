"""The tracked estimator's own frozen configuration (tick, windows, thresholds, noises).

The vehicle's geometry and the source's constants come from
:class:`estimator.config.TrackedConfig`; this is how the estimator runs on any vehicle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from estimator.tracked.model import TrackedMode

__all__ = ["TrackedEstimatorConfig"]


@dataclass(frozen=True, slots=True)
class TrackedEstimatorConfig:
    """How the tracked estimator runs (units in the names; ratios dimensionless).

    Sprocket-ratio thresholds (product recogniser): the slow over the fast sprocket speed
    ``q`` is 1 in straights, ``1/1.42`` in arcs, between them in separated turns and 0 with a
    braked track; ``arc_ratio_max`` and ``straight_ratio_min`` cut between them,
    ``ratio_std`` is the 1-sigma of a measured ``q`` that turns a margin into a confidence.
    A separated-band ``q`` closer to 1 than ``separated_check_sigmas`` times its window noise
    (:func:`~estimator.tracked.recognise.ratio_noise`, from the teeth's position error
    ``sprocket_tooth_std_pitch`` of the pitch and the periods a window holds, the
    acceleration, and ``carry_accel_std_mps2``, the 1-sigma of the odometer acceleration
    that carries each window's speed to the tick) may be a
    straight read through few edges: it must show at least ``separated_yaw_share`` of its
    kinematic yaw rate to be a turn; farther from 1 the ratio alone is the lever.
    ``start_odometer_mps``: an odometer speed above it with sprockets still unread is a start
    from standstill (a straight); so is a tick whose odometer edges end a silence longer than
    ``start_silence_s`` (the gearbox turns, though the windows cannot yet give its speed), and
    the tick before it, held, is backdated with it (a start's first edge comes up to one
    pitch of travel after the lever: ~0.16 s at 0.8 m/s² and 1 cm). No sprocket turns
    faster than the gearbox (its steering ratios are 1, ``1/1.42`` and 0): a sprocket read
    above ``sprocket_over_gearbox_max`` times the odometer's speed at the tick is a stale
    window (at a crawl a sprocket's next edge is not yet overdue while the gearbox brakes to
    a stop) and is read at that bound.
    ``max_yaw_lag_s`` bounds the learned lag ``τ`` used to lead the yaw rate (``ω + τ·ω̇``, less
    ``yaw_lead_noise_radps``, about 3 sigma of what the gyro's noise makes of ``τ·ω̇`` over a
    tick) in the separated-turn check. A steering lever crosses its travel in about
    ``lever_travel_s``; a sprocket or gear ratio changing faster than ``lever_rate_min_per_s``
    (well above what the ratios' noise makes over one tick at speed) and than
    ``lever_noise_sigmas`` times the ratio noise's change over a tick (at a crawl the reads jump
    by more) is a lever moving, and the state is read where it goes.
    Standing, the tick's mean gyro rate is the bias within the gyro's white noise over the
    tick (the zero-rate update, :func:`~estimator.tracked.step.standing_rate_var`), once the
    hull has stopped turning: ``standing_settle_lags`` times its lag ``τ`` after the gearbox
    stopped (:func:`~estimator.tracked.step.hull_settled`). ``zero_rate_std_radps`` is the
    yaw rate's 1-sigma in a track's speed.
    The odometer factors learn only once the gearbox has been steady (acceleration below
    ``learn_accel_max_mps2``, no sprocket settling) for ``learn_steady_s``, several times
    the hull's lag behind its tracks.
    A pivot's driven track slips 10-40 % (it drags the hull round the braked one), so its
    factor is held as an offset from the straight's (same ``K_D``, same ground) that starts
    at ``−initial_pivot_slip`` (the middle of that range), wider
    (``initial_pivot_factor_std``) than the others, the low gear's offset from the straight's
    narrower (``initial_low_offset_std``). An arc's or separated turn's factor is the
    straight's less ``c·θ``, ``θ = B/ρ_t`` its tightness from the sprocket ratio and ``c`` the
    fast track's turn slip per unit tightness, starting at ``initial_turn_slip`` ±
    ``initial_turn_slip_std`` (0.04-0.2 spans firm to soft ground); a slip whose 1-sigma
    exceeds ``slip_std_max_pct`` is not observable and is not given. The traction slip per
    m/s² of acceleration ``κ`` starts at ``initial_accel_slip_s2pm`` (a track's slip grows by
    2-8 % per 0.1 g of pull on firm to soft ground) and is learned from the accelerations.

    The ground under the tracks departs from its mean slip over patches about
    ``ground_patch_m`` long (the filter's ``GROUND_PATCH`` state, a Gauss-Markov process over
    the distance driven) by ``ground_patch_rel_std`` of the ground's slip level (a track's
    slip under a given pull goes inversely with the soil's shear strength, which varies from
    patch to patch by a share of itself), so a firm ground's patches differ by less than a
    soft one's; the level is the traction slip the straight's factor has learnt
    (``1 − F_straight``, :func:`~estimator.tracked.step.patch_std`) at its upper 1-sigma.
    The patch state starts at ``ground_patch_slip_std``. Beside GNSS the patch takes the
    last metres' departure, the factors (walking by ``factor_walk``, slowly: ``K_D`` and the
    ground's mean) what the next kilometre of an outage will drive on. While dead
    reckoning, the along-track position variance grows by what the mean factor's error makes
    over the distance driven and by the patches driven over, which nothing observes
    without GNSS.

    The forward speed is predicted with the accelerometer less gravity's ``g·sin θ`` (the
    filter's pitch ``θ``, carried on the pitch gyro from ``initial_tilt_std_rad``, its
    bias and noise the gyro's figures) and its bias (below); what it does not explain (the
    hull's lever-arm terms) walks by ``speed_walk_mps2`` (m/s per √s), and its white noise (the
    config's ``noise.accel_std_mps2``) is added over each tick
    (:func:`~estimator.tracked.step.accel_speed_var`); the odometer holds the speed every tick.
    The roll ``φ`` (on the roll gyro, from ``initial_tilt_std_rad``) is measured every tick by
    the lateral accelerometer, ``−ω·V − g·cos θ·sin φ``, within its white noise and
    ``lateral_force_std_mps2`` of what that model leaves out (the side-slip's changes, the
    lever arms). A row gives the pitch or roll once its 1-sigma is at most
    ``tilt_reported_std_rad`` (NaN before: the prior, not a measurement).

    The hull's side-slip in turns is the configured ``μ_t``'s times a gain learnt beside
    GNSS (the filter's ``SIDE_SLIP``), 1 ± ``initial_side_slip_std`` at first (grounds resist
    sliding by 0.35-0.8 of the weight), walking by ``side_slip_walk`` per √s. On a side
    slope the hull creeps downhill at a slip angle ``side_creep·sin φ/μ_t`` times that gain
    (:func:`~estimator.tracked.odometer.side_creep`), ``φ`` the filter's roll beyond
    ``creep_roll_sigmas`` of its 1-sigma (which holds the lateral accelerometer's bias: the
    roll takes it in unseen on level ground).

    The accelerometers' biases (forward and lateral) are states (product) from
    ``accel_bias_std_mps2`` (a MEMS unit's turn-on bias, e.g. the ADIS16470's ±0.03 m/s²
    class), walking by ``accel_bias_walk_mps2_rt_s`` (m/s² per √s; its in-run stability,
    1.3e-4 m/s², reached in a few minutes): the forward one enters the speed's prediction
    (``f_y − b_y − g·sin θ``), the lateral one the roll's measurement. Beside GNSS the
    fix's up velocity is fused against ``V·sin θ`` (product; within the fix's horizontal
    velocity 1-sigma times ``gnss_up_to_horizontal_vel_std_ratio``, gated at
    ``gnss_up_gate_nis``, χ²₁ at 99.9 %): it sees the pitch itself, so the forward bias is
    told from it. A receiver's vertical is noisier than its horizontal (every satellite is
    above the antenna: the vertical dilution of precision is 1.5-2 times the horizontal), and
    receivers state one velocity 1-sigma; the ratio's default is the middle of that range.

    The receiver's clock less the IMU's (the filter's ``GNSS_CLOCK``, product) starts at 0 ±
    ``gnss_clock_offset_std_s`` (receivers stamp their epochs 50-150 ms off a vehicle bus's
    clock: transport and buffering) and walks by ``gnss_clock_offset_walk_s_rt_s`` (s per
    √s: two crystals' drift, tens of ppm, over a drive); a fix's position, velocity and up
    velocity are compared with the hull taken back by the fix's age plus it.

    The gyro's noise is the vehicle's: its config's ``gyro`` section names the part fitted
    (:class:`estimator.config.GyroConfig`, :class:`~estimator.tracked.params.VehicleParams`),
    whose figures are typical values. A unit noisier than them is measured while standing
    (product, :mod:`~estimator.tracked.gyro_noise`): its ARW² over the data sheet's, blended
    with ``gyro_noise_prior_pairs`` standing tick pairs at the data sheet's and at most
    ``gyro_noise_ratio_max``, scales the heading's and the bias's process noise.

    Fixed-lag output (product): rows are held one tick, and up to ``report_lag_ticks``
    (0.4 s at the default) while a change is under way, each keeping its own stamp
    (:mod:`estimator.tracked.lag`); a state change seen on a
    tick is backdated over the held ticks that still show the old state while the change
    was already under way (a ratio moving, a sprocket settling, or the yaw acceleration above
    ``onset_yaw_accel_radps2``), and one tick before that run (the sprocket windows read a
    lever about half a window late). Those rows give no slip (the filter ran them with the
    old state's odometer model) and carry ``STATE_BACKDATED``.
    """

    mode: TrackedMode = TrackedMode.PRODUCT
    tick_s: float = 0.1
    odometer_window_s: float = 0.1
    sprocket_window_s: float = 0.3
    sprocket_max_edges: int = 6
    sprocket_hold_s: float = 0.6
    sprocket_missing_s: float = 8.0
    braked_ratio_max: float = 0.1
    arc_ratio_max: float = 0.74
    straight_ratio_min: float = 0.985
    ratio_std: float = 0.01
    separated_yaw_share: float = 0.5
    separated_check_sigmas: float = 3.5
    sprocket_tooth_std_pitch: float = 0.005
    carry_accel_std_mps2: float = 0.05
    start_odometer_mps: float = 0.1
    start_silence_s: float = 0.5
    sprocket_over_gearbox_max: float = 1.2
    max_yaw_lag_s: float = 1.0
    yaw_lead_noise_radps: float = 0.02
    lever_travel_s: float = 0.3
    lever_rate_min_per_s: float = 0.3
    lever_noise_sigmas: float = 2.0
    lever_accel_mps2: float = 0.5
    uncertain_below: float = 0.9
    init_speed_mps: float = 1.0
    gnss_gate_nis: float = 16.0
    gnss_regain_s: float = 2.0
    odometer_std_mps: float = 0.02
    odometer_std_per_mps: float = 0.01
    pivot_odometer_std_per_mps: float = 0.05
    odometer_std_per_mps2: float = 0.3
    learn_accel_max_mps2: float = 0.2
    learn_steady_s: float = 1.5
    standstill_odometer_mps: float = 0.02
    zero_speed_std_mps: float = 0.01
    zero_rate_std_radps: float = 0.001
    standing_settle_lags: float = 5.0
    speed_walk_mps2: float = 0.1
    position_walk_mps: float = 0.015
    lateral_model_error: float = 0.3
    gyro_scale_walk: float = 1e-6
    factor_walk: float = 1e-4
    initial_position_std_m: float = 0.1
    initial_heading_std_rad: float = 0.1
    initial_speed_std_mps: float = 0.2
    initial_gyro_bias_std_radps: float = 1e-3
    initial_tilt_std_rad: float = 0.2
    tilt_reported_std_rad: float = 0.05
    lateral_force_std_mps2: float = 0.3
    initial_gyro_scale_std: float = 0.005
    initial_factor_std: float = 0.03
    initial_pivot_factor_std: float = 0.15
    initial_pivot_slip: float = 0.25
    initial_low_offset_std: float = 0.02
    initial_turn_slip: float = 0.1
    initial_turn_slip_std: float = 0.06
    slip_std_max_pct: float = 3.0
    initial_accel_lag_std_s: float = 0.5
    accel_lag_walk_s: float = 1e-3
    initial_accel_slip_s2pm: float = 0.05
    initial_accel_slip_std_s2pm: float = 0.03
    accel_slip_walk_s2pm: float = 1e-4
    ground_patch_slip_std: float = 0.007
    ground_patch_rel_std: float = 0.15
    ground_patch_m: float = 150.0
    initial_side_slip_std: float = 0.5
    side_slip_walk: float = 1e-3
    side_creep: float = 0.05
    creep_roll_sigmas: float = 2.0
    accel_bias_std_mps2: float = 0.03
    accel_bias_walk_mps2_rt_s: float = 1e-5
    gnss_up_gate_nis: float = 10.83
    gnss_up_to_horizontal_vel_std_ratio: float = 1.75
    gnss_clock_offset_std_s: float = 0.15
    gnss_clock_offset_walk_s_rt_s: float = 2e-4
    gyro_noise_prior_pairs: float = 20.0
    gyro_noise_ratio_max: float = 9.0
    report_lag_ticks: int = 4
    onset_yaw_accel_radps2: float = 0.1

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", TrackedMode(self.mode))
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if isinstance(value, float) and not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if self.report_lag_ticks < 0:
            raise ValueError("report_lag_ticks must be >= 0")
        if self.tick_s <= 0.0 or self.sprocket_max_edges < 2:
            raise ValueError("tick_s must be > 0 and sprocket_max_edges >= 2")
        if not 0.0 < self.braked_ratio_max < self.arc_ratio_max < self.straight_ratio_min < 1.0:
            raise ValueError("need 0 < braked_ratio_max < arc_ratio_max < straight_ratio_min < 1")

    @property
    def tick_ns(self) -> int:
        return round(self.tick_s * 1e9)

    @property
    def lag_ticks(self) -> int:
        """Ticks a row is held before it is given (0 outside the product mode)."""
        return self.report_lag_ticks if self.mode == TrackedMode.PRODUCT else 0

    @property
    def release_reach_ticks(self) -> int:
        """Rows a braked track's release may take its −100 % back from
        (:func:`~estimator.tracked.lag.release`): a sprocket starting from rest shows its first
        edge up to about the lever's travel ``lever_travel_s`` late, in ticks (rounded up),
        at most the fixed lag ``lag_ticks``."""
        return min(self.lag_ticks, math.ceil(self.lever_travel_s / self.tick_s - 1e-9))

    @property
    def learns(self) -> bool:
        """Whether gyro bias and scale, odometer factors and standstill are learned/used."""
        return self.mode == TrackedMode.PRODUCT
