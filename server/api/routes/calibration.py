"""``/vehicles/{id}/calibration``: what a vehicle's estimators calibrate online, and a reset.

Generic over the specs: an estimator whose spec declares ``calibrations``
(:class:`estimator.spec.CalibrationChannel`) has a part here, read from its newest stored row
(value and 1-sigma per calibration, converged against the vehicle config's threshold) and, for
since when each has been as it is, from its rows of the last ``lookback_s``
(:mod:`server.estimation.calibration`). ``DELETE`` makes the running estimator forget the
vehicle's calibration and learn it anew; the rows after it carry the fresh calibration, so a
restart keeps the reset (the server restores each vehicle's newest stored calibration).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, Query, status
from pydantic import BaseModel, Field

from estimator.catalog import SPECS
from estimator.config import ConfigError, VehicleConfig, vehicle_config_from_dict
from estimator.spec import EstimatorSpec
from server.api.deps import (
    EventsDep,
    StoreDep,
    VehicleDep,
    require_role,
    vehicle_estimators,
)
from server.api.errors import Conflict, NotFound, error_responses
from server.estimation.calibration import (
    CalibrationState,
    calibration_states,
    converged_since,
    row_fields,
)
from server.storage.base import Store, VehicleRecord
from server.timeparse import format_ns

__all__ = [
    "CalibrationPublic",
    "CalibrationResetPublic",
    "EstimatorCalibrationPublic",
    "VehicleCalibrationPublic",
    "router",
]

router = APIRouter(prefix="/vehicles", tags=["calibration"])

_S = 1_000_000_000
DEFAULT_LOOKBACK_S = 3600
MAX_LOOKBACK_S = 24 * 3600


class CalibrationPublic(BaseModel):
    """One calibration of a vehicle as of its newest stored row."""

    key: str = Field(description="the spec's calibration key")
    label: str
    field: str = Field(description="row field of the value (`std_field`: its 1-sigma)")
    std_field: str
    unit: str
    value: float | None = Field(description="current value (null: none yet)")
    std: float | None = Field(description="its 1-sigma, in `unit`")
    limit: float | None = Field(description="converged while std <= limit (vehicle config)")
    enabled: bool = Field(description="the vehicle's config turns this calibration on")
    converged: bool
    since_ns: int | None = Field(
        description="first stored row of the current stretch (converged or not)"
    )
    since_window_start: bool = Field(
        description="the stretch began at or before the window's first row: so at least since"
    )


class EstimatorCalibrationPublic(BaseModel):
    """One estimator's calibrations of a vehicle."""

    estimator: str
    stamp_ns: int | None = Field(description="the newest stored row's stamp (null: no rows yet)")
    time: str | None
    uncalibrated: bool | None = Field(
        description="the newest row holds the spec's `uncalibrated_flag` (its values rest on a "
        "calibration that has not converged); null when the spec has none or no rows yet"
    )
    uncalibrated_since_ns: int | None
    calibrations: list[CalibrationPublic]


class VehicleCalibrationPublic(BaseModel):
    """What a vehicle's estimators calibrate online."""

    vehicle_id: str
    lookback_s: int = Field(description="window of stored rows read for `since_ns`")
    estimators: list[EstimatorCalibrationPublic]


class CalibrationResetPublic(BaseModel):
    """A reset sent to the running estimator of one vehicle."""

    vehicle_id: str
    estimator: str
    reset: bool = True


def _config(record: VehicleRecord) -> VehicleConfig | None:
    try:
        return vehicle_config_from_dict(record.config)
    except (ConfigError, TypeError, ValueError):
        return None


def _calibrating(record: VehicleRecord) -> list[EstimatorSpec]:
    """The vehicle's estimators whose spec declares calibrations, primary first."""
    return [SPECS[n] for n in vehicle_estimators(record) if n in SPECS and SPECS[n].calibrations]


def _public(state: CalibrationState, since: tuple[int, bool] | None) -> CalibrationPublic:
    c = state.channel
    return CalibrationPublic(
        key=c.key,
        label=c.label,
        field=c.field,
        std_field=c.std_field,
        unit=state.unit,
        value=state.value,
        std=state.std,
        limit=state.limit,
        enabled=state.enabled,
        converged=state.converged,
        since_ns=None if since is None else since[0],
        since_window_start=False if since is None else since[1],
    )


def _of_estimator(
    store: Store, vehicle_id: str, spec: EstimatorSpec, config: VehicleConfig, lookback_ns: int
) -> EstimatorCalibrationPublic:
    """``spec``'s calibrations of the vehicle from its newest row and the window before it."""
    newest = store.latest(vehicle_id, estimator=spec.name)
    if newest is None:
        empty = spec.empty_rows(1)
        states = calibration_states(spec, config, empty)
        return EstimatorCalibrationPublic(
            estimator=spec.name,
            stamp_ns=None,
            time=None,
            uncalibrated=None,
            uncalibrated_since_ns=None,
            calibrations=[_public(s, None) for s in states],
        )
    stamp = int(newest["stamp_ns"])
    rows = store.query_series(
        vehicle_id, stamp - lookback_ns, stamp + 1, row_fields(spec), estimator=spec.name
    )
    since = converged_since(spec, config, rows) if rows.shape[0] else {}
    flag = spec.uncalibrated_flag
    return EstimatorCalibrationPublic(
        estimator=spec.name,
        stamp_ns=stamp,
        time=format_ns(stamp),
        uncalibrated=None if flag is None else bool(int(newest["flags"]) & spec.flag_mask(flag)),
        uncalibrated_since_ns=since[flag][0] if flag is not None and flag in since else None,
        calibrations=[
            _public(s, since.get(s.channel.key))
            for s in calibration_states(spec, config, np.atleast_1d(newest))
        ],
    )


@router.get(
    "/{vehicle_id}/calibration",
    response_model=VehicleCalibrationPublic,
    responses=error_responses(401, 403, 404, 422),
    summary="The vehicle's online calibrations, each with its uncertainty",
    description=(
        "For every estimator the vehicle runs whose spec declares `calibrations` (`GET "
        "/estimators`; MDSF: the GNSS and wheel clock offsets, each wheel's rolling radius, the "
        "IMU's mounting pitch; tracked: the yaw gyro's angle random walk measured standing): "
        "each calibration's value and 1-sigma in its unit as of the "
        "newest stored row, the std it converges below (`limit`, from the vehicle's config), "
        "whether it has converged and since when (`since_ns`, the first stored row of the "
        "current stretch within the last `lookback_s`; `since_window_start` when it was "
        "already so at the window's start), and whether the newest row is flagged "
        "uncalibrated. A vehicle restarted with the server goes on from its newest stored "
        "calibration."
    ),
)
def get_calibration(
    vehicle: VehicleDep,
    store: StoreDep,
    estimator: Annotated[
        str | None, Query(max_length=64, description="only this estimator's calibrations")
    ] = None,
    lookback_s: Annotated[
        int,
        Query(ge=1, le=MAX_LOOKBACK_S, description="window of stored rows read for `since_ns`"),
    ] = DEFAULT_LOOKBACK_S,
) -> VehicleCalibrationPublic:
    specs = _calibrating(vehicle)
    if estimator is not None:
        specs = [s for s in specs if s.name == estimator]
        if not specs:
            raise NotFound(
                f"vehicle {vehicle.vehicle_id!r} runs no estimator {estimator!r} that calibrates"
            )
    config = _config(vehicle)
    parts = (
        []
        if config is None
        else [_of_estimator(store, vehicle.vehicle_id, s, config, lookback_s * _S) for s in specs]
    )
    return VehicleCalibrationPublic(
        vehicle_id=vehicle.vehicle_id, lookback_s=lookback_s, estimators=parts
    )


@router.delete(
    "/{vehicle_id}/calibration/{estimator}",
    response_model=CalibrationResetPublic,
    status_code=status.HTTP_202_ACCEPTED,
    responses=error_responses(401, 403, 404, 409),
    dependencies=[Depends(require_role("operator"))],
    summary="Reset the vehicle's calibration in one estimator (operator)",
    description=(
        "The running estimator forgets the vehicle's calibration (back to the config's priors) "
        "and learns it anew, taken between two steps (202: sent). Counted in the estimator's "
        "counters (`calibration_resets`) and logged. Rows after the reset carry the fresh "
        "calibration (and, where the spec has an `uncalibrated_flag`, that flag until it "
        "converges again); a restart keeps the reset. 404 for an "
        "estimator that does not exist or calibrates nothing, 409 when the vehicle does not "
        "run it."
    ),
)
def reset_calibration(
    vehicle: VehicleDep, estimator: str, events: EventsDep
) -> CalibrationResetPublic:
    spec = SPECS.get(estimator)
    if spec is None or not spec.calibrations:
        known = ", ".join(sorted(n for n, s in SPECS.items() if s.calibrations)) or "none"
        raise NotFound(f"estimator {estimator!r} calibrates nothing (those that do: {known})")
    runs = vehicle_estimators(vehicle)
    if estimator not in runs:
        raise Conflict(f"vehicle {vehicle.vehicle_id!r} runs {', '.join(runs)}, not {estimator!r}")
    events.on_calibration_reset(vehicle.vehicle_id, estimator)
    return CalibrationResetPublic(vehicle_id=vehicle.vehicle_id, estimator=estimator)
