"""Pure ASGI middleware: request ids, metrics and access logs, bearer auth, the request body limit and timeout.

Pure ASGI rather than ``BaseHTTPMiddleware`` because the body limit has to wrap ``receive`` (counting bytes as
they stream in, for chunked bodies with no Content-Length; timing out a body that stalls) and because it keeps
streaming and cancellation semantics intact. Order, outermost first: context (id, metrics, client disconnects
as 499, last-resort JSON 500) -> auth -> body limit and timeout.
"""

from __future__ import annotations

import hmac
import logging
import math
import re
import time
import uuid
from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any

import anyio
from starlette.datastructures import Headers, MutableHeaders
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from gradsep.service.errors import ServiceError, body_too_large, error_json
from gradsep.service.metrics import ServiceMetrics
from gradsep.service.settings import Settings
from gradsep.service.window import FirstPart, multipart_boundary, window_too_large

log = logging.getLogger("gradsep.service")

# A client's id is echoed only when it is a harmless token (no header injection, bounded log lines).
_REQUEST_ID = re.compile(r"^[A-Za-z0-9._:@/+=-]{1,128}$")
OPEN_PATHS = frozenset({"/healthz", "/readyz"})
#: The API docs: open without the token by default (settings.docs), as they hold no secret.
DOCS_PATHS = frozenset({"/docs", "/openapi.json"})
DOCS_PREFIX = "/docs/static/"
#: The status logged and counted for a request whose client went away before it was answered (nginx's
#: convention; nothing is sent): a client abort is not a server error and must not page anyone as a 5xx.
CLIENT_CLOSED = 499
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
        except ClientDisconnect:
            status = CLIENT_CLOSED
            self.metrics.rejections.labels(reason="client_disconnected").inc()
            log.info("request %s %s %s: the client disconnected before the request was answered", rid,
                     scope["method"], scope["path"])
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
    """When a token is configured, everything but health, readiness (and with ``open_docs`` the API docs, their
    assets and the OpenAPI schema) needs ``Authorization: Bearer``."""

    def __init__(self, app: ASGIApp, token: str | None, metrics: ServiceMetrics, open_docs: bool = True) -> None:
        self.app, self.metrics, self.open_docs = app, metrics, open_docs
        self.token = token.encode() if token else None

    def _open(self, path: str) -> bool:
        return path in OPEN_PATHS or (self.open_docs and (path in DOCS_PATHS or path.startswith(DOCS_PREFIX)))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and self.token is not None and not self._open(scope["path"]):
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
    """413 for bodies over ``limit`` bytes: at once from Content-Length, else while counting the stream; 408 for
    a body that stalls, no bytes arriving for ``timeout`` seconds; 503 + Retry-After for a body beyond the
    ``max_uploads`` being received at once.

    The count matters for chunked uploads (no Content-Length): the application never buffers more than the
    limit, because ``receive`` raises as soon as the running total passes it. The timeout is per wait, not for
    the whole body (a large upload on a slow link keeps going while bytes move) and only while the body is
    incomplete (after it, ``receive`` waits for a disconnect, which may rightly take forever). The upload cap
    bounds what the server holds per connection (uvicorn's read buffer) across all open uploads; an upload
    stops counting when its body is complete or its request ends.
    """

    def __init__(self, app: ASGIApp, limit: int, metrics: ServiceMetrics, timeout: float = math.inf,
                 uploads: UploadCap | None = None) -> None:
        self.app, self.limit, self.metrics, self.timeout = app, limit, metrics, timeout
        self.uploads = uploads or UploadCap(math.inf)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        declared = headers.get("content-length")
        refusal = self._refusal(declared)
        boundary = multipart_boundary(headers.get("content-type"))
        if refusal is not None and refusal.status == 413 and boundary and self.uploads.refusal() is None:
            refusal = await self._window_refusal(receive, boundary, _int_or_none(declared or ""))
        if refusal is None and (declared not in (None, "0") or "transfer-encoding" in headers):
            refusal = self.uploads.refusal()
            if refusal is None:
                counted = _CountedReceive(receive, self.limit, self.timeout, self.uploads,
                                          FirstPart(boundary) if boundary else None)
                try:
                    await self.app(scope, counted, send)
                finally:
                    counted.end()
                return
        if refusal is not None:
            await error_json(refusal.status, refusal.code, refusal.message, refusal.details, refusal.headers,
                             metrics=self.metrics)(scope, receive, send)
            return
        await self.app(scope, receive, send)

    async def _window_refusal(self, receive: Receive, boundary: bytes, declared: int | None) -> ServiceError:
        """The 413 of a multipart body declared over the limit, saying how many frames fit: the body is read
        (never past the limit, each wait within the body timeout) until its first part has been seen."""
        first, received = FirstPart(boundary), 0
        try:
            while first.size is None and received <= self.limit:
                with anyio.fail_after(self.timeout if math.isfinite(self.timeout) else None):
                    message = await receive()
                if message["type"] != "http.request":
                    break
                first.feed(message.get("body", b""))
                received += len(message.get("body", b""))
                if not message.get("more_body", False):
                    break
        except TimeoutError:
            pass  # the answer is the 413 all the same, without the count when the first part did not arrive
        return window_too_large(self.limit, first, declared)

    def _refusal(self, declared: str | None) -> ServiceError | None:
        """The answer to a Content-Length header that is invalid (400) or over the limit (413); None if fine."""
        if declared is None:
            return None
        size = _int_or_none(declared)
        if size is None or size < 0:
            return ServiceError(400, "bad_request", f"invalid Content-Length header {declared[:40]!r}", None)
        if size > self.limit:
            return body_too_large(self.limit, size)
        return None


@dataclass
class UploadCap:
    """How many request bodies may be received at once, and the Retry-After for one beyond them (only touched on
    the event loop)."""

    limit: float
    retry_after: Callable[[], int] = lambda: 1
    open: int = 0

    def refusal(self) -> ServiceError | None:
        if self.open < self.limit:
            return None
        retry = self.retry_after()
        return ServiceError(503, "uploads_full", f"{self.open} request bodies are being received, the most this "
                            f"service takes at once; retry in {retry} s", {"max_uploads": self.limit},
                            {"Retry-After": str(retry), "Connection": "close"})


class _CountedReceive:
    """``receive`` that counts body bytes (413 past the limit), times each wait (408) and holds one of the upload
    cap's places until the body is complete or :meth:`end` is called."""

    def __init__(self, receive: Receive, limit: int, timeout: float, uploads: UploadCap,
                 first: FirstPart | None = None) -> None:
        self.receive, self.limit, self.timeout, self.uploads = receive, limit, timeout, uploads
        self.first = first  # a multipart body's first part, for the 413's count of the frames that fit
        self.received, self.complete = 0, False
        uploads.open += 1

    def end(self) -> None:
        if not self.complete:
            self.complete = True
            self.uploads.open -= 1

    async def __call__(self) -> Message:
        if self.complete:
            return await self.receive()
        try:
            with anyio.fail_after(self.timeout if math.isfinite(self.timeout) else None):
                message = await self.receive()
        except TimeoutError:
            raise ServiceError(
                408, "body_timeout", f"the request body stalled: no bytes for {self.timeout:g} s after "
                f"{self.received} bytes", {"body_timeout_seconds": self.timeout, "received_bytes": self.received},
                {"Connection": "close"}) from None
        if message["type"] == "http.request":
            self.received += len(message.get("body", b""))
            if self.first is not None:
                self.first.feed(message.get("body", b""))
            if not message.get("more_body", False):
                self.end()
            if self.received > self.limit:
                raise body_too_large(self.limit) if self.first is None else window_too_large(self.limit, self.first)
        elif message["type"] == "http.disconnect":
            self.end()
        return message


def _int_or_none(text: str) -> int | None:
    try:
        return int(text.strip())
    except ValueError:
        return None


def install_middleware(app: Any, settings: Settings, metrics: ServiceMetrics,
                       retry_after: Callable[[], int] = lambda: 1) -> None:
    """Add the stack; Starlette wraps the last added outermost, so add innermost first. ``retry_after`` answers
    an upload beyond the cap."""
    known = [getattr(r, "path", "") for r in app.routes]
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_body_bytes, metrics=metrics,
                       timeout=settings.body_timeout, uploads=UploadCap(settings.max_uploads, retry_after))
    token, open_docs = settings.token_value, settings.docs == "open"
    app.add_middleware(BearerAuthMiddleware, token=token, metrics=metrics, open_docs=open_docs)
    app.add_middleware(RequestContextMiddleware, metrics=metrics, known_paths=known)
