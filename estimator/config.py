"""Vehicle configuration by kind: one frozen, self-validating dataclass per vehicle kind.

:data:`VehicleConfig` is the union of :class:`WheeledRearDriveConfig` (a rear-drive tractor:
rear-axle geometry, wheel encoders), :class:`TrackedConfig` (a crawler, ``method.md`` §4) and
:class:`Wheeled4wdSteeredConfig` (a steered four-wheel vehicle, ``method.md`` §5). Every kind
has ``noise``, ``slip`` and ``estimators``; its class attribute ``kind`` names it in JSON and
``positions`` names its wheels or tracks (:class:`~estimator.spec.WheelPosition`).

Every numeric field carries its plausible physical range and unit once, as field metadata
(:class:`Bound`, read with :func:`bound_of`); ``__post_init__`` refuses a value outside it with
:class:`ConfigError` naming the field, the range and the unit, and the REST models are built
from the same metadata. :func:`vehicle_config_from_dict` dispatches on ``"kind"`` (default
``wheeled_rear_drive``) and reads every shape this module ever wrote (see
:func:`upgrade_legacy_config`); ``to_dict`` gives it back as JSON-ready data.

Geometry of a wheeled rear-drive vehicle follows ``method.md`` section 1: the origin ``O`` is
the ground projection of the rear-axle midpoint; body frame X right, Y forward, Z up. In the
source's layout the IMU sits on the vertical through ``O`` at height ``h0`` and the antenna
``h1`` above the IMU; the horizontal offsets generalise that (lever arms), zero reproduces the
source. The other kinds give lever arms as (x right, y forward, z up) from their own origin.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import reprlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from typing import Any, ClassVar, TypeVar

from estimator.gyro import GYRO_PARTS, GyroPart
from estimator.spec import WheelPosition

__all__ = [
    "Bound",
    "CalibrationConfig",
    "ChassisConfig",
    "ConfigError",
    "Differential",
    "DrivenAxle",
    "EncoderConfig",
    "GyroConfig",
    "NoiseConfig",
    "OdometerConfig",
    "SlipConfig",
    "SprocketConfig",
    "TrackedCalibrationConfig",
    "TrackedConfig",
    "TrackedGeometry",
    "TrackedMotionConfig",
    "TrackedNoiseConfig",
    "TyreConfig",
    "VehicleConfig",
    "VehicleGeometry",
    "VehicleKind",
    "WheelPosition",
    "Wheeled4wdSteeredConfig",
    "WheeledRearDriveConfig",
    "bound_of",
    "config_class",
    "expect_kind",
    "upgrade_legacy_config",
    "vehicle_config_from_dict",
]


class ConfigError(ValueError):
    """A configuration value is out of its valid range."""


class VehicleKind(StrEnum):
    """What kind of vehicle this is; the kind picks the config class and default estimators."""

    WHEELED_REAR_DRIVE = "wheeled_rear_drive"
    TRACKED = "tracked"
    WHEELED_4WD_STEERED = "wheeled_4wd_steered"


class DrivenAxle(StrEnum):
    """Which axle of a four-wheel vehicle drives."""

    FRONT = "front"
    REAR = "rear"
    ALL = "all"


class Differential(StrEnum):
    """How a four-wheel vehicle's driven axles share torque between their left and right wheels.

    ``open``: the same torque to both (``F_L r_L = F_R r_R`` while the wheels spin steadily);
    ``locked``: no torque balance assumed (a locked or limited-slip differential).
    """

    OPEN = "open"
    LOCKED = "locked"


@dataclass(frozen=True, slots=True)
class Bound:
    """The plausible range ``low..high`` (inclusive) of a numeric field, with its unit.

    ``items`` set means the field is a tuple of ``items[0]..items[1]`` numbers, each in range.
    """

    low: float
    high: float
    unit: str  # "" for a dimensionless ratio
    doc: str
    integer: bool = False
    items: tuple[int, int] | None = None

    def describe(self) -> str:
        """``"1e-06..10 m/s²"``: the range and unit as messages and schemas show them."""
        return f"{self.low:g}..{self.high:g} {self.unit or '(dimensionless)'}"

    def check(self, name: str, value: Any) -> None:
        """Raise :class:`ConfigError` naming ``name`` unless ``value`` fits."""
        if self.items is None:
            self._check_number(name, value)
            return
        lo, hi = self.items
        if not isinstance(value, tuple) or not lo <= len(value) <= hi:
            count = f"{lo}" if lo == hi else f"{lo} to {hi}"
            raise ConfigError(
                f"{name} must be a list of {count} numbers, got {reprlib.repr(value)}"
            )
        for i, v in enumerate(value):
            self._check_number(f"{name}[{i}]", v)

    def _check_number(self, name: str, value: Any) -> None:
        kind = (int,) if self.integer else (int, float)
        ok = isinstance(value, kind) and not isinstance(value, bool)
        finite = ok and (isinstance(value, int) or math.isfinite(value))  # no float of 10**400
        if not (finite and self.low <= value <= self.high):
            what = "an integer" if self.integer else "a number"
            raise ConfigError(
                f"{name} must be {what} in {self.describe()}, got {reprlib.repr(value)}"
            )


_BOUND = "bound"


def _bounded(
    default: Any,
    low: float,
    high: float,
    unit: str,
    doc: str,
    *,
    integer: bool = False,
    items: tuple[int, int] | None = None,
) -> Any:
    """A dataclass field with its :class:`Bound` as metadata (the one place a range is written)."""
    return field(default=default, metadata={_BOUND: Bound(low, high, unit, doc, integer, items)})


def _vector(default: tuple[float, ...], doc: str) -> Any:
    """A lever arm or offset: one component per axis, each within ±10 m."""
    n = len(default)
    return _bounded(default, -10.0, 10.0, "m", doc, items=(n, n))


def bound_of(f: dataclasses.Field[Any]) -> Bound | None:
    """The :class:`Bound` of a config dataclass field (None for booleans, choices, sections)."""
    bound = f.metadata.get(_BOUND)
    return bound if isinstance(bound, Bound) else None


class _Checked:
    """Validation shared by every config dataclass: ranges, booleans and choices per field."""

    __slots__ = ()

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if isinstance(value, list):  # JSON arrays: kept as tuples (frozen, hashable)
                value = tuple(value)
                object.__setattr__(self, f.name, value)
            bound = bound_of(f)
            section = f.default_factory
            if bound is not None and (value is not None or f.default is not None):
                bound.check(f.name, value)
            elif isinstance(section, type) and not isinstance(value, section):
                raise ConfigError(
                    f"{f.name} must be a {section.__name__}, got {reprlib.repr(value)}"
                )
            elif isinstance(f.default, bool) and not isinstance(value, bool):
                raise ConfigError(f"{f.name} must be true or false, got {reprlib.repr(value)}")
            elif isinstance(f.default, Enum):
                object.__setattr__(self, f.name, _choice(f.name, type(f.default), value))
        self._check()

    def _check(self) -> None:
        """Checks across fields (none by default)."""


E = TypeVar("E", bound=Enum)


def _choice(name: str, enum: type[E], value: Any) -> E:
    try:
        return enum(value)
    except ValueError:
        raise ConfigError(
            f"{name} must be one of {[e.value for e in enum]}, got {reprlib.repr(value)}"
        ) from None


# ---------------------------------------------------------------------------------------------
# sections


@dataclass(frozen=True, slots=True)
class VehicleGeometry(_Checked):
    """Where the sensors and wheels of a rear-drive vehicle are (``method.md`` §1).

    ``h0_m`` is the source's ``h0`` (IMU height above ground), ``h1_m`` its ``h1`` (antenna
    above the IMU), ``track_width_m`` the rear track ``b``, the wheel radii the effective rolling
    radius ``r`` of each measured wheel; offsets are (x right, y forward) from the vertical
    through ``O``. ``wheel_driven_*`` false declares a wheel free-rolling (a front-drive car's
    rear wheels): its slip is ~0, so its rolling radius can be learnt online.
    """

    h0_m: float = _bounded(1.0, 0.05, 6.0, "m", "IMU height above the ground (h0)")
    h1_m: float = _bounded(1.6, -3.0, 6.0, "m", "antenna height above the IMU (h1)")
    track_width_m: float = _bounded(1.8, 0.3, 6.0, "m", "rear track width b, contact to contact")
    wheel_radius_left_m: float = _bounded(0.85, 0.1, 2.0, "m", "rolling radius, rear left wheel")
    wheel_radius_right_m: float = _bounded(0.85, 0.1, 2.0, "m", "rolling radius, rear right wheel")
    antenna_offset_m: tuple[float, float] = _vector((0.0, 0.0), "antenna (x right, y forward)")
    imu_offset_m: tuple[float, float] = _vector((0.0, 0.0), "IMU (x right, y forward)")
    wheel_driven_left: bool = True
    wheel_driven_right: bool = True


@dataclass(frozen=True, slots=True)
class EncoderConfig(_Checked):
    """Wheel encoder: a toothed ring read by a Hall or optical sensor.

    ``teeth_per_rev`` is ``Ns`` (pulses per wheel revolution); without ``has_direction``
    (quadrature) the speed is taken as forward.
    """

    teeth_per_rev: int = _bounded(120, 1, 100_000, "/rev", "Ns, teeth a turn", integer=True)
    has_direction: bool = False


def _gnss_pos_std() -> Any:
    return _bounded(
        0.02, 1e-6, 100.0, "m", "horizontal position noise per axis (RTK fixed: 1-2 cm)"
    )


@dataclass(frozen=True, slots=True)
class _SensorNoise(_Checked):
    """The noise figures (1-sigma) every kind has: GNSS velocity and the accelerometer's
    white noise per sample."""

    gnss_vel_std_mps: float = _bounded(
        0.05, 1e-6, 10.0, "m/s", "GNSS velocity noise per axis when the receiver gives none"
    )
    accel_std_mps2: float = _bounded(
        0.05, 1e-6, 10.0, "m/s²", "accelerometer white noise (1-sigma of one sample)"
    )


@dataclass(frozen=True, slots=True)
class NoiseConfig(_SensorNoise):
    """Sensor noise figures (1-sigma), used to build the filters' Q and R; the accelerometer's
    bias walk (the MDSF filter's bias state) and the gyro's white noise per sample (the
    wheeled kinds)."""

    accel_bias_walk_mps2: float = _bounded(
        0.002, 1e-7, 1.0, "m/s² per √s", "accelerometer bias random walk"
    )
    gnss_pos_std_m: float = _gnss_pos_std()
    gyro_std_radps: float = _bounded(0.005, 1e-6, 1.0, "rad/s", "gyro white noise")


@dataclass(frozen=True, slots=True)
class TrackedNoiseConfig(_SensorNoise):
    """A crawler's sensor noise figures (1-sigma): the accelerometer's white noise (the
    tracked filter's speed prediction integrates it), no bias walk (the filter has no
    accelerometer bias state: the odometer holds the speed every tick) and no gyro figure
    (the gyro's noise is its ``gyro`` section's data sheet, :class:`GyroConfig`)."""

    gnss_pos_std_m: float = _gnss_pos_std()


@dataclass(frozen=True, slots=True)
class SlipConfig(_Checked):
    """When a slip value is given, and the bands reports count time in.

    Below ``min_ground_speed_mps`` ground *and* rim speed the vehicle stands: no slip value.
    |slip| above ``alert_threshold_pct`` for ``alert_hold_s`` raises an alert. A slip value is
    given only while the ground speed changes by at most ``settle_max_change`` of itself over
    the wheel-speed fit's span (``estimator.slip.unsettled``; 1e9 turns the rule off).
    """

    min_ground_speed_mps: float = _bounded(0.2, 0.01, 5.0, "m/s", "standstill below this speed")
    band_edges_pct: tuple[float, ...] = _bounded(
        (5.0, 15.0),
        0.1,
        100.0,
        "%",
        "upper edges of the report's slip bands, increasing",
        items=(1, 10),
    )
    alert_threshold_pct: float = _bounded(15.0, 0.1, 100.0, "%", "|slip| that raises an alert")
    alert_hold_s: float = _bounded(5.0, 0.1, 3600.0, "s", "time above the threshold to alert")
    settle_max_change: float = _bounded(
        0.5, 1e-3, 1e9, "", "largest relative change of ground speed over the fit span"
    )

    def _check(self) -> None:
        if any(b <= a for a, b in itertools.pairwise(self.band_edges_pct)):
            raise ConfigError(
                f"band_edges_pct must be increasing, got {reprlib.repr(self.band_edges_pct)}"
            )


@dataclass(frozen=True, slots=True)
class CalibrationConfig(_Checked):
    """Online calibration of a rear-drive vehicle's sensors (:mod:`estimator.mdsf.calibration`).

    Each switch turns one calibration on: per-stream clock offsets (GNSS and wheels against
    the IMU), the rolling radius per wheel (learnt where slip is ~0: free-rolling wheels and
    operator calibration drives) and the IMU's mounting pitch and yaw. A calibration has converged
    once its std is below its threshold; until then slip rows are flagged UNCALIBRATED. The
    priors are the std of each quantity before any data.
    """

    clock_offsets: bool = True
    wheel_radius: bool = True
    imu_mounting: bool = True
    clock_offset_prior_ms: float = _bounded(100.0, 0.1, 1000.0, "ms", "prior std of an offset")
    clock_offset_converged_ms: float = _bounded(
        10.0, 0.01, 1000.0, "ms", "a clock offset has converged below this std"
    )
    radius_prior_pct: float = _bounded(3.0, 0.01, 20.0, "%", "prior std of a rolling radius")
    radius_converged_pct: float = _bounded(
        0.15, 0.001, 20.0, "%", "a rolling radius has converged below this std"
    )
    imu_pitch_prior_deg: float = _bounded(3.0, 0.01, 30.0, "deg", "prior std of mounting pitch")
    imu_pitch_converged_deg: float = _bounded(
        0.3, 0.001, 30.0, "deg", "the mounting pitch has converged below this std"
    )
    imu_yaw_prior_deg: float = _bounded(3.0, 0.01, 30.0, "deg", "prior std of mounting yaw")
    imu_yaw_converged_deg: float = _bounded(
        1.0, 0.001, 30.0, "deg", "the mounting yaw has converged below this std"
    )


@dataclass(frozen=True, slots=True)
class TrackedGeometry(_Checked):
    """A crawler's hull (``method.md`` §4): gauge ``B``, contact length ``L`` and lever arms.

    Lever arms are (x right, y forward, z up) from the ground point midway between the two
    tracks' contact centres; the odometer's is the point whose speed it reads.
    """

    track_gauge_m: float = _bounded(2.0, 0.5, 6.0, "m", "track gauge B, centre to centre")
    contact_length_m: float = _bounded(2.5, 0.3, 8.0, "m", "track contact length L")
    imu_lever_arm_m: tuple[float, float, float] = _vector((0.0, 0.0, 1.0), "IMU")
    antenna_lever_arm_m: tuple[float, float, float] = _vector((0.0, 0.0, 2.6), "antenna")
    odometer_lever_arm_m: tuple[float, float, float] = _vector((0.0, 0.0, 0.0), "odometer")


@dataclass(frozen=True, slots=True)
class SprocketConfig(_Checked):
    """Sprocket encoders, one per track: edges per revolution and the pitch radius."""

    pitch_radius_m: float = _bounded(0.35, 0.05, 1.5, "m", "sprocket pitch radius")
    teeth_per_rev: int = _bounded(13, 1, 10_000, "/rev", "edges per sprocket turn", integer=True)
    has_direction: bool = False


@dataclass(frozen=True, slots=True)
class OdometerConfig(_Checked):
    """Transmission odometer: one edge per ``K_D`` metres of gearbox output."""

    distance_per_edge_m: float = _bounded(0.01, 1e-4, 1.0, "m", "K_D, distance per edge")
    scale_std_pct: float = _bounded(0.5, 0.0, 10.0, "%", "1-sigma uncertainty of K_D")


_FIGURES = ("angle_random_walk_deg_rt_h", "bias_stability_deg_h", "noise_density_dps_rt_hz")
"""A gyro's data-sheet figures, named as :class:`estimator.gyro.GyroPart` names them."""


@dataclass(frozen=True, slots=True)
class GyroConfig(_Checked):
    """The yaw gyro fitted: a known part by name (``part``, one of
    :data:`estimator.gyro.GYRO_PARTS`), or any name with its three data-sheet figures given.

    A figure left null is the named part's; one given replaces it (a unit measured worse than
    its data sheet). The filters' heading and gyro-bias noise come from the figures.
    """

    part: str = "ADIS16470"
    angle_random_walk_deg_rt_h: float | None = _bounded(
        None, 1e-4, 100.0, "°/√h", "angle random walk (null: the named part's)"
    )
    bias_stability_deg_h: float | None = _bounded(
        None, 1e-4, 1000.0, "°/h", "in-run bias stability (null: the named part's)"
    )
    noise_density_dps_rt_hz: float | None = _bounded(
        None, 1e-6, 1.0, "°/s/√Hz", "rate noise density (null: the named part's)"
    )

    def _check(self) -> None:
        if not isinstance(self.part, str) or not 1 <= len(self.part) <= 64:
            raise ConfigError(
                f"part must be a name of 1 to 64 characters, got {reprlib.repr(self.part)}"
            )
        if self.part not in GYRO_PARTS and any(getattr(self, n) is None for n in _FIGURES):
            raise ConfigError(
                f"part {reprlib.repr(self.part)} is not a known gyro part "
                f"{sorted(GYRO_PARTS)}: name one, or give all three of {', '.join(_FIGURES)}"
            )

    def resolved(self) -> GyroPart:
        """The named part's figures, each one given here in its place."""
        base = GYRO_PARTS.get(self.part)
        given = {n: getattr(self, n) for n in _FIGURES}
        figures = {n: float(getattr(base, n) if v is None else v) for n, v in given.items()}
        return GyroPart(self.part, **figures)

    @classmethod
    def of(cls, part: GyroPart) -> GyroConfig:
        """A config giving ``part``'s figures (its name only, if it is a known part)."""
        if GYRO_PARTS.get(part.name) == part:
            return cls(part=part.name)
        return cls(
            part=part.name,
            angle_random_walk_deg_rt_h=part.angle_random_walk_deg_rt_h,
            bias_stability_deg_h=part.bias_stability_deg_h,
            noise_density_dps_rt_hz=part.noise_density_dps_rt_hz,
        )


@dataclass(frozen=True, slots=True)
class TrackedCalibrationConfig(_Checked):
    """What the tracked estimator learns of a crawler's sensors online: the yaw gyro's angle
    random walk, measured while the crawler stands (``gyro_noise``; off: its ``gyro``
    section's data sheet is used as it is). It has converged once its 1-sigma is below
    ``gyro_arw_converged_pct`` of itself (10 %: 75 standing tick pairs, 7.5 s at rest).
    The GNSS receiver's clock less the IMU's, learnt beside GNSS (product mode), has
    converged once its 1-sigma is below ``clock_offset_converged_ms`` (MDSF's figure: 10 ms
    puts a fix ``0.1 m`` out at 10 m/s)."""

    gyro_noise: bool = True
    gyro_arw_converged_pct: float = _bounded(
        10.0, 1.0, 100.0, "%", "the measured angle random walk has converged below this std"
    )
    clock_offset_converged_ms: float = _bounded(
        10.0, 0.01, 1000.0, "ms", "the GNSS clock offset has converged below this std"
    )


@dataclass(frozen=True, slots=True)
class TrackedMotionConfig(_Checked):
    """Transmission and motion-state constants of ``method.md`` §4 (the source's values).

    Pivot turns below ``r = pivot_radius_per_half_gauge · B/2``; separated turns above
    ``2·R_II`` with ``R_II = separated_radius_per_gauge · B``; arcs between. A tick turning
    the heading by more than ``heading_jump_rad`` is a large heading change. The side-slip
    of a turn follows from the turning pole's shift ``L·|a_y|/(2·μ_t·g)`` ahead of the
    centre, ``μ_t`` the ground's lateral resistance coefficient.
    """

    low_gear_ratio: float = _bounded(1.42, 1.0, 4.0, "", "low-gear transmission ratio")
    arc_odometer_ratio: float = _bounded(0.8688, 0.3, 1.0, "", "v_y / v_o in arc turns")
    pivot_radius_per_half_gauge: float = _bounded(1.531, 0.5, 5.0, "", "pivot radius over B/2")
    separated_radius_per_gauge: float = _bounded(2.88, 0.5, 20.0, "", "R_II over B")
    straight_radius_m: float = _bounded(
        200.0, 10.0, 1e5, "m", "R_max: straight when |ρ| is above it (Eq. 6)"
    )
    heading_jump_rad: float = _bounded(
        0.1, 1e-3, 3.0, "rad", "δφ_max: heading change per tick that drops the odometer (Eq. 16)"
    )
    stop_speed_mps: float = _bounded(0.2, 0.01, 2.0, "m/s", "standstill below this speed")
    lateral_resistance: float = _bounded(
        0.6, 0.05, 2.0, "", "μ_t, lateral resistance coefficient of the ground (side-slip model)"
    )


@dataclass(frozen=True, slots=True)
class ChassisConfig(_Checked):
    """A steered four-wheel vehicle's body (``method.md`` §5); lever arms from below the CG.

    The body rolls and pitches about a horizontal axis ``tilt_axis_height_m`` above the ground
    on the CG's vertical (a road vehicle's roll axis lies near the ground, below the CG): the
    GNSS antenna's sway is its roll and pitch rates times its height above that axis.
    """

    mass_kg: float = _bounded(2500.0, 100.0, 60_000.0, "kg", "total mass")
    yaw_inertia_kgm2: float = _bounded(4000.0, 10.0, 1e6, "kg·m²", "yaw moment of inertia")
    cg_to_front_axle_m: float = _bounded(1.3, 0.1, 6.0, "m", "lf, CG to front axle")
    cg_to_rear_axle_m: float = _bounded(1.5, 0.1, 6.0, "m", "lr, CG to rear axle")
    front_track_m: float = _bounded(1.6, 0.5, 4.0, "m", "bf, front track width")
    rear_track_m: float = _bounded(1.6, 0.5, 4.0, "m", "br, rear track width")
    cg_height_m: float = _bounded(0.7, 0.1, 4.0, "m", "hg, CG height above ground")
    steering_ratio: float = _bounded(16.0, 1.0, 50.0, "", "steering wheel over road wheel angle")
    drag_area_m2: float = _bounded(1.0, 0.0, 20.0, "m²", "drag coefficient times frontal area")
    rolling_resistance: float = _bounded(0.015, 0.0, 0.5, "", "rolling resistance coefficient")
    roll_gradient_deg_per_g: float = _bounded(4.0, 0.0, 30.0, "deg/g", "body roll per lateral g")
    pitch_gradient_deg_per_g: float = _bounded(2.0, 0.0, 30.0, "deg/g", "body pitch per long. g")
    roll_stiffness_front_share: float = _bounded(
        0.55, 0.0, 1.0, "", "front axle's share of the roll stiffness (lateral load transfer)"
    )
    load_transfer_lag_s: float = _bounded(
        0.1, 0.0, 2.0, "s", "time constant of load transfer behind the accelerations"
    )
    driven_axle: DrivenAxle = DrivenAxle.ALL
    imu_lever_arm_m: tuple[float, float, float] = _vector((0.0, 0.0, 0.7), "IMU")
    antenna_lever_arm_m: tuple[float, float, float] = _vector((0.0, 0.0, 1.8), "antenna")
    tilt_axis_height_m: float = _bounded(
        0.3, 0.0, 4.0, "m", "height above ground of the axis the body rolls and pitches about"
    )
    differential: Differential = Differential.OPEN


@dataclass(frozen=True, slots=True)
class TyreConfig(_Checked):
    """Brush-model tyre of ``method.md`` §5: ``c_x = 2a²·c_px``, ``c_y = 2a²·c_py``."""

    c_px_npm2: float = _bounded(1e7, 1e5, 1e9, "N/m²", "c_px, longitudinal stiffness per area")
    c_py_npm2: float = _bounded(6e6, 1e5, 1e9, "N/m²", "c_py, lateral stiffness per area")
    kz_npm: float = _bounded(2.5e5, 1e4, 5e6, "N/m", "kz, vertical stiffness")
    unloaded_radius_m: float = _bounded(0.33, 0.15, 1.5, "m", "r_u, unloaded radius")
    relaxation_length_m: float = _bounded(
        0.4, 0.0, 3.0, "m", "distance rolled for the tyre force to follow a slip change"
    )


# ---------------------------------------------------------------------------------------------
# kinds


def _estimator_names(value: Any) -> None:
    if not isinstance(value, tuple) or len(value) > 8:
        raise ConfigError(
            f"estimators must be a list of at most 8 names, got {reprlib.repr(value)}"
        )
    for name in value:
        if not isinstance(name, str) or not 1 <= len(name) <= 64:
            raise ConfigError(
                f"estimators must hold names of 1 to 64 characters, got {reprlib.repr(name)}"
            )


class _Kind(_Checked):
    """What every kind has: a ``kind`` name, named wheel positions, ``noise``, ``slip``."""

    __slots__ = ()
    kind: ClassVar[VehicleKind]
    positions: ClassVar[tuple[WheelPosition, ...]]
    estimators: tuple[str, ...]

    def _check(self) -> None:
        _estimator_names(self.estimators)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: ``kind`` first, tuples as lists, choices as their strings."""
        return {"kind": self.kind.value, **_plain(dataclasses.asdict(self))}  # type: ignore[call-overload]


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, Enum):
        return value.value
    return value


@dataclass(frozen=True, slots=True)
class WheeledRearDriveConfig(_Kind):
    """A rear-drive wheeled vehicle (a tractor): what MDSF needs (``method.md`` §1-3).

    ``estimators`` names the estimators to run; empty means the kind's defaults.
    """

    kind: ClassVar[VehicleKind] = VehicleKind.WHEELED_REAR_DRIVE
    positions: ClassVar[tuple[WheelPosition, ...]] = (
        WheelPosition.REAR_LEFT,
        WheelPosition.REAR_RIGHT,
    )
    geometry: VehicleGeometry = field(default_factory=VehicleGeometry)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    slip: SlipConfig = field(default_factory=SlipConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    estimators: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class TrackedConfig(_Kind):
    """A crawler with a transmission odometer and sprocket encoders (``method.md`` §4)."""

    kind: ClassVar[VehicleKind] = VehicleKind.TRACKED
    positions: ClassVar[tuple[WheelPosition, ...]] = (
        WheelPosition.TRACK_LEFT,
        WheelPosition.TRACK_RIGHT,
    )
    geometry: TrackedGeometry = field(default_factory=TrackedGeometry)
    sprocket: SprocketConfig = field(default_factory=SprocketConfig)
    odometer: OdometerConfig = field(default_factory=OdometerConfig)
    motion: TrackedMotionConfig = field(default_factory=TrackedMotionConfig)
    gyro: GyroConfig = field(default_factory=GyroConfig)
    calibration: TrackedCalibrationConfig = field(default_factory=TrackedCalibrationConfig)
    noise: TrackedNoiseConfig = field(default_factory=TrackedNoiseConfig)
    slip: SlipConfig = field(default_factory=SlipConfig)
    estimators: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Wheeled4wdSteeredConfig(_Kind):
    """A steered four-wheel vehicle: chassis and tyres for the friction estimate (§5)."""

    kind: ClassVar[VehicleKind] = VehicleKind.WHEELED_4WD_STEERED
    positions: ClassVar[tuple[WheelPosition, ...]] = (
        WheelPosition.FRONT_LEFT,
        WheelPosition.FRONT_RIGHT,
        WheelPosition.REAR_LEFT,
        WheelPosition.REAR_RIGHT,
    )
    chassis: ChassisConfig = field(default_factory=ChassisConfig)
    tyre: TyreConfig = field(default_factory=TyreConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    slip: SlipConfig = field(default_factory=SlipConfig)
    estimators: tuple[str, ...] = ()


VehicleConfig = WheeledRearDriveConfig | TrackedConfig | Wheeled4wdSteeredConfig
"""Everything the estimators need to know about one vehicle: one class per kind."""

_KINDS: Mapping[VehicleKind, type[VehicleConfig]] = {
    cls.kind: cls for cls in (WheeledRearDriveConfig, TrackedConfig, Wheeled4wdSteeredConfig)
}

C = TypeVar("C", WheeledRearDriveConfig, TrackedConfig, Wheeled4wdSteeredConfig)


def config_class(kind: VehicleKind | str) -> type[VehicleConfig]:
    """The config class of ``kind`` (raises :class:`ConfigError` for an unknown kind)."""
    return _KINDS[_choice("kind", VehicleKind, kind)]


def expect_kind(config: VehicleConfig, cls: type[C], estimator: str) -> C:
    """``config`` if it is a ``cls``, else :class:`ConfigError`: ``estimator`` cannot run it."""
    if not isinstance(config, cls):
        raise ConfigError(
            f"estimator {estimator!r} runs on {cls.kind.value} vehicles, "
            f"not on {getattr(config, 'kind', type(config).__name__)}"
        )
    return config


# ---------------------------------------------------------------------------------------------
# from JSON


def _section(cls: Any, data: Any, name: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f"{name} must be an object")
    fields = [f.name for f in dataclasses.fields(cls)]
    unknown = set(data) - set(fields)
    if unknown:
        raise ConfigError(f"{name}: unknown field(s) {sorted(unknown)}; known: {fields}")
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{name}.{exc}") from None


def vehicle_config_from_dict(data: Any) -> VehicleConfig:
    """Build a validated config of the kind ``data["kind"]`` names (missing parts default).

    Reads today's shape and every earlier one (:func:`upgrade_legacy_config`). Raises
    :class:`ConfigError` naming the kind, section and field at fault.
    """
    if not isinstance(data, dict):
        raise ConfigError("vehicle config must be an object")
    data = upgrade_legacy_config(data)
    cls = config_class(data.get("kind", VehicleKind.WHEELED_REAR_DRIVE))
    sections = {f.name: f.default_factory for f in dataclasses.fields(cls)}
    known = ["kind", *sections]
    unknown = set(data) - set(known)
    if unknown:
        raise ConfigError(f"{cls.kind.value}: unknown field(s) {sorted(unknown)}; known: {known}")
    try:
        kwargs = {
            name: data[name]
            if section is dataclasses.MISSING
            else _section(section, data[name], name)
            for name, section in sections.items()
            if name in data
        }
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{cls.kind.value}: {exc}") from None


def upgrade_legacy_config(data: dict[str, Any]) -> dict[str, Any]:
    """Today's shape of a config dict written in an earlier shape; others returned unchanged.

    Before configs had a class per kind, every kind was written whole with the rear-drive
    sections (``geometry`` of :class:`VehicleGeometry`, ``encoder``). A tracked or four-wheel
    config with exactly those keys (a part of them is read as today's shape, and refused)
    keeps its ``noise``, ``slip`` and ``estimators``; its rear track width becomes the gauge
    (tracked) or both track widths, the IMU and antenna offsets and heights become lever arms,
    and the mean wheel radius becomes the unloaded tyre radius. A tracked config's
    ``noise.gyro_std_radps`` (until a crawler's gyro was its ``gyro`` section alone) and
    ``noise.accel_bias_walk_mps2`` (until it was dropped: the tracked filter has no
    accelerometer bias state), which nothing read, are dropped. The rear-drive shape never
    changed. Values are not validated here.
    """
    kind = data.get("kind")
    if kind in (VehicleKind.TRACKED, VehicleKind.WHEELED_4WD_STEERED) and set(data) == _LEGACY:
        data = _from_rear_drive_sections(data)
    if kind == VehicleKind.TRACKED:
        noise = data.get("noise")
        if isinstance(noise, dict) and not _TRACKED_UNREAD_NOISE.isdisjoint(noise):
            kept = {k: v for k, v in noise.items() if k not in _TRACKED_UNREAD_NOISE}
            data = {**data, "noise": kept}
    return data


_TRACKED_UNREAD_NOISE = frozenset({"gyro_std_radps", "accel_bias_walk_mps2"})
"""The noise fields a tracked config had that the tracked estimator never read."""


def _from_rear_drive_sections(data: dict[str, Any]) -> dict[str, Any]:
    """A tracked or four-wheel config written with the rear-drive sections, in its kind's
    shape (:func:`upgrade_legacy_config`)."""
    kind = data["kind"]
    geo = data.get("geometry")
    geo = geo if isinstance(geo, dict) else {}
    out: dict[str, Any] = {k: data[k] for k in ("kind", "noise", "slip", "estimators") if k in data}
    arms = _legacy_lever_arms(geo)
    if kind == VehicleKind.TRACKED:
        out["geometry"] = {**_rename(geo, {"track_width_m": "track_gauge_m"}), **arms}
        return out
    out["chassis"] = {
        **_rename(geo, {"track_width_m": "front_track_m"}),
        **_rename(geo, {"track_width_m": "rear_track_m"}),
        **arms,
    }
    radii = [geo[k] for k in ("wheel_radius_left_m", "wheel_radius_right_m") if k in geo]
    if radii:
        out["tyre"] = {"unloaded_radius_m": sum(radii) / len(radii)}
    return out


_LEGACY = {"kind", "geometry", "encoder", "noise", "slip", "estimators"}
"""The keys every config had before configs had a class per kind."""


def _rename(section: dict[str, Any], names: Mapping[str, str]) -> dict[str, Any]:
    return {new: section[old] for old, new in names.items() if old in section}


def _legacy_lever_arms(geo: dict[str, Any]) -> dict[str, list[float]]:
    """Rear-drive offsets (x, y) and heights h0, h0 + h1 as (x, y, z) lever arms."""
    default = VehicleGeometry()
    h0, h1 = (geo.get(k, getattr(default, k)) for k in ("h0_m", "h1_m"))
    if not all(isinstance(h, int | float) for h in (h0, h1)):
        return {}  # a value no config could hold: left to the defaults
    arms = {
        "imu_lever_arm_m": ("imu_offset_m", h0),
        "antenna_lever_arm_m": ("antenna_offset_m", h0 + h1),
    }
    return {arm: [*geo.get(offset, (0.0, 0.0)), z] for arm, (offset, z) in arms.items()}
