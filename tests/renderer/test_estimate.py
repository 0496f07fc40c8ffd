"""The planner's reference-free error estimate (renderer/estimate.py) on synthetic images with a known truth."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model.metrics import relmse
from gradsep.renderer.estimate import at_budget, cross_relmse, relative_weights


def _truth(rng: np.random.Generator, h: int = 96, w: int = 96) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w] / 16.0
    base = 0.5 + 0.4 * np.sin(x)[..., None] * np.cos(y)[..., None] * np.array([1.0, 0.7, 0.4])
    return base + 0.05 * rng.random((h, w, 3))


def _batches(rng: np.random.Generator, truth: np.ndarray, sizes: list[int], sigma: float,
             heavy: bool = False) -> list[tuple[np.ndarray, int]]:
    """Independent batch means of per-sample noise with variance sigma^2 (heavy: a skewed, firefly-like law)."""
    out = []
    for n in sizes:
        if heavy:  # exponential noise, mean 0: skewed like path-traced radiance
            noise = (rng.exponential(1.0, (n, *truth.shape)) - 1.0).mean(axis=0) * sigma
        else:
            noise = rng.normal(0.0, sigma / np.sqrt(n), truth.shape)
        out.append((truth + noise, n))
    return out


def test_cross_relmse_needs_two_batches() -> None:
    with pytest.raises(ValueError):
        cross_relmse(np.zeros((2, 2, 3)), [(np.zeros((2, 2, 3)), 4)])


def test_cross_relmse_of_two_batches_is_the_product_of_differences() -> None:
    r = np.full((1, 1, 3), 2.0)
    value, _ = cross_relmse(r, [(np.full((1, 1, 3), 1.0), 3), (np.full((1, 1, 3), 4.0), 3)], weights=np.ones((1, 1, 3)))
    assert value == pytest.approx((2.0 - 1.0) * (2.0 - 4.0))


@pytest.mark.parametrize("heavy", [False, True])
@pytest.mark.parametrize("bias", [0.0, 0.02, 0.1])
def test_the_estimate_matches_the_true_relmse(heavy: bool, bias: float) -> None:
    """A reconstruction with a known error (noise plus a bias), judged against noisy batches whose variance is
    many times that error: the estimate lands on the true RelMSE (against the truth) within its few standard
    errors, and that standard error is a small fraction of the batches' own noise."""
    rng = np.random.default_rng(7 if heavy else 3)
    truth = _truth(rng)
    recon = truth * (1.0 + bias) + rng.normal(0.0, 0.03, truth.shape)
    batches = _batches(rng, truth, [1, 1, 1, 1, 4, 4], 0.4, heavy)
    value, se = cross_relmse(recon, batches, weights=relative_weights(truth))
    true = relmse(recon, truth)
    assert abs(value - true) < 4 * se + 0.05 * true
    pooled_variance = 0.4**2 / 12
    assert se < 0.5 * float(np.mean(relative_weights(truth))) * pooled_variance


def test_comparing_two_reconstructions_against_the_same_batches() -> None:
    """Two candidates judged against the same batches: the difference of their estimates has the sign and size of
    the difference of their true errors, although each is small against the batches' variance."""
    rng = np.random.default_rng(11)
    truth = _truth(rng)
    good = truth + rng.normal(0.0, 0.02, truth.shape)
    bad = truth * 1.04 + rng.normal(0.0, 0.03, truth.shape)
    batches = _batches(rng, truth, [1, 1, 1, 8, 8], 0.5, heavy=True)
    w = relative_weights(truth)
    diff = cross_relmse(bad, batches, w)[0] - cross_relmse(good, batches, w)[0]
    true = relmse(bad, truth) - relmse(good, truth)
    assert diff == pytest.approx(true, rel=0.3)


def test_border_is_left_out() -> None:
    truth = np.ones((20, 20, 3))
    recon = truth.copy()
    recon[:2] = 5.0  # a crop's edge artefact
    exact = [(truth, 1), (truth, 1)]
    value, _ = cross_relmse(recon, exact, border=2)
    assert value == 0.0
    assert cross_relmse(recon, exact)[0] > 0.0


def test_at_budget_follows_the_law() -> None:
    assert at_budget(0.04, 4, 16, 1.0) == pytest.approx(0.01)
    assert at_budget(0.04, 4, 16, 0.5) == pytest.approx(0.02)
    assert at_budget(-0.01, 4, 16, 1.0) == 0.0
    assert at_budget(0.04, 4, 0, 1.0) == float("inf")
