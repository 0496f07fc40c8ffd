"""The oidn-l1 method's refinement stage (model/refine.py): what the gradients add to a denoised layer."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model.frame import Layer, forward_differences
from gradsep.model.refine import REFINE_ALPHA, REFINED_LAYERS, RefineSolve, refine_layer


def _sharp(h: int, w: int, seed: int) -> np.ndarray:
    """A positive image with hard edges (blocks of different radiance): what a denoiser tends to blur."""
    rng = np.random.default_rng(seed)
    blocks = rng.uniform(0.1, 2.0, (h // 8 + 1, w // 8 + 1, 3))
    return np.repeat(np.repeat(blocks, 8, 0), 8, 1)[:h, :w].astype(np.float32)


def _blur(image: np.ndarray) -> np.ndarray:
    """A 5x5 box blur (edge-clamped): a stand-in for a denoiser's over-smoothing, energy kept."""
    pad = np.pad(image.astype(np.float64), ((2, 2), (2, 2), (0, 0)), mode="edge")
    out = np.zeros(image.shape, np.float64)
    for dy in range(5):
        for dx in range(5):
            out += pad[dy:dy + image.shape[0], dx:dx + image.shape[1]]
    return (out / 25).astype(np.float32)


def _layer_of(truth: np.ndarray, noise: float = 0.0, seed: int = 0) -> Layer:
    dx, dy = forward_differences(truth)
    if noise:
        rng = np.random.default_rng(seed)
        dx = dx + rng.normal(0, noise, dx.shape).astype(np.float32)
        dy = dy + rng.normal(0, noise, dy.shape).astype(np.float32)
    return Layer(truth.copy(), dx, dy)


def test_exact_gradients_restore_the_edges_a_denoiser_blurred() -> None:
    truth = _sharp(48, 64, 1)
    prior = _blur(truth)
    out = refine_layer("direct", prior, _layer_of(truth), REFINE_ALPHA)  # the plain refinement: OIDN's image only
    err_prior = np.mean(np.abs(prior - truth))
    err_out = np.mean(np.abs(out - truth))
    assert err_out < 0.5 * err_prior, (err_out, err_prior)  # measured ~0.33 at α = 1
    assert abs(out.mean() / truth.mean() - 1) < 1e-3


def test_noisy_gradients_still_help_and_keep_the_energy() -> None:
    truth = _sharp(64, 64, 2)
    prior = _blur(truth)
    out = refine_layer("direct", prior, _layer_of(truth, noise=0.05, seed=3), REFINE_ALPHA)
    assert np.mean(np.abs(out - truth)) < 0.5 * np.mean(np.abs(prior - truth))
    assert abs(out.mean() / prior.mean() - 1) < 0.01


def test_a_prior_that_agrees_with_the_gradients_is_kept() -> None:
    truth = _sharp(33, 47, 4)  # odd sizes
    out = refine_layer("direct", truth, _layer_of(truth))
    np.testing.assert_allclose(out, truth, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("name", ["indirect", "color"])
def test_only_the_direct_layer_is_refined(name: str) -> None:
    assert name not in REFINED_LAYERS
    truth = _sharp(16, 16, 5)
    prior = _blur(truth)
    assert refine_layer(name, prior, _layer_of(truth)) is prior


def test_a_layer_without_gradients_is_returned_as_denoised() -> None:
    prior = _blur(_sharp(16, 16, 6))
    assert refine_layer("direct", prior, Layer(prior.copy())) is prior


@pytest.mark.parametrize("decade", [-8, -4, 0, 4, 9])
def test_the_result_scales_with_the_exposure(decade: int) -> None:
    """Exposure-normalised: a frame k times brighter refines to exactly k times the result (the IRLS
    regulariser would otherwise treat a dim and a bright frame of one scene differently)."""
    truth = _sharp(32, 40, 7)
    prior = _blur(truth)
    layer = _layer_of(truth, noise=0.02, seed=8)
    k = 10.0 ** decade
    base = refine_layer("direct", prior, layer)
    scaled_layer = Layer(layer.base * np.float32(k), layer.dx * np.float32(k), layer.dy * np.float32(k))
    scaled = refine_layer("direct", (prior * np.float32(k)).astype(np.float32), scaled_layer)
    assert np.all(np.isfinite(scaled))
    np.testing.assert_allclose(scaled / k, base, rtol=2e-3, atol=1e-6 * float(base.max()))


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 1), (2, 3)])
def test_tiny_and_black_frames_stay_finite(shape: tuple[int, int]) -> None:
    h, w = shape
    black = np.zeros((h, w, 3), np.float32)
    out = refine_layer("direct", black, Layer(black.copy(), black.copy(), black.copy()))
    assert out.shape == (h, w, 3) and np.all(out == 0)
    bright = np.full((h, w, 3), 3.0, np.float32)
    out = refine_layer("direct", bright, _layer_of(bright))
    np.testing.assert_allclose(out, bright, rtol=1e-5)


def _old_refine(prior: np.ndarray, layer: Layer, preconditioner: str, cg_steps: int) -> np.ndarray:
    """refine_layer's solve as it was before the tolerance rule (issue 14), written out: what the fused models
    were trained on, so a call pinned to (preconditioner, cg_steps) must still give exactly this."""
    from gradsep.model import refine
    from gradsep.model.oidn import input_scale
    from gradsep.model.poisson import L1Options, solve_l1
    from gradsep.model.preprocess import scaled_image

    scale = input_scale(prior)
    data = scaled_image(prior, scale)
    options = L1Options(refine.REFINE_ITERATIONS, cg_iterations=cg_steps, preconditioner=preconditioner)
    solved, _ = solve_l1(data, scaled_image(layer.dx, scale), scaled_image(layer.dy, scale), refine.REFINE_ALPHA,
                         options)
    return np.clip(np.asarray(solved, np.float64) / scale, 0.0, np.finfo(np.float32).max).astype(np.float32)


@pytest.mark.parametrize(("preconditioner", "cg_steps"), [("dct", 4), ("mg", 2)])
def test_a_pinned_budget_gives_the_fixed_solve_bit_for_bit(preconditioner: str, cg_steps: int) -> None:
    truth = _sharp(40, 56, 4)
    prior, layer = _blur(truth), _layer_of(truth, noise=0.05, seed=5)
    out = refine_layer("direct", prior, layer, REFINE_ALPHA,
                       solve=RefineSolve(preconditioner, cg_steps=cg_steps))
    assert np.array_equal(out, _old_refine(prior, layer, preconditioner, cg_steps))


def test_the_default_solve_runs_each_pass_to_the_tolerance(monkeypatch: pytest.MonkeyPatch) -> None:
    from gradsep.model import refine

    seen = []
    real = refine.solve_l1

    def spy(*args, **kwargs):
        image, stats = real(*args, **kwargs)
        seen.append(stats)
        return image, stats

    monkeypatch.setattr(refine, "solve_l1", spy)
    truth = _sharp(40, 56, 6) ** 4  # high contrast: some passes need more than the old 2 steps
    out = refine_layer("direct", _blur(truth), _layer_of(truth, noise=0.05, seed=7), REFINE_ALPHA)
    (stats,) = seen
    assert refine.REFINE_CG_TOLERANCE is not None
    for steps, residual in zip(stats.cg_iterations[1:], stats.cg_residuals[1:], strict=True):
        assert residual <= refine.REFINE_CG_TOLERANCE or steps == refine.REFINE_MAX_CG_STEPS
    assert stats.total_cg_iterations > 2 * (stats.iterations - 1)  # not the old fixed budget
    explicit = refine_layer("direct", _blur(truth), _layer_of(truth, noise=0.05, seed=7), REFINE_ALPHA,
                            solve=RefineSolve(cg_steps=refine.REFINE_MAX_CG_STEPS,
                                              cg_tolerance=refine.REFINE_CG_TOLERANCE))
    assert np.array_equal(out, explicit)


# ---------------------------------------------------------------------------------------------------------------
# The trust rule (refine_layer without an explicit α): how far the frame's own base is trusted beside OIDN's image
# ---------------------------------------------------------------------------------------------------------------


def _noisy(truth: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """truth with relative Gaussian noise of ``sigma`` (clipped at 0, as radiance is)."""
    rng = np.random.default_rng(seed)
    return np.clip(truth * (1 + sigma * rng.standard_normal(truth.shape)), 0, None).astype(np.float32)


def _gradients(truth: np.ndarray, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    layer = _layer_of(truth, noise, seed)
    return layer.dx, layer.dy


def test_a_noiseless_base_and_gradients_come_back_as_the_base() -> None:
    """OIDN's bias must not survive when the frame itself is exact: the rule trusts the base fully."""
    from gradsep.model.refine import trust_weights

    truth = _sharp(48, 64, 11)
    prior = _blur(truth)  # OIDN's over-smoothing
    layer = _layer_of(truth)
    assert np.all(trust_weights(truth, layer.dx, layer.dy) == 1.0)
    out = refine_layer("direct", prior, layer)
    assert np.mean(np.abs(out - truth)) < 1e-3 * np.mean(truth)
    plain = refine_layer("direct", prior, layer, REFINE_ALPHA)
    assert np.mean(np.abs(plain - truth)) > 10 * np.mean(np.abs(out - truth))


def test_a_slightly_noisy_base_beats_a_biased_prior() -> None:
    """Low noise (the clean-layer regime): the rule's result is closer to the truth than the plain refinement."""
    truth = _sharp(64, 64, 12)
    prior = _blur(truth)
    layer = Layer(_noisy(truth, 0.01, 13), *_gradients(truth, 0.002, 14))
    err_rule = np.mean(np.abs(refine_layer("direct", prior, layer) - truth))
    err_plain = np.mean(np.abs(refine_layer("direct", prior, layer, REFINE_ALPHA) - truth))
    assert err_rule < 0.5 * err_plain, (err_rule, err_plain)


def test_a_very_noisy_base_leans_on_oidn() -> None:
    """A base far noisier than its gradients' detail is not mixed in: the plain refinement of OIDN's image, bit
    for bit."""
    from gradsep.model.refine import trust_weights

    truth = _sharp(48, 64, 15)
    prior = _blur(truth)
    layer = Layer(_noisy(truth, 1.0, 16), *_gradients(truth, 0.05, 17))
    assert np.all(trust_weights(layer.base, layer.dx, layer.dy) == 0.0)
    assert np.array_equal(refine_layer("direct", prior, layer), refine_layer("direct", prior, layer, REFINE_ALPHA))


def test_the_weight_falls_with_the_base_noise() -> None:
    from gradsep.model.refine import trust_weights

    truth = _sharp(64, 64, 18)
    layer = _layer_of(truth)
    means = []
    for sigma in (0.0, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0):
        w = trust_weights(_noisy(truth, sigma, 19), layer.dx, layer.dy)
        assert w.shape == (64, 64, 1) and w.dtype == np.float32 and np.all((w >= 0) & (w <= 1))
        means.append(float(w.mean()))
    assert means == sorted(means, reverse=True) and means[0] == 1.0 and means[-1] == 0.0, means


def test_the_weights_on_degenerate_layers() -> None:
    from gradsep.model.refine import trust_weights

    flat = np.full((6, 7, 3), 2.0, np.float32)
    zero = np.zeros_like(flat)
    assert np.all(trust_weights(flat, zero, zero) == 1.0)  # flat and agreeing: noise-free
    bumpy = flat.copy()
    bumpy[3, 3] = 5.0
    assert np.all(trust_weights(bumpy, zero, zero) == 0.0)  # structure the gradients deny, in every window
    one = np.ones((1, 1, 3), np.float32)
    assert trust_weights(one, np.zeros_like(one), np.zeros_like(one)).shape == (1, 1, 1)
    huge = np.full((5, 5, 3), np.finfo(np.float32).max / 4, np.float32)
    huge[2, 2] = 0.0
    w = trust_weights(huge, np.zeros_like(huge), np.zeros_like(huge))
    assert np.all(np.isfinite(w)) and np.all(w == 0.0)


def test_a_non_finite_base_falls_back_to_the_plain_refinement() -> None:
    """The frame reader's policy keeps NaN/Inf out; a direct caller that lets one through gets OIDN's refinement
    (the base is not mixed in), finite."""
    truth = _sharp(24, 32, 20)
    layer = _layer_of(truth)
    base = layer.base.copy()
    base[5, 5] = np.nan
    base[6, 6] = np.inf
    out = refine_layer("direct", _blur(truth), Layer(base, layer.dx, layer.dy))
    assert np.all(np.isfinite(out))
    assert np.array_equal(out, refine_layer("direct", _blur(truth), layer, REFINE_ALPHA))


@pytest.mark.parametrize("decade", [-8, 0, 9])
@pytest.mark.parametrize("sigma", [0.005, 0.5])
def test_the_rule_is_exposure_invariant(decade: int, sigma: float) -> None:
    """Both regimes (base mixed in or not) at 1e-8 … 1e9 radiance: finite, and k times the result at k times the
    light (the statistic is a ratio at mean-1 exposure)."""
    truth = _sharp(32, 40, 21)
    prior = _blur(truth)
    layer = Layer(_noisy(truth, sigma, 22), *_gradients(truth, 0.01, 23))
    k = np.float32(10.0 ** decade)
    ref = refine_layer("direct", prior, layer)
    out = refine_layer("direct", prior * k, Layer(layer.base * k, layer.dx * k, layer.dy * k))
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    np.testing.assert_allclose(out / k, ref, rtol=2e-3, atol=1e-6 * float(ref.max()))


def test_the_frame_wide_part_of_the_rule() -> None:
    """A layer clean as a whole is trusted everywhere at the lower α (the l1 method's regime); a noisy one keeps
    OIDN's image as the data term at REFINE_ALPHA; degenerate layers give a finite or infinite r, never NaN."""
    from gradsep.model.refine import TRUST_ALPHA_BASE, frame_disagreement, trusted_data

    truth = _sharp(48, 64, 24)
    prior = _blur(truth)
    layer = _layer_of(truth)
    assert frame_disagreement(truth, prior, layer.dx, layer.dy) < 1e-9  # float32 differences round
    data, alpha = trusted_data(truth, prior, layer.dx, layer.dy)
    assert alpha == TRUST_ALPHA_BASE
    np.testing.assert_allclose(data, truth, rtol=1e-6)  # prior + 1·(base − prior), rounded
    noisy = _noisy(truth, 1.0, 25)
    assert frame_disagreement(noisy, prior, layer.dx, layer.dy) > 1.0
    data, alpha = trusted_data(noisy, prior, *_gradients(truth, 0.05, 26))
    assert alpha == REFINE_ALPHA and data is prior
    flat = np.full((4, 5, 3), 2.0, np.float32)
    zero = np.zeros_like(flat)
    assert frame_disagreement(flat, flat, zero, zero) == 0.0
    bumpy = flat.copy()
    bumpy[1, 1] = 3.0
    assert frame_disagreement(bumpy, flat, zero, zero) == float("inf")


def _shadow_edge(h: int = 32, w: int = 40, noise: float = 0.002, seed: int = 31) -> tuple[np.ndarray, Layer]:
    """A clean direct layer with an umbra: a bright lit region (radiance ~50) beside pixels of exactly 0 (no sample
    found light), gradients with a little noise, as a many-spp G-PT layer has. Returns (prior, layer)."""
    rng = np.random.default_rng(seed)
    truth = np.full((h, w, 3), 50.0, np.float32) * rng.uniform(0.9, 1.1, (h, w, 1)).astype(np.float32)
    truth[:, w // 2:] = 0.0
    dx, dy = _gradients(truth, noise * 50.0, seed + 1)
    dark = np.all(truth == 0, axis=-1)  # a G-PT gradient between two umbra pixels is exactly 0 (both samples are)
    dx[:, :-1][dark[:, :-1] & dark[:, 1:]] = 0.0
    dy[:-1][dark[:-1] & dark[1:]] = 0.0
    dx[:, -1] = 0.0  # the frame contract stores 0 past the last column / row
    dy[-1] = 0.0
    return _blur(truth), Layer(_noisy(truth, 0.01, seed + 2), dx, dy)  # relative noise: the umbra stays 0


def test_the_clean_layer_gets_a_per_pixel_alpha_with_zero_pixels_pinned() -> None:
    from gradsep.model.refine import (
        TRUST_ALPHA_BASE,
        TRUST_ALPHA_CLEAN,
        TRUST_ALPHA_ZERO,
        input_scale,
        scaled_image,
        trust_terms,
    )

    prior, layer = _shadow_edge()
    s = input_scale(prior)
    data, alpha, m = trust_terms(*(scaled_image(a, s) for a in (layer.base, prior, layer.dx, layer.dy)))
    assert alpha == TRUST_ALPHA_BASE and m is not None and m.shape == layer.base.shape[:2]
    zero = np.all(layer.base == 0, axis=-1)
    np.testing.assert_allclose(m[zero], TRUST_ALPHA_ZERO / alpha, rtol=1e-6)
    np.testing.assert_allclose(m[~zero], TRUST_ALPHA_CLEAN / alpha, rtol=1e-6)
    truth = _sharp(32, 40, 32)  # a noisy layer: no frame-wide trust, no map
    noisy = Layer(_noisy(truth, 1.0, 33), *_gradients(truth, 0.5, 34))
    prior = _blur(truth)
    scaled = (scaled_image(a, input_scale(prior)) for a in (noisy.base, prior, noisy.dx, noisy.dy))
    assert trust_terms(*scaled)[2] is None


def test_black_pixels_beside_bright_ones_stay_black_on_a_clean_layer(monkeypatch) -> None:
    """What the zero-pixel pin is for: a lower clean α alone leaks the bright side of a shadow edge into the umbra
    (a relative error weighs each unit there a hundredfold)."""
    from gradsep.model import refine

    prior, layer = _shadow_edge()
    umbra = np.s_[:, 20:]
    shipped = refine_layer("direct", prior, layer)
    monkeypatch.setattr(refine, "TRUST_ALPHA_ZERO", refine.TRUST_ALPHA_CLEAN)  # one low α everywhere
    unpinned = refine_layer("direct", prior, layer)
    leak, leak_unpinned = float(np.abs(shipped[umbra]).sum()), float(np.abs(unpinned[umbra]).sum())
    assert leak < 0.5 * leak_unpinned, (leak, leak_unpinned)
    assert np.all(np.isfinite(shipped)) and np.all(shipped >= 0)


def test_a_clean_layer_starts_from_the_l2_solve_at_its_clean_alpha(monkeypatch) -> None:
    """The IRLS of a clean layer starts from the exact L2 solve at the α of its non-black pixels (the map's smallest
    α·m), not at the scalar α: with pass 0 alone the refinement is that L2 solve. A noisy layer (no map) starts
    from its scalar α."""
    from gradsep.model import refine
    from gradsep.model.poisson import solve_l2

    prior, layer = _shadow_edge(h=48, w=64, seed=61)
    s = refine.input_scale(prior)
    base, data0, dx, dy = (refine.scaled_image(a, s) for a in (layer.base, prior, layer.dx, layer.dy))
    data, alpha, m = refine.trust_terms(base, data0, dx, dy)
    assert m is not None and alpha * float(m.min()) == pytest.approx(refine.TRUST_ALPHA_CLEAN)
    monkeypatch.setattr(refine, "REFINE_ITERATIONS", 1)  # pass 0 only: the start itself
    start = np.clip(solve_l2(data, dx, dy, refine.TRUST_ALPHA_CLEAN, dtype=np.float64) / s, 0, None)
    np.testing.assert_allclose(refine_layer("direct", prior, layer), start, rtol=1e-4, atol=1e-4)
    scalar = np.clip(solve_l2(data, dx, dy, alpha, dtype=np.float64) / s, 0, None)
    assert np.abs(start - scalar).max() > 1e-2  # the scalar start is well beyond that tolerance
    truth = _sharp(32, 40, 62)
    noisy = Layer(_noisy(truth, 1.0, 63), *_gradients(truth, 0.5, 64))
    prior = _blur(truth)
    s = refine.input_scale(prior)
    scaled = [refine.scaled_image(a, s) for a in (prior, noisy.dx, noisy.dy)]
    want = np.clip(solve_l2(*scaled, refine.REFINE_ALPHA, dtype=np.float64) / s, 0, None)
    np.testing.assert_allclose(refine_layer("direct", prior, noisy), want, rtol=1e-4, atol=1e-4)


def test_a_black_pixel_is_pinned_only_where_the_gradients_agree_it_is_black() -> None:
    """An umbra (base 0 and gradients 0 around it) stays pinned; a pixel whose base is 0 while the gradients say it
    is lit (a hard edge crossing it, missed by every primal sample) takes the clean α and is filled in."""
    from gradsep.model import refine

    prior, layer = _shadow_edge(h=32, w=40, seed=71)
    base = layer.base.copy()
    base[10, 8] = 0.0  # lit, but no primal sample found the light; its gradients (from the truth) say otherwise
    layer = Layer(base, layer.dx, layer.dy)
    s = refine.input_scale(prior)
    _, alpha, m = refine.trust_terms(*(refine.scaled_image(a, s) for a in (base, prior, layer.dx, layer.dy)))
    clean, frame = float(m.min()), (1.0 - float(m.min())) / (1.0 - refine.TRUST_ALPHA_CLEAN / alpha)
    assert frame > 0.9  # a clean layer
    assert m[10, 30] == pytest.approx(1.0 - (1.0 - refine.TRUST_ALPHA_ZERO / alpha) * frame, rel=1e-5)  # umbra
    assert m[10, 8] <= clean + 0.05 * (m[10, 30] - clean)  # nearly the clean α: not pinned
    shipped = refine_layer("direct", prior, layer)
    assert np.all(np.isfinite(shipped)) and np.all(shipped >= 0)
    assert abs(float(shipped[10, 8].mean()) - 50.0) < 10.0  # filled in from its neighbours, not left black


@pytest.mark.parametrize("firefly", [1e4, 1e8, 1e20])
def test_a_gradient_firefly_changes_the_trust_weights_only_near_it(firefly: float) -> None:
    """The trust rule's windows are direct sums: with a running-sum box filter, a firefly's squared gradient (1e16
    at 1e8) left float32 rounding behind it and moved the weights along its whole row (by up to 0.6)."""
    from scipy.ndimage import gaussian_filter

    from gradsep.model.refine import trust_weights

    rng = np.random.default_rng(0)
    truth = (0.5 + gaussian_filter(rng.random((64, 64, 3)), (1, 1, 0))).astype(np.float32)
    dx, dy = forward_differences(truth)
    base = (truth + 0.02 * rng.standard_normal((64, 64, 3))).astype(np.float32)
    before = trust_weights(base, dx, dy)[..., 0]
    assert 0.2 < before.mean() < 0.9  # the rule is on its ramp here, where a change would show
    dx = dx.copy()
    dx[30, 5] = firefly
    after = trust_weights(base, dx, dy)[..., 0]
    far = np.ones((64, 64), bool)
    far[26:35, 1:10] = False  # the firefly's own windows
    np.testing.assert_allclose(after[far], before[far], atol=1e-6)
