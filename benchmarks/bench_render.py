"""Benchmark of the G-PT renderer: issue 4's numbers for both shifts on the Cornell box and procedural scenes.

    .venv/bin/python benchmarks/bench_render.py             # full run: cbox + procedural:0,1 (~10 min, 2 cores)
    .venv/bin/python benchmarks/bench_render.py --quick     # small sizes, for a smoke check (~1 min)
    .venv/bin/python benchmarks/bench_render.py --scenes procedural:3 --shifts hybrid --json out.json
    .venv/bin/python benchmarks/bench_render.py --issue16 --cache runs/refcache   # issue 16 (1 min warm, 5-8 cold)

For every scene and shift (medians of repeats, each after a warm-up render that compiles the kernels):

1. **cost per sample**: G-PT seconds / Mitsuba `path` seconds at the same scene, resolution (256^2), 16 spp and
   max depth, box filter for both; G-PT and `path` runs are interleaved so that load changes hit both alike.
   The primal-only mode (`render --no-gradients`, issue 13: at most 1.15x `path`) is timed with them
   (``--no-primal`` to skip). Wall and CPU time (all threads) are both reported: on a shared machine the CPU
   time ratio is the steadier one.
2. **gradient error at equal spp** (issue 4's metric): mean |dx - FD(reference)| (and dy) of G-PT's gradients at
   16 spp, 128^2, averaged over seeds, against forward differences of a high-spp `path` reference; the same for
   forward differences of G-PT's own primal; and the ratio replay / hybrid.
3. **what the metric can resolve**: the reference is noisy too. Its own expected error, E|FD(ref) - truth| =
   sqrt(2/pi) * sigma per pixel (sigma from the spread of the reference's chunks), is a floor under every
   estimator's measured error, so the ratio of two good estimators is compressed towards 1. Reported with it:
   the noise-corrected RMS error sqrt(MSE - Var(FD(ref))) (an unbiased estimate of the estimator's own MSE,
   since the reference is independent of it) and the estimators' own noise per layer (standard deviation over
   seeds), which needs no reference at all. The mean |err| is also split by pixel class -- geometric edges,
   texture edges, the rest (from the base path's features) -- to show where each shift's error lives.
4. optionally (``--frame``) the time of a 1280x720, 16 spp frame (both layers, features, packed into a Frame).

References are cached with ``--cache DIR`` (keyed by scene, size, depth, spp, Mitsuba version), so a re-run
costs only the G-PT renders.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

DEFAULT_SCENES = "cbox,procedural:0,procedural:1"


def resolve_scene(spec: str) -> str:
    """``cbox``/``teapot`` -> the shared file when present, else the tests' built-in stand-in; others unchanged."""
    if spec in ("cbox", "teapot"):
        from tests.renderer.scenes import resolve

        return str(resolve(spec))
    return spec


def path_image(scene, spp: int, seed: int, max_depth: int, rr_depth: int) -> np.ndarray:
    import mitsuba as mi

    integrator = mi.load_dict({"type": "path", "max_depth": max_depth, "rr_depth": rr_depth})
    return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed), dtype=np.float64)[..., :3]


def reference_chunks(loaded, spp: int, chunk: int, cache: Path | None, max_depth: int | None = None) -> np.ndarray:
    """High-spp `path` renders in independent chunks of ``chunk`` spp: (chunks, H, W, 3). ``max_depth`` 2 gives
    the direct layer (Mitsuba's convention), None the scene's depth."""
    import mitsuba as mi

    depth = loaded.max_depth if max_depth is None else max_depth
    key = hashlib.sha256(json.dumps([loaded.spec, loaded.width, loaded.height, depth, loaded.rr_depth,
                                     spp, chunk, mi.__version__]).encode()).hexdigest()[:16]
    path = cache / f"ref-{key}.npy" if cache else None
    if path is not None and path.is_file():
        return np.load(path)
    seed0 = 50_000 if max_depth is None else 70_000  # the layer references are independent of the full one
    chunks = np.stack([path_image(loaded.scene, chunk, seed0 + i, depth, loaded.rr_depth)
                       for i in range(max(2, spp // chunk))])
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, chunks)
    return chunks


def fd(img: np.ndarray, axis: str) -> np.ndarray:
    """Forward differences per the frame contract, on (..., H, W, C) stacks."""
    d = np.zeros_like(img)
    if axis == "dx":
        d[..., :, :-1, :] = img[..., :, 1:, :] - img[..., :, :-1, :]
    else:
        d[..., :-1, :, :] = img[..., 1:, :, :] - img[..., :-1, :, :]
    return d


def edge_classes(normal: np.ndarray, depth: np.ndarray, albedo: np.ndarray, axis: str) -> dict[str, np.ndarray]:
    """Pixel pairs of a forward difference by what separates the two pixels: ``geometry`` (normal or depth jump:
    silhouettes, creases), ``texture`` (albedo jump on smooth geometry) or nothing (``rest``); (H, W) masks."""
    def diff(img: np.ndarray) -> np.ndarray:
        return fd(img if img.ndim == 3 else img[..., None], axis)

    geometry = (np.abs(diff(normal)).max(-1) > 0.05) | (np.abs(diff(depth))[..., 0] > 0.03 * np.maximum(depth, 1e-3))
    texture = (np.abs(diff(albedo)).max(-1) > 0.05) & ~geometry
    return {"geometry": geometry, "texture": texture, "rest": ~geometry & ~texture}


def settings_for(loaded, offsets: str = "all", gradients: str = "all"):
    from gradsep.renderer.gpt_settings import GptSettings

    depth = loaded.max_depth
    return GptSettings(max_depth=depth, rr_depth=loaded.rr_depth, indirect=depth < 0 or depth > 2, offsets=offsets,
                       gradients=gradients)


def configuration(loaded, name: str):
    """``SHIFT`` or ``SHIFT+OPTION[+OPTION]`` -> (shift, settings). Options: an offsets mode (``hybrid+pair``: one
    axis's two offsets per sample, ``+single``: one, ``+alternate``: one per axis, neighbouring pixels paired;
    GptSettings.offsets) and/or ``direct`` (``hybrid+direct``:
    gradients of the direct layer alone, offsets traced to its vertices only; GptSettings.gradients, `gradsep
    render --gradients direct`)."""
    from gradsep.renderer.gpt_settings import GRADIENT_MODES
    from gradsep.renderer.lanes import OFFSET_MODES
    from gradsep.renderer.shift import make_shift

    shift, *options = name.split("+")
    offsets, gradients = "all", "all"
    for option in options:
        if option in OFFSET_MODES:
            offsets = option
        elif option in GRADIENT_MODES:
            gradients = option
        else:
            raise SystemExit(f"unknown configuration option {option!r} in {name!r}; expected one of "
                             f"{OFFSET_MODES + GRADIENT_MODES}")
    return make_shift(shift), settings_for(loaded, offsets, gradients)


def bench_cost(spec: str, size: int, spp: int, repeats: int, shifts: list[str]) -> dict:
    """Interleaved timings of `path`, each shift and the primal-only mode (``primal``: same layers and features,
    no offsets); medians and the ratio of medians, in wall time and in the process's CPU time (user + system of
    all of Dr.Jit's threads: on a loaded machine the wall time also measures how many cores the process got,
    the CPU time much less so)."""
    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.gpt_settings import Film
    from gradsep.renderer.scene import load_scene

    loaded = load_scene(spec, width=size, height=size)
    runs = {"path": lambda: path_image(loaded.scene, spp, 1, loaded.max_depth, loaded.rr_depth)}

    def gpt(name: str):
        shift, settings = (None, settings_for(loaded)) if name == "primal" else configuration(loaded, name)
        return lambda: render_gpt(loaded.scene, shift, settings, Film(size, size, spp, 1))

    for name in shifts:
        runs[name] = gpt(name)
    times, cpu = interleaved_rounds(runs, repeats)
    medians = {name: statistics.median(t) for name, t in times.items()}
    cpu_medians = {name: statistics.median(t) for name, t in cpu.items()}
    # the median of per-round ratios: each round's runs are back to back, so a load change between rounds
    # cancels in its ratio
    round_ratio = {name: statistics.median(c / p for c, p in zip(cpu[name], cpu["path"], strict=True))
                   for name in shifts}
    return {"size": size, "spp": spp, "max_depth": loaded.max_depth, "seconds": medians, "all": times,
            "cpu_seconds": cpu_medians, "all_cpu": cpu,
            "cost_ratio": {name: medians[name] / medians["path"] for name in shifts},
            "cpu_cost_ratio": {name: cpu_medians[name] / cpu_medians["path"] for name in shifts},
            "cpu_round_ratio": round_ratio}


def interleaved_rounds(runs: dict[str, Callable[[], object]], rounds: int
                       ) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """(wall seconds, CPU seconds) per run name over ``rounds`` rounds, each round every run once back to back,
    after one warm-up call each (kernel compilation). Interleaving makes a load change between rounds cancel in
    each round's ratios; CPU time (user + system of every thread) is steadier than wall time on a shared machine."""
    for fn in runs.values():
        fn()
    wall: dict[str, list[float]] = {name: [] for name in runs}
    cpu: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(rounds):
        for name, fn in runs.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            fn()
            wall[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
    return wall, cpu


def bench_frame(spec: str, width: int, height: int, spp: int, repeats: int, shift: str) -> dict:
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    loaded = load_scene(spec, width=width, height=height)
    render_frame(loaded, spp=spp, seed=2, shift=shift)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        render_frame(loaded, spp=spp, seed=2, shift=shift)
        times.append(time.perf_counter() - start)
    return {"width": width, "height": height, "spp": spp, "seconds": statistics.median(times), "all": times}


def bench_gradients(spec: str, size: int, spp: int, ref_spp: int, seeds: int, shifts: list[str],
                    cache: Path | None, spp_by_shift: dict[str, int] | None = None) -> dict:
    """Issue 4's gradient error for each shift, with what the reference's own noise allows to resolve.
    ``spp_by_shift``: samples per pixel of each configuration (default ``spp``): equal render time when set
    from the measured costs."""
    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.gpt_settings import Film
    from gradsep.renderer.scene import load_scene

    loaded = load_scene(spec, width=size, height=size)
    settings = settings_for(loaded)
    spp_by_shift = spp_by_shift or {}
    chunks = reference_chunks(loaded, ref_spp, 256, cache)
    ref = chunks.mean(0)
    out: dict = {"size": size, "spp": spp, "reference_spp": 256 * len(chunks), "seeds": seeds, "floor": {},
                 "shifts": {}}
    ref_fd, ref_var = {}, {}
    for axis in ("dx", "dy"):
        ref_fd[axis] = fd(ref, axis)
        ref_var[axis] = fd(chunks, axis).var(0, ddof=1) / len(chunks)  # variance of FD(ref) per pixel
        out["floor"][axis] = float(np.mean(np.sqrt(2 / np.pi * ref_var[axis])))
    # Per layer: the direct reference is `path` at depth 2 (independent chunks), the indirect one the full
    # reference minus it; each layer's gradients are compared with its own reference's differences, which
    # shows where the total's error comes from (the two shifts differ only after the first vertex).
    layer_fd: dict[str, np.ndarray] = {}
    if settings.indirect:
        direct_chunks = reference_chunks(loaded, ref_spp, 256, cache, max_depth=2)
        direct_ref = direct_chunks.mean(0)
        n = min(len(chunks), len(direct_chunks))
        for axis in ("dx", "dy"):
            layer_fd[f"{axis}_direct"] = fd(direct_ref, axis)
            layer_fd[f"{axis}_indirect"] = ref_fd[axis] - layer_fd[f"{axis}_direct"]
            var_d = fd(direct_chunks, axis).var(0, ddof=1) / len(direct_chunks)
            var_i = fd(chunks[:n] - direct_chunks[:n], axis).var(0, ddof=1) / n  # pairs of independent chunks
            out["floor"][f"{axis}_direct"] = float(np.mean(np.sqrt(2 / np.pi * var_d)))
            out["floor"][f"{axis}_indirect"] = float(np.mean(np.sqrt(2 / np.pi * var_i)))
    # Pixel classes from the features of one 64-spp render (features are the base path's, the same for every
    # shift; 64 spp so that the sampled albedo of glossy materials does not fake texture edges).
    feat = render_gpt(loaded.scene, None, settings, Film(size, size, 64, 99))
    classes = {axis: edge_classes(feat.normal, feat.depth, feat.albedo, axis) for axis in ("dx", "dy")}
    out["pixel_share"] = {f"{axis}_{c}": float(m.mean()) for axis in classes for c, m in classes[axis].items()}
    for name in shifts:
        shift, config_settings = configuration(loaded, name)
        stats: dict[str, list[float]] = {"spp": [spp_by_shift.get(name, spp)]}
        layer_stacks: dict[str, list[np.ndarray]] = {}
        for seed in range(seeds):
            film = Film(size, size, spp_by_shift.get(name, spp), 100 + seed)
            res = render_gpt(loaded.scene, shift, config_settings, film)
            primal = sum(layer["base"] for layer in res.layers.values()).astype(np.float64)
            every_layer = all("dx" in layer for layer in res.layers.values())  # not with gradients of direct alone
            for axis in ("dx", "dy") if every_layer else ():
                grad = sum(layer[axis] for layer in res.layers.values()).astype(np.float64)
                err = grad - ref_fd[axis]
                for key, value in ((f"{axis}_mean", np.abs(err).mean()), (f"{axis}_mse", (err ** 2).mean()),
                                   (f"{axis}_fd_primal_mean", np.abs(fd(primal, axis) - ref_fd[axis]).mean())):
                    stats.setdefault(key, []).append(float(value))
                # the mean |err| split by pixel class: each class's share of the image-wide mean (they add up)
                abs_err = np.abs(err).mean(-1)
                for cls, mask in classes[axis].items():
                    stats.setdefault(f"{axis}_class_{cls}", []).append(float(abs_err[mask].sum() / abs_err.size))
            for axis in ("dx", "dy"):
                for layer, images in ((n, im) for n, im in res.layers.items() if axis in im):
                    layer_stacks.setdefault(f"{axis}_{layer}", []).append(images[axis].astype(np.float64))
                    if f"{axis}_{layer}" in layer_fd:
                        err_l = images[axis].astype(np.float64) - layer_fd[f"{axis}_{layer}"]
                        stats.setdefault(f"{axis}_{layer}_mean", []).append(float(np.abs(err_l).mean()))
        row: dict = {key: float(np.mean(values)) for key, values in stats.items()}
        for axis in ("dx", "dy") if "dx_mse" in row else ():
            row[f"{axis}_rmse_corrected"] = float(np.sqrt(max(row[f"{axis}_mse"] - ref_var[axis].mean(), 0.0)))
        for key, images in layer_stacks.items():
            row[f"{key}_noise"] = float(np.stack(images).std(0, ddof=1).mean())  # estimator noise, no reference
        out["shifts"][name] = row
    if "replay" in out["shifts"]:
        base = out["shifts"]["replay"]
        for name, row in out["shifts"].items():
            if name == "replay":
                continue
            for axis in ("dx", "dy"):
                if f"{axis}_mean" in row:
                    row[f"{axis}_gain_vs_replay"] = base[f"{axis}_mean"] / row[f"{axis}_mean"]
                    row[f"{axis}_gain_vs_replay_corrected"] = (base[f"{axis}_rmse_corrected"]
                                                               / max(row[f"{axis}_rmse_corrected"], 1e-30))
                for layer in ("direct", "indirect"):
                    if f"{axis}_{layer}_mean" in row:
                        row[f"{axis}_{layer}_gain_vs_replay"] = (base[f"{axis}_{layer}_mean"]
                                                                 / max(row[f"{axis}_{layer}_mean"], 1e-30))
                    if f"{axis}_{layer}_noise" in row:
                        row[f"{axis}_{layer}_noise_gain_vs_replay"] = (base[f"{axis}_{layer}_noise"]
                                                                       / max(row[f"{axis}_{layer}_noise"], 1e-30))
    return out


def print_gradients(scene: str, g: dict) -> None:
    print(f"  gradient error ({g['size']}^2, {g['seeds']} seeds, reference {g['reference_spp']} "
          f"spp; reference's own error floor dx {g['floor']['dx']:.5f}, dy {g['floor']['dy']:.5f}):")
    for name, row in g["shifts"].items():
        parts = []
        for axis in ("dx", "dy") if "dx_mean" in row else ():
            parts.append(f"{axis} mean|err| {row[f'{axis}_mean']:.5f} "
                         f"(FD of primal {row[f'{axis}_fd_primal_mean']:.5f}), "
                         f"RMSE corrected {row[f'{axis}_rmse_corrected']:.4f}")
        print(f"    [{name}] {row['spp']:.0f} spp: " + ("; ".join(parts) or "gradients of the direct layer only"))
        noise = ", ".join(f"{k[:-6]} {v:.5f}" for k, v in row.items() if k.endswith("_noise"))
        print(f"    [{name}] own noise (std over seeds): {noise}")
        per_layer = ", ".join(f"{k[:-5]} {v:.5f} (floor {g['floor'][k[:-5]]:.5f})" for k, v in row.items()
                              if k.endswith(("_direct_mean", "_indirect_mean")))
        if per_layer:
            print(f"    [{name}] per layer mean|err| against the layer's reference: {per_layer}")
        split = ", ".join(f"{c} {row[f'dx_class_{c}']:.5f} ({g['pixel_share'][f'dx_{c}']:.0%} of pixels)"
                          for c in ("geometry", "texture", "rest") if f"dx_class_{c}" in row)
        if split:
            print(f"    [{name}] dx mean|err| = sum over pixel classes: {split}")
        if "dx_gain_vs_replay" in row and "dy_gain_vs_replay" in row:
            print(f"    [{name}] vs replay: mean|err| {row['dx_gain_vs_replay']:.2f}x (dx) "
                  f"{row['dy_gain_vs_replay']:.2f}x (dy) lower; corrected RMSE "
                  f"{row['dx_gain_vs_replay_corrected']:.2f}x / {row['dy_gain_vs_replay_corrected']:.2f}x; own noise "
                  + ", ".join(f"{k.split('_noise')[0]} {v:.2f}x" for k, v in row.items()
                              if k.endswith("noise_gain_vs_replay"))
                  + "; per-layer mean|err| " + ", ".join(
                      f"{k[:-len('_gain_vs_replay')]} {v:.2f}x" for k, v in row.items()
                      if k.endswith(("_direct_gain_vs_replay", "_indirect_gain_vs_replay"))))


def print_summary(results: dict, shifts: list[str]) -> None:
    """The final table: cost per sample against `path` and the equal-time gradient error, per scene."""
    print("\nsummary (CPU cost per sample / `path`, median of per-round ratios; gradient error mean |d - FD(ref)| "
          f"at the render time of {shifts[0]} at 16 spp: of the whole frame, and of the direct layer against its "
          "own reference where the scene has an indirect layer)")
    print(f"  {'scene':<14} {'configuration':<16} {'cost':>6} {'spp':>4} {'dx err':>9} {'dy err':>9} "
          f"{'direct dx':>9} {'direct dy':>9}")

    def cell(row: dict | None, key: str) -> str:
        return f"{row[key]:>9.5f}" if row and key in row else f"{'-':>9}"

    for spec, out in results["scenes"].items():
        for name in shifts + ["primal"]:
            cost = out.get("cost", {}).get("cpu_round_ratio", {}).get(name)
            row = out.get("gradients", {}).get("shifts", {}).get(name)
            if cost is None and row is None:
                continue
            cost_s = f"{cost:.2f}x" if cost is not None else "-"
            spp = f"{row['spp']:>4.0f}" if row else f"{'-':>4}"
            errs = " ".join(cell(row, k) for k in ("dx_mean", "dy_mean", "dx_direct_mean", "dy_direct_mean"))
            print(f"  {spec:<14} {name:<16} {cost_s:>6} {spp} {errs}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=DEFAULT_SCENES,
                        help="comma-separated: cbox, teapot, XML paths or procedural:SEED (default %(default)s)")
    parser.add_argument("--shifts", "--shift", default="replay,hybrid",
                        help="comma-separated configurations: SHIFT[+pair|+single|+alternate][+direct] "
                             "(see configuration())")
    parser.add_argument("--quick", action="store_true", help="small sizes and few repeats (smoke check)")
    parser.add_argument("--issue16", action="store_true",
                        help="issue 16's table: cbox, procedural:0, procedural:1, teapot; hybrid with all four, "
                             "gradients of the direct layer alone (+direct), one axis's two (+pair), one (+single) "
                             "or one per axis, neighbours paired (+alternate) offsets per sample; "
                             "3 repeats, 4 seeds, 2048-spp references (explicit options override)")
    parser.add_argument("--repeats", type=int, default=None, help="timing repeats (default 5, quick 2)")
    parser.add_argument("--ref-spp", type=int, default=None, help="reference spp (default 8192, quick 1024)")
    parser.add_argument("--seeds", type=int, default=None, help="G-PT renders per shift (default 4, quick 2)")
    parser.add_argument("--frame", action="store_true", help="also time a 1280x720 16 spp frame per shift")
    parser.add_argument("--skip-cost", action="store_true", help="skip the cost-per-sample timing")
    parser.add_argument("--no-primal", dest="primal", action="store_false",
                        help="do not time the primal-only mode (`render --no-gradients`) next to `path`")
    parser.add_argument("--skip-gradients", action="store_true", help="skip the gradient-error measurement")
    parser.add_argument("--cache", default=None, help="folder for cached references")
    parser.add_argument("--equal-spp", dest="equal_time", action="store_false",
                        help="measure every configuration's gradient error at 16 spp instead of at the render "
                             "time of the first configuration at 16 spp")
    parser.add_argument("--json", default=None, help="also write the results to this file")
    args = parser.parse_args(argv)
    if args.issue16:
        given = set(argv if argv is not None else sys.argv[1:])
        if "--scenes" not in given:
            args.scenes = "cbox,procedural:0,procedural:1,teapot"
        if not given & {"--shifts", "--shift"}:
            args.shifts = "hybrid,hybrid+direct,hybrid+pair,hybrid+single,hybrid+alternate"
        args.repeats = args.repeats or 3
        args.ref_spp = args.ref_spp or 2048

    import mitsuba as mi

    from gradsep.renderer.variant import select_variant

    variant = select_variant()
    repeats = args.repeats or (2 if args.quick else 5)
    seeds = args.seeds or (2 if args.quick else 4)
    ref_spp = args.ref_spp or (1024 if args.quick else 8192)
    cost_size, grad_size = (64, 48) if args.quick else (256, 128)
    shifts = [name.strip() for name in args.shifts.split(",") if name.strip()]
    cache = Path(args.cache) if args.cache else None
    results: dict = {"variant": variant, "mitsuba": mi.__version__, "quick": args.quick, "scenes": {}}
    print(f"Mitsuba {mi.__version__} ({variant}); shifts {', '.join(shifts)}")
    for spec in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        path = resolve_scene(spec)
        out: dict = {"path": path}
        results["scenes"][spec] = out
        print(f"{spec}:")
        if not args.skip_cost:
            timed = shifts + (["primal"] if args.primal else [])
            cost = out["cost"] = bench_cost(path, cost_size, 16, repeats, timed)
            secs = cost["seconds"]
            cpu = cost["cpu_seconds"]
            print(f"  cost per sample ({cost_size}^2, 16 spp, max_depth {cost['max_depth']}, median of {repeats}; "
                  f"wall / CPU time): path {secs['path']:.3f} / {cpu['path']:.3f} s; " + "; ".join(
                      f"{name} {secs[name]:.3f} / {cpu[name]:.3f} s = {cost['cost_ratio'][name]:.2f}x / "
                      f"{cost['cpu_cost_ratio'][name]:.2f}x" for name in timed))
        if args.frame:
            w, h = (320, 180) if args.quick else (1280, 720)
            for name in shifts:
                frame = out.setdefault("frame", {})[name] = bench_frame(path, w, h, 16, max(1, repeats // 2), name)
                print(f"  [{name}] frame {w}x{h} at 16 spp: {frame['seconds']:.2f} s")
        if not args.skip_gradients:
            # Equal render time: every configuration gets the samples it buys in the time the first one
            # (the baseline) takes for 16 spp, from the measured CPU cost ratios (per-round medians).
            spp_by_shift = None
            if "cost" in out and args.equal_time:
                ratio = out["cost"]["cpu_round_ratio"]
                spp_by_shift = {name: max(1, round(16 * ratio[shifts[0]] / ratio[name])) for name in shifts}
            grads = out["gradients"] = bench_gradients(path, grad_size, 16, ref_spp, seeds, shifts, cache,
                                                       spp_by_shift)
            print_gradients(spec, grads)
    print_summary(results, shifts)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
