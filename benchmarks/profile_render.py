"""Where a G-PT sample goes (issue 16): fixed per-frame costs, kernel cost by stage, and what the offsets do.

    .venv/bin/python benchmarks/profile_render.py [--scenes cbox,procedural:0,procedural:1,teapot] [--size 256]
        [--spp 16] [--rounds 7] [--json out.json]

Per scene:

1. **fixed costs**: scene load; the first render in the process (recording the loop in Python, code generation,
   LLVM compilation or a hit in Dr.Jit's kernel cache on disk, kernel launch); and, for warm renders, the time
   outside the kernel (recording + hashing the loop in Python each call, packing the result) apart from the
   kernel's own execution time (Dr.Jit's kernel history).
2. **cost by stage** (CPU time of the process, all threads, interleaved rounds, median of the per-round ratios to
   `path`): Mitsuba `path`; the primal-only mode (base path + routing + features); random replay; the hybrid
   shift in one loop (every offset through the full step until the base path ends); the hybrid shift as shipped
   (second loop for connected offsets); and the hybrid with one strategy compiled out where the scene uses it.
   The differences between rows are the cost of each stage.
3. **offset statistics** (a counting run, not timed): per base vertex in the first loop, how many of the four
   offsets traced on their own (not yet connected), were already connected, or had ended; how many offset
   vertices the first loop ran in total against the second loop; and how many offsets ended by a failed shift.
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

from benchmarks.bench_render import (  # noqa: E402
    interleaved_rounds,
    path_image,
    resolve_scene,
    settings_for,
)


def kernel_times(fn) -> tuple[float, float, float, float]:
    """(wall, kernel execution, code generation, LLVM backend) seconds of one call, from Dr.Jit's history."""
    import drjit as dr

    dr.kernel_history()  # clears it
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    start = time.perf_counter()
    fn()
    wall = time.perf_counter() - start
    history = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)

    def total(key: str) -> float:
        return sum(float(h.get(key, 0.0)) for h in history) / 1000.0

    return wall, total("execution_time"), total("codegen_time"), total("backend_time")


def variants(loaded, size: int, spp: int) -> dict:
    """name -> render function, for the stages this scene compiles."""
    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.shift import HybridShift, ReplayShift

    class OneLoopHybrid(HybridShift):
        settled = None  # not a ConnectingShift: every offset through the full step (as tests/renderer does)

    settings = settings_for(loaded)
    hybrid = HybridShift()
    copy, follow, manifold = hybrid._features(loaded.scene)
    runs = {
        "path": lambda: path_image(loaded.scene, spp, 1, loaded.max_depth, loaded.rr_depth),
        "primal": lambda: render_gpt(loaded.scene, None, settings, size, size, spp, seed=1),
        "replay": lambda: render_gpt(loaded.scene, ReplayShift(), settings, size, size, spp, seed=1),
        "hybrid one loop": lambda: render_gpt(loaded.scene, OneLoopHybrid(), settings, size, size, spp, seed=1),
        "hybrid": lambda: render_gpt(loaded.scene, hybrid, settings, size, size, spp, seed=1),
    }
    for name, on, kwargs in (("no half-vector copy", copy, {"half_vector": False}),
                             ("no follow/manifold", follow, {"follow_specular": False}),
                             ("no manifold", manifold, {"manifold": False})):
        if on:
            shift = HybridShift(**kwargs)
            runs[f"hybrid, {name}"] = (lambda s=shift: render_gpt(loaded.scene, s, settings, size, size, spp,
                                                                  seed=1))
    return runs


def stage_costs(runs: dict, rounds: int) -> dict:
    """Interleaved rounds (bench_render.interleaved_rounds: one untimed warm-up call each, so a stage's kernel
    compilation no longer lands in its first round); per-round CPU-time and wall-time ratios to `path`, medians."""
    wall, cpu = interleaved_rounds(runs, rounds)
    out = {}
    for name in runs:
        r_cpu = np.array(cpu[name]) / np.array(cpu["path"])
        r_wall = np.array(wall[name]) / np.array(wall["path"])
        out[name] = {"cpu_s": statistics.median(cpu[name]), "wall_s": statistics.median(wall[name]),
                     "cpu_ratio": float(np.median(r_cpu)), "cpu_ratio_q25": float(np.quantile(r_cpu, 0.25)),
                     "cpu_ratio_q75": float(np.quantile(r_cpu, 0.75)), "wall_ratio": float(np.median(r_wall))}
    return out


COUNTERS = ("own", "connected", "ended", "failed", "second_loop_live", "second_loop_ended")


def offset_statistics(loaded, size: int, spp: int) -> dict:
    """Counts of offset vertices by kind, from a hybrid render whose shift scatters counters (not timed)."""
    import drjit as dr
    import mitsuba as mi

    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.shift import CONNECTED, RECENTLY_CONNECTED, HybridShift

    slots = 1024  # counters spread over slots: fewer atomic collisions
    counts = dr.zeros(mi.UInt32, slots * len(COUNTERS))

    def add(kind: str, mask: mi.Bool, lane: mi.UInt32) -> None:
        index = (lane % slots) * len(COUNTERS) + COUNTERS.index(kind)
        dr.scatter_reduce(dr.ReduceOp.Add, counts, dr.select(mask, mi.UInt32(1), mi.UInt32(0)), index)

    class Counting(HybridShift):
        def step(self, scene, off, base, depth, max_depth, samples, later=False):
            lane = dr.arange(mi.UInt32, dr.width(off.active))
            connected = off.active & ((off.status == CONNECTED) | (off.status == RECENTLY_CONNECTED))
            add("own", off.active & ~connected, lane)
            add("connected", connected, lane)
            add("ended", ~off.active & base.has_hit, lane)
            new, events = super().step(scene, off, base, depth, max_depth, samples, later=later)
            # ended by a failed shift: active before, throughput zeroed while the base path still had a vertex
            add("failed", off.active & base.si.is_valid() & (dr.max(new.throughput) == 0.0), lane)
            return new, events

        def step_connected(self, off, base, depth, max_depth):
            lane = dr.arange(mi.UInt32, dr.width(off.active))
            add("second_loop_live", off.active, lane)
            add("second_loop_ended", ~off.active & base.has_hit, lane)
            return super().step_connected(off, base, depth, max_depth)

    render_gpt(loaded.scene, Counting(), settings_for(loaded), size, size, spp, seed=1)
    totals = counts.numpy().reshape(slots, len(COUNTERS)).sum(0)
    c = dict(zip(COUNTERS, (int(v) for v in totals), strict=True))
    first = c["own"] + c["connected"] + c["ended"]
    samples = size * size * spp
    return {**c, "samples": samples,
            "first_loop_offset_vertices_per_sample": first / samples,
            "second_loop_offset_vertices_per_sample": (c["second_loop_live"] + c["second_loop_ended"]) / samples,
            "share_own": c["own"] / max(first, 1), "share_connected": c["connected"] / max(first, 1),
            "share_ended": c["ended"] / max(first, 1), "failed_per_own_step": c["failed"] / max(c["own"], 1)}


def fixed_costs(spec: str, size: int, spp: int) -> dict:
    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.scene import load_scene
    from gradsep.renderer.shift import HybridShift

    start = time.perf_counter()
    loaded = load_scene(spec, width=size, height=size)
    load_s = time.perf_counter() - start
    settings = settings_for(loaded)

    def render():
        return render_gpt(loaded.scene, HybridShift(), settings, size, size, spp, seed=1)

    cold = kernel_times(render)
    warm = [kernel_times(render) for _ in range(3)]
    wall, execution = statistics.median(w[0] for w in warm), statistics.median(w[1] for w in warm)
    return {"load_s": load_s, "first_render_s": cold[0], "first_render_kernel_s": cold[1],
            "first_render_codegen_s": cold[2], "first_render_backend_s": cold[3],
            "warm_render_s": wall, "warm_kernel_s": execution, "warm_outside_kernel_s": wall - execution}, loaded


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="cbox,procedural:0,procedural:1,teapot")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--skip-stages", action="store_true")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)

    from gradsep.renderer.scene import select_variant

    select_variant()
    results = {}
    for spec in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        fixed, loaded = fixed_costs(resolve_scene(spec), args.size, args.spp)
        print(f"{spec} ({args.size}^2, {args.spp} spp, max_depth {loaded.max_depth}):")
        print(f"  fixed: scene load {fixed['load_s']:.2f} s; first hybrid render {fixed['first_render_s']:.2f} s "
              f"(kernel {fixed['first_render_kernel_s']:.2f}, codegen {fixed['first_render_codegen_s']:.2f}, "
              f"LLVM {fixed['first_render_backend_s']:.2f}); warm render {fixed['warm_render_s']:.2f} s = kernel "
              f"{fixed['warm_kernel_s']:.2f} + outside the kernel {fixed['warm_outside_kernel_s']:.2f} s")
        stats = offset_statistics(loaded, args.size, args.spp)
        print(f"  offsets, first loop: {stats['first_loop_offset_vertices_per_sample']:.2f} offset vertices per "
              f"sample: {stats['share_own']:.0%} on their own, {stats['share_connected']:.0%} connected, "
              f"{stats['share_ended']:.0%} ended; failed shifts per own step {stats['failed_per_own_step']:.1%}; "
              f"second loop: {stats['second_loop_offset_vertices_per_sample']:.2f} offset vertices per sample")
        out = {"fixed": fixed, "offsets": stats}
        if not args.skip_stages:
            runs = variants(loaded, args.size, args.spp)
            for fn in runs.values():
                fn()  # compile
            stages = out["stages"] = stage_costs(runs, args.rounds)
            for name, row in stages.items():
                print(f"  {name:32s} CPU {row['cpu_s']:.3f} s = {row['cpu_ratio']:.2f}x path "
                      f"(q25-q75 {row['cpu_ratio_q25']:.2f}-{row['cpu_ratio_q75']:.2f}); wall {row['wall_s']:.3f} s "
                      f"= {row['wall_ratio']:.2f}x")
        results[spec] = out
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
