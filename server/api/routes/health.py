"""``/health``: ready only when every part of the runtime (Zenoh, storage, …) is up."""

from __future__ import annotations

import logging

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from server.api.deps import ApiRuntime, RuntimeDep
from server.api.models import HealthPublic, HealthUnavailable

__all__ = ["checks", "router"]

router = APIRouter(prefix="/health", tags=["health"])
_log = logging.getLogger(__name__)


def checks(runtime: ApiRuntime) -> dict[str, bool]:
    """The runtime's health checks; a check that raises counts as down (``{"runtime": False}``)."""
    try:
        return {str(k): bool(v) for k, v in runtime.health().items()}
    except Exception:
        _log.exception("health check failed")
        return {"runtime": False}


@router.get(
    "",
    response_model=HealthPublic,
    responses={503: {"model": HealthUnavailable, "description": "a part is down"}},
    summary="Readiness: 200 when every part is up, 503 naming the parts that are down",
)
def get_health(runtime: RuntimeDep) -> JSONResponse:
    result = checks(runtime)
    down = sorted(k for k, ok in result.items() if not ok)
    if down or not result:
        reason = f"down: {', '.join(down)}" if down else "no health checks reported"
        body = HealthUnavailable(error="unavailable", reason=reason, checks=result)
        return JSONResponse(body.model_dump(), status_code=503)
    return JSONResponse(HealthPublic(status="ok", checks=result).model_dump())
