"""``GET /alerts``: open and recent alerts from :class:`server.analytics.alerts.AlertEngine`.

The engine is ``app.state.alert_engine`` (the app factory's lifespan puts the runtime's there).
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query, Request
from pydantic import BaseModel, Field
from starlette.datastructures import State

from server.analytics.alerts import AlertEngine
from server.api.errors import ServiceUnavailable, error_responses

__all__ = ["AlertListPublic", "AlertPublic", "find_alert_engine", "router"]

router = APIRouter(prefix="/alerts", tags=["alerts"])


class AlertPublic(BaseModel):
    """One alert. Stamps are int ns since the epoch, UTC: sensor time for vehicle alerts, wall
    time for server-wide ones (``storage_down``, ``zenoh_down``, whose ``vehicle_id`` is "")."""

    id: int
    vehicle_id: str = Field(description='the vehicle, or "" for an alert about the server')
    kind: str = Field(
        description="`slip:<estimator>:<slip channel key>`, `flag:<estimator>:<FLAG>`, "
        "`rule:<estimator>:<rule key>`, `stale`, `storage_down` or `zenoh_down`"
    )
    estimator: str | None = Field(description="estimator whose rows raised it (slip and flag)")
    channel: str | None = Field(
        description="its slip channel key, flag name or rule key (slip, flag and rule)"
    )
    start_ns: int = Field(description="where the condition began (stale: the last estimate)")
    end_ns: int | None = Field(description="where it ended; null while open")
    open: bool
    opened_wall_ns: int = Field(description="server wall time the alert opened")
    threshold: float | None = Field(
        description="slip threshold, percent (slip alerts); the rule's limit (rule alerts)"
    )
    peak: float | None = Field(
        description="largest |slip| seen, percent (slip alerts); the rule's field at its most "
        "extreme (rule alerts)"
    )


class AlertListPublic(BaseModel):
    """Alerts, newest first."""

    alerts: list[AlertPublic]
    open_count: int = Field(description="open alerts of the whole fleet")


def find_alert_engine(state: State) -> AlertEngine | None:
    """The app's engine, ``state.alert_engine``; None when the app has none."""
    engine = getattr(state, "alert_engine", None)
    return engine if isinstance(engine, AlertEngine) else None


def _engine(request: Request) -> AlertEngine:
    engine = find_alert_engine(request.app.state)
    if engine is None:
        raise ServiceUnavailable("alerts are not available")
    return engine


@router.get(
    "",
    response_model=AlertListPublic,
    responses=error_responses(503),
    summary="Open and recent alerts",
    description=(
        "Rules name a channel of an estimator's spec (`GET /api/v1/estimators`): "
        "`slip:<estimator>:<channel>` (|slip| of one of its slip channels above the vehicle's "
        "`alert_threshold_pct` for longer than its `alert_hold_s`), `flag:<estimator>:<FLAG>` "
        "(one of its `degraded_flags` held, e.g. `flag:mdsf:DEGRADED`: GNSS lost), "
        "`rule:<estimator>:<key>` (one of its spec's own rules held, e.g. "
        "`rule:tracked:long_dead_reckoning`, `rule:friction:low_mu`), `stale` (no "
        "estimate for a while); `storage_down` and `zenoh_down` are about the server. Newest "
        "first."
    ),
)
def list_alerts(
    engine: Annotated[AlertEngine, Depends(_engine)],
    state: Annotated[Literal["open", "closed", "all"], Query()] = "all",
    vehicle_id: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=5000)] = 500,
) -> AlertListPublic:
    found = engine.alerts(state=state, vehicle_id=vehicle_id, limit=limit)
    return AlertListPublic(
        alerts=[AlertPublic(**a.to_dict()) for a in found],
        open_count=engine.open_count(),
    )
