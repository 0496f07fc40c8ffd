"""Outliers as renderers make them, kept out of every denoising method: one detector, run by model.reconstruct
before any method sees the frame.

A firefly is one sample (or a few neighbouring ones: a glint, a caustic) far brighter than the rest. A
gradient-domain renderer writes it into the pixel's base *and* into the forward differences next to it (the shift
to the neighbour fails, so the difference carries the jump); it may come alone, as a pair or as a small block. One
such value reaches every pixel of a method whose statistics, receptive field or solver steps are frame-wide
(OIDN's U-Net, the networks' attention, the CG steps of a solve). So, per layer:

1. **Base.** A *cluster* is a connected (8-neighbour) group of pixels whose luminance (channel mean) exceeds
   OUTLIER_LEVEL x the frame's level (the sum of its layers' robust levels, model.robust.robust_level: what counts
   is an outlier's size beside the image, so a nearly black layer's ordinary Monte Carlo noise is left to the
   method), at most CLUSTER_SIZE pixels a side, whose
   brightest pixel exceeds OUTLIER_LOCAL x every pixel of the ring around it. A light in view larger than that, or
   one whose rim the emitter covers in part (as a rendered light's is), is no cluster: it is left as rendered.
   Each cluster's pixels are replaced by the median of its ring (per channel), and their variance by the ring's.
2. **Gradients.** The residual of each gradient against the forward difference of that base, ``dx − Δx(base)``,
   is where a gradient disagrees with the base; a cluster of values where both the gradient and its residual
   exceed the same threshold (and pass the same local test) is replaced by the median of the gradient over its
   ring (a rendered gradient is far smoother than the base's differences, so its neighbours are the closer
   estimate). A firefly's own jump,
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
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from gradsep.model.environment import thread_map
from gradsep.model.frame import FLOAT32_MAX
from gradsep.model.policy import LUMINANCE
from gradsep.model.robust import WINSOR_QUANTILE, add_points, lit_level_of_luminance, luminance

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


_WINDOW = CLUSTER_SIZE + 2  # a cluster's box and its ring


@dataclass
class Clusters:
    """Clusters found in one (H, W) magnitude image, each in a WINDOW x WINDOW window around its box: ``rows``,
    ``cols`` (n, WINDOW) the window's pixel indices (clipped to the frame), ``member`` and ``ring`` (n, WINDOW,
    WINDOW) bool: the cluster's pixels and its ring's (inside the frame)."""

    rows: np.ndarray
    cols: np.ndarray
    member: np.ndarray
    ring: np.ndarray

    @property
    def count(self) -> int:
        return int(self.member.shape[0])

    def pixels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cluster index, row, column) of every member pixel."""
        k, i, j = np.nonzero(self.member)
        return k, self.rows[k, i], self.cols[k, j]

    def mask(self, shape: tuple[int, int], which: np.ndarray | None = None) -> np.ndarray:
        """(H, W) bool: the member pixels (of the clusters ``which`` selects, default all)."""
        k, ys, xs = self.pixels()
        out = np.zeros(shape, bool)
        chosen = np.ones(k.size, bool) if which is None else which[k]
        out[ys[chosen], xs[chosen]] = True
        return out

    def window(self, image: np.ndarray) -> np.ndarray:
        """(n, WINDOW, WINDOW, ...) the windows of ``image``."""
        return image[self.rows[:, :, None], self.cols[:, None, :]]

    def ring_median(self, image: np.ndarray) -> np.ndarray:
        """(n, ...) float64: the median of ``image`` ((H, W) or (H, W, C)) over each cluster's ring."""
        values = self.window(image).astype(np.float64)
        ring = self.ring.reshape(self.ring.shape + (1,) * (values.ndim - 3))
        values = np.where(ring, values, np.nan).reshape(self.count, -1, *values.shape[3:])
        return np.nanmedian(values, axis=1)

    def sums(self, image: np.ndarray) -> np.ndarray:
        """(n, ...) float64: the sum of ``image`` over each cluster's pixels."""
        values = self.window(image).astype(np.float64)
        member = self.member.reshape(self.member.shape + (1,) * (values.ndim - 3))
        return np.where(member, values, 0.0).sum(axis=(1, 2))

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, columns): each cluster's box's middle pixel (rounded up and to the left)."""
        in_rows, in_cols = self.member.any(axis=2), self.member.any(axis=1)
        first = np.argmax(in_rows, axis=1), np.argmax(in_cols, axis=1)
        last = _WINDOW - 1 - np.argmax(in_rows[:, ::-1], axis=1), _WINDOW - 1 - np.argmax(in_cols[:, ::-1], axis=1)
        n = np.arange(self.count)
        return self.rows[n, (first[0] + last[0]) // 2], self.cols[n, (first[1] + last[1]) // 2]


def _window_indices(start: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """((n, WINDOW) indices from ``start``, clipped to [0, size), (n, WINDOW) bool: inside the frame)."""
    index = start[:, None] + np.arange(_WINDOW)
    return np.clip(index, 0, size - 1), (index >= 0) & (index < size)


def _dilate(member: np.ndarray) -> np.ndarray:
    """(n, WINDOW, WINDOW) bool: ``member`` grown by its 8 neighbours."""
    padded = np.pad(member, ((0, 0), (1, 1), (1, 1)))
    out = np.zeros_like(member)
    for dy in range(3):
        for dx in range(3):
            out |= padded[:, dy:dy + _WINDOW, dx:dx + _WINDOW]
    return out


#: :func:`find_clusters` labels the pixels over a threshold from their coordinates while they are at most this share
#: of the frame (fireflies: a few), and with scipy.ndimage.label, which reads the whole frame, above it.
SPARSE_SHARE = 1 / 64


def _nonzero(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.nonzero`` of (H, W) bool ``mask``, in its order, reading only the rows that hold a pixel: on a frame
    whose few bright pixels lie in a few rows, a pass of ``any`` replaces np.nonzero's two full passes."""
    rows = np.flatnonzero(mask.any(axis=1))
    if 2 * rows.size > mask.shape[0]:
        return np.nonzero(mask)  # type: ignore[return-value]
    ys, xs = np.nonzero(mask[rows])
    return rows[ys], xs


def _label(over: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the (H, W) int32 labels of ``over``'s connected (8-neighbour) groups, 0 elsewhere, (n, 4) their boxes
    (first row, last row + 1, first column, last column + 1)): scipy.ndimage.label's and find_objects', numbered
    as it numbers them (in the raster order of each group's first pixel), so either way gives the same clusters."""
    if np.count_nonzero(over) <= SPARSE_SHARE * over.size:
        ys, xs = _nonzero(over)
        number = _groups(over, ys, xs)
        if number is not None:
            return _labels_of(over.shape, ys, xs, number)
    labels, _ = ndimage.label(over, structure=_EIGHT)
    return labels, np.array([(s[0].start, s[0].stop, s[1].start, s[1].stop) for s in ndimage.find_objects(labels)])


#: :func:`_groups` hooks and compresses at most this many times (a group of a few pixels takes one or two rounds),
#: then leaves a tangle of long chains to scipy.ndimage.label.
GROUP_ROUNDS = 32


def _groups(over: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray | None:
    """The 0-based group number of each pixel (``ys``, ``xs``: ``over``'s, in raster order), groups numbered in
    the raster order of their first pixel; None where it did not settle in GROUP_ROUNDS rounds. Each pixel points
    at the first pixel of its group as known so far; each round points every group's first pixel at the smallest
    first pixel joined to it by a neighbour pair, then shortens every pointer to its end."""
    height, width = over.shape
    flat = ys * width + xs  # ascending
    pairs = []
    for dy, dx in ((0, 1), (1, -1), (1, 0), (1, 1)):  # each neighbour pair once, from its earlier pixel
        y2, x2 = ys + dy, xs + dx
        near = np.flatnonzero((y2 < height) & (x2 >= 0) & (x2 < width))
        near = near[over[y2[near], x2[near]]]
        pairs.append((near, np.searchsorted(flat, flat[near] + dy * width + dx)))
    src, dst = (np.concatenate(p) for p in zip(*pairs, strict=True))
    first = np.arange(ys.size)
    for _ in range(GROUP_ROUNDS):
        a, b = first[src], first[dst]
        apart = a != b
        if not apart.any():
            return np.unique(first, return_inverse=True)[1]
        np.minimum.at(first, np.maximum(a, b)[apart], np.minimum(a, b)[apart])
        while True:
            further = first[first]
            if np.array_equal(further, first):
                break
            first = further
    return None


def _labels_of(shape: tuple[int, int], ys: np.ndarray, xs: np.ndarray,
               number: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_label`'s (labels, boxes) of the pixels (``ys``, ``xs``) in groups ``number`` (0-based)."""
    labels = np.zeros(shape, np.int32)
    labels[ys, xs] = number + 1
    count = int(number.max()) + 1
    boxes = np.empty((count, 4), np.int64)
    for column, (values, bound) in enumerate(((ys, np.minimum), (ys, np.maximum), (xs, np.minimum), (xs, np.maximum))):
        box = np.full(count, values.max() if bound is np.minimum else values.min())
        bound.at(box, number, values)
        boxes[:, column] = box + (column % 2)  # the stops are one past the last row / column
    return labels, boxes


def find_clusters(over: np.ndarray, values: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> Clusters | None:
    """The clusters among the pixels ``over`` (H, W) bool marks: its connected groups at most CLUSTER_SIZE pixels a
    side whose peak exceeds OUTLIER_LOCAL x their ring's largest value; None when none. ``values(rows, cols)``
    gives the magnitude (≥ 0) of the (n, WINDOW, WINDOW) pixels at ``rows[:, :, None], cols[:, None, :]``."""
    if not over.any():
        return None
    labels, boxes = _label(over)
    small = np.nonzero((boxes[:, 1] - boxes[:, 0] <= CLUSTER_SIZE) & (boxes[:, 3] - boxes[:, 2] <= CLUSTER_SIZE))[0]
    if small.size == 0:
        return None
    rows, row_in = _window_indices(boxes[small, 0] - 1, over.shape[0])
    cols, col_in = _window_indices(boxes[small, 2] - 1, over.shape[1])
    inside = row_in[:, :, None] & col_in[:, None, :]
    window_labels = labels[rows[:, :, None], cols[:, None, :]]
    member = (window_labels == (small + 1)[:, None, None]) & inside
    ring = _dilate(member) & (window_labels == 0) & inside
    magnitude = np.asarray(values(rows, cols), np.float64)
    peak = np.where(member, magnitude, 0.0).max(axis=(1, 2))
    around = np.where(ring, magnitude, 0.0).max(axis=(1, 2))
    keep = ring.any(axis=(1, 2)) & (peak > OUTLIER_LOCAL * around)
    if not keep.any():
        return None
    return Clusters(rows[keep], cols[keep], member[keep], ring[keep])


#: The robust level of a layer larger than this many pixels is taken on a regular subsample of at most this many.
LEVEL_SAMPLE = 1 << 18


def _level(magnitude: np.ndarray) -> float:
    """model.robust.robust_level of an (H, W) float32 magnitude (≥ 0), on a regular subsample of a large frame
    (every s-th row and column): as robust, a few times cheaper."""
    step = max(1, math.ceil(math.sqrt(magnitude.size / LEVEL_SAMPLE)))
    flat = magnitude[::step, ::step].ravel()
    k = int(WINSOR_QUANTILE * (flat.size - 1))
    cap = np.partition(flat, k)[k]
    level = float(np.minimum(flat, cap).mean(dtype=np.float64))
    return level if level > 0.0 else float(magnitude.mean(dtype=np.float64))


def _magnitude(image: np.ndarray) -> np.ndarray:
    """(H, W) float32: the channel mean of |``image``|, non-finite values read as float32's largest (one reused
    temporary, and ``fmin``, which maps NaN and ∞ alike, in one pass: it runs on every layer of every request)."""
    out = np.abs(image[..., 0])
    part = np.empty_like(out) if image.shape[-1] > 1 else out
    for c in range(1, image.shape[-1]):
        out += np.abs(image[..., c], out=part)
    out /= image.shape[-1]
    return np.fmin(out, FLOAT32_MAX, out=out)


def _all_within(image: np.ndarray, bound: float) -> bool:
    """Whether every value of ``image`` is finite and within ±``bound`` (two reductions, no temporary): then no
    channel mean of its magnitudes can exceed twice ``bound``, float rounding included, and a threshold at least
    that high needs no per-pixel pass."""
    values = np.asarray(image)
    if values.size == 0:
        return True
    return bool(values.max() <= bound) and bool(-values.min() <= bound)  # NaN compares False: not within


@dataclass
class LayerSplit:
    """What the detector did to one layer: the layer the method sees, and what goes back after it."""

    layer: Layer
    rendered: Layer  # the layer as it came
    #: (rows, columns, (n, C) excess) of the noise clusters' centres, spread over a footprint around each
    spread: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
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
        out = image if self.spread is None else add_points(image, *self.spread)
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
    #: per layer, model.robust.lit_level of the base the method sees, where the detector measured it (``sources``)
    #: and OIDN's input sanitising leaves that base as it is: the ``oidn`` method's exposure, without measuring again
    lit_levels: dict[str, float] = field(default_factory=dict)

    def restore(self, name: str, image: np.ndarray) -> np.ndarray:
        split = self.layers.get(name)
        return image if split is None else split.restore(image)

    def pinned(self) -> dict[str, np.ndarray]:
        return {name: s.pinned for name, s in self.layers.items() if s.pinned is not None}

    def warnings(self, name: str, method: str) -> list[str]:
        split = self.layers.get(name)
        return [] if split is None else split.warnings(name, method)


def _split_base(base: np.ndarray, lum: np.ndarray, level: float) -> tuple[np.ndarray, Clusters, np.ndarray] | None:
    """(the base with its clusters over OUTLIER_LEVEL x ``level`` replaced by their rings' median, the clusters, the
    (n, C) float64 excess of each cluster's pixels in ``Clusters.pixels`` order), or None when it has none.
    ``lum``: the base's :func:`_magnitude`."""
    threshold = OUTLIER_LEVEL * level
    if not (math.isfinite(threshold) and threshold > 0.0):
        return None
    clusters = find_clusters(lum > threshold, lambda rows, cols: lum[rows[:, :, None], cols[:, None, :]])
    if clusters is None:
        return None
    k, ys, xs = clusters.pixels()
    value = base[ys, xs]
    local = np.minimum(clusters.ring_median(base)[k].astype(np.float32), value)
    inlier = base.copy()
    inlier[ys, xs] = local  # set, not subtracted: value − excess would cancel catastrophically at 1e30
    return inlier, clusters, value.astype(np.float64) - local


def _noise(clusters: Clusters, excess: np.ndarray, var: np.ndarray | None) -> np.ndarray:
    """(n,) bool per cluster: its excess is noise (spread), not a light (in place), by the variance's evidence."""
    k = clusters.pixels()[0]
    sizes = np.bincount(k, minlength=clusters.count)
    if var is None:
        return sizes <= 1  # no evidence: a lone pixel is noise, a group of them a light
    y = np.bincount(k, weights=excess @ np.asarray(LUMINANCE, np.float64), minlength=clusters.count) / sizes
    v = clusters.sums(var) / sizes  # NaN (no frame from model.frame has one) reads as noise below
    v[~np.isfinite(v)] = np.inf
    return v >= NOISE_SHARE * y * y


def _centred(clusters: Clusters, excess: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, columns, (n, C) excess): each noise cluster's excess at its centre pixel (its box's middle), so that
    its footprint ends OUTLIER_SPREAD_RADIUS pixels from there."""
    k = clusters.pixels()[0]
    totals = np.stack([np.bincount(k, weights=excess[:, c], minlength=clusters.count)
                       for c in range(excess.shape[1])], axis=-1)
    ys, xs = clusters.centres()
    return ys[noise], xs[noise], totals[noise]


def _residual(gradient: np.ndarray, inlier: np.ndarray, axis: int, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """The channel mean of |gradient − the forward difference of ``inlier``| at the pixels (``ys``, ``xs``) (any
    shape, broadcast), float64; non-finite values read as float32's largest."""
    ys, xs = np.broadcast_arrays(ys, xs)
    height, width = inlier.shape[:2]
    edge = (xs >= width - 1) if axis == 1 else (ys >= height - 1)
    ahead = (ys, np.minimum(xs + 1, width - 1)) if axis == 1 else (np.minimum(ys + 1, height - 1), xs)
    with np.errstate(over="ignore", invalid="ignore"):
        difference = inlier[ahead].astype(np.float64) - inlier[ys, xs]
        difference[edge] = 0.0
        out = np.abs(gradient[ys, xs].astype(np.float64) - difference).mean(axis=-1)
    out[~np.isfinite(out)] = FLOAT32_MAX
    return out


def _clean_gradient(gradient: np.ndarray, inlier: np.ndarray, axis: int, threshold: float) -> tuple[np.ndarray, int]:
    """(``gradient`` with its clusters replaced by their rings' median, the number of values replaced; ``gradient``
    itself and 0 when it has none). A cluster's pixels are where
    both the gradient and its residual against ``inlier``'s forward difference exceed ``threshold`` (a gradient
    that is large only because the base is off is left alone)."""
    if _all_within(gradient, threshold / 2):  # a clean gradient, the usual case: nothing near the threshold
        return gradient, 0
    ys, xs = _nonzero(_magnitude(gradient) > threshold)
    if ys.size == 0:
        return gradient, 0
    large = _residual(gradient, inlier, axis, ys, xs) > threshold
    if not large.any():
        return gradient, 0
    over = np.zeros(inlier.shape[:2], bool)
    over[ys[large], xs[large]] = True
    clusters = find_clusters(over, lambda rows, cols: _residual(gradient, inlier, axis, rows[:, :, None],
                                                                cols[:, None, :]))
    if clusters is None:
        return gradient, 0
    k, ys, xs = clusters.pixels()
    fixed = gradient.copy()
    fixed[ys, xs] = clusters.ring_median(gradient)[k].astype(gradient.dtype)
    return fixed, int(k.size)


def _clean_gradients(layer: Layer, inlier: np.ndarray, level: float) -> tuple[Any, Any, int]:
    """(dx, dy with their clusters over OUTLIER_LEVEL x the layer's robust ``level`` replaced (:func:`_clean_gradient`),
    the number of values replaced)."""
    threshold = OUTLIER_LEVEL * level
    if layer.dx is None or layer.dy is None or not (math.isfinite(threshold) and threshold > 0.0):
        return layer.dx, layer.dy, 0
    out, count = [], 0
    for axis, gradient in ((1, layer.dx), (0, layer.dy)):
        fixed, replaced = _clean_gradient(gradient, inlier, axis, threshold)
        out.append(fixed)
        count += replaced
    return out[0], out[1], count


def _sources(base: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray] | None, float]:
    """(``base`` with the pixels of a light in view (over SOURCE_LEVEL x the lit level, in a group) scaled down to
    that luminance, colour kept, and their (H, W) bool mask, or None when there are none; ``base``'s lit level)."""
    lum = luminance(base)
    level = lit_level_of_luminance(lum)
    if not (math.isfinite(level) and level > 0.0):
        return None, level
    cap = SOURCE_LEVEL * level
    over = lum > cap
    ys, xs = _nonzero(over)
    if ys.size == 0:
        return None, level
    grouped = _neighbour_counts(over, ys, xs) > 1  # itself and at least one of its 8 neighbours
    if not grouped.any():
        return None, level
    source = np.zeros_like(over)
    source[ys[grouped], xs[grouped]] = True
    capped = base.copy()
    capped[source] = base[source] * (cap / lum[source])[:, None]
    return (capped, source), level


def _denoised_as_is(base: np.ndarray) -> bool:
    """Whether OIDN's input sanitising (model.oidn: NaN to 0, clamped to [0, float32 max]) leaves float32 ``base``
    as it is: finite and ≥ 0."""
    return base.size > 0 and bool(base.min() >= 0.0) and math.isfinite(float(base.max()))


def _neighbour_counts(mask: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """How many pixels of ``mask`` (H, W) bool lie in the 3 x 3 block around each pixel (``ys``, ``xs``), itself
    included: a full-frame 3 x 3 convolution, read at these pixels only (few: the bright ones)."""
    padded = np.pad(mask, 1)
    counts = np.zeros(ys.shape, np.int8)
    for dy in range(3):
        for dx in range(3):
            counts += padded[ys + dy, xs + dx]
    return counts


def light_in_view(layer: Layer) -> bool:
    """Whether ``layer`` holds a light in view as ``oidn`` sees it: a cluster whose energy goes back in place, or
    a capped bright source."""
    from gradsep.model.frame import Layer

    split = split_layer(Layer(layer.base, var=layer.var), sources=True)
    return split is not None and split.in_place is not None


def _base_level(layer: Layer) -> tuple[np.ndarray, float] | None:
    """(the layer's base as float32 with its :func:`_magnitude`, its robust level), or None for no usable base."""
    base = np.asarray(layer.base, np.float32)
    if base.ndim != 3 or base.size == 0:
        return None
    lum = _magnitude(base)
    return lum, _level(lum)


def split_layer(layer: Layer, sources: bool = False, level: float | None = None,
                measured: tuple[np.ndarray, float] | None = None) -> LayerSplit | None:
    """What the detector does to ``layer`` (the module docstring), or None when it finds nothing. ``level``: the
    frame's level the thresholds are taken from (:func:`split_frame`); None: the layer's own. ``measured``: the
    layer's :func:`_base_level` when the caller has it."""
    return _split_layer(layer, sources, level, measured)[0]


def _split_layer(layer: Layer, sources: bool, level: float | None,
                 measured: tuple[np.ndarray, float] | None) -> tuple[LayerSplit | None, float | None]:
    """(:func:`split_layer`, the lit level for FrameSplit.lit_levels or None)."""
    from gradsep.model.frame import Layer

    measured = measured or _base_level(layer)
    if measured is None:
        return None, None
    lum, own = measured
    level = own if level is None else level
    base = np.asarray(layer.base, np.float32)
    found = _split_base(base, lum, level)
    split = LayerSplit(layer, layer)
    inlier, var, pinned = base, layer.var, np.zeros(base.shape[:2], bool)
    if found is not None:
        inlier, clusters, excess = found
        noise = _noise(clusters, excess, layer.var)
        split.spread = _centred(clusters, excess, noise) if noise.any() else None
        light = clusters.mask(pinned.shape, ~noise)
        pinned |= light
        split.lights = int(np.count_nonzero(light))
        split.outliers = int(clusters.member.sum()) - split.lights
        if var is not None:
            k, ys, xs = clusters.pixels()
            var = np.array(var, copy=True)
            var[ys, xs] = clusters.ring_median(var)[k]
    dx, dy, split.gradients = _clean_gradients(layer, inlier, level)
    capped, lit = _sources(inlier) if sources else (None, None)
    if capped is not None:
        inlier, source = capped
        pinned |= source
        split.sources = int(np.count_nonzero(source))
        lit = None  # measured before the capping
    elif lit is not None and not _denoised_as_is(inlier):
        lit = None
    if not split.handled:
        return None, lit
    if pinned.any():
        split.in_place, split.pinned = pinned, ndimage.binary_dilation(pinned)
    split.layer = Layer(inlier, dx, dy, var)
    return split, lit


def split_frame(frame: Frame, sources: bool = False, threads: int = 1) -> tuple[Frame, FrameSplit]:
    """(``frame`` with each layer as the method sees it, what the detector did); ``frame`` itself and an empty
    split when it finds nothing in any layer. Every layer's thresholds are taken from the frame's level (the sum of
    its layers' robust levels): what counts is an outlier's size beside the image, so a nearly black layer's
    ordinary Monte Carlo noise is left to the method. ``threads`` > 1: up to that many layers are measured, then
    searched, at once (numpy's passes over a layer release the GIL); the same result, and the same error (the
    first layer's in the frame's order), as one after the other."""
    names = list(frame.layers)
    measured = dict(zip(names, thread_map(lambda name: _base_level(frame.layers[name]), names, threads,
                                          "gradsep-outliers"), strict=True))
    level = float(sum(m[1] for m in measured.values() if m is not None))
    found = dict(zip(names, thread_map(lambda name: _split_layer(frame.layers[name], sources, level, measured[name]),
                                       names, threads, "gradsep-outliers"), strict=True))
    split = FrameSplit({name: s for name, (s, _) in found.items() if s is not None},
                       {name: lit for name, (_, lit) in found.items() if lit is not None})
    if not split.layers:
        return frame, split
    return replace(frame, layers={name: split.layers[name].layer if name in split.layers else layer
                                  for name, layer in frame.layers.items()}), split
