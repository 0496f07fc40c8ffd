"""Does `--gradients direct` help the product's default method at equal render time? (issue 16, design 1)

    PYTHONPATH=. .venv/bin/python benchmarks/study_direct_gradients.py REF_DIR:procedural:90001 [...] [--seeds 2]

For each scene (a ``REFERENCE_DIR:SCENE`` pair: a folder holding independent reference passes ``*passN-*.exr`` as
the evaluation caches them -- split into two independent halves -- and the scene they were rendered from; the
scene's size and max depth are read from the references' metadata), or a folder of benchmarks/study_refine.py's
held-out cache (``ref-1-*.npz`` and ``ref-2-*.npz``, the scene's default depth; e.g.
``~/.cache/gradsep/refine-study/procedural-81001:procedural:81001``) this renders, at **equal CPU render time**:

* ``all`` -- G-PT with every layer's gradients at ``--spp`` (the budget), reconstructed with ``oidn-l1``;
* ``direct`` -- `--gradients direct` at the spp it buys in that time, reconstructed with ``oidn-l1``;
* ``primal`` -- the primal-only mode (`--no-gradients`) at the spp it buys, reconstructed with ``oidn`` (the
  evaluation's "separated path + OIDN per layer" baseline);

and, with ``--fractions F1,F2,...`` (issue 14's split samples), ``split-F``: a fraction F of that render time spent
on ``alternate+direct`` G-PT samples (K = F x budget / its cost) and the rest on primal-only samples
(N - K = (1 - F) x budget / their cost), merged by ``render_frame(spp=N, gradient_spp=K)`` and reconstructed with
``oidn-l1`` (F = 1 is ``alternate+direct``, F = 0 is ``primal``; both are timed whenever a fraction is asked for);

and scores each with the noise-corrected RelMSE against the two reference passes (model.metrics.relmse_unbiased),
for the frame and for the direct layer. Costs are CPU times per render (median of ``--rounds`` interleaved
rounds), measured in the same process; reconstruction time is not part of the budget (oidn-l1 costs the same
on both G-PT frames; oidn is cheaper, which favours ``primal`` slightly more than shown). The ``cost@spp`` column
is each mode's CPU time at its chosen spp over `all`'s at the budget, measured on the scored renders (median over
seeds): ~1.0 when the equal-time split holds, and the check that a split render costs what its parts predict.

``--split-alpha`` (session 16) also scores every split frame a second time, as ``split-F+alpha``: the same frame,
reconstructed with ``oidn-l1`` whose trust rule has its clean-layer α (TRUST_ALPHA_BASE, the α where the data term
is the frame's own base) multiplied by N/K. A base of N samples has N/K times less variance than gradients of K, and
the screened-Poisson α weighs the data term against the gradients by that ratio; the shipped rule assumes N = K.
(OIDN's image, the data term where the base is not trusted, keeps REFINE_ALPHA: its error is mostly bias, which
does not fall as 1/N. A one-seed probe that scaled both α made the direct layer worse, 0.00038 against 0.00028 on
81005.)
"""

from __future__ import annotations

import argparse
import json
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
    from gradsep.renderer.reference import Reference, load_reference

    pairs = sorted(folder.glob("ref-*.npz"))  # benchmarks/study_refine.py's held-out cache: two references
    if len(pairs) >= 2:
        first, second = (np.load(p) for p in pairs[:2])
        return tuple(Reference(r["total"], r["direct"], None, {}) for r in (first, second))
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


SPLIT_BASE = "alternate+direct"  # the G-PT part of a split-F mode (the evaluation's gpt-direct render)


def split_fraction(mode: str) -> float | None:
    """``split-0.25`` -> 0.25; None for the plain modes."""
    return float(mode.removeprefix("split-")) if mode.startswith("split-") else None


def budgets(modes: list[str], spp: int, cost: dict[str, float], overhead: float = 0.0) -> dict[str, tuple[int, int]]:
    """mode -> (N, K): total samples and samples with gradients (K = N for the plain modes) at `all`'s time. A split
    render first pays ``overhead`` (its second kernel's fixed cost, as a fraction of `all`'s time)."""
    out: dict[str, tuple[int, int]] = {}
    for mode in modes:
        f = split_fraction(mode)
        if f is None:
            n = max(1, round(spp / cost[mode]))
            out[mode] = (n, n)
        else:
            left = spp * max(0.0, 1.0 - overhead)
            k = max(1, round(f * left / cost[SPLIT_BASE]))
            out[mode] = (k + max(0, round((1 - f) * left / cost["primal"])), k)
    return out


def reconstruct_split_aware(frame, factor: float):
    """``oidn-l1`` with the trust rule's clean-layer α multiplied by ``factor`` (N/K for a split frame)."""
    import gradsep.model.refine as refine
    from gradsep.model.reconstruct import reconstruct

    saved = refine.TRUST_ALPHA_BASE
    refine.TRUST_ALPHA_BASE = saved * factor
    try:
        return reconstruct(frame, "oidn-l1")
    finally:
        refine.TRUST_ALPHA_BASE = saved


def study(folder: Path, spec: str, spp: int, seeds: int, rounds: int, modes: list[str],
          score_all: bool = True, first_seed: int = 2000, split_alpha: bool = False) -> dict:
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.reconstruct import reconstruct
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    ref0, ref1 = references(folder)
    height, width = ref0.total.shape[:2]
    stated = ref0.metadata.get("gradsep.max_depth")
    depth = int(stated) if stated is not None else None  # None: the scene's own (what study_refine rendered)
    loaded = load_scene(spec, width=width, height=height, max_depth=depth)

    def render(mode: str, n: int, seed: int, k: int | None = None):
        base = SPLIT_BASE if split_fraction(mode) is not None else mode
        gradient_spp = None if k is None or k >= n else k
        return render_frame(loaded, spp=n, seed=seed, gradients=MODES[base][0], offsets=MODES[base][2],
                            gradient_spp=gradient_spp)

    split = any(split_fraction(m) is not None for m in modes)
    # a split render's extra cost over its parts' (its second kernel): timed as spp samples, half with gradients
    timed_modes = [m for m in modes if split_fraction(m) is None] + (["split-probe"] if split else [])

    def timed_render(mode: str, seed: int):
        if mode == "split-probe":
            return render("split-0.5", spp, seed, max(1, spp // 2))
        return render(mode, spp, seed)

    for mode in timed_modes[:len(timed_modes) - split]:  # kernel compilation (the probe reuses these kernels)
        timed_render(mode, 0)
    cpu: dict[str, list[float]] = {mode: [] for mode in timed_modes}
    for r in range(rounds):
        for mode in timed_modes:
            cpu[mode].append(timed(lambda m=mode, s=1000 + r: timed_render(m, s))[1])
    cost = {mode: statistics.median(a / b for a, b in zip(cpu[mode], cpu["all"], strict=True))
            for mode in timed_modes}
    overhead = 0.0
    if split:
        k = max(1, spp // 2)
        parts = (k * cost[SPLIT_BASE] + (spp - k) * cost["primal"]) / spp
        overhead = max(0.0, cost.pop("split-probe") - parts)
    budget = budgets(modes, spp, cost, overhead)
    scored = [m for m in modes if score_all or m != "all"]
    aware = [f"{m}+alpha" for m in scored if split_alpha and split_fraction(m) is not None]
    scores: dict[str, dict[str, list[float]]] = {mode: {"frame": [], "direct": []} for mode in scored + aware}
    seconds: dict[str, list[float]] = {mode: [] for mode in scored}
    for seed in range(seeds):
        for mode in scored:
            n, k = budget[mode]
            frame, used = timed(lambda m=mode, n=n, k=k, s=first_seed + seed: render(m, n, s, k))
            seconds[mode].append(used)
            method = "oidn-l1" if split_fraction(mode) is not None else MODES[mode][1]
            result = reconstruct(frame, method)
            scores[mode]["frame"].append(relmse_unbiased(result.image, ref0.total, ref1.total))
            scores[mode]["direct"].append(relmse_unbiased(result.layers["direct"], ref0.direct, ref1.direct))
            if f"{mode}+alpha" in scores:  # the same frame, the refinement told that its base has N/K more samples
                result = reconstruct_split_aware(frame, n / k)
                scores[f"{mode}+alpha"]["frame"].append(relmse_unbiased(result.image, ref0.total, ref1.total))
                scores[f"{mode}+alpha"]["direct"].append(
                    relmse_unbiased(result.layers["direct"], ref0.direct, ref1.direct))
    all_seconds = statistics.median(cpu["all"])
    return {"size": f"{width}x{height}", "max_depth": depth, "cost_vs_all": cost, "spp": budget,
            "split_overhead": overhead,
            "cost_at_spp": {m: statistics.median(v) / all_seconds
                            for m, v in (seconds | {a: seconds[a.removesuffix("+alpha")] for a in aware}).items()},
            "relmse": {m: {k: float(np.mean(v)) for k, v in s.items()} for m, s in scores.items()},
            "per_seed": {m: {k: [float(x) for x in v] for k, v in s.items()} for m, s in scores.items()}}


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
    parser.add_argument("--fractions", default="",
                        help="comma-separated fractions F in (0, 1) of the render time spent on alternate+direct "
                             "G-PT samples, the rest on primal-only samples (split-F modes; adds alternate+direct "
                             "and primal)")
    parser.add_argument("--skip-all", action="store_true",
                        help="time `all` (the budget) but do not score it")
    parser.add_argument("--first-seed", type=int, default=2000, help="render seed of the first scored frame")
    parser.add_argument("--split-alpha", action="store_true",
                        help="also score each split frame with the trust rule's alpha times N/K (split-F+alpha)")
    parser.add_argument("--json", default=None, help="also write every scene's numbers (per seed too) here")
    args = parser.parse_args(argv)
    modes = ["all"] + [m for m in args.modes.split(",") if m and m != "all"]
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        raise SystemExit(f"unknown modes {unknown}; expected some of {list(MODES)}")
    fractions = [float(f) for f in args.fractions.split(",") if f.strip()]
    if any(not 0 < f < 1 for f in fractions):
        raise SystemExit(f"--fractions must be in (0, 1), got {fractions}")
    if fractions:
        modes += [m for m in (SPLIT_BASE, "primal") if m not in modes]
        modes += [f"split-{f:g}" for f in fractions]
    print(f"equal CPU render time = `all` at {args.spp} spp; RelMSE noise-corrected against two reference passes")
    print(f"  {'scene':<18} {'mode':<16} {'cost':>6} {'spp (grad)':>10} {'cost@spp':>8} {'frame RelMSE':>13} "
          f"{'direct RelMSE':>14}")
    results = {}
    for item in args.scenes:
        folder, _, spec = item.partition(":")
        out = study(Path(folder), spec, args.spp, args.seeds, args.rounds, modes, score_all=not args.skip_all,
                    first_seed=args.first_seed, split_alpha=args.split_alpha)
        results[spec] = out
        for mode in out["relmse"]:
            r = out["relmse"][mode]
            n, k = out["spp"][mode.removesuffix("+alpha")]
            cost = out["cost_vs_all"].get(mode)
            spp_text = f"{n} ({k})" if k < n else f"{n}"
            print(f"  {spec:<18} {mode:<16} {f'{cost:.2f}x' if cost else '-':>6} {spp_text:>10} "
                  f"{out['cost_at_spp'][mode]:>7.2f}x {r['frame']:>13.5f} {r['direct']:>14.5f}", flush=True)
        if "split_overhead" in out and any(split_fraction(m) is not None for m in modes):
            print(f"  {spec:<18} split render overhead over its parts: {out['split_overhead']:.3f} of the budget")
        if args.json:
            Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
