"""Vehicle configuration: geometry, encoders, noise and slip thresholds.

Every section is a frozen dataclass that validates itself in ``__post_init__`` and raises
:class:`ConfigError` with the offending field named. The server turns these into JSON
(``dataclasses.asdict``) and back (:func:`vehicle_config_from_dict`).

Geometry follows ``../shared/docs/method.md`` section 1: the origin ``O`` is the ground
projection of the rear-axle midpoint; body frame X right, Y forward, Z up. In the source's
layout the IMU sits on the vertical through ``O`` at height ``h0`` and the antenna ``h1`` above
the IMU; the horizontal offsets below generalise that (lever arms), zero reproduces the source.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

__all__ = [
    "ConfigError",
    "EncoderConfig",
    "NoiseConfig",
    "SlipConfig",
    "VehicleConfig",
    "VehicleGeometry",
    "VehicleKind",
    "vehicle_config_from_dict",
]


class ConfigError(ValueError):
    """A configuration value is out of its valid range."""


class VehicleKind(StrEnum):
    """What kind of vehicle this is; the kind picks the default estimators."""

    WHEELED_REAR_DRIVE = "wheeled_rear_drive"
    TRACKED = "tracked"
    WHEELED_4WD_STEERED = "wheeled_4wd_steered"


def _positive(name: str, value: float) -> None:
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name} must be a finite number > 0, got {value!r}")


def _finite(name: str, value: float) -> None:
    if not (isinstance(value, int | float) and math.isfinite(value)):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")


@dataclass(frozen=True, slots=True)
class VehicleGeometry:
    """Where the sensors and wheels are.

    Attributes
    ----------
    h0_m : float
        IMU height above the ground (source symbol ``h0``).
    h1_m : float
        Antenna height above the IMU (source symbol ``h1``).
    track_width_m : float
        Rear track width ``b`` (wheel contact centre to contact centre).
    wheel_radius_left_m, wheel_radius_right_m : float
        Effective rolling radius ``r`` of each driven wheel.
    antenna_offset_m : tuple[float, float]
        Antenna (x right, y forward) offset from the vertical through ``O``.
    imu_offset_m : tuple[float, float]
        IMU (x right, y forward) offset from the vertical through ``O``.
    """

    h0_m: float = 1.0
    h1_m: float = 1.6
    track_width_m: float = 1.8
    wheel_radius_left_m: float = 0.85
    wheel_radius_right_m: float = 0.85
    antenna_offset_m: tuple[float, float] = (0.0, 0.0)
    imu_offset_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("h0_m", "track_width_m", "wheel_radius_left_m", "wheel_radius_right_m"):
            _positive(name, getattr(self, name))
        _finite("h1_m", self.h1_m)
        for name in ("antenna_offset_m", "imu_offset_m"):
            value = getattr(self, name)
            if len(value) != 2:
                raise ConfigError(f"{name} must have two components (x right, y forward)")
            for i, v in enumerate(value):
                _finite(f"{name}[{i}]", v)


@dataclass(frozen=True, slots=True)
class EncoderConfig:
    """Wheel encoder: a toothed ring read by a Hall or optical sensor.

    Attributes
    ----------
    teeth_per_rev : int
        ``Ns``, teeth (pulses) per wheel revolution.
    has_direction : bool
        Whether the encoder reports direction (quadrature); otherwise speed is taken as forward.
    """

    teeth_per_rev: int = 120
    has_direction: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.teeth_per_rev, int) or not 1 <= self.teeth_per_rev <= 100_000:
            raise ConfigError(
                f"teeth_per_rev must be an int in 1..100000, got {self.teeth_per_rev!r}"
            )


@dataclass(frozen=True, slots=True)
class NoiseConfig:
    """Sensor noise figures (1-sigma), used to build the filters' Q and R.

    Attributes
    ----------
    gnss_vel_std_mps : float
        GNSS velocity noise per axis when the receiver does not report it.
    accel_std_mps2 : float
        Accelerometer white noise per sample.
    gyro_std_radps : float
        Gyro white noise per sample.
    accel_bias_walk_mps2 : float
        Accelerometer bias random walk per sqrt(second).
    gnss_pos_std_m : float
        RTK-fixed horizontal position noise per axis (receivers rarely report it; 1-2 cm is
        typical) [m].
    """

    gnss_vel_std_mps: float = 0.05
    accel_std_mps2: float = 0.05
    gyro_std_radps: float = 0.005
    accel_bias_walk_mps2: float = 0.002
    gnss_pos_std_m: float = 0.02

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            _positive(f.name, getattr(self, f.name))


@dataclass(frozen=True, slots=True)
class SlipConfig:
    """When a slip value is given, and the bands reports count time in.

    Attributes
    ----------
    min_ground_speed_mps : float
        Below this ground speed *and* rim speed the vehicle is at standstill: no slip value.
    band_edges_pct : tuple[float, ...]
        Upper edges of the slip bands for reports, increasing (default <5 %, 5-15 %, >15 %).
    alert_threshold_pct : float
        |slip| above this for ``alert_hold_s`` raises an alert.
    alert_hold_s : float
    settle_max_change : float
        A slip value is given only while the wheel's ground speed changes by at most this
        fraction of itself over the span of the wheel-speed fit (``estimator.slip.unsettled``):
        starting and stopping at low speed, the fit lags and the slip is withheld (flag
        SETTLING). A large value (e.g. 1e9) turns the rule off.
    """

    min_ground_speed_mps: float = 0.2
    band_edges_pct: tuple[float, ...] = (5.0, 15.0)
    alert_threshold_pct: float = 15.0
    alert_hold_s: float = 5.0
    settle_max_change: float = 0.5

    def __post_init__(self) -> None:
        _positive("min_ground_speed_mps", self.min_ground_speed_mps)
        _positive("settle_max_change", self.settle_max_change)
        _positive("alert_threshold_pct", self.alert_threshold_pct)
        _positive("alert_hold_s", self.alert_hold_s)
        edges = list(self.band_edges_pct)
        if not edges or any(b <= a for a, b in itertools.pairwise(edges)):
            raise ConfigError("band_edges_pct must be a non-empty increasing sequence")


@dataclass(frozen=True, slots=True)
class VehicleConfig:
    """Everything the estimators need to know about one vehicle.

    Attributes
    ----------
    kind : VehicleKind
        Picks the default estimators (see the server's estimator registry).
    estimators : tuple[str, ...]
        Estimator names to run; empty means the kind's defaults.
    """

    kind: VehicleKind = VehicleKind.WHEELED_REAR_DRIVE
    geometry: VehicleGeometry = field(default_factory=VehicleGeometry)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    slip: SlipConfig = field(default_factory=SlipConfig)
    estimators: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.kind, VehicleKind):
            try:
                object.__setattr__(self, "kind", VehicleKind(self.kind))
            except ValueError as exc:
                raise ConfigError(f"kind must be one of {[k.value for k in VehicleKind]}") from exc

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (tuples become lists)."""
        return dataclasses.asdict(self)


_SECTIONS: dict[str, type] = {
    "geometry": VehicleGeometry,
    "encoder": EncoderConfig,
    "noise": NoiseConfig,
    "slip": SlipConfig,
}


def _section(cls: type, data: dict[str, Any], name: str) -> Any:
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - known
    if unknown:
        raise ConfigError(f"{name}: unknown field(s) {sorted(unknown)}")
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"{name}: {exc}") from exc


def vehicle_config_from_dict(data: dict[str, Any]) -> VehicleConfig:
    """Build a validated :class:`VehicleConfig` from a JSON-like dict (missing parts default)."""
    if not isinstance(data, dict):
        raise ConfigError("vehicle config must be an object")
    unknown = set(data) - {"kind", "estimators", *_SECTIONS}
    if unknown:
        raise ConfigError(f"unknown field(s) {sorted(unknown)}")
    kwargs: dict[str, Any] = {}
    for name, cls in _SECTIONS.items():
        if name in data:
            if not isinstance(data[name], dict):
                raise ConfigError(f"{name} must be an object")
            kwargs[name] = _section(cls, data[name], name)
    if "kind" in data:
        kwargs["kind"] = data["kind"]
    if "estimators" in data:
        kwargs["estimators"] = tuple(data["estimators"])
    return VehicleConfig(**kwargs)
