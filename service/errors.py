"""The service's one error shape, ``{"error": {"code", "message", "details"}}``, for every failure.

Clients (the render-farm client, curl scripts, contract tests) branch on ``code``; ``message`` is for people and
``details`` names what was wrong (channels, limits, parameters). Input problems raised by the frame contract
(:class:`model.errors.FrameError`) carry their own status and code, so this module maps them without a table.
Anything unexpected still answers JSON (500 ``internal``, see ``service.middleware``), never a bare text 500.
"""

from __future__ import annotations

import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import JSONResponse

from gradsep.model.errors import FrameError


class ErrorBody(BaseModel):
    code: str = Field(description="stable machine-readable error code")
    message: str = Field(description="what went wrong, for people")
    details: Any = Field(None, description="channels, limits or parameters involved, when known")


class ErrorResponse(BaseModel):
    """The body of every non-2xx response."""

    error: ErrorBody


class ServiceError(Exception):
    """A failure the service answers itself (not a frame problem): auth, limits, load, timeouts."""

    def __init__(self, status: int, code: str, message: str, details: Any = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.details = status, code, message, details
        self.headers = headers or {}


def body_too_large(limit: int, received: int | None = None) -> ServiceError:
    """413 for a body over the limit, with ``Connection: close``: the rest of the body is never read, and a kept-alive
    connection would have uvicorn read it (to discard it) for as long as the client sends."""
    details: dict[str, Any] = {"max_body_bytes": limit}
    if received is not None:
        details["received_bytes"] = received
    return ServiceError(413, "body_too_large", f"request body is over the limit of {limit} bytes", details,
                        {"Connection": "close"})


# Codes for statuses Starlette/FastAPI raise themselves (routing, multipart parsing).
_HTTP_CODES = {400: "bad_request", 401: "unauthorized", 404: "not_found", 405: "method_not_allowed",
               413: "body_too_large", 415: "unsupported_media_type", 422: "invalid_request"}


def error_json(status: int, code: str, message: str, details: Any = None,
               headers: dict[str, str] | None = None, metrics: Any = None) -> JSONResponse:
    """Build the JSON error response; count it as a rejection by ``code`` when ``metrics`` is given."""
    if metrics is not None:
        metrics.rejections.labels(reason=code).inc()
    body = {"error": {"code": code, "message": message, "details": details}}
    return JSONResponse(body, status_code=status, headers=headers)


def _metrics(request: Request) -> Any:
    return getattr(request.app.state, "metrics", None)


async def _frame_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, FrameError)
    return error_json(exc.status, exc.code, exc.message, _jsonable(exc.details), metrics=_metrics(request))


async def _service_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ServiceError)
    return error_json(exc.status, exc.code, exc.message, _jsonable(exc.details), exc.headers,
                      metrics=_metrics(request))


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    """Bad query parameters: 422 listing each parameter, its problem, and the value that was sent."""
    assert isinstance(exc, RequestValidationError)
    problems = [{"parameter": ".".join(str(p) for p in e.get("loc", ())[1:]) or "request",
                 "location": str(e.get("loc", ("request",))[0]), "message": e.get("msg", "invalid"),
                 "input": _jsonable(e.get("input"))} for e in exc.errors()]
    message = "; ".join(f"{p['parameter']}: {p['message']}" for p in problems) or "invalid request"
    return error_json(422, "invalid_parameter", message, problems, metrics=_metrics(request))


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    code = _HTTP_CODES.get(exc.status_code, "http_error")
    message = exc.detail if isinstance(exc.detail, str) else "request failed"
    return error_json(exc.status_code, code, message, None, dict(exc.headers or {}), metrics=_metrics(request))


def _jsonable(value: Any) -> Any:
    """Details must always serialise: anything exotic (bytes, exceptions) becomes its repr, truncated."""
    if value is None or isinstance(value, bool | int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)  # JSON has no NaN/Inf
    if isinstance(value, str):
        return value[:1000]
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in list(value.items())[:100]}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in list(value)[:100]]
    return repr(value)[:200]


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(FrameError, _frame_error)
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
