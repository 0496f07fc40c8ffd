"""The benchmarks' synthetic frame (gradsep.model.synthetic): a valid, seeded separated frame with gradients."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model.exr_read import read_frame
from gradsep.model.synthetic import synthetic_frame


def test_the_frame_is_a_valid_separated_frame_with_gradients_and_features() -> None:
    frame = read_frame(synthetic_frame(24, 32, seed=3))
    assert list(frame.layers) == ["direct", "indirect"]
    assert (frame.height, frame.width) == (24, 32) and frame.has_gradients and frame.features is not None
    for layer in frame.layers.values():
        assert np.all(layer.base >= 0) and np.all(np.isfinite(layer.base))
        assert np.all(layer.dx[:, -1] == 0) and np.all(layer.dy[-1] == 0)
        assert layer.var is not None and np.all(layer.var >= 0) and np.all(np.isfinite(layer.var))
    # the indirect layer is the noisier one (relative spread of base against its local mean)
    spread = {name: float(np.std(np.diff(layer.base, axis=1)) / np.mean(layer.base))
              for name, layer in frame.layers.items()}
    assert spread["indirect"] > spread["direct"]


def test_the_same_seed_gives_the_same_bytes_and_another_seed_other_noise() -> None:
    assert synthetic_frame(8, 8, seed=1) == synthetic_frame(8, 8, seed=1)
    a, b = (read_frame(synthetic_frame(8, 8, seed=s)).layers["direct"].base for s in (1, 2))
    assert not np.array_equal(a, b)


def test_a_lossless_compression_round_trips_and_a_degenerate_size_is_refused() -> None:
    zip_frame = read_frame(synthetic_frame(8, 10, seed=5))
    raw = read_frame(synthetic_frame(8, 10, seed=5, compression="NO_COMPRESSION"))
    np.testing.assert_array_equal(zip_frame.layers["indirect"].dx, raw.layers["indirect"].dx)
    with pytest.raises(ValueError, match="2x2"):
        synthetic_frame(1, 8)
