"""uvicorn's protocols as the service runs them (service/protocol.py): the parser's rejections are our JSON 400;
the read-ahead buffer passes a large body through intact."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.service.main import create_app
from tests.service.conftest import settings


def _raw_exchange(url: str, request: bytes) -> bytes:
    """Send raw bytes to a real server and read the whole answer (the server closes the connection)."""
    import socket
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    with socket.create_connection((parts.hostname, parts.port), timeout=10) as sock:
        sock.sendall(request)
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)



@pytest.mark.parametrize("parser", ["default", "h11"])
@pytest.mark.parametrize("request_bytes", [
    b"POST /v1/reconstruct HTTP/1.1\r\nHost: x\r\nContent-Type: image/x-exr\r\nContent-Length: abc\r\n\r\n",
    b"POST /v1/reconstruct HTTP/1.1\r\nHost: x\r\nContent-Length: -5\r\n\r\n",
    b"GARBAGE\x01 / HTTP/1.1\r\n\r\n"], ids=["content-length-abc", "content-length-negative", "request-line"])
def test_requests_uvicorns_parser_rejects_get_the_json_400(parser, request_bytes):
    """These never reach the app: uvicorn's parser answers them; service.protocol makes that answer ours."""
    from gradsep.service.protocol import JsonErrorH11Protocol
    from tests.service.conftest import uvicorn_server

    http = JsonErrorH11Protocol if parser == "h11" else None
    with uvicorn_server(create_app(settings()), http=http) as url:
        answer = _raw_exchange(url, request_bytes)
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 400"), answer[:200]
    assert b"content-type: application/json" in head.lower()
    error = __import__("json").loads(body)["error"]
    assert error["code"] == "bad_request" and "malformed HTTP request" in error["message"]



def test_large_body_streams_intact_through_the_buffered_protocol():
    """service.protocol reads ahead up to BODY_HIGH_WATER per connection: a body several times that size (sent as
    ``gradsep client`` sends it, memoryview slices with a Content-Length) arrives byte for byte, unchunked."""
    import hashlib

    import httpx

    from gradsep.service.client import upload_body
    from gradsep.service.protocol import BODY_HIGH_WATER
    from tests.service.conftest import uvicorn_server

    seen: dict[str, object] = {}

    async def app(scope, receive, send):
        if scope["type"] != "http":
            return
        digest, size, more = hashlib.sha256(), 0, True
        while more:
            message = await receive()
            digest.update(message.get("body", b""))
            size += len(message.get("body", b""))
            more = message.get("more_body", False)
        seen.update(size=size, headers=dict(scope["headers"]))
        body = digest.hexdigest().encode()
        await send({"type": "http.response.start", "status": 200,
                    "headers": [(b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})

    data = np.random.default_rng(5).bytes(3 * BODY_HIGH_WATER + 12345)
    with uvicorn_server(app) as url, httpx.Client(base_url=url, timeout=60) as client:
        body = upload_body(data, chunk=1 << 18)
        answer = client.post("/", content=body["content"], headers=body["headers"])
    assert answer.status_code == 200 and answer.text == hashlib.sha256(data).hexdigest()
    assert seen["size"] == len(data)
    assert seen["headers"][b"content-length"] == str(len(data)).encode()
    assert b"transfer-encoding" not in seen["headers"]

