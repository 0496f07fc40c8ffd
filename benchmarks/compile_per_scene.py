"""Per-frame fixed costs of a `dataset`-like sequence: scene load and first render of successive procedural
scenes (kernel, code generation, LLVM compilation from Dr.Jit's history), and a second render of each.

    .venv/bin/python benchmarks/compile_per_scene.py [FIRST_SEED] [COUNT]     # default 1000 4
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_render import settings_for  # noqa: E402
from benchmarks.profile_render import kernel_times  # noqa: E402


def main(argv: list[str]) -> int:
    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.scene import load_scene
    from gradsep.renderer.shift import make_shift

    first = int(argv[0]) if argv else 1000
    count = int(argv[1]) if len(argv) > 1 else 4
    for seed in range(first, first + count):
        start = time.perf_counter()
        loaded = load_scene(f"procedural:{seed}", width=64, height=64)
        load = time.perf_counter() - start
        settings = settings_for(loaded)

        def render(s: int, scene=loaded.scene, settings=settings):
            return render_gpt(scene, make_shift("hybrid"), settings, 64, 64, 4, seed=s)

        w, ex, cg, be = kernel_times(lambda: render(1))
        w2, ex2, _, be2 = kernel_times(lambda: render(2))
        print(f"procedural:{seed}: load {load:.2f} s; first render {w:.2f} s (kernel {ex:.2f}, codegen {cg:.2f}, "
              f"LLVM {be:.2f}); second {w2:.2f} s (kernel {ex2:.2f}, LLVM {be2:.2f})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
