"""Image error metrics between a reconstruction and a reference, with their conventions stated once.

All functions take ``(image, reference)`` as (H, W) or (H, W, C) arrays of linear radiance, compute in float64
and return a Python float. Non-finite input raises ValueError (a metric silently averaging NaNs would hide a
broken reconstruction).

* :func:`relmse` -- mean over pixels and channels of (x − r)² / (r² + ε), ε = 0.01, on linear radiance: the
  relative MSE of the gradient-domain rendering literature (Kettunen et al. 2015; Ma et al. 2024).
* :func:`relmse_unbiased` -- the same error against the *truth*, estimated from two independent references
  r1, r2 with the product estimator mean((x − r1)(x − r2) / (r̄² + ε)), r̄ = (r1 + r2) / 2: per pixel the
  numerator's expectation is (x − t)² because r1 and r2 are independent of each other and of x, so the
  references' own noise drops out (the normaliser r̄² uses both, so what is left is the small bias of a ratio).
  It can be slightly negative for an image close to the truth. :func:`reference_floor` is the RelMSE a perfect
  method (x = truth) would score against one of the references: mean((r1 − r2)² / (r̄² + ε)) / 2.
* :func:`flicker` -- the error that changes from frame to frame: RelMSE's estimator applied to the change of
  the error e_t = x_t − r_t between consecutive frames, mean((e_t − e_{t−1})² / (r̄² + ε)), r̄ the mean of the two
  frames' references, averaged over the shot's consecutive pairs. Normalised by both frames, not by frame t's
  alone, so that a shot played backwards flickers as much: across a light switched off, frame t−1's error divided
  by frame t's darker reference would count many times what it counts across the same light switched on. Frame
  t−1's image and reference are given already brought onto frame t's pixels (along the motion; as they are for a
  static shot), with an optional mask of the pixels where that is defined. Noise that stays put is not flicker;
  noise that changes is, and so is a frame that jumps. With a second set of independent references the product
  estimator removes their noise, as :func:`relmse_unbiased` does.
* :func:`psnr` -- 10 log10(peak² / MSE). By default on the display tonemap below, peak 1 (so an HDR firefly
  counts at most as a saturated pixel); ``tonemapped=False`` uses linear values with the given peak.
  Identical images give +inf.
* :func:`ssim` -- SSIM (Wang et al. 2004) on the display tonemap, per channel, Gaussian window σ = 1.5
  truncated at 3.5σ (the classic 11×11), K1 = 0.01, K2 = 0.03, data range 1, reflected borders, averaged over
  every pixel and channel.
* :func:`flip` -- mean HDR-FLIP (Andersson et al. 2021) via the ``flip-evaluator`` package: linear RGB input,
  ACES tonemapper, 67 pixels per degree, exposure range from the reference as FLIP computes it (see
  :func:`flip` for the one deviation that keeps the library from aborting the process).

Display tonemap: ``clip(x, 0, 1) ** (1/2.2)`` per channel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import numpy as np
from scipy.ndimage import gaussian_filter

from gradsep.model.policy import LUMINANCE

__all__ = ["RELMSE_EPSILON", "all_metrics", "flicker", "flip", "psnr", "reference_floor", "relmse",
           "relmse_unbiased", "ssim", "tonemap"]

RELMSE_EPSILON = 0.01
GAMMA = 2.2
SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5  # radius int(3.5·1.5 + 0.5) = 5: the 11×11 window of Wang et al.
SSIM_K1, SSIM_K2 = 0.01, 0.03
# Rec. 709 / linear-sRGB luminance, the weights HDR-FLIP uses for its exposure range.
_LUMINANCE = np.array(LUMINANCE)


def _pair(image: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate a pair: same shape, 2-D or 3-D, non-empty, finite; returned as float64."""
    x = np.asarray(image, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    if x.shape != r.shape:
        raise ValueError(f"image shape {x.shape} differs from reference shape {r.shape}")
    if x.ndim not in (2, 3) or x.size == 0:
        raise ValueError(f"expected a non-empty (H, W) or (H, W, C) image, got shape {x.shape}")
    for name, arr in (("image", x), ("reference", r)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            raise ValueError(f"{name} contains {bad} non-finite value(s)")
    return x, r


def tonemap(image: np.ndarray) -> np.ndarray:
    """The display tonemap PSNR and SSIM use: clip to [0, 1], then gamma 1/2.2."""
    return np.clip(image, 0.0, 1.0) ** (1.0 / GAMMA)


def relmse(image: np.ndarray, reference: np.ndarray, epsilon: float = RELMSE_EPSILON) -> float:
    """Relative MSE: mean over pixels and channels of (x − r)² / (r² + ε) on linear radiance."""
    x, r = _pair(image, reference)
    return float(np.mean((x - r) ** 2 / (r * r + epsilon)))


def relmse_unbiased(image: np.ndarray, reference1: np.ndarray, reference2: np.ndarray,
                    epsilon: float = RELMSE_EPSILON) -> float:
    """RelMSE against the truth with the references' noise removed (see the module docstring):
    mean((x − r1)(x − r2) / (r̄² + ε)) over two *independent* references of the same truth."""
    x, r1 = _pair(image, reference1)
    _, r2 = _pair(image, reference2)
    mean = 0.5 * (r1 + r2)
    return float(np.mean((x - r1) * (x - r2) / (mean * mean + epsilon)))


def reference_floor(reference1: np.ndarray, reference2: np.ndarray, epsilon: float = RELMSE_EPSILON) -> float:
    """The RelMSE a perfect method would score against *one* of two independent, equally converged
    references: E[(t − r1)²] = E[(r1 − r2)²] / 2 per pixel, normalised by r̄² + ε as :func:`relmse_unbiased`."""
    r1, r2 = _pair(reference1, reference2)
    mean = 0.5 * (r1 + r2)
    return float(np.mean((r1 - r2) ** 2 / (mean * mean + epsilon)) / 2.0)


def flicker(images: Sequence[np.ndarray], references: Sequence[np.ndarray],
            references2: Sequence[np.ndarray] | None = None, masks: Sequence[np.ndarray | None] | None = None,
            epsilon: float = RELMSE_EPSILON) -> float:
    """Flicker of a shot (see the module docstring): the mean over t ≥ 1 of the RelMSE estimator of
    e_t − e_{t−1}, e_t = images[t] − references[t], normalised by the mean of both frames' references (symmetric in
    time). ``images[t - 1]`` and ``references[t - 1]`` must already be aligned with frame t (warped along the
    motion); ``masks[t]`` (H, W) bool keeps the pixels where that alignment holds (None: all). With
    ``references2`` (independent of ``references``) the product of the two error changes is used and their noise
    drops out. Needs at least two frames."""
    if len(images) != len(references) or (references2 is not None and len(references2) != len(images)):
        raise ValueError("flicker needs one reference (and one second reference) per image")
    if len(images) < 2:
        raise ValueError(f"flicker needs at least two frames, got {len(images)}")
    second = references if references2 is None else references2
    values = []
    for t in range(1, len(images)):
        x, r1 = _pair(images[t], references[t])
        _, r2 = _pair(images[t], second[t])
        xp, p1 = _pair(images[t - 1], references[t - 1])
        _, p2 = _pair(images[t - 1], second[t - 1])
        if xp.shape != x.shape:
            raise ValueError(f"frame {t - 1} has shape {xp.shape}, frame {t} {x.shape}")
        mean = 0.25 * (r1 + r2 + p1 + p2)
        terms = ((x - r1) - (xp - p1)) * ((x - r2) - (xp - p2)) / (mean * mean + epsilon)
        mask = None if masks is None else masks[t]
        if mask is not None:
            keep = np.asarray(mask, bool)
            if keep.shape != x.shape[:2]:
                raise ValueError(f"mask {t} has shape {keep.shape}, expected {x.shape[:2]}")
            if not keep.any():
                continue
            terms = terms[keep]
        values.append(float(np.mean(terms)))
    if not values:
        raise ValueError("flicker: no frame pair has a pixel in its mask")
    return float(np.mean(values))


def psnr(image: np.ndarray, reference: np.ndarray, *, peak: float = 1.0, tonemapped: bool = True) -> float:
    """PSNR in dB, 10·log10(peak² / MSE); on the display tonemap by default (peak 1). +inf when equal."""
    x, r = _pair(image, reference)
    if not (peak > 0 and math.isfinite(peak)):
        raise ValueError(f"peak must be a finite number > 0, got {peak}")
    if tonemapped:
        x, r = tonemap(x), tonemap(r)
    mse = float(np.mean((x - r) ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(peak * peak / mse)


def _ssim_channel(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM map of one (H, W) channel pair already in [0, 1]."""

    def blur(a: np.ndarray) -> np.ndarray:
        return gaussian_filter(a, SSIM_SIGMA, mode="reflect", truncate=SSIM_TRUNCATE)

    c1, c2 = SSIM_K1**2, SSIM_K2**2
    mx, my = blur(x), blur(y)
    vx = blur(x * x) - mx * mx
    vy = blur(y * y) - my * my
    cxy = blur(x * y) - mx * my
    return ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))


def ssim(image: np.ndarray, reference: np.ndarray) -> float:
    """Mean SSIM on the display tonemap, per channel, Gaussian σ = 1.5 window; 1 for identical images."""
    x, r = _pair(image, reference)
    x, r = tonemap(x), tonemap(r)
    if x.ndim == 2:
        x, r = x[..., None], r[..., None]
    maps = [_ssim_channel(x[..., c], r[..., c]) for c in range(x.shape[-1])]
    return float(np.mean(maps))


@lru_cache(maxsize=1)
def _flip_xmax() -> float:
    """The linear value FLIP's ACES tonemapper maps to its exposure ceiling, asked of the library itself:
    for a reference of constant luminance 1 FLIP's start exposure is log2(x_max / 1)."""
    import flip_evaluator

    one = np.ones((2, 2, 3), dtype=np.float32)
    _, _, params = flip_evaluator.evaluate(one, one, "HDR", applyMagma=False)
    return float(2.0 ** params["startExposure"])


def _flip_exposures(reference: np.ndarray, test: np.ndarray) -> dict[str, float | int] | None:
    """HDR-FLIP's exposure range, computed here because the library aborts the whole process (exit status
    255) when the reference's median luminance is 0, which a direct-light layer over a black background hits.

    As FLIP: start = log2(x_max / max Y), stop = log2(x_max / median Y), count = max(2, ⌈stop − start⌉).
    Deviation: when the median is 0 it is taken over the pixels with Y > 0; when the reference is entirely
    black its range comes from the test image. Returns None when both are black (FLIP is then 0).
    """
    for source in (reference, test):
        lum = source.reshape(-1, 3) @ _LUMINANCE
        positive = lum[lum > 0]
        if positive.size:
            median = float(np.median(lum))
            if median <= 0:
                median = float(np.median(positive))
            start = math.log2(_flip_xmax() / float(positive.max()))
            stop = math.log2(_flip_xmax() / median)
            return {"startExposure": start, "stopExposure": stop, "numExposures": max(2, math.ceil(stop - start))}
    return None


def flip(image: np.ndarray, reference: np.ndarray) -> float:
    """Mean HDR-FLIP error in [0, 1] of an (H, W, 3) linear-RGB image against its reference.

    HDR-FLIP rather than LDR-FLIP because renders are linear HDR radiance: FLIP tonemaps both at a range of
    exposures and keeps the worst error per pixel. Negative values are clamped to 0 (FLIP's domain).
    """
    x, r = _pair(image, reference)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"FLIP needs (H, W, 3) RGB images, got shape {x.shape}")
    x = np.ascontiguousarray(np.clip(x, 0.0, None), dtype=np.float32)
    r = np.ascontiguousarray(np.clip(r, 0.0, None), dtype=np.float32)
    exposures = _flip_exposures(r.astype(np.float64), x.astype(np.float64))
    if exposures is None:
        return 0.0
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(r, x, "HDR", applyMagma=False, parameters=exposures)
    return float(mean)


def all_metrics(image: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Every metric at once (FLIP only for RGB images), as evaluation tables and the service report them."""
    out = {"relmse": relmse(image, reference), "psnr": psnr(image, reference), "ssim": ssim(image, reference)}
    if np.ndim(image) == 3 and np.shape(image)[-1] == 3:
        out["flip"] = flip(image, reference)
    return out
