"""model/preprocess.py: the transfer function, feature normalisation, alignment padding, numpy/torch agreement."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gradsep.model.frame import Features, Layer
from gradsep.model.poisson import L1Options, solve_l1
from gradsep.model.preprocess import (
    DATA_INPUTS,
    DEPTH_MAX,
    GRADIENT_INPUTS,
    MU,
    PRIOR_ALPHA,
    PRIOR_CG_STEPS,
    PRIOR_IRLS_PASSES,
    RADIANCE_MAX,
    TRANSFER,
    DepthRange,
    LogTransfer,
    aligned_size,
    crop_to,
    feature_planes,
    layer_planes,
    network_inputs,
    output_radiance,
    pad_to_alignment,
    poisson_prior,
)


def _layer(h: int, w: int, value: float = 1.0) -> Layer:
    base = np.full((h, w, 3), value, np.float32)
    return Layer(base, np.zeros_like(base), np.zeros_like(base))


def _features(h: int, w: int) -> Features:
    rng = np.random.default_rng(0)
    normal = rng.normal(size=(h, w, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return Features(rng.uniform(0, 1, (h, w, 3)).astype(np.float32), normal,
                    rng.uniform(1, 5, (h, w)).astype(np.float32))


class TestTransfer:
    def test_hand_values(self) -> None:
        # C(I) = log(1 + 16 I) / log(17): C(0) = 0, C(1) = 1, C(18) = log(289)/log(17) = 2
        assert TRANSFER.forward(np.float32(0.0)) == 0.0
        assert TRANSFER.forward(np.float32(1.0)) == pytest.approx(1.0, abs=1e-7)
        assert TRANSFER.forward(np.float32(18.0)) == pytest.approx(2.0, abs=1e-6)
        assert MU == 16.0

    @pytest.mark.parametrize("value", [1e-8, 1e-6, 1e-3, 0.5, 1.0, 10.0, 1e3, 6e4])
    def test_round_trip_across_range(self, value: float) -> None:
        x = np.array([value], np.float64)
        assert TRANSFER.inverse(TRANSFER.forward(x))[0] == pytest.approx(value, rel=1e-9, abs=1e-15)
        x32 = np.array([value], np.float32)
        assert TRANSFER.inverse(TRANSFER.forward(x32))[0] == pytest.approx(value, rel=2e-4, abs=1e-9)

    def test_transfer_bounds_its_domain_but_served_layers_are_exposure_scaled_into_it(self) -> None:
        """The transfer itself clamps to [0, RADIANCE_MAX] so its output is always finite; that is NOT what a
        1e6 frame gets when served: model.infer scales such a layer by a power of two into the trained range
        first (issue 15), so its encoded values stay below the clamp (tests/model/test_hdr_and_providers.py
        checks the energy end to end)."""
        from gradsep.model.frame import Layer
        from gradsep.model.infer import exposure_scale

        x = np.array([-5.0, np.inf], np.float32)
        y = TRANSFER.forward(x)
        assert y[0] == 0.0 and y[1] == pytest.approx(TRANSFER.max_encoded)
        back = TRANSFER.inverse(np.array([-1.0, np.inf], np.float32))
        assert back[0] == 0.0 and np.allclose(back[1:], RADIANCE_MAX, rtol=1e-4)
        rng = np.random.default_rng(0)
        base = (1e6 * (0.5 + rng.random((32, 32, 3)))).astype(np.float32)
        layer = Layer(base, np.zeros_like(base), np.zeros_like(base))
        served = base / np.float32(exposure_scale(layer))
        assert TRANSFER.forward(served).max() < 0.5 * TRANSFER.max_encoded

    def test_signed_is_odd_and_round_trips(self) -> None:
        g = np.array([-3.0, -1e-4, 0.0, 1e-4, 3.0])
        y = TRANSFER.forward_signed(g)
        assert np.allclose(y, -TRANSFER.forward_signed(-g))
        assert y[2] == 0.0
        assert np.allclose(TRANSFER.inverse_signed(y), g, rtol=1e-9)

    def test_monotone(self) -> None:
        x = np.logspace(-8, 6, 200)
        assert np.all(np.diff(TRANSFER.forward(x)) >= 0)

    def test_rejects_bad_constants(self) -> None:
        with pytest.raises(ValueError, match="mu"):
            LogTransfer(mu=0.0)

    def test_torch_matches_numpy(self) -> None:
        torch = pytest.importorskip("torch")
        x = np.concatenate([np.logspace(-8, 6, 50), -np.logspace(-8, 6, 50)]).astype(np.float32)
        for fn in ("forward", "forward_signed", "inverse_signed"):
            a = getattr(TRANSFER, fn)(x)
            b = getattr(TRANSFER, fn)(torch.from_numpy(x)).numpy()
            assert np.allclose(a, b, rtol=1e-6, atol=1e-7), fn


class TestPlanes:
    def test_layer_planes_order_and_sanitising(self) -> None:
        layer = _layer(2, 3, 2.0)
        layer.base[0, 0, 0] = np.nan
        layer.base[0, 1, 1] = -1.0
        layer.dx[1, 1, 2] = -np.inf
        layer.dy[1, 0, 0] = np.inf
        p = layer_planes(layer)
        assert p.shape == (12, 2, 3) and p.dtype == np.float32
        assert p[0, 0, 0] == 0.0 and p[1, 0, 1] == 0.0          # NaN → 0, negative base → 0
        assert p[5, 1, 1] == -RADIANCE_MAX and p[6, 1, 0] == RADIANCE_MAX
        assert np.all(p[2] == 2.0) and np.all(np.isfinite(p))
        assert np.all(p[9:12] >= 0) and np.all(p[9:12] <= RADIANCE_MAX)   # the prior, from sanitised planes

    def test_prior_is_the_truncated_l1_solution_of_the_sanitised_layer(self) -> None:
        rng = np.random.default_rng(3)
        layer = _layer(9, 11, 0.0)
        layer.base[:] = rng.random(layer.base.shape, dtype=np.float32)
        layer.dx[:] = rng.normal(0, 0.1, layer.dx.shape).astype(np.float32)
        layer.dy[:] = rng.normal(0, 0.1, layer.dy.shape).astype(np.float32)
        layer.dx[:, -1] = 0
        layer.dy[-1] = 0
        options = L1Options(iterations=PRIOR_IRLS_PASSES, cg_iterations=PRIOR_CG_STEPS)
        expected = np.clip(solve_l1(layer.base, layer.dx, layer.dy, PRIOR_ALPHA, options)[0], 0, None)
        assert np.allclose(poisson_prior(layer), expected, atol=1e-6)
        layer.base[4, 5, 1] = np.nan                            # sanitised first: NaN → 0, never propagated
        assert np.all(np.isfinite(poisson_prior(layer)))

    def test_banded_prior_matches_the_whole_frame_solve(self) -> None:
        """Tall frames are solved in overlapping bands to bound memory. The screening term keeps a pixel's
        influence local, but the truncated CG's step sizes and the IRLS weight normalisation are global, so
        the bands agree with the whole-frame solve closely, not bit for bit."""
        rng = np.random.default_rng(5)
        layer = _layer(150, 40, 0.0)
        layer.base[:] = rng.gamma(0.5, 0.4, layer.base.shape).astype(np.float32)     # skewed, with outliers
        layer.dx[:, :-1] = np.diff(layer.base, axis=1) * 0.5
        layer.dy[:-1] = np.diff(layer.base, axis=0) * 0.5
        whole = poisson_prior(layer)
        banded = poisson_prior(layer, band_rows=32, band_overlap=16)
        assert np.max(np.abs(banded - whole)) < 2e-3 * whole.max()
        assert np.mean(np.abs(banded - whole)) < 2e-3 * np.mean(whole)
        assert np.all(np.isfinite(banded)) and banded.min() >= 0

    def test_windows_crop_the_whole_layers_prior(self) -> None:
        """The prior is a global solve: a window's prior planes are the whole layer's, cropped, not a solve
        of the window alone (which would differ at the window's border)."""
        rng = np.random.default_rng(4)
        layer = _layer(12, 10, 0.0)
        layer.base[:] = rng.random(layer.base.shape, dtype=np.float32)
        layer.dx[:, :-1] = 0.3
        full = layer_planes(layer)
        window = (2, 9, 3, 10)
        assert np.array_equal(layer_planes(layer, window), full[:, 2:9, 3:10])
        assert np.array_equal(layer_planes(layer, window, poisson_prior(layer)), full[:, 2:9, 3:10])

    def test_features_nonfinite_and_ranges(self) -> None:
        f = _features(4, 5)
        f.albedo[0, 0] = [np.nan, np.inf, -np.inf]
        f.normal[1, 1] = [np.nan, 5.0, -5.0]
        f.depth[2, 2] = np.nan
        f.depth[3, 3] = np.inf
        p = feature_planes(f)
        assert p.shape == (7, 4, 5) and np.all(np.isfinite(p))
        assert p.min() >= 0.0 and p.max() <= 1.0
        assert list(p[0:3, 0, 0]) == [0.0, 1.0, 0.0]
        assert list(p[3:6, 1, 1]) == [0.5, 1.0, 0.0]           # normal·0.5+0.5 after clipping to [-1, 1]
        assert p[6, 3, 3] == 1.0                                # +Inf depth clamps to DEPTH_MAX, the frame max

    def test_depth_normalised_per_frame_even_in_a_window(self) -> None:
        f = _features(6, 6)
        f.depth[:] = np.arange(36, dtype=np.float32).reshape(6, 6)
        rng = DepthRange.of(f.depth)
        assert (rng.lo, rng.hi) == (0.0, 35.0)
        win = feature_planes(f, rng, window=(3, 6, 3, 6))
        full = feature_planes(f, rng)
        assert np.array_equal(win, full[:, 3:6, 3:6])
        assert full[6].max() == 1.0 and full[6].min() == 0.0

    def test_constant_and_huge_depth(self) -> None:
        assert np.all(DepthRange.of(np.full((3, 3), 7.0)).normalise(np.full((3, 3), 7.0)) == 0)
        d = np.array([[1.0, 1e9]], np.float32)
        assert DepthRange.of(d).hi == DEPTH_MAX

    def test_all_black_frame(self) -> None:
        layer = _layer(5, 7, 0.0)
        f = Features(np.zeros((5, 7, 3), np.float32), np.zeros((5, 7, 3), np.float32), np.zeros((5, 7), np.float32))
        data, grad = network_inputs(layer_planes(layer), feature_planes(f))
        assert data.shape == (len(DATA_INPUTS), 5, 7) and grad.shape == (len(GRADIENT_INPUTS), 5, 7)
        assert np.all(data[0:6] == 0) and np.all(grad == 0) and np.all(data[6:9] == 0)   # base, prior, albedo
        assert np.all(data[9:12] == 0.5) and np.all(data[12] == 0)

    def test_network_inputs_channel_order(self) -> None:
        layer = _layer(2, 2, 1.0)
        layer.dx[:] = 18.0
        layer.dy[:] = -18.0
        f = _features(2, 2)
        planes, feats = layer_planes(layer), feature_planes(f)
        data, grad = network_inputs(planes, feats)
        assert np.allclose(data[0:3], 1.0)                      # C(1) = 1
        assert np.allclose(data[3:6], TRANSFER.forward(planes[9:12]))
        assert np.array_equal(data[6:], feats)
        assert np.allclose(grad[0:3], 2.0) and np.allclose(grad[3:6], -2.0)

    def test_network_inputs_batched_torch_equals_numpy(self) -> None:
        torch = pytest.importorskip("torch")
        layer, f = _layer(3, 4, 0.3), _features(3, 4)
        layer.dx[:] = -0.2
        planes, feats = layer_planes(layer), feature_planes(f)
        d_np, g_np = network_inputs(planes, feats)
        d_t, g_t = network_inputs(torch.from_numpy(planes)[None], torch.from_numpy(feats)[None])
        assert np.allclose(d_t[0].numpy(), d_np, atol=1e-7) and np.allclose(g_t[0].numpy(), g_np, atol=1e-7)


class TestOutput:
    def test_output_radiance_finite_nonnegative_with_fallback(self) -> None:
        y = np.zeros((3, 2, 2), np.float32)
        y[0, 0, 0] = np.nan
        y[1, 0, 1] = np.inf
        y[2, 1, 1] = -4.0
        y[0, 1, 0] = 1.0
        fallback = np.full((2, 2, 3), 7.0, np.float32)
        out = output_radiance(y, fallback=fallback)
        assert out.shape == (2, 2, 3) and out.dtype == np.float32
        assert np.all(np.isfinite(out)) and out.min() >= 0
        assert out[0, 0, 0] == 7.0 and out[0, 1, 1] == 7.0    # non-finite → the input base
        assert out[1, 1, 2] == 0.0 and out[1, 0, 0] == pytest.approx(1.0, rel=1e-6)


class TestAlignment:
    @pytest.mark.parametrize(("h", "w"), [(1, 1), (1, 9), (7, 3), (8, 8), (17, 30)])
    def test_pad_and_crop(self, h: int, w: int) -> None:
        x = np.random.default_rng(1).normal(size=(4, h, w)).astype(np.float32)
        p = pad_to_alignment(x, 8)
        assert p.shape == (4, aligned_size(h, 8), aligned_size(w, 8))
        assert p.shape[1] % 8 == 0 and p.shape[2] % 8 == 0
        assert np.array_equal(crop_to(p, h, w), x)

    def test_reflection_not_zeros(self) -> None:
        x = np.arange(1, 4, dtype=np.float32).reshape(1, 1, 3)   # [1 2 3]
        p = pad_to_alignment(x, 8)
        assert list(p[0, 0, :6]) == [1, 2, 3, 2, 1, 2]
        assert np.all(p[0, 1:, :3] == x[0, 0])                  # a 1-row image repeats its row
        assert pad_to_alignment(x, 1) is x

    def test_aligned_size(self) -> None:
        assert [aligned_size(n, 8) for n in (1, 8, 9, 720)] == [8, 8, 16, 720]
        assert math.isclose(aligned_size(1280, 8), 1280)


def test_inference_fast_paths_are_bit_identical_to_the_shared_definitions() -> None:
    """network_inputs_numpy, poisson_prior(planes=...) and output_radiance's in-place path compute the very
    numbers of network_inputs / poisson_prior / TRANSFER.inverse (bitwise, signed zeros included)."""
    from gradsep.model.frame import Layer
    from gradsep.model.preprocess import (
        layer_planes,
        measured_planes,
        network_inputs,
        network_inputs_numpy,
        output_radiance,
        pad_to_alignment,
        poisson_prior,
        with_prior,
    )

    rng = np.random.default_rng(11)
    h, w = 21, 30
    base = rng.lognormal(0.0, 2.0, (h, w, 3)).astype(np.float32)
    dx, dy = (rng.normal(0.0, 3.0, (h, w, 3)).astype(np.float32) for _ in range(2))
    base[0, 0, 0], dx[1, 1, 1], dy[2, 2, 2], dx[3, 3, 0] = np.nan, np.inf, -1e9, -0.0
    layer = Layer(base, dx, dy)
    bits = lambda a: np.ascontiguousarray(a).view(np.uint32)  # noqa: E731

    planes = np.empty((12, h, w), np.float32)
    measured_planes(layer, out=planes[:9])
    prior = poisson_prior(layer, planes=planes[:9])
    assert np.array_equal(bits(prior), bits(poisson_prior(layer)))
    with_prior(planes, prior)
    assert np.array_equal(bits(planes), bits(layer_planes(layer, prior=prior)))

    features = rng.uniform(0.0, 1.0, (7, h, w)).astype(np.float32)
    for alignment in (1, 8):
        data, gradient = network_inputs_numpy(planes, features, alignment)
        want_data, want_gradient = (pad_to_alignment(a, alignment) for a in network_inputs(planes, features))
        assert np.array_equal(bits(data), bits(want_data)) and np.array_equal(bits(gradient), bits(want_gradient))
        assert data.flags.c_contiguous and gradient.flags.c_contiguous

    encoded = rng.normal(1.0, 2.0, (3, h, w)).astype(np.float32)
    from gradsep.model.preprocess import TRANSFER

    want = np.ascontiguousarray(TRANSFER.inverse(encoded).astype(np.float32).transpose(1, 2, 0))
    assert np.array_equal(bits(output_radiance(encoded)), bits(want))
