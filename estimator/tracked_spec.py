"""The tracked estimator's spec (``method.md`` §4, source 002): crawler state, track slip and
odometer-corrected dead reckoning through GNSS outages."""

from __future__ import annotations

import math
from enum import IntFlag

from estimator.spec import (
    AlertRule,
    CalibrationChannel,
    ChartSpec,
    EstimatorSpec,
    FieldSpec,
    PositionChannel,
    SlipChannel,
    SpeedChannel,
    StateChannel,
    StateValue,
    ValueChannel,
    WheelPosition,
    flags_from,
    gnss_clock_channel,
)

__all__ = ["MOTION_STATES", "SIDE_SLOPE_ALERT_RAD", "TRACKED_SPEC", "TrackedFlag"]

#: |roll| above which (held 2 s) a crawler is alerted of a steep side slope: 15°.
SIDE_SLOPE_ALERT_RAD = math.radians(15.0)

#: Labels of ``motion_state`` by value (``estimator.tracked.model.MotionState``).
MOTION_STATES = ("stop", "straight", "low_straight", "arc", "separated", "pivot", "heading_jump")
_STATE_LABELS = (
    "stop",
    "straight",
    "low-gear straight",
    "arc turn",
    "separated turn",
    "pivot",
    "heading jump",
)


class TrackedFlag(IntFlag):
    """Bits of a tracked row's ``flags``."""

    NONE = 0
    GNSS_OK = 1 << 0
    DEAD_RECKONING = 1 << 1
    STATE_UNCERTAIN = 1 << 2
    STANDSTILL = 1 << 3
    SLIP_LEFT_VALID = 1 << 4
    SLIP_RIGHT_VALID = 1 << 5
    BRAKED_LEFT = 1 << 6
    BRAKED_RIGHT = 1 << 7
    ODOMETER_USED = 1 << 8
    GNSS_GATED = 1 << 9
    SPROCKET_MISSING = 1 << 10
    NOT_STARTED = 1 << 11
    SLIP_SETTLING = 1 << 12
    STATE_BACKDATED = 1 << 13


def _f(name: str, unit: str, label: str, description: str, kind: str = "f8") -> FieldSpec:
    return FieldSpec(name, kind, unit, label, description)


_FIELDS = (
    _f("stamp_ns", "ns", "time", "tick time, ns since the Unix epoch (UTC)", "i8"),
    _f(
        "motion_state",
        "",
        "motion state",
        "0 stop, 1 straight, 2 low-gear straight, 3 arc, 4 separated, 5 pivot, 6 heading jump",
        "i4",
    ),
    _f("state_confidence", "", "state confidence", "probability the motion state is right"),
    _f("speed_mps", "m/s", "forward speed", "hull centre's forward speed (filter)"),
    _f("speed_std_mps", "m/s", "forward speed σ", "1-sigma of speed_mps"),
    _f("lateral_mps", "m/s", "lateral speed", "hull centre's side-slip speed, right +"),
    _f("yaw_rate_radps", "rad/s", "yaw rate", "gyro yaw rate, bias and scale removed, CCW +"),
    _f("turn_radius_m", "m", "turning radius", "ρ = V/ω, signed (+ left); NaN when straight"),
    _f("track_left_mps", "m/s", "left track ground speed", "V − ω·B/2 at the track centre"),
    _f("track_right_mps", "m/s", "right track ground speed", "V + ω·B/2 at the track centre"),
    _f("track_std_mps", "m/s", "track ground speed σ", "1-sigma of each track's ground speed"),
    _f("sprocket_left_mps", "m/s", "left sprocket speed", "left sprocket's pitch speed"),
    _f("sprocket_right_mps", "m/s", "right sprocket speed", "right sprocket's pitch speed"),
    _f("slip_left_pct", "%", "left track slip", "(Vs − v)/max(Vs, v): + slip, − skid"),
    _f("slip_right_pct", "%", "right track slip", "(Vs − v)/max(Vs, v): + slip, − skid"),
    _f("slip_left_std_pct", "%", "left track slip σ", "1-sigma of slip_left_pct"),
    _f("slip_right_std_pct", "%", "right track slip σ", "1-sigma of slip_right_pct"),
    _f("odometer_raw_mps", "m/s", "odometer speed", "gearbox output speed, nominal K_D"),
    _f(
        "odometer_mps",
        "m/s",
        "corrected odometer speed",
        "forward speed the odometer gives in this motion state (NaN where it gives none)",
    ),
    _f("odometer_scale", "", "odometer factor", "learned straight-state factor (K_D · (1 − s))"),
    _f("gyro_bias_radps", "rad/s", "gyro bias", "estimated yaw gyro bias"),
    _f("east_m", "m", "east", "hull centre, east of the vehicle's anchor"),
    _f("north_m", "m", "north", "hull centre, north of the vehicle's anchor"),
    _f("up_m", "m", "up", "hull centre, up from the anchor (flat ground: 0)"),
    _f("heading_rad", "rad", "heading", "from north, clockwise"),
    _f("lat_deg", "deg", "latitude", "WGS-84 latitude of the hull centre"),
    _f("lon_deg", "deg", "longitude", "WGS-84 longitude of the hull centre"),
    _f("east_std_m", "m", "east σ", "1-sigma of east_m"),
    _f("north_std_m", "m", "north σ", "1-sigma of north_m"),
    _f("east_north_cov_m2", "m²", "east-north covariance", "covariance of east_m and north_m"),
    _f("flags", "", "flags", "TrackedFlag bits", "i4"),
    _f(
        "gyro_arw_deg_rt_h",
        "°/√h",
        "gyro ARW, measured",
        "the yaw gyro's angle random walk measured while standing (NaN before the first pair "
        "of standing ticks); above the data sheet's, it widens the heading's and bias's noise",
    ),
    _f("gyro_arw_std_deg_rt_h", "°/√h", "gyro ARW σ", "1-sigma of gyro_arw_deg_rt_h"),
    _f(
        "pitch_rad",
        "rad",
        "pitch",
        "hull's pitch on the ground it stands on, nose up + (NaN until the filter has measured "
        "it: its 1-sigma above tilt_reported_std_rad)",
    ),
    _f("pitch_std_rad", "rad", "pitch σ", "1-sigma of pitch_rad"),
    _f(
        "roll_rad",
        "rad",
        "roll",
        "hull's roll on a side slope, right side down + (NaN until the filter has measured it)",
    ),
    _f("roll_std_rad", "rad", "roll σ", "1-sigma of roll_rad"),
    _f(
        "gnss_clock_offset_s",
        "s",
        "GNSS clock offset",
        "a GNSS fix stamped t was taken at the IMU clock's t − offset (online calibration, "
        "product mode; NaN in the paper modes)",
    ),
    _f("gnss_clock_offset_std_s", "s", "GNSS clock offset σ", "1-sigma of gnss_clock_offset_s"),
)
# The gyro's calibration fields come after ``flags``, the attitude's after them, the receiver
# clock's after those: rows stored before any of them convert by appending.
# Rows are given one tick late, up to ``report_lag_ticks`` (4 ticks, 0.4 s) while a state change
# is under way: the change is dated where the ratios or the yaw acceleration left their band
# (estimator.tracked.lag).

TRACKED_SPEC = EstimatorSpec(
    name="tracked",
    title="Crawler state, track slip and dead reckoning",
    description=(
        "Motion state, per-track slip and skid, and INS/odometer/GNSS position of a "
        "single-flow-transmission crawler (method.md §4, source 002); dead-reckoned through "
        "GNSS outages with the odometer corrected per motion state. Rows are given one tick "
        "late, up to 4 ticks (0.4 s) through a state change, so that it is dated when it began."
    ),
    kinds=("tracked",),
    inputs=("gnss", "imu", "odometer", "sprockets"),
    fields=_FIELDS,
    flags=flags_from(
        TrackedFlag,
        {
            "GNSS_OK": "a GNSS fix was fused within the last second",
            "DEAD_RECKONING": "no GNSS fix for more than a second: position dead-reckoned",
            "STATE_UNCERTAIN": "the motion state's confidence is below its threshold",
            "STANDSTILL": "both tracks and the hull stand still",
            "SLIP_LEFT_VALID": "slip_left_pct holds a value",
            "SLIP_RIGHT_VALID": "slip_right_pct holds a value",
            "BRAKED_LEFT": "the left track is braked (pivot): its slip is −100 % by definition",
            "BRAKED_RIGHT": "the right track is braked (pivot): its slip is −100 % by definition",
            "ODOMETER_USED": "the odometer was fused on this tick",
            "GNSS_GATED": "a GNSS fix was rejected by the innovation gate on this tick",
            "SPROCKET_MISSING": "a sprocket stream is missing: state from the turning radius",
            "NOT_STARTED": "no GNSS fix at speed yet: position and heading unknown",
            "SLIP_SETTLING": "a lever moves: a sprocket's speed changes faster than it is read, "
            "no slip value for it",
            "STATE_BACKDATED": "the state change was backdated to when the sprocket ratios or "
            "the yaw acceleration left their band (rows are given one tick late, up to 4 "
            "ticks, 0.4 s, while a change is under way; each keeps its own stamp): no slip value",
        },
    ),
    slips=(
        SlipChannel(
            "left",
            "left track",
            "slip_left_pct",
            WheelPosition.TRACK_LEFT,
            "SLIP_LEFT_VALID",
            "slip_left_std_pct",
        ),
        SlipChannel(
            "right",
            "right track",
            "slip_right_pct",
            WheelPosition.TRACK_RIGHT,
            "SLIP_RIGHT_VALID",
            "slip_right_std_pct",
        ),
    ),
    speeds=(
        SpeedChannel("forward", "forward speed", "speed_mps", std_field="speed_std_mps"),
        SpeedChannel("track_left", "left track", "track_left_mps", std_field="track_std_mps"),
        SpeedChannel("track_right", "right track", "track_right_mps", std_field="track_std_mps"),
        SpeedChannel("odometer", "corrected odometer", "odometer_mps"),
    ),
    motion="forward",
    position=PositionChannel(
        "east_m",
        "north_m",
        "up_m",
        "heading_rad",
        "DEAD_RECKONING",
        east_std_field="east_std_m",
        north_std_field="north_std_m",
        pitch_field="pitch_rad",
        roll_field="roll_rad",
    ),
    states=(
        StateChannel(
            "motion",
            "motion state",
            "motion_state",
            tuple(
                StateValue(value, name, label)
                for value, (name, label) in enumerate(
                    zip(MOTION_STATES, _STATE_LABELS, strict=True)
                )
            ),
            confidence_field="state_confidence",
            uncertain_flag="STATE_UNCERTAIN",
        ),
    ),
    values=(
        ValueChannel(
            "odometer_factor",
            "odometer factor",
            "odometer_scale",
            valid_flag="GNSS_OK",
            mapped=True,
        ),
    ),
    charts=(
        ChartSpec("slip", "Track slip", "%", ("slip_left_pct", "slip_right_pct")),
        ChartSpec(
            "speed",
            "Speeds",
            "m/s",
            ("speed_mps", "track_left_mps", "track_right_mps", "odometer_mps"),
        ),
        ChartSpec(
            "sprockets", "Sprocket speeds", "m/s", ("sprocket_left_mps", "sprocket_right_mps")
        ),
        ChartSpec("yaw", "Yaw rate", "rad/s", ("yaw_rate_radps",)),
        ChartSpec("attitude", "Pitch and roll", "rad", ("pitch_rad", "roll_rad")),
    ),
    ok_flag="GNSS_OK",
    degraded_flags=("DEAD_RECKONING",),
    # no uncalibrated flag: state, speeds, slip and position do not rest on the gyro's noise,
    # only the position's covariance through an outage does, at the data sheet's at least;
    # the receiver's clock is a state of the same filter, whose covariance carries its
    # uncertainty into the speed's, slip's and position's own while it converges (measured
    # in docs/perf/tracked.md, 2026-11-29 "issue 26")
    calibrations=(
        CalibrationChannel(
            "gyro_arw",
            "yaw gyro angle random walk (measured standing)",
            "gyro_arw_deg_rt_h",
            "gyro_arw_std_deg_rt_h",
            "calibration.gyro_arw_converged_pct",
            1e-2,
            relative=True,
            enabled_config="calibration.gyro_noise",
        ),
        gnss_clock_channel(),
    ),
    alerts=(
        # a track's slip out of its band (in place of the wheel slip threshold): a braked
        # track's −100 % in a pivot is its definition, not an alert
        *(
            AlertRule(
                f"track_slip_{side}",
                f"{side} track slip out of band",
                f"slip_{side}_pct",
                above=25.0,
                absolute=True,
                when=(f"SLIP_{side.upper()}_VALID",),
                unless=(f"BRAKED_{side.upper()}",),
                hold_s=3.0,
                slip=side,
            )
            for side in ("left", "right")
        ),
        # a crawler on a steep side slope risks rolling over: 15° held 2 s is a design choice
        # (a margin well inside the static rollover angle of a low, wide hull), not a measurement
        AlertRule(
            "side_slope",
            "steep side slope (rollover risk)",
            "roll_rad",
            above=SIDE_SLOPE_ALERT_RAD,
            absolute=True,
            hold_s=2.0,
        ),
        AlertRule(
            "long_dead_reckoning",
            "dead reckoning for long",
            when=("DEAD_RECKONING",),
            hold_s=30.0,
        ),
    ),
)
