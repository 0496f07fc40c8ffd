"""Does `--gradients direct` help the product's default method at equal render time? (issue 16, design 1)

    PYTHONPATH=. .venv/bin/python benchmarks/study_direct_gradients.py REF_DIR:procedural:90001 [...] [--seeds 2]

For each scene (a ``REFERENCE_DIR:SCENE`` pair: a folder holding independent reference passes ``*passN-*.exr`` as
the evaluation caches them -- split into two independent halves -- and the scene they were rendered from; the
scene's size and max depth are read from the references' metadata) this renders, at **equal CPU render time**:

* ``all`` -- G-PT with every layer's gradients at ``--spp`` (the budget), reconstructed with ``oidn-l1``;
* ``direct`` -- `--gradients direct` at the spp it buys in that time, reconstructed with ``oidn-l1``;
* ``primal`` -- the primal-only mode (`--no-gradients`) at the spp it buys, reconstructed with ``oidn`` (the
  evaluation's "separated path + OIDN per layer" baseline);

and scores each with the noise-corrected RelMSE against the two reference passes (model.metrics.relmse_unbiased),
for the frame and for the direct layer. Costs are CPU times per render (median of ``--rounds`` interleaved
rounds), measured in the same process; reconstruction time is not part of the budget (oidn-l1 costs the same
on both G-PT frames; oidn is cheaper, which favours ``primal`` slightly more than shown).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# mode -> (`--gradients`, reconstruction method, GptSettings.offsets); --modes picks a subset ("all" is the budget)
MODES = {"all": ("all", "oidn-l1", "all"), "direct": ("direct", "oidn-l1", "all"), "primal": ("none", "oidn", "all"),
         "alternate": ("all", "oidn-l1", "alternate"), "alternate+direct": ("direct", "oidn-l1", "alternate"),
         "pair": ("all", "oidn-l1", "pair")}


def references(folder: Path) -> tuple:
    """Two independent references from the folder's passes (the newest file of each pass index): passes 0..k-1
    averaged against passes k..2k-1, or pass 0 against pass 1."""
    from renderer.reference import Reference, load_reference

    passes = []
    for index in range(64):
        files = sorted(folder.glob(f"*pass{index}-*.exr"), key=lambda p: p.stat().st_mtime)
        if not files:
            break
        passes.append(load_reference(files[-1]))
    if len(passes) < 2:
        raise SystemExit(f"{folder}: needs at least two *passN-*.exr reference passes")
    half = len(passes) // 2

    def mean(group: list) -> Reference:
        return Reference(sum(r.total for r in group) / len(group), sum(r.direct for r in group) / len(group), None,
                         group[0].metadata)

    return mean(passes[:half]), mean(passes[half:2 * half])


def timed(fn) -> tuple[object, float]:
    start = time.process_time()
    out = fn()
    return out, time.process_time() - start


def study(folder: Path, spec: str, spp: int, seeds: int, rounds: int, modes: list[str]) -> dict:
    from model.metrics import relmse_unbiased
    from model.reconstruct import reconstruct
    from renderer.render import render_frame
    from renderer.scene import load_scene

    ref0, ref1 = references(folder)
    height, width = ref0.total.shape[:2]
    depth = int(ref0.metadata.get("gradsep.max_depth", "-1"))
    loaded = load_scene(spec, width=width, height=height, max_depth=depth)

    def render(mode: str, n: int, seed: int):
        return render_frame(loaded, spp=n, seed=seed, gradients=MODES[mode][0], offsets=MODES[mode][2])

    for mode in modes:  # kernel compilation
        render(mode, 1, 0)
    cpu: dict[str, list[float]] = {mode: [] for mode in modes}
    for r in range(rounds):
        for mode in modes:
            cpu[mode].append(timed(lambda m=mode, s=1000 + r: render(m, spp, s))[1])
    cost = {mode: statistics.median(a / b for a, b in zip(cpu[mode], cpu["all"], strict=True)) for mode in modes}
    budget = {mode: max(1, round(spp / cost[mode])) for mode in modes}
    scores: dict[str, dict[str, list[float]]] = {mode: {"frame": [], "direct": []} for mode in modes}
    for seed in range(seeds):
        for mode in modes:
            frame = render(mode, budget[mode], 2000 + seed)
            result = reconstruct(frame, MODES[mode][1])
            scores[mode]["frame"].append(relmse_unbiased(result.image, ref0.total, ref1.total))
            scores[mode]["direct"].append(relmse_unbiased(result.layers["direct"], ref0.direct, ref1.direct))
    return {"size": f"{width}x{height}", "max_depth": depth, "cost_vs_all": cost, "spp": budget,
            "relmse": {m: {k: float(np.mean(v)) for k, v in s.items()} for m, s in scores.items()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+",
                        help="REFERENCE_DIR:SCENE (e.g. runs/evalcache/evaluate/references/procedural-90001:"
                             "procedural:90001)")
    parser.add_argument("--spp", type=int, default=16, help="the budget: spp of the `all` render (default 16)")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds")
    parser.add_argument("--modes", default="all,direct,primal",
                        help=f"comma-separated, from {','.join(MODES)}; `all` (the budget) is always included")
    args = parser.parse_args(argv)
    modes = ["all"] + [m for m in args.modes.split(",") if m and m != "all"]
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        raise SystemExit(f"unknown modes {unknown}; expected some of {list(MODES)}")
    print(f"equal CPU render time = `all` at {args.spp} spp; RelMSE noise-corrected against two reference passes")
    print(f"  {'scene':<18} {'mode':<16} {'cost':>6} {'spp':>4} {'frame RelMSE':>13} {'direct RelMSE':>14}")
    for item in args.scenes:
        folder, _, spec = item.partition(":")
        out = study(Path(folder), spec, args.spp, args.seeds, args.rounds, modes)
        for mode in modes:
            r = out["relmse"][mode]
            print(f"  {spec:<18} {mode:<16} {out['cost_vs_all'][mode]:>5.2f}x {out['spp'][mode]:>4} "
                  f"{r['frame']:>13.5f} {r['direct']:>14.5f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
