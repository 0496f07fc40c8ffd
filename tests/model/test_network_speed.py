"""Issue 15, the ``network`` method's latency: its two layers run concurrently (one layer's single-threaded prior
solve beside the other's) with at most one ONNX graph at a time, bit-for-bit the sequential result; and the prior the
models are served with is the one they were trained and exported with (benchmarks/study_prior.py found no cheaper
budget that keeps the held-out error, docs/network.md).

Uses the shipped models (numpy + onnxruntime only); small frames, so it is fast.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

import gradsep.model.preprocess as preprocess
from gradsep.model import methods as table
from gradsep.model.frame import Features, Frame, Layer
from gradsep.model.reconstruct import reconstruct

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "models"

needs_models = pytest.mark.skipif(not (MODELS / "direct.onnx").is_file() or not (MODELS / "indirect.onnx").is_file(),
                                  reason="the shipped models are not in models/")


def _frame(h: int = 48, w: int = 64, seed: int = 3) -> Frame:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    layers = {}
    for k, name in enumerate(("direct", "indirect")):
        clean = np.stack([(1 + k) * (0.5 + 0.4 * np.sin(xx / (7 + c) + yy / 11)) for c in range(3)], -1)
        base = (clean * rng.gamma(4.0, 0.25, clean.shape)).astype(np.float32)
        dx = np.zeros_like(clean)
        dy = np.zeros_like(clean)
        dx[:, :-1] = clean[:, 1:] - clean[:, :-1]
        dy[:-1] = clean[1:] - clean[:-1]
        layers[name] = Layer(base, (dx + rng.normal(0, 0.02, dx.shape)).astype(np.float32) * (xx < w - 1)[..., None],
                             (dy + rng.normal(0, 0.02, dy.shape)).astype(np.float32) * (yy < h - 1)[..., None])
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1.0
    features = Features(np.full((h, w, 3), 0.6, np.float32), normal, (1.0 + yy / h).astype(np.float32))
    return Frame(layers, features)


@pytest.fixture(scope="module")
def network():
    from gradsep.model.infer import NetworkReconstructor

    if not (MODELS / "direct.onnx").is_file():
        pytest.skip("the shipped models are not in models/")
    return NetworkReconstructor.load(MODELS)


@needs_models
def test_concurrent_network_layers_equal_sequential_and_never_overlap_graphs(network, monkeypatch) -> None:
    frame = _frame()
    monkeypatch.setenv("GRADSEP_LAYER_THREADS", "1")
    sequential = reconstruct(frame, "network", models=table.LoadedModels(network=network))
    running, peak, threads = [0], [0], set()
    guard = threading.Lock()
    originals = {name: m.run for name, m in network.models.items()}

    def recording(run):
        def wrapped(data, gradient):
            with guard:
                running[0] += 1
                peak[0] = max(peak[0], running[0])
                threads.add(threading.current_thread().name)
            try:
                return run(data, gradient)
            finally:
                with guard:
                    running[0] -= 1
        return wrapped

    for name, m in network.models.items():
        monkeypatch.setattr(m, "run", recording(originals[name]))
    monkeypatch.setenv("GRADSEP_LAYER_THREADS", "2")
    concurrent = reconstruct(frame, "network", models=table.LoadedModels(network=network))
    assert threads and all(t.startswith("gradsep-layer") for t in threads)  # the layers ran in workers
    assert peak[0] == 1  # the graph lock: one ONNX graph at a time
    for name in sequential.layers:
        np.testing.assert_array_equal(concurrent.layers[name], sequential.layers[name])
    np.testing.assert_array_equal(concurrent.image, sequential.image)


def test_the_prior_is_solved_with_the_pinned_budget(monkeypatch) -> None:
    seen: dict = {}

    def spy(base, dx, dy, alpha, options):
        seen.update(alpha=alpha, options=options)
        return np.zeros_like(base), None

    monkeypatch.setattr(preprocess, "solve_l1", spy)
    preprocess.poisson_prior(_frame(16, 16).layers["direct"])
    options = seen["options"]
    assert seen["alpha"] == preprocess.PRIOR_ALPHA and (
        options.iterations, options.cg_iterations, options.reg_init, options.reg_decay, options.cg_tolerance,
        options.preconditioner) == (
        preprocess.PRIOR_IRLS_PASSES, preprocess.PRIOR_CG_STEPS, preprocess.PRIOR_REG_INIT,
        preprocess.PRIOR_REG_DECAY, preprocess.PRIOR_CG_TOLERANCE, preprocess.PRIOR_PRECONDITIONER)


@needs_models
def test_the_served_prior_is_the_one_the_shipped_models_were_exported_with(network) -> None:
    """Changing the inference prior without retraining and re-exporting changes what the models see: the
    metadata each loaded model carries (and /v1/models reports) must describe the prior this code solves (``l1``,
    the kind a model without ``gradsep.prior`` refines)."""
    assert (f"{preprocess.PRIOR_IRLS_PASSES} passes x {preprocess.PRIOR_CG_STEPS} CG steps"
            in preprocess.describe_preprocessing()["prior"])
    for entry in network.describe():
        exported = json.loads(entry["metadata"]["gradsep.preprocessing"])
        assert entry["prior"] == "l1" and exported["prior"] == preprocess.describe_prior(), entry["name"]
        assert exported["version"] == preprocess.PREPROCESS_VERSION
