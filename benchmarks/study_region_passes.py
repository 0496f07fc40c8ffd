"""Where a scene's reference floor lives, and what region passes buy against more full passes (issue 13).

Reads the evaluation cache only (renders nothing): a scene's full reference passes, its pilot and whatever region
passes are cached (``gradsep evaluate`` renders them; see docs/evaluation.md, "Region passes"). Prints

1. how concentrated the floor of the two references is (share of the floor in the worst 10 % / 25 % of
   16-pixel tiles) and, for the rectangle chosen at several design reductions, the extra samples (in frames at
   the current spp) that reach a needed reduction, against full passes (needed - 1);
2. the rectangle the pilot places (evaluation/region.py) and its share of the two references' floor;
3. with region passes cached: the floor measured with them against the floor full passes would reach with the
   same number of samples (1/spp), i.e. what the rectangle buys per sample, and with ``--time`` (renders one
   full and one region pass back to back) per second.

    python benchmarks/study_region_passes.py --scene procedural:90002 --cache runs/evalcache --time
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gradsep.evaluation.config import load_settings, make_config, resolve_scenes  # noqa: E402
from gradsep.evaluation.region import TILE, _tile_sums, choose_region, pilot_floor_map  # noqa: E402


def _gain(floor: float, reached: float, uniform: float) -> str:
    """How many times the floor's log-reduction of full passes ``reached`` is: >1, region passes buy more."""
    return f"{math.log(floor / reached) / math.log(floor / uniform):.2f}x"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="procedural:90002")
    parser.add_argument("--cache", default="runs/evalcache")
    parser.add_argument("--time", action="store_true",
                        help="render one full and one region pass back to back for the per-second comparison")
    args = parser.parse_args()

    from gradsep.evaluation.run import _Runner
    from gradsep.renderer.scene import load_scene

    config = make_config(load_settings(), output="/tmp/study-region", scenes=[args.scene], cache=args.cache)
    entry = resolve_scenes(config.scenes)[0][0]
    loaded = load_scene(entry.spec, width=config.width, height=config.height, max_depth=config.max_depth)
    source = _Runner(config, False, print).references(entry, loaded)
    base = config.ref_spp
    passes = 0
    while source.cached(2 * passes) and source.cached(2 * passes + 1):
        passes += 1
    if passes == 0:
        print(f"no cached reference passes of {args.scene} in {args.cache}")
        return 1
    spp = passes * base
    pair = source.pair(spp)
    # Per pixel, what model.metrics.reference_floor averages: the pilot map of the two references as two passes.
    floor_map = pilot_floor_map([pair.first["total"], pair.second["total"]])
    floor = float(floor_map.mean())
    print(f"{args.scene}: {spp} spp per reference in full passes ({passes} each), floor {floor:.3g}\n")

    h, w = floor_map.shape
    tiles = np.sort(_tile_sums(floor_map, TILE).ravel())[::-1]
    share = np.cumsum(tiles) / tiles.sum()
    print(f"Concentration: the worst 10 % of {TILE}-pixel tiles hold {share[int(0.1 * len(tiles)) - 1]:.0%} of the "
          f"floor, the worst 25 % {share[int(0.25 * len(tiles)) - 1]:.0%}.\n")

    needs = (1.5, 2.0, 2.3, 3.0, 4.0)
    print("| rectangle chosen for | rectangle | area | floor share | "
          + " | ".join(f"extra for {n:g}x" for n in needs) + " |")
    print("|---|---|---:|---:|" + "---:|" * len(needs))
    total = floor_map.sum()
    for design in (1.5, 2.0, 3.0, 4.0, 6.0):
        region = choose_region(floor_map, reduction=design)
        inside = floor_map[region.slices].sum()
        fraction = region.fraction(w, h)
        cells = []
        for need in needs:
            removed = total * (1 - 1 / need)
            cells.append(f"{fraction * removed / (inside - removed):.2f}" if inside > removed else "–")
        print(f"| {design:g}x | {region.describe()} | {fraction:.0%} | {inside / total:.0%} | "
              + " | ".join(cells) + " |")
    print("| full passes | whole frame | 100% | 100% | " + " | ".join(f"{n - 1:.2f}" for n in needs) + " |")
    print("\n(extra samples in frames at the current spp; full passes need (reduction - 1))\n")

    if source.pilot_passes_to_render():
        print("pilot not cached: render it with `gradsep evaluate --references-only` (it places the region)")
        return 0
    region = source.region()
    outside, inside = pair.floor_split(region)
    print(f"Pilot's rectangle: {region.describe()}, {region.fraction(w, h):.0%} of the pixels, "
          f"{inside / floor:.0%} of the references' floor ({inside:.3g} of {floor:.3g}).\n")
    count = 0
    while all(source.region_cached(count + 1)):
        count += 1
    if not count:
        print("no region passes cached yet")
        return 0
    # Seconds of one full and one region pass rendered back to back (fresh seeds, nothing cached): the recorded
    # seconds of cached passes come from whatever load they were rendered under and do not compare.
    ratio = None
    if args.time:
        from gradsep.evaluation.references import REFERENCE_SAMPLER
        from gradsep.evaluation.region import render_region
        from gradsep.renderer.reference import render_loaded

        full_s = float(render_loaded(loaded, spp=base, seed=987654, tile_spp=None, sampler=REFERENCE_SAMPLER)
                       .metadata["gradsep.render_seconds"])
        region_s = float(render_region(loaded, region, spp=base, seed=987655, sampler=REFERENCE_SAMPLER)
                         .metadata["gradsep.render_seconds"])
        ratio = region_s / full_s
        print(f"One pass of {base} spp, back to back: full frame {full_s:.1f} s, region {region_s:.1f} s "
              f"({ratio:.2f} of a full pass for {region.fraction(w, h):.0%} of the pixels).\n")
    print("| region passes each | extra spp inside | floor | full passes, same samples | gain per sample | "
          "full passes, same time | gain per second |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for k in sorted({max(1, count // 4), max(1, count // 2), count}):
        with_region = source.pair(spp, k).floor()
        samples = spp + k * base * region.fraction(w, h)  # per pixel, on average
        same_samples = floor * spp / samples
        timed = "– | –"
        if ratio is not None:
            same_time = floor * spp / (spp + k * base * ratio)  # full passes in the region passes' time
            timed = f"{same_time:.3g} | {_gain(floor, with_region, same_time)}"
        print(f"| {k} | {k * base} | {with_region:.3g} | {same_samples:.3g} | "
              f"{_gain(floor, with_region, same_samples)} | {timed} |")
    print("\n(gain: the floor's log-reduction, region passes over full passes with the same samples or time)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
