"""The temporal rejection test (model/temporal.py's step 2): whether a neighbour's pixel, warped onto frame t's, is
kept or rejected.

Per layer and pixel, a neighbour is rejected where it disagrees with frame t by more than the noise allows: the
difference of the two luminances, box-filtered, against REJECT_K standard errors of that difference (the box means'
variances from the two variance channels), at each box size in BOXES. A light switched off, a moving shadow or a
highlight that moves differently from its surface changes the mean by more than the noise, so the neighbour's
samples there are dropped; a difference within the noise is what noise looks like, so they are kept. Where the
features disagree (albedo or normal: another surface) the neighbour is rejected as well.

What the test reads of a frame (:class:`Stats`: luminance, variance, the FEATURE_BOX means of the features) is
computed once per frame (:func:`frame_stats`), and so is the frame's weight in the average (:func:`frame_weight`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gradsep.model.frame import Frame
from gradsep.model.robust import box_mean, luminance
from gradsep.model.warp import Sampler

__all__ = ["ALBEDO_TOLERANCE", "BOXES", "FEATURE_BOX", "NORMAL_COSINE", "REJECT_K", "Stats", "agrees",
           "features_agree", "frame_stats", "frame_weight"]

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
        a, b = centre.normal, sample(other.normal)
        dot = a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]
        aa = a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1] + a[..., 2] * a[..., 2]
        bb = b[..., 0] * b[..., 0] + b[..., 1] * b[..., 1] + b[..., 2] * b[..., 2]
        agree &= (dot >= NORMAL_COSINE * np.sqrt(aa * bb)) | (aa * bb == 0)
    return agree


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
            accept &= difference * difference <= (REJECT_K * REJECT_K / (size * size)) * (var + other_var)
        return accept
    valid = sample.valid
    difference = np.where(valid, sample(other.y[name]) - own.y[name], np.float32(0))
    variance = np.where(valid, warped_var + own.var[name], np.float32(0))
    for size in BOXES:  # over the n valid pixels of a box: (Σ d / n)² against K² Σ (σ² + σ'²) / n²
        box = box_mean(difference, size)
        accept &= box * box <= (REJECT_K * REJECT_K / (size * size)) * box_mean(variance, size)
    return accept
