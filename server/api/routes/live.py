"""Live WebSockets for the dashboard, fed by :class:`server.live.hub.LiveHub`.

The hub is ``app.state.live_hub`` (the app factory's lifespan puts the runtime's there).
Every message is one JSON text frame with a ``type``; NaN values are sent as ``null``; times are
integer nanoseconds (``*_ns``, sensor stamps are the vehicle clock, ``sent_ns`` and
``arrival_ns`` the server's wall clock, UTC). They exceed 2**53, so a JavaScript client holds them
as doubles, exact to about 256 ns: enough to order, merge and display them.

``/api/v1/live/fleet?interval_ms=500`` — the whole fleet, compact and column-wise
    Server → client, every ``interval_ms`` (250..5000, default 500); each vehicle by its primary
    estimator (``GET /api/v1/estimators`` describes every estimator's channels)::

        {"type": "fleet", "t_ns": 1717…, "sent_ns": 1717…,
         "ids": ["tractor-1", …],           # one entry per vehicle in each list below
         "estimator": ["mdsf", …],          # the vehicle's primary estimator
         "status": ["live" | "stale" | "offline", …],
         "stamp_ns": [1717…, …],            # newest estimate's sensor stamp
         "age_s": [0.3, …],                 # max(sensor age, wall age) of that estimate
         "speed_mps": [2.41, …],            # the primary's motion speed channel
         "slip_pct": {"<slip channel key>": [3.2 | null, …], …},
         "quality": ["ok" | "degraded" | "none", …],   # ok_flag / degraded_flags of the spec
         "flags": [17, …]}

    The client sends nothing.

``/api/v1/live/vehicles/{vehicle_id}?estimator=mdsf&window_s=60&max_points=1500`` — one
vehicle's rows of one estimator (default: its primary)
    ``window_s`` in 5..1800 (default 60), ``max_points`` in 100..5000 (default 1500).
    First the server sends a ``snapshot``, then an ``append`` at most every 100 ms (when new rows
    arrived) and at least every second::

        {"type": "snapshot", "vehicle_id": "…", "estimator": "mdsf",
         "estimators": ["mdsf", "reference_speed"],   # every estimator with rows, primary first
         "window_s": 60, "tier": "fine", "bucket_s": 0.05,
         "columns": {"stamp_ns": [...], <each live field of the spec>: [...]},
         "latest": {<every field of the spec>, "arrival_ns": …, "status": "live", "age_s": 0.2,
                    "quality": "ok", "flag_names": [<names of the flags set>]},
         "sent_ns": 1717…}

        {"type": "append", "estimator": "mdsf", "estimators": […], "from_ns": 1717…,
         "columns": {…same keys…}, "latest": {…}, "sent_ns": …}

    The live fields (``server.live.hub.live_fields``) are the spec's chart, slip, motion and
    position fields and ``flags``. On ``append`` the client drops its points with
    ``stamp_ns >= from_ns`` and then appends ``columns`` (the newest, still-filling bucket of a
    decimated window is re-sent that way), then trims points older than ``newest - window_s``.
    Columns hold the hub's decimated rows: one per ``bucket_s`` with the bucket's newest values
    and its peak slips; a snapshot longer than ``max_points`` is decimated further. Latency
    sensor → page is ``receive time - latest.stamp_ns`` when vehicle and server clocks agree.

    While the vehicle has no rows of the estimator yet the server sends ``{"type": "waiting",
    "vehicle_id": …, "estimator": … | null, "estimators": […]}`` every second. The client may
    send ``{"window_s": 300}`` at any time; the server answers with a new ``snapshot`` for that
    window.

Revocation and expiry: a socket opened with a token is closed (code 1008, "token revoked or
expired") within :data:`REVOCATION_POLL_S` of the token being revoked or deleted (over REST or
with ``slipfleet token revoke`` in another process) or of its expiry passing: each socket looks
its token up again that often, in a worker thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time
from collections.abc import Coroutine
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Depends, Query, WebSocket, WebSocketDisconnect, status
from starlette.datastructures import State

from server.api.deps import Principal, principal_of
from server.live.hub import LiveHub, quality
from server.storage.base import StorageError

__all__ = [
    "FLEET_MIN_INTERVAL_S",
    "REVOCATION_POLL_S",
    "VEHICLE_MIN_INTERVAL_S",
    "find_live_hub",
    "router",
    "while_authorised",
]

router = APIRouter(prefix="/live", tags=["live"])

FLEET_MIN_INTERVAL_S = 0.25
#: A vehicle page gets new rows at most this often (10 Hz): the estimator emits rows in
#: ``ingest.advance_step_ms`` chunks, so a slower cadence would add up to this much latency.
VEHICLE_MIN_INTERVAL_S = 0.1
_HEARTBEAT_S = 1.0
#: An open socket looks its token up again this often (revocation closes it within this).
REVOCATION_POLL_S = 0.5
_WINDOW_MIN_S, _WINDOW_MAX_S = 5.0, 1800.0


def find_live_hub(state: State) -> LiveHub | None:
    """The app's hub, ``state.live_hub``; None when the app has none."""
    hub = getattr(state, "live_hub", None)
    return hub if isinstance(hub, LiveHub) else None


def _dumps(msg: dict[str, Any]) -> str:
    return json.dumps(msg, separators=(",", ":"), allow_nan=False)


def _latest_dict(hub: LiveHub, vehicle_id: str, estimator: str) -> dict[str, Any] | None:
    """The newest row of (vehicle, estimator), every field of its spec, with its status."""
    got = hub.latest(vehicle_id, estimator)
    spec = hub.spec(estimator)
    if got is None or spec is None:
        return None
    row, arrival_ns = got
    out: dict[str, Any] = {}
    for name in spec.field_names:
        v = row[name].item()
        if isinstance(v, float):
            out[name] = None if math.isnan(v) else round(v, 4)
        else:
            out[name] = int(v)
    flags = int(out.get("flags", 0))
    out["arrival_ns"] = arrival_ns
    out["status"] = hub.status(vehicle_id, estimator)
    out["age_s"] = round(max(0.0, (time.time_ns() - arrival_ns) / 1e9), 2)
    out["quality"] = quality(spec, flags)
    out["flag_names"] = spec.flag_names(flags)
    return out


def _columns(window: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in window.items() if k not in ("estimator", "tier", "bucket_s")}


async def _close_unavailable(websocket: WebSocket) -> None:
    await websocket.accept()
    await websocket.close(code=1011, reason="live data is not available")


def _caller(websocket: WebSocket) -> Principal | None:
    """Who opened the socket; None in an app built without settings (these routes mounted on
    their own, as the live benchmark does: no tokens there)."""
    if getattr(websocket.app.state, "settings", None) is None:
        return None
    return principal_of(websocket)


CallerDep = Annotated[Principal | None, Depends(_caller)]


async def _token_revoked(websocket: WebSocket, token_sha256: str) -> None:
    """Return once the token is revoked, expired or gone (looked up every
    :data:`REVOCATION_POLL_S`; a store that does not answer keeps the socket open until the
    expiry last read)."""
    store = websocket.app.state.runtime.store
    expires_ns: int | None = None
    while True:
        await asyncio.sleep(REVOCATION_POLL_S)
        try:
            record = await anyio.to_thread.run_sync(store.get_token, token_sha256)
        except StorageError:
            if expires_ns is not None and time.time_ns() >= expires_ns:
                return
            continue
        if record is None or not record.valid_at(time.time_ns()):
            return
        expires_ns = record.expires_ns


async def while_authorised(
    websocket: WebSocket, principal: Principal | None, body: Coroutine[Any, Any, None]
) -> None:
    """Run the coroutine ``body`` (the socket's sender) until it ends or the caller's token is
    revoked; then close the socket with 1008."""
    task = asyncio.ensure_future(body)
    if principal is None or principal.token_sha256 is None:  # tokens off
        await task
        return
    watch = asyncio.create_task(_token_revoked(websocket, principal.token_sha256))
    await asyncio.wait({task, watch}, return_when=asyncio.FIRST_COMPLETED)
    for running in (task, watch):
        running.cancel()
        with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
            await running
    if watch.done() and not watch.cancelled():
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):
            await websocket.close(
                code=status.WS_1008_POLICY_VIOLATION, reason="token revoked or expired"
            )


@router.websocket("/fleet")
async def live_fleet(
    websocket: WebSocket,
    principal: CallerDep,
    interval_ms: Annotated[int, Query(ge=250, le=5000)] = 500,
) -> None:
    """Every vehicle's status, speed, slip, GNSS quality and age (see the module docstring)."""
    hub = find_live_hub(websocket.app.state)
    if hub is None:
        await _close_unavailable(websocket)
        return
    await websocket.accept()
    await while_authorised(websocket, principal, _send_fleet(websocket, hub, interval_ms))


async def _send_fleet(websocket: WebSocket, hub: LiveHub, interval_ms: int) -> None:
    interval = interval_ms / 1000.0
    loop = asyncio.get_running_loop()
    receiver = asyncio.create_task(_drain(websocket))
    try:
        while not receiver.done():
            t_sent = loop.time()
            msg = {"type": "fleet", **hub.overview(), "sent_ns": time.time_ns()}
            await websocket.send_text(_dumps(msg))
            await asyncio.sleep(max(FLEET_MIN_INTERVAL_S, interval - (loop.time() - t_sent)))
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        receiver.cancel()
        with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
            await receiver


async def _drain(websocket: WebSocket) -> None:
    """Read and ignore client frames until the client goes (ends the sender loop)."""
    with contextlib.suppress(WebSocketDisconnect, RuntimeError):
        while True:
            await websocket.receive_text()


def _clamp_window(value: Any, default: float) -> float:
    try:
        w = float(value)
    except (TypeError, ValueError):
        return default
    if not math.isfinite(w):
        return default
    return min(max(w, _WINDOW_MIN_S), _WINDOW_MAX_S)


@router.websocket("/vehicles/{vehicle_id}")
async def live_vehicle(
    websocket: WebSocket,
    vehicle_id: str,
    principal: CallerDep,
    estimator: Annotated[str | None, Query(max_length=64)] = None,
    window_s: Annotated[float, Query(ge=_WINDOW_MIN_S, le=_WINDOW_MAX_S)] = 60.0,
    max_points: Annotated[int, Query(ge=100, le=5000)] = 1500,
) -> None:
    """One vehicle's sliding-window series of one estimator (default: its primary),
    incrementally (see the module docstring)."""
    hub = find_live_hub(websocket.app.state)
    if hub is None:
        await _close_unavailable(websocket)
        return
    await websocket.accept()
    sender = _send_vehicle(websocket, hub, vehicle_id, estimator, window_s, max_points)
    await while_authorised(websocket, principal, sender)


async def _send_vehicle(
    websocket: WebSocket,
    hub: LiveHub,
    vehicle_id: str,
    estimator: str | None,
    window_s: float,
    max_points: int,
) -> None:
    requests: asyncio.Queue[float] = asyncio.Queue(maxsize=8)
    receiver = asyncio.create_task(_receive_windows(websocket, requests, window_s))
    window = window_s
    name = estimator  # None until the vehicle's primary is known
    last_stamp: int | None = None  # newest stamp the client holds; None: send a snapshot
    version = -1
    try:
        while not receiver.done():
            while not requests.empty():
                window = requests.get_nowait()
                last_stamp = None
            version = hub.version
            name = name or hub.primary(vehicle_id)
            msg, last_stamp = _vehicle_message(
                hub, vehicle_id, name, window, last_stamp, max_points
            )
            msg["estimator"] = name
            msg["estimators"] = hub.estimators(vehicle_id)
            msg["sent_ns"] = time.time_ns()
            await websocket.send_text(_dumps(msg))
            await asyncio.sleep(VEHICLE_MIN_INTERVAL_S)
            if requests.empty():
                await hub.wait_newer(version, _HEARTBEAT_S - VEHICLE_MIN_INTERVAL_S)
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        receiver.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await receiver


async def _receive_windows(
    websocket: WebSocket, requests: asyncio.Queue[float], window_s: float
) -> None:
    """Queue each window the client asks for (``{"window_s": …}``, clamped) until it leaves."""
    with contextlib.suppress(WebSocketDisconnect, RuntimeError):
        while True:
            text = await websocket.receive_text()
            try:
                data = json.loads(text)
            except ValueError:
                continue
            if isinstance(data, dict) and "window_s" in data:
                with contextlib.suppress(asyncio.QueueFull):
                    requests.put_nowait(_clamp_window(data["window_s"], window_s))


def _vehicle_message(
    hub: LiveHub,
    vehicle_id: str,
    name: str | None,
    window: float,
    last_stamp: int | None,
    max_points: int,
) -> tuple[dict[str, Any], int | None]:
    """The next message of a vehicle's feed (waiting, snapshot or append) and the newest stamp
    the client holds after it (None: a snapshot is still to send)."""
    snap = None
    if last_stamp is None and name is not None:
        snap = hub.window(vehicle_id, window, estimator=name, max_points=max_points)
    if name is None or (last_stamp is None and snap is None):
        return {"type": "waiting", "vehicle_id": vehicle_id}, last_stamp
    if snap is not None:
        msg: dict[str, Any] = {
            "type": "snapshot",
            "vehicle_id": vehicle_id,
            "window_s": window,
            "tier": snap["tier"],
            "bucket_s": snap["bucket_s"],
            "columns": _columns(snap),
            "latest": _latest_dict(hub, vehicle_id, name),
        }
        stamps = snap["stamp_ns"]
        return msg, stamps[-1] if stamps else 0
    inc = hub.window(vehicle_id, window, estimator=name, since_ns=last_stamp)
    cols = _columns(inc) if inc is not None else {"stamp_ns": []}
    msg = {
        "type": "append",
        "from_ns": last_stamp,
        "columns": cols,
        "latest": _latest_dict(hub, vehicle_id, name),
    }
    return msg, cols["stamp_ns"][-1] if cols["stamp_ns"] else last_stamp
