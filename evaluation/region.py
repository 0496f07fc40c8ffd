"""Region passes: extra reference samples where the reference floor lives.

A reference's floor is rarely spread evenly over the frame: caustics, small bright emitters seen through glossy
bounces and other rare paths put most of it into part of the image (on a held-out scene of the evaluation, a
quarter of the pixels held most of it). Raising the whole frame's spp pays for every pixel to shrink that part;
rendering extra passes over one rectangle around it buys the same floor for a fraction of the samples.

The region is one rectangle, chosen from a *pilot*: :data:`PILOT_PASSES` full-frame passes with seeds of their
own, used for nothing else. Choosing it from the two references' own samples would make the number of samples a
pixel gets depend on that pixel's noise (more samples where a firefly happened to land), which biases the mean
and breaks the independence that the product estimator (model.metrics.relmse_unbiased) rests on; a pilot that
neither reference contains keeps every pixel of both references an unbiased mean of independent samples, with a
per-pixel sample count fixed before any of them is drawn.

From the pilot, each :data:`TILE` × :data:`TILE` tile's share of the floor is estimated (the spread of the pilot
passes over the squared pilot mean, as model.metrics.reference_floor normalises it). The rectangle is the one
that reaches a :data:`DESIGN_REDUCTION`-fold smaller floor with the fewest extra samples (area × extra spp); where
the floor is spread evenly that is the whole frame, and region passes are then just more passes. The amount of
region passes is decided later, against the floor the evaluation needs (evaluation/convergence.py).

A region pass renders the rectangle alone (Mitsuba's film crop) with the reference sampler and ``path`` at the
scene's depth and at depth 2, exactly like a full pass (renderer.reference.render_loaded), so with the box pixel
filter every pixel inside it is the same estimator as in a full pass.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["DESIGN_REDUCTION", "PILOT_PASSES", "TILE", "Region", "choose_region", "pilot_floor_map",
           "render_region"]

TILE = 16  # pixels per side of the tiles the rectangle is built from
PILOT_PASSES = 8  # full-frame passes at the starting spp, seeds of their own; used only to place the region
# The floor reduction the rectangle is chosen for, fixed so that the region (and its cache entries) does not
# depend on the target. On the scene measured (docs/evaluation.md, "Region passes") a rectangle chosen for this
# reduction cost close to the cheapest for every smaller reduction needed and still reached larger ones cheaply;
# one chosen for a smaller reduction leaves too little of the floor inside to go much past it.
DESIGN_REDUCTION = 3.0


@dataclass(frozen=True)
class Region:
    """A rectangle of the frame in pixels: columns ``x`` .. ``x + width``, rows ``y`` .. ``y + height``."""

    x: int
    y: int
    width: int
    height: int

    @property
    def slices(self) -> tuple[slice, slice]:
        """(rows, columns) of the rectangle, to index an (H, W, ...) image."""
        return slice(self.y, self.y + self.height), slice(self.x, self.x + self.width)

    def fraction(self, width: int, height: int) -> float:
        """The rectangle's share of a ``width`` × ``height`` frame's pixels."""
        return self.width * self.height / (width * height)

    def describe(self) -> str:
        return f"{self.width}x{self.height} at ({self.x}, {self.y})"

    def as_list(self) -> list[int]:
        return [self.x, self.y, self.width, self.height]


def pilot_floor_map(passes: Sequence[np.ndarray], epsilon: float | None = None) -> np.ndarray:
    """Per pixel, the floor one pass would have: the passes' sample variance (mean over colour channels) over
    the squared pilot mean + ε, as model.metrics.reference_floor normalises a pixel. (H, W) float64."""
    from gradsep.model.metrics import RELMSE_EPSILON

    if len(passes) < 2:
        raise ValueError(f"a pilot needs at least 2 passes to estimate a variance, got {len(passes)}")
    stack = np.stack([np.asarray(p, np.float64) for p in passes])
    mean = stack.mean(axis=0)
    variance = stack.var(axis=0, ddof=1)
    eps = RELMSE_EPSILON if epsilon is None else epsilon
    per_pixel = variance / (mean * mean + eps)
    return per_pixel.mean(axis=-1) if per_pixel.ndim == 3 else per_pixel


def _tile_sums(floor_map: np.ndarray, tile: int) -> np.ndarray:
    """Sum of ``floor_map`` over each ``tile`` × ``tile`` tile (the last row/column of tiles may be partial)."""
    h, w = floor_map.shape
    ty, tx = -(-h // tile), -(-w // tile)
    padded = np.zeros((ty * tile, tx * tile))
    padded[:h, :w] = floor_map
    return padded.reshape(ty, tile, tx, tile).sum(axis=(1, 3))


def choose_region(floor_map: np.ndarray, *, tile: int = TILE, reduction: float = DESIGN_REDUCTION) -> Region:
    """The tile-aligned rectangle that brings the floor of ``floor_map`` (H, W; per-pixel contributions) down
    ``reduction``-fold with the fewest extra samples, counted as pixels × extra spp.

    With F the whole floor, S a rectangle's share and A its area, multiplying the rectangle's spp by f removes
    S (1 - 1/f) of F; removing D = F (1 - 1/reduction) takes f - 1 = D / (S - D), i.e. A D / (S - D) extra
    pixel-samples (per unit of the current spp). Only rectangles with S > D can; the whole frame always can.
    An all-zero or non-finite map (nothing to place) gives the whole frame."""
    if not reduction > 1.0:
        raise ValueError(f"reduction must be > 1, got {reduction}")
    h, w = floor_map.shape
    whole = Region(0, 0, w, h)
    values = np.where(np.isfinite(floor_map), floor_map, 0.0)
    total = float(values.sum())
    if not total > 0:
        return whole
    sums = _tile_sums(values, tile)
    ty, tx = sums.shape
    need = total * (1.0 - 1.0 / reduction)
    prefix = np.zeros((ty + 1, tx + 1))
    prefix[1:, 1:] = sums.cumsum(0).cumsum(1)
    # Pixel counts per tile span (partial tiles at the right and bottom edges count their real pixels).
    col_edges = np.minimum(np.arange(tx + 1) * tile, w)
    row_edges = np.minimum(np.arange(ty + 1) * tile, h)
    x0, x1 = np.triu_indices(tx + 1, k=1)  # every column span [x0, x1) in tiles
    widths = col_edges[x1] - col_edges[x0]
    best = (float(w * h) * need / (total - need), whole)
    for y0 in range(ty):
        for y1 in range(y0 + 1, ty + 1):
            strip = prefix[y1] - prefix[y0]  # (tx + 1,) cumulative sums of this row span
            share = strip[x1] - strip[x0]
            area = widths * (row_edges[y1] - row_edges[y0])
            with np.errstate(divide="ignore", invalid="ignore"):
                cost = np.where(share > need, area * need / (share - need), np.inf)
            i = int(np.argmin(cost))
            if cost[i] < best[0]:
                best = (float(cost[i]), Region(int(col_edges[x0[i]]), int(row_edges[y0]), int(widths[i]),
                                               int(row_edges[y1] - row_edges[y0])))
    return best[1]


def render_region(loaded: Any, region: Region, *, spp: int, seed: int, sampler: str) -> Any:
    """One region pass: ``path`` at the scene's depth and at depth 2 over ``region`` only, same seed, as
    renderer.reference.render_loaded renders a full pass; a renderer.reference.Reference of the crop's size."""
    import mitsuba as mi

    from gradsep.renderer.reference import (
        _check_split,
        _mean_reference,
        check_sampler,
        default_tile_spp,
        pass_seed,
        plan_passes,
        sampler_sensor,
    )

    check_sampler(sampler)
    if not (0 <= region.x and 0 <= region.y and region.width > 0 and region.height > 0
            and region.x + region.width <= loaded.width and region.y + region.height <= loaded.height):
        raise ValueError(f"region {region.describe()} is not inside the {loaded.width}x{loaded.height} frame")
    depth = loaded.max_depth
    split = depth == -1 or depth > 2  # as render_loaded: at depth <= 2 everything is direct light
    total_it = mi.load_dict({"type": "path", "max_depth": depth})
    direct_it = mi.load_dict({"type": "path", "max_depth": 2}) if split else None
    sensor = sampler_sensor(loaded, sampler)
    params = mi.traverse(sensor)
    params["film.crop_offset"] = mi.ScalarPoint2u(region.x, region.y)
    params["film.crop_size"] = mi.ScalarVector2u(region.width, region.height)
    params.update()

    def render(integrator: Any, k: int, s: int) -> np.ndarray:
        img = np.asarray(mi.render(loaded.scene, sensor=sensor, integrator=integrator, spp=k, seed=s),
                         dtype=np.float64)
        return img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, axis=-1)

    # The sample plan of a full pass of this frame (same tile, so the same counts the sampler renders exactly:
    # multijitter would turn 512 into 528), so every region pixel has a full pass's variance and weight.
    tile = default_tile_spp(spp, loaded.width, loaded.height, sampler)
    plan = plan_passes(spp, tile, sampler)
    shape = (region.height, region.width, 3)
    total, direct = np.zeros(shape), (np.zeros(shape) if direct_it is not None else None)
    start = time.perf_counter()
    for i, k in enumerate(plan):
        s = pass_seed(seed, i)
        part = render(total_it, k, s)
        total += k * part
        if direct is not None:
            part_direct = render(direct_it, k, s)
            _check_split(part, part_direct, i)
            direct += k * part_direct
    seconds = time.perf_counter() - start
    total /= spp
    if direct is not None:
        direct /= spp
    meta = loaded.scene_metadata()
    meta.update({"gradsep.kind": "reference-region", "gradsep.integrator": "path", "gradsep.spp": str(spp),
                 "gradsep.seed": str(seed), "gradsep.max_depth": str(depth), "gradsep.sampler": sampler,
                 "gradsep.tile_spp": str(tile), "gradsep.region": ",".join(str(v) for v in region.as_list()),
                 "gradsep.size": f"{region.width}x{region.height}", "gradsep.render_seconds": f"{seconds:.3f}",
                 "gradsep.variant": str(mi.variant())})
    return _mean_reference(total, direct, meta)
