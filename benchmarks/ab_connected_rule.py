"""A/B in one process of the rule for leaving the hybrid's full-step loop (issue 16, docs/renderer.md).

    .venv/bin/python benchmarks/ab_connected_rule.py [SCENE] [SIZE] [ROUNDS]      # default cbox 256 7

"new rule": offsets reconnected in the last iteration are summarised too (this code); "old rule": only
``CONNECTED`` offsets leave the first loop (the code before 2026-12-01). Interleaved rounds, 16 spp; prints the
median of the per-round CPU-time ratios to Mitsuba `path` (steadier than wall time on a shared machine).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_render import interleaved_rounds, path_image, resolve_scene, settings_for  # noqa: E402


def main(argv: list[str]) -> int:
    import mitsuba as mi

    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.scene import load_scene
    from gradsep.renderer.shift import CONNECTED, ConnectedState, HybridShift

    class OldRule(HybridShift):
        def settled(self, offset):
            return ~offset.active | (offset.status == CONNECTED)

        def summarize(self, offset):
            return ConnectedState(active=offset.active & (offset.status == CONNECTED), throughput=offset.throughput,
                                  ratio=offset.ratio, next_weight=offset.base_out_weight, next_ratio=mi.Float(1.0),
                                  own_next_pdf=mi.Float(0.0), just_connected=mi.Bool(False))

    spec = argv[0] if argv else "cbox"
    size = int(argv[1]) if len(argv) > 1 else 256
    rounds = int(argv[2]) if len(argv) > 2 else 7
    loaded = load_scene(resolve_scene(spec), width=size, height=size)
    settings = settings_for(loaded)
    runs = {"path": lambda: path_image(loaded.scene, 16, 1, loaded.max_depth, loaded.rr_depth),
            "old rule": lambda: render_gpt(loaded.scene, OldRule(), settings, size, size, 16, seed=1),
            "new rule": lambda: render_gpt(loaded.scene, HybridShift(), settings, size, size, 16, seed=1)}
    _, cpu = interleaved_rounds(runs, rounds)
    for name in runs:
        r = np.array(cpu[name]) / np.array(cpu["path"])
        print(f"{spec} {name}: CPU {np.median(cpu[name]):.3f} s, per-round ratio to path {np.median(r):.2f} "
              f"(q25 {np.quantile(r, 0.25):.2f}, q75 {np.quantile(r, 0.75):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
