"""The FastAPI app factory and its lifespan.

``create_app(settings, runtime)`` builds the app; nothing is built at import. The lifespan opens
the runtime (Zenoh session, store, estimators, writer: :class:`server.runtime.Runtime`, which
:func:`server.app_main.build_app` passes in) on start-up and closes it on shut-down. Routers are
listed once in :data:`API_ROUTERS`; all are mounted under ``/api/v1``; OpenAPI is at
``/openapi.json`` and ``/docs``.

Access: every router except those in :data:`PUBLIC_ROUTERS` (``/health``, for load balancers)
is mounted behind ``require_role("viewer")``, so a new router is closed until it says otherwise
(those in :data:`SELF_AUTHENTICATED_ROUTERS` check the token themselves, the 3D view's cookie);
routes that change things ask for more themselves (vehicle config PUT: operator, DELETE and
``/tokens``: admin). ``/metrics`` is not public: it names every vehicle and its traffic
(Prometheus sends a viewer token, ``authorization: {credentials_file: …}``).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Depends, FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.api.deps import WS_BEARER_PROTOCOL, ApiLimits, ApiRuntime, require_role
from server.api.errors import ErrorBody, error_response, install_error_handlers
from server.api.limits import HEAVY_ROUTES, HeavyLimitState, HeavyRequestLimit
from server.api.routes import (
    alerts,
    calibration,
    dashboard,
    estimators,
    health,
    live,
    metrics,
    reports,
    series,
    slipmap,
    tokens,
    vehicles,
    viewer,
)
from server.settings import Settings
from server.tokens import Role

__all__ = [
    "API_PREFIX",
    "API_ROUTERS",
    "PUBLIC_ROUTERS",
    "SELF_AUTHENTICATED_ROUTERS",
    "BodySizeLimit",
    "WebSocketBearerProtocol",
    "create_app",
]

API_PREFIX = "/api/v1"

#: Every router of the REST API, in the order they appear in the docs. Add new routers here.
API_ROUTERS: tuple[APIRouter, ...] = (
    vehicles.router,
    calibration.router,
    estimators.router,
    series.router,
    reports.router,
    slipmap.router,
    alerts.router,
    live.router,
    health.router,
    metrics.router,
    tokens.router,
    dashboard.router,
    viewer.router,
)

#: Routers anyone may call without a token.
PUBLIC_ROUTERS: tuple[APIRouter, ...] = (health.router,)
#: Routers that check the caller's token themselves: the 3D view, whose browser socket can only
#: carry a cookie (:mod:`server.api.routes.viewer`).
SELF_AUTHENTICATED_ROUTERS: tuple[APIRouter, ...] = (viewer.router,)


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


class WebSocketBearerProtocol:
    """ASGI middleware: a WebSocket client that sends its token as a subprotocol
    (``[WS_BEARER_PROTOCOL, <token>]``, see :mod:`server.api.deps`) gets ``WS_BEARER_PROTOCOL``
    back as the accepted subprotocol, as browsers require when they offered any. Never the
    token; a subprotocol the handler picked itself is left alone."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "websocket" or WS_BEARER_PROTOCOL not in (
            scope.get("subprotocols") or ()
        ):
            await self.app(scope, receive, send)
            return

        async def send_with_protocol(message: Message) -> None:
            if message["type"] == "websocket.accept" and not message.get("subprotocol"):
                message = {**message, "subprotocol": WS_BEARER_PROTOCOL}
            await send(message)

        await self.app(scope, receive, send_with_protocol)


def _openapi_with_bearer(app: FastAPI) -> dict[str, Any]:
    """The OpenAPI document, with a bearer scheme (and its 401/403 answers) on every operation
    that needs a role."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(
        title=app.title,
        version=app.version,
        summary=app.summary,
        routes=app.routes,
    )
    schema.setdefault("components", {})["securitySchemes"] = {"bearer": dict(_BEARER)}
    schemas = schema["components"].setdefault("schemas", {})
    schemas.setdefault("ErrorBody", ErrorBody.model_json_schema())
    public = {f"{API_PREFIX}{r.prefix}" for r in PUBLIC_ROUTERS}
    for path, ops in schema.get("paths", {}).items():
        if path not in public:
            _guard_operations(path, ops)
    app.openapi_schema = schema
    return schema


#: The OpenAPI security scheme of the access tokens.
_BEARER: dict[str, Any] = {
    "type": "http",
    "scheme": "bearer",
    "description": "An access token (`slipfleet token create`); roles: viewer < operator < admin.",
}
#: Why a guarded operation answers 401 or 403.
_REFUSED = {
    "401": "no token, or an unknown or revoked one",
    "403": "the token's role is too low for this operation",
}


def _guard_operations(path: str, ops: dict[str, Any]) -> None:
    """Mark the operations of a guarded ``path`` as needing a bearer token, with their 401
    and 403 answers, and their 429 answer where the path is limited (:data:`HEAVY_ROUTES`)."""
    if any(p.match(path.replace("{vehicle_id}", "v")) for p in HEAVY_ROUTES.values()):
        for op in ops.values():
            op.setdefault("responses", {})["429"] = _TOO_MANY
    for op in ops.values():
        op["security"] = [{"bearer": []}]
        for code, why in _REFUSED.items():
            op.setdefault("responses", {}).setdefault(
                code,
                {
                    "description": why,
                    "content": {
                        "application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}
                    },
                },
            )


#: OpenAPI answer of a route under :mod:`server.api.limits`.
_TOO_MANY: dict[str, Any] = {
    "description": "too many such requests running (of this token, or of all): retry after "
    "the Retry-After header's seconds",
    "headers": {"Retry-After": {"schema": {"type": "integer"}}},
    "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}},
}


def _operation_id(route: APIRoute) -> str:
    tag = str(route.tags[0]) if route.tags else "api"
    return f"{tag}-{route.name}"


#: Swagger UI files vendored from npm (``web/vendor/README.md``), served with the API docs.
SWAGGER_UI_DIR = Path(__file__).resolve().parents[2] / "web" / "vendor" / "swagger-ui"
_DOCS_ASSETS = "/docs-assets"


def _mount_docs(app: FastAPI) -> None:
    """``/docs``: Swagger UI over ``/openapi.json``, its script and style served from this app
    (a field server has no internet, so the CDN default would show a blank page)."""
    app.mount(_DOCS_ASSETS, StaticFiles(directory=SWAGGER_UI_DIR), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url="/openapi.json",
            title="Slipfleet API",
            swagger_js_url=f"{_DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{_DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url="data:,",
        )


def create_app(
    settings: Settings,
    runtime: ApiRuntime,
    *,
    limits: ApiLimits | None = None,
    routers: Sequence[APIRouter] = API_ROUTERS,
) -> FastAPI:
    """Build the REST app.

    Parameters
    ----------
    settings : Settings
        The server's settings (``settings.api`` for CORS and auth).
    runtime : ApiRuntime
        Opened and closed by the app's lifespan (the server's: ``server.runtime.Runtime``).
    limits : ApiLimits, optional
        Request and query bounds (defaults: :class:`ApiLimits`).
    routers : sequence of APIRouter
        Routers mounted under ``/api/v1`` (default :data:`API_ROUTERS`).
    """

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        runtime.open()
        app.state.runtime = runtime
        app.state.live_hub = runtime.live_hub
        app.state.alert_engine = runtime.alert_engine
        try:
            yield
        finally:
            app.state.runtime = app.state.live_hub = app.state.alert_engine = None
            runtime.close()

    app = FastAPI(
        title="Slipfleet",
        summary="Per-wheel slip telemetry of a vehicle fleet",
        version="1",
        docs_url=None,  # served below with the vendored Swagger UI: no CDN at run time
        redoc_url=None,
        openapi_url="/openapi.json",
        lifespan=lifespan,
        generate_unique_id_function=_operation_id,
    )
    app.state.settings = settings
    app.state.limits = limits or ApiLimits()
    app.state.runtime = None
    install_error_handlers(app)
    _include_routers(app, routers)
    app.openapi = lambda: _openapi_with_bearer(app)  # type: ignore[method-assign]
    _mount_docs(app)
    _add_middleware(app, settings)
    return app


def _include_routers(app: FastAPI, routers: Sequence[APIRouter]) -> None:
    """Mount each router once under ``/api/v1``, behind the viewer role unless it is public or
    authenticates by itself."""
    included: set[int] = set()
    public = {id(r) for r in (*PUBLIC_ROUTERS, *SELF_AUTHENTICATED_ROUTERS)}
    for router in routers:
        if id(router) not in included:  # each router once, even if listed twice
            included.add(id(router))
            guard = [] if id(router) in public else [Depends(require_role(Role.VIEWER))]
            app.include_router(router, prefix=API_PREFIX, dependencies=guard)


def _add_middleware(app: FastAPI, settings: Settings) -> None:
    """Add the body size and heavy-request limits, the WebSocket bearer protocol and, when
    origins are set, CORS (outermost)."""
    app.add_middleware(BodySizeLimit, max_bytes=app.state.limits.max_body_bytes)
    app.state.heavy_limits = HeavyLimitState(
        settings.api.heavy_per_token, settings.api.heavy_per_route, settings.api.retry_after_s
    )
    app.add_middleware(HeavyRequestLimit, state=app.state.heavy_limits)
    app.add_middleware(WebSocketBearerProtocol)
    if settings.api.cors_origins:  # outermost, so refusals (413) carry CORS headers too
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(settings.api.cors_origins),
            allow_methods=["GET", "POST", "PUT", "DELETE"],
            allow_headers=["Authorization", "Content-Type"],
        )
