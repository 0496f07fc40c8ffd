"""A raw-socket uploader for the body tests: a chunked (no Content-Length) body sent from one thread while the
response is read in the other, so an answer the server sends mid-upload (413, 503) is seen, not lost in a reset."""

from __future__ import annotations

import json
import socket
import threading
import time
from dataclasses import dataclass, field


@dataclass
class UploadResult:
    status: int | None  # None: no answer within the timeout, or the connection closed without one
    code: str | None = None  # the service's error code
    retry_after: str | None = None
    sent: int = 0  # body bytes the client got onto the wire
    seconds: float = 0.0
    headers: dict[str, str] = field(default_factory=dict)


def _parse(raw: bytes) -> tuple[int | None, dict[str, str], bytes]:
    head, _, body = raw.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    if not lines or not lines[0].startswith("HTTP/1.1 "):
        return None, {}, b""
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    return int(lines[0].split()[1]), headers, body


def _read_response(sock: socket.socket, deadline: float) -> bytes:
    raw = b""
    while time.monotonic() < deadline:
        try:
            chunk = sock.recv(65536)
        except TimeoutError:
            continue
        except OSError:
            break
        if not chunk:
            break
        raw += chunk
        status, headers, body = _parse(raw)
        if status is not None and len(body) >= int(headers.get("content-length", 1 << 62)):
            break
    return raw


def chunked_upload(port: int, total: int, chunk: int = 1 << 20, timeout: float = 120.0,
                   path: str = "/v1/reconstruct?method=l2") -> UploadResult:
    """POST ``total`` bytes of zeros as a chunked body; stop sending once the server answered or closed."""
    started = time.monotonic()
    sock = socket.create_connection(("127.0.0.1", port), timeout=1.0)
    sock.sendall(f"POST {path} HTTP/1.1\r\nHost: test\r\nContent-Type: image/x-exr\r\n"
                 "Transfer-Encoding: chunked\r\n\r\n".encode())
    answered = threading.Event()
    sent = 0

    def send_all(data: bytes) -> None:
        """``sendall`` that outlasts the socket's short timeout (kept short for the reader) while the server is
        slow to read, and gives up once the answer is in."""
        view, offset = memoryview(data), 0
        while offset < len(view) and not answered.is_set():
            try:
                offset += sock.send(view[offset:])
            except TimeoutError:
                continue

    def send() -> None:
        nonlocal sent
        piece = f"{chunk:x}\r\n".encode() + bytes(chunk) + b"\r\n"
        try:
            while sent < total and not answered.is_set():
                send_all(piece)
                sent += chunk
            send_all(b"0\r\n\r\n")
        except OSError:  # the server answered and closed: what a body over a limit gets
            pass

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        raw = _read_response(sock, started + timeout)
    finally:
        answered.set()
        sender.join(timeout=10)
        sock.close()
    status, headers, body = _parse(raw)
    code = None
    if status is not None and headers.get("content-type") == "application/json":
        try:
            code = json.loads(body)["error"]["code"]
        except (ValueError, KeyError, TypeError):
            code = None
    return UploadResult(status, code, headers.get("retry-after"), sent, time.monotonic() - started, headers)
