"""Dependencies of the route handlers: the runtime, its store, limits, time ranges, roles.

Authorisation is :func:`require_role` and nothing else: it resolves the caller's bearer token
(hashed, looked up in the store) and compares roles.

What the API needs from the server runtime is :class:`ApiRuntime`, with the vehicle changes it
tells the runtime of as a typed service, :class:`VehicleEvents` (:data:`EventsDep`). Tests pass
any object that fits, e.g. one holding a real SQLite store and writer and no Zenoh session. Reads go
to the store from the request's thread; writes (vehicles, tokens) through the runtime's single
store writer (:data:`WriterDep`), like every other write.

Estimate routes read one estimator's rows: :data:`EstimatorDep` resolves the ``estimator`` query
parameter (default: the vehicle's primary, the first of the estimators its config runs) to that
estimator's :class:`estimator.spec.EstimatorSpec`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Annotated, Protocol, TypeVar

import numpy as np
from fastapi import Depends, Query, Request, WebSocketException, status
from starlette.requests import HTTPConnection

from estimator.catalog import SPECS, spec_of
from estimator.config import ConfigError, SlipConfig, VehicleConfig, vehicle_config_from_dict
from estimator.spec import EstimatorSpec, ValueChannel
from server.analytics.alerts import AlertEngine
from server.analytics.slipmap import SlipMap, slip_map
from server.api.errors import (
    Forbidden,
    InvalidTime,
    NotFound,
    RangeTooLarge,
    ServiceUnavailable,
    Unauthorized,
    Unprocessable,
)
from server.estimation.registry import UnknownEstimatorError, estimator_names_for
from server.live.hub import LiveHub
from server.metrics.prometheus import MetricFamily
from server.settings import Settings
from server.storage.base import StorageError, Store, VehicleRecord
from server.timeparse import TimeParseError, parse_time_ns
from server.tokens import Role, hash_token, is_well_formed

__all__ = [
    "ANONYMOUS_ADMIN",
    "WS_BEARER_PROTOCOL",
    "WS_TOKEN_QUERY",
    "ApiLimits",
    "ApiRuntime",
    "EstimatorDep",
    "EstimatorQuery",
    "EventsDep",
    "LimitsDep",
    "NoVehicleEvents",
    "Principal",
    "PrincipalDep",
    "RoleRequirement",
    "RuntimeDep",
    "SettingsDep",
    "StoreCalls",
    "StoreDep",
    "TimeRange",
    "TimeRangeDep",
    "VehicleDep",
    "VehicleEvents",
    "WriterDep",
    "estimator_spec",
    "principal_of",
    "principal_of_token",
    "require_role",
    "slip_config",
    "vehicle_estimators",
    "vehicle_slip_map",
]

_log = logging.getLogger(__name__)

_S = 1_000_000_000
_H = 3600 * _S
_DAY = 24 * _H


_T = TypeVar("_T")


class StoreCalls(Protocol):
    """The single store writer, as the API uses it: ``call(fn)`` runs ``fn(store)`` on the
    writer's thread and returns its result or raises its error
    (:meth:`server.storage.writer.StoreWriter.call`)."""

    def call(self, fn: Callable[[Store], _T]) -> _T: ...


class VehicleEvents(Protocol):
    """What the server does when the API changes a vehicle (the routes call it after the store
    accepted the change).

    ``check_vehicle_config`` may raise :class:`estimator.config.ConfigError` to refuse a config
    before it is stored (e.g. an estimator name the registry does not know);
    ``on_vehicle_config`` is told after the store accepted it, ``on_vehicle_deleted`` after the
    store deleted the vehicle; ``on_estimator_command`` and ``on_calibration_reset`` pass an
    operator's command on to the vehicle's estimator.
    """

    def check_vehicle_config(self, vehicle_id: str, config: VehicleConfig) -> None: ...

    def on_vehicle_config(self, vehicle_id: str, config: VehicleConfig) -> None: ...

    def on_vehicle_deleted(self, vehicle_id: str) -> None: ...

    def on_estimator_command(self, vehicle_id: str, estimator: str, key: str, on: bool) -> None: ...

    def on_calibration_reset(self, vehicle_id: str, estimator: str) -> None: ...


class NoVehicleEvents:
    """:class:`VehicleEvents` of a runtime that runs no estimators (a store behind the API
    alone): every config is accepted and nothing else listens."""

    def check_vehicle_config(self, vehicle_id: str, config: VehicleConfig) -> None:
        return None

    def on_vehicle_config(self, vehicle_id: str, config: VehicleConfig) -> None:
        return None

    def on_vehicle_deleted(self, vehicle_id: str) -> None:
        return None

    def on_estimator_command(self, vehicle_id: str, estimator: str, key: str, on: bool) -> None:
        return None

    def on_calibration_reset(self, vehicle_id: str, estimator: str) -> None:
        return None


class ApiRuntime(Protocol):
    """What the API needs from the server runtime.

    The app's lifespan calls ``open()`` on start-up and ``close()`` on shut-down; ``store`` and
    ``writer`` are read only between the two (``writer`` None: not open). ``health()`` names
    each part (``"zenoh"``, ``"storage"``, …) and whether it is up; the API is ready only when
    every part is. ``live_hub`` and ``alert_engine`` (None: the runtime has none) are published
    on ``app.state`` by the lifespan for the live and alert routes. ``vehicle_events`` is told
    of the API's vehicle changes (:data:`EventsDep`);
    ``metrics()`` gives the runtime's metric families for ``GET /metrics`` (``by_vehicle``
    False: per-vehicle counters summed to fleet totals).
    """

    @property
    def store(self) -> Store: ...

    @property
    def writer(self) -> StoreCalls | None: ...

    @property
    def vehicle_events(self) -> VehicleEvents: ...

    @property
    def live_hub(self) -> LiveHub | None: ...

    @property
    def alert_engine(self) -> AlertEngine | None: ...

    def open(self) -> None: ...

    def close(self) -> None: ...

    def health(self) -> Mapping[str, bool]: ...

    def metrics(self, by_vehicle: bool = True) -> Iterable[MetricFamily]: ...

    def viewer_port(self) -> int | None:
        """The running 3D view's port (it binds ``settings.viewer.host``); None when it is off
        or not running."""


@dataclass(frozen=True, slots=True)
class ApiLimits:
    """Bounds that keep one request from exhausting the server.

    Attributes
    ----------
    max_body_bytes : int
        Largest request body (a vehicle config is a few hundred bytes).
    series_max_range_ns : int
        Longest ``end - start`` of a series query.
    series_max_rows : int
        Most rows a JSON or Parquet series answer may hold (after decimation). CSV streams chunk
        by chunk and is bounded by the range only.
    series_max_points : int
        Largest ``max_points`` a client may ask for.
    query_chunk_ns : int
        Series are read from the store in chunks of about this span (memory bound per read).
    report_max_range_ns : int
        Longest ``end - start`` of a report (a report holds its range's rows in memory, about
        36 bytes per row).
    report_max_gap_s : float
        A step between rows longer than this is a data gap in reports (and slip maps).
    slipmap_max_cells : int
        Most cells a slip map may hold (a GeoJSON cell is about 0.7 kB); its range is bounded
        by ``report_max_range_ns``.
    """

    max_body_bytes: int = 64 * 1024
    series_max_range_ns: int = 31 * _DAY
    series_max_rows: int = 200_000
    series_max_points: int = 100_000
    query_chunk_ns: int = _H
    report_max_range_ns: int = _DAY
    report_max_gap_s: float = 1.0
    slipmap_max_cells: int = 50_000


def _runtime(request: Request) -> ApiRuntime:
    runtime: ApiRuntime | None = getattr(request.app.state, "runtime", None)
    if runtime is None:  # only before the lifespan ran
        raise RuntimeError("the app's runtime is not open")
    return runtime


def _store(runtime: Annotated[ApiRuntime, Depends(_runtime)]) -> Store:
    return runtime.store


def _settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def _limits(request: Request) -> ApiLimits:
    limits: ApiLimits = request.app.state.limits
    return limits


def _writer(runtime: Annotated[ApiRuntime, Depends(_runtime)]) -> StoreCalls:
    writer = runtime.writer
    if writer is None:
        raise ServiceUnavailable("the store writer is not running")
    return writer


def _vehicle_events(runtime: Annotated[ApiRuntime, Depends(_runtime)]) -> VehicleEvents:
    return runtime.vehicle_events


RuntimeDep = Annotated[ApiRuntime, Depends(_runtime)]
EventsDep = Annotated[VehicleEvents, Depends(_vehicle_events)]
"""The runtime's listener of vehicle changes made through the API."""
StoreDep = Annotated[Store, Depends(_store)]
WriterDep = Annotated[StoreCalls, Depends(_writer)]
"""The runtime's single store writer: every REST write goes through its ``call``."""
SettingsDep = Annotated[Settings, Depends(_settings)]
LimitsDep = Annotated[ApiLimits, Depends(_limits)]


def _vehicle(vehicle_id: str, store: StoreDep) -> VehicleRecord:
    record = store.get_vehicle(vehicle_id)
    if record is None:
        raise NotFound(f"unknown vehicle {vehicle_id!r}")
    return record


VehicleDep = Annotated[VehicleRecord, Depends(_vehicle)]
"""The vehicle named by the ``{vehicle_id}`` path parameter, or 404."""


def slip_config(record: VehicleRecord) -> SlipConfig:
    """The vehicle's slip settings (moving threshold, band edges) for reports and maps; the
    defaults, with a warning, when its stored config no longer validates."""
    try:
        return vehicle_config_from_dict(record.config).slip
    except (ConfigError, TypeError, ValueError) as exc:
        _log.warning(
            "stored config of %s is invalid (%s); its statistics use the default slip settings",
            record.vehicle_id,
            exc,
        )
        return SlipConfig()


def vehicle_slip_map(
    rows: np.ndarray,
    spec: EstimatorSpec,
    slip: SlipConfig,
    tr: TimeRange,
    limits: ApiLimits,
    cell_m: float,
    layer: ValueChannel | None = None,
) -> SlipMap:
    """One vehicle's slip map as the API serves it: its own frame, cells of ``cell_m`` metres,
    the vehicle's slip settings, the API's gap and cell limits (``TooManyCells`` past those);
    ``rows`` are the vehicle's rows of ``spec`` in ``tr``, shape (n,)."""
    return slip_map(
        rows,
        spec,
        cell_m=cell_m,
        layer=layer,
        end_ns=tr.end_ns,
        band_edges_pct=slip.band_edges_pct,
        min_ground_speed_mps=slip.min_ground_speed_mps,
        max_gap_s=limits.report_max_gap_s,
        max_cells=limits.slipmap_max_cells,
    )


def vehicle_estimators(record: VehicleRecord) -> tuple[str, ...]:
    """The estimators the vehicle's config runs, primary first
    (:func:`server.estimation.registry.estimator_names_for`); none when its stored config no
    longer validates or names an estimator the server does not know."""
    try:
        return estimator_names_for(vehicle_config_from_dict(record.config))
    except (ConfigError, UnknownEstimatorError, TypeError, ValueError) as exc:
        _log.warning("stored config of %s runs no estimator: %s", record.vehicle_id, exc)
        return ()


def _catalog_doc() -> str:
    return "; ".join(f"`{name}` ({spec.title})" for name, spec in sorted(SPECS.items()))


EstimatorQuery = Annotated[
    str | None,
    Query(
        max_length=64,
        description="Estimator whose rows to read (`GET /api/v1/estimators`): "
        + _catalog_doc()
        + ". Default: the vehicle's primary estimator (the first of its `estimators`).",
        examples=sorted(SPECS),
    ),
]


def estimator_spec(name: str) -> EstimatorSpec:
    """The spec of the estimator ``name``, or 422 naming it and the known ones."""
    try:
        return spec_of(name)
    except KeyError:
        raise Unprocessable(
            f"unknown estimator {name!r}; known: {', '.join(sorted(SPECS))}"
        ) from None


def _estimator(vehicle: VehicleDep, estimator: EstimatorQuery = None) -> EstimatorSpec:
    if estimator is not None:
        return estimator_spec(estimator)
    names = vehicle_estimators(vehicle)
    if not names:
        raise NotFound(
            f"vehicle {vehicle.vehicle_id!r} runs no estimator; name one with estimator="
        )
    return estimator_spec(names[0])


EstimatorDep = Annotated[EstimatorSpec, Depends(_estimator)]
"""The spec of the estimator an estimate route reads: ``estimator=`` or the vehicle's primary."""


@dataclass(frozen=True, slots=True)
class TimeRange:
    """``[start_ns, end_ns)``, int nanoseconds since the epoch, UTC."""

    start_ns: int
    end_ns: int

    @property
    def span_ns(self) -> int:
        return self.end_ns - self.start_ns

    def check_span(self, max_ns: int) -> None:
        """Raise :class:`RangeTooLarge` when the range is longer than ``max_ns``."""
        if self.span_ns > max_ns:
            raise RangeTooLarge(
                f"range of {self.span_ns / _H:.1f} h exceeds the limit of {max_ns / _H:.1f} h"
            )


_TIME_DOC = (
    "ISO 8601 with a UTC offset (e.g. `2024-05-01T12:00:00Z`, nanosecond fractions kept), "
    "integer nanoseconds since the Unix epoch, or a time relative to the server's clock "
    "(`now`, `now-15m`, `now-24h`, `now-7d`; units s, m, h, d). Times without an offset are "
    "refused."
)


def _time_range(
    start: Annotated[
        str,
        Query(
            description="Start of the range (inclusive). " + _TIME_DOC,
            examples=["2024-05-01T12:00:00Z", "now-24h"],
            max_length=64,
        ),
    ],
    end: Annotated[
        str,
        Query(
            description="End of the range (exclusive). " + _TIME_DOC,
            examples=["2024-05-01T13:00:00Z", "now"],
            max_length=64,
        ),
    ],
) -> TimeRange:
    now_ns = time.time_ns()  # one clock reading: "now-1h" and "now" span exactly an hour
    try:
        start_ns = parse_time_ns(start, now_ns)
    except TimeParseError as exc:
        raise InvalidTime(f"start: {exc}") from exc
    try:
        end_ns = parse_time_ns(end, now_ns)
    except TimeParseError as exc:
        raise InvalidTime(f"end: {exc}") from exc
    if end_ns <= start_ns:
        raise InvalidTime("end must be after start")
    return TimeRange(start_ns, end_ns)


TimeRangeDep = Annotated[TimeRange, Depends(_time_range)]


@dataclass(frozen=True, slots=True)
class Principal:
    """Who is calling: the token's name and role (``token_id`` None while auth is off)."""

    name: str
    role: Role
    token_id: int | None
    token_sha256: str | None = None  # the token's digest (never the token): to look it up again


#: Who every caller is while ``api.require_auth`` is off (the loopback demo, some tests).
ANONYMOUS_ADMIN = Principal("anonymous (require_auth off)", Role.ADMIN, None)

#: WebSocket subprotocol that marks the next offered protocol as the bearer token.
WS_BEARER_PROTOCOL = "slipfleet.bearer"
#: Query parameter a WebSocket may carry its token in (appears in access logs: prefer the
#: subprotocol).
WS_TOKEN_QUERY = "token"
#: ``last_used_ns`` is written at most this often per token (spares the database a write per
#: request).
TOKEN_TOUCH_INTERVAL_NS = 60 * _S


def _credential(conn: HTTPConnection) -> str | None:
    """The bearer token the caller presented, or None.

    HTTP: ``Authorization: Bearer <token>`` only. WebSocket (browsers cannot set headers):
    subprotocols ``[WS_BEARER_PROTOCOL, <token>]`` or the ``token`` query parameter.
    """
    header = conn.headers.get("authorization")
    if header is not None:
        scheme, _, value = header.partition(" ")
        return value.strip() if scheme.lower() == "bearer" and value.strip() else ""
    if conn.scope["type"] != "websocket":
        return None
    offered = [str(p) for p in conn.scope.get("subprotocols") or ()]
    if WS_BEARER_PROTOCOL in offered:
        at = offered.index(WS_BEARER_PROTOCOL)
        return offered[at + 1] if at + 1 < len(offered) else ""
    return conn.query_params.get(WS_TOKEN_QUERY)


def _refuse(conn: HTTPConnection, status_code: int, reason: str) -> Exception:
    """The error ending the request: JSON 401/403 over HTTP, close code 1008 on a WebSocket
    (the handshake then fails with HTTP 403, which is all a browser can see)."""
    if conn.scope["type"] == "websocket":
        return WebSocketException(code=status.WS_1008_POLICY_VIOLATION, reason=reason)
    if status_code == 401:
        return Unauthorized(reason, headers={"WWW-Authenticate": 'Bearer realm="slipfleet"'})
    return Forbidden(reason)


def _principal(conn: HTTPConnection) -> Principal:
    """Resolve the caller's token (once per request; every role check shares the result)."""
    settings: Settings = conn.app.state.settings
    if not settings.api.require_auth:
        return ANONYMOUS_ADMIN
    token = _credential(conn)
    if token is None:
        raise _refuse(conn, 401, "an access token is required: Authorization: Bearer <token>")
    return principal_of_token(conn, token)


def principal_of_token(conn: HTTPConnection, token: str) -> Principal:
    """The holder of ``token`` (401 or WebSocket 1008 when the store does not know it, or it is
    revoked or expired), for a route that finds its token elsewhere (the 3D view's cookie)."""
    if not is_well_formed(token):
        raise _refuse(conn, 401, "invalid, revoked or expired access token")
    runtime: ApiRuntime | None = getattr(conn.app.state, "runtime", None)
    if runtime is None:
        raise RuntimeError("the app's runtime is not open")
    store = runtime.store
    digest = hash_token(token)
    record = store.get_token(digest)
    now_ns = time.time_ns()
    if record is None or not record.valid_at(now_ns):
        raise _refuse(conn, 401, "invalid, revoked or expired access token")
    if record.last_used_ns is None or now_ns - record.last_used_ns >= TOKEN_TOUCH_INTERVAL_NS:
        try:
            store.touch_token(record.id, now_ns)
        except StorageError as exc:  # bookkeeping only: never refuse a valid token for it
            _log.warning("could not record the use of token %d: %s", record.id, exc)
    return Principal(record.name, Role(record.role), record.id, digest)


def principal_of(conn: HTTPConnection) -> Principal:
    """The caller of ``conn`` (401/403 or WebSocket 1008 when refused): what
    :data:`PrincipalDep` gives, for a dependency of its own."""
    return _principal(conn)


PrincipalDep = Annotated[Principal, Depends(_principal)]
"""The authenticated caller (no role check: use :func:`require_role`)."""


class RoleRequirement:
    """A dependency admitting callers whose token holds ``role`` or a higher one."""

    def __init__(self, role: Role | str) -> None:
        self.role = Role(role)

    def __call__(self, conn: HTTPConnection, principal: PrincipalDep) -> Principal:
        if not principal.role.admits(self.role):
            raise _refuse(
                conn,
                403,
                f"this operation needs the {self.role.value!r} role; the token "
                f"{principal.name!r} has {principal.role.value!r}",
            )
        return principal

    def __repr__(self) -> str:
        return f"require_role({self.role.value!r})"


def require_role(role: Role | str) -> RoleRequirement:
    """Dependency that admits only callers holding ``role``: the single point of authorisation.

    With ``settings.api.require_auth`` on (the default) the caller must present a token
    (``Authorization: Bearer …``; WebSockets: see :func:`_credential`) that the store knows and
    that is neither revoked nor expired, else 401; a token whose role is below ``role`` gets
    403. Roles: ``viewer`` < ``operator`` < ``admin``. With ``require_auth`` off every caller
    is admitted. Works for HTTP routes and WebSocket routes alike.
    """
    return RoleRequirement(role)
