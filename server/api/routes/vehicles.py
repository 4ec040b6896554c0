"""``/vehicles``: register, configure, list and delete vehicles; their newest estimate.

Registrations, config changes and deletions go through the runtime's single store writer
(:data:`server.api.deps.WriterDep`), like every other write.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Body, Depends, Path, Response, status
from pydantic import ValidationError

from estimator.catalog import SPECS
from estimator.config import (
    ConfigError,
    VehicleConfig,
    VehicleKind,
    upgrade_legacy_config,
    vehicle_config_from_dict,
)
from estimator.spec import EstimatorSpec
from server.api.deps import (
    EstimatorDep,
    EventsDep,
    StoreDep,
    VehicleDep,
    WriterDep,
    require_role,
    vehicle_estimators,
)
from server.api.errors import Conflict, InvalidConfig, NotFound, error_responses
from server.api.models import (
    AnchorPublic,
    CommandIn,
    CommandPublic,
    EstimatePublic,
    VehicleConfigAdapter,
    VehicleConfigIn,
    VehiclePublic,
    VehiclesPublic,
)
from server.storage.base import Anchor, VehicleRecord
from server.timeparse import format_ns

__all__ = ["estimate_to_dict", "router"]

router = APIRouter(prefix="/vehicles", tags=["vehicles"])

VEHICLE_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$"
"""Ids a client may register: one Zenoh key chunk, as
:func:`server.protocol.keys.is_valid_vehicle_id` accepts (a test keeps the two in step)."""


def estimate_to_dict(row: np.ndarray) -> dict[str, Any]:
    """One estimate row (0-d structured array) as a JSON-ready dict: NaN → None."""
    names = row.dtype.names or ()
    values = row.item()
    out: dict[str, Any] = {}
    for name, value in zip(names, values, strict=True):
        if isinstance(value, float):
            out[name] = value if math.isfinite(value) else None
        else:
            out[name] = int(value)
    return out


def _public(record: VehicleRecord, anchors: Mapping[str, Anchor]) -> VehiclePublic:
    anchor = anchors.get(record.vehicle_id)
    return VehiclePublic(
        vehicle_id=record.vehicle_id,
        config=_stored_config(record.config),
        created_ns=record.created_ns,
        updated_ns=record.updated_ns,
        anchor=None if anchor is None else AnchorPublic.of(anchor),
        estimators=list(vehicle_estimators(record)),
    )


def _type_errors(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors()[:5]:
        loc = ".".join(str(p) for p in err["loc"])
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)


def _stored_config(data: dict[str, Any]) -> dict[str, Any]:
    """A stored config as answers show it: every field of its kind; one that no longer
    validates (ranges narrowed since it was stored) as stored, in its kind's shape."""
    try:
        return vehicle_config_from_dict(data).to_dict()
    except ConfigError:
        return upgrade_legacy_config({"kind": VehicleKind.WHEELED_REAR_DRIVE.value, **data})


def _parse_config(data: Any) -> VehicleConfig:
    """Validate a config body: the config's own checks, then the JSON types of every field.

    :func:`vehicle_config_from_dict` names the kind, field, range and unit at fault; the strict
    pass of the same schema OpenAPI shows catches what it lets through (``1.0`` for an integer).
    """
    try:
        config = vehicle_config_from_dict(data)
    except (ConfigError, TypeError, ValueError) as exc:
        raise InvalidConfig(str(exc)) from exc
    try:
        body = upgrade_legacy_config({"kind": config.kind.value, **data})
        VehicleConfigAdapter.validate_json(json.dumps(body), strict=True)
    except (ValidationError, ValueError) as exc:
        reason = _type_errors(exc) if isinstance(exc, ValidationError) else str(exc)
        raise InvalidConfig(f"wrong type: {reason}") from exc
    return config


@router.get("", response_model=VehiclesPublic, summary="List registered vehicles")
def list_vehicles(store: StoreDep) -> VehiclesPublic:
    anchors = store.get_anchors()
    vehicles = [_public(r, anchors) for r in store.list_vehicles()]
    return VehiclesPublic(data=vehicles, count=len(vehicles))


@router.get(
    "/{vehicle_id}",
    response_model=VehiclePublic,
    responses=error_responses(404),
    summary="One vehicle and its config",
)
def get_vehicle(vehicle: VehicleDep, store: StoreDep) -> VehiclePublic:
    return _public(vehicle, store.get_anchors(vehicle.vehicle_id))


@router.put(
    "/{vehicle_id}",
    response_model=VehiclePublic,
    responses={
        201: {"model": VehiclePublic, "description": "vehicle registered"},
        **error_responses(400, 401, 403, 413, 422),
    },
    dependencies=[Depends(require_role("operator"))],
    summary="Register a vehicle or replace its config (operator)",
    description=(
        "The body is a vehicle config of one `kind` (`wheeled_rear_drive` when omitted, "
        "`tracked`, `wheeled_4wd_steered`), each with its own sections; omitted parts take "
        "their defaults, so `{}` registers a rear-drive vehicle with the default config. Every "
        "number has a plausible range with its unit (in the schema). A config that does not "
        "validate is refused with 422 and the reason (kind, field, range and unit). The running "
        "estimator picks the new config up. Answers 201 when the vehicle is new, 200 when its "
        "config was replaced."
    ),
)
def put_vehicle(
    vehicle_id: Annotated[str, Path(pattern=VEHICLE_ID_PATTERN)],
    body: Annotated[VehicleConfigIn, Body()],
    store: StoreDep,
    writer: WriterDep,
    events: EventsDep,
    response: Response,
) -> VehiclePublic:
    config = _parse_config(body)
    try:
        events.check_vehicle_config(vehicle_id, config)
    except ConfigError as exc:
        raise InvalidConfig(str(exc)) from exc
    existed = store.get_vehicle(vehicle_id) is not None
    stored = config.to_dict()
    record = writer.call(lambda s: s.upsert_vehicle(vehicle_id, stored, time.time_ns()))
    events.on_vehicle_config(vehicle_id, config)
    response.status_code = status.HTTP_200_OK if existed else status.HTTP_201_CREATED
    return _public(record, store.get_anchors(vehicle_id))


@router.delete(
    "/{vehicle_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    dependencies=[Depends(require_role("admin"))],
    responses=error_responses(401, 403, 404),
    summary="Delete a vehicle with all its estimates and counters (admin)",
)
def delete_vehicle(vehicle_id: str, writer: WriterDep, events: EventsDep) -> Response:
    if not writer.call(lambda s: s.delete_vehicle(vehicle_id)):
        raise NotFound(f"unknown vehicle {vehicle_id!r}")
    events.on_vehicle_deleted(vehicle_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.put(
    "/{vehicle_id}/commands/{estimator}/{command}",
    response_model=CommandPublic,
    responses=error_responses(400, 401, 403, 404, 409, 413, 422),
    dependencies=[Depends(require_role("operator"))],
    summary="Turn an estimator's command on or off for a vehicle (operator)",
    description=(
        "The commands an estimator takes are in its spec (`GET /estimators`, `commands`), e.g. "
        "MDSF's `calibration_drive`: while on, the wheels are taken to roll without slip and "
        "their rolling radii are learnt. The running estimator takes it between two steps; "
        "404 for an estimator or command that does not exist, 409 when the vehicle does not "
        "run that estimator."
    ),
)
def put_command(
    vehicle: VehicleDep,
    estimator: str,
    command: str,
    body: Annotated[CommandIn, Body()],
    events: EventsDep,
) -> CommandPublic:
    spec = SPECS.get(estimator)
    if spec is None:
        raise NotFound(f"unknown estimator {estimator!r}; known: {', '.join(sorted(SPECS))}")
    try:
        spec.command(command)
    except KeyError:
        known = ", ".join(c.key for c in spec.commands) or "none"
        raise NotFound(
            f"estimator {estimator!r} has no command {command!r} (its: {known})"
        ) from None
    runs = vehicle_estimators(vehicle)
    if estimator not in runs:
        raise Conflict(f"vehicle {vehicle.vehicle_id!r} runs {', '.join(runs)}, not {estimator!r}")
    events.on_estimator_command(vehicle.vehicle_id, estimator, command, body.on)
    return CommandPublic(
        vehicle_id=vehicle.vehicle_id, estimator=estimator, command=command, on=body.on
    )


@router.get(
    "/{vehicle_id}/latest",
    response_model=EstimatePublic,
    responses=error_responses(404, 422),
    summary="The vehicle's newest estimate of one estimator",
    description="Every field of the estimator's row (`estimator`, default the vehicle's "
    "primary; NaN as null) plus its `flags` decoded into `flag_names` by the estimator's spec.",
)
def latest_estimate(vehicle: VehicleDep, spec: EstimatorDep, store: StoreDep) -> dict[str, Any]:
    row = store.latest(vehicle.vehicle_id, estimator=spec.name)
    if row is None:
        raise NotFound(f"vehicle {vehicle.vehicle_id!r} has no {spec.name} estimates yet")
    return _latest(vehicle.vehicle_id, spec, row)


def _latest(vehicle_id: str, spec: EstimatorSpec, row: np.ndarray) -> dict[str, Any]:
    out = estimate_to_dict(row)
    flags = int(out["flags"]) if spec.has_field("flags") else 0
    return {
        "vehicle_id": vehicle_id,
        "estimator": spec.name,
        "time": format_ns(out["stamp_ns"]),
        "flag_names": spec.flag_names(flags),
        **out,
    }
