"""The engine (service/engine.py): readiness while models load or after they fail, the model sets it serves and
the default method the table picks among them."""

from __future__ import annotations

import dataclasses
import threading
from types import SimpleNamespace

import numpy as np
import pytest

import gradsep.service.pipeline
from gradsep.model import methods as table
from gradsep.model.reconstruct import choose_method
from gradsep.service.main import create_app
from tests.service.conftest import assert_error, post, settings, wait_ready
from tests.service.frames import frame_bytes
from tests.service.test_gate import REAL_RECONSTRUCT, metric, wait_for


def test_not_ready_while_models_load_but_alive(serve, monkeypatch):
    loaded = threading.Event()

    def slow_load(models_dir):
        assert loaded.wait(60)
        return None

    monkeypatch.setattr("gradsep.model.reconstruct.load_network", slow_load)
    with serve(create_app(settings()), ready=False) as client:
        try:
            assert client.get("/healthz").status_code == 200
            response = client.get("/readyz")
            assert_error(response, 503, "not_ready")
            assert response.headers["retry-after"] == "1"
            assert_error(post(client, frame_bytes()), 503, "not_ready")
            assert client.get("/v1/models").json()["state"] == "loading"
            assert metric(client, "gradsep_ready") == 0.0
        finally:
            loaded.set()
        wait_ready(client)
        assert post(client, frame_bytes()).status_code == 200


def test_broken_models_keep_liveness_but_never_ready(serve, monkeypatch):
    def broken(models_dir):
        raise RuntimeError("model.onnx: protobuf parsing failed")

    monkeypatch.setattr("gradsep.model.reconstruct.load_network", broken)
    with serve(create_app(settings()), ready=False) as client:
        wait_for(lambda: client.get("/readyz").json()["error"]["code"] == "models_failed")
        assert "protobuf parsing failed" in client.get("/readyz").json()["error"]["message"]
        assert client.get("/healthz").status_code == 200
        assert_error(post(client, frame_bytes()), 503, "models_failed")


class FakeNetwork:
    """What service.engine expects of model.infer.NetworkReconstructor once loaded."""

    layers = frozenset({"direct", "indirect"})

    def __init__(self) -> None:
        self.warmed = 0

    def describe(self):
        return [{"name": "direct", "layers": ["direct"], "input_channels": 19, "sha256": "ab" * 32,
                 "export": {"opset": 17}}]

    def warm_up(self):
        self.warmed += 1


def test_loaded_network_becomes_the_default_method_without_oidn(serve, monkeypatch):
    network = FakeNetwork()
    monkeypatch.setattr("gradsep.model.reconstruct.load_network", lambda models_dir: network)
    monkeypatch.setattr("gradsep.model.oidn.available", lambda: False)  # a replica without pyoidn

    def reconstruct(frame, method, alpha, models=None):
        method = method or choose_method(frame, models)
        if method != "network" or not set(frame.layers) <= network.layers:  # the real one refuses those
            return REAL_RECONSTRUCT(frame, method, alpha, models)
        assert models.get("network") is network
        image = sum(layer.base for layer in frame.layers.values())
        return SimpleNamespace(image=image, layers={k: v.base for k, v in frame.layers.items()},
                               timings=dict.fromkeys(frame.layers, 0.001), method="network")

    monkeypatch.setattr(gradsep.service.pipeline, "reconstruct", reconstruct)
    with serve(create_app(settings())) as client:
        assert network.warmed == 1
        ready = client.get("/readyz").json()
        assert ready["methods"] == ["network", "l1", "l2"] and ready["default_method"] == "network"
        assert ready["default_method_plain"] is None  # no method for a plain frame on this replica
        assert client.get("/v1/models").json()["models"] == [{**m, "method": "network"} for m in network.describe()]
        response = post(client, frame_bytes(seed=9, features=True))
        assert response.status_code == 200
        assert response.headers["x-reconstruction-method"] == "network"
        explicit = post(client, frame_bytes(seed=9, features=True), {"method": "l2"})
        assert explicit.headers["x-reconstruction-method"] == "l2"
        # the default falls back to l1 for a frame the models do not serve (no model for `color`)
        assert post(client, frame_bytes(("color",), seed=9, features=True)).headers["x-reconstruction-method"] == "l1"
        unserved = post(client, frame_bytes(("color",), seed=9, features=True), {"method": "network"})
        assert unserved.status_code == 422 and "color" in unserved.json()["error"]["message"]


def test_fused_models_are_served_and_the_policy_order_picks_the_default(serve, monkeypatch):
    fused = FakeNetwork()
    monkeypatch.setattr("gradsep.model.reconstruct.load_fused", lambda models_dir: fused)
    calls: list[str] = []

    def reconstruct(frame, method, alpha, models=None):
        method = method or choose_method(frame, models)
        calls.append(method)
        if method != "fused":
            return REAL_RECONSTRUCT(frame, method, alpha, models)
        image = sum(layer.base for layer in frame.layers.values())
        return SimpleNamespace(image=image, layers={k: v.base for k, v in frame.layers.items()},
                               timings=dict.fromkeys(frame.layers, 0.001), method="fused")

    monkeypatch.setattr(gradsep.service.pipeline, "reconstruct", reconstruct)
    with serve(create_app(settings(warm_up=False))) as client:
        ready = client.get("/readyz").json()
        assert ready["methods"] == ["l1", "l2", "oidn", "oidn-l1", "fused"]
        assert ready["default_method"] == "oidn-l1" and ready["default_method_plain"] == "oidn"  # model/methods.py
        models = client.get("/v1/models").json()
        assert models["default_method"] == "oidn-l1" and models["models"][0]["method"] == "fused"
        assert post(client, frame_bytes(seed=9, features=True)).headers["x-reconstruction-method"] == "oidn-l1"
        assert post(client, frame_bytes(seed=9, features=True), {"method": "fused"}).headers[
            "x-reconstruction-method"] == "fused"
        with table.registered(dataclasses.replace(table.get("fused"), preference=0)):
            assert client.get("/readyz").json()["default_method"] == "fused"  # one field of the table changes it
            assert post(client, frame_bytes(seed=9, features=True)).headers["x-reconstruction-method"] == "fused"
        plain = post(client, frame_bytes(seed=9, features=True, gradients=False))
        assert plain.status_code == 200 and plain.headers["x-reconstruction-method"] == "oidn"
        refused = post(client, frame_bytes(seed=9, features=True, gradients=False), {"method": "l1"})
        assert refused.status_code == 422 and "gradients" in refused.json()["error"]["message"]


def test_exr_thread_pool_changes_no_pixel() -> None:
    """GRADSEP_EXR_THREADS: OpenEXR's pool (de)compresses line blocks in parallel; bytes and pixels are the same."""
    import OpenEXR

    from gradsep.model.exr_read import read_frame
    from gradsep.model.exr_write import configure_exr_threads, encode_exr

    data = frame_bytes(("direct", "indirect"), height=70, width=90)
    image = {"R": np.random.default_rng(0).random((70, 90), dtype=np.float32)}
    before = OpenEXR.global_thread_count()
    try:
        configure_exr_threads(0)
        serial, encoded = read_frame(data), encode_exr(image)
        assert configure_exr_threads(-1) >= 1 and OpenEXR.global_thread_count() >= 1
        threaded = read_frame(data)
        assert encode_exr(image) == encoded
        for name, layer in serial.layers.items():
            for part in ("base", "dx", "dy"):
                np.testing.assert_array_equal(getattr(layer, part), getattr(threaded.layers[name], part))
    finally:
        OpenEXR.set_global_thread_count(before)



def test_warm_up_runs_the_temporal_warp_so_a_first_window_request_compiles_nothing(serve, monkeypatch):
    """The warm-up reconstructs a window with subpixel motion: the compiled bilinear warp runs (and compiles, where
    numba has no cache) before /readyz answers 200, not inside the first window request."""
    from gradsep.model import kernels

    if not kernels.AVAILABLE:
        pytest.skip("numba unavailable: the warp runs in numpy, nothing to compile")
    calls: list[tuple[int, ...]] = []
    real = kernels.bilinear

    def spy(flat, *rest):
        calls.append(flat.shape)
        return real(flat, *rest)

    monkeypatch.setattr(kernels, "bilinear", spy)
    with serve(create_app(settings(warm_up=True))) as client:
        wait_ready(client)
    assert calls, "the warm-up did not warp a neighbour"
