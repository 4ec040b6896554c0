"""``/health``: ready only when every part of the runtime (Zenoh, storage, …) is up.

The checks run in a thread of their own limiter (:data:`HEALTH_THREADS`), not in the pool the
other sync routes share: a pool full of slow reports never starves a load balancer's probe.
"""

from __future__ import annotations

import logging

import anyio
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from server.api.deps import ApiRuntime, RuntimeDep
from server.api.models import HealthPublic, HealthUnavailable

__all__ = ["checks", "router"]

router = APIRouter(prefix="/health", tags=["health"])
_log = logging.getLogger(__name__)

#: Health checks running at once, at most (each may wait on the store's ping).
HEALTH_THREADS = 4


def _limiter(request: Request) -> anyio.CapacityLimiter:
    """The app's own thread limiter for health checks (built on first use, in its loop)."""
    limiter = getattr(request.app.state, "health_limiter", None)
    if limiter is None:
        limiter = request.app.state.health_limiter = anyio.CapacityLimiter(HEALTH_THREADS)
    return limiter


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
async def get_health(request: Request, runtime: RuntimeDep) -> JSONResponse:
    result = await anyio.to_thread.run_sync(checks, runtime, limiter=_limiter(request))
    down = sorted(k for k, ok in result.items() if not ok)
    if down or not result:
        reason = f"down: {', '.join(down)}" if down else "no health checks reported"
        body = HealthUnavailable(error="unavailable", reason=reason, checks=result)
        return JSONResponse(body.model_dump(), status_code=503)
    return JSONResponse(HealthPublic(status="ok", checks=result).model_dump())
