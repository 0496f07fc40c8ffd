"""The temporal rejection test (model/temporal.py's step 2): whether a neighbour's pixel, warped onto frame t's, is
kept or rejected.

Per layer and pixel, a neighbour is rejected where it disagrees with frame t by more than the noise allows: the
difference of the two luminances, box-filtered, against REJECT_K standard errors of that difference (the box means'
variances from the two variance channels), at each box size in BOXES. A light switched off, a moving shadow or a
highlight that moves differently from its surface changes the mean by more than the noise, so the neighbour's
samples there are dropped; a difference within the noise is what noise looks like, so they are kept. Where the
features disagree (albedo or normal: another surface) the neighbour is rejected as well.

Off the grid (a camera move, whose neighbours' pixels land between frame t's) the features are compared pixel by
pixel instead: for the moved stage's blend of results (:func:`moved_pixels`, bilinear taps) and for the first
stage's nearest-pixel inputs (:func:`taken_pixels`, which also gives their demodulation).

What the test reads of a frame (:class:`Stats`: luminance, variance, the FEATURE_BOX means of the features) is
computed once per frame (:func:`frame_stats`), and so is the frame's weight in the average (:func:`frame_weight`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.model.frame import Frame
from gradsep.model.robust import box_mean, luminance
from gradsep.model.warp import Sampler

__all__ = ["ALBEDO_FLOOR", "ALBEDO_TOLERANCE", "BOXES", "FEATURE_BOX", "MOVED_TOLERANCE", "NORMAL_COSINE",
           "REJECT_K", "TEXTURE_RATIO", "Stats", "Taken", "agrees", "features_agree", "frame_stats", "frame_weight",
           "moved_pixels", "taken_pixels"]

#: The boxes (pixels a side) over which a neighbour's luminance is compared with frame t's: a small one for local
#: changes (a shadow's edge), larger ones for changes too faint to show against one small box's noise (a light
#: switched off dims the whole room a little).
BOXES: tuple[int, ...] = (5, 17)
#: A neighbour is rejected where the box means differ by more than this many standard errors of their difference.
REJECT_K = 3.0
#: Feature agreement: the largest albedo difference and the smallest cosine between normals at which two pixels
#: still see the same surface, compared as FEATURE_BOX × FEATURE_BOX means.
ALBEDO_TOLERANCE = 0.1
NORMAL_COSINE = 0.9
FEATURE_BOX = 3
#: Off the grid (a camera move) features are compared pixel by pixel: a moved neighbour's pixel sees the same surface
#: where its albedo is within this of frame t's (every channel) and its normal's cosine with frame t's is at least 1
#: minus it: a tap that mixes two surfaces, or shading that turned with the surface, is left out.
MOVED_TOLERANCE = 0.01
#: Added to the albedo before a moved neighbour is divided by its own and multiplied by frame t's, so black albedo
#: (a light, a miss) passes the radiance through.
ALBEDO_FLOOR = 0.02
#: The nearest pixel of a moving camera's neighbour, taken by the first stage, may differ from frame t's pixel in
#: albedo by up to this factor on every channel (the texture between the two positions; more is another
#: material). Its inputs are multiplied by frame t's albedo over its own (each + ALBEDO_FLOOR).
TEXTURE_RATIO = 1.65


def _spatial_variance(y: np.ndarray) -> np.ndarray:
    """A stand-in for a missing ``L.var.Y``: the luminance's variance over the 3-pixel square around each pixel (an
    overestimate at edges, where the signal varies too)."""
    return np.maximum(box_mean(y * y, 3) - box_mean(y, 3) ** 2, 0.0)


@dataclass
class Stats:
    """What the rejection test reads of one frame, computed once per frame (a shot's frame serves several
    windows): per layer the luminance, the variance and the frame weight; the FEATURE_BOX means of albedo and
    normal; per layer and box size, once asked, the box means of the luminance and of the variance."""

    y: dict[str, np.ndarray]
    var: dict[str, np.ndarray]
    weight: dict[str, float]
    albedo: np.ndarray | None
    normal: np.ndarray | None
    boxes: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def box(self, name: str, size: int) -> tuple[np.ndarray, np.ndarray]:
        """Layer ``name``'s box means at ``size``, computed on first use: only a neighbour without motion reads
        them (a moving one's test takes box means of the warped difference)."""
        if (name, size) not in self.boxes:
            self.boxes[name, size] = (box_mean(self.y[name], size), box_mean(self.var[name], size))
        return self.boxes[name, size]


def frame_stats(frame: Frame) -> Stats:
    """Frame ``frame``'s :class:`Stats`, computed on first use and kept on the frame (``_temporal_stats``)."""
    cached = getattr(frame, "_temporal_stats", None)  # kept on the frame: it is read by up to `window` windows
    if cached is not None:
        return cached
    lum, var, weight = {}, {}, {}
    for name, layer in frame.layers.items():
        y = luminance(layer.base).astype(np.float32)
        v = (np.minimum(np.nan_to_num(layer.var, nan=0.0, posinf=1e30), 1e30).astype(np.float32)
             if layer.var is not None else _spatial_variance(y))
        lum[name], var[name], weight[name] = y, v, frame_weight(v)
    features = frame.features
    stats = Stats(lum, var, weight,
                  None if features is None or features.albedo is None else _box_features(features.albedo),
                  None if features is None or features.normal is None else _box_features(features.normal))
    frame._temporal_stats = stats  # type: ignore[attr-defined]
    return stats


def _box_features(image: np.ndarray) -> np.ndarray:
    """FEATURE_BOX × FEATURE_BOX means of an (H, W, C) feature image (float32)."""
    return np.stack([box_mean(np.asarray(image[..., c], np.float32), FEATURE_BOX) for c in range(image.shape[-1])],
                    axis=-1)


def features_agree(centre: Stats, other: Stats, sample: Sampler) -> np.ndarray:
    """Where the warped neighbour's features say it sees the same surface as frame t (True where none to test).

    Compared as FEATURE_BOX means (the neighbour's warped with it): a pixel's features are averages over its
    samples, which at a silhouette mix two surfaces in proportions that change from frame to frame; the box keeps
    that noise from reading as another surface. Depth is not compared: a pixel's mean depth mixes hits and
    misses (0) and near and far surfaces in proportions as noisy as that, and a disocclusion is what the motion
    vectors' validity marks."""
    agree = np.ones(sample.valid.shape, bool)
    if centre.albedo is not None and other.albedo is not None:
        albedo = sample(other.albedo)
        for c in range(albedo.shape[-1]):  # channel by channel: a reduction over the last axis is slow
            agree &= np.abs(albedo[..., c] - centre.albedo[..., c]) <= ALBEDO_TOLERANCE
    if centre.normal is not None and other.normal is not None:
        agree &= _cosine_at_least(centre.normal, sample(other.normal), NORMAL_COSINE, zero=True)
    return agree


def _cosine_at_least(a: np.ndarray, b: np.ndarray, cosine: float, zero: bool = False) -> np.ndarray:
    """Where two (H, W, 3) normals' cosine is at least ``cosine`` (and, with ``zero``, where either is 0: nothing
    to compare). Channel by channel: a reduction over the last axis is slow."""
    dot = a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]
    aa = a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1] + a[..., 2] * a[..., 2]
    bb = b[..., 0] * b[..., 0] + b[..., 1] * b[..., 1] + b[..., 2] * b[..., 2]
    norms = aa * bb
    out = dot >= cosine * np.sqrt(norms)
    return out | (norms == 0) if zero else out


def frame_weight(var: np.ndarray) -> float:
    """A frame's weight in the average: the inverse of its mean variance, one number per frame and layer.

    Per pixel, inverse-variance weights are biased: a pixel whose few samples missed a bright path has both a low
    value and a low variance estimate, and would weigh most. Frames of one shot usually have one sample count, so
    the weights are then equal; a frame rendered with more samples weighs more."""
    mean = float(np.mean(np.minimum(var, 1e30)))
    return 1.0 / mean if mean > 0 else 1.0


def agrees(own: Stats, other: Stats, name: str, sample: Sampler, warped_var: np.ndarray) -> np.ndarray:
    """Where two estimates of layer ``name`` agree within REJECT_K standard errors at every box size in BOXES.

    Without motion the box means of each frame are compared as computed once per frame. With motion the
    neighbour's luminance and variance are warped first and the box means taken of the difference, with frame
    the neighbour's invalid pixels left out of both sums (a box across a silhouette or a disocclusion then
    compares only what corresponds). ``warped_var`` is the neighbour's variance warped (squared weights)."""
    accept = np.ones(sample.valid.shape, bool)
    if sample.identity:
        for size in BOXES:
            (y, var), (other_y, other_var) = own.box(name, size), other.box(name, size)
            difference = other_y - y
            with np.errstate(over="ignore"):  # a difference squared past float32's largest is inf: rejected
                accept &= difference * difference <= (REJECT_K * REJECT_K / (size * size)) * (var + other_var)
        return accept
    valid = sample.valid
    difference = np.where(valid, sample(other.y[name]) - own.y[name], np.float32(0))
    variance = np.where(valid, warped_var + own.var[name], np.float32(0))
    for size in BOXES:  # over the n valid pixels of a box: (Σ d / n)² against K² Σ (σ² + σ'²) / n²
        box = box_mean(difference, size)
        with np.errstate(over="ignore"):  # as above
            accept &= box * box <= (REJECT_K * REJECT_K / (size * size)) * box_mean(variance, size)
    return accept


# ------------------------------------------------------------------------------------- off the grid, pixel by pixel


def _both_features(frame: Frame, other: Frame) -> tuple[Any, Any] | None:
    """The two frames' features, where both have albedo and normal; else None (nothing to match pixel by pixel)."""
    mine, theirs = frame.features, other.features
    if mine is None or theirs is None or any(f is None for f in (mine.albedo, mine.normal, theirs.albedo,
                                                                   theirs.normal)):
        return None
    return mine, theirs


def _same_normal(mine: np.ndarray, theirs: np.ndarray) -> np.ndarray:
    """Where two (H, W, 3) normals' cosine is at least 1 - MOVED_TOLERANCE."""
    return _cosine_at_least(np.asarray(mine, np.float32), theirs, 1.0 - MOVED_TOLERANCE)


def moved_pixels(frame: Frame, other: Frame, sample: Sampler, on_grid: np.ndarray) -> np.ndarray | None:
    """Where a neighbour's pixel lies between frame t's (valid, off the grid) and its own albedo and normal,
    sampled there (bilinear), match frame t's within MOVED_TOLERANCE; None without both features in both frames, or
    without such a pixel. Pixel by pixel, not as FEATURE_BOX means: the moved neighbour's result is blended as it
    is, so a tap across an edge of the texture or the geometry must not count."""
    features = _both_features(frame, other)
    if features is None:
        return None
    mine, theirs = features
    pixels = sample.valid & ~on_grid
    if not pixels.any():
        return None
    albedo = sample(np.asarray(theirs.albedo, np.float32))
    for c in range(albedo.shape[-1]):
        pixels &= np.abs(albedo[..., c] - mine.albedo[..., c]) <= MOVED_TOLERANCE
    return pixels & _same_normal(mine.normal, sample(np.asarray(theirs.normal, np.float32)))


@dataclass
class Taken:
    """A moving camera's neighbour as the first stage takes it, by its nearest pixels (:meth:`Sampler.nearest`)."""

    sample: Sampler
    pixels: np.ndarray  # off the grid, the same surface: normals within MOVED_TOLERANCE, albedo within TEXTURE_RATIO
    gradients: np.ndarray  # of those, where the albedo itself matches within MOVED_TOLERANCE (float32 0 / 1)
    ratio: np.ndarray  # (H, W, 3): frame t's albedo over the neighbour's, each + ALBEDO_FLOOR (1 where not taken)
    variance_scale: np.ndarray  # (H, W) float32: the square of the ratio's luminance


def taken_pixels(frame: Frame, other: Frame, sample: Sampler, on_grid: np.ndarray) -> Taken | None:
    """Where the first stage takes a moving camera's neighbour (its positions ``sample``) by its nearest pixels:
    valid, off the grid, with a normal that matches frame t's and an albedo within TEXTURE_RATIO of it; None without
    both features in both frames. Pixel by pixel: the inputs are taken as they are, so a tap across an edge of the
    geometry must not count. A pixel of the same surface with other texture is demodulated; its gradients,
    differences across the texture, are left out unless the albedo matches too."""
    features = _both_features(frame, other)
    if features is None:
        return None
    mine, theirs = features
    near = sample.nearest()
    pixels = near.valid & ~on_grid & _same_normal(mine.normal, near(np.asarray(theirs.normal, np.float32)))
    albedo, own = near(np.asarray(theirs.albedo, np.float32)), np.asarray(mine.albedo, np.float32)
    ratio = (own + np.float32(ALBEDO_FLOOR)) / (albedo + np.float32(ALBEDO_FLOOR))
    gradients = pixels.copy()
    for c in range(ratio.shape[-1]):
        pixels &= (ratio[..., c] <= TEXTURE_RATIO) & (ratio[..., c] >= 1.0 / TEXTURE_RATIO)
        gradients &= np.abs(albedo[..., c] - own[..., c]) <= MOVED_TOLERANCE
    ratio[~pixels] = 1.0  # elsewhere a tap is not taken (weight 0), and must stay finite
    scale = luminance(ratio).astype(np.float32)
    return Taken(near, pixels, gradients.astype(np.float32), ratio, scale * scale)
