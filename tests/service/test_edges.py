"""Service edges through a real uvicorn and raw sockets: a client that disconnects mid-upload (499, its own
rejection reason, no traceback), a body that stalls (408, the connection closed, nothing held), and who may
read the API docs (open by default, or protected, or off)."""

from __future__ import annotations

import logging
import socket
import time

import httpx
import pytest

from gradsep.service.main import create_app
from tests.service.conftest import in_process, settings, uvicorn_server, wait_ready
from tests.service.frames import frame_bytes


def _connect(url: str) -> socket.socket:
    host, port = url.removeprefix("http://").split(":")
    return socket.create_connection((host, int(port)), timeout=10)


def _head(length: int, path: str = "/v1/reconstruct?method=l2", media: str = "image/x-exr") -> bytes:
    return (f"POST {path} HTTP/1.1\r\nHost: test\r\nContent-Type: {media}\r\nContent-Length: {length}\r\n"
            "\r\n").encode()


def _read_all(sock: socket.socket) -> bytes:
    chunks = []
    while True:
        try:
            chunk = sock.recv(65536)
        except (ConnectionResetError, TimeoutError):
            break
        if not chunk:
            break
        chunks.append(chunk)
    return b"".join(chunks)


def _metric(text: str, name: str, **labels: str) -> float:
    """The value of one sample of ``name`` whose labels include ``labels`` (0 when absent)."""
    total = 0.0
    for line in text.splitlines():
        if line.startswith(name + "{") and all(f'{k}="{v}"' in line for k, v in labels.items()):
            total += float(line.rsplit(" ", 1)[1])
    return total


def _wait_for(client: httpx.Client, name: str, timeout: float = 10.0, **labels: str) -> str:
    deadline = time.monotonic() + timeout
    while True:
        text = client.get("/metrics").text
        if _metric(text, name, **labels) >= 1 or time.monotonic() > deadline:
            return text
        time.sleep(0.02)


@pytest.mark.parametrize("media", ["image/x-exr", "multipart/form-data; boundary=xyz"])
def test_a_client_that_disconnects_mid_upload_is_a_499_not_a_500(caplog: pytest.LogCaptureFixture,
                                                                 media: str) -> None:
    caplog.set_level(logging.INFO, logger="gradsep.service")
    body = frame_bytes(height=64, width=64)
    prefix = b"--xyz\r\nContent-Disposition: form-data; name=\"frame\"; filename=\"f.exr\"\r\n\r\n" \
        if media.startswith("multipart") else b""
    with uvicorn_server(create_app(settings())) as url, httpx.Client(base_url=url, timeout=30) as client:
        wait_ready(client)
        sock = _connect(url)
        sock.sendall(_head(len(prefix) + len(body) + 100, media=media) + prefix + body[: len(body) // 2])
        time.sleep(0.1)  # the service is reading the body
        sock.close()
        text = _wait_for(client, "gradsep_rejections_total", reason="client_disconnected")
        assert _metric(text, "gradsep_rejections_total", reason="client_disconnected") == 1
        assert _metric(text, "gradsep_http_requests_total", route="/v1/reconstruct", status="499") == 1
        assert _metric(text, "gradsep_http_requests_total", status="500") == 0
        assert _metric(text, "gradsep_rejections_total", reason="internal") == 0
        assert _metric(text, "gradsep_http_requests_in_flight") <= 1  # the /metrics request itself
        assert client.post("/v1/reconstruct", content=frame_bytes(), params={"method": "l2"},
                           headers={"content-type": "image/x-exr"}).status_code == 200
    records = [r for r in caplog.records if r.name == "gradsep.service"]
    assert any("client disconnected" in r.getMessage() for r in records)
    assert not any(r.exc_info or r.levelno >= logging.ERROR for r in records), [r.getMessage() for r in records]


@pytest.mark.parametrize("media", ["image/x-exr", "multipart/form-data; boundary=xyz"])
def test_a_stalled_body_gets_408_and_frees_its_slot(media: str) -> None:
    app = create_app(settings(body_timeout=0.3, concurrency=1, queue_size=0))
    with uvicorn_server(app) as url, httpx.Client(base_url=url, timeout=30) as client:
        wait_ready(client)
        sock = _connect(url)
        started = time.monotonic()
        sock.sendall(_head(10_000, media=media) + b"--xyz\r\n" + b"x" * 100)
        answer = _read_all(sock)  # the service answers and closes the connection
        took = time.monotonic() - started
        sock.close()
        head, _, body = answer.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 408"), answer[:300]
        assert b"connection: close" in head.lower()
        assert b'"code":"body_timeout"' in body and b"stalled" in body
        assert 0.25 < took < 5, took
        metrics = client.get("/metrics").text
        assert _metric(metrics, "gradsep_rejections_total", reason="body_timeout") == 1
        assert _metric(metrics, "gradsep_http_requests_in_flight") <= 1
        response = client.post("/v1/reconstruct", content=frame_bytes(), params={"method": "l2"},
                               headers={"content-type": "image/x-exr"})
        assert response.status_code == 200, response.text


def test_a_slow_body_that_keeps_moving_is_not_cut() -> None:
    """The timeout is per stall, not for the whole body: each wait is under it, the total is over it."""
    data = frame_bytes()
    with uvicorn_server(create_app(settings(body_timeout=0.4))) as url, \
            httpx.Client(base_url=url, timeout=30) as client:
        wait_ready(client)
        sock = _connect(url)
        sock.sendall(_head(len(data)))
        step = len(data) // 4 + 1
        for piece in (data[i:i + step] for i in range(0, len(data), step)):
            time.sleep(0.15)
            sock.sendall(piece)
        head = _read_all_until_head(sock)
        sock.close()
        assert head.startswith(b"HTTP/1.1 200"), head[:300]


def _read_all_until_head(sock: socket.socket) -> bytes:
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            break
        data += chunk
    return data


def test_docs_are_open_without_the_token_by_default() -> None:
    with in_process(create_app(settings(token="s3cret-token"))) as client:
        for path in ("/docs", "/docs/static/swagger-ui-bundle.js", "/openapi.json"):
            assert client.get(path).status_code == 200, path
        assert client.get("/v1/models").status_code == 401
        for sneaky in ("/docs/static/%2e%2e/%2e%2e/v1/models", "/docs/static/..%2f..%2fmetrics"):
            assert client.get(sneaky).status_code == 404, sneaky  # the static mount, which refuses traversal


def test_docs_can_be_protected() -> None:
    with in_process(create_app(settings(token="s3cret-token", docs="protected"))) as client:
        for path in ("/docs", "/docs/static/swagger-ui-bundle.js", "/openapi.json"):
            assert client.get(path).status_code == 401, path
            assert client.get(path, headers={"Authorization": "Bearer s3cret-token"}).status_code == 200, path


def test_docs_can_be_turned_off() -> None:
    with in_process(create_app(settings(docs="off"))) as client:
        for path in ("/docs", "/docs/static/swagger-ui-bundle.js", "/openapi.json"):
            response = client.get(path)
            assert response.status_code == 404, path
            assert response.json()["error"]["code"] == "not_found"
        assert client.post("/v1/reconstruct", content=frame_bytes(), params={"method": "l2"},
                           headers={"content-type": "image/x-exr"}).status_code == 200


def test_body_timeout_and_docs_settings_are_validated() -> None:
    from pydantic import ValidationError

    for bad in ({"body_timeout": 0}, {"body_timeout": -1}, {"docs": "public"}):
        with pytest.raises(ValidationError):
            settings(**bad)
    assert settings().body_timeout == 30.0 and settings().docs == "open"
