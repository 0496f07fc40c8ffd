"""Backing a denoiser off where the input is already converged: the per-pixel blend of a layer's denoised image
toward its own rendered base, by the layer's variance channel (``L.var.Y``, model/frame.py).

A denoiser cannot tell a converged pixel from a noisy one, so it changes both: on a nearly converged frame, or
where a light or a smooth wall needs no help, its change is bias, not noise removed. With the variance ``σ²`` of
the input ``x`` and the denoiser's image ``y``, the blend ``x + w (y − x)`` is the least-squares mix of an
unbiased estimate with variance ``σ²`` and one with bias ``b``: ``w = σ² / (σ² + b²)``. The bias is estimated
from the change itself, ``E[(y − x)²] ≈ σ² + b²`` where the denoiser removed the noise; so over a window,

    D = box(Y(y − x)² / m²),   S = box(σ² / m²),   b² = max(D − NOISE_MARGIN · S, 0),   w = S / (S + b²)

(w = 1 where b² = 0), Y the luminance (model.policy.LUMINANCE). A change within NOISE_MARGIN times the noise reads
as noise removed and keeps the denoiser's image untouched, so a noisy frame is served as before; a change far above
the noise (a converged pixel, the halo around a light in view) goes back to the input. A firefly has a large
variance and stays the denoiser's. The window averages the per-pixel variance estimate, which at a few samples is
itself noisy.

The weight is computed twice and the smaller one is used: with ``m = 1`` (absolute terms, where the window's
brightest pixels weigh most) and with ``m² = Y(y)² + (RELATIVE_FLOOR · lit level of x)²`` (relative terms, as
RelMSE weighs them). The absolute weight alone misses the halo around a small light in view: the light's edge
pixels, half covered by an emitter, carry a variance far above their dark neighbours', and a box spreads it over the
window. The relative weight alone gives back more noise on a few textured frames. A light in view that the outlier
detector kept out of the method (model/outliers.py), with its rim, is pinned (``pinned``): given back as rendered
and left out of every window, so its coverage noise hides nothing around it. The rule and WINDOW were chosen
on held-out procedural rooms and studios 93301-93303 and checked on 93304-93308; NOISE_MARGIN on all 16, per layer:
a lower margin lets a few samples that miss rare bright paths (their variance reads low) cost the indirect layer
(docs/decisions.md, "Backing OIDN off converged pixels", has the figures).
"""

from __future__ import annotations

import numpy as np

from gradsep.model.frame import FLOAT32_MAX, VARIANCE_MAX
from gradsep.model.robust import box_mean, lit_level_of_luminance, luminance

#: The box window (pixels a side) over which the change and the variance are averaged.
WINDOW = 7
#: A change up to this many times the input's variance is read as noise the denoiser removed.
NOISE_MARGIN = 4.0
#: The relative weight's floor on the denoised luminance, as a fraction of the input's lit level (model/robust.py),
#: so that black pixels do not divide by zero.
RELATIVE_FLOOR = 0.01


def back_off(noisy: np.ndarray, denoised: np.ndarray, variance: np.ndarray,
             pinned: np.ndarray | None = None) -> np.ndarray:
    """``denoised`` (H, W, 3) blended toward ``noisy`` (H, W, 3) by the variance (H, W) of ``noisy``'s per-pixel
    mean luminance, as the module docstring says; float32, finite wherever both images are. Non-finite variances
    read as VARIANCE_MAX (very noisy: the denoiser's value is kept). ``pinned`` (H, W) bool: pixels that come back
    as ``noisy`` and are left out of every window (a light in view and its rim, model/outliers.py: its
    edge pixels carry a variance far above their neighbours', which would read as noise over the whole window)."""
    x = np.asarray(noisy, np.float32)
    y = np.asarray(denoised, np.float32)
    if x.shape != y.shape or x.ndim != 3 or x.shape[-1] != 3 or np.shape(variance) != x.shape[:2]:
        raise ValueError(f"back_off needs (H, W, 3) images and an (H, W) variance, got {x.shape}, {y.shape} and "
                         f"{np.shape(variance)}")
    if pinned is not None and np.shape(pinned) != x.shape[:2]:
        raise ValueError(f"back_off's pinned mask must be (H, W) = {x.shape[:2]}, got {np.shape(pinned)}")
    var = np.nan_to_num(np.asarray(variance, np.float64), nan=VARIANCE_MAX, posinf=VARIANCE_MAX)
    np.clip(var, 0.0, VARIANCE_MAX, out=var)
    lum_x, lum_y = luminance(x), luminance(y)  # float64, non-finite read as 0
    d2 = np.minimum((lum_y - lum_x) ** 2, VARIANCE_MAX)
    keep = None
    if pinned is not None and np.any(pinned):
        keep = (~np.asarray(pinned, bool)).astype(np.float64)
        d2 *= keep
        var *= keep
        keep = box_mean(keep, WINDOW)  # the kept share of each window
    floor = (RELATIVE_FLOOR * lit_level_of_luminance(lum_x)) ** 2
    weight = _weight(d2, var, keep)
    if floor > 0:
        scale2 = lum_y * lum_y + floor
        np.minimum(weight, _weight(d2 / scale2, var / scale2, keep), out=weight)
        np.nan_to_num(weight, copy=False, nan=1.0)  # Inf/Inf only past a 1e150 dynamic range: keep the denoiser's
    if pinned is not None:
        weight[np.asarray(pinned, bool)] = 0.0
    out = x.astype(np.float64)
    out += weight[..., None] * (y - out)
    return np.clip(out, -FLOAT32_MAX, FLOAT32_MAX).astype(np.float32)


def _weight(d2: np.ndarray, var: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """The denoiser's per-pixel weight from the squared change and the variance (the module docstring's w); with
    ``keep`` (the share of each window that is not pinned, whose pixels are 0 in ``d2`` and ``var``) the windows
    average over their kept pixels only. The ratio of the two averages is all that counts, so both are left as sums
    over the window and the share cancels; a window with no kept pixel keeps the denoiser's image."""
    spread = box_mean(d2, WINDOW)  # sums of non-negative values: non-negative
    noise = box_mean(var, WINDOW)
    bias2 = spread
    bias2 -= NOISE_MARGIN * noise
    weight = np.ones_like(noise)
    # where bias2 > 0 the sum is > 0 and finite (both terms are capped at VARIANCE_MAX before the box)
    usable = bias2 > 0.0 if keep is None else (bias2 > 0.0) & (keep > 1e-9)
    np.divide(noise, noise + bias2, out=weight, where=usable)
    return weight
