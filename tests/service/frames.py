"""Real EXR test frames built with numpy + the frame contract only (the serving CI venv has no torch/mitsuba).

Frames are *consistent*: each layer's dx/dy are the exact forward differences of its base image. For such a
frame the screened Poisson energy is zero at the base image itself, so every Poisson method (l1, l2, any alpha)
must return the sum of the layers' bases. That gives tests an answer that does not depend on the solver's
implementation, and distinct seeds give every request a distinct answer (a mixed-up response is detected).
"""

from __future__ import annotations

import io
import struct
from collections.abc import Iterable

import numpy as np
import OpenEXR

from gradsep.model.exr_write import encode_exr
from gradsep.model.frame import forward_differences, rgb_channels
from gradsep.model.policy import FEATURE_GROUPS


def layer_image(height: int, width: int, seed: int, layer: str) -> np.ndarray:
    """A smooth positive (H, W, 3) image, different for every (seed, layer)."""
    rng = np.random.default_rng([seed, sum(map(ord, layer))])
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    fx, fy, phase = rng.uniform(0.02, 0.2, 3), rng.uniform(0.02, 0.2, 3), rng.uniform(0, 6.28, 3)
    img = 0.5 + 0.4 * np.sin(x[..., None] * fx + phase) * np.cos(y[..., None] * fy)
    return (img * rng.uniform(0.2, 2.0)).astype(np.float32)


def frame_channels(layers: Iterable[str] = ("direct", "indirect"), height: int = 24, width: int = 32,
                   seed: int = 0, features: bool = False, gradients: bool = True) -> dict[str, np.ndarray]:
    channels: dict[str, np.ndarray] = {}
    for layer in layers:
        base = layer_image(height, width, seed, layer)
        channels.update(rgb_channels(layer, base))
        if gradients:  # a plain path-traced frame carries the base alone
            dx, dy = forward_differences(base)
            channels.update(rgb_channels(f"{layer}.dx", dx))
            channels.update(rgb_channels(f"{layer}.dy", dy))
    if features:
        values = {"albedo": np.full((height, width, 3), 0.5, np.float32),
                  "normal": np.dstack([np.zeros((height, width, 2), np.float32), np.ones((height, width))])}
        for group, names in FEATURE_GROUPS.items():
            for i, name in enumerate(names):
                channels[name] = values[group][..., i] if group in values else np.ones((height, width))
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}


def expected_sum(layers: Iterable[str] = ("direct", "indirect"), height: int = 24, width: int = 32,
                 seed: int = 0) -> np.ndarray:
    """What any Poisson reconstruction of :func:`frame_bytes` must return: the sum of the layer bases."""
    return sum(layer_image(height, width, seed, layer) for layer in layers)  # type: ignore[return-value]


def frame_bytes(layers: Iterable[str] = ("direct", "indirect"), height: int = 24, width: int = 32, *,
                seed: int = 0, half: bool = False, features: bool = False, gradients: bool = True) -> bytes:
    return encode_exr(frame_channels(layers, height, width, seed, features, gradients), half=half)


def channels_bytes(channels: dict[str, np.ndarray], half: bool = False) -> bytes:
    """Exactly these pixels as EXR, written by OpenEXR directly (no saturation: half Inf stays Inf)."""
    dtype = np.float16 if half else np.float32
    pixels = {name: np.ascontiguousarray(value, dtype=dtype) for name, value in channels.items()}
    buffer = io.BytesIO()
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, pixels).write(buffer)
    return buffer.getvalue()


def huge_header(data: bytes, width: int = 200_000, height: int = 200_000) -> bytes:
    """A real EXR whose header declares ``width`` x ``height``: the dataWindow box2i patched in place."""
    key = b"dataWindow\x00box2i\x00"
    at = data.index(key) + len(key) + 4  # skip the attribute size
    out = bytearray(data)
    out[at:at + 16] = struct.pack("<4i", 0, 0, width - 1, height - 1)
    return bytes(out)


def subsampled(data: bytes, channel: str) -> bytes:
    """Declare ``channel`` 2x2-subsampled: its raster no longer matches the others' size."""
    at = data.index(channel.encode() + b"\x00") + len(channel) + 1
    out = bytearray(data)
    out[at + 8:at + 16] = struct.pack("<ii", 2, 2)  # after pixel type (4), pLinear (1), reserved (3)
    return bytes(out)


def decode(data: bytes) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Channels (float32, plus the stored dtype under ``dtype``) and string attributes of an EXR answer."""
    exr = OpenEXR.File(io.BytesIO(data), separate_channels=True)
    channels = {name: ch.pixels for name, ch in exr.channels().items()}
    attributes = {k: v for k, v in exr.header().items() if isinstance(v, str)}
    return channels, attributes


def rgb(channels: dict[str, np.ndarray], prefix: str = "") -> np.ndarray:
    dot = f"{prefix}." if prefix else ""
    return np.stack([channels[f"{dot}{c}"].astype(np.float32) for c in "RGB"], axis=-1)



def window_frame_bytes(noise_seed: int = 0, height: int = 16, width: int = 16, *, scale: float = 1.0,
                       motion: bool = True, layers: Iterable[str] = ("direct",),
                       metadata: dict[str, str] | None = None) -> bytes:
    """A frame of a still shot for temporal windows: every frame the same smooth image (times ``scale``: a light
    switched up) plus its own small noise (``noise_seed``), consistent gradients (so l1/l2 need no model), a
    variance channel matching the noise, and zero motion vectors valid everywhere (as the renderer writes a
    still shot's)."""
    rng = np.random.default_rng(noise_seed)
    channels: dict[str, np.ndarray] = {}
    for layer in layers:
        base = layer_image(height, width, 0, layer) * scale + 0.01 * rng.standard_normal((height, width, 1))
        base = base.astype(np.float32)
        dx, dy = forward_differences(base)
        channels.update(rgb_channels(layer, base))
        channels.update(rgb_channels(f"{layer}.dx", dx))
        channels.update(rgb_channels(f"{layer}.dy", dy))
        channels[f"{layer}.var.Y"] = np.full((height, width), 1e-4, np.float32)
    if motion:
        for direction in ("backward", "forward"):
            channels[f"{direction}.u"] = channels[f"{direction}.v"] = np.zeros((height, width), np.float32)
            channels[f"{direction}.valid"] = np.ones((height, width), np.float32)
    channels = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    return encode_exr(channels, metadata=metadata)
