"""model/backoff.py: a denoiser's image blended back toward the rendered base where the base's variance says the
change was bias, not noise; and its use by the OIDN methods through the frame's variance channel."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from gradsep.model.backoff import NOISE_MARGIN, back_off
from gradsep.model.frame import VARIANCE_MAX, Features, Frame, Layer
from gradsep.model.policy import LUMINANCE


def smooth_scene(h: int = 48, w: int = 40, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (0.2 + gaussian_filter(rng.random((h, w, 3)), 4.0)).astype(np.float64)


def luminance_variance(sigma: float, shape: tuple[int, int]) -> np.ndarray:
    """The variance of Y for independent Gaussian noise of std ``sigma`` per channel."""
    return np.full(shape, sigma**2 * float(np.sum(np.square(LUMINANCE))))


def test_a_noise_free_base_is_kept_whatever_the_denoiser_did() -> None:
    truth = smooth_scene()
    biased = gaussian_filter(truth, (3, 3, 0)) * 1.1  # blurred and too bright: all bias
    out = back_off(truth, biased, np.zeros(truth.shape[:2]))
    np.testing.assert_array_equal(out, truth.astype(np.float32))


def test_a_noisy_base_keeps_a_good_denoisers_image() -> None:
    truth = smooth_scene()
    rng = np.random.default_rng(1)
    sigma = 0.05
    noisy = truth + rng.normal(0, sigma, truth.shape)
    out = back_off(noisy, truth, luminance_variance(sigma, truth.shape[:2]))
    # a change within NOISE_MARGIN × the noise is noise removed: most pixels keep the denoiser's value exactly
    kept = np.all(out == truth.astype(np.float32), axis=-1)
    assert kept.mean() > 0.95
    assert np.mean((out - truth) ** 2) < 0.05 * np.mean((noisy - truth) ** 2)


def test_the_blend_beats_both_where_the_denoiser_is_biased_and_the_base_nearly_converged() -> None:
    truth = smooth_scene()
    rng = np.random.default_rng(2)
    sigma = 0.002
    noisy = truth + rng.normal(0, sigma, truth.shape)
    denoised = truth.copy()
    denoised[:, : truth.shape[1] // 2] *= 1.2  # bias on the left half only
    out = back_off(noisy, denoised, luminance_variance(sigma, truth.shape[:2]))
    err = {name: float(np.mean((img - truth) ** 2)) for name, img in
           (("out", out), ("noisy", noisy), ("denoised", denoised))}
    assert err["out"] < err["noisy"] and err["out"] < 0.01 * err["denoised"], err
    right = slice(truth.shape[1] // 2 + 8, None)  # away from the bias's edge, the denoiser's exact image stays
    np.testing.assert_allclose(out[:, right], truth[:, right], rtol=1e-6)


def test_a_firefly_stays_the_denoisers() -> None:
    truth = smooth_scene()
    noisy = truth.copy()
    noisy[20, 20] += 1e4
    var = np.zeros(truth.shape[:2])
    var[20, 20] = (1e4) ** 2  # the one sample that found the firefly
    out = back_off(noisy, truth, var)
    np.testing.assert_allclose(out[20, 20], truth[20, 20], rtol=1e-6)


@pytest.mark.parametrize("scale", [1e-8, 1e-3, 1e3, 1e6])
def test_scale_exact_over_the_radiance_range(scale: float) -> None:
    """Radiance × s with variance × s² gives the image × s: nothing absolute in the rule."""
    truth = smooth_scene()
    rng = np.random.default_rng(3)
    noisy = truth + rng.normal(0, 0.01, truth.shape)
    denoised = gaussian_filter(noisy, (1.5, 1.5, 0))
    var = rng.random(truth.shape[:2]) * 2e-4
    ref = back_off(noisy, denoised, var).astype(np.float64)
    out = back_off(noisy * scale, denoised * scale, var * scale * scale).astype(np.float64)
    np.testing.assert_allclose(out / scale, ref, rtol=1e-5, atol=1e-12)


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 1), (3, 5), (17, 13)])
def test_tiny_and_odd_sizes(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(4)
    noisy = rng.random((*shape, 3))
    denoised = rng.random((*shape, 3))
    out = back_off(noisy, denoised, rng.random(shape) * 1e-3)
    assert out.shape == (*shape, 3) and out.dtype == np.float32 and np.isfinite(out).all()
    lo, hi = np.minimum(noisy, denoised), np.maximum(noisy, denoised)
    assert np.all(out >= lo - 1e-6) and np.all(out <= hi + 1e-6)  # a blend, never an extrapolation


def test_black_frames_and_extreme_variances_stay_finite() -> None:
    black = np.zeros((9, 11, 3))
    assert not back_off(black, black, np.zeros((9, 11))).any()
    rng = np.random.default_rng(5)
    noisy, denoised = rng.random((9, 11, 3)) * 1e6, rng.random((9, 11, 3)) * 1e6
    var = rng.random((9, 11))
    var[0, 0], var[1, 1], var[2, 2], var[3, 3] = np.inf, np.nan, -1.0, 1e300
    out = back_off(noisy, denoised, var)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[0, 0], denoised[0, 0], rtol=1e-6)  # Inf reads as very noisy
    assert back_off(noisy, denoised, np.full((9, 11), VARIANCE_MAX)).tolist() == denoised.astype(np.float32).tolist()


def test_margin_is_what_separates_noise_from_bias() -> None:
    """A uniform change of exactly sqrt(k·σ²) in luminance keeps the denoiser's image for k ≤ NOISE_MARGIN and
    backs off above it."""
    base = np.full((16, 16, 3), 1.0)
    var = np.full((16, 16), 1e-4)
    for k, kept in ((0.9 * NOISE_MARGIN, True), (4 * NOISE_MARGIN, False)):
        denoised = base + np.sqrt(k * 1e-4)  # a grey shift: its luminance change is the shift itself
        out = back_off(base, denoised, var)
        assert np.allclose(out, denoised) == kept, k


def test_shapes_are_checked() -> None:
    with pytest.raises(ValueError, match="variance"):
        back_off(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), np.zeros((4, 5)))
    with pytest.raises(ValueError, match="images"):
        back_off(np.zeros((4, 4, 3)), np.zeros((4, 4, 1)), np.zeros((4, 4)))


def converged_frame(var: float | None) -> Frame:
    """A smooth, exactly rendered two-layer frame: what OIDN should leave alone."""
    truth = smooth_scene(64, 64).astype(np.float32)
    variance = None if var is None else np.full((64, 64), var, np.float32)
    layers = {"direct": Layer(truth, var=variance), "indirect": Layer(0.3 * truth, var=variance)}
    normal = np.zeros((64, 64, 3), np.float32)
    normal[..., 2] = 1
    return Frame(layers, Features(np.full((64, 64, 3), 0.5, np.float32), normal, None))


def test_oidn_leaves_a_converged_frame_alone_when_it_carries_its_variance() -> None:
    from gradsep.model import oidn
    from gradsep.model.reconstruct import reconstruct

    if not oidn.available():
        pytest.skip("OIDN is not installed")
    with_var = reconstruct(converged_frame(0.0), "oidn")
    without = reconstruct(converged_frame(None), "oidn")
    truth = sum(layer.base for layer in converged_frame(None).layers.values())
    np.testing.assert_allclose(with_var.image, truth, rtol=1e-6)
    assert not np.allclose(without.image, truth, rtol=1e-4)  # OIDN alone changes it


def test_a_light_in_view_leaves_no_halo(monkeypatch: pytest.MonkeyPatch) -> None:
    """The outlier detector (model/outliers.py) keeps a small light in view out of OIDN and pins it with its rim: a
    light's pixels, half covered by the emitter, carry a variance that would otherwise read as noise over the whole
    window and keep OIDN's halo. Around a converged light the answer is the input, with or without the variance;
    without the detector OIDN spreads it."""
    from gradsep.model import oidn, outliers
    from gradsep.model.reconstruct import reconstruct

    if not oidn.available():
        pytest.skip("OIDN is not installed")
    h = w = 48
    base = np.full((h, w, 3), 0.5, np.float32)
    base[22:25, 22:24] = 2e4  # a 3x2-pixel light
    var = np.full((h, w), 1e-10, np.float32)
    var[22:25, 22:24] = (2e4) ** 2 / 4 / 64  # its pixels half covered by the emitter, 64 samples
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1

    def answer(variance: np.ndarray | None) -> np.ndarray:
        frame = Frame({"direct": Layer(base.copy(), var=variance)},
                      Features(np.full((h, w, 3), 0.5, np.float32), normal, None))
        return reconstruct(frame, "oidn").image

    ring = np.zeros((h, w), bool)
    ring[18:29, 18:28] = True
    ring[22:25, 22:24] = False
    for variance in (var, None):
        np.testing.assert_allclose(answer(variance)[ring], 0.5, rtol=1e-4 if variance is not None else 1e-2)
        np.testing.assert_allclose(answer(variance)[22:25, 22:24], 2e4, rtol=1e-6)
    monkeypatch.setattr(outliers, "split_frame", lambda frame, sources=False, threads=1: (frame, outliers.FrameSplit()))
    assert np.abs(answer(None)[ring] - 0.5).max() > 1e-2  # OIDN alone spreads the light


def test_a_lights_pinned_pixels_are_its_pixels_and_their_rim() -> None:
    from gradsep.model.outliers import split_layer

    base = np.full((20, 20, 3), 0.5, np.float32)
    base[3, 3:5] = 1e3  # a 1x2 light (no variance: a group of pixels reads as a light)
    split = split_layer(Layer(base))
    want = np.zeros((20, 20), bool)
    want[3, 2:6] = True
    want[2, 3:5] = want[4, 3:5] = True
    np.testing.assert_array_equal(split.pinned, want)
    np.testing.assert_array_equal(split.in_place, np.any(base > 1, axis=-1))


def test_pinned_pixels_come_back_as_rendered_and_stay_out_of_the_windows() -> None:
    rng = np.random.default_rng(6)
    noisy = rng.random((20, 20, 3))
    denoised = noisy + 0.01
    var = np.full((20, 20), 1.0)  # noisy: the denoiser's image is kept ...
    pinned = np.zeros((20, 20), bool)
    pinned[5:8, 5:8] = True
    out = back_off(noisy, denoised, var, pinned)
    np.testing.assert_array_equal(out[pinned], noisy[pinned].astype(np.float32))  # ... except where pinned
    np.testing.assert_allclose(out[~pinned], denoised[~pinned], rtol=1e-6)
    quiet = np.where(pinned, 1.0, 0.0)  # a pinned pixel's variance does not hide its neighbours' bias
    out = back_off(noisy, denoised, quiet, pinned)
    np.testing.assert_allclose(out, noisy, rtol=1e-6)
    with pytest.raises(ValueError, match="pinned"):
        back_off(noisy, denoised, var, np.zeros((3, 3), bool))


def test_a_firefly_changes_nothing_along_its_row() -> None:
    """A firefly's huge variance must not leave the window it is in: with a running-sum box filter the small
    variances behind it were lost to rounding, and the rest of its row read as noise-free and backed off."""
    rng = np.random.default_rng(7)
    x = 0.5 + 0.01 * rng.standard_normal((64, 64, 3))
    y = np.full((64, 64, 3), 0.5)  # a perfect denoiser
    var = np.full((64, 64), 1e-4 * float(np.sum(np.square(LUMINANCE))))
    x[30, 5] = 1e10
    var[30, 5] = 1e20  # the firefly the denoiser removed
    out = back_off(x, y, var)
    far = np.ones((64, 64), bool)
    far[27:34, 2:9] = False  # the firefly's own window
    np.testing.assert_array_equal(out[far], y[far].astype(np.float32))
