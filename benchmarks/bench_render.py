"""Benchmark of the G-PT renderer: cost per sample against Mitsuba's `path`, frame time, gradient quality.

    .venv/bin/python benchmarks/bench_render.py            # full run (a few minutes on 2 cores)
    .venv/bin/python benchmarks/bench_render.py --quick    # small sizes, for a smoke check
    .venv/bin/python benchmarks/bench_render.py --shift hybrid --scene procedural:3 --json out.json

Reports, for each shift (default: replay and hybrid; medians of repeats, each after a warm-up render that
compiles the kernels):

1. cost per sample: G-PT seconds / Mitsuba `path` seconds at the same scene, resolution, spp and max depth
   (both with the box filter). G-PT traces five paths per sample plus their shadow rays.
2. the time of a 1280x720, 16 spp frame (both layers, features, packing into a Frame).
3. gradient error at equal spp: mean |dx - FD(reference)| for G-PT's dx and for forward differences of G-PT's
   own primal, against a high-spp `path` reference; their ratio (and the same for dy and the medians).
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

DEFAULT_SCENE = "/work/shared/scenes/cbox/cbox.xml"


def timed(fn, repeats: int) -> tuple[float, list[float]]:
    """Median wall time of ``fn()`` over ``repeats`` runs after one warm-up (kernel compilation) run."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times


def path_image(scene, spp: int, seed: int, max_depth: int) -> np.ndarray:
    import mitsuba as mi

    integrator = mi.load_dict({"type": "path", "max_depth": max_depth})
    return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed), dtype=np.float64)


def reference(scene, spp: int, max_depth: int, chunk: int = 256) -> np.ndarray:
    """High-spp `path` image in chunks of ``chunk`` spp (distinct seeds), averaged."""
    chunks = max(1, spp // chunk)
    return np.mean([path_image(scene, chunk, 50_000 + i, max_depth) for i in range(chunks)], axis=0)


def fd(img: np.ndarray, axis: str) -> np.ndarray:
    d = np.zeros_like(img)
    if axis == "dx":
        d[:, :-1] = img[:, 1:] - img[:, :-1]
    else:
        d[:-1] = img[1:] - img[:-1]
    return d


def bench_cost(spec: str, size: int, spp: int, repeats: int, shift_name: str) -> dict:
    from renderer.gpt import GptSettings, render_gpt
    from renderer.scene import load_scene
    from renderer.shift import make_shift

    loaded = load_scene(spec, width=size, height=size)
    depth = loaded.max_depth
    settings = GptSettings(max_depth=depth, rr_depth=loaded.rr_depth, indirect=depth < 0 or depth > 2)
    shift = make_shift(shift_name)
    t_gpt, _ = timed(lambda: render_gpt(loaded.scene, shift, settings, size, size, spp, seed=1), repeats)
    t_path, _ = timed(lambda: path_image(loaded.scene, spp, 1, depth), repeats)
    return {"scene": spec, "size": size, "spp": spp, "max_depth": depth, "gpt_s": t_gpt, "path_s": t_path,
            "cost_ratio": t_gpt / t_path}


def bench_frame(spec: str, width: int, height: int, spp: int, repeats: int, shift_name: str) -> dict:
    from renderer.render import render_frame
    from renderer.scene import load_scene

    loaded = load_scene(spec, width=width, height=height)
    median, times = timed(lambda: render_frame(loaded, spp=spp, seed=2, shift=shift_name), repeats)
    return {"scene": spec, "width": width, "height": height, "spp": spp, "seconds": median, "all": times}


def bench_gradients(spec: str, size: int, spp: int, ref_spp: int, seeds: int, shift_name: str) -> dict:
    from renderer.gpt import GptSettings, render_gpt
    from renderer.scene import load_scene
    from renderer.shift import make_shift

    loaded = load_scene(spec, width=size, height=size)
    depth = loaded.max_depth
    settings = GptSettings(max_depth=depth, rr_depth=loaded.rr_depth, indirect=depth < 0 or depth > 2)
    ref = reference(loaded.scene, ref_spp, depth)
    shift = make_shift(shift_name)
    out: dict = {"scene": spec, "size": size, "spp": spp, "reference_spp": ref_spp, "seeds": seeds}
    errors: dict[str, list[float]] = {}
    for seed in range(seeds):
        res = render_gpt(loaded.scene, shift, settings, size, size, spp, seed=100 + seed)
        primal = sum(layer["base"] for layer in res.layers.values()).astype(np.float64)
        for axis in ("dx", "dy"):
            grad = sum(layer[axis] for layer in res.layers.values()).astype(np.float64)
            ref_d = fd(ref, axis)
            e_gpt, e_fd = np.abs(grad - ref_d), np.abs(fd(primal, axis) - ref_d)
            for key, value in ((f"{axis}_gpt_mean", e_gpt.mean()), (f"{axis}_fd_mean", e_fd.mean()),
                               (f"{axis}_gpt_median", np.median(e_gpt)), (f"{axis}_fd_median", np.median(e_fd))):
                errors.setdefault(key, []).append(float(value))
    for key, values in errors.items():
        out[key] = float(np.mean(values))
    for axis in ("dx", "dy"):
        out[f"{axis}_ratio_mean"] = out[f"{axis}_fd_mean"] / out[f"{axis}_gpt_mean"]
        out[f"{axis}_ratio_median"] = out[f"{axis}_fd_median"] / max(out[f"{axis}_gpt_median"], 1e-12)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=DEFAULT_SCENE, help="XML path or procedural:SEED")
    parser.add_argument("--shift", default="replay,hybrid", help="comma-separated shifts to compare")
    parser.add_argument("--quick", action="store_true", help="small sizes and few repeats (smoke check)")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--skip-frame", action="store_true", help="skip the 1280x720 frame timing")
    parser.add_argument("--json", default=None, help="also write the results to this file")
    args = parser.parse_args(argv)

    from renderer.scene import select_variant

    variant = select_variant()
    repeats = args.repeats or (2 if args.quick else 5)
    shifts = [name.strip() for name in args.shift.split(",") if name.strip()]
    results: dict = {"variant": variant, "scene": args.scene, "quick": args.quick, "shifts": {}}
    size, spp = (64, 16) if args.quick else (256, 16)
    gsize, gref, gseeds = (48, 2048, 4) if args.quick else (128, 8192, 8)
    for shift in shifts:
        out: dict = {}
        results["shifts"][shift] = out
        cost = out["cost"] = bench_cost(args.scene, size, spp, repeats, shift)
        print(f"[{shift}] cost per sample ({cost['size']}^2, {spp} spp, max_depth {cost['max_depth']}): "
              f"G-PT {cost['gpt_s']:.3f} s, path {cost['path_s']:.3f} s -> {cost['cost_ratio']:.2f}x")
        if not args.skip_frame:
            w, h = (320, 180) if args.quick else (1280, 720)
            frame = out["frame"] = bench_frame(args.scene, w, h, 16, max(1, repeats // 2), shift)
            print(f"[{shift}] frame {w}x{h} at 16 spp: {frame['seconds']:.2f} s (median of {len(frame['all'])})")
        grads = out["gradients"] = bench_gradients(args.scene, gsize, 16, gref, gseeds, shift)
        for axis in ("dx", "dy"):
            print(f"[{shift}] {axis} error at 16 spp ({gsize}^2, reference {gref} spp, {gseeds} seeds): "
                  f"mean |G-PT - ref| {grads[f'{axis}_gpt_mean']:.5f}, mean |FD(primal) - ref| "
                  f"{grads[f'{axis}_fd_mean']:.5f} -> ratio {grads[f'{axis}_ratio_mean']:.2f} "
                  f"(medians: ratio {grads[f'{axis}_ratio_median']:.2f})")
    if len(shifts) > 1 and "replay" in results["shifts"]:
        base = results["shifts"]["replay"]["gradients"]
        for shift in shifts:
            if shift == "replay":
                continue
            other = results["shifts"][shift]["gradients"]
            for axis in ("dx", "dy"):
                gain = base[f"{axis}_gpt_mean"] / other[f"{axis}_gpt_mean"]
                print(f"{shift} vs replay, {axis}: mean gradient error {gain:.2f}x lower")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
