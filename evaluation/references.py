"""Two independent references per scene, grown (cached, additively) until their noise no longer matters.

Each reference is the mean of independent *passes* of Mitsuba's ``path`` (renderer.reference, split exactly
into direct and indirect, drawn with the stratified REFERENCE_SAMPLER), every pass at the starting spp with its
own seed: pass 0, 2, 4, ... belong to the first reference, 1, 3, 5, ... to the second. A reference at k times
the starting spp is the mean of its first k passes, so raising the reference spp re-uses every pass already
rendered (each pass is one cache entry).

The *floor* is what a perfect method would score against one reference (model.metrics.reference_floor); the
run doubles both references until the floor is under FLOOR_FRACTION of the scene's smallest ranked RelMSE or
the cap is reached. Where the full passes stop (the cap or the time budget) with the floor still too high,
*region passes* add samples over one rectangle placed from a pilot (evaluation/region.py): pass 0, 2, ... of
the region belong to the first reference, 1, 3, ... to the second, and a pixel inside the rectangle is the mean
of all its samples. Only then, still short, does the report warn. Error figures use the product estimator over the two
(model.metrics.relmse_unbiased), whose expectation does not depend on the reference spp; SSIM, PSNR and FLIP
are scored against the mean of the two (a reference at twice the spp), and so keep a small bias.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.evaluation.cache import EvalCache, key_hash, sources_sha256
from gradsep.evaluation.region import PILOT_PASSES, Region, choose_region, pilot_floor_map
from gradsep.renderer.reference import DEFAULT_SAMPLER

__all__ = ["REFERENCE_SAMPLER", "ReferencePair", "ReferenceSource", "next_reference_spp"]

# Mitsuba's sampler for every reference pass: the stratified one chosen by floor per CPU-second on held-out
# scenes (docs/evaluation.md, "Reference sampler"); part of every pass's cache key.
REFERENCE_SAMPLER = DEFAULT_SAMPLER


@dataclass
class ReferencePair:
    """Two independent references at ``spp`` each (plus ``region_spp`` more inside ``region``, when set): per
    layer name (total, direct[, indirect]) an image pair."""

    spp: int
    first: dict[str, np.ndarray]
    second: dict[str, np.ndarray]
    tag: str  # hash of everything that determines both
    seconds: float  # render seconds of all passes used (as recorded when they were rendered)
    metadata: dict[str, str] = field(default_factory=dict)
    region: Region | None = None  # where region passes were added (evaluation/region.py)
    region_spp: int = 0  # extra spp of each reference inside ``region``

    def mean(self, layer: str = "total") -> np.ndarray:
        """The two references averaged: one reference at twice the spp (for SSIM, PSNR, FLIP, crops)."""
        return (0.5 * (self.first[layer].astype(np.float64) + self.second[layer])).astype(np.float32)

    def floor(self, layer: str = "total") -> float:
        from gradsep.model.metrics import reference_floor

        return reference_floor(self.first[layer], self.second[layer])

    def floor_split(self, region: Region) -> tuple[float, float]:
        """The total floor split into its parts (outside, inside) ``region``: they add up to :meth:`floor`."""
        from gradsep.model.metrics import reference_floor

        rows, cols = region.slices
        first, second = self.first["total"], self.second["total"]
        height, width = first.shape[:2]
        # The floor is a mean over pixels: the rectangle's mean weighted by its share of the frame.
        inside = reference_floor(first[rows, cols], second[rows, cols]) * region.fraction(width, height)
        return self.floor() - inside, inside


# Seed streams of a scene's reference passes (evaluation/region.py explains the pilot and the region).
SEED_STREAMS = {"pass": 1, "pilot": 2, "region": 3}
# Code that determines a region pass's pixels beyond the full passes' (part of its cache key).
REGION_SOURCES = ("evaluation/region.py",)

# Raise the references to this much more than the floor's 1/spp fall predicts: the floor is itself an estimate
# (heavy-tailed pixels make it noisy) and falls a little slower than 1/spp where paths are rare (the measured
# slopes: docs/evaluation.md, "Reference sampler").
RAISE_MARGIN = 1.25


def next_reference_spp(spp: int, floor: float, smallest: float, fraction: float, cap: int,
                       step: int | None = None) -> int | None:
    """The reference spp predicted to bring ``floor`` under ``fraction`` × ``smallest`` (the floor falls as
    1/spp), at most ``cap``; None when ``spp`` already suffices or is at the cap. A non-positive ``smallest``
    (an error the references cannot resolve) asks for the cap.

    ``step`` None: a power-of-two multiple of ``spp``. ``step`` = the pass spp: the smallest multiple of it
    at least :data:`RAISE_MARGIN` × the prediction (so 22 passes are rendered, not the 32 of the next power of
    two), at least one pass more than now."""
    if spp >= cap:
        return None
    if smallest > 0 and floor <= fraction * smallest:
        return None
    needed = math.inf if smallest <= 0 else spp * floor / (fraction * smallest)
    if step is not None:
        if not math.isfinite(needed):
            return cap
        passes = max(spp // step + 1, math.ceil(RAISE_MARGIN * needed / step))
        return min(cap, passes * step)
    factor = 2
    while spp * factor < needed and spp * factor < cap:
        factor *= 2
    return min(cap, spp * factor)


class ReferenceSource:
    """The reference passes of one scene, from the cache or rendered: full passes (``render_pass(spp, seed)``),
    and, where the floor needs them, the pilot and the region passes (``render_region(region, spp, seed)``)."""

    def __init__(self, cache: EvalCache, scene_name: str, key: dict[str, Any], base_spp: int,
                 render_pass: Callable[[int, int], Any], log: Callable[[str], None],
                 render_region: Callable[[Region, int, int], Any] | None = None) -> None:
        self.cache = cache
        self.scene_name = scene_name
        self.key = key  # scene identity, size, depth, code, mitsuba, base seed
        self.base_spp = base_spp
        self.render_pass = render_pass  # (spp, seed) -> renderer.reference.Reference
        self.log = log
        self.rendered = 0  # passes of any kind rendered (not cached) by this source
        self.rendered_seconds = 0.0  # their render time
        self._passes: dict[int, tuple[dict[str, np.ndarray], float]] = {}
        self._region: Region | None = None
        self._region_passes: dict[int, tuple[dict[str, np.ndarray], float]] = {}
        self.region_code = sources_sha256(REGION_SOURCES)
        self.render_region = render_region  # (region, spp, seed) -> renderer.reference.Reference of the crop

    def ensure(self, index: int, stream: str = "pass") -> None:
        """Pass ``index`` of ``stream`` (``pass`` or ``pilot``) is in the cache afterwards (rendered when it was
        not): a farm shard's unit of work."""
        if stream not in ("pass", "pilot"):
            raise ValueError(f"a farm renders full passes and pilot passes, not {stream!r} ones")
        self._pass(index, stream)

    def _entry(self, index: int, stream: str = "pass") -> tuple[int, str, Any]:
        """(seed, key hash, cache path) of pass ``index`` of a seed ``stream``: ``pass`` (the references' full
        passes), ``pilot`` (full passes that only place the region) or ``region`` (crops of the region)."""
        seed = int(np.random.SeedSequence([int(self.key["seed"]), SEED_STREAMS[stream], index])
                   .generate_state(1, np.uint32)[0])
        # For ``pass`` this is the key (and name) full passes had before the other streams existed: they still count.
        key = {**self.key, "kind": f"reference-{stream}", "spp": self.base_spp, "pass": index, "pass_seed": seed}
        if stream == "region":
            assert self._region is not None
            key.update(region=self._region.as_list(), region_code=self.region_code)
        name = f"spp{self.base_spp}-{stream}{index}"
        path = self.cache.entry("references", self.scene_name, name, key, ".exr")
        return seed, key_hash(key), path

    def cached(self, index: int) -> bool:
        """Whether pass ``index`` needs no rendering: loaded already, or its cache file exists (the file name
        carries the hash of its key; a corrupt one is re-rendered when loaded)."""
        return index in self._passes or self._entry(index)[2].is_file()

    def passes_to_render(self, spp: int) -> int:
        """How many passes both references at ``spp`` each still need rendered (not in the cache)."""
        return sum(not self.cached(i) for i in range(2 * (spp // self.base_spp)))

    def _pass(self, index: int, stream: str = "pass") -> tuple[dict[str, np.ndarray], float]:
        memo = self._region_passes if stream == "region" else self._passes if stream == "pass" else None
        if memo is not None and index in memo:
            return memo[index]
        from gradsep.model.errors import FrameError
        from gradsep.renderer.reference import load_reference, write_reference

        seed, tag, path = self._entry(index, stream)
        ref = None
        if path.is_file():
            try:
                ref = load_reference(str(path))
                if ref.metadata.get("gradsep.eval_key") != tag:
                    ref = None
            except FrameError:
                ref = None
            if ref is None:
                self.log(f"cache entry {path} unreadable; re-rendering the reference pass")
        if ref is None:
            if stream == "region":
                assert self._region is not None and self.render_region is not None
                ref = self.render_region(self._region, self.base_spp, seed)
            else:
                ref = self.render_pass(self.base_spp, seed)
            ref.metadata["gradsep.eval_key"] = tag
            path.parent.mkdir(parents=True, exist_ok=True)
            write_reference(path, ref)
            self.rendered += 1
            took = float(ref.metadata.get("gradsep.render_seconds", "nan"))
            self.rendered_seconds += took if math.isfinite(took) else 0.0
        images = ref.images()
        seconds = float(ref.metadata.get("gradsep.render_seconds", "nan"))
        if memo is not None:
            memo[index] = (images, seconds)
        return images, seconds

    # ------------------------------------------------------------------------------------------ region passes

    def region(self) -> Region:
        """The rectangle region passes cover, placed from the pilot passes (rendered when not cached; see
        evaluation/region.py); the whole frame when the floor is spread evenly."""
        if self._region is None:
            pilots = [self._pass(i, "pilot")[0]["total"] for i in range(PILOT_PASSES)]
            self._region = choose_region(pilot_floor_map(pilots))
        return self._region

    def pilot_passes_to_render(self) -> int:
        """How many pilot passes :meth:`region` would still render (0 once it has been placed)."""
        if self._region is not None:
            return 0
        return sum(not self._entry(i, "pilot")[2].is_file() for i in range(PILOT_PASSES))

    def region_cached(self, count: int) -> list[bool]:
        """Whether each of region passes 0 .. 2 ``count`` - 1 (``count`` per reference) needs no rendering."""
        self.region()
        return [i in self._region_passes or self._entry(i, "region")[2].is_file() for i in range(2 * count)]

    def pair(self, spp: int, region_passes: int = 0) -> ReferencePair:
        """Both references at ``spp`` (a multiple of the starting spp) each, plus ``region_passes`` region passes
        each inside :meth:`region`: there a pixel is the mean of all its samples, full and region passes alike
        (every one an independent, unbiased sample of the same pixel estimator)."""
        if spp % self.base_spp:
            raise ValueError(f"reference spp {spp} is not a multiple of the starting spp {self.base_spp}")
        if region_passes < 0:
            raise ValueError(f"region passes must be >= 0, got {region_passes}")
        count = spp // self.base_spp
        sums: list[dict[str, np.ndarray]] = [{}, {}]
        seconds = 0.0
        for which in (0, 1):
            for k in range(count):
                images, took = self._pass(2 * k + which)
                seconds += took if math.isfinite(took) else 0.0
                for name, image in images.items():
                    acc = sums[which].setdefault(name, np.zeros(image.shape, np.float64))
                    acc += image
        tag_key: dict[str, Any] = {**self.key, "kind": "reference-pair", "base_spp": self.base_spp, "spp": spp}
        region = self.region() if region_passes else None
        counts = np.full(next(iter(sums[0].values())).shape[:2] + (1,), float(count))
        if region is not None:
            rows, cols = region.slices
            counts[rows, cols] += region_passes
            for which in (0, 1):
                for k in range(region_passes):
                    images, took = self._pass(2 * k + which, "region")
                    seconds += took if math.isfinite(took) else 0.0
                    for name, image in images.items():
                        sums[which][name][rows, cols] += image
            tag_key.update(region=region.as_list(), region_passes=region_passes, region_code=self.region_code)
        first, second = ({n: (a / counts).astype(np.float32) for n, a in s.items()} for s in sums)
        metadata = {"gradsep.spp": str(spp)}
        if region is not None:
            metadata.update({"gradsep.region": region.describe(),
                             "gradsep.region_spp": str(region_passes * self.base_spp)})
        return ReferencePair(spp, first, second, key_hash(tag_key), seconds, metadata, region,
                             region_passes * self.base_spp)


def within_time(spp: int, wanted: int, seconds: float, budget: float, step: int | None = None,
                 to_render: Callable[[int], int] | None = None) -> int | None:
    """The largest spp up to ``wanted`` whose new rendering (both references) is predicted to fit ``budget``
    seconds: a power-of-two multiple of ``spp`` (``step`` None) or a multiple of ``step`` (the pass spp); None
    when nothing above ``spp`` fits. Render time is predicted linearly in spp from the ``seconds`` the current
    ``spp`` took. With ``to_render`` (spp -> passes of that level not in the cache yet, ``step`` given), only
    those count: passes already cached (a farm's shards, an earlier run) cost this run nothing, whatever time
    they were recorded with; without it every pass above the current ``spp`` is new."""
    if not (seconds > 0 and math.isfinite(seconds)):
        return wanted  # no timing recorded: the spp cap alone decides
    if step is not None:
        per_pass = seconds / (2 * spp / step)  # both references: two passes per step
        level = wanted // step * step
        while level > spp:
            new = to_render(level) if to_render is not None else 2 * (level - spp) // step
            if new * per_pass <= budget:
                return level
            level -= step
        return None
    best = None
    level = spp * 2
    while level <= wanted and seconds * (level - spp) / spp <= budget:
        best = level
        level *= 2
    return best
