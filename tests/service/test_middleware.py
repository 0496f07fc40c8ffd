"""The middleware (service/middleware.py): a crash is a JSON 500 with the request id; at most GRADSEP_MAX_UPLOADS
bodies are received at once, the next gets 503 + Retry-After."""

from __future__ import annotations

import socket
import time

import httpx

import gradsep.service.pipeline
from gradsep.service.main import create_app
from tests.service.conftest import TRANSPORT, assert_error, post, settings, uvicorn_server, wait_ready
from tests.service.frames import frame_bytes
from tests.service.uploads import chunked_upload


def test_an_unexpected_failure_is_a_json_500_with_the_request_id(serve, monkeypatch):
    def crash(frame, method, alpha, models=None):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(gradsep.service.pipeline, "reconstruct", crash)
    with serve(create_app(settings(warm_up=False))) as client:
        response = post(client, frame_bytes(), headers={"X-Request-ID": "req-500"})
        error = assert_error(response, 500, "internal")
        assert error["details"] == {"request_id": "req-500"}
        assert "exploded" not in response.text  # internals stay in the server log
        assert client.get("/healthz").status_code == 200


def test_an_upload_beyond_the_cap_is_503_with_retry_after_and_the_cap_frees_as_bodies_end():
    """Two stalled uploads hold both places of GRADSEP_MAX_UPLOADS=2: a third body is refused at once (its bytes
    never read); a bodiless request is not an upload; once the stalled bodies end, uploads are taken again."""
    app = create_app(settings(max_uploads=2, body_timeout=1.0, warm_up=False))
    with uvicorn_server(app) as url, httpx.Client(base_url=url, timeout=30) as client:
        wait_ready(client)
        port = int(url.rsplit(":", 1)[1])
        stalled = []
        for _ in range(2):
            sock = socket.create_connection(("127.0.0.1", port), timeout=10)
            sock.sendall(b"POST /v1/reconstruct HTTP/1.1\r\nHost: t\r\nContent-Type: image/x-exr\r\n"
                         b"Content-Length: 1000\r\n\r\n" + bytes(10))
            stalled.append(sock)
        deadline = time.monotonic() + 10
        while app.state.engine.gate is None or _open_uploads(app) < 2:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        refused = chunked_upload(port, 1 << 20, chunk=1 << 16, timeout=10)
        assert (refused.status, refused.code) == (503, "uploads_full") and int(refused.retry_after) >= 1
        assert client.get("/v1/models").status_code == 200  # no body: not an upload
        for sock in stalled:  # the body timeout (408) ends both
            assert sock.recv(65536).startswith(b"HTTP/1.1 408")
            sock.close()
        assert post(client, frame_bytes(seed=5), {"method": "l2"}).status_code == 200
        assert 'gradsep_rejections_total{reason="uploads_full"} 1.0' in client.get("/metrics").text


def _open_uploads(app) -> int:
    """The cap's count, from the body-limit middleware in the app's built stack."""
    layer = app.middleware_stack
    while not hasattr(layer, "uploads"):
        layer = layer.app
    return layer.uploads.open


def test_bearer_token_guards_everything_but_health_readiness_and_the_docs(serve):
    with serve(create_app(settings(token="s3cret-token"))) as client:
        assert client.get("/healthz").status_code == 200
        assert client.get("/readyz").status_code == 200
        for path in ("/docs", "/docs/static/swagger-ui.css", "/openapi.json"):  # no secret in them (docs=open)
            assert client.get(path).status_code == 200, path
        for path in ("/v1/models", "/metrics", "/nothing", "/docsx", "/openapi.json/x"):
            response = client.get(path)
            assert_error(response, 401, "unauthorized")
            assert response.headers["www-authenticate"].startswith("Bearer")
        assert_error(post(client, b"garbage"), 401, "unauthorized")  # auth before the body is looked at
        assert_error(client.get("/v1/models", headers={"Authorization": "Bearer wrong"}), 401, "unauthorized")
        assert_error(client.get("/v1/models", headers={"Authorization": "Basic czNjcmV0LXRva2Vu"}),
                     401, "unauthorized")
        good = {"Authorization": "Bearer s3cret-token"}
        assert client.get("/v1/models", headers=good).status_code == 200
        assert post(client, frame_bytes(), headers=good).status_code == 200
        schema = client.get("/openapi.json", headers=good).json()
        assert schema["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
        assert schema["paths"]["/healthz"]["get"]["security"] == []
        assert 'reason="unauthorized"' in client.get("/metrics", headers=good).text



@TRANSPORT
def test_unknown_route_and_wrong_verb_are_json(poisson_api, transport):
    assert_error(poisson_api[transport].get("/v2/nothing"), 404, "not_found")
    response = poisson_api[transport].get("/v1/reconstruct")
    assert_error(response, 405, "method_not_allowed")
    assert response.headers["allow"] == "POST"

