"""Reference sampler study (issue 13): the reference floor per CPU-second of each Mitsuba sampler, and how the
floor falls with samples.

The *floor* of a scene is what a perfect method would score against one reference (model.metrics.reference_floor,
estimated from two independent references). For a 1/t estimator, floor x seconds is a constant of the scene and
sampler: the **floor-seconds** (floor x CPU-seconds of one reference, direct + full-depth renders, as
renderer.reference.render_loaded spends them). Lower is better; ``gain`` is independent's floor-seconds over the
sampler's. CPU seconds are the process's user + system time (time.process_time), so other jobs on a shared
machine inflate them less than wall time.

    python benchmarks/bench_reference.py samplers procedural:81001 procedural:81002 --spp 256
    python benchmarks/bench_reference.py scaling procedural:81001 --sampler multijitter --passes 8 --spp 256

``samplers``: per scene two references of ``--spp`` (one pass each; a sampler that cannot render that count
exactly gets the nearest count it renders: orthogonal 289 for 256) per sampler; prints floor, CPU s, floor-seconds,
gain and both references' image means (the unbiasedness check: every sampler renders the same expectation).
``scaling``: two references of ``--passes`` passes of ``--spp`` each, the floor after 1, 2, 4, ... passes, the
fitted exponent of floor ~ spp^a (a = -1: plain 1/t; shallower: heavy-tailed noise, fireflies) and the share of
the floor carried by the brightest 0.1 % of pixel-differences.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gradsep.model.metrics import reference_floor  # noqa: E402
from gradsep.renderer.reference import SAMPLERS, pass_seed, render_loaded, sampler_count  # noqa: E402
from gradsep.renderer.scene import load_scene  # noqa: E402


def _pair(loaded, sampler: str, spp: int, seeds: tuple[int, int]) -> tuple[list, float]:
    """Two references (one pass each) and the CPU seconds of the second: the first pays the kernel compilation
    (a stratified sampler's spp is compiled into the kernel; seeds are not), which a real reference pays once."""
    refs, cpu = [], 0.0
    for seed in seeds:
        t0 = time.process_time()
        refs.append(render_loaded(loaded, spp=spp, seed=seed, tile_spp=spp, sampler=sampler))
        cpu = time.process_time() - t0
    return refs, cpu


def samplers(args: argparse.Namespace) -> None:
    print(f"{'scene':20s} {'sampler':12s} {'spp':>4s} {'floor':>10s} {'CPU s':>6s} {'floor-s':>10s} "
          f"{'gain':>6s}  means", flush=True)
    for spec in args.scenes:
        loaded = load_scene(spec, width=args.width, height=args.height, max_depth=args.max_depth)
        render_loaded(loaded, spp=1, seed=0, tile_spp=1, sampler="independent")  # Dr.Jit compiles once
        base, depth = None, "" if args.max_depth is None else f" d{args.max_depth}"
        for sampler in args.sampler or SAMPLERS:
            spp = sampler_count(sampler, args.spp)
            refs, cpu = _pair(loaded, sampler, spp, (args.seed, args.seed + 1))
            floor = reference_floor(refs[0].total, refs[1].total)
            fs = floor * cpu
            base = fs if sampler == "independent" else base
            gain = f"{base / fs:6.2f}" if base else "     -"
            print(f"{spec + depth:20s} {sampler:12s} {spp:4d} {floor:10.3e} {cpu:6.1f} {fs:10.3e} {gain}  "
                  f"{refs[0].total.mean():.5f}/{refs[1].total.mean():.5f}", flush=True)


def scaling(args: argparse.Namespace) -> None:
    for spec in args.scenes:
        loaded = load_scene(spec, width=args.width, height=args.height, max_depth=args.max_depth)
        sums = [np.zeros((loaded.height, loaded.width, 3)), np.zeros((loaded.height, loaded.width, 3))]
        cpu, xs, ys = 0.0, [], []
        for i in range(args.passes):
            for which in (0, 1):
                t0 = time.process_time()
                ref = render_loaded(loaded, spp=args.spp, seed=pass_seed(args.seed + which, i), tile_spp=args.spp,
                                    sampler=args.sampler[0] if args.sampler else "multijitter")
                cpu += time.process_time() - t0
                sums[which] += ref.total
            n = i + 1  # pass 0 pays the kernel compilation: a small share of 8 passes
            if n & (n - 1) == 0 or n == args.passes:  # powers of two and the last
                a, b = (s / n for s in sums)
                floor = reference_floor(a.astype(np.float32), b.astype(np.float32))
                rbar = 0.5 * (a + b)
                per = ((a - b) ** 2 / (rbar ** 2 + 0.01)).ravel()
                top = np.sort(per)[-max(1, per.size // 1000):].sum() / max(per.sum(), 1e-30)
                xs.append(math.log(n * args.spp))
                ys.append(math.log(floor))
                print(f"{spec:20s} spp {n * args.spp:6d} floor {floor:10.3e} CPU s/ref {cpu / 2:7.1f} "
                      f"floor-s {floor * cpu / 2:10.3e} top0.1% share {top:5.1%}", flush=True)
        if len(xs) > 1:
            slope = np.polyfit(xs, ys, 1)[0]
            print(f"{spec:20s} fitted floor ~ spp^{slope:.2f}", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mode", choices=("samplers", "scaling"))
    p.add_argument("scenes", nargs="+")
    p.add_argument("--sampler", action="append", choices=SAMPLERS)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--passes", type=int, default=8)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--max-depth", type=int, default=None, help="override the scenes' depth (2: direct light only)")
    p.add_argument("--seed", type=int, default=7001)
    args = p.parse_args()
    samplers(args) if args.mode == "samplers" else scaling(args)


if __name__ == "__main__":
    main()
