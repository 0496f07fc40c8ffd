"""Outliers as a gradient-domain renderer writes them, for tests/model/test_outliers.py and
benchmarks/bench_outliers.py.

A firefly is one sample (or a few neighbouring ones: a glint, a caustic) far brighter than the rest. It lands in a
pixel's base; the shift to each neighbour fails, so the forward differences ``dx``/``dy`` carry the jump; and the
pixel's variance of its mean is that of a single sample that large (its excess squared).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gradsep.model.frame import Frame, Layer
from gradsep.model.policy import LUMINANCE

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
