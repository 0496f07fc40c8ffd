"""Two independent references per scene, grown (cached, additively) until their noise no longer matters.

Each reference is the mean of independent *passes* of Mitsuba's ``path`` (renderer.reference, split exactly
into direct and indirect, drawn with the stratified REFERENCE_SAMPLER), every pass at the starting spp with its
own seed: pass 0, 2, 4, ... belong to the first reference, 1, 3, 5, ... to the second. A reference at k times
the starting spp is the mean of its first k passes, so raising the reference spp re-uses every pass already
rendered (each pass is one cache entry).

The *floor* is what a perfect method would score against one reference (model.metrics.reference_floor); the
run doubles both references until the floor is under FLOOR_FRACTION of the scene's smallest ranked RelMSE or
the cap is reached (then the report warns). Error figures use the product estimator over the two
(model.metrics.relmse_unbiased), whose expectation does not depend on the reference spp; SSIM, PSNR and FLIP
are scored against the mean of the two (a reference at twice the spp), and so keep a small bias.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from evaluation.cache import EvalCache, key_hash
from model.policy import SEPARATED_LAYERS
from renderer.reference import DEFAULT_SAMPLER

__all__ = ["REFERENCE_SAMPLER", "ReferencePair", "ReferenceSource", "next_reference_spp"]

LAYER_NAMES = ("total", *SEPARATED_LAYERS)
# Mitsuba's sampler for every reference pass: the stratified one chosen by floor per CPU-second on held-out
# scenes (docs/evaluation.md, "Reference sampler"); part of every pass's cache key.
REFERENCE_SAMPLER = DEFAULT_SAMPLER


@dataclass
class ReferencePair:
    """Two independent references at ``spp`` each: per layer name (total, direct[, indirect]) an image pair."""

    spp: int
    first: dict[str, np.ndarray]
    second: dict[str, np.ndarray]
    tag: str  # hash of everything that determines both
    seconds: float  # render seconds of all passes used (as recorded when they were rendered)
    metadata: dict[str, str] = field(default_factory=dict)

    def mean(self, layer: str = "total") -> np.ndarray:
        """The two references averaged: one reference at twice the spp (for SSIM, PSNR, FLIP, crops)."""
        return (0.5 * (self.first[layer].astype(np.float64) + self.second[layer])).astype(np.float32)

    def floor(self, layer: str = "total") -> float:
        from model.metrics import reference_floor

        return reference_floor(self.first[layer], self.second[layer])


# Raise the references to this much more than the floor's 1/spp fall predicts: the floor is itself an estimate
# (heavy-tailed pixels make it noisy) and falls a little slower than 1/spp where paths are rare (measured slopes
# -0.9 to -1.0 on cbox, teapot, procedural:90001; docs/evaluation.md, "Reference sampler").
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
    """The reference passes of one scene, from the cache or rendered (``render_pass(seed) -> Reference``)."""

    def __init__(self, cache: EvalCache, scene_name: str, key: dict[str, Any], base_spp: int,
                 render_pass: Callable[[int, int], Any], log: Callable[[str], None]) -> None:
        self.cache = cache
        self.scene_name = scene_name
        self.key = key  # scene identity, size, depth, code, mitsuba, base seed
        self.base_spp = base_spp
        self.render_pass = render_pass  # (spp, seed) -> renderer.reference.Reference
        self.log = log
        self.rendered = 0
        self._passes: dict[int, tuple[dict[str, np.ndarray], float]] = {}

    def ensure(self, index: int) -> None:
        """Pass ``index`` is in the cache afterwards (rendered when it was not): a farm shard's unit of work."""
        self._pass(index)

    def _entry(self, index: int) -> tuple[int, str, Any]:
        """(seed, key hash, cache path) of pass ``index``."""
        seed = int(np.random.SeedSequence([int(self.key["seed"]), 1, index]).generate_state(1, np.uint32)[0])
        key = {**self.key, "kind": "reference-pass", "spp": self.base_spp, "pass": index, "pass_seed": seed}
        path = self.cache.entry("references", self.scene_name, f"spp{self.base_spp}-pass{index}", key, ".exr")
        return seed, key_hash(key), path

    def cached(self, index: int) -> bool:
        """Whether pass ``index`` needs no rendering: loaded already, or its cache file exists (the file name
        carries the hash of its key; a corrupt one is re-rendered when loaded)."""
        return index in self._passes or self._entry(index)[2].is_file()

    def passes_to_render(self, spp: int) -> int:
        """How many passes both references at ``spp`` each still need rendered (not in the cache)."""
        return sum(not self.cached(i) for i in range(2 * (spp // self.base_spp)))

    def _pass(self, index: int) -> tuple[dict[str, np.ndarray], float]:
        if index in self._passes:
            return self._passes[index]
        from model.frame import FrameError
        from renderer.reference import load_reference, write_reference

        seed, tag, path = self._entry(index)
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
            ref = self.render_pass(self.base_spp, seed)
            ref.metadata["gradsep.eval_key"] = tag
            path.parent.mkdir(parents=True, exist_ok=True)
            write_reference(path, ref)
            self.rendered += 1
        images = ref.images()
        seconds = float(ref.metadata.get("gradsep.render_seconds", "nan"))
        self._passes[index] = (images, seconds)
        return self._passes[index]

    def pair(self, spp: int) -> ReferencePair:
        """Both references at ``spp`` (a multiple of the starting spp) each."""
        if spp % self.base_spp:
            raise ValueError(f"reference spp {spp} is not a multiple of the starting spp {self.base_spp}")
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
        first, second = ({n: (a / count).astype(np.float32) for n, a in s.items()} for s in sums)
        tag = key_hash({**self.key, "kind": "reference-pair", "base_spp": self.base_spp, "spp": spp})
        return ReferencePair(spp, first, second, tag, seconds, {"gradsep.spp": str(spp)})
