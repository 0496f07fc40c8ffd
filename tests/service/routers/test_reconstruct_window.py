"""``POST /v1/reconstruct`` with a temporal window (service/window.py): frame t in ``frame``, its neighbours in
``previous`` / ``next`` parts, nearest first. Tiny still shots with motion vectors and consistent gradients, the
l2 method: no model is needed (the serve-only venv runs these)."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model.exr_read import read_frame
from gradsep.model.temporal import reconstruct_window
from gradsep.service.main import create_app
from gradsep.service.window import MAX_NEIGHBOURS, FirstPart
from tests.service.conftest import TRANSPORT, assert_error, in_process, settings
from tests.service.frames import decode, rgb, window_frame_bytes

SHOT = [window_frame_bytes(seed) for seed in range(5)]  # frames t-2 .. t+2 of a still shot


def window_files(frame: bytes, previous: list[bytes] = (), following: list[bytes] = ()) -> list[tuple]:
    """The multipart files of a window request: frame t, then its neighbours nearest first."""
    return [("frame", ("t.exr", frame, "image/x-exr")),
            *(("previous", (f"p{i}.exr", data, "image/x-exr")) for i, data in enumerate(previous, 1)),
            *(("next", (f"n{i}.exr", data, "image/x-exr")) for i, data in enumerate(following, 1))]


def post_window(client, frame: bytes, previous: list[bytes] = (), following: list[bytes] = (),
                method: str = "l2"):
    return client.post(f"/v1/reconstruct?method={method}", files=window_files(frame, previous, following))


@pytest.fixture(scope="module")
def api():
    with in_process(create_app(settings())) as client:
        yield client


# ------------------------------------------------------------------------------------------------------ 200


@TRANSPORT
def test_the_answer_is_frame_t_reconstructed_from_its_window(poisson_api, transport):
    response = post_window(poisson_api[transport], SHOT[2], [SHOT[1], SHOT[0]], [SHOT[3], SHOT[4]])
    assert response.status_code == 200, response.text
    assert response.headers["x-gradsep-neighbours"] == "-2,-1,+1,+2"
    assert "x-gradsep-warnings" not in response.headers
    expected = reconstruct_window([read_frame(data) for data in SHOT], 2, "l2")
    channels, attributes = decode(response.content)
    np.testing.assert_array_equal(rgb(channels), expected.image)
    assert attributes["gradsep.temporal.offsets"] == "-2,-1,+1,+2"
    alone = rgb(decode(post_window(poisson_api[transport], SHOT[2]).content)[0])
    assert not np.array_equal(alone, expected.image)  # the neighbours changed the answer


def test_a_single_frame_request_is_answered_as_before_without_the_neighbours_header(api):
    response = post_window(api, SHOT[2])
    assert response.status_code == 200, response.text
    assert "x-gradsep-neighbours" not in response.headers
    np.testing.assert_array_equal(rgb(decode(response.content)[0]),
                                  reconstruct_window([read_frame(SHOT[2])], 0, "l2").image)


def test_an_empty_part_is_a_missing_neighbour_and_the_answer_says_so(api):
    response = post_window(api, SHOT[2], [b"", SHOT[0]], [SHOT[3]])
    assert response.status_code == 200, response.text
    assert "-1" not in response.headers["x-gradsep-neighbours"].split(",")
    assert "+1" in response.headers["x-gradsep-neighbours"].split(",")
    assert "neighbour(s) -1 missing" in response.headers["x-gradsep-warnings"]
    expected = reconstruct_window([read_frame(SHOT[0]), None, read_frame(SHOT[2]), read_frame(SHOT[3])], 2, "l2")
    np.testing.assert_array_equal(rgb(decode(response.content)[0]), expected.image)


def test_a_neighbour_that_changed_is_rejected_and_the_answer_says_so(api):
    brighter = window_frame_bytes(9, scale=3.0)  # a light switched up: far outside the noise
    response = post_window(api, SHOT[2], [SHOT[1]], [brighter])
    assert response.status_code == 200, response.text
    assert response.headers["x-gradsep-neighbours"] == "-1"
    assert "neighbour(s) +1 rejected" in response.headers["x-gradsep-warnings"]


def test_a_frame_without_motion_vectors_is_reconstructed_alone_and_says_so(api):
    still = window_frame_bytes(2, motion=False)
    response = post_window(api, still, [window_frame_bytes(1, motion=False)])
    assert response.status_code == 200, response.text
    assert response.headers["x-gradsep-neighbours"] == "none"
    assert "no motion vectors" in response.headers["x-gradsep-warnings"]


def test_neighbours_of_one_shot_or_without_a_shot_name_are_accepted(api):
    ours = window_frame_bytes(2, metadata={"gradsep.shot": "sh010"})
    response = post_window(api, ours, [window_frame_bytes(1, metadata={"gradsep.shot": "sh010"})], [SHOT[3]])
    assert response.status_code == 200, response.text


# ------------------------------------------------------------------------------------------------------ 422


@pytest.mark.parametrize("case", ["size", "layout", "shot"])
def test_a_neighbour_of_another_size_layout_or_shot_is_422_naming_the_part(api, case):
    other = {"size": window_frame_bytes(3, height=12),
             "layout": window_frame_bytes(3, layers=("direct", "indirect")),
             "shot": window_frame_bytes(3, metadata={"gradsep.shot": "sh020"})}[case]
    frame = window_frame_bytes(2, metadata={"gradsep.shot": "sh010"}) if case == "shot" else SHOT[2]
    error = assert_error(post_window(api, frame, [SHOT[1]], [SHOT[3], other]), 422, "window_mismatch")
    assert "next #2" in error["message"]
    assert {k: error["details"][k] for k in ("part", "index", "offset")} == {"part": "next", "index": 2, "offset": 2}
    if case == "shot":
        assert "sh020" in error["message"] and "sh010" in error["message"]


def test_a_neighbour_without_one_side_of_motion_vectors_is_the_same_layout(api):
    data = window_frame_bytes(1, motion=False)  # the layout check leaves motion vectors out
    assert post_window(api, SHOT[2], [data]).status_code == 200


# ------------------------------------------------------------------------------------------------------ 400


@pytest.mark.parametrize("damage", ["truncated", "not-exr"])
def test_a_neighbour_that_does_not_decode_is_400_naming_the_part(api, damage):
    bad = SHOT[1][:len(SHOT[1]) * 2 // 3] if damage == "truncated" else b"not an exr at all"
    response = post_window(api, SHOT[2], [SHOT[1], bad], [SHOT[3]])
    assert response.status_code == 400, response.text
    error = response.json()["error"]
    assert "previous #2" in error["message"]
    assert (error["details"]["part"], error["details"]["offset"]) == ("previous", -2)


def test_malformed_window_parts_are_400(api):
    text = api.post("/v1/reconstruct?method=l2", files=window_files(SHOT[2]), data={"next": "frame.0003.exr"})
    assert "next" in assert_error(text, 400, "bad_request")["message"]
    many = post_window(api, SHOT[2], [SHOT[1]] * (MAX_NEIGHBOURS + 1))
    assert assert_error(many, 400, "too_many_neighbours")["details"]["max_neighbours"] == MAX_NEIGHBOURS
    two = api.post("/v1/reconstruct?method=l2", files=[*window_files(SHOT[2]), ("frame", ("x", SHOT[1]))])
    assert "more than one" in assert_error(two, 400, "missing_frame")["message"]


# ------------------------------------------------------------------------------------------------------ 413


def _multipart(files: list[tuple]) -> tuple[bytes, str]:
    import httpx

    request = httpx.Request("POST", "http://x/v1/reconstruct", files=files)
    return request.read(), request.headers["content-type"]


def test_a_window_over_the_body_limit_is_413_saying_how_many_frames_fit(serve):
    body, content_type = _multipart(window_files(SHOT[2], [SHOT[1], SHOT[0]], [SHOT[3], SHOT[4]]))
    per_frame = len(body) // 5  # the parts are nearly the same size
    limit = int(per_frame * 2.5)
    with serve(create_app(settings(max_body_bytes=limit))) as client:
        declared = assert_error(client.post("/v1/reconstruct?method=l2", content=body,
                                            headers={"Content-Type": content_type}), 413, "body_too_large")

        def chunks():  # no Content-Length: counted while streaming
            for i in range(0, len(body), 1000):
                yield body[i:i + 1000]

        streamed = assert_error(client.post("/v1/reconstruct?method=l2", content=chunks(),
                                            headers={"Content-Type": content_type}), 413, "body_too_large")
        for error in (declared, streamed):
            assert error["details"]["frames_fit"] == 2, error
            assert abs(error["details"]["frame_bytes"] - per_frame) < per_frame // 10
            assert "2 frame(s)" in error["message"]
        assert post_window(client, SHOT[2], [SHOT[1]]).status_code == 200  # two frames fit, and are served


def test_a_first_part_alone_over_the_limit_fits_no_frame(serve):
    body, content_type = _multipart(window_files(SHOT[2], [SHOT[1]]))
    with serve(create_app(settings(max_body_bytes=len(SHOT[2]) // 2))) as client:
        error = assert_error(client.post("/v1/reconstruct", content=body, headers={"Content-Type": content_type}),
                             413, "body_too_large")
        assert error["details"]["frames_fit"] == 0


def test_the_first_part_is_found_across_chunk_boundaries():
    body, content_type = _multipart(window_files(SHOT[2], [SHOT[1]]))
    boundary = content_type.split("boundary=", 1)[1].encode()
    whole = FirstPart(boundary)
    whole.feed(body)
    for step in (1, 7, len(boundary) + 1):
        split = FirstPart(boundary)
        for i in range(0, len(body), step):
            split.feed(body[i:i + step])
        assert split.size == whole.size
    assert whole.size == body.index(b"--" + boundary, 10) - body.index(b"--" + boundary)


def test_neighbours_are_held_in_memory_only_up_to_their_small_head(monkeypatch):
    """The frame part keeps Starlette's in-memory head; each neighbour part moves to disk past a smaller one, so a
    window request holds about what a single frame's does (docs/service.md, request bodies and memory)."""
    import asyncio

    from starlette.requests import Request

    from gradsep.service.routers import reconstruct as router

    big = window_frame_bytes(1, height=64, width=64)
    assert router.NEIGHBOUR_HEAD_BYTES < len(big) < router.FRAME_HEAD_BYTES
    body, content_type = _multipart(window_files(big, [big], [big]))

    async def form():
        chunks = [body[i:i + 4096] for i in range(0, len(body), 4096)]

        async def receive():
            return {"type": "http.request", "body": chunks.pop(0) if chunks else b"", "more_body": bool(chunks)}

        scope = {"type": "http", "method": "POST", "headers": [(b"content-type", content_type.encode())]}
        return await router._parse_form(Request(scope, receive))

    parsed = asyncio.run(form())
    try:
        rolled = {name: value.file._rolled for name, value in parsed.multi_items()}  # SpooledTemporaryFile
        assert rolled == {"frame": False, "previous": True, "next": True}
    finally:
        asyncio.run(parsed.close())
