"""Held-out study behind the ``oidn-l1`` method (model/refine.py, docs/network.md "The oidn-l1 method"): does an
L1 gradient-domain solve with OIDN's image as its data term improve on OIDN, for which layers, at which α, with
how many IRLS passes, and at what cost.

    python benchmarks/study_refine.py render --seeds 81001-81008 --spp 1,4,16,64   # frames + references (cached)
    python benchmarks/study_refine.py error                                      # the tables (cached frames)
    python benchmarks/study_refine.py error --family speed                       # cheaper solves of the same
    python benchmarks/study_refine.py error --family tolerance                   # per-pass CG tolerance rules
    python benchmarks/study_refine.py convergence                                # CG rules vs the converged solve
    python benchmarks/study_refine.py time                                       # 1280x720 cost of the refinement

Scenes: procedural seeds that are neither evaluation scenes (90001, 90002) nor in the training range; nothing
here reads cbox or the teapot. Frames: G-PT at 320x240 (seed 7), each spp. References: two independent Mitsuba
``path`` renders (seeds 1 and 2, ``--ref-spp`` each). Error: RelMSE of the summed layers with the references'
noise removed (model.metrics.relmse_unbiased), as a ratio to ``oidn`` at the same OIDN setting; geometric means.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from unittest import mock

import numpy as np

SIZE = (320, 240)
DEFAULT_CACHE = Path(os.environ.get("GRADSEP_CACHE", Path.home() / ".cache" / "gradsep")) / "refine-study"
ALPHAS = (0.5, 1.0, 2.0)
PASSES = (2, 4, 8, 20)


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return out


def render(seeds: list[int], spps: list[int], ref_spp: int, cache: Path, family: str = "mixed") -> None:
    """G-PT frames (seed 7) and two independent ``path`` references of procedural:[FAMILY:]SEED into
    ``cache/procedural-[FAMILY-]SEED``."""
    from gradsep.model.frame import write_frame
    from gradsep.renderer.procedural import ProceduralSpec
    from gradsep.renderer.reference import render_loaded
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    for seed in seeds:
        spec = str(ProceduralSpec(seed, family))
        folder = cache / spec.replace(":", "-")
        folder.mkdir(parents=True, exist_ok=True)
        loaded = load_scene(spec, width=SIZE[0], height=SIZE[1])
        for spp in spps:
            path = folder / f"gpt-{spp}.exr"
            if not path.is_file():
                write_frame(path, render_frame(loaded, spp=spp, seed=7))
        for ref_seed in (1, 2):
            path = folder / f"ref-{ref_seed}-{ref_spp}.npz"
            if not path.is_file():
                ref = render_loaded(loaded, spp=ref_spp, seed=ref_seed, tile_spp=None, progress=False)
                np.savez(path, **{k: np.asarray(v, np.float32) for k, v in ref.images().items()})
        print(f"{spec}: cached in {folder}", flush=True)


def _solver(alpha: float, passes: int, layers: frozenset[str], **solver) -> Callable:
    """f(name, denoised, layer): model.refine.refine_layer with its module settings overridden for the call;
    ``solver``: REFINE_CG_STEPS / REFINE_WARM_START / REFINE_PRECONDITIONER (lower-case keys without REFINE_)."""
    from gradsep.model import refine

    if "cg_steps" in solver and "cg_tolerance" not in solver:  # a fixed budget: no tolerance rule
        solver["cg_tolerance"] = None
    settings = {"REFINE_ITERATIONS": passes, "REFINED_LAYERS": layers,
                **{f"REFINE_{k.upper()}": v for k, v in solver.items()}}

    def run(name, denoised, layer):
        if name not in layers:
            return denoised
        with mock.patch.multiple(refine, **settings):
            return refine.refine_layer(name, denoised, layer, alpha)
    return run


def _variants(setting: str) -> dict[str, Callable]:
    """name -> f(name, denoised, layer) for one layer; 'oidn' is the identity."""
    from gradsep.model import refine

    solve = _solver
    direct, both = frozenset({"direct"}), frozenset({"direct", "indirect"})
    out: dict[str, Callable] = {"oidn": lambda name, denoised, layer: denoised}
    out["oidn-l1 (shipped)"] = solve(refine.REFINE_ALPHA, refine.REFINE_ITERATIONS, refine.REFINED_LAYERS)
    for alpha in ALPHAS:
        out[f"direct, a={alpha:g}"] = solve(alpha, refine.REFINE_ITERATIONS, direct)
        out[f"both layers, a={alpha:g}"] = solve(alpha, refine.REFINE_ITERATIONS, both)
    for passes in PASSES:
        out[f"direct, a={refine.REFINE_ALPHA:g}, {passes} passes"] = solve(refine.REFINE_ALPHA, passes, direct)
    return out


def _speed_variants(setting: str) -> dict[str, Callable]:
    """Cheaper solves of the shipped refinement (issue 15): a warm start from OIDN's image instead of the L2
    solve, fewer IRLS passes, fewer CG steps per pass, the multigrid preconditioner."""
    from gradsep.model import refine

    solve = _solver
    a, direct = refine.REFINE_ALPHA, refine.REFINED_LAYERS
    out: dict[str, Callable] = {"oidn": lambda name, denoised, layer: denoised}
    out["shipped"] = solve(a, refine.REFINE_ITERATIONS, direct)
    out["L2 start, 8 passes, 4 dct CG (before issue 15)"] = solve(a, 8, direct, cg_steps=4, preconditioner="dct")
    for passes in (3, 5, 8):
        out[f"warm start, {passes} passes, 4 dct CG"] = solve(a, passes, direct, warm_start=True, cg_steps=4,
                                                             preconditioner="dct")
    for passes, cg in ((5, 4), (6, 3)):
        out[f"L2 start, {passes} passes, {cg} dct CG"] = solve(a, passes, direct, cg_steps=cg, preconditioner="dct")
    for passes, cg in ((8, 4), (8, 2), (8, 1), (6, 2), (5, 2), (6, 1)):
        out[f"L2 start, {passes} passes, {cg} mg CG"] = solve(a, passes, direct, cg_steps=cg, preconditioner="mg")
    return out


def _tolerance_variants(setting: str) -> dict[str, Callable]:
    """Issue 14's convergence rule for the default refinement: per IRLS pass, V-cycle-preconditioned CG until the
    relative residual is below a tolerance, with a cap on the steps; against the fixed budgets."""
    from gradsep.model import refine

    solve = _solver
    a, direct, passes = refine.REFINE_ALPHA, refine.REFINED_LAYERS, refine.REFINE_ITERATIONS
    out: dict[str, Callable] = {"oidn": lambda name, denoised, layer: denoised}
    out["shipped"] = solve(a, passes, direct)
    for cg in (2, 4, 8):
        out[f"fixed {cg} mg CG"] = solve(a, passes, direct, cg_steps=cg, preconditioner="mg")
    for tol in (0.2, 0.1, 0.05, 0.02):
        for cap in (4, 8):
            out[f"mg CG to {tol:g}, at most {cap}"] = solve(a, passes, direct, preconditioner="mg", cg_tolerance=tol,
                                                           max_cg_steps=cap)
    return out


FAMILIES = {"design": "_variants", "speed": "_speed_variants", "tolerance": "_tolerance_variants"}


def error(cache: Path, settings: list[str], family: str = "design") -> None:
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.oidn import Denoiser

    scores: dict[tuple[str, str], list[float]] = {}
    seconds: dict[tuple[str, str], list[float]] = {}
    cases = 0
    for folder in sorted(p for p in cache.glob("procedural-*") if p.is_dir()):
        refs = sorted(folder.glob("ref-*.npz"))
        if len(refs) < 2:
            continue
        r1, r2 = (np.load(p) for p in refs[:2])
        for frame_path in sorted(folder.glob("gpt-*.exr"), key=lambda p: int(p.stem.split("-")[1])):
            frame = read_frame(str(frame_path))
            cases += 1
            for setting in settings:
                den = Denoiser(setting)
                aux = den.prefilter(frame.features) if frame.features is not None else None
                denoised = {n: den.denoise(layer.base, aux) for n, layer in frame.layers.items()}
                base = None
                variants = globals()[FAMILIES[family]](setting)
                for variant, run in variants.items():
                    start = time.perf_counter()
                    total = sum(run(n, denoised[n], layer) for n, layer in frame.layers.items())
                    seconds.setdefault((setting, variant), []).append(time.perf_counter() - start)
                    score = relmse_unbiased(total, r1["total"], r2["total"])
                    base = score if variant == "oidn" else base
                    scores.setdefault((setting, variant), []).append(score / base)
                den.close()
            print(f"{folder.name} {frame_path.stem}: done", flush=True)
    print(f"\n{cases} frames; RelMSE / oidn's at the same OIDN setting (geometric mean, worst, cases better)\n")
    print("| OIDN setting | variant | geo mean | worst | better than oidn | s per frame (320x240, mean) |")
    print("|---|---|---:|---:|---:|---:|")
    for (setting, variant), ratios in scores.items():
        if variant == "oidn":
            continue
        geo = math.exp(sum(math.log(r) for r in ratios) / len(ratios))
        better = sum(r < 1 for r in ratios)
        secs = statistics.mean(seconds[(setting, variant)])
        print(f"| {setting} | {variant} | {geo:.3f} | {max(ratios):.2f} | {better}/{len(ratios)} | {secs:.3f} |")


CONVERGENCE_RULES = ((2, None), (4, None), (8, 0.2), (8, 0.1), (8, 0.05), (8, 0.02), (16, 0.05))


def convergence(cache: Path, setting: str, rules=CONVERGENCE_RULES) -> None:
    """How far each CG rule of the default refinement leaves the direct layer from the *converged* IRLS of the same
    passes, against that converged result's own error: RelMSE(rule, converged) / RelMSE_unbiased(converged, truth)
    per frame. A rule whose ratio is small on every frame has converged where it matters; the mean CG steps per
    pass are its cost. ``rules``: (at most / fixed steps, tolerance or None for the fixed budget)."""
    from gradsep.model import refine
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse, relmse_unbiased
    from gradsep.model.oidn import Denoiser

    steps: list[int] = []
    real_solve = refine.solve_l1

    def counting_solve(*args, **kwargs):
        image, stats = real_solve(*args, **kwargs)
        steps.append(stats.total_cg_iterations)
        return image, stats

    refine.solve_l1 = counting_solve
    den = Denoiser(setting)
    rows: dict[str, list[tuple[float, float]]] = {}
    try:
        for folder in sorted(p for p in cache.glob("procedural-*") if p.is_dir()):
            r1, r2 = (np.load(p) for p in sorted(folder.glob("ref-*.npz"))[:2])
            for frame_path in sorted(folder.glob("gpt-*.exr"), key=lambda p: int(p.stem.split("-")[1])):
                frame = read_frame(str(frame_path))
                layer = frame.layers["direct"]
                aux = den.prefilter(frame.features) if frame.features is not None else None
                prior = den.denoise(layer.base, aux)
                exact = refine.refine_layer("direct", prior, layer, preconditioner="mg", cg_steps=40,
                                            cg_tolerance=1e-5)
                floor = relmse_unbiased(exact, r1["direct"], r2["direct"])
                line = f"{folder.name} {frame_path.stem}: converged {floor:.5f}"
                for cap, tol in rules:
                    steps.clear()
                    img = refine.refine_layer("direct", prior, layer, preconditioner="mg", cg_steps=cap,
                                              cg_tolerance=tol)
                    ratio = relmse(img, exact) / max(floor, 1e-12)
                    rows.setdefault(f"{cap}:{tol}", []).append((ratio, steps[0] / (refine.REFINE_ITERATIONS - 1)))
                    line += f" | {cap}:{tol} {ratio:.3f}"
                print(line, flush=True)
    finally:
        refine.solve_l1 = real_solve
        den.close()
    print("\n| rule (steps:tolerance) | mean ratio | worst ratio | mean CG steps per pass |")
    print("|---|---:|---:|---:|")
    for rule, values in rows.items():
        ratios, per_pass = zip(*values, strict=True)
        print(f"| {rule} | {statistics.mean(ratios):.3f} | {max(ratios):.3f} | {statistics.mean(per_pass):.2f} |")


def timing(width: int, height: int, repeats: int, variants: list[str] | None = None) -> None:
    """The refinement of one 1280x720 direct layer (synthetic noisy HDR data: the solve's cost does not depend
    on content), medians of ``repeats``; ``variants`` ("PASSES:CG:PRECONDITIONER[:warm]", e.g. "8:2:mg") are
    timed in the same run, interleaved with the shipped setting."""
    from gradsep.model import refine

    settings = [None, *(variants or [])]
    runs = {v: [] for v in settings}
    for _ in range(repeats):
        for v in settings:
            runs[v].append(_time_refinement(width, height, v))
    for v in settings:
        times = runs[v]
        label = v or (f"shipped {refine.REFINE_ITERATIONS}:{refine.REFINE_CG_STEPS}:{refine.REFINE_PRECONDITIONER}"
                      f"{':warm' if refine.REFINE_WARM_START else ''}")
        print(f"refinement of one {width}x{height} direct layer, {label}: median {statistics.median(times):.3f} s "
              f"(min {min(times):.3f}, {repeats} repeats), load {os.getloadavg()[0]:.2f}")


def _time_refinement(width: int, height: int, variant: str | None) -> float:
    from gradsep.model.frame import Layer, forward_differences
    from gradsep.model.refine import REFINED_LAYERS

    rng = np.random.default_rng(0)
    truth = rng.uniform(0.1, 2.0, (height // 16 + 1, width // 16 + 1, 3)).astype(np.float32)
    truth = np.repeat(np.repeat(truth, 16, 0), 16, 1)[:height, :width]
    dx, dy = forward_differences(truth)
    noise = lambda: rng.normal(0, 0.1, truth.shape).astype(np.float32)  # noqa: E731
    layer = Layer(truth + noise(), dx + noise(), dy + noise())
    if variant is None:
        from gradsep.model.refine import REFINE_ALPHA, REFINE_ITERATIONS

        run = _solver(REFINE_ALPHA, REFINE_ITERATIONS, REFINED_LAYERS)
    else:
        passes, cg, preconditioner, *warm = variant.split(":")
        run = _solver(1.0, int(passes), REFINED_LAYERS, cg_steps=int(cg), preconditioner=preconditioner,
                      warm_start=bool(warm))
    run("direct", truth, layer)  # warm-up (numba/FFT plans)
    start = time.perf_counter()
    run("direct", truth, layer)
    return time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render")
    r.add_argument("--seeds", default="81001-81008")
    r.add_argument("--spp", default="1,4,16,64")
    r.add_argument("--ref-spp", type=int, default=1024)
    e = sub.add_parser("error")
    e.add_argument("--settings", default="raw-fast", help="comma-separated model.oidn.SETTINGS names")
    e.add_argument("--family", choices=tuple(FAMILIES), default="design",
                   help="design: alpha, layers, passes (the method's choice); speed: cheaper solves of it; "
                        "tolerance: a per-pass CG tolerance with a cap on the steps (issue 14)")
    c = sub.add_parser("convergence", help="distance of CG rules from the converged refinement (issue 14)")
    c.add_argument("--setting", default="raw-fast")
    t = sub.add_parser("time")
    t.add_argument("--width", type=int, default=1280)
    t.add_argument("--height", type=int, default=720)
    t.add_argument("--repeats", type=int, default=5)
    t.add_argument("--variants", default="", help="comma-separated PASSES:CG:PRECONDITIONER[:warm], e.g. 8:2:mg")
    args = parser.parse_args()
    if args.command == "render":
        render(_seeds(args.seeds), [int(s) for s in args.spp.split(",")], args.ref_spp, args.cache)
    elif args.command == "convergence":
        convergence(args.cache, args.setting)
    elif args.command == "error":
        error(args.cache, args.settings.split(","), args.family)
    else:
        timing(args.width, args.height, args.repeats, [v for v in args.variants.split(",") if v])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
