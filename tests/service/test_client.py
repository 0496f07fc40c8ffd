"""`gradsep client`: retries, never retrying 4xx, atomic writes, exit codes -- against a scripted HTTP server
and against the real service."""

from __future__ import annotations

import argparse
import json
import random
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import httpx
import numpy as np
import pytest

from gradsep.cli import main
from gradsep.model.errors import CommandError
from gradsep.service.client import (
    EXIT_SERVER_ERROR,
    EXIT_UNAVAILABLE,
    RetryPolicy,
    backoff_delay,
    parse_retry_after,
)
from gradsep.service.commands import client_command
from gradsep.service.main import create_app
from tests.service.conftest import settings, uvicorn_server, wait_ready
from tests.service.frames import decode, expected_sum, frame_bytes, rgb

EXR_BODY = frame_bytes(("color",), height=4, width=4)


def json_error(status: int, code: str, headers: dict | None = None) -> tuple[int, dict, bytes]:
    body = json.dumps({"error": {"code": code, "message": f"scripted {code}", "details": None}}).encode()
    return status, {"Content-Type": "application/json", **(headers or {})}, body


OK = (200, {"Content-Type": "image/x-exr", "X-Reconstruction-Method": "l1"}, EXR_BODY)


@contextmanager
def scripted_server(script: list[tuple[int, dict, bytes]]) -> Iterator[tuple[str, list[dict]]]:
    """An HTTP server answering POSTs from ``script`` in order (the last answer repeats); records requests."""
    seen: list[dict] = []

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 (http.server's naming)
            body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
            seen.append({"path": self.path, "headers": dict(self.headers), "body": body})
            status, headers, payload = script[min(len(seen), len(script)) - 1]
            self.send_response(status)
            for key, value in {**headers, "Content-Length": str(len(payload))}.items():
                self.send_header(key, value)
            self.end_headers()
            self.wfile.write(payload)

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", seen
    finally:
        server.shutdown()
        server.server_close()


def args_for(frame: Path, output: Path, url: str, **overrides: object) -> argparse.Namespace:
    values = {"frame": str(frame), "output": str(output), "url": url, "method": None, "alpha": None,
              "format": None, "layers": None, "retries": 5, "timeout": 30.0, "token": None}
    values.update(overrides)
    return argparse.Namespace(**values)


@pytest.fixture
def frame(tmp_path: Path) -> Path:
    path = tmp_path / "frame.exr"
    path.write_bytes(frame_bytes(seed=11))
    return path


def test_retries_503_honouring_retry_after_then_writes_the_answer(tmp_path, frame):
    script = [json_error(503, "queue_full", {"Retry-After": "2"}), json_error(503, "not_ready"), OK]
    sleeps: list[float] = []
    out = tmp_path / "out.exr"
    with scripted_server(script) as (url, seen):
        status = client_command(args_for(frame, out, url, method="l2", layers="all"), sleep=sleeps.append)
    assert status == 0
    assert out.read_bytes() == EXR_BODY
    assert len(seen) == 3
    assert 2.0 <= sleeps[0] <= 2.4  # Retry-After honoured, plus at most 20 % jitter
    assert 0.0 <= sleeps[1] <= 1.0  # no Retry-After: full-jitter backoff, ceiling 0.5 s * 2
    assert len({r["headers"]["X-Request-ID"] for r in seen}) == 1  # one id across retries
    assert all(r["body"] == frame.read_bytes() for r in seen)
    assert seen[0]["path"] == "/v1/reconstruct?method=l2&layers=all"
    assert seen[0]["headers"]["Content-Type"] == "image/x-exr"


@pytest.mark.parametrize("status, code", [(400, "not_exr"), (401, "unauthorized"), (413, "too_large"),
                                          (422, "bad_channels")])
def test_4xx_is_never_retried_and_exits_2_with_one_line(tmp_path, frame, capsys, status, code):
    out = tmp_path / "out.exr"
    with scripted_server([json_error(status, code), OK]) as (url, seen):
        assert main(["client", str(frame), "-o", str(out), "--url", url]) == 2
    assert len(seen) == 1
    assert not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    request_id = seen[0]["headers"]["X-Request-ID"]
    assert err[0].startswith("gradsep client: error:") and f"{status} {code}" in err[0] and request_id in err[0]


def test_unavailable_after_every_retry_exits_75_and_keeps_the_old_output(tmp_path, frame, capsys):
    out = tmp_path / "out.exr"
    out.write_bytes(b"previous result")
    with scripted_server([json_error(503, "queue_full", {"Retry-After": "0"})]) as (url, seen):
        assert main(["client", str(frame), "-o", str(out), "--url", url, "--retries", "2"]) == EXIT_UNAVAILABLE
    assert len(seen) == 3
    assert out.read_bytes() == b"previous result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.exr", "out.exr"]  # no temp leftovers
    lines = capsys.readouterr().err.strip().splitlines()
    request_id = seen[0]["headers"]["X-Request-ID"]
    assert all(request_id in line for line in lines)  # every log line carries the request id
    assert "gave up after 3 attempts" in lines[-1]


def test_connection_refused_is_retried_then_exits_75(tmp_path, frame):
    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    sleeps: list[float] = []
    status = client_command(args_for(frame, tmp_path / "o.exr", f"http://127.0.0.1:{port}", retries=3),
                            sleep=sleeps.append)
    assert status == EXIT_UNAVAILABLE
    assert len(sleeps) == 3
    assert not (tmp_path / "o.exr").exists()


def test_service_timeout_504_exits_75_without_retry(tmp_path, frame, capsys):
    """A 504 is the service's inference timeout: the exit table's 75 (retry the task later), not 1; no retry,
    since the abandoned job still runs on the service."""
    with scripted_server([json_error(504, "timeout"), OK]) as (url, seen):
        assert client_command(args_for(frame, tmp_path / "o.exr", url), sleep=lambda s: None) == EXIT_UNAVAILABLE
    assert len(seen) == 1
    assert not (tmp_path / "o.exr").exists()
    assert "504 timeout" in capsys.readouterr().err


@pytest.mark.parametrize("answer", [json_error(500, "internal"),
                                    (200, {"Content-Type": "text/html"}, b"<html>proxy login</html>")],
                         ids=["500", "200-not-exr"])
def test_server_failures_exit_1_without_retry(tmp_path, frame, answer):
    with scripted_server([answer, OK]) as (url, seen):
        assert client_command(args_for(frame, tmp_path / "o.exr", url), sleep=lambda s: None) == EXIT_SERVER_ERROR
    assert len(seen) == 1
    assert not (tmp_path / "o.exr").exists()


def _truncated(data: bytes) -> bytes:
    return data[: len(data) - 40]


def _corrupt_pixels(data: bytes) -> bytes:
    """The header intact, the last line block's compressed bytes garbled."""
    out = bytearray(data)
    out[-30:] = b"\x00" * 30
    return bytes(out)


@pytest.mark.parametrize("damage", [_truncated, _corrupt_pixels, lambda d: d[:12]], ids=["truncated", "garbled",
                                                                                         "header-cut"])
def test_an_answer_that_does_not_decode_exits_1_with_one_line_and_writes_nothing(tmp_path, frame, capsys,
                                                                                  damage):
    body = frame_bytes(("color",), height=32, width=32, seed=3)  # several line blocks, so a cut hits pixels
    answer = (200, {"Content-Type": "image/x-exr", "X-Reconstruction-Method": "l1"}, damage(body))
    (tmp_path / "o.exr").write_bytes(b"previous result")
    with scripted_server([answer, OK]) as (url, seen):
        code = client_command(args_for(frame, tmp_path / "o.exr", url), sleep=lambda s: None)
    assert code == EXIT_SERVER_ERROR and len(seen) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "does not decode" in lines[0], lines
    assert (tmp_path / "o.exr").read_bytes() == b"previous result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.exr", "o.exr"]


def test_url_and_token_come_from_the_environment(tmp_path, frame, monkeypatch):
    with scripted_server([OK]) as (url, seen):
        monkeypatch.setenv("GRADSEP_URL", url)
        monkeypatch.setenv("GRADSEP_TOKEN", "env-token")
        assert main(["client", str(frame), "-o", str(tmp_path / "o.exr")]) == 0
    assert seen[0]["headers"]["Authorization"] == "Bearer env-token"


@pytest.mark.parametrize("problem", ["missing-frame", "missing-folder", "bad-url", "negative-retries"])
def test_bad_local_input_exits_2_before_any_request(tmp_path, frame, problem):
    argv = {"missing-frame": [str(tmp_path / "nope.exr"), "-o", str(tmp_path / "o.exr")],
            "missing-folder": [str(frame), "-o", str(tmp_path / "no" / "o.exr")],
            "bad-url": [str(frame), "-o", str(tmp_path / "o.exr"), "--url", "ftp://x"],
            "negative-retries": [str(frame), "-o", str(tmp_path / "o.exr"), "--retries", "-1"]}[problem]
    with scripted_server([OK]) as (url, seen):
        if "--url" not in argv:
            argv += ["--url", url]
        assert main(["client", *argv]) == 2
    assert seen == []


def test_end_to_end_against_the_real_service_with_a_token(tmp_path, frame):
    out = tmp_path / "out.exr"
    with uvicorn_server(create_app(settings(token="farm-token"))) as url:
        with httpx.Client(base_url=url, timeout=60) as probe:  # warm-up (OIDN, numba kernels) can outlast
            wait_ready(probe)                                   # the client's retries on a loaded machine
        assert main(["client", str(frame), "-o", str(out), "--url", url, "--token", "farm-token",
                     "--method", "l2", "--layers", "all", "--format", "half"]) == 0
        with pytest.raises(CommandError, match="401 unauthorized"):
            client_command(args_for(frame, out, url, token="wrong"))
    channels, attributes = decode(out.read_bytes())
    assert channels["R"].dtype == np.float16 and "direct.R" in channels
    np.testing.assert_allclose(rgb(channels), expected_sum(seed=11), rtol=5e-3, atol=5e-3)
    assert attributes["gradsep.method"] == "l2"


def test_retry_after_parsing_and_backoff_bounds():
    assert parse_retry_after("7") == 7.0
    assert parse_retry_after("Wed, 21 Oct 2015 07:28:00 GMT", now=1445412470.0) == 10.0
    assert parse_retry_after("soon") is None and parse_retry_after(None) is None
    policy, rng = RetryPolicy(base_seconds=0.5, max_seconds=4.0, max_retry_after=60), random.Random(1)
    delays = [backoff_delay(attempt, policy, None, rng) for attempt in range(10) for _ in range(20)]
    assert max(delays) <= 4.0 and min(delays) >= 0.0
    assert 60.0 <= backoff_delay(0, policy, 3600.0, rng) <= 72.0  # a huge Retry-After is capped
