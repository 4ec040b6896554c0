# ruff: noqa: N818  (named after the HTTP statuses they stand for, as clients see them)
"""The API's exception tree and the one place it becomes HTTP.

::

    ApiError                      (500 "internal")
    ├── BadRequest                (400 "bad_request")
    │   └── RangeTooLarge         (400 "range_too_large")
    ├── Unauthorized              (401 "unauthorized")
    ├── Forbidden                 (403 "forbidden")
    ├── NotFound                  (404 "not_found")
    ├── Conflict                  (409 "conflict")
    ├── PayloadTooLarge           (413 "payload_too_large")
    ├── Unprocessable             (422 "invalid")
    │   ├── InvalidConfig         (422 "invalid_config")
    │   └── InvalidTime           (422 "invalid_time")
    └── ServiceUnavailable        (503 "unavailable")

Every error response has the body ``{"error": <code>, "reason": <text>}`` (:class:`ErrorBody`),
including FastAPI's request-validation errors (422 ``"invalid_request"``; a body refused because
it was not sent as JSON says so, not what its form-decoded shape lacked), unknown paths and
methods (Starlette's HTTP errors), the store's :class:`~server.storage.base.StorageError`
(503 ``"storage_unavailable"``) and anything unexpected (500 ``"internal"``, details only in the
log). Handlers raise; :func:`install_error_handlers` maps. An ``invalid_time`` whose query holds
an ISO time with a space where its offset's ``+`` was (a ``+`` unencoded in a URL query reads
as a space) says so.
"""

from __future__ import annotations

import logging
import re
from typing import Any, ClassVar

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from server.storage.base import StorageError

__all__ = [
    "ApiError",
    "BadRequest",
    "Conflict",
    "ErrorBody",
    "Forbidden",
    "InvalidConfig",
    "InvalidTime",
    "NotFound",
    "PayloadTooLarge",
    "RangeTooLarge",
    "ServiceUnavailable",
    "Unauthorized",
    "Unprocessable",
    "error_response",
    "error_responses",
    "install_error_handlers",
]

_log = logging.getLogger(__name__)


class ErrorBody(BaseModel):
    """Body of every error response."""

    error: str
    reason: str


class ApiError(Exception):
    """Base of every error a handler raises on purpose."""

    status_code: ClassVar[int] = 500
    code: ClassVar[str] = "internal"

    def __init__(
        self,
        reason: str,
        *,
        extra: dict[str, Any] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(reason)
        self.reason = reason
        self.extra = extra or {}
        self.headers = headers or {}


class BadRequest(ApiError):
    status_code = 400
    code = "bad_request"


class RangeTooLarge(BadRequest):
    """The query would read more than the server's limits allow."""

    code = "range_too_large"


class Unauthorized(ApiError):
    status_code = 401
    code = "unauthorized"


class Forbidden(ApiError):
    status_code = 403
    code = "forbidden"


class NotFound(ApiError):
    status_code = 404
    code = "not_found"


class Conflict(ApiError):
    status_code = 409
    code = "conflict"


class PayloadTooLarge(ApiError):
    status_code = 413
    code = "payload_too_large"


class Unprocessable(ApiError):
    status_code = 422
    code = "invalid"


class InvalidConfig(Unprocessable):
    code = "invalid_config"


class InvalidTime(Unprocessable):
    code = "invalid_time"


class ServiceUnavailable(ApiError):
    status_code = 503
    code = "unavailable"


def error_response(
    status_code: int, code: str, reason: str, extra: dict[str, Any] | None = None
) -> JSONResponse:
    """The JSON error response (``extra`` keys are added next to ``error`` and ``reason``)."""
    body: dict[str, Any] = {"error": code, "reason": reason}
    if extra:
        body.update(extra)
    return JSONResponse(body, status_code=status_code)


def error_responses(*status_codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for the error statuses a route can answer."""
    return {code: {"model": ErrorBody, "description": "error"} for code in status_codes}


# "…T10:00:00 01:00": a "+01:00" offset whose "+" the URL query decoding read as a space
_SPACE_FOR_PLUS = re.compile(
    r"[0-9]{2}:?[0-9]{2}(?::?[0-9]{2}(?:[.,][0-9]+)?)? [0-9]{2}(?::?[0-9]{2})?$"
)
_PLUS_HINT = (
    "; a '+' in a URL query stands for a space: write the offset's '+' as %2B "
    "(e.g. 2024-05-01T12:00:00%2B02:00), or give the time in UTC with 'Z'"
)
_JSON_TYPES = ("application/json", "+json")


def _time_hint(request: Request) -> str:
    """The hint for an ISO time whose offset's ``+`` arrived as a space, else ``""``."""
    values = request.query_params.values()
    return _PLUS_HINT if any(_SPACE_FOR_PLUS.search(v) for v in values) else ""


def _not_json_body(request: Request, exc: RequestValidationError) -> str | None:
    """The reason to give when a body was refused because it was not sent as JSON, else None."""
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type.endswith(_JSON_TYPES):
        return None
    if not any(tuple(err.get("loc", ()))[:1] == ("body",) for err in exc.errors()):
        return None
    got = f"Content-Type {content_type!r}" if content_type else "no Content-Type"
    return (
        f"the body must be JSON sent with Content-Type: application/json (this request had {got})"
    )


def _bad_json(exc: RequestValidationError) -> str | None:
    """The reason for a body that is not valid JSON (what the parser said, and where), else None."""
    for err in exc.errors():
        if err.get("type") == "json_invalid":
            loc = tuple(err.get("loc", ()))
            where = f" at character {loc[1]}" if len(loc) > 1 else ""
            said = (err.get("ctx") or {}).get("error", "not JSON")
            return f"the body is not valid JSON: {said}{where}"
    return None


def _validation_reason(exc: RequestValidationError) -> str:
    parts = []
    for err in exc.errors()[:10]:
        loc = ".".join(str(p) for p in err.get("loc", ()))
        msg = str(err.get("msg", "invalid"))
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts) or "invalid request"


_HTTP_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "invalid",
    429: "too_many_requests",
}


def _allowed_methods(request: Request) -> list[str]:
    """Every method some route serves at the request's path (Starlette names only the first)."""
    methods: set[str] = set()
    for route in request.app.router.routes:
        route_methods = getattr(route, "methods", None)
        if route_methods and route.matches(request.scope)[0] != Match.NONE:
            methods |= set(route_methods)
    return sorted(methods)


def install_error_handlers(app: FastAPI) -> None:
    """Map the exception tree (and the framework's own errors) to JSON responses."""

    async def on_api_error(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ApiError)
        if exc.status_code >= 500:
            _log.warning("%s: %s", exc.code, exc.reason)
        reason = exc.reason + (_time_hint(request) if isinstance(exc, InvalidTime) else "")
        response = error_response(exc.status_code, exc.code, reason, exc.extra)
        response.headers.update(exc.headers)
        return response

    async def on_validation(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RequestValidationError)
        reason = _not_json_body(request, exc) or _bad_json(exc) or _validation_reason(exc)
        return error_response(422, "invalid_request", reason)

    async def on_http(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, StarletteHTTPException)
        code = _HTTP_CODES.get(exc.status_code, "http_error")
        response = error_response(exc.status_code, code, str(exc.detail))
        if exc.headers:
            response.headers.update(exc.headers)
        if exc.status_code == 405:
            response.headers["Allow"] = ", ".join(_allowed_methods(request))
        return response

    async def on_storage(_: Request, exc: Exception) -> JSONResponse:
        _log.error("storage error: %s", exc)
        return error_response(503, "storage_unavailable", "the database did not answer")

    async def on_unexpected(_: Request, exc: Exception) -> JSONResponse:
        _log.exception("unhandled error", exc_info=exc)
        return error_response(500, "internal", "internal server error")

    app.add_exception_handler(ApiError, on_api_error)
    app.add_exception_handler(RequestValidationError, on_validation)
    app.add_exception_handler(StarletteHTTPException, on_http)
    app.add_exception_handler(StorageError, on_storage)
    app.add_exception_handler(Exception, on_unexpected)
