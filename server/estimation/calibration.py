"""Online calibrations read from an estimator's rows, generically from its spec.

A spec's :class:`~estimator.spec.CalibrationChannel` names the value and std fields of its rows
and where a vehicle's config sets the std below which the calibration has converged. This module
reads that, for any estimator:

* :func:`calibration_states`: each calibration of one row (value, std, limit, converged);
* :func:`converged_since`: since when each has been as it is now (converged or not), over a
  window of rows: the stamp of the first row after the last one that differed;
* :func:`stored_calibrations`: the newest stored calibration of every vehicle and estimator,
  which the server gives its estimator registry at start, so a restart restores rather than
  relearns (:class:`server.estimation.registry.EstimatorRegistry`);
* :func:`known_calibrations`: of a calibration's fields, those of the channels that hold a
  value (what an estimator is given back: a calibration not learnt yet is left to start anew).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from estimator.catalog import SPECS
from estimator.config import VehicleConfig
from estimator.spec import CalibrationChannel, EstimatorSpec
from server.storage.base import Store

__all__ = [
    "CalibrationState",
    "calibration_states",
    "converged_since",
    "known_calibrations",
    "row_fields",
    "stored_calibrations",
]


@dataclass(frozen=True, slots=True)
class CalibrationState:
    """One calibration of one row: ``value`` and ``std`` in ``unit`` (None where the row has
    none), the std it converges below (``limit``, None without one in the config), whether
    the config turns it on and whether it has converged."""

    channel: CalibrationChannel
    unit: str
    value: float | None
    std: float | None
    limit: float | None
    enabled: bool
    converged: bool


def _config_value(config: VehicleConfig, path: str | None) -> object:
    """The config's attribute at the dotted ``path`` (None where there is none)."""
    if path is None:
        return None
    out: object = config
    for part in path.split("."):
        out = getattr(out, part, None)
    return out


def _enabled(channel: CalibrationChannel, config: VehicleConfig) -> bool:
    return channel.enabled_config is None or bool(_config_value(config, channel.enabled_config))


def _limits(
    channel: CalibrationChannel, config: VehicleConfig, values: np.ndarray
) -> np.ndarray | None:
    """The std below which the calibration has converged, per row of ``values`` (n,): the
    config's number times ``limit_scale`` (times ``|value|`` when ``relative``); None if the
    config has no such number."""
    raw = _config_value(config, channel.limit_config)
    if not isinstance(raw, int | float) or isinstance(raw, bool):
        return None
    limit = float(raw) * channel.limit_scale
    return limit * np.abs(values) if channel.relative else np.full(values.shape, limit)


def _converged(
    channel: CalibrationChannel, config: VehicleConfig, values: np.ndarray, stds: np.ndarray
) -> np.ndarray:
    """Which rows (n,) hold a converged calibration: on, finite, std at most its limit."""
    limits = _limits(channel, config, values)
    if limits is None or not _enabled(channel, config):
        return np.zeros(values.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        return np.isfinite(values) & np.isfinite(stds) & (stds <= limits)


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def calibration_states(
    spec: EstimatorSpec, config: VehicleConfig, row: np.ndarray
) -> list[CalibrationState]:
    """Each of ``spec.calibrations`` in ``row`` (a 0-d or 1-element array of ``spec.dtype``)."""
    out = []
    for c in spec.calibrations:
        value = np.atleast_1d(np.asarray(row[c.field], dtype=float))
        std = np.atleast_1d(np.asarray(row[c.std_field], dtype=float))
        limit = _limits(c, config, value)
        out.append(
            CalibrationState(
                channel=c,
                unit=spec.field(c.field).unit,
                value=_finite(float(value[0])),
                std=_finite(float(std[0])),
                limit=None if limit is None else _finite(float(limit[0])),
                enabled=_enabled(c, config),
                converged=bool(_converged(c, config, value, std)[0]),
            )
        )
    return out


def _since(stamps: np.ndarray, state: np.ndarray) -> tuple[int, bool]:
    """Stamp of the first row of the last stretch of equal ``state`` (n,) and whether that
    stretch starts at the window's first row (it may have begun before)."""
    changed = np.flatnonzero(state != state[-1])
    if changed.size == 0:
        return int(stamps[0]), True
    return int(stamps[changed[-1] + 1]), False


def converged_since(
    spec: EstimatorSpec, config: VehicleConfig, rows: np.ndarray
) -> dict[str, tuple[int, bool]]:
    """Per calibration key (and ``spec.uncalibrated_flag``'s name, when the spec has one):
    ``(since_ns, from_window_start)``, when the calibration became what it is in the last of
    ``rows`` (time-ordered, at least one, with ``stamp_ns``, the calibration fields and
    ``flags``); ``from_window_start`` says it already was so at the first row."""
    stamps = rows["stamp_ns"]
    out = {}
    for c in spec.calibrations:
        values = np.asarray(rows[c.field], dtype=float)
        stds = np.asarray(rows[c.std_field], dtype=float)
        out[c.key] = _since(stamps, _converged(c, config, values, stds))
    if spec.uncalibrated_flag is not None:
        mask = spec.flag_mask(spec.uncalibrated_flag)
        out[spec.uncalibrated_flag] = _since(stamps, (rows["flags"] & mask) != 0)
    return out


def row_fields(spec: EstimatorSpec) -> list[str]:
    """The fields :func:`converged_since` reads of ``spec``'s rows."""
    fields = ["stamp_ns"]
    for c in spec.calibrations:
        fields += [c.field, c.std_field]
    if spec.uncalibrated_flag is not None:
        fields.append("flags")
    return fields


def known_calibrations(spec: EstimatorSpec, values: Mapping[str, float]) -> dict[str, float]:
    """The fields of ``values`` (``{field: value}`` of ``spec``'s calibrations) of every channel
    whose value and std are both there and finite; the others (NaN: not learnt yet, or a mode
    that does not calibrate) left out."""
    out: dict[str, float] = {}
    for c in spec.calibrations:
        value, std = values.get(c.field), values.get(c.std_field)
        if value is not None and std is not None and math.isfinite(value) and math.isfinite(std):
            out[c.field], out[c.std_field] = float(value), float(std)
    return out


def stored_calibrations(
    store: Store, specs: dict[str, EstimatorSpec] | None = None
) -> dict[tuple[str, str], dict[str, float]]:
    """The calibration of every vehicle's newest stored row, per ``(vehicle_id, estimator)``
    of the estimators whose spec declares calibrations (``{field: value}``, values and stds,
    of the channels the row holds: :func:`known_calibrations`); rows without any (NaN: a mode
    that does not calibrate) are left out."""
    out: dict[tuple[str, str], dict[str, float]] = {}
    for name, spec in (specs or SPECS).items():
        if not spec.calibrations:
            continue
        fields = [f for c in spec.calibrations for f in (c.field, c.std_field)]
        try:
            newest = store.latest_all(name)
        except ValueError:  # a store built without this estimator's tables
            continue
        for vid, row in newest.items():
            values = known_calibrations(spec, {f: float(row[f]) for f in fields})
            if values:
                out[(vid, name)] = values
    return out
