"""Summarise `study_direct_gradients.py --json` files: per scene, and geometric means of RelMSE ratios.

    python benchmarks/summarize_split_study.py 'OUT/s16-*.json' [--baselines primal,alternate+direct]

Per scene the mean and the median over seeds of the frame RelMSE (the metric is heavy-tailed: one firefly seed can
dominate a mean); then for every mode the geometric mean over scenes of its per-scene mean (and median) over the
best baseline's, how many scenes it beats every baseline on, and the geometric mean over frames (scene x seed:
the same render seed in every mode) of its ratio to each baseline.
"""

from __future__ import annotations

import argparse
import glob
import json
import sys

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pattern", help="glob of --json files")
    parser.add_argument("--baselines", default="primal,alternate+direct")
    args = parser.parse_args(argv)
    base = args.baselines.split(",")
    rows: list[tuple[str, dict[str, np.ndarray], dict]] = []
    for name in sorted(glob.glob(args.pattern)):
        for spec, out in json.loads(open(name).read()).items():
            rows.append((spec, {m: np.array(v["frame"]) for m, v in out["per_seed"].items()}, out))
    if not rows:
        raise SystemExit(f"no files match {args.pattern}")
    modes = list(rows[0][1])
    print("frame RelMSE per scene, mean | median over seeds (spp, with gradients)")
    for spec, frame, out in rows:
        # a split-F+alpha mode (--split-alpha) scores the split-F frame: its spp are that frame's
        cells = [f"{m} {frame[m].mean():.5f}|{np.median(frame[m]):.5f} "
                 f"({'/'.join(map(str, out['spp'][m.removesuffix('+alpha')]))})" for m in modes]
        print(f"  {spec}: " + "; ".join(cells))
    for label, stat in (("mean", np.mean), ("median", np.median)):
        print(f"per-scene {label} over the best baseline's (geometric mean over {len(rows)} scenes), scenes won:")
        for m in modes:
            ratio = [stat(f[m]) / min(stat(f[b]) for b in base) for _, f, _ in rows]
            wins = sum(r < 1 for r in ratio)
            print(f"  {m:<18} {np.exp(np.mean(np.log(ratio))):.3f}  beats {'+'.join(base)} on {wins}/{len(rows)}")
    print("per frame (same seed), geometric mean of the ratio to " + ", ".join(base) + ":")
    for m in modes:
        cells = [np.exp(np.concatenate([np.log(f[m] / f[b]) for _, f, _ in rows]).mean()) for b in base]
        print(f"  {m:<18} " + "  ".join(f"{c:.3f}" for c in cells))
    cost = {m: float(np.median([o["cost_at_spp"][m] for *_, o in rows])) for m in modes}
    print("median cost@spp (CPU time of the scored render over the budget): "
          + ", ".join(f"{m} {c:.2f}" for m, c in cost.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
