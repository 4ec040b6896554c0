"""The friction estimator's spec (``method.md`` §5, source 004): tyre–ground μ of a steered
four-wheel vehicle, with whether the data inform it.

``mu`` is given only while the data inform it (``INFORMED``: its relative 1-σ below the
estimator's bound and the tyres using enough of the grip); otherwise it holds the last
informed value (``HELD``), never a drifting value, and ``mu_std`` is that held value's 1-σ
against the filter's posterior now (it grows as the filter moves away from it). Per wheel: load,
slip (a slip channel, so reports, maps and colours read it), slip angle and the share of
the grip in use. The position (GNSS antenna in the vehicle's ENU frame, dead-reckoned
briefly between fixes and through short outages, ``DEAD_RECKONED``) makes μ a slip-map
layer and places the vehicle in the 3D view.
"""

from __future__ import annotations

from enum import IntFlag

import numpy as np

from estimator.spec import (
    AlertRule,
    ChartSpec,
    EstimatorSpec,
    FieldSpec,
    PositionChannel,
    SlipChannel,
    SpeedChannel,
    ValueChannel,
    WheelPosition,
    WheelValueChannel,
    flags_from,
)

__all__ = ["FRICTION_DTYPE", "FRICTION_SPEC", "WHEEL_KEYS", "FrictionFlag"]

WHEEL_KEYS = ("fl", "fr", "rl", "rr")
_POSITIONS = (
    WheelPosition.FRONT_LEFT,
    WheelPosition.FRONT_RIGHT,
    WheelPosition.REAR_LEFT,
    WheelPosition.REAR_RIGHT,
)
_WHEEL_NAMES = ("front left", "front right", "rear left", "rear right")


class FrictionFlag(IntFlag):
    """Bits of a friction row's ``flags``."""

    NONE = 0
    INFORMED = 1 << 0
    """The data inform μ now: ``mu`` is this tick's estimate with its ``mu_std``."""
    HELD = 1 << 1
    """μ is not informed now: ``mu`` is the last informed value, held (``mu_std`` its 1-σ now)."""
    NO_UPDATE = 1 << 2
    """No measurement update this tick (too slow, or an input missing)."""
    GNSS_SPEED = 1 << 3
    """GNSS velocity corrected the speed and side-slip on this tick."""
    MEE_FALLBACK = 1 << 4
    """Paper mode: the MEE covariance was not positive definite; the standard step ran."""
    RESET = 1 << 5
    """The filter started on this tick."""
    TYRE_SUSPECT = 1 << 6
    """A tyre's calibrated rolling radius sinks more (or less) under load than its config's
    ``kz`` gives: its own vertical stiffness is learnt from it (and its brush stiffness)."""
    DEAD_RECKONED = 1 << 7
    """No GNSS fix for more than ``PositionConfig.after_s``: the position and heading are
    carried from the last one by the speed and the gyro (:mod:`estimator.friction.position`)."""
    NO_STEERING = 1 << 8
    """No steering-wheel angle from the vehicle yet, or the last older than
    ``FrontEndConfig.steer_timeout_s`` (the stream stopped): the front wheels' steer angle, an
    input of every row of the μ update, is unknown, so μ is not updated (``NO_UPDATE``) and
    the front pair's slip, slip-angle and grip-used columns are NaN; the next angle ends it."""


_FLAG_TEXT = {
    "INFORMED": "the data inform μ now: mu is this tick's estimate with its mu_std",
    "HELD": "μ not informed now: mu holds the last informed value (NaN before the first), "
    "mu_std its 1-sigma against the filter now",
    "NO_UPDATE": "no measurement update this tick (below the minimum speed or an input missing)",
    "GNSS_SPEED": "GNSS velocity corrected the speed and side-slip on this tick",
    "MEE_FALLBACK": "paper mode: the MEE covariance was not positive definite, standard step",
    "RESET": "the filter started on this tick",
    "TYRE_SUSPECT": "a tyre's rolling radius is far from its config's (soft or damaged): "
    "its vertical stiffness is learnt from it",
    "DEAD_RECKONED": "no GNSS fix for more than 0.25 s: position and heading carried by the "
    "speed and the gyro (none after 10 s)",
    "NO_STEERING": "no steering angle from the vehicle yet, or none for 0.1 s: μ not updated, "
    "front wheels' slip columns empty",
}


def _wheel_fields() -> list[FieldSpec]:
    out = []
    for key, name in zip(WHEEL_KEYS, _WHEEL_NAMES, strict=True):
        out += [
            FieldSpec(f"fz_{key}_n", "f8", "N", f"load {name}", f"vertical load, {name} wheel"),
            FieldSpec(
                f"slip_{key}_pct",
                "f8",
                "%",
                f"slip {name}",
                f"longitudinal slip κ, {name} wheel (+ driving)",
            ),
            FieldSpec(
                f"alpha_{key}_rad",
                "f8",
                "rad",
                f"slip angle {name}",
                f"slip angle α, {name} wheel (+ pushes left)",
            ),
            FieldSpec(
                f"util_{key}_pct",
                "f8",
                "%",
                f"grip used {name}",
                f"hypot(Fx, Fy) / (μ Fz) at the filter's μ, {name} wheel",
            ),
        ]
    return out


_FIELDS = (
    FieldSpec("stamp_ns", "i8", "ns", "time", "tick time, ns since the Unix epoch (UTC)"),
    FieldSpec("mu", "f8", "", "μ", "friction coefficient: informed estimate, or the last held"),
    FieldSpec(
        "mu_std",
        "f8",
        "",
        "μ σ",
        "1-sigma of mu: the filter's while informed; while held, hypot(filter's, held − filter's "
        "μ); NaN before the first informed μ",
    ),
    FieldSpec("mu_filter", "f8", "", "μ (filter)", "the filter's μ this tick, informed or not"),
    FieldSpec("vx_mps", "f8", "m/s", "speed", "forward speed at the CG"),
    FieldSpec("vy_mps", "f8", "m/s", "lateral speed", "lateral speed at the CG (left +)"),
    *_wheel_fields(),
    FieldSpec("flags", "i4", "", "flags", "FrictionFlag bits"),
    # the position came after the first release: appended, so stored rows convert in place
    FieldSpec("east_m", "f8", "m", "east", "GNSS antenna, east of the vehicle's anchor"),
    FieldSpec("north_m", "f8", "m", "north", "GNSS antenna, north of the vehicle's anchor"),
    FieldSpec("up_m", "f8", "m", "up", "GNSS antenna height above the vehicle's anchor"),
    FieldSpec("heading_rad", "f8", "rad", "heading", "from north, clockwise"),
    # the speed's 1-σ came after the position: appended too
    FieldSpec(
        "vx_std_mps",
        "f8",
        "m/s",
        "speed σ",
        "1-sigma of vx_mps against the ground: the speed filter's, with the wheel readings' "
        "persistent errors (window lag, the radii's shared scale) considered",
    ),
)

FRICTION_DTYPE = np.dtype([(f.name, f.kind) for f in _FIELDS])

FRICTION_SPEC = EstimatorSpec(
    name="friction",
    title="Tyre–ground friction μ",
    description=(
        "Friction coefficient μ from IMU, four CAN wheel speeds, steering angle and optional "
        "GNSS: brush tyres with load-adaptive stiffness in a square-root cubature Kalman "
        "filter (method.md §5); μ is reported only while the data inform it."
    ),
    kinds=("wheeled_4wd_steered",),
    inputs=("imu", "wheel_speeds4", "steering", "gnss"),
    fields=_FIELDS,
    flags=flags_from(FrictionFlag, _FLAG_TEXT),
    slips=tuple(
        SlipChannel(key, f"slip {name}", f"slip_{key}_pct", pos)
        for key, name, pos in zip(WHEEL_KEYS, _WHEEL_NAMES, _POSITIONS, strict=True)
    ),
    speeds=(SpeedChannel("speed", "speed", "vx_mps", std_field="vx_std_mps"),),
    motion="speed",
    position=PositionChannel(
        "east_m", "north_m", "up_m", "heading_rad", carried_flag="DEAD_RECKONED"
    ),
    charts=(
        ChartSpec("mu", "Friction μ", "", ("mu", "mu_filter")),
        ChartSpec("grip", "Grip used", "%", tuple(f"util_{k}_pct" for k in WHEEL_KEYS)),
        ChartSpec("slip", "Wheel slip", "%", tuple(f"slip_{k}_pct" for k in WHEEL_KEYS)),
        ChartSpec("load", "Wheel load", "N", tuple(f"fz_{k}_n" for k in WHEEL_KEYS)),
    ),
    ok_flag="INFORMED",
    degraded_flags=("HELD", "DEAD_RECKONED", "NO_STEERING"),
    values=(ValueChannel("mu", "μ", "mu", std_field="mu_std", valid_flag="INFORMED", mapped=True),),
    wheel_values=tuple(
        WheelValueChannel(key, f"grip used {name}", f"util_{key}_pct", pos)
        for key, name, pos in zip(WHEEL_KEYS, _WHEEL_NAMES, _POSITIONS, strict=True)
    ),
    row_dtype=FRICTION_DTYPE,
    # mu is the informed value or the last one held (NaN before the first): low grip stays
    # low while the data say nothing new
    alerts=(AlertRule("low_mu", "low friction μ", "mu", below=0.3, hold_s=1.0),),
)
