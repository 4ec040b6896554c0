"""``/metrics``: Prometheus text exposition of the runtime's metrics and health."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from server.api.deps import RuntimeDep
from server.api.limits import HeavyLimitState
from server.api.routes.health import checks
from server.metrics.prometheus import CONTENT_TYPE, MetricFamily, Sample, render

__all__ = ["router"]

router = APIRouter(prefix="/metrics", tags=["metrics"])


@router.get(
    "",
    response_class=Response,
    responses={
        200: {
            "content": {"text/plain": {"schema": {"type": "string"}}},
            "description": "Prometheus text format 0.0.4",
        }
    },
    summary="Prometheus metrics",
    description=(
        "`slipfleet_up{component}` (1 up, 0 down) from the health checks, then every metric the "
        "runtime provides (per-vehicle ingest counters by reason, estimates produced, writer "
        "backlog and commits, …)."
    ),
)
def get_metrics(
    request: Request,
    runtime: RuntimeDep,
    by_vehicle: Annotated[
        bool,
        Query(
            description="false: per-vehicle counters summed to fleet totals (no `vehicle` label; "
            "far fewer samples for a large fleet)"
        ),
    ] = True,
) -> Response:
    up = MetricFamily(
        name="slipfleet_up",
        type="gauge",
        help="1 when the component is up, 0 when down.",
        samples=tuple(
            Sample(1.0 if ok else 0.0, {"component": name})
            for name, ok in sorted(checks(runtime).items())
        ),
    )
    provided = runtime.metrics(by_vehicle)
    limits = _limit_families(getattr(request.app.state, "heavy_limits", None))
    return Response(render([up, *provided, *limits]), media_type=CONTENT_TYPE)


def _limit_families(state: HeavyLimitState | None) -> list[MetricFamily]:
    """Requests of the expensive routes running now and refused with 429, by route."""
    if state is None:
        return []
    running = MetricFamily(
        "slipfleet_api_heavy_requests_running",
        "gauge",
        "Reports, slip maps and series exports running now, by route.",
        tuple(Sample(float(n), {"route": r}) for r, n in sorted(state.in_flight.items())),
    )
    refused = MetricFamily(
        "slipfleet_api_requests_refused",
        "counter",
        "Requests answered 429, by route and the limit they passed (token or route).",
        tuple(
            Sample(float(n), {"route": r, "limit": lim}, "_total")
            for (r, lim), n in sorted(state.refused.items())
        ),
    )
    return [running, refused]
