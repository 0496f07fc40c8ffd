"""A/B in one process, after the first-vertex peel: the loop body told that its vertices are never the first
(``Shift.step(later=True)``: the hybrid shift's primary-ray case folds away) or not (issue 16, docs/renderer.md).

    .venv/bin/python benchmarks/ab_later.py [SCENES] [ROUNDS]      # default cbox,procedural:1,teapot 5

First checks that both give the same frames bit for bit (cbox, teapot; all and direct gradients), then prints per
scene the median CPU seconds at 256², 16 spp and the median of the per-round CPU-time ratios to `path`.
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_render import interleaved_rounds, path_image, resolve_scene, settings_for  # noqa: E402


def main(argv: list[str]) -> int:
    from gradsep.renderer import gpt
    from gradsep.renderer.scene import load_scene, select_variant
    from gradsep.renderer.shift import HybridShift

    select_variant()

    class NotLater(HybridShift):
        def step(self, *args, later=False, **kwargs):
            return super().step(*args, **kwargs)

    for spec in ("cbox", "teapot"):
        loaded = load_scene(resolve_scene(spec), width=24, height=20)
        base = settings_for(loaded)
        for gradients in ("all", "direct"):
            settings = gpt.GptSettings(max_depth=base.max_depth, rr_depth=base.rr_depth, indirect=base.indirect,
                                       gradients=gradients)
            a = gpt.render_gpt(loaded.scene, HybridShift(), settings, 24, 20, 5, seed=3)
            b = gpt.render_gpt(loaded.scene, NotLater(), settings, 24, 20, 5, seed=3)
            same = all(np.array_equal(a.layers[layer][key], b.layers[layer][key])
                       for layer in a.layers for key in a.layers[layer])
            print(f"{spec} gradients={gradients}: {'identical' if same else 'DIFFERENT'}", flush=True)
    scenes = argv[0] if argv else "cbox,procedural:1,teapot"
    rounds = int(argv[1]) if len(argv) > 1 else 5
    size = 256
    for spec in scenes.split(","):
        loaded = load_scene(resolve_scene(spec), width=size, height=size)
        settings = settings_for(loaded)
        runs = {"path": lambda ls=loaded: path_image(ls.scene, 16, 1, ls.max_depth, ls.rr_depth),
                "peel": lambda ls=loaded, st=settings: gpt.render_gpt(ls.scene, NotLater(), st, size, size, 16, 1),
                "peel+later": lambda ls=loaded, st=settings: gpt.render_gpt(ls.scene, HybridShift(), st, size, size,
                                                                           16, 1)}
        _, cpu = interleaved_rounds(runs, rounds)
        cells = [f"{name} {statistics.median(t):.3f} s = "
                 f"{statistics.median(x / p for x, p in zip(t, cpu['path'], strict=True)):.2f}x"
                 for name, t in cpu.items()]
        print(spec, "; ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
