"""Reference-free error estimates for the planner (numpy only): how far a reconstruction is from the truth,
judged against an independent noisy render of the same frame.

With ``B`` an unbiased estimate of the image independent of the reconstruction ``R``, per pixel
``E[(R - B)^2] = (R - I)^2 + Var(B)``: the squared difference overestimates the reconstruction's squared error
(bias included) by exactly B's variance. B's variance comes from B itself: B is the sample-weighted mean of
independent batches (render passes) of one estimator, so the spread of the batch means around B estimates it
(:func:`pooled_mean_and_variance`). Subtracting it per pixel rather than in the mean also cancels most of a firefly's
weight: a bright sample in one batch inflates both terms alike.

Weighted like RelMSE (model.metrics.relmse: ``1 / (I^2 + eps)`` per channel) with ``I`` taken from the
reconstruction itself, since no reference exists; the weight is independent of B, which keeps the subtraction
unbiased for a fixed weight.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gradsep.model.metrics import RELMSE_EPSILON


def pooled_mean_and_variance(batches: Sequence[tuple[np.ndarray, int]]) -> tuple[np.ndarray, np.ndarray]:
    """The sample-weighted mean of independent batch means ``(mean, spp)`` and the variance of that mean per pixel.

    With per-sample variance ``s2`` the batch of ``n_j`` samples has variance ``s2 / n_j``; the unbiased estimate
    is ``s2_hat = sum_j n_j (b_j - B)^2 / (J - 1)`` and the pooled mean's variance ``s2_hat / N``. Needs two batches
    or more."""
    if len(batches) < 2:
        raise ValueError("the variance of a pooled mean needs at least two independent batches")
    total = float(sum(n for _, n in batches))
    mean = sum(np.asarray(b, dtype=np.float64) * n for b, n in batches) / total
    spread = sum(n * (np.asarray(b, dtype=np.float64) - mean) ** 2 for b, n in batches)
    return mean, spread / ((len(batches) - 1) * total)


def relative_weights(image: np.ndarray, epsilon: float = RELMSE_EPSILON) -> np.ndarray:
    """RelMSE's per-pixel, per-channel weight ``1 / (I^2 + eps)`` with the (clipped, non-negative) image as I."""
    i = np.clip(np.asarray(image, dtype=np.float64), 0.0, None)
    return 1.0 / (i * i + epsilon)


def estimated_relmse(reconstruction: np.ndarray, target_mean: np.ndarray, target_variance: np.ndarray,
                     weights: np.ndarray | None = None, border: int = 0) -> tuple[float, float]:
    """``mean(w ((R - B)^2 - Var(B)))``: the reconstruction's weighted squared error, estimated without a reference,
    and the standard error of that mean (over pixels and channels, taken as independent).

    ``target_mean``/``target_variance`` are B and the variance of B (independent of R). ``weights`` default to
    :func:`relative_weights` of R. ``border`` pixels on each side are left out (a reconstruction of a crop differs
    from the full frame's near the crop's edge). Where the error is small against B's noise the estimate can come
    out near or below 0; the caller floors it with the standard error."""
    r = np.asarray(reconstruction, dtype=np.float64)
    w = relative_weights(r) if weights is None else np.asarray(weights, dtype=np.float64)
    d = w * ((r - target_mean) ** 2 - target_variance)
    if border:
        d = d[border:-border or None, border:-border or None]
    return float(np.mean(d)), float(np.std(d) / np.sqrt(max(d.size, 1)))


def at_budget(error: float, spp: float, budget_spp: float, exponent: float) -> float:
    """Carry an error measured at ``spp`` to ``budget_spp`` with the law ``error ~ spp^-exponent``."""
    if spp <= 0 or budget_spp <= 0:
        return float("inf")
    return float(max(error, 0.0) * (spp / budget_spp) ** exponent)
