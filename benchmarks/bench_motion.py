"""What motion vectors cost next to the frame they belong to: render_motion (both sides) against a G-PT render.

Usage: PYTHONPATH=$PWD python benchmarks/bench_motion.py [--size 128] [--spp 16] [--repeats 3] [SCENE ...]

Per scene: three frames are loaded (t-1, t, t+1; tests/data/motion/shot.xml moves its camera and objects, other
scenes are their own neighbours, which costs the same), each timed step runs once to compile its kernels, then
the G-PT render (``render_frame``, default plan: both layers, all gradients) and ``render_motion`` alternate
``--repeats`` times. Prints medians and their ratio, and the first (compiling) call of each.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

from gradsep.renderer.motion import render_motion
from gradsep.renderer.render import render_frame
from gradsep.renderer.scene import load_scene

SHOT = Path(__file__).resolve().parents[1] / "tests" / "data" / "motion" / "shot.xml"
SHOT_FRAMES = ({"cx": "-0.1", "sx": "0.3"}, {"cx": "0", "sx": "0.4"}, {"cx": "0.1", "sx": "0.5"})


def _timed(step) -> float:
    start = time.perf_counter()
    step()
    return time.perf_counter() - start


def bench(spec: str, size: int, spp: int, repeats: int) -> None:
    defines = SHOT_FRAMES if spec == str(SHOT) else ({}, {}, {})
    previous, current, following = (load_scene(spec, width=size, height=size, defines=d) for d in defines)
    first_motion = _timed(lambda: render_motion(current, previous, following))
    first_render = _timed(lambda: render_frame(current, spp=spp, seed=0))
    renders, motions = [], []
    for r in range(repeats):
        renders.append(_timed(lambda r=r: render_frame(current, spp=spp, seed=r + 1)))
        motions.append(_timed(lambda: render_motion(current, previous, following)))
    render, motion = statistics.median(renders), statistics.median(motions)
    print(f"{Path(spec).name} {size}x{size}: G-PT {spp} spp median {render:.3f} s, render_motion median "
          f"{motion:.4f} s, ratio {motion / render:.4f} (first calls: render {first_render:.2f} s, motion "
          f"{first_motion:.2f} s)", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="*", default=[str(SHOT)])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores", flush=True)
    for spec in args.scenes:
        bench(spec, args.size, args.spp, args.repeats)


if __name__ == "__main__":
    main()
