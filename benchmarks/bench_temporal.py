"""Temporal reconstruction (gradsep.model.temporal) against the per-frame pipeline, on shots rendered here.

``quality`` renders small shots with ``gradsep render`` (a static camera and scene with a new seed per frame; the
Cornell box with a lamp switched off half-way, tests/data/temporal/lightswitch.xml), plain frames and
``--gradients direct --offsets alternate`` frames, and two independent high-spp references per distinct image.
Then two shots of tests/data/shot/moving.xml rendered with ``--frames`` and ``--animate`` (a moving camera, a
moving object), which carry the renderer's motion vectors, and per-frame references. Each shot is reconstructed
per frame (the frame's default method) and temporally (``--window``), and the script
prints per pipeline: RelMSE against the truth (two references, their noise removed), as the geometric mean over
the frames, and its ratio to the per-frame pipeline on the same frames; flicker (model.metrics.flicker) and its
ratio to primal + OIDN per frame (the plain frames' per-frame pipeline); on the light switch, the error ratio on
the frames after the switch; on the moving shots, the error ratio in the pixels without a correspondence in a
neighbour (disoccluded or about to be occluded) and flicker along the motion; and seconds per frame. The still
shots carry no motion vectors (nothing moves), so the script gives each frame zero motion, all valid.

``cost`` times a 1280x720 frame of ``gradsep.model.synthetic`` (two layers with gradients, variance and
features) reconstructed per frame against temporally from a window (a shot reconstructed in order, so each
frame's first stage runs once), interleaved with repeats, and each one's peak RSS in a fresh process.

    python benchmarks/bench_temporal.py quality --frames 8 --size 128 --spp 16 --ref-spp 1024
    python benchmarks/bench_temporal.py cost --repeats 3
    python benchmarks/bench_temporal.py cost --repeats 3 --shift 0.5
"""

from __future__ import annotations

import argparse
import json
import math
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
from gradsep.model.metrics import flicker, relmse_unbiased
from gradsep.model.reconstruct import reconstruct
from gradsep.model.temporal import Motion, ShotReconstructor

LIGHTSWITCH = Path(__file__).resolve().parent.parent / "tests" / "data" / "temporal" / "lightswitch.xml"
PLANS = {"plain": ["--no-gradients"], "direct-alternate": ["--gradients", "direct", "--offsets", "alternate"]}


def _render(scene: str, out: Path, spp: int, size: int, seed: int, extra: list[str]) -> Path:
    if not out.exists():
        subprocess.run([sys.executable, "-m", "gradsep", "render", scene, "--spp", str(spp), "--width", str(size),
                        "--height", str(size), "--seed", str(seed), *extra, "-o", str(out)], check=True,
                       capture_output=True)
    return out


def _zero_motion(frame, shift: float = 0.0):  # noqa: ANN001, ANN202 - a Frame in, the same Frame out
    """Give ``frame`` motion vectors: every pixel moving ``shift`` pixels right per frame (0: still), all valid."""
    h, w = frame.height, frame.width
    backward, forward = np.zeros((h, w, 2), np.float32), np.zeros((h, w, 2), np.float32)
    backward[..., 0], forward[..., 0] = -shift, shift
    ones = np.ones((h, w), np.float32)
    frame.motion = Motion(backward, forward, ones, ones)
    return frame


def _shots(args: argparse.Namespace, folder: Path) -> dict[str, tuple[list[str], list[list[str]]]]:
    """shot name -> (scene per frame, -D defines per frame)."""
    half = args.frames // 2
    lamp = [["-D", "lamp=6.0"]] * half + [["-D", "lamp=0.0"]] * (args.frames - half)
    return {f"static procedural:{args.scene}": ([f"procedural:{args.scene}"] * args.frames, [[]] * args.frames),
            "light switched off": ([str(LIGHTSWITCH)] * args.frames, lamp)}


def _geomean(values: list[float]) -> float:
    return math.exp(float(np.mean(np.log(np.maximum(values, 1e-12)))))


def _run(frames: list, window: int) -> tuple[list[np.ndarray], float]:
    """Each frame reconstructed (window 1: per frame), and the median seconds per frame."""
    outs, seconds = [], []
    shot = ShotReconstructor(lambda n: frames[n] if 0 <= n < len(frames) else None, window)
    for n in range(len(frames)):
        start = time.perf_counter()
        outs.append(reconstruct(frames[n]).image if window == 1 else shot.reconstruct(n).image)
        seconds.append(time.perf_counter() - start)
    return outs, statistics.median(seconds)


def _references(scenes: list[str], defines: list[list[str]], args: argparse.Namespace,
                folder: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    refs: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
    for scene, define in zip(scenes, defines, strict=True):
        key = (scene, *define)
        if key not in refs:
            name = "".join(c if c.isalnum() else "_" for c in "_".join(key))[-60:]
            pair = [_render(scene, folder / f"ref_{name}_{k}.exr", args.ref_spp, args.size, 90000 + k,
                            ["--no-gradients", *define]) for k in (1, 2)]
            refs[key] = tuple(read_frame(p).combined().base for p in pair)  # type: ignore[assignment]
    return [refs[(s, *d)][0] for s, d in zip(scenes, defines, strict=True)], \
        [refs[(s, *d)][1] for s, d in zip(scenes, defines, strict=True)]


def _report(plan: str, frames: list, refs: tuple[list, list], window: int, baseline: float | None) -> tuple:
    """Print one plan's per-frame and temporal rows; returns (per-frame errors, temporal errors, outputs, the
    per-frame flicker). Flicker is taken along the motion: frame t - 1 warped onto t by t's backward vectors."""
    r1, r2 = refs
    per, per_seconds = _run(frames, 1)
    tem, tem_seconds = _run(frames, window)
    e_per = [relmse_unbiased(x, a, b) for x, a, b in zip(per, r1, r2, strict=True)]
    e_tem = [relmse_unbiased(x, a, b) for x, a, b in zip(tem, r1, r2, strict=True)]
    f_per, f_tem = _flicker_along(per, frames, r1, r2), _flicker_along(tem, frames, r1, r2)
    baseline = baseline or f_per
    for name, errors, flick, seconds in (("per-frame", e_per, f_per, per_seconds),
                                         ("temporal", e_tem, f_tem, tem_seconds)):
        print(f"  {plan:17s} {name:9s} RelMSE {_geomean(errors):.5g} "
              f"({_geomean(errors) / _geomean(e_per):.3f}x per-frame)  flicker {flick:.4g} "
              f"({flick / baseline:.3f}x primal+OIDN)  {seconds:.3f} s/frame")
    return e_per, e_tem, (per, tem), f_per


def _warp_back(image: np.ndarray, frame) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001 - a Frame
    """``image`` (frame t - 1's) sampled where frame t's backward vectors point, and where that is valid."""
    from scipy.ndimage import map_coordinates

    rows, cols, valid = frame.motion.warp_source("backward")
    inside = valid & (rows >= 0) & (rows <= image.shape[0] - 1) & (cols >= 0) & (cols <= image.shape[1] - 1)
    out = np.stack([map_coordinates(image[..., c], [rows, cols], order=1, mode="nearest")
                    for c in range(image.shape[-1])], axis=-1)
    return out, inside


def _flicker_along(images: list, frames: list, r1: list, r2: list) -> float:
    values = []
    for t in range(1, len(images)):
        if frames[t].motion is None or frames[t].motion.backward is None:
            continue
        (x, mask), (a, _), (b, _) = (_warp_back(v[t - 1], frames[t]) for v in (images, r1, r2))
        values.append(flicker([x, images[t]], [a, r1[t]], [b, r2[t]], masks=[None, mask]))
    return float(np.mean(values))


def quality(args: argparse.Namespace) -> None:
    folder = Path(args.cache or tempfile.mkdtemp(prefix="bench_temporal_"))
    folder.mkdir(parents=True, exist_ok=True)
    for shot, (scenes, defines) in _shots(args, folder).items():
        refs = _references(scenes, defines, args, folder)
        baseline = None
        print(f"\n{shot}: {args.frames} frames, {args.size}x{args.size}, {args.spp} spp, window {args.window}")
        for plan, extra in PLANS.items():
            tag = "".join(c if c.isalnum() else "_" for c in shot + plan)
            frames = [_zero_motion(read_frame(_render(s, folder / f"{tag}.{n}.exr", args.spp, args.size,
                                                      1000 * (n + 1) + len(plan), [*extra, *d])))
                      for n, (s, d) in enumerate(zip(scenes, defines, strict=True))]
            e_per, e_tem, _, f_per = _report(plan, frames, refs, args.window, baseline)
            baseline = baseline or f_per  # plain frames first: primal + OIDN per frame
            if "light" in shot:
                after = [n for n in range(1, args.frames) if defines[n] != defines[n - 1]]
                for n in after + [a + 1 for a in after if a + 1 < args.frames]:
                    print(f"  {plan:17s} frame {n} (after the switch): temporal/per-frame error "
                          f"{e_tem[n] / e_per[n]:.3f}")
    for shot, animate in MOVING.items():
        _moving(args, folder, shot, animate)


#: Shots of tests/data/shot/moving.xml (a ball over a floor under an area light) with the renderer's motion vectors.
MOVING = {"moving camera": "eye=-1,1.5,4:1,1.2,3.2", "moving object": "pos=-1,0.5,0:1,0.5,0"}
MOVING_SCENE = Path(__file__).resolve().parent.parent / "tests" / "data" / "shot" / "moving.xml"


def _render_shot(out: str, args: argparse.Namespace, animate: str, spp: int, seed: int, extra: list[str]) -> list:
    frames = f"1-{args.frames}"
    height = args.size * 3 // 4
    subprocess.run([sys.executable, "-m", "gradsep", "render", str(MOVING_SCENE), "--frames", frames, "--animate",
                    animate, "--spp", str(spp), "--width", str(args.size), "--height", str(height), "--seed",
                    str(seed), *extra, "-o", out], check=True, capture_output=True)
    return [read_frame(out.replace("%d", str(n))) for n in range(1, args.frames + 1)]


def _moving(args: argparse.Namespace, folder: Path, shot: str, animate: str) -> None:
    tag = "".join(c if c.isalnum() else "_" for c in shot)
    refs = tuple([f.combined().base for f in _render_shot(str(folder / f"{tag}_ref{k}.%d.exr"), args, animate,
                                                          args.ref_spp, 500 + k, ["--no-gradients"])]
                 for k in (1, 2))
    print(f"\n{shot} ({animate}): {args.frames} frames, {args.size}x{args.size * 3 // 4}, {args.spp} spp, window "
          f"{args.window}, the renderer's motion vectors")
    baseline = None
    for k, (plan, extra) in enumerate(PLANS.items()):
        frames = _render_shot(str(folder / f"{tag}_{k}.%d.exr"), args, animate, args.spp, 700 + k, extra)
        e_per, e_tem, (per, tem), f_per = _report(plan, frames, refs, args.window, baseline)  # type: ignore[arg-type]
        baseline = baseline or f_per
        ratios = []
        for t, frame in enumerate(frames):
            motion = frame.motion
            if motion is None or motion.backward is None or motion.forward is None:
                continue
            mask = ~(motion.backward_valid & motion.forward_valid) & (refs[0][t].sum(-1) > 0)
            if mask.sum() >= 100:
                a, b = refs[0][t][mask], refs[1][t][mask]
                ratios.append(relmse_unbiased(tem[t][mask], a, b) / relmse_unbiased(per[t][mask], a, b))
        print(f"  {plan:17s} disoccluded/occluded lit pixels, temporal/per-frame error per frame: "
              + " ".join(f"{r:.2f}" for r in ratios))


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
    q.add_argument("--cache", default=None, help="folder to keep the renders in (re-runs reuse them)")
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
