"""The expensive routes' concurrency limits (:mod:`server.api.limits`): per caller, per
route, 429 with Retry-After, cheap routes and /health never limited, slots given back."""

from __future__ import annotations

from collections.abc import Callable

import anyio
import httpx
import pytest
from starlette.types import Receive, Scope, Send

from server.api.limits import HeavyLimitState, HeavyRequestLimit


class _Gate:
    """An ASGI app answering 200 once ``open`` is set (a slow report, held at will)."""

    def __init__(self) -> None:
        self.open = anyio.Event()
        self.started = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        self.started += 1
        await self.open.wait()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})


def _bearer(token: str) -> dict[str, str]:
    return {"authorization": f"Bearer {token}"}


@pytest.mark.anyio
async def test_limits_per_caller_and_per_route() -> None:
    gate = _Gate()
    state = HeavyLimitState(per_token=2, per_route=3, retry_after_s=7)
    app = HeavyRequestLimit(gate, state)
    statuses: list[tuple[str, int]] = []
    report = "/api/v1/fleet/report"

    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app), base_url="http://t"
    ) as client:

        async def call(path: str, token: str) -> None:
            r = await client.get(path, headers=_bearer(token))
            statuses.append((token, r.status_code))
            if r.status_code == 429:
                assert r.headers["retry-after"] == "7"
                assert r.json()["error"] == "too_many_requests"

        async with anyio.create_task_group() as tg:
            for token in ("a", "a", "b"):
                tg.start_soon(call, report, token)
            await _wait(lambda: gate.started == 3)
            await call(report, "a")  # a's third: over its own limit
            await call(report, "c")  # c's first: over the route's limit
            tg.start_soon(call, "/api/v1/vehicles/x/series", "c")  # another route has room
            await _wait(lambda: gate.started == 4)
            assert state.in_flight == {"fleet_report": 3, "series": 1}
            gate.open.set()
        await call(report, "a")  # slots given back
    assert statuses.count(("a", 429)) == 1 and statuses.count(("c", 429)) == 1
    assert dict(state.refused) == {("fleet_report", "token"): 1, ("fleet_report", "route"): 1}
    assert sum(state.in_flight.values()) == 0 and not state.by_caller


@pytest.mark.anyio
async def test_cheap_routes_are_never_limited() -> None:
    gate = _Gate()
    gate.open.set()
    state = HeavyLimitState(per_token=1, per_route=1, retry_after_s=1)
    app = HeavyRequestLimit(gate, state)
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app), base_url="http://t"
    ) as client:
        for path in ("/api/v1/health", "/api/v1/vehicles", "/api/v1/vehicles/x/latest"):
            assert state.over("fleet_report", "x") is None
            assert (await client.get(path)).status_code == 200
    assert not state.refused and not state.in_flight


async def _wait(cond: Callable[[], bool], timeout_s: float = 5.0) -> None:
    with anyio.fail_after(timeout_s):
        while not cond():
            await anyio.sleep(0.01)


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"
