"""Reference-free error estimates for the planner (numpy only): how far a reconstruction is from the truth,
judged against independent noisy renders of the same frame.

With ``b_j`` independent unbiased estimates of the image (render passes), each independent of the reconstruction
``R``, ``E[(R - b_j)(R - b_k)] = (R - I)^2`` for ``j != k``: the product of two independent differences is an
unbiased estimate of the reconstruction's squared error, bias included, with no variance to subtract (the same
idea as model.metrics.relmse_unbiased with two references). Averaged over every pair of passes, weighted by
their sample counts (:func:`cross_relmse`). A firefly in one pass meets only the other passes' independent noise,
so it weighs far less than in ``(R - B)^2`` less an estimated variance of ``B`` (an estimator of that form was
tried: heavy tails made that difference too noisy to read at pilot sample counts).

Weighted like RelMSE (model.metrics.relmse: ``1 / (I^2 + eps)`` per channel) with ``I`` taken from the
reconstructions, since no reference exists.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gradsep.model.metrics import RELMSE_EPSILON

#: The error-vs-spp law a reconstruction's estimated error is carried to other sample counts with (RelMSE ~
#: spp^-ERROR_EXPONENT): a denoised frame's error falls far slower than a raw frame's 1/spp. One exponent for every
#: plan: per-plan exponents, measured, predicted no better (docs/decisions.md).
ERROR_EXPONENT = 0.5


def relative_weights(image: np.ndarray, epsilon: float = RELMSE_EPSILON) -> np.ndarray:
    """RelMSE's per-pixel, per-channel weight ``1 / (I^2 + eps)`` with the (clipped, non-negative) image as I."""
    i = np.clip(np.asarray(image, dtype=np.float64), 0.0, None)
    return 1.0 / (i * i + epsilon)


def cross_relmse(reconstruction: np.ndarray, batches: Sequence[tuple[np.ndarray, int]],
                 weights: np.ndarray | None = None, border: int = 0) -> tuple[float, float]:
    """The reconstruction's weighted squared error, estimated without a reference, and its standard error.

    ``batches`` are independent unbiased images ``(mean, spp)`` of the same frame (two or more), independent of
    ``reconstruction``. With ``x_j = R - b_j`` and pair weights ``n_j n_k``, per pixel and channel
    ``sum_{j != k} n_j n_k x_j x_k / sum_{j != k} n_j n_k = (S1^2 - S2) / (N^2 - sum n_j^2)``, where ``S1 = sum n_j
    x_j`` and ``S2 = sum n_j^2 x_j^2``. ``weights`` default to :func:`relative_weights` of R. ``border`` pixels on
    each side are left out (a reconstruction of a crop differs from the full frame's near its edge). The
    standard error takes pixels and channels as independent. The value may come out below 0 where the error is
    small against the batches' noise; the caller floors it."""
    d = cross_terms(reconstruction, batches, weights)
    if border:
        d = d[border:-border or None, border:-border or None]
    return mean_and_se(d)


def mean_and_se(values: np.ndarray) -> tuple[float, float]:
    """The mean of ``values`` and its standard error, taking them as independent."""
    return float(np.mean(values)), float(np.std(values) / np.sqrt(max(values.size, 1)))


def cross_terms(reconstruction: np.ndarray, batches: Sequence[tuple[np.ndarray, int]],
                weights: np.ndarray | None = None) -> np.ndarray:
    """:func:`cross_relmse`'s per-pixel, per-channel terms (their mean is the estimate). Two reconstructions'
    terms against the same batches, with the same weights, differ by ``w (R_x^2 - R_y^2 - (R_x - R_y) S1 / N)``:
    the batches' own noise products cancel, so a difference of two estimates is far less noisy than either."""
    if len(batches) < 2:
        raise ValueError("a reference-free error estimate needs at least two independent batches")
    r = np.asarray(reconstruction, dtype=np.float64)
    w = relative_weights(r) if weights is None else np.asarray(weights, dtype=np.float64)
    s1 = np.zeros_like(r)
    s2 = np.zeros_like(r)
    for image, n in batches:
        x = r - np.asarray(image, dtype=np.float64)
        s1 += n * x
        s2 += (n * x) ** 2
    total = float(sum(n for _, n in batches))
    pairs = total * total - float(sum(n * n for _, n in batches))
    return w * (s1 * s1 - s2) / pairs


def at_budget(error: float, spp: float, budget_spp: float, exponent: float) -> float:
    """Carry an error measured at ``spp`` to ``budget_spp`` with the law ``error ~ spp^-exponent``."""
    if spp <= 0 or budget_spp <= 0:
        return float("inf")
    return float(max(error, 0.0) * (spp / budget_spp) ** exponent)
