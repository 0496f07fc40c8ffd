"""Wall time and peak memory of one frame against the renderer's lanes per pass (docs/renderer.md, "Lanes per pass").

    .venv/bin/python benchmarks/bench_pass_size.py [--scenes procedural:90001,cbox] [--size 1280x720]
        [--spp 16,64] [--modes direct-alternate,all,primal] [--caps 4194304,67108864] [--rounds 2]

Every (scene, mode, spp, cap) is rendered in a fresh process (``--one``), so its peak RSS is its own: first a 1-spp
warm-up frame (kernel compilation, scene set-up), then ``--rounds`` timed frames with seeds 7, 8, ...; the table
shows the median wall time, the passes the frame took and the process's peak RSS. Processes run interleaved by
cap, round-robin, so a change of the machine's load falls on both caps alike. The frames of two caps are different
random streams (each pass has its own seed), equally valid estimates.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

MODES = {
    "direct-alternate": {"gradients": "direct", "offsets": "alternate"},
    "all": {},
    "primal": {"gradients": "none"},
}


def one(spec: str, size: tuple[int, int], spp: int, mode: str, cap: int, rounds: int) -> dict:
    """Render in this process; returns the timings (the parent starts one process per configuration)."""
    import resource
    import time

    from gradsep.renderer import gpt
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    defaults = list(gpt.render_gpt.__defaults__ or ())
    # render_gpt(..., seed=0, progress=None, max_lanes=MAX_LANES_PER_PASS, gradient_spp=None)
    defaults[2] = cap
    gpt.render_gpt.__defaults__ = tuple(defaults)
    loaded = load_scene(spec, width=size[0], height=size[1])
    render_frame(loaded, spp=1, seed=1, **MODES[mode])
    walls, passes = [], 0
    for r in range(rounds):
        start = time.perf_counter()
        frame = render_frame(loaded, spp=spp, seed=7 + r, **MODES[mode])
        walls.append(time.perf_counter() - start)
        passes = int(frame.metadata["gradsep.passes"])
    return {"walls": walls, "passes": passes,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="procedural:90001,cbox")
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--spp", default="16,64")
    parser.add_argument("--modes", default="direct-alternate,all,primal")
    parser.add_argument("--caps", default=f"{1 << 22},{1 << 26}")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    if args.one:
        spec, mode, spp, cap = args.scenes, args.modes, int(args.spp), int(args.caps)
        print(json.dumps(one(spec, (w, h), spp, mode, cap, args.rounds)))
        return 0

    from benchmarks.bench_render import resolve_scene

    caps = [int(c) for c in args.caps.split(",")]
    print(f"| scene | mode | spp | {' | '.join(f'cap {c}: wall s / passes / peak RSS GB' for c in caps)} | ratio |")
    print(f"|---|---|---:|{'---:|' * len(caps)}---:|")
    for spec in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        for mode in args.modes.split(","):
            for spp in (int(s) for s in args.spp.split(",")):
                cells, medians = [], []
                for cap in caps:
                    out = subprocess.run(
                        [sys.executable, __file__, "--one", "--scenes", resolve_scene(spec), "--modes", mode,
                         "--spp", str(spp), "--caps", str(cap), "--size", args.size, "--rounds", str(args.rounds)],
                        capture_output=True, text=True, check=True)
                    r = json.loads(out.stdout.strip().splitlines()[-1])
                    medians.append(statistics.median(r["walls"]))
                    cells.append(f"{medians[-1]:.2f} / {r['passes']} / {r['peak_rss_gb']:.2f}")
                print(f"| {spec} | {mode} | {spp} | {' | '.join(cells)} | {medians[-1] / medians[0]:.2f} |",
                      flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
