"""Live WebSockets for the dashboard, fed by :class:`server.live.hub.LiveHub`.

The hub is found as ``app.state.live_hub`` or, failing that, ``app.state.runtime.live_hub``.
Every message is one JSON text frame with a ``type``; NaN values are sent as ``null``; times are
integer nanoseconds (``*_ns``, sensor stamps are the vehicle clock, ``sent_ns`` and
``arrival_ns`` the server's wall clock, UTC). They exceed 2**53, so a JavaScript client holds them
as doubles, exact to about 256 ns: enough to order, merge and display them.

``/api/v1/live/fleet?interval_ms=500`` — the whole fleet, compact and column-wise
    Server → client, every ``interval_ms`` (250..5000, default 500)::

        {"type": "fleet", "t_ns": 1717…, "sent_ns": 1717…,
         "ids": ["tractor-1", …],           # one entry per vehicle in each list below
         "status": ["live" | "stale" | "offline", …],
         "stamp_ns": [1717…, …],            # newest estimate's sensor stamp
         "age_s": [0.3, …],                 # max(sensor age, wall age) of that estimate
         "vg_mps": [2.41, …], "slip_left_pct": [3.2 | null, …], "slip_right_pct": [...],
         "gnss": ["ok" | "gated" | "degraded" | "none", …], "flags": [17, …]}

    The client sends nothing.

``/api/v1/live/vehicles/{vehicle_id}?window_s=60&max_points=1500`` — one vehicle's charts
    ``window_s`` in 5..1800 (default 60), ``max_points`` in 100..5000 (default 1500).
    First the server sends a ``snapshot``, then an ``append`` at most every 100 ms (when new rows
    arrived) and at least every second::

        {"type": "snapshot", "vehicle_id": "…", "window_s": 60, "tier": "fine", "bucket_s": 0.05,
         "columns": {"stamp_ns": [...], "vg_mps": [...], "vl_mps": [...], "vr_mps": [...],
                     "rim_left_mps": [...], "rim_right_mps": [...], "slip_left_pct": [...],
                     "slip_right_pct": [...], "east_m": [...], "north_m": [...], "flags": [...]},
         "latest": {<every ESTIMATE_DTYPE field>, "arrival_ns": …, "status": "live", "age_s": 0.2,
                    "gnss": "ok",
                    "slip_note": "" | "standstill" | "starting/stopping" | "wheel data lost"},
         "sent_ns": 1717…}

        {"type": "append", "from_ns": 1717…, "columns": {…same keys…}, "latest": {…},
         "sent_ns": …}

    On ``append`` the client drops its points with ``stamp_ns >= from_ns`` and then appends
    ``columns`` (the newest, still-filling bucket of a decimated window is re-sent that way), then
    trims points older than ``newest - window_s``. Columns hold the hub's decimated rows: one per
    ``bucket_s`` with the bucket's newest values and its peak slip; a snapshot longer than
    ``max_points`` is decimated further. Latency sensor → page is ``receive time - latest.stamp_ns``
    when vehicle and server clocks agree.

    While the vehicle has no estimate yet the server sends ``{"type": "waiting", "vehicle_id": …}``
    every second. The client may send ``{"window_s": 300}`` at any time; the server answers with a
    new ``snapshot`` for that window.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time
from typing import Annotated, Any

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect
from starlette.datastructures import State

from estimator.types import ESTIMATE_DTYPE
from server.live.hub import LiveHub, gnss_quality, slip_note

__all__ = ["FLEET_MIN_INTERVAL_S", "VEHICLE_MIN_INTERVAL_S", "find_live_hub", "router"]

router = APIRouter(prefix="/live", tags=["live"])

FLEET_MIN_INTERVAL_S = 0.25
#: A vehicle page gets new rows at most this often (10 Hz): the estimator emits rows in
#: ``ingest.advance_step_ms`` chunks, so a slower cadence would add up to this much latency.
VEHICLE_MIN_INTERVAL_S = 0.1
_HEARTBEAT_S = 1.0
_WINDOW_MIN_S, _WINDOW_MAX_S = 5.0, 1800.0


def find_live_hub(state: State) -> LiveHub | None:
    """The app's hub: ``state.live_hub`` or ``state.runtime.live_hub`` (None when neither)."""
    hub = getattr(state, "live_hub", None)
    if hub is None:
        hub = getattr(getattr(state, "runtime", None), "live_hub", None)
    return hub if isinstance(hub, LiveHub) else None


def _dumps(msg: dict[str, Any]) -> str:
    return json.dumps(msg, separators=(",", ":"), allow_nan=False)


def _latest_dict(hub: LiveHub, vehicle_id: str) -> dict[str, Any] | None:
    got = hub.latest(vehicle_id)
    if got is None:
        return None
    row, arrival_ns = got
    out: dict[str, Any] = {}
    for name in ESTIMATE_DTYPE.names or ():
        v = row[name].item()
        if isinstance(v, float):
            out[name] = None if math.isnan(v) else round(v, 4)
        else:
            out[name] = int(v)
    out["arrival_ns"] = arrival_ns
    out["status"] = hub.status(vehicle_id)
    out["age_s"] = round(max(0.0, (time.time_ns() - arrival_ns) / 1e9), 2)
    out["gnss"] = gnss_quality(out["flags"])
    out["slip_note"] = slip_note(out["flags"])
    return out


def _columns(window: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in window.items() if k not in ("tier", "bucket_s")}


async def _close_unavailable(websocket: WebSocket) -> None:
    await websocket.accept()
    await websocket.close(code=1011, reason="live data is not available")


@router.websocket("/fleet")
async def live_fleet(
    websocket: WebSocket,
    interval_ms: Annotated[int, Query(ge=250, le=5000)] = 500,
) -> None:
    """Every vehicle's status, speed, slip, GNSS quality and age (see the module docstring)."""
    hub = find_live_hub(websocket.app.state)
    if hub is None:
        await _close_unavailable(websocket)
        return
    await websocket.accept()
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
    window_s: Annotated[float, Query(ge=_WINDOW_MIN_S, le=_WINDOW_MAX_S)] = 60.0,
    max_points: Annotated[int, Query(ge=100, le=5000)] = 1500,
) -> None:
    """One vehicle's sliding-window series, incrementally (see the module docstring)."""
    hub = find_live_hub(websocket.app.state)
    if hub is None:
        await _close_unavailable(websocket)
        return
    await websocket.accept()
    requests: asyncio.Queue[float] = asyncio.Queue(maxsize=8)

    async def receive() -> None:
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

    receiver = asyncio.create_task(receive())
    window = window_s
    last_stamp: int | None = None  # newest stamp the client holds; None: send a snapshot
    version = -1
    try:
        while not receiver.done():
            while not requests.empty():
                window = requests.get_nowait()
                last_stamp = None
            version = hub.version
            if last_stamp is None:
                snap = hub.window(vehicle_id, window, max_points=max_points)
                if snap is None:
                    msg: dict[str, Any] = {"type": "waiting", "vehicle_id": vehicle_id}
                else:
                    msg = {
                        "type": "snapshot",
                        "vehicle_id": vehicle_id,
                        "window_s": window,
                        "tier": snap["tier"],
                        "bucket_s": snap["bucket_s"],
                        "columns": _columns(snap),
                        "latest": _latest_dict(hub, vehicle_id),
                    }
                    stamps = snap["stamp_ns"]
                    last_stamp = stamps[-1] if stamps else 0
            else:
                inc = hub.window(vehicle_id, window, since_ns=last_stamp)
                cols = _columns(inc) if inc is not None else {"stamp_ns": []}
                msg = {
                    "type": "append",
                    "from_ns": last_stamp,
                    "columns": cols,
                    "latest": _latest_dict(hub, vehicle_id),
                }
                if cols["stamp_ns"]:
                    last_stamp = cols["stamp_ns"][-1]
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
