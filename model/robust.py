"""Frame statistics one pixel cannot move, and the footprint an outlier's energy is put back over.

Every denoising method needs a few numbers about the whole layer (the exposure OIDN and the networks see, the
level the solvers work at, the trust rule's frame weight). Taken as a plain mean, a sum or a maximum, one firefly
moves them, and with them every pixel of the output. The statistics here are *robust*: :func:`robust_level` is a
winsorised mean and :func:`winsorised_sum` a winsorised sum, so a single pixel, whatever its value, counts as the
99.9th percentile at most: it moves the level by at most that percentile over the pixel count.

The outliers themselves are found and kept out of the methods by model/outliers.py; their excess comes back here:
:func:`add_excess` spreads it over a small Gaussian footprint (its energy kept exactly, its effect ending
OUTLIER_SPREAD_RADIUS pixels away along each axis).
"""

from __future__ import annotations

import math

import numpy as np

from gradsep.model import kernels
from gradsep.model.frame import FLOAT32_MAX
from gradsep.model.policy import LUMINANCE

#: The quantile at which :func:`robust_level` winsorises the per-pixel values: the top 0.1 % of the pixels count
#: as this quantile's value, so no single pixel can move the level by more than one order statistic's step.
WINSOR_QUANTILE = 0.999
#: An outlier's excess (its value above the median of its 8 neighbours, per channel) is spread over a Gaussian
#: footprint of this σ in pixels, truncated at OUTLIER_SPREAD_RADIUS and renormalised at the frame's border, so its
#: energy is kept exactly and its effect ends OUTLIER_SPREAD_RADIUS pixels from it along each axis. The footprint
#: is a square centred on a cluster's centre, so the radius is chosen for the corner of the largest cluster's
#: footprint, seen from the cluster's farthest pixel, to stay within the locality contract's 16 px:
#: (10 + CLUSTER_SIZE - 1) · √2 < 16.
OUTLIER_SPREAD_SIGMA = 3.5
OUTLIER_SPREAD_RADIUS = 10


def channel_mean(image: np.ndarray) -> np.ndarray:
    """The per-pixel mean over the channels of (H, W, C) ``image`` (an (H, W) image as it is), a new float64 array
    (summed channel by channel: several times faster than a float64 reduction over a short last axis)."""
    values = np.asarray(image)
    if values.ndim != 3:
        return np.array(values, np.float64)
    total = values[..., 0].astype(np.float64)
    for c in range(1, values.shape[-1]):
        total += values[..., c]
    total /= values.shape[-1]
    return total


def robust_level(image: np.ndarray) -> float:
    """The winsorised mean (at WINSOR_QUANTILE) of the per-pixel channel mean of ``image`` ((H, W) or (H, W, C)),
    float64 statistics, non-finite and negative values read as 0. Scales with the image (level(s·x) = s·level(x)
    up to rounding). 0 for an empty or black image; for an image lit in fewer pixels than the quantile leaves
    (its winsorised mean is 0) the plain mean of those pixels' values."""
    flat = channel_mean(image).ravel()
    flat[~np.isfinite(flat)] = 0.0
    np.maximum(flat, 0.0, out=flat)
    return _winsorised_mean(flat)


def _winsorised_mean(flat: np.ndarray) -> float:
    """:func:`robust_level` of 1-D float64 values already finite and ≥ 0."""
    if flat.size == 0:
        return 0.0
    k = int(WINSOR_QUANTILE * (flat.size - 1))
    cap = float(np.partition(flat, k)[k])
    level = float(np.minimum(flat, cap).mean())
    return level if level > 0.0 else float(flat.mean())


#: OIDN's autoexposure conventions (its ``core/autoexposure.h``): luminance averaged over bins of at most this many
#: pixels a side, and bins darker than LIT_FRACTION are left out. OIDN's threshold is an absolute 1e-8; here it is
#: relative to the frame's robust level, so that the level scales exactly with the image.
LIT_BIN = 16
LIT_FRACTION = 1e-8


def box_mean(image: np.ndarray, size: int) -> np.ndarray:
    """The ``size`` × ``size`` mean of an (H, W) image (edges repeated), as two direct 1-D sums. Not a running sum
    (scipy's ``uniform_filter``): once a huge value (a firefly's variance, or its squared gradient) leaves a running
    sum, the small values behind it are lost to rounding, and the rest of its row or column reads as 0. With direct
    sums a value reaches only the windows that hold it. The image's dtype is kept. A 2-D float image and an odd
    size run compiled (model.kernels.box_mean, float64 sums), anything else through scipy's ``correlate1d``."""
    from scipy.ndimage import correlate1d

    values = np.asarray(image)
    if kernels.AVAILABLE and values.ndim == 2 and values.dtype in (np.float32, np.float64) and size % 2 == 1 \
            and values.size:
        return kernels.box_mean(np.ascontiguousarray(values), size, np.empty(values.shape, values.dtype))
    weights = np.full(size, 1.0 / size, dtype=values.dtype if values.dtype.kind == "f" else np.float64)
    return correlate1d(correlate1d(values, weights, axis=0, mode="nearest"), weights, axis=1, mode="nearest")


def luminance(image: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of (H, W, 3) ``image`` as float64 (an (H, W) image, or one of other channel counts, by its
    channel mean); non-finite and negative values read as 0."""
    values = np.asarray(image)
    if values.ndim == 3 and values.shape[-1] == 3:
        weights = np.array(LUMINANCE, np.float64)  # float64 scalars: each product is computed in float64
        lum = values[..., 0] * weights[0]
        part = np.empty_like(lum)  # one temporary for both products (this runs per layer of every request)
        lum += np.multiply(values[..., 1], weights[1], out=part)
        lum += np.multiply(values[..., 2], weights[2], out=part)
    else:
        lum = channel_mean(values)
    if not math.isfinite(float(lum.sum())):  # one reduction; only a non-finite (or overflowing) sum looks closer
        lum[~np.isfinite(lum)] = 0.0
    return np.maximum(lum, 0.0, out=lum)


def lit_level(image: np.ndarray) -> float:
    """The winsorised mean luminance (at WINSOR_QUANTILE) of the *lit* part of ``image``: the pixels of the LIT_BIN
    bins (OIDN's autoexposure bins) whose mean luminance exceeds LIT_FRACTION x the frame's robust level.

    Unlike :func:`robust_level` it does not count black or near-black regions: a small object on a black background
    gets the level of the object, not of the frame. One pixel moves it by at most the 99.9th percentile over the
    lit pixel count (it can light one bin more), and it scales with the image. 0 for an empty or black image."""
    return lit_level_of_luminance(luminance(image))


def lit_level_of_luminance(lum: np.ndarray) -> float:
    """:func:`lit_level` of a luminance image ((H, W) float64, finite, ≥ 0: :func:`luminance`'s)."""
    if lum.size == 0:
        return 0.0
    height, width = lum.shape
    rows = np.array([i * height // -(-height // LIT_BIN) for i in range(-(-height // LIT_BIN))])
    cols = np.array([j * width // -(-width // LIT_BIN) for j in range(-(-width // LIT_BIN))])
    sums = np.add.reduceat(np.add.reduceat(lum, rows, axis=0), cols, axis=1)
    row_sizes, col_sizes = np.diff(np.append(rows, height)), np.diff(np.append(cols, width))
    bins = sums / np.outer(row_sizes, col_sizes)
    # as luminance gives it (float64, finite, ≥ 0), robust_level's sanitising copy would hold the same values
    clean = lum.dtype == np.float64 and bool(lum.min() >= 0.0) and math.isfinite(float(lum.max()))
    # one pixel cannot move the threshold (the brightest bin, a firefly's, could)
    frame_level = _winsorised_mean(lum.ravel()) if clean else robust_level(lum)
    if not (math.isfinite(frame_level) and frame_level > 0.0):
        return 0.0
    lit_bins = bins > LIT_FRACTION * frame_level
    if lit_bins.all() and clean:
        return frame_level  # every pixel lit: the same values as robust_level's, so the same winsorised mean
    lit = lum.ravel() if lit_bins.all() else lum[np.repeat(np.repeat(lit_bins, row_sizes, axis=0), col_sizes, axis=1)]
    k = int(WINSOR_QUANTILE * (lit.size - 1))
    cap = float(np.partition(lit, k)[k])
    level = float(np.minimum(lit, cap).mean())
    return level if level > 0.0 else float(lit.mean())


def winsorised_sum(values: np.ndarray) -> float:
    """The float64 sum of ``values`` (≥ 0, finite) with each capped at their WINSOR_QUANTILE: a sum over a layer
    that no single pixel can dominate."""
    flat = np.asarray(values, np.float64).ravel()
    if flat.size == 0:
        return 0.0
    k = int(WINSOR_QUANTILE * (flat.size - 1))
    cap = np.partition(flat, k)[k]
    return float(np.minimum(flat, cap).sum())


#: Above this many outliers in a layer, :func:`spread` filters the whole frame at once instead of adding a patch per
#: outlier (both give the same image to rounding; the patches are cheaper while outliers are few, as they are).
SPREAD_PATCH_LIMIT = 4096


def _spread_kernel() -> np.ndarray:
    """The 1-D footprint: scipy.ndimage.gaussian_filter's kernel for OUTLIER_SPREAD_SIGMA truncated at
    OUTLIER_SPREAD_RADIUS (normalised to sum 1)."""
    radius = int(OUTLIER_SPREAD_RADIUS + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / OUTLIER_SPREAD_SIGMA) ** 2)
    return k / k.sum()


def _patch(y: int, x: int, height: int, width: int) -> tuple[slice, slice, np.ndarray]:
    """The footprint of a point at (y, x): its rows, its columns and its (h, w) weights, renormalised to its part
    inside the frame (they sum to 1)."""
    k = _spread_kernel()
    r = k.size // 2
    y0, y1, x0, x1 = max(y - r, 0), min(y + r + 1, height), max(x - r, 0), min(x + r + 1, width)
    ky, kx = k[y0 - y + r:y1 - y + r], k[x0 - x + r:x1 - x + r]
    return slice(y0, y1), slice(x0, x1), np.outer(ky, kx) / (ky.sum() * kx.sum())


def spread(excess: np.ndarray) -> np.ndarray:
    """``excess`` spread over each outlier's Gaussian footprint (OUTLIER_SPREAD_SIGMA, truncated at
    OUTLIER_SPREAD_RADIUS), each footprint renormalised to its part inside the frame so the sum of ``excess`` is
    kept exactly (to rounding): (H, W, C) float64. The footprint is separable, so a patch per outlier costs a few
    hundred multiply-adds; only a layer with very many outliers is filtered whole."""
    ys, xs = np.nonzero(np.any(excess != 0, axis=-1))
    height, width = excess.shape[:2]
    if ys.size > SPREAD_PATCH_LIMIT:
        from scipy.ndimage import gaussian_filter

        blur = {"sigma": OUTLIER_SPREAD_SIGMA, "mode": "constant",
                "truncate": OUTLIER_SPREAD_RADIUS / OUTLIER_SPREAD_SIGMA}
        inside = gaussian_filter(np.ones(excess.shape[:2]), **blur)  # each footprint's mass inside the frame
        source = np.asarray(excess, np.float64) / inside[..., None]
        return np.stack([gaussian_filter(source[..., c], **blur) for c in range(excess.shape[-1])], axis=-1)
    out = np.zeros(excess.shape, np.float64)
    for y, x in zip(ys.tolist(), xs.tolist(), strict=True):
        rows, cols, weights = _patch(y, x, height, width)
        out[rows, cols] += weights[..., None] * excess[y, x].astype(np.float64)
    return out


def add_points(image: np.ndarray, ys: np.ndarray, xs: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``image`` (H, W, C) with ``values`` (n, C) added over the footprints of the points (``ys``, ``xs``), as
    :func:`add_excess` adds an excess image holding them, but patch by patch (float64 sums clipped to float32's
    range): no frame-sized float64 image while the points are few. A new float32 array."""
    if ys.size > SPREAD_PATCH_LIMIT:
        dense = np.zeros(np.shape(image), np.float64)
        np.add.at(dense, (ys, xs), values)
        return add_excess(image, dense)
    out = np.array(image, np.float32)
    height, width = out.shape[:2]
    for y, x, value in zip(ys.tolist(), xs.tolist(), np.asarray(values, np.float64), strict=True):
        rows, cols, weights = _patch(y, x, height, width)
        total = out[rows, cols].astype(np.float64) + weights[..., None] * value
        out[rows, cols] = np.clip(total, 0.0, FLOAT32_MAX)
    return out


def add_excess(image: np.ndarray, excess: np.ndarray | None) -> np.ndarray:
    """``image`` (a denoised layer) with the outliers' ``excess`` added back over their footprints
    (:func:`spread`), float64 sum clipped to float32's range; ``image`` itself when ``excess`` is None."""
    if excess is None:
        return image
    total = np.asarray(image, np.float64) + spread(excess)
    return np.clip(total, 0.0, FLOAT32_MAX).astype(np.float32)


#: The outlier locality contract (tests/model/test_outliers.py, benchmarks/bench_outliers.py): beyond FAR_RADIUS
#: pixels from an outlier, at least FAR_KEPT of the pixels stay within far_agreement's bound.
FAR_RADIUS, FAR_KEPT = 16.0, 0.999


def far_agreement(image: np.ndarray, reference: np.ndarray, where: tuple[int, int], radius: float,
                  tolerance: float = 0.01, epsilon: float = 1e-3) -> tuple[float, float]:
    """How far a change at pixel ``where`` reached from ``reference`` to ``image`` ((H, W, C) each): (the fraction of
    the pixels farther than ``radius`` from it whose every channel is within ``tolerance`` · (|reference| +
    ``epsilon`` · the reference's mean), the largest distance of a pixel outside that bound, 0 if none)."""
    ref = np.asarray(reference, np.float64)
    bad = np.any(np.abs(np.asarray(image, np.float64) - ref) > tolerance * (np.abs(ref) + epsilon * ref.mean()),
                 axis=-1)
    yy, xx = np.mgrid[0:ref.shape[0], 0:ref.shape[1]]
    distance = np.hypot(yy - where[0], xx - where[1])
    far = distance > radius
    fraction = 1.0 - np.count_nonzero(bad & far) / max(np.count_nonzero(far), 1)
    return fraction, float(distance[bad].max()) if bad.any() else 0.0
