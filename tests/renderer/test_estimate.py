"""The planner's reference-free error estimate (renderer/estimate.py) on synthetic images with a known truth."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model.metrics import relmse
from gradsep.renderer.estimate import at_budget, estimated_relmse, pooled_mean_and_variance, relative_weights


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


def test_pooled_variance_is_unbiased() -> None:
    rng = np.random.default_rng(1)
    truth = _truth(rng)
    sigma = 0.3
    sizes = [1, 1, 1, 5]
    mean, var = pooled_mean_and_variance(_batches(rng, truth, sizes, sigma))
    expected = sigma**2 / sum(sizes)
    assert float(np.mean(var)) == pytest.approx(expected, rel=0.05)
    assert float(np.mean((mean - truth) ** 2)) == pytest.approx(expected, rel=0.05)


def test_pooled_variance_needs_two_batches() -> None:
    with pytest.raises(ValueError):
        pooled_mean_and_variance([(np.zeros((2, 2, 3)), 4)])


@pytest.mark.parametrize("heavy", [False, True])
@pytest.mark.parametrize("bias", [0.0, 0.02, 0.1])
def test_the_estimate_matches_the_true_relmse(heavy: bool, bias: float) -> None:
    """A reconstruction with a known error (noise plus a bias), judged against a noisy B many times larger than
    that error: the estimate lands on the true RelMSE (against the truth) within its few standard errors."""
    rng = np.random.default_rng(7 if heavy else 3)
    truth = _truth(rng)
    recon = truth * (1.0 + bias) + rng.normal(0.0, 0.03, truth.shape)
    target, variance = pooled_mean_and_variance(_batches(rng, truth, [1, 1, 1, 1, 8], 0.4, heavy))
    value, se = estimated_relmse(recon, target, variance, weights=relative_weights(truth))
    true = relmse(recon, truth)
    assert abs(value - true) < 4 * se + 0.05 * true
    assert se < 0.5 * float(np.mean(relative_weights(truth) * variance))  # B's noise is mostly subtracted away


def test_comparing_two_reconstructions_against_one_b() -> None:
    """Two candidates judged against the same B: the difference of their estimates has the sign and size of the
    difference of their true errors, although each is small against B's variance."""
    rng = np.random.default_rng(11)
    truth = _truth(rng)
    good = truth + rng.normal(0.0, 0.02, truth.shape)
    bad = truth * 1.04 + rng.normal(0.0, 0.03, truth.shape)
    target, variance = pooled_mean_and_variance(_batches(rng, truth, [1, 1, 1, 16], 0.5, heavy=True))
    w = relative_weights(truth)
    diff = estimated_relmse(bad, target, variance, w)[0] - estimated_relmse(good, target, variance, w)[0]
    true = relmse(bad, truth) - relmse(good, truth)
    assert diff == pytest.approx(true, rel=0.3)


def test_border_is_left_out() -> None:
    truth = np.ones((20, 20, 3))
    recon = truth.copy()
    recon[:2] = 5.0  # a crop's edge artefact
    value, _ = estimated_relmse(recon, truth, np.zeros_like(truth), border=2)
    assert value == 0.0
    assert estimated_relmse(recon, truth, np.zeros_like(truth))[0] > 0.0


def test_at_budget_follows_the_law() -> None:
    assert at_budget(0.04, 4, 16, 1.0) == pytest.approx(0.01)
    assert at_budget(0.04, 4, 16, 0.5) == pytest.approx(0.02)
    assert at_budget(-0.01, 4, 16, 1.0) == 0.0
    assert at_budget(0.04, 4, 0, 1.0) == float("inf")
