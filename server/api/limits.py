"""Concurrency limits of the expensive routes (429 with ``Retry-After`` beyond them) and the
size and time budgets of one request (:class:`WorkBudget`, 413 beyond them).

Reports, slip maps and series exports read and reduce up to a day of a whole fleet's rows in a
worker thread each; fifty of them at once took every thread of the server's pool and starved
everything else. :class:`HeavyRequestLimit` (ASGI middleware) lets at most
``api.heavy_per_token`` of them run at once for one caller (its ``Authorization`` header; its
address without one) and at most ``api.heavy_per_route`` for one route, all callers together;
a request beyond either is answered at once, on the event loop, with 429 and
``Retry-After: api.retry_after_s``, and counted (:attr:`HeavyLimitState.refused`, in
``/metrics`` as ``slipfleet_api_requests_refused_total{route,limit}``). ``/health`` and the
cheap routes are never limited. A request counts until its answer is sent whole (streamed CSV
included).

A fleet report works vehicle by vehicle in its worker thread; :class:`WorkBudget` refuses one
over too many vehicles before it reads anything (``api.report_max_vehicles``) and stops one that
has worked longer than ``api.report_time_budget_s`` between two vehicles, each with 413 and one
line naming the setting: the caller narrows the request instead of holding a thread for minutes.
"""

from __future__ import annotations

import hashlib
import re
import time
from collections import Counter

from starlette.types import ASGIApp, Receive, Scope, Send

from server.api.errors import PayloadTooLarge, error_response

__all__ = ["HEAVY_ROUTES", "HeavyLimitState", "HeavyRequestLimit", "WorkBudget"]

#: Route name -> path pattern of the expensive routes (under the API prefix).
HEAVY_ROUTES: dict[str, re.Pattern[str]] = {
    "fleet_report": re.compile(r"^/api/v1/fleet/report/?$"),
    "fleet_slipmap": re.compile(r"^/api/v1/fleet/slipmap/?$"),
    "vehicle_report": re.compile(r"^/api/v1/vehicles/[^/]+/report/?$"),
    "vehicle_slipmap": re.compile(r"^/api/v1/vehicles/[^/]+/slipmap/?$"),
    "series": re.compile(r"^/api/v1/vehicles/[^/]+/series/?$"),
    "calibration": re.compile(r"^/api/v1/vehicles/[^/]+/calibration/?$"),
}


def _route_of(path: str) -> str | None:
    if not path.startswith("/api/v1/"):
        return None
    for name, pattern in HEAVY_ROUTES.items():
        if pattern.match(path):
            return name
    return None


def _caller_of(scope: Scope) -> str:
    """A caller's key: a digest of its Authorization header (never the token itself), else
    its address."""
    for name, value in scope.get("headers", ()):
        if name == b"authorization":
            return hashlib.sha256(value).hexdigest()
    client = scope.get("client")
    return f"addr:{client[0]}" if client else "addr:?"


class HeavyLimitState:
    """The limits and what runs and was refused under them (the event loop's thread only)."""

    def __init__(self, per_token: int, per_route: int, retry_after_s: int) -> None:
        self.per_token = per_token
        self.per_route = per_route
        self.retry_after_s = retry_after_s
        self.in_flight: Counter[str] = Counter()  # route -> requests running
        self.by_caller: Counter[str] = Counter()  # caller -> heavy requests running
        self.refused: Counter[tuple[str, str]] = Counter()  # (route, "token" | "route")

    def over(self, route: str, caller: str) -> str | None:
        """Which limit a new request would pass: "token", "route" or None."""
        if self.by_caller[caller] >= self.per_token:
            return "token"
        if self.in_flight[route] >= self.per_route:
            return "route"
        return None

    def enter(self, route: str, caller: str) -> None:
        self.in_flight[route] += 1
        self.by_caller[caller] += 1

    def leave(self, route: str, caller: str) -> None:
        self.in_flight[route] -= 1
        self.by_caller[caller] -= 1
        if self.by_caller[caller] <= 0:
            del self.by_caller[caller]  # callers come and go: keep only the running ones


class HeavyRequestLimit:
    """ASGI middleware: see the module docstring."""

    def __init__(self, app: ASGIApp, state: HeavyLimitState) -> None:
        self.app = app
        self.state = state

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        route = _route_of(scope["path"]) if scope["type"] == "http" else None
        if route is None:
            await self.app(scope, receive, send)
            return
        caller = _caller_of(scope)
        over = self.state.over(route, caller)
        if over is not None:
            self.state.refused[(route, over)] += 1
            await self._refuse(route, over, scope, receive, send)
            return
        self.state.enter(route, caller)
        try:
            await self.app(scope, receive, send)
        finally:
            self.state.leave(route, caller)

    async def _refuse(
        self, route: str, over: str, scope: Scope, receive: Receive, send: Send
    ) -> None:
        st = self.state
        limit, who = (st.per_token, "this token") if over == "token" else (st.per_route, "all")
        response = error_response(
            429,
            "too_many_requests",
            f"{route}: {limit} requests of {who} callers running; retry after {st.retry_after_s} s",
        )
        response.headers["Retry-After"] = str(st.retry_after_s)
        await response(scope, receive, send)


class WorkBudget:
    """The size and time budgets of one request working through ``total`` items (``unit``:
    what they are, for the message; see the module docstring). Built before the work: 413 when
    ``total`` is over ``max_items``; :meth:`check` between items: 413 once the time is spent.
    ``max_items`` and ``time_budget_s`` are ``(value, setting name)``."""

    def __init__(
        self,
        what: str,
        total: int,
        unit: str,
        *,
        max_items: tuple[int, str],
        time_budget_s: tuple[float, str],
    ) -> None:
        self.what = what
        self.total = total
        self.unit = unit
        self.max_items, self._items_setting = max_items
        self.time_budget_s, self._time_setting = time_budget_s
        self._deadline = time.monotonic() + self.time_budget_s
        if total > self.max_items:
            raise PayloadTooLarge(
                f"{what} would cover {total} {unit}, over {self._items_setting} "
                f"({self.max_items}): ask for fewer, or raise the setting"
            )

    def check(self, done: int) -> None:
        """Raise 413 when the time budget is spent (``done`` items of :attr:`total` made)."""
        if time.monotonic() > self._deadline:
            raise PayloadTooLarge(
                f"{self.what} passed its time budget {self._time_setting} "
                f"({self.time_budget_s:g} s) after {done} of {self.total} {self.unit}: narrow "
                "start..end, or raise the setting"
            )
