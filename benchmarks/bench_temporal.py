"""Temporal reconstruction (gradsep.model.temporal) against the per-frame pipeline, on shots rendered here.

``quality`` runs gradsep.evaluation.shots on four small shots -- what ``gradsep evaluate --shot`` runs, so the two
give the same numbers: a static camera and scene (a procedural room, a new seed per frame); the Cornell box with a
lamp switched off half-way (tests/data/temporal/lightswitch.xml, written here as a per-frame XML pattern); and two
shots of tests/data/shot/moving.xml with ``--animate`` (a moving camera, a moving object). Every shot is rendered
with ``gradsep render --frames`` (motion vectors included) with each of ``--plans``: primal frames, the default plan
and ``--gradients direct --offsets alternate`` frames, at ``--spp`` or at equal ``--seconds`` per frame, with two
independent references per frame; each plan's frames are reconstructed per frame (the frame's default method) and
temporally (``--window``). Per pipeline it prints (evaluation/shot_metrics.py defines each figure): RelMSE against
the truth (the references' noise removed) as the geometric mean over the frames and its ratio to the best per-frame
pipeline; flicker along the motion and its ratio to primal + OIDN per frame (the primal frames' per-frame pipeline);
the error ratios, to the same frames per frame, in the disoccluded pixels and on the frames after the truth changes
(the light switch); and seconds per frame. ``--report DIR`` also writes each shot's report folder.

``cost`` times a 1280x720 frame of ``gradsep.model.synthetic`` (two layers with gradients, variance and
features) reconstructed per frame against temporally from a window (a shot reconstructed in order, so each
frame's first stage runs once), interleaved with repeats, and each one's peak RSS in a fresh process.

    python benchmarks/bench_temporal.py quality --frames 8 --size 128 --spp 16 --ref-spp 1024
    python benchmarks/bench_temporal.py quality --frames 16 --size 128 --seconds 10 --ref-spp 512 --report out/
    python benchmarks/bench_temporal.py cost --repeats 3
    python benchmarks/bench_temporal.py cost --repeats 3 --shift 0.5
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gradsep.model.exr_read import read_frame
from gradsep.model.reconstruct import reconstruct
from gradsep.model.temporal import Motion, ShotReconstructor

LIGHTSWITCH = Path(__file__).resolve().parent.parent / "tests" / "data" / "temporal" / "lightswitch.xml"
#: Beside the evaluation's plans (primal, the default plan): G-PT with direct-light gradients, alternate offsets.
EXTRA_PLANS = {"direct-alternate": ("--gradients", "direct", "--offsets", "alternate")}


def _lightswitch_pattern(frames: int, folder: Path) -> str:
    """The light-switch shot as a per-frame XML pattern (as exporters write shots): the lamp on for the first half
    of the frames, off for the rest."""
    text = LIGHTSWITCH.read_text()
    on = '<default name="lamp" value="6.0"/>'
    if on not in text:
        raise SystemExit(f"{LIGHTSWITCH} no longer has {on}")
    for n in range(1, frames + 1):
        path = folder / f"lightswitch.{n:04d}.xml"
        lamp = on if n <= frames // 2 else on.replace("6.0", "0.0")
        if not path.exists() or path.read_text() != text.replace(on, lamp):
            path.write_text(text.replace(on, lamp))
    return str(folder / "lightswitch.%04d.xml")


def _shots(args: argparse.Namespace, folder: Path) -> dict[str, dict]:
    """shot name -> the ShotConfig fields that make it."""
    square, wide = (args.size, args.size), (args.size, args.size * 3 // 4)
    return {f"static procedural:{args.scene}": {"scene": f"procedural:{args.scene}", "size": square},
            "light switched off": {"scene": _lightswitch_pattern(args.frames, folder), "size": square},
            **{name: {"scene": str(MOVING_SCENE), "animate": (animate,), "size": wide}
               for name, animate in MOVING.items()}}


def quality(args: argparse.Namespace) -> None:
    """Each shot through gradsep.evaluation.shots (what `gradsep evaluate --shot` runs), printed as its table."""
    from gradsep.evaluation.shot_report import summary_rows, write_shot_report
    from gradsep.evaluation.shots import PLANS, Plan, ShotConfig, evaluate_shot
    from gradsep.model.policy import models_dir_from

    folder = Path(args.cache or tempfile.mkdtemp(prefix="bench_temporal_"))
    folder.mkdir(parents=True, exist_ok=True)
    known = {**{p.name: p for p in PLANS}, **{n: Plan(n, n, f) for n, f in EXTRA_PLANS.items()}}
    names = [n.strip() for n in args.plans.split(",") if n.strip()]
    if not names or names[0] != PLANS[0].name or any(n not in known for n in names):
        raise SystemExit(f"--plans: a comma-separated list of {', '.join(known)}, {PLANS[0].name} first (the "
                         "flicker baseline)")
    plans = tuple(known[n] for n in names)
    budget = {"seconds": args.seconds} if args.seconds else {"spp": args.spp}
    for shot, fields in _shots(args, folder).items():
        report = Path(args.report) / "".join(c if c.isalnum() else "_" for c in shot) if args.report else folder
        config = ShotConfig(frames=f"1-{args.frames}", output=report, cache_dir=folder,
                            models_dir=models_dir_from(None), ref_spp=args.ref_spp, window=args.window, **budget,
                            **fields)
        result = evaluate_shot(config, plans, log=lambda m: None)
        print(f"\n{shot}: {args.frames} frames, {config.size[0]}x{config.size[1]}, "
              + (f"{args.seconds:g} s" if args.seconds else f"{args.spp} spp") + f" per frame, window "
              f"{args.window}; frames where the light changes: "
              + (", ".join(str(result.numbers[t]) for t in result.changes) or "none"))
        for row in summary_rows(result):
            print(f"  {row['label']:42s} RelMSE {_g(row['relmse'], 5)} ({_x(row['relmse_vs_best_per_frame'])} best "
                  f"per-frame)  flicker {_g(row['flicker'])} ({_x(row['flicker_vs_primal_oidn'])} primal+OIDN)  "
                  f"disoccluded {_x(row['disoccluded_vs_per_frame'])}, after a change "
                  f"{_x(row['after_change_vs_per_frame'])} per-frame  {_g(row['seconds_per_frame'])} s/frame, "
                  f"{_g(row['spp'])} spp")
        if args.report:
            write_shot_report(result, " ".join(["python", *sys.argv]))


def _g(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}g}"


def _x(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3g}x"


#: Shots of tests/data/shot/moving.xml (a ball over a floor under an area light) with the renderer's motion vectors.
MOVING = {"moving camera": "eye=-1,1.5,4:1,1.2,3.2", "moving object": "pos=-1,0.5,0:1,0.5,0"}
MOVING_SCENE = Path(__file__).resolve().parent.parent / "tests" / "data" / "shot" / "moving.xml"


def _zero_motion(frame, shift: float = 0.0):  # noqa: ANN001, ANN202 - a Frame in, the same Frame out
    """Give ``frame`` motion vectors: every pixel moving ``shift`` pixels right per frame (0: still), all valid."""
    h, w = frame.height, frame.width
    backward, forward = np.zeros((h, w, 2), np.float32), np.zeros((h, w, 2), np.float32)
    backward[..., 0], forward[..., 0] = -shift, shift
    ones = np.ones((h, w), np.float32)
    frame.motion = Motion(backward, forward, ones, ones)
    return frame


def _synthetic_files(count: int, folder: Path) -> list[Path]:
    from gradsep.model.synthetic import synthetic_frame

    paths = [folder / f"synthetic.{k}.exr" for k in range(count)]
    for k, path in enumerate(paths):
        if not path.exists():
            path.write_bytes(synthetic_frame(720, 1280, seed=k))
    return paths


def _child(mode: str, window: int, folder: Path, shift: float) -> None:
    """One mode in this process on the frames in ``folder``: reconstruct the middle frames, print the peak RSS."""
    paths = sorted(folder.glob("synthetic.*.exr"))[:window + 2]
    frames = [_zero_motion(read_frame(p), shift) for p in paths]
    shot = ShotReconstructor(lambda n: frames[n] if 0 <= n < len(frames) else None, window)
    for n in range(1, len(frames) - 1):
        reconstruct(frames[n]) if mode == "per-frame" else shot.reconstruct(n)
    print(json.dumps({"mode": mode, "peak_rss_mib": _peak_rss_mib()}))


def _peak_rss_mib() -> float:
    """This process's peak RSS: VmHWM (Linux), which exec resets; getrusage's ru_maxrss keeps the forking
    parent's peak across exec, so a child started from a large parent would report the parent's."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def cost(args: argparse.Namespace) -> None:
    folder = Path(tempfile.mkdtemp(prefix="bench_temporal_"))
    frames = [_zero_motion(read_frame(p), args.shift)
              for p in _synthetic_files(args.window + 2 * args.repeats + 2, folder)]
    shot = ShotReconstructor(lambda n: frames[n] if 0 <= n < len(frames) else None, args.window)
    shot.reconstruct(0)  # warm-up: the first frame's window of first stages, OIDN's first call
    reconstruct(frames[0])
    per, tem = [], []
    for n in range(1, 2 * args.repeats + 1):  # interleaved: both see the same load
        start = time.perf_counter()
        reconstruct(frames[n])
        per.append(time.perf_counter() - start)
        start = time.perf_counter()
        shot.reconstruct(n)  # steady state: one new first stage (frame n + r1) and the second stage of n
        tem.append(time.perf_counter() - start)
    print(f"1280x720, window {args.window}, motion {args.shift:g} px/frame, load average "
          f"{os.getloadavg()[0]:.2f}: per-frame default "
          f"{statistics.median(per):.3f} s, temporal {statistics.median(tem):.3f} s per frame "
          f"({statistics.median(tem) / statistics.median(per):.2f}x), medians of {len(per)}")
    for mode in ("per-frame", "temporal"):
        out = subprocess.run([sys.executable, __file__, "cost", "--child", mode, "--window", str(args.window),
                              "--folder", str(folder), "--shift", str(args.shift)],
                             check=True, capture_output=True, text=True)
        print(f"  peak RSS {mode}: {json.loads(out.stdout.strip().splitlines()[-1])['peak_rss_mib']:.0f} MiB "
              f"({args.window + 2} frames decoded)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    q = sub.add_parser("quality", help="RelMSE, flicker and time per frame on rendered shots")
    q.add_argument("--frames", type=int, default=8)
    q.add_argument("--size", type=int, default=128)
    q.add_argument("--spp", type=int, default=16)
    q.add_argument("--ref-spp", type=int, default=1024)
    q.add_argument("--scene", type=int, default=90012, help="the static shot's procedural seed")
    q.add_argument("--window", type=int, default=5)
    q.add_argument("--plans", default="primal,plan,direct-alternate",
                   help="the plans rendered: primal (first: the flicker baseline), plan (the default plan, as "
                        "gradsep evaluate --shot), direct-alternate")
    q.add_argument("--seconds", type=float, default=None,
                   help="render seconds per frame instead of --spp (equal time: gradsep render --seconds)")
    q.add_argument("--cache", default=None, help="folder to keep the renders in (re-runs reuse them)")
    q.add_argument("--report", default=None, help="also write each shot's report folder (gradsep evaluate --shot's) "
                                                  "under this folder")
    c = sub.add_parser("cost", help="seconds per 720p frame and peak RSS, per-frame against temporal")
    c.add_argument("--repeats", type=int, default=3)
    c.add_argument("--window", type=int, default=5)
    c.add_argument("--shift", type=float, default=0.0,
                   help="motion in pixels per frame (0: a still shot; a fraction exercises the bilinear warp)")
    c.add_argument("--child", default=None, help=argparse.SUPPRESS)
    c.add_argument("--folder", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.command == "quality":
        quality(args)
    elif args.child:
        _child(args.child, args.window, Path(args.folder), args.shift)
    else:
        cost(args)


if __name__ == "__main__":
    main()
