"""Named indices and enums of the tracked-vehicle estimator (``method.md`` §4, source 002).

:class:`MotionState` is what the recogniser returns and the simulator labels its truth with;
:class:`TrackedState` indexes the filter's state vector; :class:`TrackedMode` picks between
the source as printed and the product's corrections.
"""

from __future__ import annotations

from enum import IntEnum, StrEnum

__all__ = ["N_STATES", "TURNING", "MotionState", "TrackedMode", "TrackedState"]


class MotionState(IntEnum):
    """Motion state of a single-flow-transmission crawler (source 002, Table 1 and §2).

    Steering units (fast side, slow side): straight = direct/direct, low_straight = I/I,
    arc = direct/I, separated = direct/slipping between I and direct, pivot = direct/II
    (brake), stop = II/II; heading_jump is a heading change above ``δφ_max`` in one tick
    (Eq. 16), whatever the levers.
    """

    STOP = 0
    STRAIGHT = 1
    LOW_STRAIGHT = 2
    ARC = 3
    SEPARATED = 4
    PIVOT = 5
    HEADING_JUMP = 6


#: States in which the hull turns on purpose (fast track ahead of the slow one).
TURNING = (MotionState.ARC, MotionState.SEPARATED, MotionState.PIVOT)


class TrackedState(IntEnum):
    """Index of the filter's state vector.

    Position of the hull centre (ground point midway between the track contact centres) in
    the vehicle's ENU frame, heading from north clockwise, forward speed, gyro z bias and
    scale error, the odometer factor ``F_s`` of each motion state (the fast track's ground speed
    over the odometer speed: ``K_D`` scale and that state's traction slip together), and the
    hull's lag behind its tracks ``τ`` (s): while it accelerates at ``a`` the hull runs
    ``τ·a`` slower than ``F_s`` times the odometer says. ``F_LOW`` and ``F_PIVOT`` hold the
    low gear's and the pivot's offsets from the straight's factor (``F_low = F_STRAIGHT +
    F_LOW``). ``TURN_SLIP`` is the fast track's turn slip per unit tightness ``c``, shared by
    arcs and separated turns: ``F_turn = F_STRAIGHT − c·θ``, ``θ = B/ρ_t`` from the sprocket
    ratio. ``ACCEL_SLIP`` is
    ``κ`` (s²/m), the traction slip per m/s² of acceleration: the odometer's ground speed is
    ``F_s·(1 − κ·a)·v_o``. ``GROUND_PATCH`` ``p`` is the patch of ground under the tracks: how
    far its slip moves every factor from the ground's mean (``F_s + p``), a Gauss-Markov
    process over the distance driven (correlation length ``ℓ``): the factors hold the
    ground's mean, which the next kilometre of an outage drives on, and ``p`` the last
    patches' departure from it, which dies out over ``ℓ``. ``SIDE_SLIP`` ``g_s`` is the
    ground's side-slip over what the configured lateral resistance ``μ_t`` gives (the turning
    pole ``g_s·L·|a_y|/(2·μ_t·g)`` ahead of the centre): learnt beside GNSS in turns, so that
    a ground sliding more or less than configured is not read as a gyro scale error; a side
    slope's creep downhill (gravity's cross share against the same resistance) scales by it too.
    ``PITCH`` ``θ`` (rad, nose up +) is the hull's pitch on the ground it climbs, carried on
    the pitch gyro less its bias ``PITCH_GYRO_BIAS``: the tracks' speed is along the ground
    (the hull moves ``V·cos θ`` horizontally) and the forward accelerometer reads
    ``a + g·sin θ``, so the odometer's speed against the accelerometer's observes it.
    ``ROLL`` ``φ`` (rad, right side down +) on the roll gyro less ``ROLL_GYRO_BIAS``: the
    lateral accelerometer reads ``−ω·V − g·cos θ·sin φ``, and a turn on a side slope turns
    the yaw rate into pitch rate (``θ̇ = ω_x·cos φ + ω_z·sin φ``).
    ``ACCEL_BIAS_X`` / ``ACCEL_BIAS_Y`` (m/s²) are the lateral (right +) and forward
    accelerometers' biases: each reads as ``g`` times a tilt (``b_y/g`` of pitch, ``b_x/g`` of
    roll) until something else sees the tilt, so without them the pitch and roll take the
    biases in and their variance does not know it.
    ``GNSS_CLOCK`` ``c`` (s) is the receiver's clock less the IMU's (the filter ticks on the
    IMU's): a fix stamped ``s`` was taken at ``s − c``, so it is ``age + lead + c`` older
    than the state (``age = t − s`` at the tick ``t``; the predicted state stands ``lead``
    past the tick, ``step.state_lead_s``). Beside GNSS its along-track position against
    ``V·cos θ`` and its velocity against the hull's acceleration and turn observe it.
    """

    EAST = 0
    NORTH = 1
    HEADING = 2
    SPEED = 3
    GYRO_BIAS = 4
    GYRO_SCALE = 5
    F_STRAIGHT = 6
    F_LOW = 7
    TURN_SLIP = 8
    F_PIVOT = 9
    ACCEL_LAG = 10
    ACCEL_SLIP = 11
    GROUND_PATCH = 12
    SIDE_SLIP = 13
    PITCH = 14
    PITCH_GYRO_BIAS = 15
    ROLL = 16
    ROLL_GYRO_BIAS = 17
    ACCEL_BIAS_X = 18
    ACCEL_BIAS_Y = 19
    GNSS_CLOCK = 20


N_STATES = len(TrackedState)


class TrackedMode(StrEnum):
    """Which method the estimator runs.

    ``paper``: the source as printed (Eqs. 1, 6, 7, 11, 14-17, 20, 23), lateral term ``−φ̇·L``
    included; ``paper_no_lateral``: the same without the lateral term; ``raw_odometer``: the
    odometer speed taken as the hull's forward speed in every state; ``product``: motion state
    from the sprocket ratios, learned odometer factor per state, modelled side-slip.
    """

    PRODUCT = "product"
    PAPER = "paper"
    PAPER_NO_LATERAL = "paper_no_lateral"
    RAW_ODOMETER = "raw_odometer"
