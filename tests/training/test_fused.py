"""The fused (blend) method end to end on a tiny synthetic Noise2Noise dataset: the training cache holds exactly
the candidates and network inputs inference computes; train, export, load from ``models/fused``, reconstruct;
exposure invariance; models of another prior kind refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("pyoidn")

from gradsep.model.exr_read import read_frame  # noqa: E402
from gradsep.model.fused import OIDN_SETTING, blend_inputs, layer_candidates  # noqa: E402
from gradsep.model.infer import ModelError  # noqa: E402
from gradsep.model.methods import LoadedModels  # noqa: E402
from gradsep.model.oidn import shared_denoiser  # noqa: E402
from gradsep.model.preprocess import FUSED_MEAN  # noqa: E402
from gradsep.model.reconstruct import load_fused, load_network, reconstruct  # noqa: E402
from gradsep.training import fused as fused_training  # noqa: E402
from gradsep.training.dataset import load_manifest  # noqa: E402
from tests.training.synthetic import make_synthetic_dataset  # noqa: E402

CACHED = fused_training.CANDIDATES  # the cache's candidates (oidn, refine-fast), in order
KINDS = ("oidn", "refine-fast")  # the test models' candidates

pytestmark = pytest.mark.train


@pytest.fixture(scope="module")
def paired(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_synthetic_dataset(tmp_path_factory.mktemp("pairs"), frames=4, width=64, height=48, pairs=True)


@pytest.fixture(scope="module")
def cache(paired: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cache")
    fused_training.build_cache(paired, out)
    return out


@pytest.fixture(scope="module")
def blend_models(cache: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("blend")
    for layer in ("direct", "indirect"):
        run = root / f"run-{layer}"
        fused_training.main(["train", "--cache", str(cache), "--layer", layer, "--candidates", ",".join(KINDS),
                             "--minutes", "0.03", "--patch", "32", "--batch", "2", "--width", "4", "--blocks", "1",
                             "-o", str(run)])
        fused_training.main(["export", str(run), "-o", str(root / "models" / "fused" / f"{layer}.onnx")])
    return root / "models"


def test_cache_holds_what_inference_computes(paired: Path, cache: Path) -> None:
    """Candidates, scaled planes and the network inputs of training equal inference's, bit for bit."""
    entry = load_manifest(paired).frames[1]
    frame = read_frame(entry.path, nonfinite="zero")
    planes = np.load(cache / "indirect" / f"{entry.index:05d}.npy")
    aux = shared_denoiser(OIDN_SETTING).prefilter(frame.features)
    scaled, cands, scale = layer_candidates(frame.layers["indirect"], aux, CACHED)
    for k in range(len(CACHED)):
        np.testing.assert_array_equal(planes[9 + 3 * k:12 + 3 * k], cands[k].transpose(2, 0, 1))
    np.testing.assert_array_equal(planes[0:3], scaled.base.transpose(2, 0, 1))
    assert cands[0].mean() == pytest.approx(FUSED_MEAN, rel=1e-3)  # the exposure normalises OIDN's image
    data, gradient = blend_inputs(scaled, cands, frame.features)
    t_data, t_grad, t_cands, target = fused_training.tensors(torch.from_numpy(planes)[None], CACHED, CACHED)
    np.testing.assert_allclose(t_data[0].numpy(), data, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(t_grad[0].numpy(), gradient, rtol=1e-6, atol=1e-6)
    other = read_frame(entry.target, nonfinite="zero").layers["indirect"].base  # the N2N target, scaled by s
    np.testing.assert_allclose(target[0].numpy(), (other * scale).transpose(2, 0, 1), rtol=1e-5, atol=1e-7)
    # a candidate subset is read from the same planes, in its order
    sub = fused_training.tensors(torch.from_numpy(planes)[None], ("refine-fast",), CACHED)[2]
    np.testing.assert_array_equal(sub[0, 0].numpy(), planes[12:15])
    assert planes.shape[0] == fused_training.cache_planes(len(CACHED))


def test_flip_augmentation_keeps_gradients_consistent() -> None:
    """A (possibly flipped) patch's dx are the forward differences of its base, exactly, where the patch has them."""
    rng = np.random.default_rng(0)
    planes = rng.uniform(0, 1, (fused_training.cache_planes(3), 40, 50)).astype(np.float32)
    base = planes[0:3]
    planes[3:6] = 0.0
    planes[3:6, :, :-1] = base[:, :, 1:] - base[:, :, :-1]  # the contract's dx: last column 0
    flips = 0
    for seed in range(12):
        crop = fused_training.sample([planes], 1, 16, np.random.default_rng(seed))[0].numpy()
        np.testing.assert_allclose(crop[3:6, :, :-1], crop[0:3, :, 1:] - crop[0:3, :, :-1], atol=1e-6)
        flips += not any(np.array_equal(crop[0], planes[0, y:y + 16, x:x + 16]) for y in range(25) for x in range(35))
    assert 0 < flips < 12  # both branches ran


@pytest.mark.slow
def test_blend_models_load_reconstruct_and_are_exposure_invariant(blend_models: Path, paired: Path) -> None:
    fused = load_fused(blend_models)
    assert fused is not None and fused.layers == {"direct", "indirect"}
    assert all(d["prior"] == "blend" and d["inputs"]["candidates"] == list(KINDS) for d in fused.describe())
    frame = read_frame(load_manifest(paired).frames[0].path, nonfinite="zero")
    result = reconstruct(frame, "fused", models=LoadedModels(fused=fused))
    assert result.method == "fused" and np.isfinite(result.image).all() and result.image.min() >= 0
    base = sum(layer.base for layer in frame.layers.values())
    assert result.image.mean() == pytest.approx(base.mean(), rel=0.25)  # a convex blend keeps the energy
    for k in (1e-8, 1e9):
        scaled = read_frame(load_manifest(paired).frames[0].path, nonfinite="zero")
        for layer in scaled.layers.values():
            for a in (layer.base, layer.dx, layer.dy):
                a *= np.float32(k)
        out = reconstruct(scaled, "fused", models=LoadedModels(fused=fused)).image / k
        assert np.abs(out - result.image).max() <= 1e-3 * result.image.max(), k


@pytest.mark.slow
def test_models_of_another_prior_kind_are_refused(blend_models: Path, tmp_path: Path) -> None:
    import onnx

    with pytest.raises(ModelError, match="prior"):
        load_network(blend_models / "fused")  # a blend model in the network method's folder
    wrong = tmp_path / "models" / "fused"
    wrong.mkdir(parents=True)
    proto = onnx.load(blend_models / "fused" / "direct.onnx")
    for prop in proto.metadata_props:
        if prop.key == "gradsep.prior":
            prop.value = "oidn"  # a kind no fused model has
    onnx.save(proto, wrong / "direct.onnx")
    with pytest.raises(ModelError, match="prior kind 'oidn'"):
        load_fused(tmp_path / "models")
    shutil.copy(blend_models / "fused" / "direct.onnx", wrong / "indirect.onnx")  # a direct model as indirect
    (wrong / "direct.onnx").unlink()
    with pytest.raises(ModelError, match="layer"):
        load_fused(tmp_path / "models")


@pytest.mark.slow
@pytest.mark.parametrize("case", ["black", "1x1", "17x9", "nan-inf", "huge"])
def test_stiff_frames_stay_finite(blend_models: Path, case: str) -> None:
    from gradsep.model.frame import Features, Frame, Layer

    fused = load_fused(blend_models)
    h, w = {"1x1": (1, 1), "17x9": (9, 17)}.get(case, (20, 24))
    rng = np.random.default_rng(0)
    base = rng.gamma(0.5, 1.0, (h, w, 3)).astype(np.float32) * (0.0 if case == "black" else 1.0)
    dx, dy = (rng.normal(0, 0.3, (h, w, 3)).astype(np.float32) for _ in range(2))
    if case == "black":
        dx[:] = dy[:] = 0.0
    if case == "nan-inf":
        base[0, 0, 0], dx[1, 1, 1], dy[2, 2, 2] = np.nan, np.inf, -np.inf
    if case == "huge":
        base *= np.float32(1e30)
        dx *= np.float32(1e30)
        dy *= np.float32(1e30)
    feats = Features(rng.uniform(0, 1, (h, w, 3)).astype(np.float32),
                     np.tile(np.float32([0, 0, 1]), (h, w, 1)), np.ones((h, w), np.float32))
    frame = Frame({"direct": Layer(base, dx, dy), "indirect": Layer(base.copy(), dx.copy(), dy.copy())}, feats)
    image = reconstruct(frame, "fused", models=LoadedModels(fused=fused)).image
    assert image.shape == (h, w, 3) and np.isfinite(image).all() and image.min() >= 0
    if case == "black":
        assert image.max() == 0.0


@pytest.mark.slow
def test_a_fixed_layer_is_its_candidate_and_old_formats_are_refused(blend_models: Path, paired: Path,
                                                                     tmp_path: Path) -> None:
    """A layer without a model in the folder is served by its FIXED_LAYERS candidate alone (the direct layer:
    OIDN refined by its gradients, the oidn-l1 method's refinement at fused's CG budget); a model of blend
    format 1 (trained on the former DCT-solved candidates) is refused rather than fed candidates it never saw."""
    import onnx

    from gradsep.model.fused import FIXED_LAYERS

    folder = tmp_path / "models" / "fused"
    folder.mkdir(parents=True)
    shutil.copy(blend_models / "fused" / "indirect.onnx", folder / "indirect.onnx")
    fused = load_fused(tmp_path / "models")
    assert fused is not None and fused.layers == {"indirect"} | set(FIXED_LAYERS)
    frame = read_frame(load_manifest(paired).frames[0].path, nonfinite="zero")
    result = reconstruct(frame, "fused", models=LoadedModels(fused=fused))
    assert np.isfinite(result.image).all() and result.image.min() >= 0
    for name, kind in FIXED_LAYERS.items():
        aux = shared_denoiser(OIDN_SETTING).prefilter(frame.features)
        _, (image,), scale = layer_candidates(frame.layers[name], aux, (kind,))
        np.testing.assert_allclose(result.layers[name], image / scale, rtol=1e-6, atol=1e-7)
    # the direct layer, served by oidn-l1's refinement solved less far, is close to the oidn-l1 method's
    oidn_l1 = reconstruct(frame, "oidn-l1").layers["direct"]
    assert np.abs(result.layers["direct"] - oidn_l1).mean() < 0.05 * oidn_l1.mean()
    proto = onnx.load(folder / "indirect.onnx")
    for prop in proto.metadata_props:
        if prop.key == "gradsep.format":
            prop.value = "1"
    onnx.save(proto, folder / "indirect.onnx")
    with pytest.raises(ModelError, match="format '1'"):
        load_fused(tmp_path / "models")


def test_cache_layers_option_and_caches_of_removed_options_are_refused(paired: Path, tmp_path: Path) -> None:
    """``cache --layers direct`` writes the direct layer only; a cache made with a target or loss normalisation
    this code no longer trains on (recorded in cache.json) is refused by ``train`` rather than misread."""
    out = tmp_path / "cache"
    fused_training.main(["cache", "--data", str(paired), "-o", str(out), "--layers", "direct"])
    assert not (out / "indirect").exists() and sorted((out / "direct").glob("*.npy"))
    meta = json.loads((out / "cache.json").read_text())
    assert meta["candidates"] == list(fused_training.CANDIDATES) and "target" not in meta
    with pytest.raises(SystemExit, match="--layers"):
        fused_training.build_cache(paired, tmp_path / "other", layers=("specular",))
    args = ["train", "--cache", str(out), "--layer", "direct", "--minutes", "0", "--patch", "32", "--batch", "2",
            "--width", "4", "--blocks", "1", "-o", str(tmp_path / "run")]
    (out / "cache.json").write_text(json.dumps({**meta, "target": "l2"}))
    with pytest.raises(SystemExit, match="rebuild the cache"):
        fused_training.main(args)
    assert not (tmp_path / "run").exists()


def test_cache_extra_data_is_cached_beside_and_recorded(paired: Path, tmp_path: Path) -> None:
    """``cache --extra-data D`` adds a second dataset's frames as x0-NNNNN.npy beside the first's (training
    samples every file of the layer folder), and the cache records both datasets."""
    other = make_synthetic_dataset(tmp_path / "other", frames=2, width=40, height=32, spp=16, first_seed=7000,
                                   pairs=True)
    out = tmp_path / "cache"
    fused_training.main(["cache", "--data", str(paired), "--extra-data", str(other), "-o", str(out),
                         "--candidates", "oidn", "--layers", "indirect"])
    names = sorted(p.name for p in (out / "indirect").glob("*.npy"))
    first = [n for n in names if not n.startswith("x0-")]
    extra = [n for n in names if n.startswith("x0-")]
    assert len(first) == len([e for e in load_manifest(paired).frames if e.target is not None])
    assert len(extra) == len([e for e in load_manifest(other).frames if e.target is not None]) > 0
    meta = json.loads((out / "cache.json").read_text())
    assert meta["dataset"] == load_manifest(paired).sha256 and meta["extra_datasets"] == [load_manifest(other).sha256]
    assert np.load(out / "indirect" / extra[0]).shape[1:] == (32, 40)
