"""A seeded synthetic G-PT frame as EXR bytes: the one input the latency benchmarks share.

The benchmarks (benchmarks/bench_service.py, bench_floor.py, bench_layers.py) time the service's pipeline on this
frame so their figures are comparable and need no renderer: a separated frame (``direct`` and ``indirect``, each a
base with ``dx``/``dy`` gradients and its variance, as ``gradsep render`` writes them) plus albedo/normal/depth
features, float32. The content is generic -- smooth
shading with a step edge and a disc, multiplicative Monte-Carlo-like noise and rare fireflies in the bases, lighter
noise in the gradients -- and fitted to no scene. It exercises the cost of each method, not its quality (quality
comes from ``gradsep evaluate`` on rendered frames).

It also makes outliers as a gradient-domain renderer writes them (:func:`with_outlier`, for the outlier tests and
benchmarks/bench_outliers.py): a firefly is one sample (or a few neighbouring ones: a glint, a caustic) far brighter
than the rest. It lands in a pixel's base; the shift to each neighbour fails, so the forward differences
``dx``/``dy`` carry the jump; and the pixel's variance of its mean is that of a single sample that large.

Standard library, numpy and the frame contract only, so a serving host (no torch, no mitsuba) can run it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gradsep.model.exr_write import encode_exr
from gradsep.model.frame import Frame, Layer, forward_differences, rgb_channels, variance_channel
from gradsep.model.policy import LUMINANCE

#: Relative base noise per layer; the indirect layer is the noisier one, as in a rendered frame.
_LAYER_NOISE: dict[str, float] = {"direct": 0.3, "indirect": 0.8}


def synthetic_frame(height: int, width: int, seed: int = 0, compression: str | None = None) -> bytes:
    """A noisy separated frame with gradients and features, ``height`` x ``width``, as EXR bytes.

    ``compression`` is an OpenEXR compression name (model.exr_write.LOSSLESS_COMPRESSIONS); None is the frame
    contract's default. The same ``seed`` gives the same bytes.
    """
    if height < 2 or width < 2:
        raise ValueError(f"a synthetic frame needs at least 2x2 pixels, got {width}x{height}")
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    yy, xx = yy / height, xx / width
    channels: dict[str, np.ndarray] = {}
    weights = np.asarray(LUMINANCE)
    for layer, noise in _LAYER_NOISE.items():
        shading = np.stack([0.4 + 0.3 * np.sin(7 * xx + c) * np.cos(5 * yy - c) for c in range(3)], -1)
        edges = (xx > 0.35) * 0.5 + ((xx - 0.7) ** 2 + (yy - 0.4) ** 2 < 0.03) * 2.0
        truth = (shading + edges[..., None]) * (1.0 if layer == "direct" else 0.4)
        dx, dy = forward_differences(truth)
        fireflies = (rng.random(truth.shape[:2]) < 0.002)[..., None] * rng.exponential(20.0, truth.shape)
        base = truth * (1 + noise * rng.standard_normal(truth.shape)) + fireflies
        dx = dx + 0.3 * noise * rng.standard_normal(dx.shape)
        dy = dy + 0.3 * noise * rng.standard_normal(dy.shape)
        dx[:, -1], dy[-1] = 0, 0  # the contract: no difference past the last column / row
        channels.update(rgb_channels(layer, np.maximum(base, 0)))
        # the variance a renderer would write (L.var.Y): the noise model's, a firefly's as one sample's square
        channels[variance_channel(layer)] = ((noise * truth) ** 2) @ weights**2 + (fireflies @ weights) ** 2
        channels.update(rgb_channels(f"{layer}.dx", dx))
        channels.update(rgb_channels(f"{layer}.dy", dy))
    normal = np.dstack([np.zeros((height, width, 2), np.float32), np.ones((height, width), np.float32)])
    channels.update(dict(zip(("albedo.R", "albedo.G", "albedo.B"), np.full((3, height, width), 0.6), strict=True)))
    channels.update(dict(zip(("normal.X", "normal.Y", "normal.Z"), np.moveaxis(normal, -1, 0), strict=True)))
    channels["depth.Z"] = 2.0 + yy
    return encode_exr({k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}, compression=compression)


#: (rows, columns) of each case's pixels, relative to where it lands.
SHAPES: dict[str, tuple[int, int]] = {"grad": (1, 1), "pair": (1, 2), "block": (3, 3)}
CASES = tuple(SHAPES)


def frame_mean(frame: Frame) -> float:
    """The mean of the frame's image (the sum of its layers), over pixels and channels."""
    return float(sum(layer.base.astype(np.float64) for layer in frame.layers.values()).mean())


def outlier_layer(layer: Layer, mask: np.ndarray, value: float, gradients: bool = True,
                  variance: bool = True) -> Layer:
    """``layer`` with ``value`` added to every channel of the pixels in ``mask`` (H, W), its jump added to the
    gradients (forward differences, last column / row 0) and a single sample's variance to ``L.var.Y``."""
    extra = np.zeros(layer.base.shape, np.float64)
    extra[mask] = value
    base = np.minimum(layer.base + extra, 3e38).astype(np.float32)
    dx, dy, var = layer.dx, layer.dy, layer.var
    if gradients and dx is not None and dy is not None:
        jump_x, jump_y = np.zeros_like(extra), np.zeros_like(extra)
        jump_x[:, :-1] = extra[:, 1:] - extra[:, :-1]
        jump_y[:-1] = extra[1:] - extra[:-1]
        dx = np.clip(dx + jump_x, -3e38, 3e38).astype(np.float32)
        dy = np.clip(dy + jump_y, -3e38, 3e38).astype(np.float32)
    if variance and var is not None:
        lum = float(np.dot(LUMINANCE, [value] * 3))
        var = np.minimum(var + mask * lum * lum, 3e38).astype(np.float32)
    return Layer(base, dx, dy, var)


def with_outlier(frame: Frame, case: str, where: tuple[int, int], times: float,
                 layers: tuple[str, ...] | None = None) -> Frame:
    """``frame`` with outlier ``case`` (SHAPES) of ``times`` x the frame's mean at ``where`` (its top-left pixel)
    in each of ``layers`` (default: every layer)."""
    rows, cols = SHAPES[case]
    mask = np.zeros((frame.height, frame.width), bool)
    mask[where[0]:where[0] + rows, where[1]:where[1] + cols] = True
    value = min(times * frame_mean(frame), 3e38)
    chosen = frame.layers if layers is None else layers
    new = {name: outlier_layer(layer, mask, value) if name in chosen else layer
           for name, layer in frame.layers.items()}
    return replace(frame, layers=new)


def places(frame: Frame) -> list[tuple[int, int]]:
    """Nine places for an outlier: a quarter, half and three quarters down and across the frame."""
    return [(frame.height * i // 4, frame.width * j // 4) for i in (1, 2, 3) for j in (1, 2, 3)]


def hidden_given_back(clean: Frame, hit: Frame, handled: Frame) -> Frame:
    """``handled`` (what the outlier detector made of ``hit``, ``clean`` with an outlier) with every value the
    detector filled (base and gradients: where ``handled`` differs from ``hit``) set to what ``clean`` holds there.

    An outlier hides what the pixels under it held, and no detector can know it; a method whose output far away
    depends on that content (a large receptive field, a global solve) moves there however the outlier is handled.
    Given back, what is left of a far change is the handling's own: its detection, its fills' reach, the energy's
    footprint (tests/model/test_outliers.py, benchmarks/bench_outliers.py ``--hidden``)."""
    layers = {}
    for name, layer in handled.layers.items():
        planes = []
        for attribute in ("base", "dx", "dy"):
            filled, own, original = (getattr(f.layers[name], attribute) for f in (handled, hit, clean))
            if filled is None or filled is own:
                planes.append(filled)
            else:
                planes.append(np.where(filled != own, original, filled).astype(np.float32))
        layers[name] = Layer(planes[0], planes[1], planes[2], layer.var)
    return replace(handled, layers=layers)
