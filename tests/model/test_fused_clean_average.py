"""fused's clean-layer average (model/fused.py CLEAN_AVERAGE): on a direct layer the trust rule calls
clean, the refinement is averaged with the ``network`` method's image where the two agree; a noisy layer runs no
network at all."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gradsep.model import fused
from gradsep.model.frame import Features, Layer, forward_differences
from gradsep.model.refine import clean_weight

pytest.importorskip("pyoidn")
REPO = Path(__file__).resolve().parents[2]


def _image(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0.1, 2.0, (h // 5 + 1, w // 5 + 1, 3))
    return np.repeat(np.repeat(coarse, 5, 0), 5, 1)[:h, :w].astype(np.float32)


def _features(h: int, w: int) -> Features:
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1
    return Features(np.full((h, w, 3), 0.5, np.float32), normal, np.ones((h, w), np.float32))


def _exact(h: int = 30, w: int = 34, seed: int = 1) -> Layer:
    """A layer whose base agrees with its gradients exactly: clean as a whole (w_f = 1)."""
    image = _image(h, w, seed)
    return Layer(image, *forward_differences(image))


def _noisy(h: int = 30, w: int = 34, seed: int = 2) -> Layer:
    """Exact gradients, a base with multiplicative noise far above them: not clean (w_f = 0)."""
    image = _image(h, w, seed)
    rng = np.random.default_rng(seed)
    base = image * rng.gamma(1.0, 1.0, image.shape).astype(np.float32)
    return Layer(base, *forward_differences(image))


class _Second:
    """A stand-in for the network method's reconstructor: counts calls, returns a fixed image."""

    def __init__(self, image: np.ndarray | None = None, factor: float = 1.0) -> None:
        self.models = {"direct": object()}
        self.image, self.factor, self.calls = image, factor, 0

    def reconstruct_layer(self, name: str, layer: Layer, features: Features) -> np.ndarray:
        self.calls += 1
        return self.image if self.image is not None else (layer.base * np.float32(self.factor))


def test_agreement_weights_one_where_equal_zero_where_far_and_exposure_invariant() -> None:
    a = _image(12, 14, 3)
    low, high = fused.CLEAN_AVERAGE
    assert np.all(fused.agreement_weights(a, a, 1.0, (low, high)) == 1.0)
    assert np.all(fused.agreement_weights(a, 10 * a, 1.0, (low, high)) == 0.0)
    near = a * np.float32(1.05)  # ρ ≈ 0.05² / 1.05 ≈ 0.0024: below the low threshold
    assert np.all(fused.agreement_weights(a, near, 1.0, (low, high)) == 1.0)
    mid = fused.agreement_weights(a, a * np.float32(1.2), 1.0, (low, high))
    assert np.all((mid > 0) & (mid < 1))
    for k in (1e-8, 1e6):  # the same images at another exposure, the scale following it: the same weights
        np.testing.assert_allclose(fused.agreement_weights(a * k, a * np.float32(1.2) * k, 1.0 / k, (low, high)),
                                   mid, rtol=1e-5, atol=1e-6)


def test_clean_average_is_at_most_half_way_and_refined_itself_when_not_clean() -> None:
    rng = np.random.default_rng(4)
    refined = rng.uniform(0, 2, (9, 11, 3)).astype(np.float32)
    second = refined * rng.uniform(0.9, 1.1, refined.shape).astype(np.float32)
    out = fused.clean_average(refined, second, 1.0, 1.0)
    lo, hi = np.minimum(refined, second), np.maximum(refined, second)
    assert np.all(out >= lo - 1e-6) and np.all(out <= hi + 1e-6)
    assert np.all(np.abs(out - refined) <= 0.5 * np.abs(second - refined) + 1e-6)
    assert not np.array_equal(out, refined)
    assert fused.clean_average(refined, second, 0.0, 1.0) is refined
    bad = second.copy()
    bad[0, 0, 0] = np.nan
    assert fused.clean_average(refined, bad, 1.0, 1.0) is refined  # a broken second estimate is not used


def test_a_noisy_layer_runs_no_network_and_is_the_refinement_alone() -> None:
    layer, feats = _noisy(), _features(30, 34)
    alone = fused.FusedReconstructor({}, fused.FIXED_LAYERS)
    second = _Second(factor=1.01)
    with_second = fused.FusedReconstructor({}, fused.FIXED_LAYERS, second)
    assert with_second._averages("direct")
    a = alone.reconstruct_layer("direct", layer, feats)
    b = with_second.reconstruct_layer("direct", layer, feats)
    assert second.calls == 0
    np.testing.assert_array_equal(a, b)


def test_a_clean_layer_is_averaged_with_the_second_estimate_where_they_agree() -> None:
    from gradsep.model.oidn import input_scale, shared_denoiser

    layer, feats = _exact(), _features(30, 34)
    aux = shared_denoiser(fused.OIDN_SETTING).prefilter(feats)
    denoised = shared_denoiser(fused.OIDN_SETTING).denoise(layer.base, aux)
    assert clean_weight(denoised, layer) == 1.0
    refined = fused.FusedReconstructor({}, fused.FIXED_LAYERS).reconstruct_layer("direct", layer, feats, aux)
    second = _Second(image=(refined * np.float32(1.02)))  # agrees: averaged half way
    got = fused.FusedReconstructor({}, fused.FIXED_LAYERS, second).reconstruct_layer("direct", layer, feats, aux)
    assert second.calls == 1
    np.testing.assert_allclose(got, fused.clean_average(refined, second.image, 1.0, input_scale(denoised)),
                               rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(got, refined * np.float32(1.01), rtol=1e-5)
    far = _Second(image=(refined * np.float32(5.0) + np.float32(1.0)))  # disagrees everywhere: the refinement
    got = fused.FusedReconstructor({}, fused.FIXED_LAYERS, far).reconstruct_layer("direct", layer, feats, aux)
    np.testing.assert_array_equal(got, refined)


def test_without_gradients_no_second_estimate() -> None:
    layer, feats = _exact(), _features(30, 34)
    second = _Second(factor=1.01)
    recon = fused.FusedReconstructor({}, fused.FIXED_LAYERS, second)
    plain = Layer(layer.base, None, None)
    out = recon.reconstruct_layer("direct", plain, feats)
    assert second.calls == 0 and np.isfinite(out).all()


def test_the_second_model_loads_from_beside_the_folder_and_a_broken_one_is_named(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    shipped = REPO / "models" / "direct.onnx"
    if not shipped.is_file():
        pytest.skip("models/direct.onnx is not in this checkout")
    second = fused._load_second(shipped, {"direct"})
    assert second is not None and set(second.models) == {"direct"}
    assert fused._load_second(shipped, {"color"}) is None  # no fixed direct layer: nothing to average
    assert fused._load_second(tmp_path / "absent.onnx", {"direct"}) is None
    broken = tmp_path / "direct.onnx"
    broken.write_bytes(b"not an onnx file")
    with pytest.raises(fused.BlendModelError, match="clean-layer average"):
        fused._load_second(broken, {"direct"})


def _partly_clean(h: int = 30, w: int = 34, seed: int = 4, noise: float = 0.06) -> Layer:
    """Exact gradients and a mildly noisy base: a frame-wide r between TRUST_FRAME_R's ends (0 < w_f < 1)."""
    image = _image(h, w, seed)
    rng = np.random.default_rng(seed)
    base = image * (1.0 + noise * rng.standard_normal(image.shape)).astype(np.float32)
    return Layer(np.maximum(base, 0.0).astype(np.float32), *forward_differences(image))


@pytest.mark.parametrize("make", [_exact, _noisy, _partly_clean, lambda: Layer(_image(30, 34, 5))],
                         ids=["clean", "noisy", "partly clean", "no gradients"])
def test_the_refinement_reports_the_clean_weight_it_used(make) -> None:
    """refine_layer's ``report`` carries the w_f its trust rule computed: model.refine.clean_weight's value
    (fused reads it instead of computing the frame statistic a second time)."""
    from gradsep.model.oidn import shared_denoiser
    from gradsep.model.refine import refine_layer

    layer, feats = make(), _features(30, 34)
    den = shared_denoiser(fused.OIDN_SETTING)
    denoised = den.denoise(layer.base, den.prefilter(feats))
    report: dict[str, float] = {}
    refined = refine_layer("direct", denoised, layer, report=report)
    np.testing.assert_array_equal(refined, refine_layer("direct", denoised, layer))  # the report changes nothing
    assert report["clean_weight"] == pytest.approx(clean_weight(denoised, layer), abs=1e-9)


def test_partly_clean_layer_has_an_intermediate_weight() -> None:
    """The case above that exercises the ramp between the ends (not only the exact 0 and 1)."""
    from gradsep.model.oidn import shared_denoiser

    layer, feats = _partly_clean(), _features(30, 34)
    den = shared_denoiser(fused.OIDN_SETTING)
    assert 0.0 < clean_weight(den.denoise(layer.base, den.prefilter(feats)), layer) < 1.0


def test_fused_does_not_recompute_the_clean_weight(monkeypatch: pytest.MonkeyPatch) -> None:
    """The served path takes w_f from the refinement: model.refine.clean_weight is never called, and the average
    is the one clean_weight's value gives."""
    from gradsep.model import refine
    from gradsep.model.oidn import input_scale, shared_denoiser

    layer, feats = _partly_clean(), _features(30, 34)
    aux = shared_denoiser(fused.OIDN_SETTING).prefilter(feats)
    denoised = shared_denoiser(fused.OIDN_SETTING).denoise(layer.base, aux)
    expected_weight = clean_weight(denoised, layer)
    refined = fused.FusedReconstructor({}, fused.FIXED_LAYERS).reconstruct_layer("direct", layer, feats, aux)
    second = _Second(image=(refined * np.float32(1.02)))

    def forbidden(*args, **kwargs):
        raise AssertionError("clean_weight recomputed")

    monkeypatch.setattr(refine, "clean_weight", forbidden)
    got = fused.FusedReconstructor({}, fused.FIXED_LAYERS, second).reconstruct_layer("direct", layer, feats, aux)
    assert second.calls == 1
    np.testing.assert_allclose(got, fused.clean_average(refined, second.image, expected_weight,
                                                         input_scale(denoised)), rtol=1e-6, atol=1e-7)
