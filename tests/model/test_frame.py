"""The frame types and the contract's channel names (model/frame.py)."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model.frame import (
    FEATURE_CHANNELS,
    Layer,
    forward_differences,
    frame_channels,
    layer_channels,
)


def test_layer_channels_are_nine_in_canonical_order() -> None:
    assert layer_channels("direct") == (
        "direct.R", "direct.G", "direct.B", "direct.dx.R", "direct.dx.G", "direct.dx.B",
        "direct.dy.R", "direct.dy.G", "direct.dy.B")
    with pytest.raises(ValueError):
        layer_channels("specular")


def test_forward_differences_follow_the_contract() -> None:
    img = np.arange(12, dtype=np.float64).reshape(3, 4)
    dx, dy = forward_differences(img)
    assert np.all(dx[:, :-1] == 1) and np.all(dx[:, -1] == 0)
    assert np.all(dy[:-1, :] == 4) and np.all(dy[-1, :] == 0)


def test_frame_channels_lists_layers_then_features() -> None:
    names = frame_channels(["indirect"])
    assert names[:9] == layer_channels("indirect") and names[9:] == FEATURE_CHANNELS


def test_summed_layers_bound_their_variance_from_above() -> None:
    a = Layer(np.zeros((2, 2, 3), np.float32), var=np.full((2, 2), 4.0, np.float32))
    b = Layer(np.zeros((2, 2, 3), np.float32), var=np.full((2, 2), 9.0, np.float32))
    assert np.all((a + b).var == 25.0)  # (2 + 3)²: the layers of one sample may be correlated
    assert (a + Layer(np.zeros((2, 2, 3), np.float32))).var is None
