"""The 3D view through the API's origin, behind the same tokens as REST.

viser (:mod:`server.live.viewer`) has no authentication of its own, so it binds loopback only
and this router is the way to it from elsewhere:

``GET /api/v1/viewer/?token=<token>``
    Checks the token (any role may watch) and sets it as an HttpOnly, ``SameSite=Strict``
    cookie scoped to ``/api/v1/viewer``, then redirects to ``/api/v1/viewer/`` so the token
    leaves the address bar and the history.
``GET /api/v1/viewer/{path}`` (the cookie, or ``Authorization: Bearer``)
    viser's page (and any file it serves), fetched from its loopback port.
``WS /api/v1/viewer``
    The page's WebSocket: viser's client derives its URL from the page's, without the query,
    so a browser authenticates with the cookie; other clients as on the live sockets (header,
    bearer subprotocol, ``token`` query). A cookie-authenticated socket must come from the
    API's own origin (its ``Origin`` names the ``Host``): no other site's page can use the
    cookie. Frames are relayed both ways to viser; the socket is closed with 1008 within
    :data:`server.api.routes.live.REVOCATION_POLL_S` of the token being revoked or expiring.

Without a valid token: 401 over HTTP, 1008 on the WebSocket (the handshake fails with 403).
With ``viewer.enabled = false``: 404. With ``api.require_auth = false`` everyone is let in.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
from typing import Annotated, Any
from urllib.parse import urlsplit

import httpx
import websockets
from fastapi import APIRouter, Depends, Query, Request, WebSocket, WebSocketException, status
from fastapi.responses import RedirectResponse, Response
from starlette.datastructures import State
from starlette.requests import HTTPConnection
from starlette.websockets import WebSocketDisconnect
from websockets.asyncio.client import ClientConnection, connect

from server.api.deps import (
    ANONYMOUS_ADMIN,
    WS_TOKEN_QUERY,
    ApiRuntime,
    Principal,
    principal_of,
    principal_of_token,
)
from server.api.errors import ApiError, NotFound, ServiceUnavailable
from server.api.routes.live import while_authorised

__all__ = ["VIEWER_COOKIE", "VIEWER_PATH", "router"]

router = APIRouter(prefix="/viewer", tags=["viewer"])

#: The cookie holding the token of a browser watching the 3D view.
VIEWER_COOKIE = "slipfleet_viewer"
#: Where the 3D view is served (the cookie's path).
VIEWER_PATH = "/api/v1/viewer"
#: Time to fetch a file from viser on loopback.
_UPSTREAM_TIMEOUT_S = 10.0
#: Request headers passed on to viser (no ``accept-encoding``: the body is relayed decoded).
_PASSED_HEADERS = ("accept", "if-none-match")
#: Response headers passed back from viser.
_RETURNED_HEADERS = ("content-type", "etag", "cache-control")


def _same_origin(conn: HTTPConnection) -> bool:
    """True when the request's ``Origin`` names the host it was sent to (a browser always sends
    ``Origin`` on a WebSocket handshake)."""
    origin = conn.headers.get("origin")
    host = conn.headers.get("host")
    return origin is not None and host is not None and urlsplit(origin).netloc == host


def _viewer_principal(conn: HTTPConnection) -> Principal:
    """The caller: a ``token`` query parameter, else the cookie, else what every route accepts
    (:func:`server.api.deps.principal_of`); 401 or 1008 without a valid one."""
    if not conn.app.state.settings.api.require_auth:
        return ANONYMOUS_ADMIN
    if conn.headers.get("authorization") is not None:
        return principal_of(conn)
    query_token = conn.query_params.get(WS_TOKEN_QUERY)
    if query_token is not None:
        return principal_of_token(conn, query_token)
    cookie_token = conn.cookies.get(VIEWER_COOKIE)
    if cookie_token is None:
        return principal_of(conn)  # the subprotocol of a WebSocket, else 401
    if conn.scope["type"] == "websocket" and not _same_origin(conn):
        raise WebSocketException(status.WS_1008_POLICY_VIOLATION, "cookie from another origin")
    return principal_of_token(conn, cookie_token)


ViewerPrincipal = Annotated[Principal, Depends(_viewer_principal)]


def _viser_address(state: State) -> tuple[str, int]:
    """``(host, port)`` of the running viser server (loopback when it binds every address);
    404 when the 3D view is off, 503 when it is not running."""
    if not state.settings.viewer.enabled:
        raise NotFound("the 3D view is disabled (viewer.enabled = false)")
    runtime: ApiRuntime = state.runtime
    port = runtime.viewer_port()
    if port is None:
        raise ServiceUnavailable("the 3D view is not running")
    host = str(state.settings.viewer.host).strip("[]")
    with contextlib.suppress(ValueError):
        address = ipaddress.ip_address(host)
        if address.is_unspecified:
            host = "::1" if address.version == 6 else "127.0.0.1"
    return (f"[{host}]" if ":" in host else host), port


@router.get("/{path:path}", include_in_schema=False)
async def viewer_file(
    request: Request,
    principal: ViewerPrincipal,
    path: str,
    token: Annotated[str | None, Query(description="a token, set as the cookie")] = None,
) -> Response:
    """A file of the 3D view (``path`` empty: its page), fetched from viser."""
    if token is not None:  # already checked: keep it as the cookie, take it off the URL
        moved = RedirectResponse(f"{VIEWER_PATH}/{path}", status_code=status.HTTP_303_SEE_OTHER)
        moved.set_cookie(
            VIEWER_COOKIE,
            token,
            path=VIEWER_PATH,
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
        )
        moved.headers["referrer-policy"] = "no-referrer"
        return moved
    host, port = _viser_address(request.app.state)
    headers = {k: v for k, v in request.headers.items() if k in _PASSED_HEADERS}
    async with httpx.AsyncClient(timeout=_UPSTREAM_TIMEOUT_S) as client:
        try:
            got = await client.get(f"http://{host}:{port}/{path}", headers=headers)
        except httpx.HTTPError as exc:
            raise ServiceUnavailable(f"the 3D view does not answer: {exc}") from exc
    returned = {k: v for k, v in got.headers.items() if k in _RETURNED_HEADERS}
    returned["referrer-policy"] = "no-referrer"
    return Response(got.content, status_code=got.status_code, headers=returned)


async def _to_viser(websocket: WebSocket, upstream: ClientConnection) -> None:
    """Pass the browser's frames on to viser until the browser leaves."""
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        data = message.get("bytes")
        await upstream.send(data if data is not None else message.get("text") or "")


async def _to_browser(websocket: WebSocket, upstream: ClientConnection) -> None:
    """Pass viser's frames on to the browser until viser closes."""
    async for data in upstream:
        if isinstance(data, bytes):
            await websocket.send_bytes(data)
        else:
            await websocket.send_text(data)


async def _relay(websocket: WebSocket, upstream: ClientConnection) -> None:
    """Both directions at once; returns when either side is gone."""
    tasks = [
        asyncio.create_task(_to_viser(websocket, upstream)),
        asyncio.create_task(_to_browser(websocket, upstream)),
    ]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(
                asyncio.CancelledError, WebSocketDisconnect, websockets.ConnectionClosed
            ):
                await task


@router.websocket("")
async def viewer_socket(websocket: WebSocket, principal: ViewerPrincipal) -> None:
    """The 3D view's WebSocket, relayed to viser (see the module docstring)."""
    try:
        host, port = _viser_address(websocket.app.state)
    except ApiError as exc:
        raise WebSocketException(status.WS_1011_INTERNAL_ERROR, str(exc)) from exc
    offered = [p for p in websocket.scope.get("subprotocols") or () if p.startswith("viser-v")]
    kwargs: dict[str, Any] = {"compression": None, "max_size": None, "open_timeout": 10}
    try:
        upstream = await connect(f"ws://{host}:{port}", subprotocols=offered or None, **kwargs)
    except (OSError, websockets.InvalidHandshake, TimeoutError):
        await websocket.accept()
        await websocket.close(code=status.WS_1011_INTERNAL_ERROR, reason="3D view not running")
        return
    async with upstream:
        await websocket.accept(subprotocol=upstream.subprotocol)
        await while_authorised(websocket, principal, _relay(websocket, upstream))
    with contextlib.suppress(WebSocketDisconnect, RuntimeError):
        await websocket.close()
