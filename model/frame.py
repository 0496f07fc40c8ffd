"""The frame contract's in-memory side: what a gradsep frame is, its channel names and the frame types.

A frame is a single-part scanline OpenEXR file (float32 or half, any compression OpenEXR reads) carrying

* per illumination layer ``L`` in ``direct``, ``indirect`` (or ``color`` for a frame rendered without
  separation): the base radiance ``L.R L.G L.B`` and, for a gradient-domain frame, its forward differences
  ``L.dx.{R,G,B}``, ``L.dy.{R,G,B}`` (a plain path-traced frame carries the base alone; each layer has its
  three base channels or all nine, so a frame may carry gradients on some layers only, e.g. ``gradsep render
  --gradients direct``: the direct layer's gradients and a plain indirect layer), and optionally ``L.var.Y``, the
  variance of each pixel's mean luminance (float32 even in a half file; the OIDN methods use it to leave converged
  pixels alone, model/backoff.py);
* features, three optional groups, each all three (or one) of its channels or none: ``albedo.{R,G,B}`` in
  [0, 1], ``normal.{X,Y,Z}`` unit camera-space normals, ``depth.Z`` distance in scene units (0 where the camera ray
  missed). Which method uses or needs which group is declared in model/methods.py;
* optionally ``A``, alpha, carried through to the output unchanged;
* optionally motion vectors (:class:`Motion`), Nuke's ``backward`` and ``forward`` layers: ``D.u``, ``D.v`` in
  pixels and ``D.valid`` (1 valid, 0 no correspondence), float32 even in a half file. ``x_prev = x +
  backward.u``, ``y_prev = y - backward.v`` with ``y`` the row (growing downward): ``v`` grows upward, as in
  Nuke; likewise ``x_next = x + forward.u``, ``y_next = y - forward.v``.

Gradients follow ``dx(x, y) = I(x+1, y) - I(x, y)`` and ``dy(x, y) = I(x, y+1) - I(x, y)`` with ``y`` growing
downward (row order); the last column of dx and the last row of dy are 0. A frame carries only the layers its
scene needs. ``docs/frame-format.md`` is the prose version of the contract; the code is its source of truth:

* this module -- the channel names and the in-memory :class:`Frame` (its :class:`Layer` s and :class:`Features`);
* model/exr_read.py -- reading untrusted bytes into a Frame (files from other renderers through a channel layout,
  model/channels.py);
* model/exr_write.py -- writing frames and answers, whole files only;
* model/header_keys.py -- the ``gradsep.*`` header keys an answer or a planned render writes;
* model/errors.py -- :class:`~gradsep.model.errors.FrameError` and its subclasses, each with its HTTP status.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.model.channels import ALPHA
from gradsep.model.policy import FEATURE_GROUPS, ILLUMINATION_LAYERS

# ---------------------------------------------------------------------------------------------------------------
# Channel names: data, not code
# ---------------------------------------------------------------------------------------------------------------

# The layer names are the contract's constants (model/policy.py, import-light for the argument parsers).
RGB: tuple[str, ...] = ("R", "G", "B")
GRADIENTS: tuple[str, ...] = ("dx", "dy")
# A layer's optional variance channel, L.var.Y: the variance of the pixel's mean luminance (model.policy.LUMINANCE),
# the samples' variance over their count. Always float32 in a file: a half variance would underflow to 0 (read as
# "noise-free") on dim pixels.
VARIANCE = "var.Y"
#: A variance above this reads as this (a capped firefly's); Inf in a file reads as this too.
VARIANCE_MAX = 1e30
#: The largest finite float32: a frame's channels are float32, so every output is clipped to it, and no value past it
#: is ever written.
FLOAT32_MAX = float(np.finfo(np.float32).max)
# FEATURE_GROUPS (group -> its channels) is a contract constant too (model/policy.py, import-light).
FEATURE_CHANNELS: tuple[str, ...] = tuple(c for group in FEATURE_GROUPS.values() for c in group)
# Prefixes this contract owns: a channel under one of them that is not a contract channel is a producer bug and
# is rejected; channels outside them (a renderer's extra AOVs) are ignored with a warning; "A" is alpha.
OWNED_PREFIXES: tuple[str, ...] = (*ILLUMINATION_LAYERS, *FEATURE_GROUPS, "backward", "forward")
#: The motion-vector directions (Nuke's layer names): to the previous frame and to the next.
MOTION_DIRECTIONS: tuple[str, ...] = ("backward", "forward")
#: A direction's channels: displacement in pixels (u right, v up) and validity (1 valid, 0 none).
MOTION_COMPONENTS: tuple[str, ...] = ("u", "v", "valid")
#: A vector longer than this many frame diagonals is not a motion vector: it reads as invalid (with a warning).
MOTION_MAX_DIAGONALS = 4.0


def motion_channels(direction: str) -> tuple[str, ...]:
    """``backward.u backward.v backward.valid`` (or forward's): one direction's channels, in file order."""
    if direction not in MOTION_DIRECTIONS:
        raise ValueError(f"unknown motion direction {direction!r}; expected one of {MOTION_DIRECTIONS}")
    return tuple(f"{direction}.{c}" for c in MOTION_COMPONENTS)


#: Every motion channel, in canonical order.
MOTION_CHANNELS: tuple[str, ...] = tuple(c for d in MOTION_DIRECTIONS for c in motion_channels(d))


def shot_layout(channels: Iterable[str]) -> tuple[str, ...]:
    """The channels every frame of one shot shares, sorted: all but the motion vectors, which a shot's first and
    last frames carry on one side only, and the variance channels (``L.var.Y``), which a frame rendered to a
    deadline lacks where it got one sample (the temporal stages estimate a missing one per frame)."""
    return tuple(sorted(c for c in channels
                        if c.split(".", 1)[0] not in MOTION_DIRECTIONS and not is_variance_channel(c)))


def layer_channels(layer: str, gradients: bool = True) -> tuple[str, ...]:
    """The channel names of an illumination layer: base RGB, then (with ``gradients``) dx RGB, then dy RGB."""
    if layer not in ILLUMINATION_LAYERS:
        raise ValueError(f"unknown illumination layer {layer!r}; expected one of {ILLUMINATION_LAYERS}")
    base = tuple(f"{layer}.{c}" for c in RGB)
    return (*base, *(f"{layer}.{g}.{c}" for g in GRADIENTS for c in RGB)) if gradients else base


def variance_channel(layer: str) -> str:
    """The optional channel holding the variance of the layer's per-pixel mean luminance: ``L.var.Y``."""
    if layer not in ILLUMINATION_LAYERS:
        raise ValueError(f"unknown illumination layer {layer!r}; expected one of {ILLUMINATION_LAYERS}")
    return f"{layer}.{VARIANCE}"


def is_variance_channel(name: str) -> bool:
    """Whether ``name`` is a layer's variance channel (kept float32 in a half file: see :func:`encode_exr`)."""
    return name.split(".", 1)[-1] == VARIANCE and name.split(".", 1)[0] in ILLUMINATION_LAYERS


def is_float32_channel(name: str) -> bool:
    """Whether ``name`` stays float32 in a half file: a layer's variance, or a motion channel (half's step at a
    few hundred pixels would move a warped sample by a fraction of a pixel)."""
    return is_variance_channel(name) or name in MOTION_CHANNELS


def frame_channels(layers: Iterable[str], features: bool = True, gradients: bool = True) -> tuple[str, ...]:
    """Every channel a frame with these layers (and optionally the features) carries, in canonical order."""
    names = [c for layer in layers for c in layer_channels(layer, gradients)]
    return (*names, *(FEATURE_CHANNELS if features else ()))


# ---------------------------------------------------------------------------------------------------------------
# The in-memory frame
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class Layer:
    """One illumination layer: float32 arrays of shape (H, W, 3) (the variance (H, W)). A plain (primal-only) layer
    has no gradients; a layer from another renderer, or rendered at 1 spp, has no variance."""

    base: np.ndarray  # primal radiance I
    dx: np.ndarray | None = None  # I(x+1, y) - I(x, y); last column 0; None for a gradient-free layer
    dy: np.ndarray | None = None  # I(x, y+1) - I(x, y); last row 0; None for a gradient-free layer
    var: np.ndarray | None = None  # (H, W): the variance of each pixel's mean luminance Y; None: not carried

    def __post_init__(self) -> None:
        if (self.dx is None) != (self.dy is None):
            raise ValueError("a layer carries both gradients (dx and dy) or neither")

    @property
    def has_gradients(self) -> bool:
        return self.dx is not None

    def __add__(self, other: Layer) -> Layer:
        """Layers add channel-wise: gradients are linear, so direct + indirect is the unseparated layer."""
        var = None
        if self.var is not None and other.var is not None:
            # the layers of one sample are correlated: (σa + σb)² bounds the sum's variance from above
            var = (np.sqrt(self.var) + np.sqrt(other.var)) ** 2
        if self.has_gradients and other.has_gradients:
            return Layer(self.base + other.base, self.dx + other.dx, self.dy + other.dy, var)  # type: ignore[operator]
        return Layer(self.base + other.base, var=var)


@dataclass
class Features:
    """Auxiliary features at the first non-specular vertex, float32. Each group is optional (None: the frame does
    not carry it); a method that needs a group is refused for a frame without it (model/methods.py)."""

    albedo: np.ndarray | None = None  # (H, W, 3) in [0, 1]
    normal: np.ndarray | None = None  # (H, W, 3) unit camera-space normals
    depth: np.ndarray | None = None  # (H, W) distance in scene units, 0 where the camera ray missed

    @property
    def groups(self) -> tuple[str, ...]:
        """The groups present, in FEATURE_GROUPS order."""
        return tuple(g for g in FEATURE_GROUPS if getattr(self, g) is not None)

    def only(self, groups: Iterable[str]) -> Features | None:
        """These features restricted to ``groups`` (what a method declares it uses); None when none is left."""
        keep = set(groups)
        out = Features(**{g: getattr(self, g) if g in keep else None for g in FEATURE_GROUPS})
        return out if out.groups else None


def feature_groups(features: Features | None) -> tuple[str, ...]:
    """The feature groups a frame carries (``frame.features`` may be None: none)."""
    return () if features is None else features.groups


@dataclass
class Motion:
    """Motion vectors to the previous frame (``backward``) and to the next (``forward``): float32 (H, W, 2) arrays
    of (u, v) in pixels, u to the right and v upward (Nuke's convention), each with its (H, W) validity (bool; a
    pixel without a correspondence is invalid and its vector is 0). A side is None when the frame has no
    neighbour there (a shot's first or last frame) or the file does not carry it."""

    backward: np.ndarray | None = None
    forward: np.ndarray | None = None
    backward_valid: np.ndarray | None = None
    forward_valid: np.ndarray | None = None

    def __post_init__(self) -> None:
        for direction in MOTION_DIRECTIONS:
            vectors, valid = getattr(self, direction), getattr(self, f"{direction}_valid")
            if (vectors is None) != (valid is None):
                raise ValueError(f"motion {direction}: vectors and validity come together or not at all")
            if vectors is None:
                continue
            if vectors.ndim != 3 or vectors.shape[2] != 2 or valid.shape != vectors.shape[:2]:
                raise ValueError(f"motion {direction}: expected (H, W, 2) vectors and (H, W) validity, got "
                                 f"{vectors.shape} and {valid.shape}")
            setattr(self, f"{direction}_valid", np.asarray(valid) > 0.5 if valid.dtype != bool else valid)

    @property
    def directions(self) -> tuple[str, ...]:
        """The directions carried, in MOTION_DIRECTIONS order."""
        return tuple(d for d in MOTION_DIRECTIONS if getattr(self, d) is not None)

    def side(self, direction: str) -> tuple[np.ndarray, np.ndarray]:
        """(vectors (H, W, 2), validity (H, W) bool) of one direction; ValueError when it is not carried."""
        motion_channels(direction)  # checks the name
        vectors = getattr(self, direction)
        if vectors is None:
            raise ValueError(f"this frame carries no {direction} motion vectors")
        return vectors, getattr(self, f"{direction}_valid")

    def warp_source(self, direction: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where each pixel's surface point is in the neighbouring frame, as fractional (rows, cols) of pixel
        indices (row 0 at the top; pixel (r, c) has its centre at (r, c)), and the validity. Sampling the
        neighbour's image there (bilinearly) warps it onto this frame."""
        vectors, valid = self.side(direction)
        rows, cols = np.indices(valid.shape, dtype=np.float32)
        return rows - vectors[..., 1], cols + vectors[..., 0], valid

    def to_channels(self) -> dict[str, np.ndarray]:
        """Channel name -> (H, W) float32 array, for the directions carried."""
        out: dict[str, np.ndarray] = {}
        for direction in self.directions:
            vectors, valid = self.side(direction)
            u, v, ok = motion_channels(direction)
            out[u], out[v], out[ok] = vectors[..., 0], vectors[..., 1], valid.astype(np.float32)
        return out


def sanitize_motion(vectors: np.ndarray, valid: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, int]:
    """(vectors, validity, count): non-finite vectors and vectors longer than MOTION_MAX_DIAGONALS frame diagonals
    become invalid (count: how many valid ones did), and every invalid pixel's vector becomes 0. ``valid`` None:
    every pixel is valid unless its vector is bad (a file from a tool that writes no validity)."""
    vectors = np.array(vectors, dtype=np.float32)
    ok = np.ones(vectors.shape[:2], dtype=bool) if valid is None else np.asarray(valid) > 0.5
    limit = MOTION_MAX_DIAGONALS * float(np.hypot(*vectors.shape[:2]))
    with np.errstate(invalid="ignore", over="ignore"):
        bad = ~np.all(np.isfinite(vectors), axis=-1) | (np.hypot(vectors[..., 0], vectors[..., 1]) > limit)
    count = int(np.count_nonzero(bad & ok))
    ok &= ~bad
    vectors[~ok] = 0.0
    return vectors, ok, count


@dataclass
class Frame:
    """A decoded, validated frame. ``layers`` holds only the layers present, in ILLUMINATION_LAYERS order."""

    layers: dict[str, Layer]
    features: Features | None = None
    metadata: dict[str, str] = field(default_factory=dict)  # the input's string attributes
    warnings: list[str] = field(default_factory=list)
    alpha: np.ndarray | None = None  # (H, W) float32 "A" of the input, carried through to the output
    image_attributes: dict[str, Any] = field(default_factory=dict)  # data/display window, aspect...: IMAGE_ATTRIBUTES
    layout: str = "gradsep"  # the channel layout it was read with (model/channels.py)
    motion: Motion | None = None  # motion vectors to the neighbouring frames of a shot

    @property
    def height(self) -> int:
        return int(next(iter(self.layers.values())).base.shape[0])

    @property
    def width(self) -> int:
        return int(next(iter(self.layers.values())).base.shape[1])

    @property
    def has_gradients(self) -> bool:
        """True for a gradient-domain frame (every layer carries dx/dy); False for a plain path-traced one and for
        a frame with gradients on some layers only (see :attr:`gradient_layers`)."""
        return all(layer.has_gradients for layer in self.layers.values())

    @property
    def gradient_layers(self) -> tuple[str, ...]:
        """The layers that carry dx/dy, in contract order: all of them, some (``--gradients direct``), or none."""
        return tuple(name for name, layer in self.layers.items() if layer.has_gradients)

    def combined(self) -> Layer:
        """All layers summed: the unseparated ("color") layer of this frame."""
        layers = list(self.layers.values())
        total = layers[0]
        for layer in layers[1:]:
            total = total + layer
        return total

    def to_channels(self) -> dict[str, np.ndarray]:
        """Channel name -> (H, W) float32 array, in canonical order."""
        out: dict[str, np.ndarray] = {}
        for name, layer in self.layers.items():
            out.update(rgb_channels(name, layer.base))
            if layer.dx is not None and layer.dy is not None:
                out.update(rgb_channels(f"{name}.dx", layer.dx))
                out.update(rgb_channels(f"{name}.dy", layer.dy))
            if layer.var is not None:
                out[variance_channel(name)] = layer.var
        for group in feature_groups(self.features):
            image = getattr(self.features, group)
            planes = np.moveaxis(image, -1, 0) if image.ndim == 3 else image[None]
            out.update(zip(FEATURE_GROUPS[group], planes, strict=True))
        if self.alpha is not None:
            out[ALPHA] = self.alpha
        if self.motion is not None:
            out.update(self.motion.to_channels())
        return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}


def rgb_channels(prefix: str, image: np.ndarray) -> dict[str, np.ndarray]:
    """Split an (H, W, 3) image into named channels: prefix "" gives R G B, "direct" gives direct.R ..."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {image.shape}")
    dot = f"{prefix}." if prefix else ""
    return {f"{dot}{c}": image[..., i] for i, c in enumerate(RGB)}


def forward_differences(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) of an (H, W[, C]) image per the contract: forward differences, zero in the last column/row."""
    dx = np.zeros_like(image)
    dy = np.zeros_like(image)
    dx[:, :-1] = image[:, 1:] - image[:, :-1]
    dy[:-1, :] = image[1:, :] - image[:-1, :]
    return dx, dy

