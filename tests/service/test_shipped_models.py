"""The shipped models (models/direct.onnx, indirect.onnx, color.onnx) through the HTTP service (issue 15, item 7).

Every other service test points at a folder without models, so the default method of a real deployment, ONNX
inference, is exercised here: the contract (through TestClient and a real uvicorn) and a short load test against
`gradsep serve` in its own process. Runs in the serve-only venv too (numpy, OpenEXR, onnxruntime; no torch).
"""

from __future__ import annotations

import io
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import OpenEXR
import pytest

from gradsep.model.exr_read import read_frame
from gradsep.model.exr_write import encode_exr
from gradsep.model.frame import rgb_channels
from gradsep.model.metrics import relmse
from gradsep.service.main import create_app
from tests.service.conftest import REPO, rss_bytes, server_process, settings
from tests.service.frames import decode, frame_bytes, rgb

MODELS = REPO / "models"
EXAMPLE = REPO / "examples" / "cbox-16spp.exr"
REFERENCE = REPO / "examples" / "cbox-reference.exr"
pytestmark = pytest.mark.skipif(not all((MODELS / f"{n}.onnx").is_file() for n in ("direct", "indirect")),
                                reason="the shipped models are not in models/")


def _reference() -> np.ndarray:
    return np.asarray(OpenEXR.File(str(REFERENCE)).channels()["RGB"].pixels, np.float32)


def _post(client: httpx.Client, data: bytes, **params: str) -> httpx.Response:
    return client.post("/v1/reconstruct", params=params, content=data, headers={"Content-Type": "image/x-exr"})


def _scaled_example(k: float) -> bytes:
    channels = read_frame(EXAMPLE).to_channels()
    radiance = {n: v * np.float32(k) if not n.startswith(("albedo", "normal", "depth")) else v
                for n, v in channels.items()}
    return encode_exr(radiance)


@pytest.fixture(scope="module")
def example() -> bytes:
    return EXAMPLE.read_bytes()


def test_models_endpoint_lists_the_shipped_models_and_their_provider(serve):
    with serve(create_app(settings(models_dir=MODELS))) as client:
        info = client.get("/v1/models").json()
        assert "network" in info["methods"]  # the default follows model.policy (fused > oidn > network > l1)
        by_name = {m["name"]: m for m in info["models"]}
        assert {"direct", "indirect"} <= set(by_name)
        for model in by_name.values():
            assert model["provider"] in ("openvino", "cpu") and model["precision"] in ("bf16", "fp32")
            assert len(model["sha256"]) == 64 and model["provider_reason"]


def test_fused_lists_the_network_model_its_clean_layer_average_reads(serve):
    """fused's direct layer reads models/direct.onnx on clean layers (model/fused.py CLEAN_AVERAGE): /v1/models
    says so, with the same file and checksum the network method serves."""
    pytest.importorskip("pyoidn")
    with serve(create_app(settings(models_dir=MODELS))) as client:
        info = client.get("/v1/models").json()
        if "fused" not in info["methods"]:
            pytest.skip("no fused models in this checkout")
        second = [m for m in info["models"] if m["method"] == "fused" and "role" in m]
        assert [(m["name"], m["file"]) for m in second] == [("direct", "direct.onnx")]
        network = [m for m in info["models"] if m["method"] == "network" and m["name"] == "direct"]
        assert network and network[0]["sha256"] == second[0]["sha256"]


def test_network_beats_the_input_on_the_example(serve, example):
    reference = _reference()
    noisy = read_frame(EXAMPLE).combined().base
    with serve(create_app(settings(models_dir=MODELS))) as client:
        response = _post(client, example, layers="all", method="network")
        assert response.status_code == 200, response.text
        assert response.headers["x-reconstruction-method"] == "network"
        assert "direct" in response.headers["server-timing"] and "indirect" in response.headers["server-timing"]
        channels, attributes = decode(response.content)
        image = rgb(channels)
        assert attributes["gradsep.method"] == "network"
        assert np.isfinite(image).all() and image.min() >= 0
        np.testing.assert_allclose(rgb(channels, "direct") + rgb(channels, "indirect"), image, rtol=1e-5, atol=1e-6)
        assert relmse(image, reference) < 0.5 * relmse(noisy, reference)
        # the same request again gives the same bytes' worth of pixels (no state carried between requests)
        again = rgb(decode(_post(client, example, method="network").content)[0])
        np.testing.assert_array_equal(again, image)


@pytest.mark.parametrize("k", [1e4, 1e6, 1e9])
def test_network_over_http_keeps_the_energy_of_a_bright_frame(serve, example, k):
    """Before issue 15 the network clipped each layer at 65504: a 1e6 frame came back ~1e5x too dark."""
    with serve(create_app(settings(models_dir=MODELS))) as client:
        ordinary = rgb(decode(_post(client, example, method="network").content)[0])
        response = _post(client, _scaled_example(k), method="network")
        assert response.status_code == 200, response.text
        bright = rgb(decode(response.content)[0])
        assert np.isfinite(bright).all()
        ratio = float(bright.mean(dtype=np.float64)) / (k * float(ordinary.mean(dtype=np.float64)))
        assert abs(ratio - 1.0) < 0.02, ratio


def test_network_needs_features_and_says_so(serve):
    with serve(create_app(settings(models_dir=MODELS))) as client:
        no_features = frame_bytes(height=32, width=48)
        response = _post(client, no_features, method="network")
        assert response.status_code == 422, response.text
        assert "feature" in response.json()["error"]["message"]


def test_short_load_with_the_shipped_models(tmp_path: Path, example):
    """`gradsep serve` with the shipped models: 2 clients x 4 network requests on 2 inference slots, all 200
    and identical, the provider named in the log, and memory that does not grow from request to request."""
    env = {"GRADSEP_MODELS": str(MODELS), "GRADSEP_CONCURRENCY": "2", "GRADSEP_QUEUE_SIZE": "4",
           "GRADSEP_LOG_LEVEL": "info"}
    argv = ["-m", "gradsep", "serve", "--host", "127.0.0.1", "--port", "{port}"]
    with server_process(argv, env, tmp_path / "server.log") as (url, proc):
        with httpx.Client(base_url=url, timeout=120) as http:
            first = _post(http, example, method="network")
            assert first.status_code == 200, first.text
        expected = rgb(decode(first.content)[0])
        baseline = rss_bytes(proc.pid)

        def client(c: int) -> list[np.ndarray]:
            with httpx.Client(base_url=url, timeout=120) as http:
                out = []
                for _ in range(4):
                    r = _post(http, example, method="network")
                    assert r.status_code == 200, r.text
                    assert r.headers["x-reconstruction-method"] == "network"
                    out.append(rgb(decode(r.content)[0]))
                return out

        with ThreadPoolExecutor(2) as pool:
            results = [image for images in pool.map(client, range(2)) for image in images]
        grown = rss_bytes(proc.pid) - baseline
    assert len(results) == 8
    for image in results:
        np.testing.assert_array_equal(image, expected)
    assert grown < 200 * 1024 * 1024, f"RSS grew by {grown / 2**20:.0f} MiB over 8 small requests"
    log = (tmp_path / "server.log").read_text()
    assert re.search(r"model direct \(direct\.onnx\): (openvino|cpu) provider, (bf16|fp32)", log), log[-2000:]
    assert re.search(r"ready; methods .*network.*; network inference on (openvino|cpu)/(bf16|fp32)", log), log[-2000:]


def test_example_frame_round_trips_through_encode():  # guards the helper the bright-frame test relies on
    frame = read_frame(io.BytesIO(_scaled_example(1.0)))
    np.testing.assert_array_equal(frame.combined().base, read_frame(EXAMPLE).combined().base)
    assert set(rgb_channels("", frame.combined().base)) == {"R", "G", "B"}
