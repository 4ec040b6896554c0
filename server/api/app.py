"""The FastAPI app factory and its lifespan.

``create_app(settings, runtime)`` builds the app; nothing is built at import. The lifespan opens
the runtime (Zenoh session, store, estimators, writer — :class:`server.runtime.Runtime` unless a
runtime is passed in) on start-up and closes it on shut-down. Routers are listed once in
:data:`API_ROUTERS`; all are mounted under ``/api/v1``; OpenAPI is at ``/openapi.json`` and
``/docs``.
"""

from __future__ import annotations

import importlib
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from typing import cast

from fastapi import APIRouter, FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.routing import APIRoute
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.api.deps import ApiLimits, ApiRuntime
from server.api.errors import error_response, install_error_handlers
from server.api.routes import alerts, health, live, metrics, reports, series, vehicles
from server.settings import Settings

__all__ = ["API_PREFIX", "API_ROUTERS", "BodySizeLimit", "create_app"]

API_PREFIX = "/api/v1"

#: Every router of the REST API, in the order they appear in the docs. Add new routers here.
API_ROUTERS: tuple[APIRouter, ...] = (
    vehicles.router,
    series.router,
    reports.router,
    alerts.router,
    live.router,
    health.router,
    metrics.router,
)


class BodySizeLimit:
    """ASGI middleware refusing request bodies over ``max_bytes`` with 413 (JSON error body).

    Checks ``Content-Length`` first, then counts streamed bytes, so chunked uploads cannot get
    around it. The body is buffered (it is small by construction) and replayed to the app.
    """

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", ()):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared < 0 or declared > self.max_bytes:
                    await self._refuse(scope, receive, send)
                    return
        messages: list[Message] = []
        size = 0
        while True:
            message = await receive()
            messages.append(message)
            if message["type"] != "http.request":
                break
            size += len(message.get("body", b""))
            if size > self.max_bytes:
                await self._refuse(scope, receive, send)
                return
            if not message.get("more_body", False):
                break

        async def replay() -> Message:
            if messages:
                return messages.pop(0)
            return await receive()

        await self.app(scope, replay, send)

    async def _refuse(self, scope: Scope, receive: Receive, send: Send) -> None:
        response = error_response(
            413, "payload_too_large", f"request body larger than {self.max_bytes} bytes"
        )
        await response(scope, receive, send)


def _operation_id(route: APIRoute) -> str:
    tag = str(route.tags[0]) if route.tags else "api"
    return f"{tag}-{route.name}"


def _default_runtime(settings: Settings) -> ApiRuntime:
    module = importlib.import_module("server.runtime")
    return cast(ApiRuntime, module.Runtime(settings))


def create_app(
    settings: Settings,
    runtime: ApiRuntime | None = None,
    *,
    limits: ApiLimits | None = None,
    routers: Sequence[APIRouter] = API_ROUTERS,
) -> FastAPI:
    """Build the REST app.

    Parameters
    ----------
    settings : Settings
        The server's settings (``settings.api`` for CORS and auth).
    runtime : ApiRuntime, optional
        Opened and closed by the app's lifespan; default ``server.runtime.Runtime(settings)``,
        created when the app starts.
    limits : ApiLimits, optional
        Request and query bounds (defaults: :class:`ApiLimits`).
    routers : sequence of APIRouter
        Routers mounted under ``/api/v1`` (default :data:`API_ROUTERS`).
    """

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        rt = runtime if runtime is not None else _default_runtime(settings)
        rt.open()
        app.state.runtime = rt
        try:
            yield
        finally:
            app.state.runtime = None
            rt.close()

    app = FastAPI(
        title="Slipfleet",
        summary="Per-wheel slip telemetry of a vehicle fleet",
        version="1",
        docs_url="/docs",
        redoc_url=None,
        openapi_url="/openapi.json",
        lifespan=lifespan,
        generate_unique_id_function=_operation_id,
    )
    app.state.settings = settings
    app.state.limits = limits or ApiLimits()
    app.state.runtime = None
    install_error_handlers(app)
    included: set[int] = set()
    for router in routers:
        if id(router) not in included:  # each router once, even if listed twice
            included.add(id(router))
            app.include_router(router, prefix=API_PREFIX)
    app.add_middleware(BodySizeLimit, max_bytes=app.state.limits.max_body_bytes)
    if settings.api.cors_origins:  # outermost, so refusals (413) carry CORS headers too
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(settings.api.cors_origins),
            allow_methods=["GET", "PUT", "DELETE"],
            allow_headers=["Authorization", "Content-Type"],
        )
    return app
