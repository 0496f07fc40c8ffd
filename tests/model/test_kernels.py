"""The compiled IRLS kernels (model/kernels.py): the fused inner loop gives the numpy formulation's result."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model import kernels
from gradsep.model.frame import forward_differences
from gradsep.model.poisson import solve_l1


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("dtype_alpha", [0.2, 1e-3], ids=["float32", "float64"])
def test_compiled_kernels_match_the_numpy_path(monkeypatch: pytest.MonkeyPatch, dtype_alpha: float) -> None:
    """model.kernels fuses the IRLS inner loop; it must give the numpy formulation's result to rounding."""
    rng = np.random.default_rng(11)
    truth = rng.random((37, 53, 3))
    dx, dy = forward_differences(truth)
    base = truth * (1 + 0.5 * rng.standard_normal(truth.shape))
    dx, dy = dx + 0.1 * rng.standard_normal(dx.shape), dy + 0.1 * rng.standard_normal(dy.shape)
    compiled, stats_c = solve_l1(base, dx, dy, dtype_alpha)
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    plain, stats_p = solve_l1(base, dx, dy, dtype_alpha)
    np.testing.assert_allclose(compiled, plain, rtol=0, atol=2e-5 * np.abs(plain).max())
    np.testing.assert_allclose(stats_c.energies, stats_p.energies, rtol=1e-4)
    assert stats_c.cg_iterations == stats_p.cg_iterations


def _scipy_box(image: np.ndarray, size: int) -> np.ndarray:
    from scipy.ndimage import correlate1d

    weights = np.full(size, 1.0 / size, image.dtype)
    return correlate1d(correlate1d(image, weights, axis=0, mode="nearest"), weights, axis=1, mode="nearest")


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (4, 6), (23, 40)])
@pytest.mark.parametrize("size", [3, 5, 17])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_compiled_box_mean_is_scipys_to_rounding(monkeypatch: pytest.MonkeyPatch, shape: tuple[int, int],
                                                     size: int, dtype: type) -> None:
    """model.robust.box_mean runs compiled for 2-D float images and odd sizes: the same means (edges repeated,
    a box wider than the image included) as scipy's two direct 1-D sums, in the image's dtype."""
    from gradsep.model.robust import box_mean

    image = (np.random.default_rng(size).random(shape) * 10.0 ** (np.arange(shape[1])[None, :] % 7)).astype(dtype)
    got = box_mean(image, size)
    assert got.dtype == dtype and got.shape == shape
    np.testing.assert_allclose(got, _scipy_box(image, size), rtol=4e-7 if dtype == np.float32 else 1e-14)
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    np.testing.assert_array_equal(box_mean(image, size), _scipy_box(image, size))


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba is not installed")
def test_the_compiled_box_mean_keeps_a_huge_value_to_its_own_windows() -> None:
    """Direct sums: a firefly's variance (1e30) beside 1e-6 raises only the windows that hold it; the rest of its
    row and column read 1e-6 exactly (a running sum would leave them 0 or garbage), and NaN and inf stay in their
    windows too."""
    from gradsep.model.robust import box_mean

    image = np.full((40, 60), 1e-6, np.float32)
    image[20, 30] = 1e30
    image[2, 2], image[37, 57] = np.nan, np.inf
    got = box_mean(image, 17)
    held = np.zeros(image.shape, bool)
    held[12:29, 22:39] = True
    np.testing.assert_allclose(got[held], 1e30 / 289, rtol=1e-6)
    poisoned = np.zeros(image.shape, bool)
    poisoned[:11, :11] = True  # the NaN's windows (edges repeated)
    poisoned[29:, 49:] = True  # the inf's
    assert np.isnan(got[:11, :11]).all() and np.isposinf(got[29:, 49:]).all()
    np.testing.assert_allclose(got[~held & ~poisoned], 1e-6, rtol=1e-6)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba is not installed")
def test_the_compiled_gather_is_take() -> None:
    """A whole-pixel warp (model.warp.Sampler on integral positions) gathers compiled: np.take's values."""
    rng = np.random.default_rng(3)
    flat = rng.random((50, 3)).astype(np.float32)
    index = rng.integers(0, 50, 80).astype(np.int32)
    np.testing.assert_array_equal(kernels.gather(flat, index, np.empty((80, 3), np.float32)),
                                  np.take(flat, index, axis=0))
