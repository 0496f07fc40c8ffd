"""`gradsep client 'shot.%04d.exr' --frames A-B -o 'out.%04d.exr' [--window N]` (service/client.py): each frame
posted with its window, against a scripted server (the parts sent, retries and exit statuses per frame) and against
the real service (the answers are reconstruct_window's)."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import numpy as np
import pytest

from gradsep.cli import main
from gradsep.model.exr_read import read_frame
from gradsep.model.temporal import reconstruct_window
from gradsep.service.client import EXIT_UNAVAILABLE
from gradsep.service.main import create_app
from tests.service.conftest import settings, uvicorn_server, wait_ready
from tests.service.frames import decode, rgb, window_frame_bytes
from tests.service.test_client import OK, json_error, scripted_server


@pytest.fixture
def shot(tmp_path: Path) -> Path:
    """Frames 1-3 of a still shot with motion vectors (frame 0 and 4 absent: the shot's ends)."""
    for n in (1, 2, 3):
        (tmp_path / f"shot.{n:04d}.exr").write_bytes(window_frame_bytes(n))
    return tmp_path


def parts(body: bytes) -> list[tuple[str, str, int]]:
    """(field, filename, content bytes) of each part of a recorded multipart body."""
    boundary = body.split(b"\r\n", 1)[0]
    out = []
    for chunk in body.split(boundary)[1:-1]:
        head, _, content = chunk.partition(b"\r\n\r\n")
        field, filename = re.search(rb'name="([^"]+)"; filename="([^"]+)"', head).groups()
        out.append((field.decode(), filename.decode(), len(content) - 2))  # less the CRLF before the boundary
    return out


def shot_argv(folder: Path, url: str, *more: str) -> list[str]:
    return ["client", str(folder / "shot.%04d.exr"), "-o", str(folder / "out.####.exr"), "--url", url, *more]


def test_each_frame_is_posted_with_its_window_nearest_first(shot):
    with scripted_server([OK]) as (url, seen):
        assert main(shot_argv(shot, url, "--frames", "1-3", "--window", "5", "--method", "l2")) == 0
    assert len(seen) == 3
    assert all(r["path"] == "/v1/reconstruct?method=l2" for r in seen)
    assert all(r["headers"]["Content-Type"].startswith("multipart/form-data; boundary=") for r in seen)
    size = len((shot / "shot.0001.exr").read_bytes())
    frame_1, frame_2, _ = (parts(r["body"]) for r in seen)
    # frame 1: t-1 is frame 0, absent (an empty part: the service reports it missing); nothing before frame 0
    assert [(f, n) for f, n, _ in frame_1] == [("frame", "shot.0001.exr"), ("previous", "shot.0000.exr"),
                                               ("next", "shot.0002.exr"), ("next", "shot.0003.exr")]
    assert [b for _, _, b in frame_1] == [size, 0, len((shot / "shot.0002.exr").read_bytes()),
                                          len((shot / "shot.0003.exr").read_bytes())]
    assert [(f, n) for f, n, _ in frame_2] == [("frame", "shot.0002.exr"), ("previous", "shot.0001.exr"),
                                               ("previous", "shot.0000.exr"), ("next", "shot.0003.exr"),
                                               ("next", "shot.0004.exr")]
    assert sorted(p.name for p in shot.glob("out.*")) == ["out.0001.exr", "out.0002.exr", "out.0003.exr"]


def test_a_frame_that_stays_unavailable_stops_the_shot_with_75_keeping_the_frames_written(shot, capsys):
    script = [OK, json_error(503, "queue_full", {"Retry-After": "0"})]
    with scripted_server(script) as (url, seen):
        assert main(shot_argv(shot, url, "--frames", "1-3", "--window", "3", "--retries", "1")) == EXIT_UNAVAILABLE
    assert len(seen) == 3  # frame 1, then frame 2 and its one retry; frame 3 never posted
    assert [p.name for p in shot.glob("out.*")] == ["out.0001.exr"]
    assert "frame 2 failed" in capsys.readouterr().err


def test_a_4xx_stops_the_shot_with_2(shot):
    with scripted_server([json_error(422, "window_mismatch")]) as (url, seen):
        assert main(shot_argv(shot, url, "--frames", "1-3")) == 2
    assert len(seen) == 1 and not list(shot.glob("out.*"))


@pytest.mark.parametrize("problem", ["missing-frame", "even-window", "window-without-frames", "no-field"])
def test_bad_shot_input_exits_2_before_any_request(shot, problem):
    with scripted_server([OK]) as (url, seen):
        argv = {"missing-frame": shot_argv(shot, url, "--frames", "1-4"),
                "even-window": shot_argv(shot, url, "--frames", "1-3", "--window", "4"),
                "window-without-frames": ["client", str(shot / "shot.0001.exr"), "-o", str(shot / "o.exr"),
                                          "--url", url, "--window", "3"],
                "no-field": ["client", str(shot / "shot.0001.exr"), "-o", str(shot / "o.exr"), "--url", url,
                             "--frames", "1-3"]}[problem]
        assert main(argv) == 2
    assert seen == []


def test_a_shot_against_the_real_service_is_reconstruct_window_of_each_frame(shot):
    with uvicorn_server(create_app(settings())) as url:
        with httpx.Client(base_url=url, timeout=60) as probe:
            wait_ready(probe)
        assert main(shot_argv(shot, url, "--frames", "1-3", "--window", "3", "--method", "l2")) == 0
    frames = {n: read_frame(shot / f"shot.{n:04d}.exr") for n in (1, 2, 3)}
    for n in (1, 2, 3):
        expected = reconstruct_window([frames.get(n - 1), frames[n], frames.get(n + 1)], 1, "l2")
        channels, attributes = decode((shot / f"out.{n:04d}.exr").read_bytes())
        np.testing.assert_array_equal(rgb(channels), expected.image)
        assert attributes["gradsep.temporal.offsets"] == {1: "+1", 2: "-1,+1", 3: "-1"}[n]
