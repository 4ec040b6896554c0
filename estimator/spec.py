"""Estimator specs: what an estimator takes and gives, declared once, as plain data.

Everything after an estimator's ``advance()`` (storage, REST, reports, slip maps, live views,
alerts, the 3D view, the dashboard) works from its :class:`EstimatorSpec`, never from one
estimator's field names. A spec says:

* ``fields``: the output row, a numpy structured dtype (``stamp_ns`` int64 first, units in the
  names) with a label, unit and description per field;
* ``flags``: the bits of its ``flags`` field, by name;
* *channels*, what the rest of the product may read of a row:

  - :class:`SlipChannel`: a per-wheel or per-track slip-like value in percent (label, validity
    flag, standard deviation, band edges), what reports, slip maps, alerts and colours read;
  - :class:`SpeedChannel`: a speed; ``motion`` names the one that decides "moving";
  - :class:`PositionChannel`: east/north/up in the vehicle's local ENU frame (its anchor) and a
    heading, with the flag that marks a dead-reckoned position;
  - :class:`ChartSpec`: which fields a live or history chart draws together;
  - :class:`StateChannel`: an enumerated field (a crawler's motion state), drawn as a band of
    coloured stretches under the charts;
  - :class:`ValueChannel`: a headline value that is neither slip nor speed (friction μ), with
    the flag of the rows that inform it; ``mapped`` makes it a layer of the slip map;
  - :class:`WheelValueChannel`: a per-wheel share in percent other than slip (grip used), what
    the 3D view colours a tyre by when the spec has one;
  - :class:`CommandSpec`: a switch an operator turns on or off for one vehicle (MDSF's
    calibration drive), sent to the running estimator;
  - :class:`CalibrationChannel`: a quantity the estimator calibrates online per vehicle (a
    rolling radius, a clock offset), its value and 1-sigma carried in the rows, and where the
    vehicle's config sets the std below which it has converged;
  - ``ok_flag`` / ``degraded_flags``: the row's quality at a glance.

A spec is pure data (no numerics, no I/O) so the server can read every spec without building an
estimator. ``to_dict()`` is what REST (``/api/v1/estimators``) and the dashboard receive.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import InitVar, dataclass, field
from enum import IntFlag, StrEnum
from typing import Any

import numpy as np

__all__ = [
    "AlertRule",
    "CalibrationChannel",
    "ChartSpec",
    "CommandSpec",
    "EstimatorSpec",
    "FieldSpec",
    "FlagSpec",
    "PositionChannel",
    "SlipChannel",
    "SpecError",
    "SpeedChannel",
    "StateChannel",
    "StateValue",
    "ValueChannel",
    "WheelPosition",
    "WheelValueChannel",
    "flags_from",
    "gnss_clock_channel",
]

#: numpy kinds a field may have: float64, int64, int32.
FIELD_KINDS = ("f8", "i8", "i4")


class SpecError(ValueError):
    """A spec contradicts itself (unknown field in a channel, duplicate name or bit, ...)."""


class WheelPosition(StrEnum):
    """Named place of a wheel or track on a vehicle (a kind's ``positions``, a slip channel's)."""

    REAR_LEFT = "rear_left"
    REAR_RIGHT = "rear_right"
    FRONT_LEFT = "front_left"
    FRONT_RIGHT = "front_right"
    TRACK_LEFT = "track_left"
    TRACK_RIGHT = "track_right"


@dataclass(frozen=True, slots=True)
class FieldSpec:
    """One column of an estimator's output row.

    ``kind`` is a numpy type code (``f8``, ``i8``, ``i4``); floats are NaN where unknown.
    ``unit`` is what the name's suffix says (``m/s``, ``%``, ``rad``, ``ns``, ``""`` for counts
    and bit fields).
    """

    name: str
    kind: str
    unit: str
    label: str
    description: str = ""


@dataclass(frozen=True, slots=True)
class FlagSpec:
    """One bit of the ``flags`` field."""

    name: str
    bit: int
    description: str = ""

    @property
    def mask(self) -> int:
        return 1 << self.bit


def flags_from(bits: type[IntFlag], descriptions: Mapping[str, str]) -> tuple[FlagSpec, ...]:
    """One :class:`FlagSpec` per single-bit member of ``bits``, described by ``descriptions``
    (every member must have one: a flag nobody can read is a flag nobody can use)."""
    out = []
    for member in bits:
        if member.value and member.name is not None:
            out.append(
                FlagSpec(member.name, member.value.bit_length() - 1, descriptions[member.name])
            )
    return tuple(out)


@dataclass(frozen=True, slots=True)
class SlipChannel:
    """A slip-like value of one wheel or track, in percent (+ traction slip, − skid).

    A row's value counts where ``valid_flag`` is set (or, without one, where it is finite).
    ``band_edges_pct`` cut |slip| into bands for reports, maps and colours (a vehicle's config
    may override them).
    """

    key: str
    label: str
    field: str
    position: WheelPosition
    valid_flag: str | None = None
    std_field: str | None = None
    band_edges_pct: tuple[float, ...] = (5.0, 15.0)


@dataclass(frozen=True, slots=True)
class SpeedChannel:
    """A speed in m/s (signed, forward positive)."""

    key: str
    label: str
    field: str
    std_field: str | None = None


@dataclass(frozen=True, slots=True)
class PositionChannel:
    """Where the vehicle is: metres in its local ENU frame (origin: the vehicle's anchor).

    ``carried_flag`` marks rows whose position was dead-reckoned rather than measured;
    ``pitch_field`` / ``roll_field`` (rad) give the body's attitude where the estimator has it;
    ``east_std_field`` / ``north_std_field`` (m) the position's 1-sigma where it has one.
    """

    east_field: str
    north_field: str
    up_field: str | None = None
    heading_field: str | None = None
    carried_flag: str | None = None
    pitch_field: str | None = None
    roll_field: str | None = None
    east_std_field: str | None = None
    north_std_field: str | None = None


@dataclass(frozen=True, slots=True)
class StateValue:
    """One value of an enumerated field: its integer, a name (``"pivot"``) and a label."""

    value: int
    name: str
    label: str


@dataclass(frozen=True, slots=True)
class StateChannel:
    """An enumerated ``i4`` field whose values name states (a crawler's motion state).

    Views draw it as a band of stretches, one colour per state in ``states`` order; a value
    not in ``states`` is drawn as unknown. ``confidence_field`` (0..1) and ``uncertain_flag``
    say how sure the estimator is of the state.
    """

    key: str
    label: str
    field: str
    states: tuple[StateValue, ...]
    confidence_field: str | None = None
    uncertain_flag: str | None = None


@dataclass(frozen=True, slots=True)
class ValueChannel:
    """A headline value that is neither a slip nor a speed (friction μ), in ``unit``.

    Rows with ``valid_flag`` inform it (their value is this tick's estimate, with
    ``std_field``); rows without it hold an older value, shown as held, never as current.
    ``mapped`` makes it a layer of the slip map: per cell the time-weighted mean over the
    informing samples and their count.
    """

    key: str
    label: str
    field: str
    unit: str = ""
    std_field: str | None = None
    valid_flag: str | None = None
    mapped: bool = False

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (in the spec's ``values``, and a slip map's ``layer``)."""
        return {
            "key": self.key,
            "label": self.label,
            "field": self.field,
            "unit": self.unit,
            "std_field": self.std_field,
            "valid_flag": self.valid_flag,
            "mapped": self.mapped,
        }


@dataclass(frozen=True, slots=True)
class WheelValueChannel:
    """A per-wheel share in percent other than slip (the share of the available grip used):
    a tile per wheel, and what the 3D view colours a tyre by (0 % green to 100 % red)."""

    key: str
    label: str
    field: str
    position: WheelPosition


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """A switch an operator turns on or off for one vehicle while it runs (``PUT
    /vehicles/{id}/commands/{estimator}/{key}``): the fleet estimator's ``command(vehicle_id,
    key, on)`` takes it on its own thread, between two steps."""

    key: str
    label: str
    description: str


@dataclass(frozen=True, slots=True)
class CalibrationChannel:
    """A quantity the estimator learns online for each vehicle, read from its rows.

    ``field`` holds the value and ``std_field`` its 1-sigma (same unit). It has converged while
    ``std <= limit``, the limit being the vehicle config's number at ``limit_config`` (a dotted
    path, e.g. ``"calibration.radius_converged_pct"``) times ``limit_scale`` (into the std's
    unit), times ``|value|`` too when ``relative``. ``enabled_config`` names the config switch
    that turns it on (off: the estimator keeps the configured value). An estimator whose spec
    has calibrations gives a vehicle's with ``calibration_fields(vehicle_id)`` (``{field:
    value}`` as in its rows), takes them back with ``restore_calibration_fields(vehicle_id,
    values)`` and forgets them with ``reset_calibration(vehicle_id)``.
    """

    key: str
    label: str
    field: str
    std_field: str
    limit_config: str
    limit_scale: float = 1.0
    relative: bool = False
    enabled_config: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (in the spec's ``calibrations``)."""
        return {
            "key": self.key,
            "label": self.label,
            "field": self.field,
            "std_field": self.std_field,
            "limit_config": self.limit_config,
            "limit_scale": self.limit_scale,
            "relative": self.relative,
            "enabled_config": self.enabled_config,
        }


def gnss_clock_channel(enabled_config: str | None = None) -> CalibrationChannel:
    """The GNSS receiver's clock offset against the IMU as a calibration (``gnss_clock_offset_s``
    and its 1-sigma, seconds), converged below the config's ``clock_offset_converged_ms``:
    the same quantity wherever an estimator learns it."""
    return CalibrationChannel(
        "gnss_clock_offset",
        "GNSS clock offset",
        "gnss_clock_offset_s",
        "gnss_clock_offset_std_s",
        "calibration.clock_offset_converged_ms",
        1e-3,
        enabled_config=enabled_config,
    )


@dataclass(frozen=True, slots=True)
class AlertRule:
    """An alert an estimator's rows raise: a condition on one row, held ``hold_s`` (sensor time).

    The condition holds where ``field`` (``|field|`` with ``absolute``) is above ``above`` or
    below ``below`` (one of the two), every flag of ``when`` is set and none of ``unless``; a
    rule without a field holds on its flags alone. NaN never holds. A rule naming a slip
    channel (``slip``) alerts on it in place of the vehicle's slip threshold. ``above``,
    ``below`` and ``hold_s`` are defaults a server may set otherwise per rule.
    """

    key: str
    label: str
    field: str | None = None
    above: float | None = None
    below: float | None = None
    absolute: bool = False
    when: tuple[str, ...] = ()
    unless: tuple[str, ...] = ()
    hold_s: float = 2.0
    slip: str | None = None


@dataclass(frozen=True, slots=True)
class ChartSpec:
    """Fields one chart draws together, all in ``unit``."""

    key: str
    title: str
    unit: str
    fields: tuple[str, ...]


@dataclass(frozen=True)
class EstimatorSpec:
    """Everything the product needs to know of one estimator's inputs and outputs.

    Parameters
    ----------
    name : str
        Registry name (``"mdsf"``); also the storage and REST key.
    title, description : str
        For people (dashboard, OpenAPI).
    kinds : tuple of str
        Vehicle kinds (``estimator.config.VehicleKind`` values) it can run on.
    inputs : tuple of str
        Wire stream names it consumes (``"gnss"``, ``"imu"``, ``"wheels"`` …); others are not
        pushed to it.
    fields : tuple of FieldSpec
        Output row, ``stamp_ns`` (``i8``) first; a ``flags`` field (``i4``) when ``flags`` is set.
    flags : tuple of FlagSpec
    slips, speeds : tuple of SlipChannel / SpeedChannel
    motion : str or None
        Key of the speed channel whose ``|value|`` decides whether the vehicle moves.
    position : PositionChannel or None
    charts : tuple of ChartSpec
    ok_flag : str or None
        Flag of a row whose main reference is sound (for MDSF: GNSS fused).
    degraded_flags : tuple of str
        Flags of a row computed without its main reference (shaded in charts).
    states, values, wheel_values : tuple of StateChannel / ValueChannel / WheelValueChannel
        Enumerated fields (bands under the charts, reports per state), headline values (tiles,
        map layers) and per-wheel shares (tiles, tyre colours).
    alerts : tuple of AlertRule
        Alerts of the estimator's own beyond the slip threshold and degraded flags.
    commands : tuple of CommandSpec
        Switches an operator may send the running estimator for one vehicle.
    calibrations : tuple of CalibrationChannel
        What it calibrates online per vehicle (value and std fields of its rows).
    uncalibrated_flag : str or None
        Flag of rows whose values rest on a calibration that has not converged.
    row_dtype : numpy.dtype, optional
        The estimator's own dtype object for its rows, when it has one: it must equal the
        fields' dtype, and :attr:`dtype` is then that very object, so checking a row array's
        dtype is an identity test rather than a field-by-field comparison.
    """

    name: str
    title: str
    kinds: tuple[str, ...]
    inputs: tuple[str, ...]
    fields: tuple[FieldSpec, ...]
    flags: tuple[FlagSpec, ...] = ()
    slips: tuple[SlipChannel, ...] = ()
    speeds: tuple[SpeedChannel, ...] = ()
    motion: str | None = None
    position: PositionChannel | None = None
    charts: tuple[ChartSpec, ...] = ()
    ok_flag: str | None = None
    degraded_flags: tuple[str, ...] = ()
    description: str = ""
    states: tuple[StateChannel, ...] = ()
    values: tuple[ValueChannel, ...] = ()
    wheel_values: tuple[WheelValueChannel, ...] = ()
    alerts: tuple[AlertRule, ...] = ()
    commands: tuple[CommandSpec, ...] = ()
    calibrations: tuple[CalibrationChannel, ...] = ()
    uncalibrated_flag: str | None = None
    row_dtype: InitVar[np.dtype | None] = None
    _by_name: Mapping[str, FieldSpec] = field(init=False, repr=False, compare=False)
    _dtype: np.dtype = field(init=False, repr=False, compare=False)

    def __post_init__(self, row_dtype: np.dtype | None) -> None:
        names = [f.name for f in self.fields]
        if not names or names[0] != "stamp_ns" or self.fields[0].kind != "i8":
            raise SpecError(f"{self.name}: the first field must be stamp_ns (i8)")
        if len(set(names)) != len(names):
            raise SpecError(f"{self.name}: duplicate field names")
        for f in self.fields:
            if f.kind not in FIELD_KINDS:
                raise SpecError(f"{self.name}.{f.name}: kind {f.kind!r} not in {FIELD_KINDS}")
        object.__setattr__(self, "_by_name", {f.name: f for f in self.fields})
        built = np.dtype([(f.name, f.kind) for f in self.fields])
        if row_dtype is not None and row_dtype != built:
            raise SpecError(f"{self.name}: row_dtype differs from the fields")
        object.__setattr__(self, "_dtype", row_dtype if row_dtype is not None else built)
        self._check_flags()
        self._check_channels()

    def _check_flags(self) -> None:
        if not self.flags:
            return
        if self._by_name.get("flags") is None or self._by_name["flags"].kind != "i4":
            raise SpecError(f"{self.name}: flags declared but no i4 'flags' field")
        bits = [f.bit for f in self.flags]
        if len(set(bits)) != len(bits) or not all(0 <= b < 31 for b in bits):
            raise SpecError(f"{self.name}: flag bits must be distinct, 0..30")
        if len({f.name for f in self.flags}) != len(self.flags):
            raise SpecError(f"{self.name}: duplicate flag names")

    def _need_field(self, name: str | None, what: str, kind: str = "f8") -> None:
        if name is None:
            return
        f = self._by_name.get(name)
        if f is None or f.kind != kind:
            raise SpecError(f"{self.name}: {what} names {name!r}, not a {kind} field")

    def _need_flag(self, name: str | None, what: str) -> None:
        if name is not None and name not in {f.name for f in self.flags}:
            raise SpecError(f"{self.name}: {what} names unknown flag {name!r}")

    def _check_channels(self) -> None:
        for s in self.slips:
            self._need_field(s.field, f"slip channel {s.key}")
            self._need_field(s.std_field, f"slip channel {s.key}")
            self._need_flag(s.valid_flag, f"slip channel {s.key}")
            edges = list(s.band_edges_pct)
            if not edges or edges != sorted(set(edges)) or not all(map(math.isfinite, edges)):
                raise SpecError(f"{self.name}: slip channel {s.key} band edges must increase")
        for v in self.speeds:
            self._need_field(v.field, f"speed channel {v.key}")
            self._need_field(v.std_field, f"speed channel {v.key}")
        for keys in ([s.key for s in self.slips], [v.key for v in self.speeds]):
            if len(set(keys)) != len(keys):
                raise SpecError(f"{self.name}: duplicate channel keys {keys}")
        if self.motion is not None and self.motion not in {v.key for v in self.speeds}:
            raise SpecError(f"{self.name}: motion names unknown speed channel {self.motion!r}")
        if self.position is not None:
            p = self.position
            fields = (p.east_field, p.north_field, p.up_field, p.heading_field)
            stds = (p.east_std_field, p.north_std_field)
            for name in (*fields, p.pitch_field, p.roll_field, *stds):
                self._need_field(name, "position")
            self._need_flag(p.carried_flag, "position")
        self._check_extra_channels()
        for c in self.charts:
            for name in c.fields:
                self._need_field(name, f"chart {c.key}")
        self._need_flag(self.ok_flag, "ok_flag")
        for name in self.degraded_flags:
            self._need_flag(name, "degraded_flags")
        self._check_alerts()

    def _check_alerts(self) -> None:
        if len({a.key for a in self.alerts}) != len(self.alerts):
            raise SpecError(f"{self.name}: duplicate alert keys")
        for a in self.alerts:
            what = f"alert {a.key}"
            self._need_field(a.field, what)
            for flag in (*a.when, *a.unless):
                self._need_flag(flag, what)
            if a.field is not None and (a.above is None) == (a.below is None):
                raise SpecError(f"{self.name}: {what} needs one of above and below")
            if a.field is None and not a.when:
                raise SpecError(f"{self.name}: {what} needs a field or a flag")
            if a.slip is not None and a.slip not in {s.key for s in self.slips}:
                raise SpecError(f"{self.name}: {what} names unknown slip channel {a.slip!r}")
            if not a.hold_s >= 0:
                raise SpecError(f"{self.name}: {what} hold_s must be >= 0")

    def _check_extra_channels(self) -> None:
        for st in self.states:
            self._need_field(st.field, f"state channel {st.key}", "i4")
            self._need_field(st.confidence_field, f"state channel {st.key}")
            self._need_flag(st.uncertain_flag, f"state channel {st.key}")
            values = [v.value for v in st.states]
            if not values or len(set(values)) != len(values):
                raise SpecError(f"{self.name}: state channel {st.key} needs distinct values")
        for v in self.values:
            self._need_field(v.field, f"value channel {v.key}")
            self._need_field(v.std_field, f"value channel {v.key}")
            self._need_flag(v.valid_flag, f"value channel {v.key}")
        for w in self.wheel_values:
            self._need_field(w.field, f"wheel value channel {w.key}")
        for c in self.calibrations:
            self._need_field(c.field, f"calibration {c.key}")
            self._need_field(c.std_field, f"calibration {c.key}")
        self._need_flag(self.uncalibrated_flag, "uncalibrated_flag")
        for keys in (
            [s.key for s in self.states],
            [v.key for v in self.values],
            [c.key for c in self.commands],
            [c.key for c in self.calibrations],
        ):
            if len(set(keys)) != len(keys):
                raise SpecError(f"{self.name}: duplicate channel keys {keys}")

    # --- reading -----------------------------------------------------------------------------
    def command(self, key: str) -> CommandSpec:
        """The command ``key`` (``KeyError`` naming the estimator if it has none)."""
        for c in self.commands:
            if c.key == key:
                return c
        raise KeyError(f"estimator {self.name!r} has no command {key!r}")

    def calibration(self, key: str) -> CalibrationChannel:
        """The calibration ``key`` (``KeyError`` naming the estimator if it has none)."""
        for c in self.calibrations:
            if c.key == key:
                return c
        raise KeyError(f"estimator {self.name!r} has no calibration {key!r}")

    def value(self, key: str) -> ValueChannel:
        """The value channel ``key`` (``KeyError`` naming the estimator if it has none)."""
        for v in self.values:
            if v.key == key:
                return v
        raise KeyError(f"estimator {self.name!r} has no value channel {key!r}")

    @property
    def dtype(self) -> np.dtype:
        """Structured dtype of one output row (native byte order, in field order)."""
        return self._dtype

    @property
    def field_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    def field(self, name: str) -> FieldSpec:
        """The field ``name`` (``KeyError`` naming the estimator if it has none)."""
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"estimator {self.name!r} has no field {name!r}") from None

    def has_field(self, name: str) -> bool:
        return name in self._by_name

    def flag_mask(self, name: str) -> int:
        """Bit mask of the flag ``name`` (``KeyError`` if it has none)."""
        for f in self.flags:
            if f.name == name:
                return f.mask
        raise KeyError(f"estimator {self.name!r} has no flag {name!r}")

    def flag_names(self, bits: int) -> list[str]:
        """Names of the flags set in ``bits``, lowest bit first."""
        return [f.name for f in sorted(self.flags, key=lambda f: f.bit) if bits & f.mask]

    def speed(self, key: str) -> SpeedChannel:
        for v in self.speeds:
            if v.key == key:
                return v
        raise KeyError(f"estimator {self.name!r} has no speed channel {key!r}")

    @property
    def motion_field(self) -> str | None:
        """Field whose ``|value|`` decides "moving", or None."""
        return None if self.motion is None else self.speed(self.motion).field

    def slip(self, key: str) -> SlipChannel:
        for s in self.slips:
            if s.key == key:
                return s
        raise KeyError(f"estimator {self.name!r} has no slip channel {key!r}")

    def empty_rows(self, n: int = 0) -> np.ndarray:
        """``n`` rows, floats NaN, integers zero."""
        out = np.zeros(n, dtype=self.dtype)
        for f in self.fields:
            if f.kind == "f8":
                out[f.name] = np.nan
        return out

    def check_rows(self, rows: object) -> np.ndarray:
        """``rows`` as a 1-d array of :attr:`dtype`, or ``TypeError`` naming what is wrong."""
        if not isinstance(rows, np.ndarray) or (
            rows.dtype is not self._dtype and rows.dtype != self._dtype
        ):
            got = getattr(rows, "dtype", type(rows).__name__)
            raise TypeError(f"rows of {self.name!r} must have its dtype, got {got}")
        if rows.ndim != 1:
            raise TypeError(f"rows of {self.name!r} must be 1-d, got shape {rows.shape}")
        return rows

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (REST ``/api/v1/estimators``, the dashboard)."""
        return {
            "name": self.name,
            "title": self.title,
            "description": self.description,
            "kinds": list(self.kinds),
            "inputs": list(self.inputs),
            "fields": [
                {
                    "name": f.name,
                    "kind": f.kind,
                    "unit": f.unit,
                    "label": f.label,
                    "description": f.description,
                }
                for f in self.fields
            ],
            "flags": [
                {"name": f.name, "bit": f.bit, "description": f.description} for f in self.flags
            ],
            "slips": [
                {
                    "key": s.key,
                    "label": s.label,
                    "field": s.field,
                    "position": str(s.position),
                    "valid_flag": s.valid_flag,
                    "std_field": s.std_field,
                    "band_edges_pct": list(s.band_edges_pct),
                }
                for s in self.slips
            ],
            "speeds": [
                {"key": v.key, "label": v.label, "field": v.field, "std_field": v.std_field}
                for v in self.speeds
            ],
            "motion": self.motion,
            "position": None
            if self.position is None
            else {
                "east_field": self.position.east_field,
                "north_field": self.position.north_field,
                "up_field": self.position.up_field,
                "heading_field": self.position.heading_field,
                "carried_flag": self.position.carried_flag,
                "pitch_field": self.position.pitch_field,
                "roll_field": self.position.roll_field,
                "east_std_field": self.position.east_std_field,
                "north_std_field": self.position.north_std_field,
            },
            "charts": [
                {"key": c.key, "title": c.title, "unit": c.unit, "fields": list(c.fields)}
                for c in self.charts
            ],
            "ok_flag": self.ok_flag,
            "degraded_flags": list(self.degraded_flags),
            **self._extra_channels_dict(),
        }

    def _extra_channels_dict(self) -> dict[str, Any]:
        """``states``, ``values``, ``wheel_values``, ``alerts``, ``commands``,
        ``calibrations`` and ``uncalibrated_flag`` of :meth:`to_dict`."""
        return {
            "states": [
                {
                    "key": s.key,
                    "label": s.label,
                    "field": s.field,
                    "states": [
                        {"value": v.value, "name": v.name, "label": v.label} for v in s.states
                    ],
                    "confidence_field": s.confidence_field,
                    "uncertain_flag": s.uncertain_flag,
                }
                for s in self.states
            ],
            "values": [v.to_dict() for v in self.values],
            "wheel_values": [
                {"key": w.key, "label": w.label, "field": w.field, "position": str(w.position)}
                for w in self.wheel_values
            ],
            "alerts": [
                {
                    "key": a.key,
                    "label": a.label,
                    "field": a.field,
                    "above": a.above,
                    "below": a.below,
                    "hold_s": a.hold_s,
                    "slip": a.slip,
                }
                for a in self.alerts
            ],
            "commands": [
                {"key": c.key, "label": c.label, "description": c.description}
                for c in self.commands
            ],
            "calibrations": [c.to_dict() for c in self.calibrations],
            "uncalibrated_flag": self.uncalibrated_flag,
        }
