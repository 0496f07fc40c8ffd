"""model/warp.py: bilinear sampling along motion vectors (the compiled pass and numpy agree, and are bilinear)."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model import warp


@pytest.mark.parametrize("channels", [None, 3])
def test_the_compiled_warp_is_the_numpy_warp_bit_for_bit_and_bilinear(monkeypatch: pytest.MonkeyPatch,
                                                                     channels: int | None) -> None:
    """The sampler's compiled pass (model.kernels.bilinear) and its numpy path give the same bits, and both are
    bilinear interpolation at the positions clamped to the frame (squared weights for a variance)."""
    from scipy.ndimage import map_coordinates

    from gradsep.model import kernels

    rng = np.random.default_rng(5)
    h, w = 23, 31
    shape = (h, w) if channels is None else (h, w, channels)
    image = rng.random(shape).astype(np.float32)
    rows = (rng.random((h, w)) * (h + 4) - 2).astype(np.float32)  # some positions off screen
    cols = (rng.random((h, w)) * (w + 4) - 2).astype(np.float32)
    rows[-1], cols[:, -1] = h - 1, w - 1  # on the last row and column: the lower and right taps repeat them
    rows[0, 0] = np.nan
    sample = warp.Sampler(rows, cols, np.ones((h, w), bool))
    assert not sample.integral and not sample.valid[0, 0] and not sample.valid[rows < 0].any()
    got = {squared: sample(image, squared) for squared in (False, True)}
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    for squared in (False, True):
        np.testing.assert_array_equal(sample(image, squared), got[squared])
    cols[0, 0] = -1.0  # a position with a non-finite coordinate is read at (-1, -1), clamped (and invalid)
    r = np.clip(np.nan_to_num(rows, nan=-1.0), 0, h - 1).astype(np.float64)
    c = np.clip(cols, 0, w - 1).astype(np.float64)
    planes = image.reshape(h, w, -1).astype(np.float64)
    linear = np.stack([map_coordinates(planes[..., k], [r, c], order=1, mode="nearest")
                       for k in range(planes.shape[-1])], -1)
    np.testing.assert_allclose(got[False], linear.reshape(shape), rtol=1e-5, atol=1e-6)
    r0, c0 = np.floor(r).astype(int), np.floor(c).astype(int)
    r1, c1, fr, fc = np.minimum(r0 + 1, h - 1), np.minimum(c0 + 1, w - 1), r - r0, c - c0
    squares = sum((weight**2)[..., None] * planes[rr, cc] for rr, cc, weight in
                  ((r0, c0, (1 - fr) * (1 - fc)), (r0, c1, (1 - fr) * fc), (r1, c0, fr * (1 - fc)), (r1, c1, fr * fc)))
    np.testing.assert_allclose(got[True], squares.reshape(shape), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("scale", [0.8, 1.0, 1.25])
def test_nearest_takes_each_pixel_whole_and_once(scale: float) -> None:
    """Rounded positions: every valid pixel reads one neighbour pixel whole (integral, no mixing), within half a
    pixel of its position on each axis; where a zoom puts several of frame t's pixels on one (scale < 1) the nearest
    keeps it and no neighbour pixel is read twice; a whole-pixel warp is its own nearest."""
    h, w = 17, 19
    rows, cols = warp.grid(h, w)
    rows, cols = rows * scale + 0.3, cols * scale - 0.45
    bilinear = warp.Sampler(rows, cols, np.ones((h, w), bool))
    near = bilinear.nearest()
    assert near.integral and near.valid.any()
    assert not (near.valid & ~bilinear.valid).any()
    image = np.arange(h * w, dtype=np.float32).reshape(h, w)
    read = near(image)[near.valid].astype(int)
    assert len(set(read.tolist())) == read.size  # each neighbour pixel once
    r, c = np.divmod(read, w)
    assert np.abs(r - rows[near.valid]).max() <= 0.5 and np.abs(c - cols[near.valid]).max() <= 0.5
    kept = near.valid.sum() / bilinear.valid.sum()
    assert kept == 1.0 if scale >= 1.0 else kept < 1.0
    whole = warp.Sampler(*warp.grid(h, w), np.ones((h, w), bool))
    assert whole.nearest() is whole
