"""The network keeps a frame's energy at any exposure (each layer run at its trained exposure), and the
execution provider choice (OpenVINO bf16 vs ORT CPU fp32) is explicit, reported, and accurate.

Uses the shipped models (models/direct.onnx, indirect.onnx) and the shipped example frame: numpy + onnxruntime
only, no torch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gradsep.model.exr_read import read_frame
from gradsep.model.frame import Frame
from gradsep.model.infer import NETWORK_LEVEL, NetworkReconstructor, exposure_scale
from gradsep.model.methods import LoadedModels
from gradsep.model.metrics import relmse
from gradsep.model.onnx_session import (
    BF16_FLAGS,
    CPU_EP,
    CUDA_EP,
    OPENVINO_EP,
    ProviderChoice,
    SessionSettings,
    choose_provider,
    cpu_flags,
    served_by,
)
from gradsep.model.preprocess import scaled_layer
from gradsep.model.reconstruct import reconstruct
from gradsep.model.robust import robust_level

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "models"
EXAMPLE = ROOT / "examples" / "cbox-16spp.exr"
REFERENCE = ROOT / "examples" / "cbox-reference.exr"

needs_models = pytest.mark.skipif(not (MODELS / "direct.onnx").is_file() or not (MODELS / "indirect.onnx").is_file(),
                                  reason="the shipped models are not in models/")


@pytest.fixture(scope="module")
def frame() -> Frame:
    return read_frame(EXAMPLE)


@pytest.fixture(scope="module")
def network() -> NetworkReconstructor:
    if not (MODELS / "direct.onnx").is_file():
        pytest.skip("the shipped models are not in models/")
    net = NetworkReconstructor.load(MODELS)
    assert net is not None
    return net


def _scaled(frame: Frame, k: float) -> Frame:
    return Frame({n: scaled_layer(layer, k) for n, layer in frame.layers.items()}, frame.features)


# ------------------------------------------------------------------------------------------- exposure scaling


def test_every_layer_runs_at_the_trained_level_and_the_scale_follows_the_exposure(frame: Frame) -> None:
    for layer in frame.layers.values():
        s = exposure_scale(layer)
        assert robust_level(scaled_layer(layer, 1.0 / s).base) == pytest.approx(NETWORK_LEVEL, rel=1e-6)
        for k in (1e-8, 1e-5, 1e4, 1e6, 1e9, 1e30):
            assert exposure_scale(scaled_layer(layer, k)) == pytest.approx(k * s, rel=1e-6)
    black = scaled_layer(next(iter(frame.layers.values())), 0.0)
    assert exposure_scale(black) == 1.0


@pytest.mark.parametrize("where", [(0, 0), (48, 95), (50, 40)])
def test_one_pixel_cannot_move_the_exposure(frame: Frame, where: tuple[int, int]) -> None:
    """The scale is a winsorised mean: a firefly of any size counts as the 99.9th percentile at most, so it moves the
    level by at most that percentile over the pixel count (0.9 % on this 96x96 frame, whose light fills the top)."""
    for layer in frame.layers.values():
        base = layer.base.copy()
        base[where] = 1e30
        moved = exposure_scale(type(layer)(base, layer.dx, layer.dy))
        pixels = layer.base.mean(axis=-1, dtype=np.float64)
        bound = 2 * np.quantile(pixels, 0.999) / pixels.size / robust_level(layer.base)
        assert moved == pytest.approx(exposure_scale(layer), rel=bound)
        assert bound < 0.02


@needs_models
@pytest.mark.parametrize("k", [1e-8, 1e4, 1e6, 1e9])
def test_network_keeps_the_energy_at_any_exposure(frame: Frame, network: NetworkReconstructor, k: float) -> None:
    """Before issue 15 the network clipped each layer at 65504 (a 1e6 frame came back ~1e5x too dark)."""
    ref = reconstruct(frame, "network", models=LoadedModels(network=network))
    out = reconstruct(_scaled(frame, k), "network", models=LoadedModels(network=network))
    assert np.isfinite(out.image).all() and out.image.min() >= 0
    for name, image in out.layers.items():
        ratio = float(image.mean(dtype=np.float64)) / (k * float(ref.layers[name].mean(dtype=np.float64)))
        assert abs(ratio - 1.0) < 0.02, (name, ratio)
    # and the shape of the image, not only its mean: RelMSE against the scaled 1x result stays small
    assert relmse(out.image / np.float32(k), ref.image) < 0.01


@pytest.mark.parametrize("method", ["l1", "l2"])
@pytest.mark.parametrize("k", [1e4, 1e6, 1e9])
def test_poisson_methods_keep_the_energy_at_high_exposure(frame: Frame, method: str, k: float) -> None:
    base = reconstruct(_scaled(frame, 1e4), method)  # the L1 reg is absolute: compare within the HDR regime
    out = reconstruct(_scaled(frame, k), method)
    assert np.isfinite(out.image).all()
    ratio = float(out.image.mean(dtype=np.float64)) / (k / 1e4 * float(base.image.mean(dtype=np.float64)))
    assert abs(ratio - 1.0) < 1e-3, ratio
    energy = float(frame.combined().base.mean(dtype=np.float64)) * k
    assert 0.8 < float(out.image.mean(dtype=np.float64)) / energy < 1.2


# ------------------------------------------------------------------------------------------- providers


@pytest.mark.parametrize(("requested", "available", "flags", "want"), [
    ("auto", [OPENVINO_EP, CPU_EP], {"avx512f", "avx512_bf16"}, ("openvino", "bf16")),
    ("auto", [OPENVINO_EP, CPU_EP], {"amx_bf16"}, ("openvino", "bf16")),
    ("auto", [OPENVINO_EP, CPU_EP], {"avx512f"}, ("cpu", "fp32")),      # no native bf16: plain CPU EP
    ("auto", [CPU_EP], {"avx512_bf16"}, ("cpu", "fp32")),                # onnxruntime without OpenVINO
    ("openvino", [OPENVINO_EP, CPU_EP], set(), ("openvino", "fp32")),
    ("openvino", [CPU_EP], {"avx512_bf16"}, ("cpu", "fp32")),
    ("cpu", [OPENVINO_EP, CPU_EP], {"avx512_bf16"}, ("cpu", "fp32")),
    ("auto", [CUDA_EP, OPENVINO_EP, CPU_EP], {"avx512_bf16"}, ("cuda", "fp32")),  # onnxruntime-gpu: the GPU
    ("cuda", [CUDA_EP, CPU_EP], set(), ("cuda", "fp32")),
    ("cuda", [OPENVINO_EP, CPU_EP], {"avx512_bf16"}, ("openvino", "bf16")),  # no CUDA build: auto's CPU choice
    ("cuda", [CPU_EP], set(), ("cpu", "fp32")),
    ("cpu", [CUDA_EP, CPU_EP], set(), ("cpu", "fp32")),
])
def test_provider_choice(requested: str, available: list[str], flags: set[str], want: tuple[str, str]) -> None:
    choice = choose_provider(requested, available, frozenset(flags))
    assert (choice.provider, choice.precision) == want and choice.reason
    names = [p if isinstance(p, str) else p[0] for p in choice.providers()]
    assert names[-1] == CPU_EP and (OPENVINO_EP in names) == (want[0] == "openvino")
    assert (CUDA_EP in names) == (want[0] == "cuda")


def test_unknown_provider_is_refused() -> None:
    with pytest.raises(ValueError, match="provider"):
        choose_provider("tpu", [CPU_EP], frozenset())


@pytest.mark.parametrize(("choice", "session", "want"), [
    (("cuda", "fp32"), [CUDA_EP, CPU_EP], "cuda"),
    (("cuda", "fp32"), [CPU_EP], "cpu"),          # a CUDA build on a host without a usable GPU
    (("openvino", "bf16"), [OPENVINO_EP, CPU_EP], "openvino"),
    (("openvino", "bf16"), [CPU_EP], "cpu"),
    (("cpu", "fp32"), [CPU_EP], "cpu"),
])
def test_the_reported_provider_is_the_one_the_session_runs(choice: tuple[str, str], session: list[str],
                                                           want: str) -> None:

    got = served_by(ProviderChoice(*choice, "asked"), session)
    assert got.provider == want and (got == ProviderChoice(*choice, "asked")) == (want == choice[0])


def test_cpu_flags_reads_cpuinfo(tmp_path: Path) -> None:
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx512f avx512_bf16\n\nprocessor\t: 1\n")
    assert {"avx512f", "avx512_bf16"} <= cpu_flags(info)
    assert cpu_flags(tmp_path / "missing") == frozenset()


@needs_models
def test_models_report_their_provider(network: NetworkReconstructor) -> None:
    import onnxruntime as ort

    want = choose_provider(SessionSettings().provider, ort.get_available_providers(), cpu_flags())
    for entry in network.describe():
        assert (entry["provider"], entry["precision"]) == (want.provider, want.precision)
        assert entry["provider_reason"]


def _accelerated_available() -> bool:
    import onnxruntime as ort

    return OPENVINO_EP in ort.get_available_providers() and bool(BF16_FLAGS & cpu_flags())


@needs_models
@pytest.mark.skipif(not _accelerated_available(), reason="needs onnxruntime-openvino and a CPU with native bf16")
def test_openvino_bf16_matches_fp32_on_the_example_frame(frame: Frame) -> None:
    """The accelerated provider must not cost accuracy: RelMSE against the 4096 spp reference changes by
    less than 1 % relative to ORT's fp32 CPU provider, and the images agree closely."""
    from gradsep.renderer.reference import load_reference

    reference = load_reference(REFERENCE).total
    fast = NetworkReconstructor.load(MODELS, SessionSettings(provider="openvino"))
    exact = NetworkReconstructor.load(MODELS, SessionSettings(provider="cpu"))
    assert fast is not None and exact is not None
    assert {m["precision"] for m in fast.describe()} == {"bf16"}
    a = reconstruct(frame, "network", models=LoadedModels(network=fast)).image
    b = reconstruct(frame, "network", models=LoadedModels(network=exact)).image
    err_fast, err_exact = relmse(a, reference), relmse(b, reference)
    assert abs(err_fast - err_exact) / err_exact < 0.01, (err_fast, err_exact)
    assert relmse(a, b) < 1e-3
