"""A/B in one process: the manifold solve's Newton steps unrolled or as a symbolic loop (docs/renderer.md, "The
manifold solve as a loop"); with ``--toggle direct-shift``, the `--gradients direct` mode with or without the solve.

    .venv/bin/python benchmarks/ab_manifold_loop.py [--scenes cbox,procedural:90001] [--size 320x240]
        [--spp 1,16] [--modes direct-alternate,all] [--rounds 5] [--cold]

``--toggle direct-shift`` flips ``renderer.gpt.DIRECT_LAYER_SHIFT`` instead (off: the full hybrid shift in the
direct-gradients mode; on: ``HybridShift.for_direct_layer``, no manifold solve); use it with ``--modes
direct-alternate``.

``renderer.shift.MANIFOLD_LOOP`` off (the unrolled code before) and on: the script first checks that both give
the same frame bit for bit (every channel, one seed), then times warm renders in interleaved rounds and prints per
configuration the median wall time of a frame at each spp, and of the first (compiling) frame. Only scenes with
a curved mirror run the solve at all (``scene_has_curved_mirrors``); elsewhere both configurations are one code.
``--cold`` instead times the first 1-spp frame (``all`` mode) of each configuration in a fresh process whose HOME
is an empty folder, so that Dr.Jit's kernel cache (``~/.drjit``) is empty and the frame includes the compilation.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_render import resolve_scene  # noqa: E402

MODES = {"direct-alternate": {"gradients": "direct", "offsets": "alternate"}, "all": {}}


def channels(frame) -> dict[str, np.ndarray]:
    out = {f"{name}.{part}": getattr(layer, part) for name, layer in frame.layers.items()
           for part in ("base", "dx", "dy") if getattr(layer, part) is not None}
    out.update(albedo=frame.features.albedo, normal=frame.features.normal, depth=frame.features.depth)
    return out


def cold_one(spec: str, looped: bool, w: int, h: int) -> int:
    """The first 1-spp frame of a fresh process (prints its seconds)."""
    from gradsep.renderer import shift as shift_module
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    shift_module.MANIFOLD_LOOP = looped
    loaded = load_scene(spec, width=w, height=h)
    start = time.perf_counter()
    render_frame(loaded, spp=1, seed=1)
    print(f"{time.perf_counter() - start:.2f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="cbox,procedural:90001")
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--spp", default="1,16")
    parser.add_argument("--modes", default="direct-alternate,all")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--toggle", choices=("loop", "direct-shift"), default="loop",
                        help="the flag the A/B flips: MANIFOLD_LOOP (loop) or DIRECT_LAYER_SHIFT (direct-shift)")
    parser.add_argument("--cold", action="store_true", help="time the first (compiling) frame in fresh processes")
    parser.add_argument("--cold-one", nargs=2, metavar=("SCENE", "LOOP"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    if args.cold_one:
        return cold_one(args.cold_one[0], args.cold_one[1] == "1", w, h)
    if args.cold and args.toggle != "loop":
        parser.error("--cold times the manifold loop's A/B only (--toggle loop)")
    if args.cold:
        for spec in [s.strip() for s in args.scenes.split(",") if s.strip()]:
            cells = []
            for looped in ("0", "1"):
                with tempfile.TemporaryDirectory() as home:
                    out = subprocess.run([sys.executable, __file__, "--cold-one", resolve_scene(spec), looped,
                                          "--size", args.size], env={**os.environ, "HOME": home},
                                         capture_output=True, text=True, check=True)
                cells.append(out.stdout.strip().splitlines()[-1])
            print(f"{spec} ({w}x{h}, all, 1 spp, empty kernel cache): first frame unrolled {cells[0]} s -> "
                  f"loop {cells[1]} s", flush=True)
        return 0
    spps = [int(s) for s in args.spp.split(",")]

    from gradsep.renderer import gpt
    from gradsep.renderer import shift as shift_module
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene
    from gradsep.renderer.shift import scene_has_curved_mirrors

    owner, flag = (shift_module, "MANIFOLD_LOOP") if args.toggle == "loop" else (gpt, "DIRECT_LAYER_SHIFT")

    def render(loaded, mode: str, looped: bool, spp: int, seed: int):
        setattr(owner, flag, looped)
        try:
            return render_frame(loaded, spp=spp, seed=seed, **MODES[mode])
        finally:
            setattr(owner, flag, True)

    for spec in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        loaded = load_scene(resolve_scene(spec), width=w, height=h)
        mirrors = scene_has_curved_mirrors(loaded.scene)
        for mode in args.modes.split(","):
            first = {}
            frames = {}
            for looped in (False, True):
                start = time.perf_counter()
                frames[looped] = channels(render(loaded, mode, looped, spps[-1], 3))
                first[looped] = time.perf_counter() - start
            same = all(np.array_equal(frames[False][k], frames[True][k]) for k in frames[False])
            times: dict[tuple[bool, int], list[float]] = {}
            for r in range(args.rounds):
                for spp in spps:
                    for looped in ((False, True) if r % 2 == 0 else (True, False)):
                        start = time.perf_counter()
                        render(loaded, mode, looped, spp, 10 + r)
                        times.setdefault((looped, spp), []).append(time.perf_counter() - start)
            cells = ", ".join(f"{spp} spp {statistics.median(times[(False, spp)]):.3f} -> "
                              f"{statistics.median(times[(True, spp)]):.3f} s" for spp in spps)
            print(f"{spec} {mode} ({w}x{h}, {flag} off -> on, curved mirrors: {mirrors}): bit-identical {same}; "
                  f"first frame {first[False]:.2f} -> {first[True]:.2f} s; warm median of {args.rounds}: {cells}",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
