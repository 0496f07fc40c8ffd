"""Pure ASGI middleware: request ids, metrics and access logs, bearer auth, and the request body limit.

Pure ASGI rather than ``BaseHTTPMiddleware`` because the body limit has to wrap ``receive`` (counting bytes as
they stream in, for chunked bodies with no Content-Length) and because it keeps streaming and cancellation
semantics intact. Order, outermost first: context (id, metrics, last-resort JSON 500) -> auth -> body limit.
"""

from __future__ import annotations

import hmac
import logging
import re
import time
import uuid
from collections.abc import Collection
from typing import Any

from starlette.datastructures import Headers, MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from gradsep.service.errors import body_too_large, error_json
from gradsep.service.metrics import ServiceMetrics

log = logging.getLogger("gradsep.service")

# A client's id is echoed only when it is a harmless token (no header injection, bounded log lines).
_REQUEST_ID = re.compile(r"^[A-Za-z0-9._:@/+=-]{1,128}$")
OPEN_PATHS = frozenset({"/healthz", "/readyz"})
QUIET_PATHS = OPEN_PATHS | {"/metrics"}  # probes and scrapes: access-logged at DEBUG unless they fail


def request_id_of(scope: Scope) -> str:
    return str(scope.get("state", {}).get("request_id", "-"))


class RequestContextMiddleware:
    """Assign ``X-Request-ID``, count and time every request, log one access line, JSON 500 for crashes."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics, known_paths: Collection[str] = ()) -> None:
        self.app, self.metrics, self.known_paths = app, metrics, frozenset(known_paths)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        given = Headers(scope=scope).get("x-request-id", "")
        rid = given if _REQUEST_ID.match(given) else uuid.uuid4().hex
        scope.setdefault("state", {})["request_id"] = rid
        status, started = 500, False

        async def send_with_id(message: Message) -> None:
            nonlocal status, started
            if message["type"] == "http.response.start":
                status, started = message["status"], True
                MutableHeaders(scope=message)["X-Request-ID"] = rid
            await send(message)

        t0 = time.perf_counter()
        self.metrics.in_flight.inc()
        try:
            await self.app(scope, receive, send_with_id)
        except Exception:
            log.exception("request %s %s %s failed unexpectedly", rid, scope["method"], scope["path"])
            if started:
                raise  # headers are out: nothing left but dropping the connection
            response = error_json(500, "internal", "internal error; the server log has it under this request id",
                                  {"request_id": rid}, metrics=self.metrics)
            await response(scope, receive, send_with_id)
        finally:
            seconds = time.perf_counter() - t0
            self.metrics.in_flight.dec()
            route = self._route(scope)
            self.metrics.requests.labels(route=route, method=scope["method"], status=str(status)).inc()
            self.metrics.latency.labels(route=route).observe(seconds)
            client = scope.get("client") or ("-", 0)
            level = logging.DEBUG if scope["path"] in QUIET_PATHS and status < 400 else logging.INFO
            log.log(level, "%s %s %s %d %.1fms request_id=%s", client[0], scope["method"], scope["path"], status,
                     seconds * 1000, rid)

    def _route(self, scope: Scope) -> str:
        """Route template as the metrics label; unknown paths collapse so label cardinality stays bounded."""
        route = getattr(scope.get("route"), "path", None)
        if route:
            return str(route)
        return scope["path"] if scope["path"] in self.known_paths else "other"


class BearerAuthMiddleware:
    """When a token is configured, everything but health and readiness needs ``Authorization: Bearer``."""

    def __init__(self, app: ASGIApp, token: str | None, metrics: ServiceMetrics) -> None:
        self.app, self.metrics = app, metrics
        self.token = token.encode() if token else None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and self.token is not None and scope["path"] not in OPEN_PATHS:
            problem = self._problem(Headers(scope=scope).get("authorization"))
            if problem:
                response = error_json(401, "unauthorized", problem, None,
                                      {"WWW-Authenticate": 'Bearer realm="gradsep"'}, metrics=self.metrics)
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)

    def _problem(self, header: str | None) -> str | None:
        if not header:
            return "this endpoint needs a bearer token (Authorization: Bearer <token>)"
        scheme, _, credentials = header.partition(" ")
        if scheme.lower() != "bearer" or not credentials.strip():
            return "the Authorization header must be 'Bearer <token>'"
        if not hmac.compare_digest(credentials.strip().encode(), self.token or b""):  # constant time
            return "invalid bearer token"
        return None


class BodyLimitMiddleware:
    """413 for bodies over ``limit`` bytes: at once from Content-Length, else while counting the stream.

    The count matters for chunked uploads (no Content-Length): the application never buffers more than the
    limit, because ``receive`` raises as soon as the running total passes it.
    """

    def __init__(self, app: ASGIApp, limit: int, metrics: ServiceMetrics) -> None:
        self.app, self.limit, self.metrics = app, limit, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length")
        if declared is not None:
            size = _int_or_none(declared)
            if size is None or size < 0:
                response = error_json(400, "bad_request", f"invalid Content-Length header {declared[:40]!r}",
                                      None, metrics=self.metrics)
                await response(scope, receive, send)
                return
            if size > self.limit:
                err = body_too_large(self.limit, size)
                await error_json(err.status, err.code, err.message, err.details,
                                 {"Connection": "close"}, metrics=self.metrics)(scope, receive, send)
                return
        received = 0

        async def counted_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise body_too_large(self.limit)
            return message

        await self.app(scope, counted_receive, send)


def _int_or_none(text: str) -> int | None:
    try:
        return int(text.strip())
    except ValueError:
        return None


def install_middleware(app: Any, *, token: str | None, max_body_bytes: int, metrics: ServiceMetrics) -> None:
    """Add the stack; Starlette wraps the last added outermost, so add innermost first."""
    known = [getattr(r, "path", "") for r in app.routes]
    app.add_middleware(BodyLimitMiddleware, limit=max_body_bytes, metrics=metrics)
    app.add_middleware(BearerAuthMiddleware, token=token, metrics=metrics)
    app.add_middleware(RequestContextMiddleware, metrics=metrics, known_paths=known)
