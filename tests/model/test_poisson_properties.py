"""Property-based tests (hypothesis) of the screened Poisson solvers.

* exact data: a base image with its exact forward differences is the minimiser of both energies for every α, so
  each solver must return it -- for any size and any α in 1e-6 .. 1e3;
* homogeneity: scaling the inputs scales the output (exactly for L2; for L1 with its regulariser, which is in
  radiance units, scaled alike);
* black in, black out.

Images come from numpy generators seeded by hypothesis; hypothesis picks the size, α, scale and the kind of
content (smooth, random, sparse), which is what the solvers' code paths depend on.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gradsep.model.frame import forward_differences
from gradsep.model.poisson import L1Options, solve_l1, solve_l2

SETTINGS = settings(max_examples=30, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
sizes = st.integers(1, 24)
alphas = st.floats(-6, 3).map(lambda e: 10.0**e)
seeds = st.integers(0, 2**32 - 1)
kinds = st.sampled_from(["smooth", "random", "sparse"])


def image(h: int, w: int, seed: int, kind: str) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "smooth":
        yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
        f = rng.uniform(1, 6, 3)
        return np.stack([0.5 + 0.45 * np.sin(f[c] * xx + c) * np.cos(f[2 - c] * yy) for c in range(3)], -1)
    if kind == "random":
        return rng.uniform(0.01, 1.0, (h, w, 3))
    img = np.full((h, w, 3), 1e-3)  # mostly dark with a few bright pixels (fireflies, small lights)
    img[rng.random((h, w)) < 0.05] = 50.0
    return img


def noisy(h: int, w: int, seed: int, kind: str) -> tuple[np.ndarray, ...]:
    clean = image(h, w, seed, kind)
    rng = np.random.default_rng(seed + 1)
    dx, dy = forward_differences(clean)
    return tuple(a + rng.normal(0, 0.2, a.shape) for a in (clean, dx, dy))


@SETTINGS
@given(sizes, sizes, alphas, seeds, kinds)
def test_l2_recovers_exact_data_for_any_alpha(h: int, w: int, alpha: float, seed: int, kind: str) -> None:
    exact = image(h, w, seed, kind)
    got = solve_l2(exact, *forward_differences(exact), alpha, dtype=np.float64)
    # float64 DCTs: ~1e-15 of the peak per pixel, ÷ α² on the constant mode only (whose coefficient is exact)
    assert np.abs(got - exact).max() <= 1e-9 * exact.max(), f"α={alpha:g}"
    assert abs(got.mean() - exact.mean()) <= 1e-12 * exact.max()


@SETTINGS
@given(sizes, sizes, alphas, seeds, kinds)
def test_l1_recovers_exact_data_for_any_alpha(h: int, w: int, alpha: float, seed: int, kind: str) -> None:
    """IRLS starts at the exact L2 solution; its reweighting must not move away from a zero-residual answer
    (float32 iterates on inputs scaled to peak 1: ~1e-7 of the peak, docs/poisson.md)."""
    exact = image(h, w, seed, kind)
    got, stats = solve_l1(exact, *forward_differences(exact), alpha, L1Options(dtype=np.float64))
    assert np.abs(got - exact).max() <= 1e-6 * exact.max(), f"α={alpha:g}"
    assert np.isfinite(stats.energies).all()


@SETTINGS
@given(sizes, sizes, alphas, seeds, kinds, st.floats(-8, 8).map(lambda e: 10.0**e))
def test_scaling_the_input_scales_the_l2_output(h: int, w: int, alpha: float, seed: int, kind: str,
                                                scale: float) -> None:
    base, dx, dy = noisy(h, w, seed, kind)
    l2 = solve_l2(base, dx, dy, alpha, dtype=np.float64)
    l2s = solve_l2(base * scale, dx * scale, dy * scale, alpha, dtype=np.float64)
    np.testing.assert_allclose(l2s / scale, l2, rtol=1e-9, atol=1e-9 * np.abs(l2).max())


@SETTINGS
@given(sizes, sizes, alphas, seeds, kinds, st.integers(-60, 60))
def test_scaling_the_input_scales_the_l1_output(h: int, w: int, alpha: float, seed: int, kind: str,
                                                exponent: int) -> None:
    """IRLS normalises its inputs to peak 1 and its regulariser is in radiance units: scaled by a power of two
    (exact in floating point) with the regulariser scaled alike, every iterate is bit-for-bit the same, so the
    output is exactly the scaled output. (With a non-power-of-two scale the float32 rounding differs, and CG's
    relative stopping test can stop one step earlier or later: equal only to ~1 %.)"""
    scale = 2.0**exponent
    base, dx, dy = noisy(h, w, seed, kind)
    l1, _ = solve_l1(base, dx, dy, alpha, L1Options(dtype=np.float64))
    l1s, _ = solve_l1(base * scale, dx * scale, dy * scale, alpha, L1Options(reg_init=0.05 * scale, dtype=np.float64))
    np.testing.assert_allclose(l1s / scale, l1, rtol=1e-12, atol=1e-12 * np.abs(l1).max())


@SETTINGS
@given(sizes, sizes, alphas)
def test_black_in_black_out(h: int, w: int, alpha: float) -> None:
    zeros = np.zeros((h, w, 3), np.float32)
    assert not solve_l2(zeros, zeros, zeros, alpha).any()
    got, stats = solve_l1(zeros, zeros, zeros, alpha)
    assert not got.any() and stats.energies[-1] == 0
