"""The frame contract: the one definition of what a gradsep frame is, how it is read and how it is written.

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
* optionally ``A``, alpha, carried through to the output unchanged.

Files from other renderers (a single-layer ``R G B [A]`` beauty pass, Mitsuba's aov integrator, a Blender Cycles
multilayer EXR) are read through a channel layout (model/channels.py) that maps their names onto these.

What a reader keeps of the header and writes on the answer (:func:`encode_answer`): the data window, display
window, pixel aspect ratio, screen window, chromaticities and every string attribute (``gradsep.*`` and others).

Gradients follow ``dx(x, y) = I(x+1, y) - I(x, y)`` and ``dy(x, y) = I(x, y+1) - I(x, y)`` with ``y`` growing
downward (row order); the last column of dx and the last row of dy are 0. A frame carries only the layers its
scene needs. ``docs/frame-format.md`` is the prose version of this module; this module is the source of truth.

Reading is safe for untrusted bytes: the magic number and version flags are checked, the header is read without
decoding, multi-part / tiled / deep files and anything over the pixel budget are rejected, OpenEXR's maximum
image size is set, and only then are pixels decoded. Every problem raises a :class:`FrameError` subclass that
says what is wrong and carries the HTTP status the service answers with.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import sys
import tempfile
import threading
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np
import OpenEXR

from gradsep.model.channels import ALPHA, DEFAULT_LAYOUT, ChannelMap, LayoutError, map_channels
from gradsep.model.policy import FEATURE_GROUPS, ILLUMINATION_LAYERS, SEPARATED_LAYERS

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
# FEATURE_GROUPS (group -> its channels) is a contract constant too (model/policy.py, import-light).
FEATURE_CHANNELS: tuple[str, ...] = tuple(c for group in FEATURE_GROUPS.values() for c in group)
# Prefixes this contract owns: a channel under one of them that is not a contract channel is a producer bug and
# is rejected; channels outside them (a renderer's extra AOVs) are ignored with a warning; "A" is alpha.
OWNED_PREFIXES: tuple[str, ...] = (*ILLUMINATION_LAYERS, *FEATURE_GROUPS)

NonFinitePolicy = Literal["reject", "zero"]
NONFINITE_POLICIES: tuple[str, ...] = ("reject", "zero")

_EXR_MAGIC = 20000630  # OpenEXR's magic number, little-endian int32 at offset 0
_FLAG_TILED = 0x200  # version field bit 9: single-part tiled
_FLAG_NON_IMAGE = 0x800  # bit 11: deep data
_FLAG_MULTIPART = 0x1000  # bit 12


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


def frame_channels(layers: Iterable[str], features: bool = True, gradients: bool = True) -> tuple[str, ...]:
    """Every channel a frame with these layers (and optionally the features) carries, in canonical order."""
    names = [c for layer in layers for c in layer_channels(layer, gradients)]
    return (*names, *(FEATURE_CHANNELS if features else ()))


# ---------------------------------------------------------------------------------------------------------------
# Errors: each knows the HTTP status and stable code the service answers with
# ---------------------------------------------------------------------------------------------------------------


class FrameError(ValueError):
    """Base of every problem with an input frame. ``details`` names channels or limits where it can."""

    status: int = 400
    code: str = "bad_frame"

    def __init__(self, message: str, details: Any = None) -> None:
        super().__init__(message)
        self.message = message
        self.details = details


class NotExrError(FrameError):
    """Not an OpenEXR file, or a corrupt or truncated one."""

    status, code = 400, "not_exr"


class UnsupportedExrError(FrameError):
    """A valid OpenEXR file of a kind the contract excludes: multi-part, tiled, deep, subsampled, integer."""

    status, code = 400, "unsupported_exr"


class FrameTooLargeError(FrameError):
    """The header declares more pixels or values than the reader's budget; decided before decoding."""

    status, code = 413, "too_large"


class ChannelError(FrameError):
    """Missing, unknown or inconsistent channels, or no illumination layer. ``details`` lists the channels."""

    status, code = 422, "bad_channels"


class NonFiniteError(FrameError):
    """NaN or Inf in radiance or gradients under the ``reject`` policy. ``details`` maps channel to count."""

    status, code = 422, "non_finite"


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
class Frame:
    """A decoded, validated frame. ``layers`` holds only the layers present, in ILLUMINATION_LAYERS order."""

    layers: dict[str, Layer]
    features: Features | None = None
    metadata: dict[str, str] = field(default_factory=dict)  # the input's string attributes
    warnings: list[str] = field(default_factory=list)
    alpha: np.ndarray | None = None  # (H, W) float32 "A" of the input, carried through to the output
    image_attributes: dict[str, Any] = field(default_factory=dict)  # data/display window, aspect...: IMAGE_ATTRIBUTES
    layout: str = "gradsep"  # the channel layout it was read with (model/channels.py)

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


# ---------------------------------------------------------------------------------------------------------------
# Reading untrusted bytes
# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReadLimits:
    """Decoding budget, checked against the header before any pixel is decoded."""

    max_pixels: int = 8192 * 8192
    max_values: int = 8192 * 8192 * 24  # width * height * channels
    max_side: int = 65536  # OpenEXR's process-wide maximum image width/height while decoding


@dataclass(frozen=True)
class HeaderInfo:
    width: int
    height: int
    channels: tuple[str, ...]
    compression: str
    attributes: dict[str, str]
    image_attributes: dict[str, Any] = field(default_factory=dict)  # IMAGE_ATTRIBUTES present, checked


Source = str | os.PathLike[str] | bytes | bytearray | memoryview | BinaryIO


@contextlib.contextmanager
def _native_output_captured(sink: list[str]) -> Iterator[None]:
    """Capture what OpenEXR prints on fds 1 and 2 (it warns there on truncated files instead of raising).

    Only on the main thread of a command-line run: redirecting file descriptors is process-wide, so in a threaded
    server the library's warnings are left alone (they go to the server log) rather than swallowing other threads'
    output.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(AttributeError, OSError, ValueError):
            stream.flush()
    with contextlib.ExitStack() as stack:
        captures = []
        for fd in (1, 2):
            try:
                saved = os.dup(fd)
            except OSError:
                continue
            capture = stack.enter_context(tempfile.TemporaryFile())
            os.dup2(capture.fileno(), fd)
            captures.append((fd, saved, capture))
        try:
            yield
        finally:
            for fd, saved, capture in captures:
                os.dup2(saved, fd)
                os.close(saved)
                capture.seek(0)
                text = capture.read().decode(errors="replace")
                sink.extend(line.strip() for line in text.splitlines() if line.strip())


def _open(source: Source, header_only: bool) -> OpenEXR.File:
    """Open with OpenEXR from a path or from bytes; any library failure becomes NotExrError."""
    native: list[str] = []
    with _native_output_captured(native):
        exr = _open_quietly(source, header_only)
    if not header_only and len(exr.parts) != 1:
        # OpenEXR 3.5 does not raise on a truncated file: it returns a File with zero parts and warns on stderr.
        reason = f": {native[-1]}" if native else ""
        raise NotExrError(f"truncated or corrupt OpenEXR file (pixel data could not be decoded){reason}")
    return exr


def _open_quietly(source: Source, header_only: bool) -> OpenEXR.File:
    try:
        if isinstance(source, str | os.PathLike):
            return OpenEXR.File(os.fspath(source), separate_channels=True, header_only=header_only)
        stream = io.BytesIO(bytes(source)) if isinstance(source, bytes | bytearray | memoryview) else source
        stream.seek(0)
        return OpenEXR.File(stream, separate_channels=True, header_only=header_only)
    except (RuntimeError, OSError, ValueError, TypeError) as exc:
        raise NotExrError(f"not a readable OpenEXR file: {exc}") from exc


def _prefix(source: Source, n: int) -> bytes:
    if isinstance(source, str | os.PathLike):
        try:
            with open(source, "rb") as fh:
                return fh.read(n)
        except OSError as exc:
            raise NotExrError(f"cannot read {os.fspath(source)!r}: {exc.strerror or exc}") from exc
    if isinstance(source, bytes | bytearray | memoryview):
        return bytes(source[:n])
    source.seek(0)  # a stream source is the whole file, as for OpenEXR below
    return source.read(n)


_MAX_HEADER_BYTES = 16 << 20  # attributes beyond this are not a frame header we accept


@dataclass(frozen=True)
class _RawHeader:
    width: int
    height: int
    channels: int


def _scan_header(source: Source) -> _RawHeader:
    """Check the preamble and walk the attribute list ourselves, before OpenEXR parses anything.

    Rejects non-EXR, multi-part, tiled and deep files from the version flags, and finds the declared data window and
    channel count, so an over-budget image is refused from its header alone: OpenEXR would otherwise refuse (or try
    to allocate for) a forged 200000x200000 header in ways that do not say "too large".
    """
    head = _prefix(source, _MAX_HEADER_BYTES)
    if len(head) < 8 or struct.unpack_from("<i", head)[0] != _EXR_MAGIC:
        raise NotExrError("not an OpenEXR file (bad magic number)")
    flags = struct.unpack_from("<I", head, 4)[0]
    if flags & _FLAG_MULTIPART:
        raise UnsupportedExrError("multi-part OpenEXR files are not supported; write a single-part scanline file")
    if flags & _FLAG_NON_IMAGE:
        raise UnsupportedExrError("deep OpenEXR files are not supported; write a single-part scanline file")
    if flags & _FLAG_TILED:
        raise UnsupportedExrError("tiled OpenEXR files are not supported; write a single-part scanline file")
    pos, window, channels = 8, None, None
    try:
        while head[pos] != 0:  # attribute: name\0 type\0 int32 size, value
            name_end = head.index(b"\0", pos)
            type_end = head.index(b"\0", name_end + 1)
            name, kind = head[pos:name_end], head[name_end + 1:type_end]
            (size,) = struct.unpack_from("<i", head, type_end + 1)
            value = type_end + 5
            if size < 0 or value + size > len(head):
                raise NotExrError("truncated or corrupt OpenEXR header")
            if name == b"dataWindow" and kind == b"box2i" and size == 16:
                x0, y0, x1, y1 = struct.unpack_from("<4i", head, value)
                window = (x1 - x0 + 1, y1 - y0 + 1)
            elif name == b"channels" and kind == b"chlist":
                channels, cur = 0, value
                while head[cur] != 0:  # entry: name\0 + 16 bytes
                    cur = head.index(b"\0", cur) + 17
                    channels += 1
            pos = value + size
    except (IndexError, ValueError, struct.error) as exc:
        raise NotExrError("truncated or corrupt OpenEXR header") from exc
    if window is None or channels is None:
        raise NotExrError("OpenEXR header lacks a dataWindow or channel list")
    return _RawHeader(window[0], window[1], channels)


def _check_budget(width: int, height: int, channels: int, limits: ReadLimits) -> None:
    if width <= 0 or height <= 0:
        raise NotExrError(f"OpenEXR dataWindow is empty ({width}x{height})")
    pixels, values = width * height, width * height * max(channels, 1)
    budget = {"width": width, "height": height, "channels": channels,
              "max_pixels": limits.max_pixels, "max_values": limits.max_values, "max_side": limits.max_side}
    if max(width, height) > limits.max_side or pixels > limits.max_pixels:
        raise FrameTooLargeError(
            f"image of {width}x{height} pixels is over the limit of {limits.max_pixels} pixels "
            f"(and {limits.max_side} per side)", budget)
    if values > limits.max_values:
        raise FrameTooLargeError(
            f"image of {width}x{height} pixels x {channels} channels = {values} values is over the limit "
            f"of {limits.max_values}", budget)


def _string_attributes(header: Mapping[str, Any]) -> dict[str, str]:
    return {k: v for k, v in header.items() if isinstance(v, str) and k not in _STRUCTURAL_ATTRIBUTES}


#: Typed header attributes an answer carries over from its request, each with the shape of numbers it must have
#: (values from untrusted files are checked here, so writing them back cannot fail). Where the pixels sit
#: (data window inside the display window), their shape (pixel aspect ratio, screen window) and their colour
#: space (chromaticities, white luminance): a compositor places and grades the answer as it did the input.
IMAGE_ATTRIBUTES: dict[str, tuple[int, ...]] = {
    "dataWindow": (2, 2), "displayWindow": (2, 2), "pixelAspectRatio": (), "screenWindowCenter": (2,),
    "screenWindowWidth": (), "chromaticities": (8,), "whiteLuminance": (),
}
_INTEGER_ATTRIBUTES = frozenset({"dataWindow", "displayWindow"})
#: Attributes that describe a file's storage, not its image: never copied (the writer sets its own).
_STRUCTURAL_ATTRIBUTES = frozenset({"channels", "compression", "type", "lineOrder", "name", "version", "chunkCount",
                                    "tiles"})


def _image_attributes(header: Mapping[str, Any]) -> dict[str, Any]:
    """The IMAGE_ATTRIBUTES of a header, as tuples or numpy arrays OpenEXR writes back; malformed ones dropped."""
    out: dict[str, Any] = {}
    for key, shape in IMAGE_ATTRIBUTES.items():
        if key not in header:
            continue
        try:
            value = np.asarray(header[key], dtype=np.float64)
        except (TypeError, ValueError):
            continue
        if value.shape != shape or not np.all(np.isfinite(value)):
            continue
        if key in _INTEGER_ATTRIBUTES:
            box = value.astype(np.int64)
            if np.any(np.abs(box) > 2**30) or np.any(box[1] < box[0]):
                continue
            out[key] = (box[0].astype(np.int32), box[1].astype(np.int32))
        elif shape == ():
            out[key] = float(value)
        elif key == "chromaticities":
            out[key] = tuple(float(v) for v in value)
        else:
            out[key] = value.astype(np.float32)
    return out


def read_header(source: Source, limits: ReadLimits = ReadLimits()) -> HeaderInfo:
    """Read and check the header only: size, channel names, storage. Raises before any pixel is decoded."""
    raw = _scan_header(source)
    _check_budget(raw.width, raw.height, raw.channels, limits)
    exr = _open(source, header_only=True)
    if len(exr.parts) != 1:
        raise UnsupportedExrError(f"expected a single-part OpenEXR file, found {len(exr.parts)} parts")
    header = exr.header()
    storage = header.get("type", OpenEXR.scanlineimage)
    if storage != OpenEXR.scanlineimage:
        raise UnsupportedExrError(f"expected a scanline OpenEXR image, found {getattr(storage, 'name', storage)}")
    try:
        lo, hi = header["dataWindow"]
        width, height = int(hi[0]) - int(lo[0]) + 1, int(hi[1]) - int(lo[1]) + 1
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise NotExrError("OpenEXR header has no valid dataWindow") from exc
    channels = header.get("channels", [])
    names = tuple(c.name for c in channels)
    _check_budget(width, height, len(names), limits)  # what OpenEXR parsed must agree with our own scan
    subsampled = [c.name for c in channels if (c.xSampling, c.ySampling) != (1, 1)]
    if subsampled:
        raise UnsupportedExrError(f"subsampled channels are not supported: {', '.join(subsampled)}", subsampled)
    compression = header.get("compression")
    return HeaderInfo(width, height, names, getattr(compression, "name", str(compression)),
                      _string_attributes(header), _image_attributes(header))


def _classify(names: Iterable[str]) -> tuple[list[str], list[str], list[str]]:
    """Split channel names into (layers present, unknown channels under our prefixes, foreign channels)."""
    known = {*frame_channels(ILLUMINATION_LAYERS), *map(variance_channel, ILLUMINATION_LAYERS)}
    present_layers = [layer for layer in ILLUMINATION_LAYERS if any(n.startswith(f"{layer}.") for n in names)]
    unknown, foreign = [], []
    for n in names:
        if n in known:
            continue
        if n.split(".", 1)[0] in OWNED_PREFIXES:
            unknown.append(n)
        else:
            foreign.append(n)
    return present_layers, unknown, foreign


def has_gradient_channels(names: Iterable[str], layer: str | None = None) -> bool:
    """Whether these channels carry any gradient channel (``L.dx.*``/``L.dy.*``) -- of ``layer``, or of any layer.

    Gradients are decided per layer: a layer with one gradient channel needs all nine of its channels (the
    missing ones are named); a layer with none is a plain layer (its three base channels).
    """
    layers = ILLUMINATION_LAYERS if layer is None else (layer,)
    return any(n.split(".")[1:2] in (["dx"], ["dy"]) and n.split(".", 1)[0] in layers for n in names)


def validate_channels(names: Iterable[str]) -> tuple[list[str], tuple[str, ...], list[str]]:
    """Check channel names against the contract; return (layers, feature groups, warnings) or raise ChannelError.

    Each layer is its three base channels (a plain layer) or, when it has any gradient channel, its nine channels;
    the layers of one frame may differ (gradients on the direct layer only). Each feature group is optional and
    all-or-nothing. Every problem is collected and reported together, naming the channels, so a producer fixes
    them in one go.
    """
    names = list(names)
    present = set(names)
    layers, unknown, foreign = _classify(names)
    problems: list[str] = []
    details: dict[str, list[str]] = {}
    if unknown:
        problems.append(f"unknown channels {', '.join(sorted(unknown))}")
        details["unknown"] = sorted(unknown)
    missing = [c for layer in layers for c in layer_channels(layer, has_gradient_channels(names, layer))
               if c not in present]
    groups = tuple(g for g, chans in FEATURE_GROUPS.items() if any(c in present for c in chans))
    # each group is all-or-nothing: albedo.R without albedo.G means the producer dropped a channel
    missing += [c for g in groups for c in FEATURE_GROUPS[g] if c not in present]
    if missing:
        problems.append(f"missing channels {', '.join(missing)}")
        details["missing"] = missing
    if not layers:
        problems.append("no illumination layer (expected direct.*, indirect.* or color.* channels, a top-level "
                        "R G B beauty pass, or a Cycles multilayer VIEWLAYER.Combined.R ...; see model/channels.py)")
        details["expected_layers"] = list(ILLUMINATION_LAYERS)
    if "color" in layers and any(layer in layers for layer in SEPARATED_LAYERS):
        problems.append("a frame carries either color.* (unseparated) or direct.*/indirect.* layers, not both")
        details["conflicting_layers"] = layers
    if problems:
        raise ChannelError("; ".join(problems), details)
    warnings = [f"ignored channels outside the frame contract: {', '.join(sorted(foreign))}"] if foreign else []
    return layers, groups, warnings


def _sanitize(channels: dict[str, np.ndarray], names: Iterable[str], policy: NonFinitePolicy,
              warnings: list[str]) -> None:
    """Apply the non-finite policy to radiance/gradient channels in place."""
    bad = {n: int(np.count_nonzero(~np.isfinite(channels[n]))) for n in names}
    bad = {n: k for n, k in bad.items() if k}
    if not bad:
        return
    listing = ", ".join(f"{n} ({k})" for n, k in bad.items())
    if policy == "reject":
        raise NonFiniteError(f"non-finite values (NaN/Inf) in {listing}", bad)
    for n in bad:
        np.nan_to_num(channels[n], copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    warnings.append(f"replaced non-finite values with 0 in {listing}")


def negative_radiance(channels: Mapping[str, np.ndarray], names: Iterable[str]) -> dict[str, int]:
    """Per channel, how many values are below 0 (radiance is non-negative; gradients are signed, not counted)."""
    counts = {n: int(np.count_nonzero(channels[n] < 0)) for n in names}
    return {n: k for n, k in counts.items() if k}


def map_frame_channels(names: Iterable[str], layout: str = DEFAULT_LAYOUT) -> ChannelMap:
    """The file's channels mapped through ``layout`` (model/channels.py); layout problems are ChannelErrors."""
    try:
        return map_channels(list(names), layout)
    except LayoutError as exc:
        raise ChannelError(exc.message, exc.details) from None
    except ValueError as exc:  # an unknown layout name
        raise ChannelError(str(exc), {"layout": layout}) from None


def read_frame(source: Source, *, limits: ReadLimits = ReadLimits(),
               nonfinite: NonFinitePolicy = "reject", layout: str = DEFAULT_LAYOUT) -> Frame:
    """Read, check and decode a frame from a path, bytes or a binary stream.

    Non-finite feature values become 0 (as the paper does). Non-finite radiance or gradients are rejected naming
    the channel and count (``reject``), or replaced with 0 and reported in ``Frame.warnings`` (``zero``).
    ``layout`` is the channel layout (model/channels.py: ``auto``, ``gradsep``, ``mitsuba-aov``, ``cycles``,
    ``cycles:VIEWLAYER``). Negative radiance is kept for the solvers and reported with its count (the
    reconstruction's output is clamped at 0: model/reconstruct.py). Alpha (``A``) is kept, non-finite values 0.
    """
    if nonfinite not in NONFINITE_POLICIES:
        raise ValueError(f"nonfinite must be one of {NONFINITE_POLICIES}, got {nonfinite!r}")
    info = read_header(source, limits)
    cmap = map_frame_channels(info.channels, layout)  # contract name -> the file's channel
    layers, groups, warnings = validate_channels(cmap.names)
    warnings += cmap.warnings()
    feature_channels = [c for g in groups for c in FEATURE_GROUPS[g]]
    gradients = {layer: has_gradient_channels(cmap.names, layer) for layer in layers}

    # OpenEXR's own guard, in case a header trick slips past the check above; process-wide but fixed per config.
    OpenEXR.setMaxImageSize(limits.max_side, limits.max_side)
    exr = _open(source, header_only=False)
    decoded = exr.channels()
    channels: dict[str, np.ndarray] = {}
    wanted = [c for layer in layers for c in layer_channels(layer, gradients[layer])]
    for name in (*wanted, *feature_channels):
        channels[name] = _decoded(decoded, cmap.sources[name], info)

    _sanitize(channels, wanted, nonfinite, warnings)
    for name in feature_channels:
        np.nan_to_num(channels[name], copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    warnings += _negative_radiance_warning(channels, layers)
    alpha = None if cmap.alpha is None else _decoded(decoded, cmap.alpha, info)
    if alpha is not None:
        np.nan_to_num(alpha, copy=False, nan=0.0, posinf=0.0, neginf=0.0)

    def stack(names: Iterable[str]) -> np.ndarray:
        return np.stack([channels[n] for n in names], axis=-1)

    frame_layers = {}
    for layer in layers:
        names = layer_channels(layer, gradients[layer])
        var = None
        if variance_channel(layer) in cmap.sources:
            var = _variance(_decoded(decoded, cmap.sources[variance_channel(layer)], info), layer, warnings)
        frame_layers[layer] = (Layer(stack(names[0:3]), stack(names[3:6]), stack(names[6:9]), var)
                               if gradients[layer] else Layer(stack(names[0:3]), var=var))
    features = None
    if groups:
        features = Features(**{g: stack(FEATURE_GROUPS[g]) if len(FEATURE_GROUPS[g]) > 1
                               else channels[FEATURE_GROUPS[g][0]] for g in groups})
    return Frame(frame_layers, features, info.attributes, warnings, alpha=alpha,
                 image_attributes=dict(info.image_attributes), layout=cmap.layout)


def _variance(values: np.ndarray, layer: str, warnings: list[str]) -> np.ndarray | None:
    """A layer's variance channel as read: +Inf and values above VARIANCE_MAX read as VARIANCE_MAX ("very noisy");
    a channel with NaN or negative values is not a variance, so it is dropped with a warning (the layer is then
    reconstructed as a frame without one) rather than guessed at."""
    bad = int(np.count_nonzero(np.isnan(values) | (values < 0)))
    if bad:
        warnings.append(f"{variance_channel(layer)} has {bad} NaN or negative value(s): not a variance; ignored "
                        "(the layer is reconstructed without it)")
        return None
    return np.minimum(values, VARIANCE_MAX, out=values)


def _decoded(decoded: Mapping[str, Any], name: str, info: HeaderInfo) -> np.ndarray:
    """One decoded channel of the file as a writable float32 (H, W) array, or the error naming it."""
    ch = decoded.get(name)
    pixels = None if ch is None else ch.pixels
    if pixels is None or getattr(pixels, "shape", None) != (info.height, info.width):
        raise NotExrError(f"truncated or corrupt OpenEXR file (channel {name} could not be decoded)")
    if pixels.dtype.kind != "f":
        raise UnsupportedExrError(f"channel {name} has integer pixels; expected half or float", [name])
    if pixels.dtype == np.float32 and pixels.flags.writeable and pixels.flags.c_contiguous:
        return pixels  # the decoder's own fresh array: no copy needed (~0.1 s on a 720p frame)
    return np.array(pixels, dtype=np.float32)  # half -> float32; own, writable copy


def _negative_radiance_warning(channels: Mapping[str, np.ndarray], layers: Iterable[str]) -> list[str]:
    """The negative-radiance policy's warning: how many base values are below 0, per channel (gradients are
    signed and not counted). The values are kept for the solvers; every output layer is clamped at 0."""
    negative = negative_radiance(channels, [c for layer in layers for c in layer_channels(layer, False)])
    if not negative:
        return []
    listing = ", ".join(f"{n} ({k})" for n, k in negative.items())
    return [f"{sum(negative.values())} negative radiance value(s) in {listing}: radiance is non-negative, the "
            "output is clamped at 0"]


# ---------------------------------------------------------------------------------------------------------------
# Writing: always whole files, never half-written
# ---------------------------------------------------------------------------------------------------------------


#: Compressions an answer may reuse from its request: the lossless ones. A lossy or unknown request compression
#: gets ZIP (a reconstruction must never lose precision on the way out). `benchmarks/bench_service.py --io`
#: (720p two-layer frame with features, 2 shared cores under load): read / encode an RGB float answer take
#: none 0.23 / 0.01 s, RLE 0.31 / 0.06, ZIPS 0.68 / 0.29, ZIP 0.62 / 0.27, PIZ 1.10 / 0.91, ZSTD 0.25 / 0.14.
LOSSLESS_COMPRESSIONS = tuple(c for c in ("NO_COMPRESSION", "RLE_COMPRESSION", "ZIPS_COMPRESSION",
                                          "ZIP_COMPRESSION", "PIZ_COMPRESSION", "ZSTD_COMPRESSION")
                              if hasattr(OpenEXR, c))
DEFAULT_COMPRESSION = "ZIP_COMPRESSION"


def output_compression(requested: str | None) -> str:
    """The compression to write: ``requested`` when it is lossless and known, else ZIP."""
    return requested if requested in LOSSLESS_COMPRESSIONS else DEFAULT_COMPRESSION


HALF_MAX = 65504.0  # the largest finite half float


def half_saturation(channels: Mapping[str, np.ndarray]) -> int:
    """How many values a half-float answer saturates at ±65504 (finite values beyond half's range)."""
    return sum(int(np.count_nonzero(np.abs(np.asarray(v, dtype=np.float32)) > HALF_MAX)) for v in channels.values())


def _exr_file(channels: Mapping[str, np.ndarray], half: bool, metadata: Mapping[str, str] | None,
              compression: str | None = None, image_attributes: Mapping[str, Any] | None = None) -> OpenEXR.File:
    dtype = np.float16 if half else np.float32
    shapes = {np.shape(v) for v in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"channels must be 2-D arrays of one shape, got {sorted(shapes)}")
    pixels = {}
    for name, value in channels.items():
        arr = np.asarray(value)
        if is_variance_channel(name):  # float32 even in a half file: VARIANCE's comment
            pixels[name] = np.ascontiguousarray(arr, dtype=np.float32)
            continue
        if half:  # float32 -> half overflows to Inf above 65504: saturate instead, outputs stay finite
            arr = np.clip(arr, -HALF_MAX, HALF_MAX)
        pixels[name] = np.ascontiguousarray(arr, dtype=dtype)
    header: dict[str, Any] = {"compression": getattr(OpenEXR, output_compression(compression)),
                              "type": OpenEXR.scanlineimage}
    height, width = next(iter(shapes))
    for key, value in (image_attributes or {}).items():
        if key == "dataWindow":  # the pixels decide the window's size; the input decides where it sits
            lo = np.asarray(value[0], dtype=np.int32)
            value = (lo, lo + np.array([width - 1, height - 1], dtype=np.int32))
        header[key] = value
    header.update({k: str(v) for k, v in (metadata or {}).items()})
    return OpenEXR.File(header, pixels)  # OpenEXR mutates both dicts: they are our own copies


def configure_exr_threads(count: int = -1) -> int:
    """Set OpenEXR's process-wide thread pool (-1: one thread per core, 0: single-threaded) and return its size.

    OpenEXR's Python binding defaults to no pool, so a ZIP-compressed frame is encoded and decoded on one core: a
    1280x720 rendered frame (21 float channels) took 0.68 s to encode alone and 0.39 s with a pool of 2 on 2 cores.
    The command line sets it once for every command (gradsep/cli.py), the service from its settings. Pixels are
    identical.
    """
    threads = (os.cpu_count() or 1) if count < 0 else count
    OpenEXR.set_global_thread_count(threads)
    return threads


def encode_exr(channels: Mapping[str, np.ndarray], *, half: bool = False,
               metadata: Mapping[str, str] | None = None, compression: str | None = None,
               image_attributes: Mapping[str, Any] | None = None) -> bytes:
    """Encode channels as the bytes of a single-part scanline EXR: ZIP compression, or ``compression`` (an
    OpenEXR name such as ``"NO_COMPRESSION"``, e.g. the request's) when it is lossless. ``image_attributes``:
    typed header attributes (IMAGE_ATTRIBUTES, e.g. a Frame's) written as well."""
    buffer = io.BytesIO()
    _exr_file(channels, half, metadata, compression, image_attributes).write(buffer)
    return buffer.getvalue()


#: The OIDN setting (model.oidn.SETTINGS) a render plan asks its frame to be reconstructed with, and, on an answer,
#: the one that ran (model.oidn.frame_setting).
OIDN_SETTING_KEY = "gradsep.oidn_setting"
#: Keys an answer writes itself: the input's values for them are not carried over.
ANSWER_KEYS = frozenset({"gradsep.method", "gradsep.layers", "gradsep.alpha", "gradsep.warnings",
                         "gradsep.request_id", "gradsep.source", "gradsep.channels", OIDN_SETTING_KEY})
WARNINGS_ATTRIBUTE = "gradsep.warnings"
WARNINGS_LIMIT = 2000  # characters of gradsep.warnings in the header
#: A planned render's predicted RelMSE after reconstruction with ``PLAN_METHOD_KEY`` (renderer/plan.py writes
#: both). An answer carries the prediction only when it was reconstructed with that method: for another method
#: it would state some other method's error.
PREDICTED_RELMSE_KEY = "gradsep.predicted_relmse"
PLAN_METHOD_KEY = "gradsep.plan_method"
#: Where the prediction comes from (``frame``: the frame's own halves, renderer/check.py; ``pilot``) and the
#: frame check's figures (JSON: per half its samples, estimated RelMSE and standard error; the error-vs-spp
#: exponent it was carried with; the check's seconds and what the render held back for it). Both describe
#: PREDICTED_RELMSE_KEY and travel with it.
PREDICTED_FROM_KEY = "gradsep.predicted_from"
CHECK_KEY = "gradsep.frame_check"
PREDICTION_KEYS = (PREDICTED_RELMSE_KEY, PREDICTED_FROM_KEY, CHECK_KEY)


def encode_answer(frame: Frame, channels: Mapping[str, np.ndarray], *, half: bool = False,
                  metadata: Mapping[str, str] | None = None, warnings: list[str] | None = None,
                  compression: str | None = None) -> bytes:
    """The EXR of a reconstruction of ``frame``: the one definition the CLI and the service write answers with.

    ``channels`` (R G B, maybe layers) plus the frame's alpha as ``A``; the header carries the frame's image
    attributes (data window, display window, pixel aspect...) and string attributes, then ``metadata`` (the
    answer's own ``gradsep.*``), then ``gradsep.warnings``. A half answer that saturates values above 65504 adds a
    warning naming the count to ``warnings`` (the caller's list, so its header, stderr or HTTP header says so too).
    """
    warnings = warnings if warnings is not None else []
    out = dict(channels)
    if frame.alpha is not None:
        out[ALPHA] = frame.alpha
    if half:
        saturated = half_saturation(out)
        if saturated:
            warnings.append(f"{saturated} value(s) above the half-float range saturated at {HALF_MAX:g} "
                            "(ask for format=float / drop --half to keep them)")
    carried = {k: v for k, v in frame.metadata.items() if k not in ANSWER_KEYS and k not in IMAGE_ATTRIBUTES}
    own = dict(metadata or {})
    if PREDICTED_RELMSE_KEY in carried and own.get("gradsep.method") != carried.get(PLAN_METHOD_KEY):
        carried = {k: v for k, v in carried.items() if k not in PREDICTION_KEYS}
    if frame.layout != "gradsep":
        own["gradsep.channels"] = frame.layout

    def encode(carried: Mapping[str, str], image_attributes: Mapping[str, Any]) -> bytes:
        header = {**carried, **own}
        if warnings:
            header[WARNINGS_ATTRIBUTE] = "; ".join(warnings)[:WARNINGS_LIMIT]
        return encode_exr(out, half=half, metadata=header, compression=compression,
                          image_attributes=image_attributes)

    try:
        return encode(carried, frame.image_attributes)
    except (RuntimeError, TypeError, ValueError) as exc:  # an input attribute OpenEXR reads but will not write
        warnings.append(f"the input's header attributes could not be written on the answer and were left out "
                        f"({type(exc).__name__}: {str(exc)[:200]})")
        return encode({}, {})


def verify_exr(data: bytes, limits: ReadLimits = ReadLimits()) -> HeaderInfo:
    """Decode every channel of an EXR held in memory; NotExrError (or another FrameError) unless all decode.

    For a client that must not write a truncated or corrupt answer: OpenEXR itself does not raise on a
    truncated file (it returns no parts), and a file can have a valid header and broken pixel data.
    """
    info = read_header(data, limits)
    exr = _open(data, header_only=False)
    decoded = exr.channels()
    for name in info.channels:
        ch = decoded.get(name)
        pixels = None if ch is None else ch.pixels
        if pixels is None or getattr(pixels, "shape", None) != (info.height, info.width):
            raise NotExrError(f"truncated or corrupt OpenEXR file (channel {name} could not be decoded)")
    return info


def _default_file_mode() -> int:
    """0666 minus the process umask: what ``open()`` would create (read from /proc without changing the umask)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o644


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path`` and rename it into place (atomic on POSIX).

    The file gets the permissions ``open()`` would give it (mkstemp's 0600 would hide frames from the other users
    of a shared render-farm folder).
    """
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent or ".")
    try:
        os.fchmod(fd, _default_file_mode())
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_exr(path: str | os.PathLike[str], channels: Mapping[str, np.ndarray], *, half: bool = False,
              metadata: Mapping[str, str] | None = None, image_attributes: Mapping[str, Any] | None = None) -> None:
    """Write channels to ``path`` atomically: a killed run never leaves a half-written file."""
    write_bytes_atomic(path, encode_exr(channels, half=half, metadata=metadata, image_attributes=image_attributes))


def write_frame(path: str | os.PathLike[str], frame: Frame, *, half: bool = False) -> None:
    """Write a frame per the contract (its alpha, attributes and image attributes too), atomically."""
    write_exr(path, frame.to_channels(), half=half, metadata=frame.metadata, image_attributes=frame.image_attributes)
