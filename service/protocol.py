"""uvicorn HTTP protocols whose parse-error answer is the service's JSON error, not uvicorn's plain text.

A request uvicorn's HTTP parser rejects (``Content-Length: abc``, a malformed request line or header) never
reaches the ASGI app, so the app's error handlers cannot shape the answer: uvicorn writes
``400 text/plain "Invalid HTTP request received."`` itself. These subclasses override only that one method
(``send_400_response``, present in both of uvicorn's implementations) to write the documented
``{"error": {"code": "bad_request", "message", "details"}}`` body instead, then close the connection as
uvicorn does (after a parse error the byte stream cannot be trusted). ``gradsep serve`` passes the class to
uvicorn's ``http`` option (see :func:`http_protocol`).

The httptools protocol also buffers more of a request body before pausing the socket (:data:`BODY_HIGH_WATER`
instead of uvicorn's 64 KiB): uvicorn pauses reading as soon as 64 KiB wait for the app, so a large frame arrives
in many pause/resume round trips, each letting the TCP window close (docs/decisions.md has the measurement). The
bound stays: at most this many bytes per connection wait beyond what the app consumed.
"""

from __future__ import annotations

import json

from uvicorn.protocols.http.h11_impl import H11Protocol

#: Bytes of a request body buffered per connection before reading pauses (uvicorn's own limit is 64 KiB).
BODY_HIGH_WATER = 4 << 20


def bad_request_bytes(parser_message: str) -> bytes:
    """A complete HTTP/1.1 400 response with the service's JSON error body, ``Connection: close``."""
    body = json.dumps({"error": {
        "code": "bad_request",
        "message": f"malformed HTTP request: {parser_message} (check the request line and headers such as "
                   "Content-Length, which must be a non-negative integer)",
        "details": None}}).encode()
    head = ("HTTP/1.1 400 Bad Request\r\ncontent-type: application/json\r\n"
            f"content-length: {len(body)}\r\nconnection: close\r\n\r\n").encode("ascii")
    return head + body


def _send_json_400(protocol: object, msg: str) -> None:
    transport = protocol.transport  # type: ignore[attr-defined]
    transport.write(bad_request_bytes(msg))
    transport.close()


class JsonErrorH11Protocol(H11Protocol):
    """uvicorn's pure-Python (h11) protocol with the JSON parse-error answer."""

    def send_400_response(self, msg: str) -> None:
        _send_json_400(self, msg)


def http_protocol() -> type:
    """The protocol ``gradsep serve`` runs: httptools when installed (uvicorn[standard], uvicorn's own
    preference, faster), else h11 -- each with the JSON parse-error answer."""
    try:
        from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
    except ImportError:  # uvicorn without its optional C parser
        return JsonErrorH11Protocol

    class JsonErrorHttpToolsProtocol(HttpToolsProtocol):
        """uvicorn's httptools protocol with the JSON parse-error answer."""

        def send_400_response(self, msg: str) -> None:
            _send_json_400(self, msg)

        def on_body(self, body: bytes) -> None:
            """uvicorn's handler (appends the chunk, pauses reading past 64 KiB), then reading resumes while
            less than BODY_HIGH_WATER waits for the app, so a large upload streams in big reads."""
            super().on_body(body)
            cycle = getattr(self, "cycle", None)
            if cycle is not None and not cycle.response_complete and len(cycle.body) <= BODY_HIGH_WATER:
                self.flow.resume_reading()

    return JsonErrorHttpToolsProtocol
