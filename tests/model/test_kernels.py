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
