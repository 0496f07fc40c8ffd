"""`gradsep evaluate --references-only --shard K/N`: render a share of the evaluation's reference passes on a
farm, so N machines buy N times the reference samples of one evaluation.

Each of a scene's two references is the mean of passes at the starting spp (evaluation/references.py), every
pass its own seed and its own cache file, named by a hash of what determines it (scene, size, depth, seed, pass
index, sampler, reference code, Mitsuba version). A reference at ``--ref-spp-cap`` uses passes
0 .. 2 x cap / start - 1 (even ones the first reference, odd ones the second), and a smaller reference spp a
prefix of them. Shard K of N renders the passes whose index is K-1 modulo N into its cache: exactly the files one
machine would have written, so combining the shards is copying their ``evaluate/references/`` folders into one
cache (the names never collide, and an identical name means an identical pass). The final ``gradsep evaluate``
on that cache (same --ref-spp, --seed, --size, code and Mitsuba) then finds every pass it needs and renders none:
its ``--ref-seconds`` budget counts only passes it would render itself.

The shards also render the pilot passes (pilot i in shard K when i = K-1 modulo N), which place the region
passes of a scene whose floor the full passes leave too high (evaluation/region.py). Region passes themselves
depend on the floor the evaluation needs, so the evaluating machine renders them, within its own budget.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from gradsep.evaluation.config import EvalConfig, resolve_scenes
from gradsep.evaluation.region import PILOT_PASSES
from gradsep.model.errors import CommandError

__all__ = ["ShardReport", "render_reference_shard"]


@dataclass
class ShardReport:
    """What one shard did per scene: passes it owns, passes it rendered (the rest were cached), seconds, and
    the pilot passes it owns (they place the region passes; evaluation/region.py)."""

    scene: str
    passes: list[int]
    rendered: int
    seconds: float
    pilots: list[int]


def shard_passes(ref_spp: int, cap: int, shard: tuple[int, int]) -> list[int]:
    """Pass indices of shard (K, N) among the 2 x cap / ref_spp passes of both references at the cap."""
    if cap % ref_spp:
        raise CommandError(f"--ref-spp-cap {cap} is not a multiple of --ref-spp {ref_spp}: the references are "
                           "means of whole passes")
    k, n = shard
    return list(range(k - 1, 2 * cap // ref_spp, n))


def render_reference_shard(config: EvalConfig, shard: tuple[int, int], *, progress: bool | None = None,
                           log: Callable[[str], None] = print) -> list[ShardReport]:
    """Render shard ``(K, N)`` of every configured scene's reference passes up to ``config.reference_cap``."""
    from gradsep.evaluation.run import _Runner
    from gradsep.renderer.scene import load_scene

    entries, notes = resolve_scenes(config.scenes)
    for note in notes:
        log(f"note: {note}")
    runner = _Runner(config, progress, log)
    try:
        runner.cache.prepare()
    except OSError as exc:
        raise CommandError(f"cache folder {str(runner.cache.root)!r} cannot be created: {exc.strerror or exc}") from exc
    indices = shard_passes(config.ref_spp, config.reference_cap, shard)
    loaded_scenes = [load_scene(e.spec, width=config.width, height=config.height, max_depth=config.max_depth)
                     for e in entries]  # all validated before the first render
    out = []
    for entry, loaded in zip(entries, loaded_scenes, strict=True):
        source = runner.references(entry, loaded)
        before, start = runner.computed["references"], time.perf_counter()
        for i in indices:
            source.ensure(i)
        pilots = list(range(shard[0] - 1, PILOT_PASSES, shard[1]))
        for i in pilots:
            source.ensure(i, "pilot")
        rendered = runner.computed["references"] - before
        out.append(ShardReport(entry.name, indices, rendered, time.perf_counter() - start, pilots))
        log(f"{entry.name}: shard {shard[0]}/{shard[1]}: {len(indices)} passes and {len(pilots)} pilot passes of "
            f"{config.ref_spp} spp ({rendered} rendered, {len(indices) + len(pilots) - rendered} cached) in "
            f"{out[-1].seconds:.0f} s")
    return out
