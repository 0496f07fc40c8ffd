"""Lanes: one wavefront lane is one pixel sample. Where in its pixel the sample falls (stratified), which offset
paths it traces (all four, or fewer: :data:`OFFSET_MODES`) and its primary rays -- the base pixel's and the
shifted pixels' through the same sub-pixel position.
"""

from __future__ import annotations

from collections.abc import Sequence

import drjit as dr
import mitsuba as mi

# Pixel offsets of the four offset paths, (dx, dy) with y growing downward: right, left, down, up.
SHIFT_OFFSETS: tuple[tuple[int, int], ...] = ((1, 0), (-1, 0), (0, 1), (0, -1))

# Which offsets a sample traces: "all" four of SHIFT_OFFSETS; "pair": the two of one axis, right and left
# (SHIFT_OFFSETS[0:2]) or down and up ([2:4]); "single": one of the four. The group is chosen per sample
# (offset_group) and its gradient terms count OFFSET_GROUPS[mode] times (the group's inverse probability).
# "alternate": one offset per axis, right or left and down or up, chosen so that neighbouring pixels pair up
# (alternate_offsets): on a given sample pixel x traces right exactly when pixel x+1 traces left, so each pixel
# pair gets both of its MIS techniques on half the samples; every offset is traced with probability 1/2.
OFFSET_MODES: tuple[str, ...] = ("all", "pair", "single", "alternate")
OFFSET_GROUPS: dict[str, int] = {"all": 1, "pair": 2, "single": 4, "alternate": 2}


def stratified_sub_pixel(u: mi.Point2f, sample: mi.UInt32, strata: mi.UInt32) -> mi.Point2f:
    """Jitter the pixel's first ``strata^2`` samples over a ``strata x strata`` grid (sample ``i`` in cell
    ``(i mod strata, i div strata)``); later samples stay uniform. Each sample is uniform within its cell, so the
    pixel's mean is unbiased; coverage of edges (silhouettes, light boundaries) is estimated with far less noise
    than by independent positions, for the primal and -- since base and offset rays share the position -- for the
    gradients. Pixels stay independent of each other (the jitter is the pixel's own random numbers)."""
    cells = strata * strata
    cell = mi.Point2f(mi.Float(sample % strata), mi.Float(sample // strata))
    return dr.select(sample < cells, (cell + u) / mi.Float(strata), u)


def offset_group(pixel: mi.UInt32, sample: mi.UInt32, strata: mi.UInt32, seed: mi.UInt32,
                 groups: int) -> mi.UInt32:
    """Which group of offsets (of ``groups`` equal groups of SHIFT_OFFSETS: 2 axes, or 4 single offsets) sample
    ``sample`` of ``pixel`` traces when a sample traces fewer than all four.

    The pixel's stratified samples (one per cell of its ``strata x strata`` grid) are dealt out along the grid's
    diagonals -- cell (cx, cy) gets ``cx + (groups // 2) cy`` (a checkerboard for two groups) -- later samples in
    turn, and a random offset per pixel and pass (a hash of the pixel and the pass's seed) rotates the groups.
    So every sample traces each group with probability exactly ``1/groups``, whatever its sub-pixel position --
    counting its gradient terms ``groups`` times keeps every gradient estimate unbiased -- and each group's
    samples still spread over the pixel (every row of the grid holds every group)."""
    rotate = mi.sample_tea_32(pixel, seed)[0]
    cell = sample % strata + (groups // 2) * (sample // strata)
    return (dr.select(sample < strata * strata, cell, sample) + rotate) % groups


def alternate_offsets(px: mi.Int32, py: mi.Int32, sample: mi.UInt32, strata: mi.UInt32,
                      seed: mi.UInt32) -> tuple[mi.UInt32, mi.UInt32]:
    """Which offset of each axis sample ``sample`` of pixel (px, py) traces in the "alternate" mode: indices into
    SHIFT_OFFSETS, right (0) or left (1), and down (2) or up (3).

    Pixel x traces right where ``x + c + r`` is even and left where it is odd, with ``c`` the sample's place in
    the pixel's stratified grid (cell (cx, cy) -> cx + cy, a checkerboard, so each direction's samples cover
    every row and column of the grid; later samples: the sample index) and ``r`` a random bit per image row and
    pass (a hash of the row and the pass's seed). So on every sample pixel x traces right exactly when pixel x+1
    traces left -- the pair (x, x+1) gets both of its MIS techniques on the same half of the samples, and the
    weights of the two techniques still sum to 1 -- and, over ``r``, each sample traces each direction with
    probability exactly 1/2 whatever its sub-pixel position: counted twice (OFFSET_GROUPS), every gradient
    estimate stays unbiased. Vertically likewise, with a bit per column."""
    diagonal = dr.select(sample < strata * strata, sample % strata + sample // strata, sample)
    row_bits = mi.sample_tea_32(mi.UInt32(py), seed)[0]
    column_bits = mi.sample_tea_32(mi.UInt32(px), seed)[1]
    horizontal = (mi.UInt32(px) + diagonal + row_bits) & 1
    vertical = (mi.UInt32(py) + diagonal + column_bits) & 1
    return horizontal, vertical + 2


def offsets_by_index(targets: Sequence[mi.UInt32]) -> list[tuple[mi.Int32, mi.Int32]]:
    """Per-lane pixel shifts (dx, dy) of the offsets ``targets`` (indices into SHIFT_OFFSETS)."""
    shifts = []
    for target in targets:
        ox, oy = mi.Int32(SHIFT_OFFSETS[0][0]), mi.Int32(SHIFT_OFFSETS[0][1])
        for i, (cx, cy) in enumerate(SHIFT_OFFSETS[1:], start=1):
            ox = dr.select(target == i, cx, ox)
            oy = dr.select(target == i, cy, oy)
        shifts.append((ox, oy))
    return shifts


def camera_rays(sensor: mi.Sensor, sampler: mi.Sampler, pixel: tuple[mi.Int32, mi.Int32],
                res: tuple[mi.Int32, mi.Int32], sample: mi.UInt32, strata: mi.UInt32,
                shifts: Sequence[tuple[int | mi.Int32, int | mi.Int32]] = SHIFT_OFFSETS,
                ) -> tuple[list[tuple[mi.Ray3f, mi.Spectrum, mi.Bool]], mi.Bool]:
    """Primary rays of the base pixel ``pixel`` (x, y) of an image of ``res`` (width, height) and of the shifted
    pixels (``shifts``; none for a primal-only render), all through the same sub-pixel sample (``sample``-th of
    the pixel, stratified: :func:`stratified_sub_pixel`).

    The shifted pixel index is formed in integers first, so an offset ray and the base ray of the neighbouring
    pixel it stands for are computed bit for bit alike.
    """
    sub_pixel = stratified_sub_pixel(sampler.next_2d(), sample, strata)
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    time = sensor.shutter_open()
    if sensor.shutter_open_time() > 0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    px, py = pixel
    width, height = res
    size = mi.Vector2f(mi.Float(width), mi.Float(height))
    rays = []
    for ox, oy in ((0, 0), *shifts):
        qx, qy = px + ox, py + oy
        inside = (qx >= 0) & (qx < width) & (qy >= 0) & (qy < height)
        pos = (mi.Point2f(mi.Float(qx), mi.Float(qy)) + sub_pixel) / size
        ray, weight = sensor.sample_ray(time, 0.5, pos, aperture, inside)
        rays.append((ray, mi.Spectrum(weight), inside))
    return rays, rays[0][2]
