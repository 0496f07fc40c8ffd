"""Reading a frame from untrusted bytes: the header checked, the channels mapped and validated, the pixels decoded.

Files from other renderers (a single-layer ``R G B [A]`` beauty pass, Mitsuba's aov integrator, a Blender Cycles
multilayer EXR) are read through a channel layout (model/channels.py) that maps their names onto the contract's
(model/frame.py). What a reader keeps of the header, for the answer (model/exr_write.py): the data window, display
window, pixel aspect ratio, screen window, chromaticities and every string attribute (``gradsep.*`` and others).

Reading is safe for untrusted bytes: the magic number and version flags are checked, the header is read without
decoding, multi-part / tiled / deep files and anything over the pixel budget are rejected, OpenEXR's maximum
image size is set, and only then are pixels decoded. Every problem raises a :class:`FrameError` subclass
(model/errors.py) that says what is wrong and carries the HTTP status the service answers with. Every value the
reader replaces (non-finite radiance under the ``zero`` policy, non-finite alpha) is counted in the frame's
warnings; non-finite feature values become 0, as the paper does.
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
from typing import Any, BinaryIO, Literal

import numpy as np
import OpenEXR

from gradsep.model.channels import DEFAULT_LAYOUT, ChannelMap, LayoutError, expected_text, map_channels
from gradsep.model.errors import (
    ChannelError,
    FrameTooLargeError,
    NonFiniteError,
    NotExrError,
    UnsupportedExrError,
)
from gradsep.model.frame import (
    MOTION_CHANNELS,
    MOTION_DIRECTIONS,
    MOTION_MAX_DIAGONALS,
    OWNED_PREFIXES,
    VARIANCE_MAX,
    Features,
    Frame,
    Layer,
    Motion,
    frame_channels,
    layer_channels,
    motion_channels,
    sanitize_motion,
    variance_channel,
)
from gradsep.model.policy import FEATURE_GROUPS, ILLUMINATION_LAYERS, SEPARATED_LAYERS

NonFinitePolicy = Literal["reject", "zero"]
NONFINITE_POLICIES: tuple[str, ...] = ("reject", "zero")
_EXR_MAGIC = 20000630  # OpenEXR's magic number, little-endian int32 at offset 0
_FLAG_TILED = 0x200  # version field bit 9: single-part tiled
_FLAG_NON_IMAGE = 0x800  # bit 11: deep data
_FLAG_MULTIPART = 0x1000  # bit 12


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
    known = {*frame_channels(ILLUMINATION_LAYERS), *map(variance_channel, ILLUMINATION_LAYERS), *MOTION_CHANNELS}
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
    # a motion direction is its u and v (its validity optional: compositing tools write none)
    missing += [c for d in motion_directions(present) for c in motion_channels(d)[:2] if c not in present]
    if missing:
        problems.append(f"missing channels {', '.join(missing)}")
        details["missing"] = missing
    if not layers:
        problems.append(f"no illumination layer (expected {expected_text()}; see model/channels.py)")
        details["expected_layers"] = list(ILLUMINATION_LAYERS)
    if "color" in layers and any(layer in layers for layer in SEPARATED_LAYERS):
        problems.append("a frame carries either color.* (unseparated) or direct.*/indirect.* layers, not both")
        details["conflicting_layers"] = layers
    if problems:
        raise ChannelError("; ".join(problems), details)
    warnings = [f"ignored channels outside the frame contract: {', '.join(sorted(foreign))}"] if foreign else []
    return layers, groups, warnings


def motion_directions(names: Iterable[str]) -> tuple[str, ...]:
    """The motion directions these channels carry any channel of (``backward``, ``forward``)."""
    present = set(names)
    return tuple(d for d in MOTION_DIRECTIONS if any(c in present for c in motion_channels(d)))


def _motion(decoded: Mapping[str, Any], cmap: ChannelMap, info: HeaderInfo, warnings: list[str]) -> Motion | None:
    """The file's motion vectors (None without any): a layout's sign conventions applied, non-finite or absurd
    vectors made invalid and counted in a warning, invalid pixels' vectors 0."""
    sides: dict[str, np.ndarray | None] = {}
    for direction in motion_directions(cmap.names):
        u, v, ok = motion_channels(direction)
        planes = [_decoded(decoded, cmap.sources[c], info) * np.float32(cmap.signs.get(c, 1.0)) for c in (u, v)]
        valid = _decoded(decoded, cmap.sources[ok], info) if ok in cmap.sources else None
        if valid is not None:
            valid = np.isfinite(valid) & (valid > 0.5)
        vectors, valid, bad = sanitize_motion(np.stack(planes, axis=-1), valid)
        if bad:
            warnings.append(f"{bad} non-finite or absurd {direction} motion vector(s) (over "
                            f"{MOTION_MAX_DIAGONALS:g} frame diagonals) marked invalid")
        sides[direction], sides[f"{direction}_valid"] = vectors, valid
    return Motion(**sides) if sides else None


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
    reconstruction's output is clamped at 0: model/reconstruct.py). Alpha (``A``) is kept; its non-finite values
    become 0 and are counted in ``Frame.warnings``.
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
    alpha = None if cmap.alpha is None else _alpha(_decoded(decoded, cmap.alpha, info), cmap.alpha, warnings)

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
    motion = _motion(decoded, cmap, info, warnings)
    return Frame(frame_layers, features, info.attributes, warnings, alpha=alpha,
                 image_attributes=dict(info.image_attributes), layout=cmap.layout, motion=motion)


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


def _alpha(values: np.ndarray, name: str, warnings: list[str]) -> np.ndarray:
    """The alpha channel as read: non-finite values (NaN, ±Inf) become 0, and a warning counts them."""
    bad = int(np.count_nonzero(~np.isfinite(values)))
    if bad:
        np.nan_to_num(values, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
        warnings.append(f"replaced non-finite alpha values with 0 in {name} ({bad})")
    return values


def _decoded(decoded: Mapping[str, Any], name: str, info: HeaderInfo) -> np.ndarray:
    """One decoded channel of the file as a writable float32 (H, W) array, or the error naming it."""
    ch = decoded.get(name)
    pixels = None if ch is None else ch.pixels
    if pixels is None or getattr(pixels, "shape", None) != (info.height, info.width):
        raise NotExrError(f"truncated or corrupt OpenEXR file (channel {name} could not be decoded)")
    if pixels.dtype.kind != "f":
        raise UnsupportedExrError(f"channel {name} has integer pixels; expected half or float", [name])
    if pixels.dtype == np.float32 and pixels.flags.writeable and pixels.flags.c_contiguous:
        return pixels  # the decoder's own fresh array: no copy needed
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
