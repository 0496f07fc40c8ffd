"""model/infer.py: loading exported models, ORT inference equal to the PyTorch pipeline, tiling, errors."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from gradsep.model.errors import ChannelError  # noqa: E402
from gradsep.model.frame import Features, Layer  # noqa: E402
from gradsep.model.infer import (  # noqa: E402
    ModelError,
    NetworkReconstructor,
    TileSettings,
    _ramp,
    exposure_scale,
    plan_tiles,
)
from gradsep.model.network import DualBranchNet, NetworkConfig  # noqa: E402
from gradsep.model.preprocess import (  # noqa: E402
    crop_to,
    feature_planes,
    layer_planes,
    network_inputs,
    output_radiance,
    pad_to_alignment,
    scaled_layer,
    unlit_pixels,
)
from gradsep.training.export import model_metadata, save_onnx, to_onnx  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
ATTENTION = NetworkConfig(width=4, residual_blocks=1)
PLAIN = NetworkConfig(width=4, residual_blocks=0, use_attention=False)


def _export(folder: Path, layer: str, cfg: NetworkConfig, seed: int) -> DualBranchNet:
    torch.manual_seed(seed)
    net = DualBranchNet(cfg).eval()
    save_onnx(to_onnx(net, model_metadata(cfg, layer)), folder / f"{layer}.onnx")
    return net


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, DualBranchNet]]:
    """direct.onnx (with CBAM) and indirect.onnx (without), from seeded untrained networks."""
    folder = tmp_path_factory.mktemp("models")
    nets = {"direct": _export(folder, "direct", ATTENTION, 1), "indirect": _export(folder, "indirect", PLAIN, 2)}
    return folder, nets


def _frame(h: int, w: int, seed: int = 0) -> tuple[Layer, Features]:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    clean = (1.0 + np.sin(xx / 7.0) * np.cos(yy / 5.0))[..., None] * np.array([0.8, 0.5, 0.3], np.float32)
    base = (clean * rng.lognormal(-0.02, 0.2, clean.shape)).astype(np.float32)
    dx = np.zeros_like(clean)
    dy = np.zeros_like(clean)
    dx[:, :-1] = clean[:, 1:] - clean[:, :-1]
    dy[:-1] = clean[1:] - clean[:-1]
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1
    albedo = np.clip(clean / 2, 0, 1).astype(np.float32)
    return Layer(base, dx, dy), Features(albedo, normal, (1 + yy / max(h, 1)).astype(np.float32))


def _torch_reference(net: DualBranchNet, layer: Layer, features: Features) -> np.ndarray:
    planes = layer_planes(layer)
    data, grad = network_inputs(planes, feature_planes(features))
    h, w = planes.shape[1:]
    a = net.config.alignment
    with torch.no_grad():
        y = net(torch.from_numpy(pad_to_alignment(data, a))[None], torch.from_numpy(pad_to_alignment(grad, a))[None])
    return output_radiance(crop_to(y[0].numpy(), h, w))


@pytest.mark.slow
def test_load_nothing_and_something(models: tuple[Path, dict], tmp_path: Path) -> None:
    assert NetworkReconstructor.load(tmp_path) is None
    folder, _ = models
    rec = NetworkReconstructor.load(folder)
    assert rec is not None and rec.layers == {"direct", "indirect"}
    described = {d["name"]: d for d in rec.describe()}
    assert described["direct"]["sha256"] == hashlib.sha256((folder / "direct.onnx").read_bytes()).hexdigest()
    assert described["direct"]["attention"] is True and described["indirect"]["attention"] is False
    assert described["direct"]["inputs"]["data"][0] == "base.R" and len(described["direct"]["inputs"]["gradient"]) == 6
    assert described["indirect"]["metadata"]["gradsep.layer"] == "indirect"
    assert rec.warm_up() >= 0.0


@pytest.mark.parametrize(("h", "w"), [(13, 21), (8, 8), (1, 1), (3, 40)])
def test_matches_the_pytorch_pipeline(models: tuple[Path, dict], h: int, w: int) -> None:
    folder, nets = models
    rec = NetworkReconstructor.load(folder)
    layer, features = _frame(h, w)
    for name in ("direct", "indirect"):
        out = rec.reconstruct_layer(name, layer, features)
        assert out.shape == (h, w, 3) and out.dtype == np.float32
        assert np.all(np.isfinite(out)) and out.min() >= 0
        exposure = exposure_scale(layer)  # the network runs at its trained exposure and is scaled back
        ref = exposure * _torch_reference(nets[name], scaled_layer(layer, 1.0 / exposure), features)
        assert np.abs(out - ref).max() <= 1e-4 * max(float(np.abs(ref).max()), 1e-6)


@pytest.mark.slow
def test_unlit_pixels_stay_black(tmp_path: Path) -> None:
    """A network that adds light everywhere (head bias > 0) must leave pixels with no measured light at 0 —
    base and every gradient touching them 0 — and change nothing where light was measured."""
    net = DualBranchNet(PLAIN).eval()
    with torch.no_grad():
        net.head.bias.fill_(0.3)
    save_onnx(to_onnx(net, model_metadata(PLAIN, "direct")), tmp_path / "direct.onnx")
    layer, features = _frame(16, 24)
    for arr in (layer.base, layer.dx, layer.dy):
        arr[:, 12:] = 0.0                        # right half: nothing measured
    layer.dx[:, 11] = 0.0                        # the term linking column 11 to column 12
    out = NetworkReconstructor.load(tmp_path).reconstruct_layer("direct", layer, features)
    exposure = exposure_scale(layer)
    ref = exposure * _torch_reference(net, scaled_layer(layer, 1.0 / exposure), features)
    assert np.all(out[:, 12:] == 0) and ref[:, 12:].min() > 0          # the raw network output is not black
    assert np.abs(out[:, :12] - ref[:, :12]).max() <= 1e-4 * float(ref.max())
    mask = unlit_pixels(layer)
    assert mask[:, 12:].all() and not mask[:, :12].any()
    layer.dy[5, 20] = 1e-3                       # one measured gradient lights both pixels it links
    mask = unlit_pixels(layer)
    assert not mask[5, 20] and not mask[6, 20] and mask[7, 20] and mask[4, 20]


def _hostile(layer: Layer, features: Features, nan: float, inf: float) -> None:
    """Poke NaN/±Inf (or the values the documented input policy maps them to) into a layer and its features."""
    layer.base[0, 0] = [nan, inf, -inf]
    layer.dx[1, 1] = 1e30
    features.albedo[2, 2] = nan
    features.depth[3, 3] = inf
    features.normal[4, 4] = [nan, 1e9, -1e9]


def test_hostile_values_follow_the_input_policy(models: tuple[Path, dict]) -> None:
    """Non-finite inputs are sanitised *before* the network (NaN -> 0, ±Inf -> the nearest bound): the output
    must equal the output for a frame holding those replacements already. The output clamp alone cannot make
    this pass: a NaN reaching the network would spread through its convolutions and attention and the clamp
    would turn the whole image black or into the fallback, far from the sanitised frame's answer."""
    rec = NetworkReconstructor.load(models[0])
    layer, features = _frame(9, 11)
    _hostile(layer, features, np.nan, np.inf)
    out = rec.reconstruct_layer("direct", layer, features)
    layer, features = _frame(9, 11)
    _hostile(layer, features, 0.0, 1e30)
    features.depth[3, 3] = 1e30  # clamped to DEPTH_MAX like +Inf
    want = rec.reconstruct_layer("direct", layer, features)
    assert want.max() > 0 and np.isfinite(want).all()
    np.testing.assert_allclose(out, want, rtol=1e-5, atol=1e-6 * float(want.max()))


def test_input_errors_name_the_problem(models: tuple[Path, dict]) -> None:
    rec = NetworkReconstructor.load(models[0])
    layer, features = _frame(8, 8)
    with pytest.raises(ChannelError, match="albedo"):
        rec.reconstruct_layer("direct", layer, None)
    bad = Features(features.albedo, features.normal, features.depth[:, :4])
    with pytest.raises(ChannelError, match="depth") as info:
        rec.reconstruct_layer("direct", layer, bad)
    assert info.value.details == ["depth"]
    with pytest.raises(KeyError, match="color"):
        rec.reconstruct_layer("color", layer, features)


def test_models_for_another_layer_or_corrupt_are_refused(models: tuple[Path, dict], tmp_path: Path) -> None:
    shutil.copy(models[0] / "direct.onnx", tmp_path / "indirect.onnx")
    with pytest.raises(ModelError, match="trained for layer 'direct'"):
        NetworkReconstructor.load(tmp_path)
    (tmp_path / "indirect.onnx").write_bytes(b"not an onnx file")
    with pytest.raises(ModelError, match="cannot load"):
        NetworkReconstructor.load(tmp_path)


# ------------------------------------------------------------------------------------------------ tiling


def test_tile_plan_covers_every_pixel_once_on_the_alignment_grid() -> None:
    settings = TileSettings(tile=30, overlap=10, max_untiled_pixels=100)
    plans = plan_tiles(70, 50, settings, alignment=8)
    cover = np.zeros((70, 50), int)
    for p in plans:
        y0, y1, x0, x1 = p.core
        cover[y0:y1, x0:x1] += 1
        wy0, wy1, wx0, wx1 = p.window
        assert wy0 % 8 == 0 and wx0 % 8 == 0                  # same stride-2 grid as the whole frame
        assert wy0 <= y0 and wy1 >= y1 and wx0 <= x0 and wx1 >= x1
    assert np.all(cover == 1)
    assert len(plan_tiles(10, 10, settings)) == 1             # small frames are not tiled


def test_blend_ramp() -> None:
    w = _ramp(8, 40, 64, 8)                                     # interior on both sides, 8 px of context
    assert np.all(w[:4] == 0) and np.all(w[-4:] == 0)          # the outer half of the context is dropped
    assert w[4] == pytest.approx(1 / 5) and w[7] == pytest.approx(4 / 5) and w[-5] == pytest.approx(1 / 5)
    assert np.all(w[8:-8] == 1.0)
    assert np.all(_ramp(0, 16, 16, 8) == 1.0)                  # a window spanning the axis needs no ramp


def test_tiled_equals_untiled_without_attention(models: tuple[Path, dict]) -> None:
    """Convolutions only: with enough overlap, windows reproduce the whole-frame result."""
    folder, _ = models
    layer, features = _frame(100, 90)
    whole = NetworkReconstructor.load(folder).reconstruct_layer("indirect", layer, features)
    tiles = TileSettings(tile=32, overlap=48, max_untiled_pixels=1000)
    tiled = NetworkReconstructor.load(folder, tiles=tiles).reconstruct_layer("indirect", layer, features)
    assert np.abs(tiled - whole).max() <= 1e-3 * float(np.abs(whole).max())


def test_tiled_close_to_untiled_with_attention(models: tuple[Path, dict]) -> None:
    """Channel attention pools over each window, so tiles differ slightly from the whole frame."""
    folder, _ = models
    layer, features = _frame(100, 90)
    whole = NetworkReconstructor.load(folder).reconstruct_layer("direct", layer, features)
    tiles = TileSettings(tile=48, overlap=24, max_untiled_pixels=1000)
    tiled = NetworkReconstructor.load(folder, tiles=tiles).reconstruct_layer("direct", layer, features)
    rel = np.abs(tiled - whole) / (np.abs(whole) + 1e-2)
    assert np.mean(rel) < 0.02 and np.all(np.isfinite(tiled)) and tiled.min() >= 0


def test_inference_runs_without_torch(models: tuple[Path, dict]) -> None:
    """model.infer needs only numpy + onnxruntime: the serving host has no torch."""
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import numpy as np\n"
        "from model.infer import NetworkReconstructor\n"
        "from model.frame import Layer, Features\n"
        f"rec = NetworkReconstructor.load({str(models[0])!r})\n"
        "z = np.zeros((5, 7, 3), np.float32)\n"
        "out = rec.reconstruct_layer('direct', Layer(z + 1, z, z), Features(z + 0.5, z, z[..., 0] + 2))\n"
        "assert out.shape == (5, 7, 3) and np.isfinite(out).all()\n"
        "assert 'torch' not in [m.split('.')[0] for m, v in sys.modules.items() if v is not None]\n"
        "print('ok')\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", code], env=env, cwd=REPO, capture_output=True, text=True,
                          timeout=120, check=False)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]


@pytest.mark.parametrize(("h", "w"), [(13, 21), (24, 40), (1, 1)])
def test_single_window_path_is_the_windowed_pipeline_bit_for_bit(models: tuple[Path, dict], h: int, w: int) -> None:
    """The one-window fast path (planes made once, prior solved from them, inputs written in place, the frame's
    feature planes reused by its next layer) gives exactly what the per-window pipeline gives."""
    from gradsep.model.preprocess import DepthRange, poisson_prior

    folder, _ = models
    rec = NetworkReconstructor.load(folder)
    layer, features = _frame(h, w, seed=3)
    layer.base[0, 0] = np.nan  # hostile values go through the same sanitising in both paths
    layer.dx[-1, 0] = -np.inf
    for name in ("direct", "indirect", "direct"):  # the second and third calls reuse the cached feature planes
        fast = rec._reconstruct(name, layer, features)  # at the layer's own exposure, as the windows below
        model = rec.models[name]
        slow = rec._run_window(model, layer, features, DepthRange.of(features.depth), poisson_prior(layer),
                               (0, h, 0, w))
        slow[unlit_pixels(layer)] = 0.0
        assert fast.dtype == np.float32 and np.array_equal(fast.view(np.uint32), slow.view(np.uint32))
    other = Features(features.albedo * 0.5, features.normal, features.depth)  # another frame: planes not reused
    expected = rec._run_window(rec.models["direct"], layer, other, DepthRange.of(other.depth), poisson_prior(layer),
                               (0, h, 0, w))
    expected[unlit_pixels(layer)] = 0.0
    assert np.array_equal(rec._reconstruct("direct", layer, other), expected)
