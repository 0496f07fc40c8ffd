"""Metrics against hand-computed values and an independent brute-force SSIM."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gradsep.model import metrics
from gradsep.model.metrics import all_metrics, flip, psnr, relmse, ssim, tonemap


def test_relmse_hand_computed() -> None:
    image = np.array([[1.0, 2.0], [0.0, 0.5]])
    reference = np.array([[1.0, 1.0], [0.1, 0.0]])
    # (0/1.01 + 1/1.01 + 0.01/0.02 + 0.25/0.01) / 4
    want = (0.0 + 1.0 / 1.01 + 0.01 / 0.02 + 0.25 / 0.01) / 4
    assert relmse(image, reference) == pytest.approx(want, rel=1e-12)
    assert relmse(reference, reference) == 0.0


def test_psnr_hand_computed() -> None:
    zeros, ones = np.zeros((4, 4, 3)), np.ones((4, 4, 3))
    assert psnr(zeros, ones) == pytest.approx(0.0, abs=1e-12)  # tonemapped MSE 1, peak 1
    # tonemap(0.25) = 0.25^(1/2.2): PSNR = -20 log10(0.25^(1/2.2)) = (20/2.2) log10 4
    assert psnr(np.full((3, 3), 0.25), np.zeros((3, 3))) == pytest.approx(20 / 2.2 * math.log10(4), rel=1e-12)
    # an HDR firefly counts as a saturated pixel on the display tonemap ...
    assert psnr(np.full((2, 2), 1e6), np.zeros((2, 2))) == pytest.approx(0.0, abs=1e-12)
    # ... and at full value on linear radiance: MSE 1, peak 2 -> 10 log10 4
    assert psnr(zeros, ones, peak=2.0, tonemapped=False) == pytest.approx(10 * math.log10(4), rel=1e-12)
    assert psnr(ones, ones) == math.inf


def test_ssim_of_constant_images_is_the_luminance_term() -> None:
    a, b = 0.25, 0.64
    ta, tb = a ** (1 / 2.2), b ** (1 / 2.2)
    c1 = 0.01**2
    want = (2 * ta * tb + c1) / (ta * ta + tb * tb + c1)  # variances are 0: contrast-structure term is c2/c2
    assert ssim(np.full((9, 7), a), np.full((9, 7), b)) == pytest.approx(want, rel=1e-9)
    assert ssim(np.full((9, 7, 3), a), np.full((9, 7, 3), a)) == pytest.approx(1.0)


def _brute_force_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """Direct windowed sums with explicit Gaussian weights and symmetric (half-sample) border reflection."""
    radius = int(3.5 * 1.5 + 0.5)
    offsets = np.arange(-radius, radius + 1)
    g = np.exp(-(offsets**2) / (2 * 1.5**2))
    g /= g.sum()
    window = np.outer(g, g)
    x, y = tonemap(x), tonemap(y)
    px, py = (np.pad(a, radius, mode="symmetric") for a in (x, y))
    c1, c2 = 0.01**2, 0.03**2
    values = []
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            wx = px[i : i + 2 * radius + 1, j : j + 2 * radius + 1]
            wy = py[i : i + 2 * radius + 1, j : j + 2 * radius + 1]
            mx, my = (window * wx).sum(), (window * wy).sum()
            vx = (window * (wx - mx) ** 2).sum()
            vy = (window * (wy - my) ** 2).sum()
            cov = (window * (wx - mx) * (wy - my)).sum()
            values.append(((2 * mx * my + c1) * (2 * cov + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    return float(np.mean(values))


def test_ssim_matches_a_brute_force_implementation() -> None:
    rng = np.random.default_rng(0)
    reference = rng.random((13, 17)) * 1.2
    image = reference + rng.normal(0, 0.1, reference.shape)
    assert ssim(image, reference) == pytest.approx(_brute_force_ssim(image, reference), rel=1e-9)
    assert 0.0 < ssim(image, reference) < 1.0


def test_flip_identical_is_zero_and_error_grows_with_noise() -> None:
    rng = np.random.default_rng(1)
    reference = (rng.random((24, 32, 3)) ** 2 * 3).astype(np.float32)
    assert flip(reference, reference) == 0.0
    small = flip(reference * 1.05, reference)
    large = flip(reference + rng.random(reference.shape).astype(np.float32) * 2, reference)
    assert 0.0 < small < large <= 1.0


def test_flip_equals_the_library_on_an_ordinary_image() -> None:
    """Our exposure range is FLIP's own when the median luminance is positive: results are identical."""
    import flip_evaluator

    rng = np.random.default_rng(2)
    reference = (rng.random((33, 47, 3)) ** 3 * 5).astype(np.float32)
    image = (reference * 1.1 + 0.01).astype(np.float32)
    _, want, _ = flip_evaluator.evaluate(reference, image, "HDR", applyMagma=False)
    assert flip(image, reference) == pytest.approx(want, rel=1e-6)


def test_flip_survives_black_references() -> None:
    """flip-evaluator aborts the process (exit 255) for a reference whose median luminance is 0; ours must not."""
    reference = np.zeros((16, 16, 3), np.float32)
    reference[:4, :4] = 2.0  # 1/16 of the pixels lit: median luminance 0
    assert 0.0 < flip(reference * 1.5, reference) < 1.0
    black = np.zeros_like(reference)
    assert 0.0 < flip(reference, black) <= 1.0
    assert flip(black, black) == 0.0


def test_flip_clamps_negative_values() -> None:
    reference = np.full((8, 8, 3), 0.5, np.float32)
    negative = reference.copy()
    negative[0, 0] = -3.0
    clamped = negative.copy()
    clamped[0, 0] = 0.0
    assert flip(negative, reference) == flip(clamped, reference)


@pytest.mark.parametrize("fn", [relmse, psnr, ssim, flip])
def test_bad_inputs_are_named(fn) -> None:
    good = np.ones((4, 4, 3))
    with pytest.raises(ValueError, match="differs"):
        fn(good, good[:3])
    bad = good.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="image contains 1 non-finite"):
        fn(bad, good)
    with pytest.raises(ValueError, match="reference contains 1 non-finite"):
        fn(good, bad)


def test_all_metrics_reports_each_metric() -> None:
    rng = np.random.default_rng(3)
    reference = rng.random((12, 12, 3))
    image = reference + 0.05
    got = all_metrics(image, reference)
    assert set(got) == {"relmse", "psnr", "ssim", "flip"}
    assert got["relmse"] == relmse(image, reference) and got["flip"] == flip(image, reference)
    assert "flip" not in all_metrics(image[..., 0], reference[..., 0])


def test_flip_needs_rgb() -> None:
    with pytest.raises(ValueError, match="RGB"):
        metrics.flip(np.ones((4, 4)), np.ones((4, 4)))
