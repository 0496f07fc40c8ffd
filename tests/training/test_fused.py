"""The fused method end to end on the tiny synthetic dataset: train with ``prior=oidn``, export, load from
``models/fused``, reconstruct -- and the cache holds exactly the normalised-exposure planes inference computes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("pyoidn")

from model.frame import read_frame  # noqa: E402
from model.infer import ModelError  # noqa: E402
from model.preprocess import FUSED_MEAN, layer_planes, prior_exposure  # noqa: E402
from model.reconstruct import load_fused, load_network, reconstruct  # noqa: E402
from training.dataset import build_cache, load_manifest  # noqa: E402
from training.export import export_run  # noqa: E402
from training.train import train  # noqa: E402

pytestmark = pytest.mark.train


@pytest.fixture(scope="module")
def fused_models(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from tests.training.conftest import tiny_config

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("fused")
    for layer in ("direct", "indirect"):
        cfg = tiny_config(tiny_dataset, root / f"run-{layer}", layer=layer, epochs=1, prior="oidn")
        train(cfg, quiet=True)
        export_run(cfg.output, root / "models" / "fused" / f"{layer}.onnx")
    return root / "models"


def test_oidn_cache_is_at_the_normalised_exposure(tiny_dataset: Path, tmp_path: Path) -> None:
    manifest = load_manifest(tiny_dataset)
    files, warnings = build_cache(manifest, "direct", tmp_path / "cache", prior="oidn")
    assert not warnings and all(f is not None for f in files)
    planes = np.load(files[0])
    assert planes[9:12].mean() == pytest.approx(FUSED_MEAN, rel=1e-3)  # the prior's mean, by construction of s
    frame = read_frame(manifest.frames[0].path, nonfinite="zero")
    raw = layer_planes(frame.layers["direct"])
    scale = planes[0:3].mean() / raw[0:3].mean()  # the base was scaled by the same s as the prior
    assert scale == pytest.approx(FUSED_MEAN / (planes[9:12].mean() / scale), rel=1e-3)
    l1_files, _ = build_cache(manifest, "direct", tmp_path / "cache-l1")
    assert not np.allclose(np.load(l1_files[0])[9:12], planes[9:12])  # the two priors differ


@pytest.mark.slow
@pytest.mark.train
def test_fused_models_load_only_as_fused_and_reconstruct(fused_models: Path, tiny_dataset: Path) -> None:
    fused = load_fused(fused_models)
    assert fused is not None and fused.layers == {"direct", "indirect"} and fused.needs_aux
    assert all(d["prior"] == "oidn" and d["metadata"]["gradsep.exposure"] == "prior-mean" for d in fused.describe())
    with pytest.raises(ModelError, match="different prior"):
        load_network(fused_models / "fused")  # a fused model in the network method's folder is refused
    frame = read_frame(load_manifest(tiny_dataset).frames[0].path, nonfinite="zero")
    assert reconstruct(frame, network=None, fused=fused).method == "oidn-l1"  # the default (model/policy.py)
    result = reconstruct(frame, "fused", fused=fused)
    assert result.method == "fused" and "features" in result.timings
    assert np.isfinite(result.image).all() and result.image.mean() > 0
    # energy: an (almost untrained) fused model stays close to its OIDN prior, which keeps the frame's mean
    base = sum(layer.base for layer in frame.layers.values())
    assert result.image.mean() == pytest.approx(base.mean(), rel=0.25)


@pytest.mark.slow
@pytest.mark.train
def test_fused_is_exposure_invariant(fused_models: Path, tiny_dataset: Path) -> None:
    """A frame at 1e-6 or 1e6 times the radiance comes back scaled by the same factor (no HDR clipping)."""
    fused = load_fused(fused_models)
    frame = read_frame(load_manifest(tiny_dataset).frames[1].path, nonfinite="zero")
    reference = reconstruct(frame, "fused", fused=fused).image
    for k in (1e-6, 1e6):
        scaled = read_frame(load_manifest(tiny_dataset).frames[1].path, nonfinite="zero")
        for layer in scaled.layers.values():
            for a in (layer.base, layer.dx, layer.dy):
                a *= np.float32(k)
        out = reconstruct(scaled, "fused", fused=fused).image / k
        assert np.abs(out - reference).max() <= 2e-3 * reference.max(), k
        assert prior_exposure(np.ones((2, 2, 3), np.float32) * k) == pytest.approx(FUSED_MEAN / k)
