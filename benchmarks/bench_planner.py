"""The render planner's figures (renderer/planner.py): `gradsep render --seconds T` against its budget, and
`--gradients auto` against every fixed plan at equal wall time on held-out scenes.

    # the deadline: wall time of the whole command (a subprocess, as a farm runs it) against T
    python benchmarks/bench_planner.py timing [--scenes procedural:93101] [--sizes 320x240,1280x720]
        [--seconds 5,10,20] [--plans auto,all]

    # the choice and the prediction: each plan rendered with --seconds T, reconstructed with its default method,
    # RelMSE against two independent `gradsep reference` renders (the floor removed: relmse_unbiased)
    python benchmarks/bench_planner.py validate [--scenes procedural:93101,...] [--size 128] [--seconds 20,40]
        [--ref-spp 2048] [--cache ~/.cache/gradsep/planner-bench]

    # validate's cached frames through today's reconstruction (same samples, same wall time): today / recorded
    # RelMSE and today / best fixed, per family and pipeline; --setting for the frames with gradients; --against
    # another validate cache: this cache's frames over its, both reconstructed today
    python benchmarks/bench_planner.py rescore [--setting prefiltered-high] [--cache ...] [--against CACHE]

    # the frame's own error estimate (renderer/check.py): `--gradients auto` frames with --seconds T, their
    # gradsep.predicted_relmse and the checkpoint's prediction against the measured RelMSE (with the measurement's
    # own standard error and the references' floor), the OIDN setting their halves chose against the better one
    # measured, and `auto` over each fixed plan (--plan P) rendered into the same cache with the same seeds and
    # over the best of them per frame
    python benchmarks/bench_planner.py predict [--plan auto] [--scenes ...] [--size 192] [--seconds 20]
        [--seeds 10,11] [--ref-spp 1024] [--cache ...]

    # the OIDN setting a frame's halves choose (raw-fast or prefiltered-high) against the better one measured, at a
    # fixed sample count, in one process
    python benchmarks/bench_planner.py choose [--scenes ...] [--plan primal] [--spp 960] [--cache ...]

    # the plan cache on a shot: one frame judges, the others read its choice; their samples against the fixed
    # plan's, interleaved
    python benchmarks/bench_planner.py shot [--scenes ...] [--size 192] [--seconds 20] [--seeds 61,62,63]

    # a plain-frame plan's cost against Mitsuba's `path` (same scene, size, spp, depth, box filter): a whole frame
    # and the marginal cost of a sample (frames of spp and 2 spp)
    python benchmarks/bench_planner.py cost [--scenes procedural:93201,procedural:studio:93201]
        [--sizes 320x240,1280x720] [--spp 16] [--repeats 5]

``validate`` renders every plan of a (scene, budget, seed) back to back (the order rotated per seed, so that a
change of the machine's load falls on every plan alike), seed-major, after compiling every plan's kernels at the
frame's size (Dr.Jit's cache is keyed by it; a farm re-rendering a scene has them cached), then scores the frames
whose references exist and prints per frame auto's choice, auto / best fixed, the chosen plan's own fixed frame /
best (the choice alone, free of the pilot's cost), predicted / measured, each fixed plan / best and the reference
floor / best; then per family the geometric means, worst and frames above 1.05x, and how many predictions are
within 1.5x. The scenes must be held out: never the evaluation's (evaluation/config.py) or the shared ones, nor
seeds a design was tuned on.

The figures in docs/renderer.md ("The render planner", Validation; "The frame's own error estimate") come from
(2-core Intel Xeon, otherwise idle; 4096-spp references of each scene, seeds 1 and 2, rendered into the cache by
``predict`` itself or beforehand with `gradsep reference SCENE --width 192 --height 192 --spp 4096 --seed 1` and
`--seed 2`), each plan in turn into one cache:

    for plan in direct-alternate primal auto; do
        python benchmarks/bench_planner.py predict --plan $plan --seconds 20 --seeds 21,22 --ref-spp 4096 \
            --cache /work/pred11; done

(`auto` then once more into the same cache after its entries were removed, with the reconstruction's start-up in
the background), and on 8 rooms never used before:

    for plan in direct-alternate primal auto; do
        python benchmarks/bench_planner.py predict --plan $plan --seconds 20 --seeds 31,32 --ref-spp 4096 \
            --scenes procedural:93301,procedural:93302,procedural:93303,procedural:93304,procedural:93305,\
procedural:93306,procedural:93307,procedural:93308 --cache /work/pred12; done

The plan cache (docs/renderer.md, "A shot's frames share the choice"): the cost, interleaved, and the estimate a
reading frame carries, on rooms never used for its design (the fixed plans rendered first into the cache, the
4096-spp references of the run above linked into it):

    python benchmarks/bench_planner.py shot --seconds 20 --seeds 61,62,63 \
        --scenes procedural:93301,procedural:93303,procedural:93305,procedural:93307 --cache /work/shot15
    python benchmarks/bench_planner.py predict --plan auto --seconds 20 --seeds 41,31,32 --ref-spp 4096 \
        --scenes procedural:93301,...,procedural:93308 --cache /work/pred14 --plan-cache /work/pred14/plans

The fixed plans at a budget too small for a checkpoint (3 s at 192x192; the 4096-spp references of the runs above
linked into each cache):

    for plan in direct-alternate primal; do
        python benchmarks/bench_planner.py predict --plan $plan --seconds 3 --seeds 21,22 --ref-spp 4096 \
            --cache /work/pred10
        python benchmarks/bench_planner.py predict --plan $plan --seconds 3 --seeds 31,32 --ref-spp 4096 \
            --scenes procedural:93301,procedural:93302,procedural:93303,procedural:93304,procedural:93305,\
procedural:93306,procedural:93307,procedural:93308 --cache /work/pred13; done

The earlier fixed pipelines' figures there come from (2 shared cores, load 4-6 from other work; 1024-spp
references):

    python benchmarks/bench_planner.py validate --size 192 --seconds 20 --seeds 3 --ref-spp 1024 \
        --cache /work/val/cache --no-references

docs/cli.md's `--seconds` timing with `auto` (3 runs per cell, and the 1280x720 T = 5 s cell alone, 5 runs, beside
`all`):

    python benchmarks/bench_planner.py timing --sizes 320x240,1280x720 --seconds 5,10,20 --plans auto --repeats 3
    python benchmarks/bench_planner.py timing --sizes 1280x720 --seconds 5 --plans auto,all --repeats 5

The deadline with primal filler passes, the write predicted from three bands and measured again near the end (this
tree as /tmp/dl/new, d6f0358 as /tmp/dl/base, both `git archive | tar -x`; 2 shared cores, load 5.2-7.6 from other
work, so one run of a cell may get half the machine another got):

    python benchmarks/bench_planner.py timing --sizes 1280x720,320x240 --seconds 10,20 --plans all,auto \
        --repeats 3 --checkouts /tmp/dl/base,/tmp/dl/new --cache /tmp/dl/timing5

Median wall / T (3 runs each, none past T), new against d6f0358: 1280x720 all 0.760 (0.679-0.906) against 0.788 at
T = 10 s, 0.951 (0.948-0.960) against 0.939 at 20 s; auto 0.906 against 0.777 at 10 s, 0.948 against 0.941 at
20 s; 320x240 all 0.970, 0.988 (0.971, 0.987 before), auto 0.955, 0.980 (0.981, 0.990). A 1280x720 run at 10 s
that ends near 0.7 T rendered its compiling pass alone: under this load that pass took 3-5 s, and no filler
kernel surely fits after it. At T = 5 s a 1280x720 frame is one pass (0.72-0.82 T) or refused.

At a lighter load (1-minute load 2.6-3.6 on the 2 cores, a niced reference render beside it; this tree, 3 runs
each, none past T):

    python benchmarks/bench_planner.py timing --sizes 1280x720,320x240 --seconds 10 \
        --plans all,direct-alternate --repeats 3

median wall / T at T = 10 s: 1280x720 `all` 0.921 (0.914-0.923), `direct-alternate` 0.921 (0.915-0.935); 320x240
0.978 and 0.982. So the 720p frame at 10 s meets the ±10 % target on a machine that is not oversubscribed.

A plain-frame plan against `path` (2 shared cores, load ~5.9 from other work; CPU time, medians of 5 interleaved
rounds), planner / path for a whole 8-spp frame and for a further sample (frames of 8 and 16 spp):

    python benchmarks/bench_planner.py cost --scenes procedural:93201,procedural:studio:93201 \
        --sizes 320x240,1280x720 --spp 8 --repeats 5

procedural:93201: frame 1.15 (320x240), 1.22 (1280x720); a further sample 0.94, 0.98. procedural:studio:93201:
frame 1.20, 1.50; a further sample 0.83, 0.63 (a cheap scene: 0.05 s and 0.45 s per `path` frame, so the difference
of two frames is noisy). `render --no-gradients`: frame 1.14-1.17. Dr.Jit's kernel history (JitFlag.KernelHistory)
puts the primal kernel's execution at `path`'s (1280x720, 16 spp: 0.85-0.90 s against 0.89-0.94 s on the studio,
7.6-7.8 s against 7.6 s on 93201): the per-frame excess is outside the kernel, reading the 15 channels of sums
back as float64 and assembling the frame (renderer/gpt.py `_pixel_sums`, `finish`), which `--no-gradients` pays
alike. At 16 spp (4 rounds, load ~5) the whole frame was 1.08, 1.09, 1.22, 1.30 here and 1.14, 1.13, 1.24, 1.54
at d6f0358, which assembled the frame once more after its first pass for a write estimate that a sample count does
not need.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

#: The fixed pipelines auto is judged against (issue 39): separated primal + oidn per layer, G-PT direct/alternate
#: + oidn-l1, G-PT all + the default method, primal + oidn on the unseparated sum; and G-PT direct (every offset)
#: + oidn-l1, auto's third candidate, so that each of its choices has a fixed frame of the same run.
FIXED = {"primal": ["--gradients", "none"], "direct-alternate": ["--gradients", "direct", "--offsets", "alternate"],
         "all": ["--gradients", "all"], "primal-sum": ["--gradients", "none", "--layers", "color"],
         "direct": ["--gradients", "direct"]}
PLANS = {"auto": ["--gradients", "auto"], **FIXED}


ROOT = Path(__file__).resolve().parents[1]


def gradsep(*args: str, checkout: Path = ROOT) -> tuple[float, str]:
    """Run the gradsep CLI of ``checkout`` (a source tree) in a fresh process; returns its wall time and stdout
    (raises on failure)."""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "gradsep", *args], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"gradsep {' '.join(args)}: exit {proc.returncode}: {proc.stderr.strip()[-400:]}")
    return wall, proc.stdout.strip()


def size_args(size: str) -> list[str]:
    w, _, h = size.partition("x")
    return ["--width", w, "--height", h or w]


def warm_kernels(scene: str, out: Path, size: tuple[str, str] = ("16", "16"), checkout: Path = ROOT) -> None:
    """Compile every plan's kernels for ``scene`` at ``size`` (Dr.Jit's kernel cache is keyed by the frame size
    too: a kernel compiled at another size is compiled again), so that no timed render pays a compilation."""
    for plan in FIXED.values():
        gradsep("render", scene, "--width", size[0], "--height", size[1], "--spp", "1", *plan, "-o", str(out),
                checkout=checkout)


def timing(args: argparse.Namespace) -> None:
    """Each (scene, size, T, plan, checkout) cell ``--repeats`` times; every repeat runs all cells once, in turn, so
    that a change of the machine's load falls on every cell (and every checkout) alike. One row per run (with the
    1-minute load average when it started), then the median, min and max of wall / T per cell."""
    out = Path(args.cache) / "timing.exr"
    out.parent.mkdir(parents=True, exist_ok=True)
    checkouts = [Path(c).resolve() for c in args.checkouts.split(",")] if args.checkouts else [ROOT]
    label = {c: (c.name if len(checkouts) > 1 else "") for c in checkouts}
    cells = [(scene, size, seconds, plan, c) for scene in args.scenes.split(",") for size in args.sizes.split(",")
             for seconds in args.seconds.split(",") for plan in args.plans.split(",") for c in checkouts]
    for scene in dict.fromkeys(cell[0] for cell in cells):
        for size in args.sizes.split(","):
            for c in checkouts:
                warm_kernels(scene, out, tuple(size_args(size)[1::2]), c)  # type: ignore[arg-type]
    print("| repeat | scene | size | plan | checkout | T (s) | load | wall (s) | wall / T | spp | chosen | "
          "predicted from |")
    print("|---:|---|---|---|---|---:|---:|---:|---:|---:|---|---|")
    results: dict[tuple, list[float]] = {cell: [] for cell in cells}
    loads: list[float] = []
    for repeat in range(args.repeats):
        for cell in cells:
            scene, size, seconds, plan, c = cell
            out.unlink(missing_ok=True)
            load = os.getloadavg()[0]
            loads.append(load)
            where = f"| {repeat} | {scene} | {size} | {plan} | {label[c]} | {seconds} | {load:.2f} |"
            try:
                wall, _ = gradsep("render", scene, *size_args(size), "--seconds", seconds, *PLANS[plan],
                                  "-o", str(out), checkout=c)
            except RuntimeError as exc:  # a budget below the start-up cost is refused (exit 2, no file)
                print(f"{where} refused | | | {str(exc)[-160:]} |", flush=True)
                assert not out.exists()
                continue
            meta = header(out)
            results[cell].append(wall / float(seconds))
            print(f"{where} {wall:.2f} | {wall / float(seconds):.3f} | {meta['gradsep.spp']} | "
                  f"{meta.get('gradsep.plan', '')} | {meta.get('gradsep.predicted_from', '')} |", flush=True)
    print(f"\nload (1-minute average) during the runs: median {statistics.median(loads):.2f}, "
          f"{min(loads):.2f}-{max(loads):.2f} (2 cores)\n")
    print("| scene | size | plan | checkout | T (s) | runs | median wall / T | min | max | past T |")
    print("|---|---|---|---|---:|---:|---:|---:|---:|---:|")
    for cell, ratios in results.items():
        scene, size, seconds, plan, c = cell
        if not ratios:
            print(f"| {scene} | {size} | {plan} | {label[c]} | {seconds} | 0 | refused | | | |")
            continue
        print(f"| {scene} | {size} | {plan} | {label[c]} | {seconds} | {len(ratios)} | "
              f"{statistics.median(ratios):.3f} | {min(ratios):.3f} | {max(ratios):.3f} | "
              f"{sum(r > 1.0 for r in ratios)} |")


def header(path: Path) -> dict[str, str]:
    from gradsep.model.exr_read import read_frame

    return dict(read_frame(path).metadata)


def reference(scene: str, size: int, spp: int, seed: int, cache: Path, render: bool = True) -> Path | None:
    """The cached reference (``gradsep reference``) of ``scene``; rendered when missing unless ``render`` is False
    (then None: the frames are scored on a later run, e.g. while the references render elsewhere)."""
    path = cache / f"ref-{scene.replace(':', '_')}-{size}-{spp}-{seed}.exr"
    if not path.exists():
        if not render:
            return None
        gradsep("reference", scene, "--width", str(size), "--height", str(size), "--spp", str(spp), "--seed",
                str(seed), "-o", str(path))
    return path


def measured_relmse(frame_path: Path, refs: tuple[Path, Path]) -> float:
    return measurement(frame_path, refs)["relmse"]


def measurement(frame_path: Path, refs: tuple[Path, Path], block: int = 16) -> dict[str, float]:
    """The frame's measured RelMSE (its reconstruction x against the two references, floor removed), the standard
    error the references' noise puts on it, and their floor: the measurement is only as sharp as its references,
    and every run shares them. Per pixel the product (x − r1)(x − r2) is the error e² plus the noise
    −e(n1 + n2) + n1·n2; half the difference of the squared errors, ((x − r1)² − (x − r2)²) / 2, is zero in
    expectation with the same variance (2e²σ² + σ⁴ for Gaussian noise), so its mean's spread over ``block``-pixel
    squares (a denoiser's error is correlated within its footprint) is the measurement's standard error."""
    import numpy as np

    from gradsep.model.exr_read import read_frame
    from gradsep.model.metrics import RELMSE_EPSILON, reference_floor
    from gradsep.model.reconstruct import reconstruct
    from gradsep.renderer.reference import load_reference

    image = reconstruct(read_frame(frame_path)).image.astype(np.float64)
    r1, r2 = (load_reference(str(p)).total.astype(np.float64) for p in refs)
    norm = (0.5 * (r1 + r2)) ** 2 + RELMSE_EPSILON  # model.metrics.relmse_unbiased's, pixel by pixel
    product = ((image - r1) * (image - r2) / norm).mean(axis=-1)
    noise = (((image - r1) ** 2 - (image - r2) ** 2) / (2 * norm)).mean(axis=-1)
    h, w = (n // block * block for n in noise.shape)
    blocks = noise[:h, :w].reshape(h // block, block, w // block, block).mean(axis=(1, 3)).ravel()
    return {"relmse": float(product.mean()), "relmse_se": float(np.sqrt(np.mean(blocks**2) / blocks.size)),
            "floor": reference_floor(r1, r2)}


def family(scene: str) -> str:
    return scene.rsplit(":", 1)[0]


def validate(args: argparse.Namespace) -> None:
    """Render every plan of every (scene, budget, seed) back to back (plan order rotated per seed, so that a drift
    of the machine's load falls on every plan alike), score the frames whose references exist, and print the
    targets' summary. A frame already in the cache (``validate.json`` and its EXR) is not rendered again."""
    from gradsep.model.metrics import reference_floor
    from gradsep.renderer.reference import load_reference

    cache = Path(args.cache).expanduser()
    cache.mkdir(parents=True, exist_ok=True)
    budgets = [float(s) for s in args.seconds.split(",")]
    seeds = [7 + i for i in range(args.seeds)]
    path = cache / "validate.json"
    rows: dict[str, dict] = json.loads(path.read_text()) if path.exists() else {}
    plans = list(PLANS)
    scenes = args.scenes.split(",")
    warmed: set[str] = set()
    for i, seed in enumerate(seeds):  # seed-major: a run cut short still has every scene at the first seeds
        for scene in scenes:
            for seconds in budgets:
                for plan in plans[i % len(plans):] + plans[:i % len(plans)]:
                    key = f"{scene}|{seconds:g}|{seed}|{plan}"
                    out = cache / f"frame-{scene.replace(':', '_')}-{seconds:g}-{seed}-{plan}.exr"
                    if key in rows and out.exists():
                        continue
                    if scene not in warmed:
                        warm_kernels(scene, cache / "warm.exr", (str(args.size), str(args.size)))
                        warmed.add(scene)
                    wall, _ = gradsep("render", scene, "--width", str(args.size), "--height", str(args.size),
                                      "--seconds", f"{seconds:g}", "--seed", str(seed), *PLANS[plan], "-o", str(out))
                    meta = header(out)
                    rows[key] = {"scene": scene, "seconds": seconds, "seed": seed, "plan": plan, "wall": wall,
                                 "spp": int(meta["gradsep.spp"]), "chosen": meta.get("gradsep.plan"),
                                 "predicted": meta.get("gradsep.predicted_relmse"),
                                 "candidates": meta.get("gradsep.plan_candidates"),
                                 "pilot": meta.get("gradsep.pilot_seconds"), "trace": meta.get("gradsep.plan_trace"),
                                 "load": os.getloadavg()[0], "file": out.name}
                    path.write_text(json.dumps(rows, indent=1))
                    print(f"{key}: {wall:.1f} s, {rows[key]['spp']} spp, plan {rows[key]['chosen']}", flush=True)
    floors: dict[str, float] = {}
    for scene in scenes:  # score what the references allow
        refs = [reference(scene, args.size, args.ref_spp, s, cache, render=not args.no_references) for s in (1, 2)]
        if None in refs:
            print(f"{scene}: references not there yet; its frames are not scored", flush=True)
            continue
        totals = [load_reference(str(p)).total for p in refs]
        floors[scene] = reference_floor(*totals)
        for row in rows.values():
            if row["scene"] == scene and "relmse" not in row:
                row["relmse"] = measured_relmse(cache / row["file"], tuple(refs))  # type: ignore[arg-type]
                path.write_text(json.dumps(rows, indent=1))
    summary([r for r in rows.values() if r["scene"] in floors and r["seconds"] in budgets], floors)


def summary(rows: list[dict], floors: dict[str, float]) -> None:
    """The issue's targets over the scored frames: auto against the best fixed plan of the same (scene, budget,
    seed), the choice alone (the fixed frame of the plan auto chose against the best), each fixed plan against the
    best, per family and overall (geometric means, worst, frames above 1.05x), and the prediction's accuracy."""
    groups: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        if "relmse" in r:
            groups.setdefault((r["scene"], r["seconds"], r["seed"]), {})[r["plan"]] = r
    complete = {k: g for k, g in groups.items() if set(g) == set(PLANS)}
    print("\n| scene | T (s) | seed | auto chose | auto / best | chosen plan's frame / best | predicted / measured |"
          " best fixed | " + " | ".join(f"{p} / best" for p in FIXED) + " | floor / best |")
    print("|---|---:|---:|---|---:|---:|---:|---|" + "---:|" * (len(FIXED) + 1))
    stats: dict[str, dict[str, list[float]]] = {}
    for (scene, seconds, seed), g in sorted(complete.items()):
        best_plan = min(FIXED, key=lambda p: g[p]["relmse"])
        best = max(g[best_plan]["relmse"], 1e-30)
        auto = g["auto"]
        chosen = g[auto["chosen"]]["relmse"] / best if auto["chosen"] in g else math.nan
        pred = float(auto["predicted"]) / auto["relmse"] if auto["predicted"] and auto["relmse"] > 0 else math.nan
        ratios = {"auto": auto["relmse"] / best, "choice": chosen, **{p: g[p]["relmse"] / best for p in FIXED}}
        for fam in (family(scene), "all"):
            st = stats.setdefault(fam, {})
            for name, v in ratios.items():
                st.setdefault(name, []).append(v)
            st.setdefault("prediction", []).append(pred)
        print(f"| {scene} | {seconds:g} | {seed} | {auto['chosen']} | {ratios['auto']:.3f} | {chosen:.3f} | "
              f"{pred:.2f} | {best_plan} | " + " | ".join(f"{ratios[p]:.3f}" for p in FIXED)
              + f" | {floors[scene] / best:.3f} |")
    print()
    for fam, st in stats.items():
        def geo(v: list[float]) -> float:
            v = [x for x in v if x > 0 and math.isfinite(x)]
            return math.exp(sum(map(math.log, v)) / len(v)) if v else math.nan
        parts = [f"{name} geo {geo(v):.3f} worst {max(v):.3f} >1.05x on {sum(x > 1.05 for x in v)}/{len(v)}"
                 for name, v in st.items() if name != "prediction"]
        pred = st["prediction"]
        inside = sum(1 / 1.5 <= x <= 1.5 for x in pred)
        print(f"{fam}: " + "; ".join(parts) + f"; prediction within 1.5x on {inside}/{len(pred)}")


def cost(args: argparse.Namespace) -> None:
    """A plain-frame plan's cost per sample against Mitsuba's `path`: the planner's primal passes (what
    ``--seconds T --gradients none`` and a pilot's ``primal`` choice render: renderer.planner.render_planned with the
    fixed plan ``primal``, passes split by MAX_LANES_PER_PASS, added into the frame's sums, the frame assembled),
    ``render --no-gradients`` (render_frame) beside them, and `path` (mi.render) at the same scene, size, spp, max
    depth and box filter; interleaved rounds (as benchmarks/bench_render.py's), CPU time of every thread (wall
    time beside it). Two figures: a whole frame of ``--spp`` samples (per-frame costs included: reading the sums back,
    assembling the frame), and the marginal cost of a sample, from frames of ``--spp`` and twice as many (what a
    budget's further samples cost; the issue's "cost per sample")."""
    print("| scene | size | spp | max depth | runs | path wall / CPU (s) | planner wall / CPU (s) | "
          "planner / path: frame (wall) | frame (CPU) | marginal sample (CPU) | --no-gradients / path: frame (CPU) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for scene in args.scenes.split(","):
        for size in args.sizes.split(","):
            cost_row(scene, size, args.spp, args.repeats)
    print(f"\nload (1-minute average) at the end: {os.getloadavg()[0]:.2f} (2 cores)")


def cost_row(scene: str, size: str, spp: int, repeats: int) -> None:
    import mitsuba as mi
    import numpy as np

    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.planner import FixedChoice, render_planned
    from gradsep.renderer.plans import plan_named
    from gradsep.renderer.render import plan_layers, render_frame
    from gradsep.renderer.scene import load_scene

    w, _, h = size.partition("x")
    loaded = load_scene(scene, width=int(w), height=int(h or w))  # the box filter, as every gradsep render
    layers, _ = plan_layers(("direct", "indirect"), loaded.max_depth)
    integrator = mi.load_dict({"type": "path", "max_depth": loaded.max_depth, "rr_depth": loaded.rr_depth})

    def path(n: int):
        return lambda: np.array(mi.render(loaded.scene, integrator=integrator, spp=n, seed=1))

    def planner(n: int):
        return lambda: render_planned(loaded, layers, FixedChoice(plan_named("primal")), FrameBudget(spp=n), seed=1)

    runs = {"path": path(spp), "path2": path(2 * spp), "planner": planner(spp), "planner2": planner(2 * spp),
            "no-gradients": lambda: render_frame(loaded, spp=spp, seed=1, layers=layers, gradients=False)}
    for run in runs.values():  # warm-up: kernels compiled or loaded
        run()
    wall: dict[str, list[float]] = {k: [] for k in runs}
    cpu: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(repeats):
        for k, run in runs.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            run()
            wall[k].append(time.perf_counter() - start)
            cpu[k].append(time.process_time() - start_cpu)
    med = {k: statistics.median(v) for k, v in wall.items()}
    cmed = {k: statistics.median(v) for k, v in cpu.items()}
    # medians of per-round ratios: each round's runs are back to back, so a load change between rounds cancels
    ratio = {k: statistics.median(c / b for c, b in zip(cpu[k], cpu["path"], strict=True)) for k in runs}
    marginal = statistics.median((p2 - p1) / (q2 - q1) for p1, p2, q1, q2 in
                                 zip(cpu["planner"], cpu["planner2"], cpu["path"], cpu["path2"], strict=True))
    print(f"| {scene} | {size} | {spp} | {loaded.max_depth} | {repeats} | {med['path']:.3f} / {cmed['path']:.3f} | "
          f"{med['planner']:.3f} / {cmed['planner']:.3f} | {med['planner'] / med['path']:.3f} | "
          f"{ratio['planner']:.3f} | {marginal:.3f} | {ratio['no-gradients']:.3f} |", flush=True)


def rescore(args: argparse.Namespace) -> None:
    """Reconstruct ``validate``'s cached frames again with today's code (``--setting`` for the frames with
    gradients) against the same references, and print, per family and pipeline, today's RelMSE over the recorded
    one (geometric mean, range) and today's ratio to the best fixed pipeline of each (scene, seed). The frames are
    not rendered again: the same samples at the same wall time, only the reconstruction is today's. With
    ``--against OTHER`` (another ``validate`` cache of the same scenes, budgets, seeds and references: frames
    rendered by other code), both caches' frames are reconstructed with today's code and the RelMSE of this cache's
    frames over the other's is printed per family and pipeline: what the renderer's change did at equal time."""
    cache = Path(args.cache).expanduser()
    rows: dict[str, dict] = json.loads((cache / "validate.json").read_text())
    today = _score_today(cache, rows, args)

    def geo(values: list[float]) -> float:
        return math.exp(sum(map(math.log, values)) / len(values))

    fixed = ("primal", "direct-alternate", "all", "primal-sum")
    print(f"setting for frames with gradients: {args.setting or 'the oidn method default'}; {len(today)} frames")
    print("| family | pipeline | today / recorded RelMSE | range | today / best fixed | worst |")
    print("|---|---|---:|---:|---:|---:|")
    groups: dict[tuple[str, str], dict[str, float]] = {}
    for key, value in today.items():
        scene, _, seed, plan = key.split("|")
        groups.setdefault((scene, seed), {})[plan] = value
    for fam in sorted({family(k.split("|")[0]) for k in today}):
        for plan in PLANS:
            change = [today[k] / rows[k]["relmse"] for k in today
                      if k.endswith("|" + plan) and family(k.split("|")[0]) == fam and rows[k]["relmse"] > 0]
            best = [g[plan] / min(g[f] for f in fixed) for (scene, _), g in groups.items()
                    if family(scene) == fam and plan in g and all(f in g for f in fixed)]
            if change and best:
                print(f"| {fam} | {plan} | {geo(change):.2f} | {min(change):.2f}-{max(change):.2f} | "
                      f"{geo(best):.2f} | {max(best):.1f} |")
    if not args.against:
        return
    other_cache = Path(args.against).expanduser()
    other_rows: dict[str, dict] = json.loads((other_cache / "validate.json").read_text())
    other = _score_today(other_cache, {k: v for k, v in other_rows.items() if k in today}, args)
    print(f"\nthis cache's frames over {other_cache}'s, both reconstructed today ({len(other)} pairs)\n")
    print("| family | pipeline | RelMSE ratio, geometric mean | range | frames |")
    print("|---|---|---:|---:|---:|")
    for fam in sorted({family(k.split("|")[0]) for k in other}):
        for plan in PLANS:
            ratio = [today[k] / other[k] for k in other if k.endswith("|" + plan)
                     and family(k.split("|")[0]) == fam and today[k] > 0 and other[k] > 0]
            if ratio:
                print(f"| {fam} | {plan} | {geo(ratio):.3f} | {min(ratio):.3f}-{max(ratio):.2f} | {len(ratio)} |")


def predict(args: argparse.Namespace) -> None:
    """The error estimate a farm reads: ``--plan`` (``auto``) frames rendered with ``--seconds T`` (cached), each
    frame's ``gradsep.predicted_relmse`` (the frame's own check where it ran: renderer/check.py) and the
    checkpoint's prediction for the chosen plan (``gradsep.plan_candidates``) against the RelMSE measured with two
    references, and how many of each are within 1.5x."""
    cache = Path(args.cache).expanduser()
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / "predict.json"
    rows: dict[str, dict] = json.loads(path.read_text()) if path.exists() else {}
    scenes = args.scenes.split(",")
    for seed in [int(s) for s in args.seeds.split(",")]:
        for scene in scenes:
            key = f"{scene}|{args.seconds:g}|{seed}" + ("" if args.plan == "auto" else f"|{args.plan}")
            out = cache / f"{args.plan}-{scene.replace(':', '_')}-{args.size}-{args.seconds:g}-{seed}.exr"
            if key not in rows or not out.exists():
                shared = ["--plan-cache", str(Path(args.plan_cache).expanduser())] if args.plan_cache else []
                wall, _ = gradsep("render", scene, "--width", str(args.size), "--height", str(args.size), "--seconds",
                                  f"{args.seconds:g}", "--seed", str(seed), *PLANS[args.plan], *shared, "-o", str(out))
                meta = header(out)
                pilot = dict(kv.split("=") for kv in meta.get("gradsep.plan_candidates", "").split(",") if kv)
                rows[key] = {"scene": scene, "seed": seed, "wall": wall, "file": out.name,
                             "plan": meta.get("gradsep.plan"), "spp": int(meta["gradsep.spp"]),
                             "predicted": float(meta.get("gradsep.predicted_relmse", "nan")),
                             "from": meta.get("gradsep.predicted_from"),
                             "pilot": float(pilot.get(meta.get("gradsep.plan", ""), "nan"))}
                path.write_text(json.dumps(rows, indent=1))
            row = rows[key]
            if "relmse_se" not in row or row.get("ref_spp") != args.ref_spp:
                refs = [reference(scene, args.size, args.ref_spp, s, cache, render=not args.no_references)
                        for s in (1, 2)]
                if None in refs:
                    continue
                row.update(measurement(cache / row["file"], tuple(refs)), ref_spp=args.ref_spp)  # type: ignore[arg-type]
                row.update(_setting_choice(cache / row["file"], tuple(refs)))  # type: ignore[arg-type]
                path.write_text(json.dumps(rows, indent=1))
            print(f"{key}: {row['wall']:.1f} s, {row['spp']} spp, plan {row['plan']}, predicted "
                  f"{row['predicted']:.3g} ({row['from']}), pilot {row['pilot']:.3g}, measured "
                  f"{row.get('relmse', math.nan):.3g}", flush=True)
    scored = [r for k, r in rows.items() if "relmse_se" in r and r["relmse"] > 0 and r["scene"] in scenes
              and r.get("ref_spp") == args.ref_spp and (k.split("|")[3:] or ["auto"])[0] == args.plan]
    print(f"\n| family | frames | frame's estimate / measured: within 1.5x | median | checkpoint's / measured: "
          f"within 1.5x | median | measured: median standard error | {args.ref_spp}-spp references' floor / "
          "measured, median |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for fam in sorted({family(r["scene"]) for r in scored}):
        rs = [r for r in scored if family(r["scene"]) == fam]
        cols = []
        for name in ("predicted", "pilot"):
            ratios = sorted(r[name] / r["relmse"] for r in rs if math.isfinite(r[name]))
            inside = sum(1 / 1.5 <= x <= 1.5 for x in ratios)
            cols.append(f"{inside}/{len(ratios)} | {ratios[len(ratios) // 2]:.2f}" if ratios else "- | -")
        cols.append(f"{statistics.median(r['relmse_se'] / r['relmse'] for r in rs):.0%}")
        cols.append(f"{statistics.median(r['floor'] / r['relmse'] for r in rs):.2g}")
        print(f"| {fam} | {len(rs)} | " + " | ".join(cols) + " |")
    _against_fixed(rows, scenes, args)
    chose = [r for r in scored if r.get("by_setting")]
    if chose:
        print("\nOIDN setting, RelMSE over the better of raw-fast and prefiltered-high per frame (geometric mean, "
              "worst; frames where the halves compared both):\n")
        print("| family | frames | as served (the halves' choice) | the fixed rule's | always raw-fast | "
              "always prefiltered-high | the choice changed the rule's on |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for fam in sorted({family(r["scene"]) for r in chose}):
            rs = [r for r in chose if family(r["scene"]) == fam]

            def over_best(pick: Callable[[dict], str], rs: list[dict] = rs) -> str:
                v = [r["by_setting"][pick(r)] / min(r["by_setting"].values()) for r in rs]
                return f"{math.exp(sum(map(math.log, v)) / len(v)):.3f} ({max(v):.2f})"
            print(f"| {fam} | {len(rs)} | {over_best(lambda r: r['served_setting'])} | "
                  f"{over_best(lambda r: r['rule_setting'])} | {over_best(lambda r: 'raw-fast')} | "
                  f"{over_best(lambda r: 'prefiltered-high')} | "
                  f"{sum(r['served_setting'] != r['rule_setting'] for r in rs)} |")


def _against_fixed(rows: dict[str, dict], scenes: list[str], args: argparse.Namespace) -> None:
    """`auto` against each fixed plan whose frames of the same (scene, budget, seed) are in the cache, both scored
    with the same references: the equal-time ratio and what went to samples; with several fixed plans, `auto` and
    each of them against the best of them per frame (the frames that have them all)."""
    if args.plan != "auto":
        return
    autos: dict[str, dict] = {}  # auto's key -> its row
    fixed: dict[str, dict[str, dict]] = {}  # auto's key -> fixed plan -> that plan's row of the same frame
    for key, row in rows.items():
        parts = key.split("|")
        frame = "|".join(parts[:3])
        auto = rows.get(frame)
        if (len(parts) == 4 and auto and row["scene"] in scenes and float(parts[1]) == args.seconds
                and all(r.get("ref_spp") == args.ref_spp and "relmse_se" in r for r in (row, auto))):
            autos[frame] = auto
            fixed.setdefault(frame, {})[parts[3]] = row
    plans = sorted({plan for by_plan in fixed.values() for plan in by_plan})
    if not plans:
        return
    geo = statistics.geometric_mean
    print(f"\n`auto` over a fixed plan at {args.seconds:g} s, same scene and seed (geometric mean, worst):\n")
    print("| fixed plan | frames | RelMSE ratio | worst | `auto` chose it | `auto`'s spp / the plan's |")
    print("|---|---:|---:|---:|---:|---:|")
    for plan in plans:
        ps = [(autos[k], by_plan[plan]) for k, by_plan in fixed.items() if plan in by_plan]
        ratios = [a["relmse"] / f["relmse"] for a, f in ps]
        spp = statistics.median(a["spp"] / f["spp"] for a, f in ps)
        print(f"| {plan} | {len(ps)} | {geo(ratios):.2f} | {max(ratios):.2f} | "
              f"{sum(a['plan'] == plan for a, _ in ps)} | {spp:.2f} |")
    best = {k: min(r["relmse"] for r in by_plan.values()) for k, by_plan in fixed.items() if len(by_plan) == len(plans)}
    if len(plans) > 1 and best:
        ratios = [autos[k]["relmse"] / b for k, b in best.items()]
        print(f"| the best of {', '.join(plans)}, per frame | {len(ratios)} | {geo(ratios):.2f} | "
              f"{max(ratios):.2f} | – | – |")
        print("\nEach fixed plan over the best of them, per frame (geometric mean, worst):\n")
        print("| fixed plan | frames | RelMSE ratio | worst |\n|---|---:|---:|---:|")
        for plan in plans:
            rs = [fixed[k][plan]["relmse"] / b for k, b in best.items()]
            print(f"| {plan} | {len(rs)} | {geo(rs):.2f} | {max(rs):.2f} |")


def shot(args: argparse.Namespace) -> None:
    """The plan cache on a shot (`--plan-cache`, renderer/plancache.py): per scene one `auto` frame judges and
    writes the entry (seed ``--judge-seed``), then per seed, interleaved (the order alternating, so that a drift of
    the machine's speed falls on both alike), a frame that reads the entry and the fixed plan it names, each with
    ``--seconds T``. Prints the samples each got: the first frame's and a cached frame's over the fixed plan's of
    the same seed (medians). A cached frame renders the fixed plan's passes, so at equal samples its RelMSE is that
    plan's; what it saves is the checkpoint."""
    cache = Path(args.cache).expanduser()
    plans = cache / "plans"
    plans.mkdir(parents=True, exist_ok=True)
    common = ["--width", str(args.size), "--height", str(args.size), "--seconds", f"{args.seconds:g}"]

    def render(scene: str, seed: int, extra: list[str]) -> dict[str, str]:
        out = cache / "shot.exr"
        gradsep("render", scene, *common, "--seed", str(seed), *extra, "-o", str(out))
        return header(out)

    print("| scene | plan | first frame's spp / the plan's | cached frames' spp / the plan's (median) | seeds |")
    print("|---|---|---:|---:|---:|")
    firsts, cached = [], []
    seeds = [int(s) for s in args.seeds.split(",")]
    for scene in args.scenes.split(","):
        first = render(scene, args.judge_seed, ["--plan-cache", str(plans)])
        plan = first["gradsep.plan"]
        fixed_first = render(scene, args.judge_seed, PLANS[plan])
        ratios = []
        for i, seed in enumerate(seeds):
            pair = [["--plan-cache", str(plans)], PLANS[plan]]
            got = [render(scene, seed, extra) for extra in (pair if i % 2 == 0 else pair[::-1])]
            reads, fixed = got if i % 2 == 0 else got[::-1]
            assert reads.get("gradsep.plan_cache", "").startswith("read"), reads.get("gradsep.plan_cache")
            ratios.append(int(reads["gradsep.spp"]) / int(fixed["gradsep.spp"]))
        firsts.append(int(first["gradsep.spp"]) / int(fixed_first["gradsep.spp"]))
        cached.append(statistics.median(ratios))
        print(f"| {scene} | {plan} | {firsts[-1]:.2f} | {cached[-1]:.2f} ({min(ratios):.2f}-{max(ratios):.2f}) | "
              f"{len(seeds)} |", flush=True)
    print(f"| all | | {statistics.median(firsts):.2f} | {statistics.median(cached):.2f} | |")


def choose(args: argparse.Namespace) -> None:
    """The OIDN setting the frame's halves choose (renderer/check.py) against the better one measured: each scene
    rendered with ``--plan`` to ``--spp`` samples in ~24 passes dealt into the check's groups, its halves compared
    with raw-fast and prefiltered-high, then the whole frame reconstructed with both and scored against two
    references. In one process, at a fixed sample count (the choice, not the budget, is measured here)."""
    from gradsep.model.header_keys import OIDN_SETTING_KEY
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.reconstruct import reconstruct
    from gradsep.renderer.check import check_frame
    from gradsep.renderer.passes import Passes, as_frame
    from gradsep.renderer.plans import plan_named
    from gradsep.renderer.reference import load_reference
    from gradsep.renderer.scene import load_scene

    cache = Path(args.cache).expanduser()
    cache.mkdir(parents=True, exist_ok=True)
    c = plan_named(args.plan)
    method = "oidn" if c.gradients == "none" else "oidn-l1"
    settings = ("raw-fast", "prefiltered-high")

    def served(setting: str) -> Callable:
        def run(frame):  # noqa: ANN001, ANN202
            frame.metadata = {OIDN_SETTING_KEY: setting}
            return reconstruct(frame, method).image
        return run

    print("| scene | plan | spp | chosen | better measured | prefiltered-high / raw-fast measured | "
          "paired difference (prefiltered-high - raw-fast) / its standard error |")
    print("|---|---|---:|---|---|---:|---:|")
    hits, ratios = 0, []
    against_default: dict[str, list[float]] = {}  # per family: the chosen setting's RelMSE over raw-fast's
    scenes = args.scenes.split(",")
    for scene in scenes:
        refs = [reference(scene, args.size, args.ref_spp, s, cache, render=not args.no_references) for s in (1, 2)]
        if None in refs:
            continue
        r1, r2 = (load_reference(str(p)).total for p in refs)
        loaded = load_scene(scene, width=args.size, height=args.size)
        passes = Passes(loaded, ("direct", "indirect"), args.seed)
        passes.start_split()
        per = max(1, args.spp // 24)
        while passes.spp < args.spp:
            passes.run(c, min(per, args.spp - passes.spp))
        result = check_frame(passes.halves(c), passes.spp, 0.5, {s: served(s) for s in settings})  # type: ignore[arg-type]
        frame = as_frame(passes.frame_result(c))
        measured = {}
        for setting in settings:
            frame.metadata = {OIDN_SETTING_KEY: setting}
            measured[setting] = relmse_unbiased(reconstruct(frame, method).image, r1, r2)
        best = min(measured, key=measured.__getitem__)
        hits += result.chosen == best
        ratios.append(measured[result.chosen] / measured[best])
        against_default.setdefault(family(scene), []).append(measured[result.chosen] / measured["raw-fast"])
        d, se = result.differences["prefiltered-high"]
        print(f"| {scene} | {args.plan} | {passes.spp} | {result.chosen} | {best} | "
              f"{measured['prefiltered-high'] / measured['raw-fast']:.3f} | {d / se:.1f} |", flush=True)
    if ratios:
        geo = math.exp(sum(map(math.log, ratios)) / len(ratios))
        print(f"\nchosen = better on {hits}/{len(ratios)}; chosen / better: geometric mean {geo:.3f}, worst "
              f"{max(ratios):.3f}")
        for fam, v in against_default.items():
            print(f"{fam}: chosen / raw-fast geometric mean {math.exp(sum(map(math.log, v)) / len(v)):.3f} "
                  f"({min(v):.3f}-{max(v):.3f}), {len(v)} frames")


def _setting_choice(frame_path: Path, refs: tuple[Path, Path]) -> dict:
    """The frame's RelMSE with each OIDN setting its check compared (``$GRADSEP_OIDN_SETTING`` forcing each), the
    setting it is served with, and the fixed rule's (the check's first option): {} where it compared none."""
    from gradsep.model.header_keys import CHECK_KEY, OIDN_SETTING_KEY
    from gradsep.model.oidn import METHOD_SETTING, SETTING_ENV

    meta = header(frame_path)
    figures = json.loads(meta.get(CHECK_KEY) or "{}")
    if "options" not in figures:
        return {}
    by_setting = {}
    for setting in figures["options"]:
        os.environ[SETTING_ENV] = setting
        try:
            by_setting[setting] = measured_relmse(frame_path, refs)
        finally:
            os.environ.pop(SETTING_ENV, None)
    return {"by_setting": by_setting, "rule_setting": next(iter(figures["options"])),
            "served_setting": meta.get(OIDN_SETTING_KEY) or METHOD_SETTING}


def _score_today(cache: Path, rows: dict[str, dict], args: argparse.Namespace) -> dict[str, float]:
    """Each scored row's frame in ``cache`` reconstructed with today's code (``--setting`` for the frames with
    gradients) and its RelMSE against the cache's references, by row key."""
    from gradsep.model.oidn import SETTING_ENV

    today: dict[str, float] = {}
    for key, row in rows.items():
        refs = tuple(cache / f"ref-{row['scene'].replace(':', '_')}-{args.size}-{args.ref_spp}-{s}.exr"
                     for s in (1, 2))
        if "relmse" not in row or not (cache / row["file"]).exists() or not all(p.exists() for p in refs):
            continue
        plain = row["plan"] in ("primal", "primal-sum") or (row["plan"] == "auto" and row.get("chosen") == "primal")
        if args.setting and not plain:
            os.environ[SETTING_ENV] = args.setting
        else:
            os.environ.pop(SETTING_ENV, None)
        today[key] = measured_relmse(cache / row["file"], refs)
    return today


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    t = sub.add_parser("timing")
    t.add_argument("--scenes", default="procedural:93101")
    t.add_argument("--sizes", default="320x240,1280x720")
    t.add_argument("--seconds", default="5,10,20")
    t.add_argument("--plans", default="auto,all")
    t.add_argument("--repeats", type=int, default=3)
    t.add_argument("--checkouts", default="", help="source trees to time side by side (default: this one)")
    t.add_argument("--cache", default=str(Path.home() / ".cache/gradsep/planner-bench"))
    v = sub.add_parser("validate")
    v.add_argument("--scenes", default=",".join([f"procedural:{s}" for s in range(93201, 93209)]
                                                + [f"procedural:studio:{s}" for s in range(93201, 93209)]))
    v.add_argument("--size", type=int, default=192)
    v.add_argument("--seconds", default="20")
    v.add_argument("--seeds", type=int, default=3, help="render seeds per (scene, budget)")
    v.add_argument("--ref-spp", type=int, default=4096)
    v.add_argument("--no-references", action="store_true",
                   help="do not render missing references (score only the scenes whose references exist)")
    v.add_argument("--cache", default=str(Path.home() / ".cache/gradsep/planner-bench"))
    c = sub.add_parser("cost")
    c.add_argument("--scenes", default="procedural:93201,procedural:studio:93201")
    c.add_argument("--sizes", default="320x240,1280x720")
    c.add_argument("--spp", type=int, default=16)
    c.add_argument("--repeats", type=int, default=5)
    pr = sub.add_parser("predict")
    pr.add_argument("--scenes", default=",".join(f"procedural:{s}" for s in range(93201, 93209)))
    pr.add_argument("--size", type=int, default=192)
    pr.add_argument("--seconds", type=float, default=20.0)
    pr.add_argument("--plan", default="auto", choices=sorted(PLANS), help="a fixed plan's frames carry the estimate "
                    "where their check fits the budget (no pilot: its prediction column is empty)")
    pr.add_argument("--seeds", default="10,11")
    pr.add_argument("--ref-spp", type=int, default=1024)
    pr.add_argument("--no-references", action="store_true", help="score only the frames whose references exist")
    pr.add_argument("--plan-cache", default=None, metavar="DIR",
                    help="render `auto` frames with `--plan-cache DIR` (a shot's frames: the first seed's judge)")
    pr.add_argument("--cache", default=str(Path.home() / ".cache/gradsep/planner-bench"))
    ch = sub.add_parser("choose")
    ch.add_argument("--scenes", default=",".join(f"procedural:{s}" for s in range(93201, 93209)))
    ch.add_argument("--plan", default="primal")
    ch.add_argument("--spp", type=int, default=960)
    ch.add_argument("--size", type=int, default=192)
    ch.add_argument("--seed", type=int, default=31)
    ch.add_argument("--ref-spp", type=int, default=1024)
    ch.add_argument("--no-references", action="store_true", help="skip the scenes whose references are missing")
    ch.add_argument("--cache", default=str(Path.home() / ".cache/gradsep/planner-bench"))
    sh = sub.add_parser("shot")
    sh.add_argument("--scenes", default=",".join(f"procedural:{s}" for s in range(93301, 93305)))
    sh.add_argument("--size", type=int, default=192)
    sh.add_argument("--seconds", type=float, default=20.0)
    sh.add_argument("--judge-seed", type=int, default=40, help="the seed of the frame that judges and writes")
    sh.add_argument("--seeds", default="61,62,63", help="seeds of the frames that read the entry")
    sh.add_argument("--cache", default=str(Path.home() / ".cache/gradsep/planner-bench-shot"))
    r = sub.add_parser("rescore")
    r.add_argument("--setting", default="", help="OIDN setting for the frames with gradients (e.g. "
                   "prefiltered-high: what a --seconds budget asks for); default: the oidn method's")
    r.add_argument("--size", type=int, default=192, help="validate's --size")
    r.add_argument("--ref-spp", type=int, default=1024, help="validate's --ref-spp")
    r.add_argument("--cache", default=str(Path.home() / ".cache/gradsep/planner-bench"))
    r.add_argument("--against", default="", help="another validate cache (same scenes, seeds, references): print "
                   "this cache's RelMSE over its, both reconstructed today")
    args = parser.parse_args(argv)
    {"timing": timing, "validate": validate, "cost": cost, "rescore": rescore,
     "predict": predict, "choose": choose, "shot": shot}[args.what](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
