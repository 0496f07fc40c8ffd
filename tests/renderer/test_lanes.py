"""renderer/lanes.py: where a lane's sample falls in its pixel (stratified) and which offsets it traces when it
traces fewer than four (the groups of "pair"/"single", the neighbour pairing of "alternate"). Their effect on
the renders (unbiased gradients, the primal unchanged) is tested with the integrator (tests/renderer/test_gpt.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from gradsep.renderer.lanes import alternate_offsets, offset_group, stratified_sub_pixel  # noqa: E402
from gradsep.renderer.variant import select_variant  # noqa: E402

pytestmark = pytest.mark.render


@pytest.mark.parametrize("groups", [2, 4])
def test_offset_groups_are_balanced_and_spread(groups):
    """Each sample traces each group with probability 1/groups (over pixels and passes), and within a pixel the
    stratified cells are dealt out evenly, every row of the grid holding every group."""
    select_variant()
    strata, spp, pixels = 4, 20, 4096
    pixel = np.repeat(np.arange(pixels), spp)
    sample = np.tile(np.arange(spp), pixels)
    group = np.array(offset_group(mi.UInt32(pixel), mi.UInt32(sample), mi.UInt32(strata), mi.UInt32(12345),
                                  groups)).reshape(pixels, spp)
    for s in range(spp):
        counts = np.bincount(group[:, s], minlength=groups) / pixels
        assert np.all(np.abs(counts - 1 / groups) < 5 * np.sqrt(1 / pixels)), (s, counts)
    grid = group[:, :strata * strata].reshape(pixels, strata, strata)  # [pixel, row, column]
    for g in range(groups):
        assert np.all((grid == g).sum(axis=(1, 2)) == strata * strata // groups)
        assert np.all((grid == g).any(axis=2))


def test_alternate_offsets_pair_neighbours_and_are_balanced():
    """The "alternate" mode: on every sample, pixel x traces right exactly when pixel x+1 traces left (and y
    down exactly when y+1 traces up), so each pixel pair gets both MIS techniques on the same samples; over
    rows/columns and passes each sample traces each direction with probability 1/2; within a pixel each
    direction's stratified samples cover every row and column of the grid."""
    select_variant()
    strata, spp, size = 4, 20, 64
    y, x, s = np.meshgrid(np.arange(size), np.arange(size), np.arange(spp), indexing="ij")
    h, v = (np.array(a).reshape(size, size, spp) for a in alternate_offsets(
        mi.Int32(x.ravel()), mi.Int32(y.ravel()), mi.UInt32(s.ravel()), mi.UInt32(strata), mi.UInt32(777)))
    assert set(np.unique(h)) == {0, 1} and set(np.unique(v)) == {2, 3}  # SHIFT_OFFSETS: right/left, down/up
    np.testing.assert_array_equal(h[:, :-1] == 0, h[:, 1:] == 1)  # right at x  <=>  left at x+1
    np.testing.assert_array_equal(v[:-1, :] == 2, v[1:, :] == 3)  # down at y  <=>  up at y+1
    for sample in range(spp):  # the random bit per row (column) and pass makes each direction equally likely
        for axis_choice in (h[:, 0, sample] == 0, v[0, :, sample] == 2):
            assert abs(axis_choice.mean() - 0.5) < 5 * np.sqrt(0.25 / size), sample
    grid = h[..., :strata * strata].reshape(size, size, strata, strata)  # [y, x, grid row, grid column]
    for direction in (0, 1):
        assert np.all((grid == direction).sum(axis=(2, 3)) == strata * strata // 2)
        assert np.all((grid == direction).any(axis=3)) and np.all((grid == direction).any(axis=2))


@pytest.mark.parametrize("spp", [1, 7, 16, 20])
def test_sub_pixel_positions_are_stratified(spp):
    """The pixel's first floor(sqrt(spp))^2 samples fall one per cell of a jittered grid, the rest anywhere in
    the pixel; every position stays inside the pixel."""
    select_variant()
    n = math.isqrt(spp)
    rng = np.random.default_rng(spp)
    u = rng.uniform(0, 1, (2, spp))
    sample = np.arange(spp)
    pos = np.array(stratified_sub_pixel(mi.Point2f(u[0], u[1]), mi.UInt32(sample), mi.UInt32(n)))
    assert np.all((pos >= 0) & (pos < 1))
    cells = np.floor(pos[:, :n * n] * n).astype(int)
    assert len({(int(x), int(y)) for x, y in cells.T}) == n * n
    np.testing.assert_allclose(pos[:, n * n:], u[:, n * n:])
