"""Queueing, timeouts, readiness and crash handling, made deterministic with a reconstruction that blocks."""

from __future__ import annotations

import dataclasses
import re
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import pytest

import gradsep.service.pipeline
from gradsep.model import methods as table
from gradsep.model.reconstruct import choose_method
from gradsep.service.main import create_app
from tests.service.conftest import settings, wait_ready
from tests.service.frames import decode, expected_sum, frame_bytes, rgb
from tests.service.test_contract import assert_error, post

REAL_RECONSTRUCT = gradsep.service.pipeline.reconstruct


class BlockingReconstruction:
    """Stands in for model.reconstruct: signals entry, waits for ``release``, then reconstructs for real."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Semaphore(0)
        self.calls = 0

    def __call__(self, frame, method, alpha, models=None):
        self.calls += 1
        self.entered.release()
        assert self.release.wait(60), "test never released the reconstruction"
        return REAL_RECONSTRUCT(frame, method, alpha, models)


@pytest.fixture
def blocker(monkeypatch) -> BlockingReconstruction:
    fake = BlockingReconstruction()
    monkeypatch.setattr(gradsep.service.pipeline, "reconstruct", fake)
    yield fake
    fake.release.set()  # never leave a worker thread hanging, whatever the test did


def metric(client, name: str) -> float:
    match = re.search(rf"^{name} ([0-9.e+-]+)$", client.get("/metrics").text, re.MULTILINE)
    assert match, name
    return float(match.group(1))


def wait_for(predicate, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.01)


def test_full_queue_is_503_with_retry_after_while_health_and_metrics_answer(serve, blocker):
    app = create_app(settings(concurrency=1, queue_size=1, warm_up=False))
    with serve(app) as client, ThreadPoolExecutor(2) as pool:
        running = pool.submit(post, client, frame_bytes(seed=1), {"method": "l2"})
        assert blocker.entered.acquire(timeout=30)
        queued = pool.submit(post, client, frame_bytes(seed=2), {"method": "l2"})
        wait_for(lambda: metric(client, "gradsep_inference_queue_waiting") == 1.0)
        assert metric(client, "gradsep_inference_running") == 1.0
        assert metric(client, "gradsep_http_requests_in_flight") == 3.0  # two posts + this scrape

        rejected = post(client, frame_bytes(seed=3), {"method": "l2"})
        error = assert_error(rejected, 503, "queue_full")
        assert int(rejected.headers["retry-after"]) >= 1
        assert error["details"] == {"running": 1, "waiting": 1, "queue_size": 1}
        assert client.get("/healthz").status_code == 200
        assert client.get("/readyz").status_code == 200

        blocker.release.set()
        for future, seed in ((running, 1), (queued, 2)):
            response = future.result(timeout=60)
            assert response.status_code == 200, response.text
            np.testing.assert_allclose(rgb(decode(response.content)[0]), expected_sum(seed=seed), rtol=1e-4,
                                       atol=1e-4)
        assert 'gradsep_rejections_total{reason="queue_full"} 1.0' in client.get("/metrics").text


def test_timeout_is_504_and_the_abandoned_thread_keeps_its_slot(serve, blocker):
    # 2 s: the blocked request times out whatever the timeout (it waits for the release), and the last request's
    # real reconstruction must fit in it on a loaded 2-core machine (0.5 s did not, under a parallel test run)
    app = create_app(settings(concurrency=1, queue_size=0, inference_timeout=2.0, warm_up=False))
    with serve(app) as client:
        error = assert_error(post(client, frame_bytes(seed=4)), 504, "timeout")
        assert error["details"] == {"timeout_seconds": 2.0, "started": True}
        # The thread cannot be killed: it still holds the only slot, so the next request is shed, not run beside it.
        assert metric(client, "gradsep_inference_running") == 1.0
        assert_error(post(client, frame_bytes(seed=5)), 503, "queue_full")
        blocker.release.set()
        wait_for(lambda: metric(client, "gradsep_inference_running") == 0.0)
        assert post(client, frame_bytes(seed=6)).status_code == 200
        assert blocker.calls == 2


def test_a_request_that_times_out_while_queued_never_runs(serve, blocker):
    app = create_app(settings(concurrency=1, queue_size=1, inference_timeout=1.0, warm_up=False))
    with serve(app) as client, ThreadPoolExecutor(1) as pool:
        first = pool.submit(post, client, frame_bytes(seed=7))
        assert blocker.entered.acquire(timeout=30)
        error = assert_error(post(client, frame_bytes(seed=8)), 504, "timeout")
        assert error["details"]["started"] is False
        assert_error(first.result(timeout=30), 504, "timeout")
        blocker.release.set()
        wait_for(lambda: metric(client, "gradsep_inference_running") == 0.0)
        assert blocker.calls == 1


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
    """What service.inference expects of model.infer.NetworkReconstructor once loaded."""

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
