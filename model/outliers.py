"""Outliers as renderers make them, kept out of every denoising method: one detector, run by model.reconstruct
before any method sees the frame.

A firefly is one sample (or a few neighbouring ones: a glint, a caustic) far brighter than the rest. A
gradient-domain renderer writes it into the pixel's base *and* into the forward differences next to it (the shift
to the neighbour fails, so the difference carries the jump); it may come alone, as a pair or as a small block. One
such value reaches every pixel of a method whose statistics, receptive field or solver steps are frame-wide
(OIDN's U-Net, the networks' attention, the CG steps of a solve). So, per layer:

1. **Base.** A *cluster* is a connected (8-neighbour) group of pixels whose luminance (channel mean) exceeds
   OUTLIER_LEVEL x the layer's robust level (model.robust.robust_level), at most CLUSTER_SIZE pixels a side, whose
   brightest pixel exceeds OUTLIER_LOCAL x every pixel of the ring around it. A light in view larger than that, or
   one whose rim the emitter covers in part (as a rendered light's is), is no cluster: it is left as rendered.
   Each cluster's pixels are replaced by the median of its ring (per channel), and their variance by the ring's.
2. **Gradients.** The residual of each gradient against the forward difference of that base, ``dx − Δx(base)``,
   is where a gradient disagrees with the base; a cluster of it (the same test, at OUTLIER_LEVEL x the larger of the
   residual's and the base's level) is replaced by the median of the gradient over its ring (a rendered gradient
   is far smoother than the base's differences, so its neighbours are the closer estimate). A firefly's own jump,
   carried by the gradients, is such a cluster once its base was replaced; so is a lone gradient spike. A gradient
   has no energy of its own (the base carries it): nothing of it is kept.
3. **Where the energy goes.** Each base cluster's excess (its value above the replacement) comes back after the
   method. The variance channel (``L.var.Y``) is the evidence: where the cluster's variance is at least
   NOISE_SHARE of its excess luminance squared (a single sample that large has a variance of about its square), it
   is noise, and its excess is spread over a Gaussian footprint around the cluster's centre
   (model.robust.spread: kept exactly, ending OUTLIER_SPREAD_RADIUS pixels away). Where many samples agree (a low
   variance: a small light in view), or a cluster of several pixels comes without a variance, it is a light: its
   pixels come back as rendered, and they and their 1-pixel rim are *pinned* (model/backoff.py gives the rim back
   as rendered too and leaves it out of its windows).
4. **Lights in view** (``sources``, the methods with ``split_sources``: ``oidn``, which smears them): on the
   replaced base, each pixel over SOURCE_LEVEL x the layer's lit level with a neighbour over it too is scaled down
   to that luminance (colour kept) for the method, comes back as rendered, and is pinned with its rim.

A layer where nothing is found is passed on as it came, the same object: a frame without outliers is reconstructed
bit for bit as without the detector. Every pixel handled is counted in the reconstruction's warnings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from gradsep.model.robust import (
    add_excess,
    channel_mean,
    lit_level_of_luminance,
    luminance,
    robust_level,
)

if TYPE_CHECKING:
    from gradsep.model.frame import Frame, Layer

#: A cluster's brightest pixel exceeds OUTLIER_LOCAL x every pixel of its ring, and every pixel of it exceeds
#: OUTLIER_LEVEL x the layer's robust level: far above Monte Carlo noise at the sample counts the methods serve.
OUTLIER_LOCAL = 8.0
OUTLIER_LEVEL = 64.0
#: The largest cluster, in pixels along each axis (a glint, a small caustic).
CLUSTER_SIZE = 3
#: A cluster whose mean variance is at least this share of its mean excess luminance squared is noise (a single
#: sample's excess x has a variance of the pixel's mean of about x²); below it, its samples agree.
NOISE_SHARE = 0.1
#: A bright source (for ``sources``): a pixel over SOURCE_LEVEL x the layer's lit level with a neighbour over it.
SOURCE_LEVEL = 256.0

_EIGHT = np.ones((3, 3), bool)


@dataclass
class Clusters:
    """Clusters found in one (H, W) magnitude image: ``labels`` (H, W) int (0: none), their ids, and ``ring``
    (H, W) int: each cluster's ring pixels carry its id."""

    labels: np.ndarray
    ids: np.ndarray
    ring: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        return self.labels > 0

    def ring_median(self, image: np.ndarray) -> np.ndarray:
        """(n, C) (or (n,) for an (H, W) image): the median of ``image`` over each cluster's ring."""
        if image.ndim == 2:
            return np.asarray(ndimage.median(image, self.ring, self.ids), np.float64).reshape(-1)
        return np.stack([self.ring_median(image[..., c]) for c in range(image.shape[-1])], axis=-1)

    def spread_image(self, image: np.ndarray, values: np.ndarray) -> np.ndarray:
        """An image shaped like ``image`` holding each cluster's row of ``values`` on its pixels (0 elsewhere)."""
        lookup = np.zeros((int(self.ids.max()) + 1, *values.shape[1:]), values.dtype)
        lookup[self.ids] = values
        out = lookup[self.labels]
        out[~self.mask] = 0
        return out


def find_clusters(magnitude: np.ndarray, threshold: float) -> Clusters | None:
    """The clusters of ``magnitude`` (H, W), finite and ≥ 0: its connected groups over ``threshold`` at most
    CLUSTER_SIZE pixels a side whose peak exceeds OUTLIER_LOCAL x their ring's largest value; None when none."""
    if not (math.isfinite(threshold) and threshold > 0.0):
        return None
    over = magnitude > threshold
    if not over.any():
        return None
    labels, count = ndimage.label(over, structure=_EIGHT)
    slices = ndimage.find_objects(labels)
    small = [i + 1 for i, s in enumerate(slices)
             if s is not None and s[0].stop - s[0].start <= CLUSTER_SIZE and s[1].stop - s[1].start <= CLUSTER_SIZE]
    if not small:
        return None
    ids = np.array(small)
    ring = np.where(over, 0, ndimage.grey_dilation(labels, footprint=_EIGHT, mode="constant", cval=0))
    peak = np.asarray(ndimage.maximum(magnitude, labels, ids), np.float64).reshape(-1)
    around = np.asarray(ndimage.maximum(magnitude, ring, ids), np.float64).reshape(-1)
    has_ring = np.asarray(ndimage.sum(np.ones_like(ring), ring, ids)).reshape(-1) > 0
    keep = ids[has_ring & (peak > OUTLIER_LOCAL * around)]
    if keep.size == 0:
        return None
    chosen = np.zeros(count + 1, bool)
    chosen[keep] = True
    return Clusters(np.where(chosen[labels], labels, 0), keep, np.where(chosen[ring], ring, 0))


@dataclass
class LayerSplit:
    """What the detector did to one layer: the layer the method sees, and what goes back after it."""

    layer: Layer
    rendered: Layer  # the layer as it came
    spread: np.ndarray | None = None  # (H, W, C) excess spread over a footprint (noise)
    in_place: np.ndarray | None = None  # (H, W) bool: pixels given back as rendered (a light)
    pinned: np.ndarray | None = None  # (H, W) bool: given back as rendered by the back-off
    outliers: int = 0  # base pixels of noise clusters (spread)
    lights: int = 0  # base pixels of light clusters (put back in place)
    gradients: int = 0  # gradient values replaced
    sources: int = 0  # pixels of a light in view capped (``sources``)

    @property
    def handled(self) -> int:
        """Every value the detector changed."""
        return self.outliers + self.lights + self.gradients + self.sources

    def restore(self, image: np.ndarray) -> np.ndarray:
        """The method's output for this layer with the excess added back: spread, or the pixels as rendered."""
        out = add_excess(image, self.spread)
        if self.in_place is not None:
            out = np.array(out, np.float32)
            out[self.in_place] = np.asarray(self.rendered.base, np.float32)[self.in_place]
        return out

    def warnings(self, name: str, method: str) -> list[str]:
        out = []
        if self.outliers or self.gradients:
            out.append(f"layer {name}: {self.outliers} outlier pixel(s) and {self.gradients} outlier gradient "
                       f"value(s) kept out of the {method} denoiser; the pixels' energy was spread over a few pixels "
                       "around each")
        if self.lights:
            out.append(f"layer {name}: {self.lights} pixel(s) of a small light in view (a bright cluster whose "
                       f"samples agree) kept out of the {method} denoiser and put back in place")
        if self.sources:
            out.append(f"layer {name}: {self.sources} pixel(s) of a bright source (a light in view) capped for the "
                       f"{method} denoiser and put back in place")
        return out


@dataclass
class FrameSplit:
    """Every layer the detector changed, by name (a layer absent here went through untouched)."""

    layers: dict[str, LayerSplit] = field(default_factory=dict)

    def restore(self, name: str, image: np.ndarray) -> np.ndarray:
        split = self.layers.get(name)
        return image if split is None else split.restore(image)

    def pinned(self) -> dict[str, np.ndarray]:
        return {name: s.pinned for name, s in self.layers.items() if s.pinned is not None}

    def warnings(self, name: str, method: str) -> list[str]:
        split = self.layers.get(name)
        return [] if split is None else split.warnings(name, method)


def _split_base(base: np.ndarray, var: np.ndarray | None) -> tuple[np.ndarray, Clusters, np.ndarray] | None:
    """(the base with its clusters replaced by their rings' median, the clusters, their excess (H, W, C) float64),
    or None when the base has none."""
    lum = channel_mean(base)
    lum[~np.isfinite(lum)] = 0.0
    clusters = find_clusters(lum, OUTLIER_LEVEL * robust_level(lum))
    if clusters is None:
        return None
    mask = clusters.mask
    local = np.minimum(clusters.spread_image(base, clusters.ring_median(base).astype(np.float32))[mask], base[mask])
    inlier = base.copy()
    inlier[mask] = local  # set, not subtracted: value − excess would cancel catastrophically at 1e30
    excess = np.zeros(base.shape, np.float64)
    excess[mask] = base[mask].astype(np.float64) - local
    return inlier, clusters, excess


def _noise(clusters: Clusters, excess: np.ndarray, var: np.ndarray | None) -> np.ndarray:
    """(n,) bool per cluster: its excess is noise (spread), not a light (in place), by the variance's evidence."""
    sizes = np.asarray(ndimage.sum(np.ones(clusters.labels.shape), clusters.labels, clusters.ids)).reshape(-1)
    if var is None:
        return sizes <= 1  # no evidence: a lone pixel is noise, a group of them a light
    y = np.asarray(ndimage.mean(luminance(excess), clusters.labels, clusters.ids), np.float64).reshape(-1)
    v = np.asarray(ndimage.mean(np.nan_to_num(var, nan=np.inf), clusters.labels, clusters.ids)).reshape(-1)
    return v >= NOISE_SHARE * y * y


def _centred(clusters: Clusters, excess: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """The noise clusters' excess moved to each cluster's centre pixel (its box's middle), so that its footprint
    ends OUTLIER_SPREAD_RADIUS pixels from there."""
    ids = clusters.ids[noise]
    totals = np.stack([np.asarray(ndimage.sum(excess[..., c], clusters.labels, ids)).reshape(-1)
                       for c in range(excess.shape[-1])], axis=-1)
    out = np.zeros_like(excess)
    boxes = ndimage.find_objects(clusters.labels)
    for cluster, total in zip(ids.tolist(), totals, strict=True):
        box = boxes[cluster - 1]
        out[(box[0].start + box[0].stop - 1) // 2, (box[1].start + box[1].stop - 1) // 2] += total
    return out


def _differences(base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The forward differences of ``base`` (the frame format's convention: last column / row 0), float64."""
    values = base.astype(np.float64)
    dx, dy = np.zeros_like(values), np.zeros_like(values)
    dx[:, :-1] = values[:, 1:] - values[:, :-1]
    dy[:-1] = values[1:] - values[:-1]
    return dx, dy


def _clean_gradient(gradient: np.ndarray, difference: np.ndarray, floor: float) -> tuple[np.ndarray, int]:
    """(``gradient`` with its residual clusters against ``difference`` replaced, the number of values replaced);
    ``gradient`` itself when it has none."""
    residual = gradient.astype(np.float64) - difference
    magnitude = channel_mean(np.abs(residual))
    magnitude[~np.isfinite(magnitude)] = 0.0
    clusters = find_clusters(magnitude, OUTLIER_LEVEL * max(robust_level(magnitude), floor))
    if clusters is None:
        return gradient, 0
    mask = clusters.mask
    out = gradient.copy()
    out[mask] = clusters.spread_image(gradient, clusters.ring_median(gradient).astype(gradient.dtype))[mask]
    return out, int(np.count_nonzero(mask))


def _sources(base: np.ndarray) -> np.ndarray | None:
    """(H, W) bool: the pixels of a light in view (SOURCE_LEVEL, in a group), or None when there are none."""
    lum = luminance(base)
    level = lit_level_of_luminance(lum)
    if not (math.isfinite(level) and level > 0.0):
        return None
    over = lum > SOURCE_LEVEL * level
    if not over.any():
        return None
    source = over & (ndimage.convolve(over.astype(np.int8), _EIGHT.astype(np.int8), mode="constant") > 1)
    return source if source.any() else None


def _cap_sources(base: np.ndarray, source: np.ndarray) -> np.ndarray:
    """``base`` with the ``source`` pixels scaled down to SOURCE_LEVEL x the lit level, colour kept."""
    lum = luminance(base)
    cap = SOURCE_LEVEL * lit_level_of_luminance(lum)
    capped = base.copy()
    capped[source] = base[source] * (cap / lum[source])[:, None]
    return capped


def light_in_view(layer: Layer) -> bool:
    """Whether ``layer`` holds a light in view as ``oidn`` sees it: a cluster whose energy goes back in place, or
    a capped bright source."""
    from gradsep.model.frame import Layer

    split = split_layer(Layer(layer.base, var=layer.var), sources=True)
    return split is not None and split.in_place is not None


def split_layer(layer: Layer, sources: bool = False) -> LayerSplit | None:
    """What the detector does to ``layer`` (the module docstring), or None when it finds nothing."""
    from gradsep.model.frame import Layer

    base = np.asarray(layer.base, np.float32)
    if base.ndim != 3 or base.size == 0:
        return None
    found = _split_base(base, layer.var)
    split = LayerSplit(layer, layer)
    inlier, var, pinned = base, layer.var, np.zeros(base.shape[:2], bool)
    if found is not None:
        inlier, clusters, excess = found
        noise = _noise(clusters, excess, layer.var)
        split.spread = _centred(clusters, excess, noise) if noise.any() else None
        light = np.isin(clusters.labels, clusters.ids[~noise])
        pinned |= light
        split.lights = int(np.count_nonzero(light))
        split.outliers = int(np.count_nonzero(clusters.mask)) - split.lights
        if var is not None:
            var = var.copy()
            var[clusters.mask] = clusters.spread_image(var, clusters.ring_median(var))[clusters.mask]
    dx, dy = layer.dx, layer.dy
    if dx is not None and dy is not None:
        diff_x, diff_y = _differences(inlier)
        floor = robust_level(inlier)
        dx, fixed_x = _clean_gradient(dx, diff_x, floor)
        dy, fixed_y = _clean_gradient(dy, diff_y, floor)
        split.gradients = fixed_x + fixed_y
    source = _sources(inlier) if sources else None
    if source is not None:
        inlier = _cap_sources(inlier, source)
        pinned |= source
        split.sources = int(np.count_nonzero(source))
    if not split.handled:
        return None
    if pinned.any():
        split.in_place, split.pinned = pinned, ndimage.binary_dilation(pinned)
    split.layer = Layer(inlier, dx, dy, var)
    return split


def split_frame(frame: Frame, sources: bool = False) -> tuple[Frame, FrameSplit]:
    """(``frame`` with each layer as the method sees it, what the detector did); ``frame`` itself and an empty
    split when it finds nothing in any layer."""
    split = FrameSplit({name: s for name, layer in frame.layers.items()
                        if (s := split_layer(layer, sources)) is not None})
    if not split.layers:
        return frame, split
    return replace(frame, layers={name: split.layers[name].layer if name in split.layers else layer
                                  for name, layer in frame.layers.items()}), split
