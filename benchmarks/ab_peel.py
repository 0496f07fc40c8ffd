"""A/B in one process: the first path vertex traced before the symbolic loop or inside it (issue 16,
docs/renderer.md "Peeling the first vertex").

    .venv/bin/python benchmarks/ab_peel.py [--scenes cbox,procedural:0,procedural:1,teapot] [--size 256]
        [--rounds 5] [--configurations hybrid,hybrid+direct]

``renderer.gpt.PEEL_FIRST_VERTEX`` on (this code) and off (the loop of the code before): the frames are bit for
bit the same (tests/renderer/test_gpt.py), so only the cost differs, and the equal-time gradient error improves by
the square root of the cost ratio. Interleaved rounds, 16 spp; prints per configuration the median CPU seconds and
the median of the per-round CPU-time ratios to Mitsuba `path` (steadier than wall time on a shared machine).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_render import (  # noqa: E402
    configuration,
    interleaved_rounds,
    path_image,
    resolve_scene,
    settings_for,
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="cbox,procedural:0,procedural:1,teapot")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--configurations", default="hybrid",
                        help="bench_render.py configurations (SHIFT[+pair|+single][+direct]); 'primal' for the "
                             "primal-only mode")
    args = parser.parse_args(argv)

    from gradsep.renderer import gpt
    from gradsep.renderer.scene import load_scene, select_variant

    select_variant()
    for spec in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        loaded = load_scene(resolve_scene(spec), width=args.size, height=args.size)
        runs = {"path": lambda ls=loaded: path_image(ls.scene, args.spp, 1, ls.max_depth, ls.rr_depth)}
        for name in args.configurations.split(","):
            shift, settings = (None, settings_for(loaded)) if name == "primal" else configuration(loaded, name)
            for peel in (False, True):
                def render(shift=shift, settings=settings, peel=peel, ls=loaded):
                    gpt.PEEL_FIRST_VERTEX = peel
                    try:
                        return gpt.render_gpt(ls.scene, shift, settings, args.size, args.size, args.spp, seed=1)
                    finally:
                        gpt.PEEL_FIRST_VERTEX = True
                runs[f"{name} {'peeled' if peel else 'in loop'}"] = render
        _, cpu = interleaved_rounds(runs, args.rounds)
        print(f"{spec} ({args.size}^2, {args.spp} spp, max_depth {loaded.max_depth}, {args.rounds} rounds):")
        for name, times in cpu.items():
            ratio = statistics.median(t / p for t, p in zip(times, cpu["path"], strict=True))
            print(f"  {name:28s} CPU {statistics.median(times):.3f} s = {ratio:.2f}x path", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
