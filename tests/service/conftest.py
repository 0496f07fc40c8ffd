"""Fixtures: apps with chosen settings, served through TestClient or a real uvicorn on 127.0.0.1."""

from __future__ import annotations

import signal
import socket
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import uvicorn
from fastapi import FastAPI

from gradsep.service.main import create_app
from gradsep.service.protocol import http_protocol
from gradsep.service.settings import Settings

with warnings.catch_warnings():  # Starlette 1.x nags about httpx in its TestClient; it still works
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

READY_TIMEOUT = 60.0

#: The same contract test through TestClient and through a real uvicorn (the ``poisson_api`` fixture's clients).
TRANSPORT = pytest.mark.parametrize("transport", ["testclient", "uvicorn"])


def settings(tmp_path: Path | None = None, **overrides: object) -> Settings:
    """Settings for a test app: no models (Poisson only) unless a test says otherwise, no env influence."""
    values: dict[str, object] = {"models_dir": Path("/nonexistent/gradsep-models"), "token": None}
    values.update(overrides)
    return Settings(**values)  # type: ignore[arg-type]


def wait_ready(client: httpx.Client, timeout: float = READY_TIMEOUT) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if client.get("/readyz").status_code == 200:
            return
        time.sleep(0.02)
    raise AssertionError(f"service not ready after {timeout} s: {client.get('/readyz').text}")


@contextmanager
def in_process(app: FastAPI, ready: bool = True) -> Iterator[httpx.Client]:
    with TestClient(app, raise_server_exceptions=False) as client:
        if ready:
            wait_ready(client)
        yield client


@contextmanager
def uvicorn_server(app: FastAPI, http: type | None = None) -> Iterator[str]:
    """Serve ``app`` with a real uvicorn in a thread on a free port; yield its base URL; stop gracefully.

    ``http`` is uvicorn's protocol class: by default the one ``gradsep serve`` runs (service.protocol)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    config = uvicorn.Config(app, log_level="warning", lifespan="on", timeout_graceful_shutdown=30,
                            http=http or http_protocol())
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + READY_TIMEOUT
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise AssertionError("uvicorn did not start")
        time.sleep(0.01)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=60)
        sock.close()


@contextmanager
def over_uvicorn(app: FastAPI, ready: bool = True) -> Iterator[httpx.Client]:
    with uvicorn_server(app) as url, httpx.Client(base_url=url, timeout=60) as client:
        if ready:
            wait_ready(client)
        yield client


TRANSPORTS: dict[str, Callable[..., object]] = {"testclient": in_process, "uvicorn": over_uvicorn}


@pytest.fixture(params=sorted(TRANSPORTS))
def serve(request: pytest.FixtureRequest) -> Callable[..., object]:
    """``with serve(app) as client:`` -- the same test through TestClient and through a real uvicorn."""
    return TRANSPORTS[request.param]


@pytest.fixture(scope="module")
def poisson_api() -> Iterator[dict[str, httpx.Client]]:
    """One default app per transport, shared by the read-only contract tests of a module (fast)."""
    with in_process(create_app(settings())) as tc, over_uvicorn(create_app(settings())) as lc:
        yield {"testclient": tc, "uvicorn": lc}


REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextmanager
def server_process(argv: list[str], env: dict[str, str], log_path: Path) -> Iterator[tuple[str, object]]:
    """Run a service command (``[..., "--port", "{port}"]``) in a subprocess; yield (url, Popen) once ready.

    Leaving the block sends SIGTERM (what an orchestrator does) and requires a clean exit: uvicorn shuts down
    gracefully and then re-raises the signal, so the status is "terminated by SIGTERM" (or 0).
    """
    import os
    import subprocess
    import sys

    port = free_port()
    full_env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
                "GRADSEP_MODELS": "/nonexistent/gradsep-models", **env}
    full_env.pop("GRADSEP_TOKEN", None)
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, *[a.format(port=port) for a in argv]], cwd=REPO, env=full_env,
                                stdout=log, stderr=subprocess.STDOUT)
        url = f"http://127.0.0.1:{port}"
        try:
            with httpx.Client(base_url=url, timeout=5) as client:
                deadline = time.monotonic() + READY_TIMEOUT
                while True:
                    assert proc.poll() is None, f"server exited: {log_path.read_text()[-2000:]}"
                    assert time.monotonic() < deadline, f"server not ready: {log_path.read_text()[-2000:]}"
                    try:
                        if client.get("/readyz").status_code == 200:
                            break
                    except httpx.TransportError:
                        pass
                    time.sleep(0.05)
            yield url, proc
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                code = proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                raise AssertionError("server did not stop within 60 s of SIGTERM") from None
    assert code in (0, -signal.SIGTERM), f"server exit status {code}: {log_path.read_text()[-2000:]}"


def rss_bytes(pid: int, field: str = "VmRSS") -> int:
    """Resident memory of a process from /proc (Linux): VmRSS now, or VmHWM for the peak."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"{field} not in /proc/{pid}/status")


def post(client, data: bytes, params: dict | None = None, content_type: str | None = "image/x-exr",
         headers: dict | None = None):
    headers = dict(headers or {})
    if content_type is not None:
        headers["Content-Type"] = content_type
    return client.post("/v1/reconstruct", params=params or {}, content=data, headers=headers)



def assert_error(response, status: int, code: str) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json")
    error = response.json()["error"]
    assert error["code"] == code, error
    assert error["message"]
    return error

