"""The scores of a shot: per-frame RelMSE, flicker along the motion, disoccluded and after-a-change errors.

One definition, used by ``gradsep evaluate --shot`` (evaluation/shots.py) and ``benchmarks/bench_temporal.py
quality``, so both give the same numbers. Everything here takes images already in memory: a pipeline's
reconstructed frames, the frames themselves (for their motion vectors) and two independent references per frame.

* **RelMSE** per frame is model.metrics.relmse_unbiased (the references' noise removed); a shot's figure is the
  geometric mean over its frames (:func:`geomean`).
* **Flicker** is model.metrics.flicker along the motion: for each frame t with backward vectors, frame t − 1's
  image and references are warped onto t (bilinear, where the vectors are valid and land on screen) and the
  estimator is applied to the change of the error over that pair; the shot's flicker is the mean over pairs.
  A pair without a valid pixel counts as no pair.
* **Disoccluded pixels** are the pixels of a frame with vectors on both sides where either side has no
  correspondence (the surface is not in the previous or the next frame, or there is no surface to follow: a
  light, a mirror, the background), and the references are not black. Their
  error is pooled over the shot's frames (one relmse_unbiased over all of them): a frame holds too few such
  pixels for an estimate of its own.
* **After a change** (a light switched on or off): frame t is a change when the references' mean luminance,
  along the motion, changes by more than CHANGE_THRESHOLD (:func:`changed_frames`); the frames after it are t and
  t + 1 (a window reaches both).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.model.metrics import flicker, relmse_unbiased

__all__ = ["CHANGE_THRESHOLD", "MIN_DISOCCLUDED", "PipelineScores", "ShotTruth", "changed_frames",
           "disoccluded_masks", "flicker_pairs", "geomean", "reconstruct_shot", "score_pipeline", "warp_back"]

#: The relative change of the frame's mean luminance (along the motion) above which the light changed.
CHANGE_THRESHOLD = 0.1
#: The fewest disoccluded pixels (over the whole shot) for which their error is reported.
MIN_DISOCCLUDED = 64


def geomean(values: Sequence[float]) -> float:
    """The geometric mean of positive figures (a figure at or below zero counts as 1e-12: an error the references
    cannot resolve)."""
    return math.exp(float(np.mean(np.log(np.maximum(np.asarray(values, np.float64), 1e-12)))))


def warp_back(image: np.ndarray, frame: Any) -> tuple[np.ndarray, np.ndarray]:
    """``image`` (frame t − 1's) sampled where frame t's backward vectors point (bilinear), and the mask of the
    pixels where that is defined: valid vectors landing on screen."""
    from scipy.ndimage import map_coordinates

    rows, cols, valid = frame.motion.warp_source("backward")
    inside = valid & (rows >= 0) & (rows <= image.shape[0] - 1) & (cols >= 0) & (cols <= image.shape[1] - 1)
    out = np.stack([map_coordinates(image[..., c], [rows, cols], order=1, mode="nearest")
                    for c in range(image.shape[-1])], axis=-1)
    return out, inside


def _has_backward(frame: Any) -> bool:
    motion = getattr(frame, "motion", None)
    return motion is not None and motion.backward is not None


@dataclass
class ShotTruth:
    """Two independent references per frame, and the frames whose motion vectors the scores follow."""

    first: list[np.ndarray]
    second: list[np.ndarray]
    frames: list[Any]  # model.frame.Frame, for .motion

    def __post_init__(self) -> None:
        if not (len(self.first) == len(self.second) == len(self.frames)) or not self.frames:
            raise ValueError("a shot's truth needs two references per frame and at least one frame")


def flicker_pairs(images: Sequence[np.ndarray], truth: ShotTruth) -> list[float | None]:
    """Flicker of each consecutive pair (index t: frames t − 1 and t) along the motion; None for frame 0 and for
    a pair that cannot be aligned (no backward vectors, or no valid pixel)."""
    r1, r2 = truth.first, truth.second
    out: list[float | None] = [None]
    for t in range(1, len(images)):
        frame = truth.frames[t]
        if not _has_backward(frame):
            out.append(None)
            continue
        (x, mask), (a, _), (b, _) = (warp_back(v[t - 1], frame) for v in (images, r1, r2))
        if not mask.any():
            out.append(None)
            continue
        out.append(flicker([x, images[t]], [a, r1[t]], [b, r2[t]], masks=[None, mask]))
    return out


def disoccluded_masks(truth: ShotTruth) -> list[np.ndarray | None]:
    """Per frame, the pixels without a correspondence on one side (see the module docstring); None for a frame
    without vectors on both sides."""
    masks: list[np.ndarray | None] = []
    for t, frame in enumerate(truth.frames):
        motion = getattr(frame, "motion", None)
        if motion is None or motion.backward is None or motion.forward is None:
            masks.append(None)
            continue
        lit = (truth.first[t] + truth.second[t]).sum(-1) > 0
        masks.append(~(motion.backward_valid & motion.forward_valid) & lit)
    return masks


def _pooled_error(images: Sequence[np.ndarray], truth: ShotTruth, masks: Sequence[np.ndarray | None]) -> float | None:
    """relmse_unbiased over the masked pixels of every frame together; None below MIN_DISOCCLUDED pixels."""
    picked = [(images[t][m], truth.first[t][m], truth.second[t][m]) for t, m in enumerate(masks) if m is not None]
    if sum(len(p[0]) for p in picked) < MIN_DISOCCLUDED:
        return None
    x, a, b = (np.concatenate([p[k] for p in picked])[None] for k in range(3))
    return relmse_unbiased(x, a, b)


def changed_frames(truth: ShotTruth) -> list[int]:
    """The frames t >= 1 where the light changes: the references' mean luminance over the pixels that frame t − 1
    covers (warped along the motion; unwarped without backward vectors) differs from frame t − 1's there by more
    than CHANGE_THRESHOLD, relatively. A global figure on purpose: a light switched on or off adds or removes light
    everywhere it reaches, while a moving shadow or object moves light around (its pixels count as disoccluded,
    or as flicker) and the references' noise averages out over the frame."""
    from gradsep.model.robust import luminance

    out = []
    for t in range(1, len(truth.frames)):
        frame = truth.frames[t]
        before = 0.5 * (truth.first[t - 1].astype(np.float64) + truth.second[t - 1])
        if _has_backward(frame):
            before, mask = warp_back(before, frame)
        else:
            mask = np.ones(before.shape[:2], bool)
        now = luminance(0.5 * (truth.first[t].astype(np.float64) + truth.second[t]))[mask]
        was = luminance(before)[mask]
        if was.size and float(was.mean()) > 0 and abs(float(now.mean()) / float(was.mean()) - 1) > CHANGE_THRESHOLD:
            out.append(t)
    return out


@dataclass
class PipelineScores:
    """One pipeline's scores on a shot (see the module docstring)."""

    name: str
    errors: list[float]  # relmse_unbiased per frame
    flickers: list[float | None]  # per pair, index t: frames t - 1 and t
    disoccluded: float | None  # pooled RelMSE in the disoccluded pixels; None: not enough of them
    seconds: list[float] = field(default_factory=list)  # per frame, render + reconstruction
    method: str = ""
    spp: float = math.nan  # the rendered frames' median samples per pixel

    @property
    def relmse(self) -> float:
        return geomean(self.errors)

    @property
    def flicker(self) -> float | None:
        values = [f for f in self.flickers if f is not None]
        return float(np.mean(values)) if values else None


def score_pipeline(name: str, images: Sequence[np.ndarray], truth: ShotTruth) -> PipelineScores:
    """Every score of one pipeline's images against ``truth``."""
    if len(images) != len(truth.frames):
        raise ValueError(f"{name}: {len(images)} images for {len(truth.frames)} frames")
    errors = [relmse_unbiased(x, a, b) for x, a, b in zip(images, truth.first, truth.second, strict=True)]
    return PipelineScores(name, errors, flicker_pairs(images, truth),
                          _pooled_error(images, truth, disoccluded_masks(truth)))


def ratio(numerator: float | None, denominator: float | None) -> float | None:
    """numerator / denominator when both are finite and the denominator is > 0, else None (not defined)."""
    if numerator is None or denominator is None or not denominator > 0:
        return None
    value = numerator / denominator
    return value if math.isfinite(value) else None


def after_change_ratio(scores: PipelineScores, per_frame: PipelineScores, changes: Sequence[int]) -> float | None:
    """The worst ratio of ``scores``' error to ``per_frame``'s (the same frames reconstructed per frame) over the
    frames after a change (t and t + 1 for each change t); None without a change."""
    frames = sorted({n for t in changes for n in (t, t + 1) if n < len(scores.errors)})
    ratios = [ratio(scores.errors[n], per_frame.errors[n]) for n in frames]
    known = [r for r in ratios if r is not None]
    return max(known) if known else None


def reconstruct_shot(frames: Sequence[Any], window: int, models: Any = None,
                     clock: Callable[[], float] = time.perf_counter) -> tuple[list[np.ndarray], list[float], str]:
    """Each frame reconstructed per frame (``window`` 1: model.reconstruct.reconstruct, the frame's default method)
    or temporally (model.temporal.ShotReconstructor, in order so each frame's first stage runs once): the images,
    the seconds each took, and the method."""
    from gradsep.model.reconstruct import reconstruct
    from gradsep.model.temporal import ShotReconstructor

    shot = ShotReconstructor(lambda n: frames[n] if 0 <= n < len(frames) else None, window, models=models)
    images, seconds, method = [], [], ""
    for n in range(len(frames)):
        start = clock()
        result = reconstruct(frames[n], models=models) if window == 1 else shot.reconstruct(n)
        seconds.append(clock() - start)
        images.append(result.image)
        method = result.method
    return images, seconds, method


def median_seconds(values: Sequence[float]) -> float:
    return float(statistics.median(values)) if values else math.nan
