"""Screened Poisson solvers: the DCT closed form against a sparse direct solve, IRLS behaviour and API."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from gradsep.model.frame import forward_differences
from gradsep.model.poisson import L1_PASSES, MIN_ALPHA, L1Options, energy_l1, energy_l2, solve_l1, solve_l2


def _difference_matrix(n: int) -> sp.csr_matrix:
    """(n-1) x n forward differences: the contract's operator without the (zero) last entry."""
    if n == 1:
        return sp.csr_matrix((0, 1))
    return sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n)).tocsr()


def _sparse_solve(base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float) -> np.ndarray:
    """The L2 problem written out as a sparse least-squares system and solved directly, per channel.

    Row-major pixel order: H_x = I_H ⊗ D_W, H_y = D_H ⊗ I_W; normal equations (α² + HᵀH) I = α² b + Hᵀ g.
    """
    h, w, c = base.shape
    hx = sp.kron(sp.eye(h), _difference_matrix(w)).tocsr()
    hy = sp.kron(_difference_matrix(h), sp.eye(w)).tocsr()
    a = (alpha**2 * sp.eye(h * w) + hx.T @ hx + hy.T @ hy).tocsc()
    out = np.empty((h, w, c))
    for ch in range(c):
        rhs = alpha**2 * base[..., ch].ravel() + hx.T @ dx[:, :-1, ch].ravel() + hy.T @ dy[:-1, :, ch].ravel()
        out[..., ch] = spl.spsolve(a, rhs).reshape(h, w)
    return out


def _random_problem(h: int, w: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    base, dx, dy = (rng.normal(size=(h, w, 3)) for _ in range(3))
    dx[:, -1] = 0
    dy[-1] = 0
    return base, dx, dy


def _smooth_image(h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w, 1)
    return np.stack([0.5 + 0.3 * np.sin(5 * xx + c) * np.cos(3 * yy) for c in range(3)], -1).astype(np.float32)


SIZES = [(1, 1), (1, 9), (8, 1), (5, 6), (13, 9), (24, 31)]


@pytest.mark.parametrize("alpha", [1e-2, 0.2, 10.0, 1e3])
@pytest.mark.parametrize("size", SIZES)
def test_l2_equals_sparse_direct_solve(size: tuple[int, int], alpha: float) -> None:
    base, dx, dy = _random_problem(*size)
    got = solve_l2(base, dx, dy, alpha, dtype=np.float64)
    want = _sparse_solve(base, dx, dy, alpha)
    assert got.dtype == np.float64
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * max(1.0, np.abs(want).max()))


@pytest.mark.parametrize("size", SIZES)
def test_l2_tiny_alpha_is_exact_where_the_sparse_solve_is_not(size: tuple[int, int]) -> None:
    """At α = 1e-4 the constant mode has eigenvalue 1e-8: spsolve's mean drifts by ~1e-9, ours does not.

    The exact mean is known (1ᵀ(α² + HᵀH) I = α² 1ᵀI and 1ᵀHᵀg = 0, so mean(I) = mean(base)); the zero-mean
    part is well conditioned and must match the direct solve to 1e-10.
    """
    alpha = 1e-4
    base, dx, dy = _random_problem(*size, seed=3)
    got = solve_l2(base, dx, dy, alpha, dtype=np.float64)
    want = _sparse_solve(base, dx, dy, alpha)
    np.testing.assert_allclose(got.mean(axis=(0, 1)), base.mean(axis=(0, 1)), rtol=0, atol=1e-12)
    centred = got - got.mean(axis=(0, 1)), want - want.mean(axis=(0, 1))
    np.testing.assert_allclose(*centred, rtol=0, atol=1e-10)


def test_l2_ignores_the_contract_zero_column_and_row() -> None:
    """The last column of dx and last row of dy have no term in the operator: their values cannot matter."""
    base, dx, dy = _random_problem(9, 11)
    dx2, dy2 = dx.copy(), dy.copy()
    dx2[:, -1] = 123.0
    dy2[-1] = -7.0
    np.testing.assert_array_equal(solve_l2(base, dx, dy), solve_l2(base, dx2, dy2))


def test_l2_minimises_its_energy() -> None:
    base, dx, dy = _random_problem(10, 12, seed=5)
    x = solve_l2(base, dx, dy, 0.2, dtype=np.float64)
    best = energy_l2(x, base, dx, dy, 0.2)
    rng = np.random.default_rng(1)
    for _ in range(5):
        assert energy_l2(x + 1e-3 * rng.normal(size=x.shape), base, dx, dy, 0.2) > best


@pytest.mark.parametrize("method", ["l1", "l2"])
def test_channels_are_independent_for_l2_and_2d_input_works(method: str) -> None:
    base, dx, dy = _random_problem(7, 8)
    if method == "l2":
        full = solve_l2(base, dx, dy)
        for c in range(3):
            np.testing.assert_allclose(solve_l2(base[..., c], dx[..., c], dy[..., c]), full[..., c], atol=1e-6)
    else:
        single, stats = solve_l1(base[..., 0], dx[..., 0], dy[..., 0])
        assert single.shape == (7, 8) and single.dtype == np.float32 and np.isfinite(single).all()
        assert stats.iterations == L1_PASSES


@pytest.mark.parametrize("method", ["l1", "l2"])
@pytest.mark.parametrize("size", [(1, 1), (1, 17), (15, 1), (9, 14), (33, 20)])
def test_exact_data_is_recovered(method: str, size: tuple[int, int]) -> None:
    image = _smooth_image(*size)
    dx, dy = forward_differences(image)
    got = solve_l2(image, dx, dy) if method == "l2" else solve_l1(image, dx, dy)[0]
    assert np.abs(got - image).max() <= 1e-6 * np.abs(image).max()


def test_l1_stats_describe_every_pass() -> None:
    image = _smooth_image(20, 24)
    rng = np.random.default_rng(2)
    base = image + rng.normal(0, 0.1, image.shape).astype(np.float32)
    dx, dy = forward_differences(image)
    _, stats = solve_l1(base, dx, dy, options=L1Options(iterations=6, cg_iterations=3))
    assert stats.iterations == 6
    assert len(stats.cg_iterations) == len(stats.cg_residuals) == len(stats.energies) == 6
    assert stats.cg_iterations[0] == 0 and all(1 <= n <= 3 for n in stats.cg_iterations[1:])
    assert stats.total_cg_iterations == sum(stats.cg_iterations)
    assert stats.seconds > 0
    assert stats.energies[-1] < stats.energies[0]  # reweighting lowers the L1 energy of the L2 start


def test_l1_energy_reported_matches_the_returned_image() -> None:
    image = _smooth_image(16, 18)
    rng = np.random.default_rng(4)
    base = image + rng.normal(0, 0.2, image.shape).astype(np.float32)
    dx, dy = (g + rng.normal(0, 0.05, g.shape).astype(np.float32) for g in forward_differences(image))
    x, stats = solve_l1(base, dx, dy)
    assert energy_l1(x, base, dx, dy, 0.2) == pytest.approx(stats.energies[-1], rel=1e-4)
    assert stats.energies[-1] < energy_l1(solve_l2(base, dx, dy), base, dx, dy, 0.2)


@pytest.mark.parametrize("preconditioner", ["dct", "mg"])
def test_l1_preconditioners_converge_to_the_same_minimiser(preconditioner: str) -> None:
    """Run to convergence, every preconditioner must reach the same IRLS fixed point (they only change speed)."""
    image = _smooth_image(12, 14)
    rng = np.random.default_rng(6)
    base = image + rng.normal(0, 0.2, image.shape).astype(np.float32)
    dx, dy = forward_differences(image)
    kwargs = dict(iterations=8, cg_iterations=400, cg_tolerance=1e-6, dtype=np.float64)
    ref, _ = solve_l1(base, dx, dy, options=L1Options(preconditioner="dct", **kwargs))
    got, _ = solve_l1(base, dx, dy, options=L1Options(preconditioner=preconditioner, **kwargs))
    np.testing.assert_allclose(got, ref, atol=1e-4)


def test_l1_is_more_robust_than_l2_to_a_gradient_outlier() -> None:
    """One corrupted gradient term: L2 spreads it over the image, L1 all but ignores it."""
    image = _smooth_image(32, 40)
    rng = np.random.default_rng(0)
    base = image + rng.normal(0, 0.05, image.shape).astype(np.float32)
    dx, dy = forward_differences(image)
    dx[16, 20] += 50.0
    err_l2 = np.abs(solve_l2(base, dx, dy) - image).max()
    err_l1 = np.abs(solve_l1(base, dx, dy)[0] - image).max()
    assert err_l2 > 1.0
    assert err_l1 < 0.05 * err_l2


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(alpha=0.0), "alpha"),
        (dict(alpha=-1.0), "alpha"),
        (dict(alpha=float("nan")), "alpha"),
        (dict(alpha=float("inf")), "alpha"),
        (dict(alpha=1e-200), "at least"),  # alpha² underflows: the mean would be undetermined (issue 15)
        (dict(alpha=MIN_ALPHA / 2), "at least"),
    ],
)
@pytest.mark.parametrize("solver", ["l1", "l2"])
def test_bad_alpha_is_rejected(solver: str, kwargs: dict, match: str) -> None:
    base, dx, dy = _random_problem(4, 4)
    fn = solve_l2 if solver == "l2" else solve_l1
    with pytest.raises(ValueError, match=match):
        fn(base, dx, dy, **kwargs)


@pytest.mark.parametrize("solver", ["l1", "l2"])
def test_smallest_alpha_is_exact_on_exact_data(solver: str) -> None:
    """At MIN_ALPHA (the smallest accepted α) both solvers still return the exact image from exact data,
    mean included: the documented range is honoured, not merely not rejected."""
    rng = np.random.default_rng(3)
    truth = (0.5 + rng.random((24, 40, 3))).astype(np.float32)
    dx, dy = forward_differences(truth)
    out = solve_l2(truth, dx, dy, MIN_ALPHA) if solver == "l2" else solve_l1(truth, dx, dy, MIN_ALPHA)[0]
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out, truth, atol=1e-5)


@pytest.mark.parametrize("solver", ["l1", "l2"])
def test_bad_inputs_are_named(solver: str) -> None:
    fn = solve_l2 if solver == "l2" else solve_l1
    base, dx, dy = _random_problem(4, 5)
    with pytest.raises(ValueError, match="dy has shape"):
        fn(base, dx, dy[:, :4])
    bad = dx.copy()
    bad[1, 1, 1] = np.nan
    bad[2, 2, 2] = np.inf
    with pytest.raises(ValueError, match="dx contains 2 non-finite"):
        fn(base, bad, dy)
    with pytest.raises(ValueError, match="empty"):
        fn(base[:0], dx[:0], dy[:0])
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        fn(base[0, 0], dx[0, 0], dy[0, 0])


def test_l1_bad_options_are_rejected() -> None:
    for bad, match in (({"iterations": 0}, "iterations"), ({"cg_iterations": 0}, "cg_iterations"),
                       ({"reg_init": 0.0}, "reg"), ({"reg_decay": 1.5}, "reg_decay"),
                       ({"preconditioner": "ilu"}, "preconditioner")):
        with pytest.raises(ValueError, match=match):
            L1Options(**bad)


@pytest.mark.parametrize("size", [(1, 1), (5, 7)])
def test_solvers_never_modify_their_inputs(size: tuple[int, int]) -> None:
    """solve_l1 scales its working copies in place: they must be copies even when no conversion is needed."""
    base, dx, dy = (a.astype(np.float32) for a in _random_problem(*size))
    before = [a.copy() for a in (base, dx, dy)]
    solve_l1(base, dx, dy)
    solve_l2(base, dx, dy)
    for a, b in zip((base, dx, dy), before, strict=True):
        np.testing.assert_array_equal(a, b)



# ---------------------------------------------------------------------------------------------------------------
# A per-pixel α (``alpha_map``: model/refine.py's clean-layer rule)
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preconditioner", ["dct", "mg"])
def test_an_alpha_map_of_ones_is_the_solve_without_one(preconditioner: str) -> None:
    base, dx, dy = _random_problem(23, 31, 5)
    plain, _ = solve_l1(base, dx, dy, 0.5, L1Options(preconditioner=preconditioner))
    ones, _ = solve_l1(base, dx, dy, 0.5, L1Options(preconditioner=preconditioner), alpha_map=np.ones((23, 31)))
    np.testing.assert_allclose(ones, plain, rtol=0, atol=1e-6 * float(np.abs(plain).max()))


def test_a_large_alpha_map_pins_its_pixels_to_the_base() -> None:
    base, dx, dy = _random_problem(16, 16, 7)
    m = np.ones((16, 16))
    m[4:8, 4:8] = 1e3
    out, _ = solve_l1(base, dx, dy, 0.2, alpha_map=m)
    free, _ = solve_l1(base, dx, dy, 0.2)
    pinned = np.abs(out[4:8, 4:8] - base[4:8, 4:8]).max()
    assert pinned < 0.02 * np.abs(free[4:8, 4:8] - base[4:8, 4:8]).max()


@pytest.mark.parametrize("bad", [np.zeros((8, 9)), np.full((8, 9), np.nan), -np.ones((8, 9)), np.ones((9, 8))])
def test_a_bad_alpha_map_is_refused(bad: np.ndarray) -> None:
    base, dx, dy = _random_problem(8, 9, 8)
    with pytest.raises(ValueError, match="alpha_map"):
        solve_l1(base, dx, dy, 0.5, alpha_map=bad)


def test_start_alpha_sets_the_l2_start_only() -> None:
    """``start_alpha`` (model/refine.py's clean start): pass 0 alone is the L2 solve at that α; the default is the
    scalar α bit for bit; a uniform map c with start α·c is the scalar solve at α·c (same start, same passes)."""
    base, dx, dy = _random_problem(20, 26, 9)
    default, _ = solve_l1(base, dx, dy, 0.5)
    same, _ = solve_l1(base, dx, dy, 0.5, start_alpha=0.5)
    assert np.array_equal(default, same)
    first, _ = solve_l1(base, dx, dy, 0.5, L1Options(iterations=1), start_alpha=0.2)
    np.testing.assert_allclose(first, solve_l2(base, dx, dy, 0.2), rtol=0, atol=1e-5 * float(np.abs(first).max()))
    assert np.abs(first - solve_l1(base, dx, dy, 0.5, L1Options(iterations=1))[0]).max() > 1e-3
    converged = L1Options(cg_iterations=400, cg_tolerance=1e-9, dtype=np.float64)
    mapped, _ = solve_l1(base, dx, dy, 0.5, converged, alpha_map=np.full((20, 26), 0.4), start_alpha=0.2)
    scalar, _ = solve_l1(base, dx, dy, 0.2, converged)
    np.testing.assert_allclose(mapped, scalar, rtol=0, atol=1e-4 * float(np.abs(scalar).max()))
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="start_alpha"):
            solve_l1(base, dx, dy, 0.5, start_alpha=bad)


@pytest.mark.parametrize("start_alpha", [1e-6, 1e-3, 1e3, 1e6])
def test_an_extreme_start_alpha_stays_finite_and_starts_where_asked(start_alpha: float) -> None:
    """Stiff starts (a tiny α takes the float64 path, a huge one pins the start to the base): finite, and pass 0
    alone is the L2 solve at that α."""
    base, dx, dy = _random_problem(12, 17, 10)
    first, _ = solve_l1(base, dx, dy, 0.5, L1Options(iterations=1), start_alpha=start_alpha)
    expected = solve_l2(base, dx, dy, start_alpha, dtype=np.float64)
    assert np.all(np.isfinite(first))
    np.testing.assert_allclose(first, expected, rtol=0, atol=1e-4 * max(1.0, float(np.abs(expected).max())))
    out, _ = solve_l1(base, dx, dy, 0.5, start_alpha=start_alpha)
    assert np.all(np.isfinite(out))
