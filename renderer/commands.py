"""`gradsep render | reference | reference-merge | dataset`: the argument parsers and their handlers.

Only argparse and the import-light model modules at module level: each handler imports Mitsuba (through the
renderer modules) when it runs, so ``gradsep --help`` and ``gradsep serve`` work without Mitsuba installed.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Any

from gradsep.model.errors import CommandError
from gradsep.model.policy import SEPARATED_LAYERS


def render_command(args: argparse.Namespace) -> int:
    """`gradsep render`: render a frame and write it atomically to ``args.output``; with ``--frames`` (or a frame
    field in the output or scene), a shot (renderer/shot.py)."""
    from gradsep.model.exr_write import write_frame
    from gradsep.renderer.scene import load_scene, parse_defines
    from gradsep.renderer.shot import RenderCall

    deadline = _deadline(args)  # first: the budget counts from the process's start
    gradients = default_gradients(args)
    _check_plan_flags(args, gradients, deadline is not None)
    if deadline is None and args.spp < 1:
        raise CommandError(f"--spp must be >= 1, got {args.spp}")
    if _is_shot(args):
        from gradsep.renderer.shot import render_shot

        return render_shot(args, deadline, gradients, _plan_cache_folder(args, gradients), render_loaded)
    output = Path(args.output)
    if output.suffix.lower() != ".exr":
        raise CommandError(f"output {args.output} must end in .exr")
    if not output.parent.exists():
        raise CommandError(f"output folder {output.parent} does not exist")
    cache_folder = _plan_cache_folder(args, gradients)
    plan_cache = None
    if cache_folder is not None:
        from gradsep.renderer.plancache import CacheFolder, scene_identity

        plan_cache = CacheFolder(cache_folder, f"key:{args.plan_key}" if args.plan_key
                                 else scene_identity(args.scene, parse_defines(args.define)))
    if deadline is not None and deadline.left() <= 0:
        from gradsep.renderer.frame_budget import startup_error

        raise startup_error(deadline.seconds, deadline.elapsed())
    scene = load_scene(args.scene, width=args.width, height=args.height, max_depth=args.max_depth,
                       defines=parse_defines(args.define))
    frame, plan_text = render_loaded(args, scene, RenderCall(args.seed, deadline, gradients, plan_cache))
    write_frame(output, frame)
    for note in frame.warnings:
        print(f"gradsep render: note: {note}", file=sys.stderr)
    print(f"{output}: {frame_summary(frame, deadline)}" + (f"; {plan_text}" if plan_text else ""))
    return 0


def _is_shot(args: argparse.Namespace) -> bool:
    """Whether the command renders a shot: ``--frames``, or a frame field in the output or the scene (without
    ``--frames`` that is the shot's one-line error)."""
    from gradsep.model.shot import FramePattern

    return (args.frames is not None or FramePattern(args.output).has_field or FramePattern(args.scene).has_field
            or bool(args.animate) or args.shard is not None)


def render_loaded(args: argparse.Namespace, scene: Any, call: Any) -> tuple[Any, str]:
    """Render the loaded ``scene`` with the command's settings and ``call``'s seed, budget and plan: the frame (not
    yet written) and its plan's summary."""
    from gradsep.renderer.render import FrameOptions, render_frame

    show = sys.stderr.isatty()

    def progress(done: int, total: int) -> None:
        if show:
            of = f"/{total}" if total else ""
            print(f"\rgradsep render: {done}{of} spp", end="", file=sys.stderr, flush=True)

    if call.deadline is None and call.gradients != "auto":
        frame = render_frame(scene, spp=args.spp, seed=call.seed, layers=args.layers, shift=args.shift,
                             gradients=call.gradients, options=FrameOptions(offsets=args.offsets,
                                                                            gradient_spp=args.gradient_spp,
                                                                            progress=progress))
        plan_text = ""
    else:
        frame, plan_text = _render_planned(args, scene, call, progress)
    if show:
        print(file=sys.stderr)
    return frame, plan_text


def frame_summary(frame: Any, deadline: Any) -> str:
    """A written frame's size, samples, layers and time, for the command's line."""
    spp = frame.metadata["gradsep.spp"]
    split = frame.metadata.get("gradsep.gradient_spp")
    spp_text = f"{spp} spp ({split} with gradients)" if split else f"{spp} spp"
    took = (f"{deadline.elapsed():.2f} s of {deadline.seconds:g} s" if deadline
            else f"{frame.metadata['gradsep.render_seconds']} s")
    return f"{frame.width}x{frame.height}, {spp_text}, layers {', '.join(frame.layers)}, {took}"


def _check_plan_flags(args: argparse.Namespace, gradients: str, budgeted: bool) -> None:
    """The flags that shape the plan (``--gradients``, ``--no-gradients``, ``--shift``, ``--offsets``,
    ``--gradient-spp``) checked against each other and ``--seconds`` (``budgeted``): a one-line user error."""
    if args.no_gradients and gradients != "none":
        raise CommandError(f"--no-gradients is --gradients none; it contradicts --gradients {args.gradients}")
    if gradients == "none" and args.shift is not None:
        flag = "--no-gradients" if args.no_gradients else "--gradients none"
        raise CommandError(f"--shift has no effect with {flag} (no offset paths are traced)")
    if gradients == "none" and args.offsets != "all":
        flag = "--no-gradients" if args.no_gradients else "--gradients none"
        raise CommandError(f"--offsets has no effect with {flag} (no offset paths are traced)")
    if gradients == "auto" and args.offsets != "all":
        given = "" if args.gradients else " (the default with --seconds)"
        raise CommandError(f"--offsets is chosen by the plan with --gradients auto{given}; give --gradients all or "
                           "direct to set it")
    if args.gradient_spp is not None:
        if gradients == "none":
            flag = "--no-gradients" if args.no_gradients else "--gradients none"
            raise CommandError(f"--gradient-spp has no effect with {flag} (no offset paths are traced)")
        if budgeted or gradients == "auto":
            raise CommandError("--gradient-spp needs --spp and a fixed --gradients (all or direct)")
        if args.spp >= 1:  # checked before the scene loads (a bad --spp: render_frame's error)
            from gradsep.renderer.render import check_gradient_spp

            check_gradient_spp(args.gradient_spp, args.spp, gradients)


def _render_planned(args: argparse.Namespace, scene: Any, call: Any, progress: Any) -> tuple[Any, str]:
    """`gradsep render --seconds` or ``--gradients auto``: the planned frame and its plan's summary."""
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.planned_frame import PlanRequest, render_planned_frame

    budget = FrameBudget(call.deadline) if call.deadline is not None else FrameBudget(spp=args.spp)
    request = PlanRequest(seed=call.seed, layers=args.layers, shift=args.shift, gradients=call.gradients,
                          offsets=args.offsets)
    return render_planned_frame(scene, budget, request, progress=progress, plan_cache=call.plan_cache)


def _plan_cache_folder(args: argparse.Namespace, gradients: str) -> Path | None:
    """``--plan-cache`` (else $GRADSEP_PLAN_CACHE) for an ``auto`` frame, checked; None without one. Given on the
    command line with a fixed plan it is an error (there is no choice to keep); from the environment, a farm-wide
    setting, it is left unused there."""
    from gradsep.renderer.plancache import CACHE_ENV, check_folder

    folder = args.plan_cache or os.environ.get(CACHE_ENV, "").strip() or None
    if args.plan_cache and gradients != "auto":
        raise CommandError(f"--plan-cache keeps the choice of --gradients auto; it has no effect with --gradients "
                           f"{gradients}")
    if args.plan_key is not None and (folder is None or gradients != "auto"):
        raise CommandError(f"--plan-key names the shot in the plan cache; give --plan-cache DIR (or set {CACHE_ENV}) "
                           "and --gradients auto")
    if args.plan_key is not None and not args.plan_key.strip():
        raise CommandError("--plan-key must not be empty")
    return check_folder(folder) if folder is not None and gradients == "auto" else None


def default_gradients(args: argparse.Namespace) -> str:
    """``--gradients`` as given; else ``none`` with ``--no-gradients``, ``auto`` with ``--seconds`` (the plan is
    chosen per scene within the budget; docs/decisions.md) and ``all`` with ``--spp`` (a frame that serves every
    method)."""
    if args.gradients:
        return str(args.gradients)
    if args.no_gradients:
        return "none"
    return "auto" if args.seconds is not None else "all"


def _deadline(args: argparse.Namespace) -> Any:
    """``--seconds`` as a renderer.budget.Deadline counted from the process's start, or None with ``--spp``."""
    if (args.seconds is None) == (args.spp is None):
        raise CommandError("give exactly one of --spp (samples per pixel) or --seconds (a wall-time budget)")
    if args.seconds is None:
        return None
    from gradsep.renderer.budget import Deadline, check_seconds, process_age

    return Deadline(check_seconds(args.seconds), spent=process_age())


def reference_command(args: argparse.Namespace) -> int:
    """Handler of `gradsep reference`: validate, render, write atomically, print a one-line summary."""
    from gradsep.renderer.reference import ReferenceJob, parse_shard, render_reference, write_reference
    from gradsep.renderer.scene import parse_defines

    for name in ("spp", "tile_spp", "width", "height"):
        value = getattr(args, name, None)
        if value is not None and value < 1:
            raise CommandError(f"--{name.replace('_', '-')} must be a positive integer, got {value}")
    if args.max_depth is not None and (args.max_depth == 0 or args.max_depth < -1):
        raise CommandError(f"--max-depth must be -1 (unbounded) or a positive integer, got {args.max_depth}")
    if args.seed < 0:
        raise CommandError(f"--seed must be non-negative, got {args.seed}")
    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        raise CommandError(f"output must be an .exr file, got {out}")
    if not out.parent.exists():
        raise CommandError(f"output folder {out.parent} does not exist")
    try:
        shard = parse_shard(args.shard) if args.shard else None
        job = ReferenceJob(spp=args.spp, seed=args.seed, tile_spp=args.tile_spp, sampler=args.sampler, shard=shard)
        ref = render_reference(args.scene, job, width=args.width, height=args.height, max_depth=args.max_depth,
                               defines=parse_defines(args.define), progress=None)
    except (ValueError, FileNotFoundError) as exc:
        raise CommandError(str(exc)) from exc
    write_reference(out, ref)
    _print_written(out, ref)
    return 0


def _print_written(out: Path, ref: Any) -> None:
    layers = "direct, indirect" if ref.indirect is not None else "direct"
    seconds = float(ref.metadata["gradsep.render_seconds"])
    spp = int(ref.metadata["gradsep.spp"])
    part = f", shard {ref.metadata['gradsep.shard']}" if "gradsep.shard" in ref.metadata else ""
    sampler = ref.metadata.get("gradsep.sampler", "?")
    print(f"wrote {out}: {ref.total.shape[1]}x{ref.total.shape[0]}, {spp} spp{part}, layers {layers}, "
          f"sampler {sampler}, {seconds:.1f} s ({_rate(spp, ref.total.shape, seconds)})")


def reference_merge_command(args: argparse.Namespace) -> int:
    """Handler of `gradsep reference-merge`: the N ``--shard K/N`` files of one job -> the job's reference."""
    from gradsep.model.errors import FrameError
    from gradsep.renderer.reference import load_reference, merge_references, write_reference

    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        raise CommandError(f"output must be an .exr file, got {out}")
    if not out.parent.exists():
        raise CommandError(f"output folder {out.parent} does not exist")
    parts = []
    for name in args.parts:
        if not Path(name).is_file():
            raise CommandError(f"shard file not found: {name}")
        try:
            parts.append(load_reference(name))
        except FrameError as exc:
            raise CommandError(f"{name}: {exc}") from exc
    try:
        ref = merge_references(parts)
    except ValueError as exc:
        raise CommandError(str(exc)) from exc
    write_reference(out, ref)
    _print_written(out, ref)
    return 0


def _rate(spp: int, shape: tuple[int, ...], seconds: float) -> str:
    samples = spp * shape[0] * shape[1]
    return f"{samples / max(seconds, 1e-9) / 1e6:.1f} M samples/s" if math.isfinite(seconds) else ""


def dataset_command(args: argparse.Namespace) -> int:
    """Handler of `gradsep dataset`."""
    from gradsep.renderer.dataset import (
        MANIFEST_NAME,
        PARTS_DIR,
        DatasetError,
        JobOptions,
        finished_frames,
        make_job,
        run_dataset,
    )

    job = make_job(JobOptions(count=args.count, spp=args.spp, size=args.size, shard=args.shard,
                              first_seed=args.first_seed, max_depth=args.max_depth, pairs=args.pairs,
                              family=args.family, seconds=args.seconds))
    root = Path(args.output)
    if root.exists() and not root.is_dir():
        raise DatasetError(f"output {root} exists and is not a folder")
    before = len(finished_frames(root)) if (root / PARTS_DIR).is_dir() else 0
    manifest = run_dataset(root, job, progress=None)
    mine = set(job.seeds())
    have = sum(1 for f in manifest.frames if f.seed in mine)
    total = sum(1 for f in manifest.frames if job.first_seed <= f.seed < job.first_seed + job.count)
    budget = ""
    if job.seconds is not None:
        spps = sorted(f.spp for f in manifest.frames if f.seed in mine)
        budget = f", {job.seconds:g} s per frame" + (f" ({spps[0]}-{spps[-1]} spp)" if spps else "")
    print(f"{root}: shard {job.shard_name} has {have}/{len(mine)} frames; dataset {total}/{job.count} "
          f"({len(manifest.frames) - before:+d} this run{budget}); manifest {root / MANIFEST_NAME} "
          f"hash {manifest.hash[:16]}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    _add_render_parser(sub)
    _add_reference_parsers(sub)
    _add_dataset_parser(sub)


def _add_render_parser(sub: argparse._SubParsersAction) -> None:
    from gradsep.renderer.render import OFFSET_CHOICES  # no Mitsuba at import time

    p = sub.add_parser("render", help="render a G-PT frame (base + gradients + features per illumination layer)")
    p.add_argument("scene", help="Mitsuba 3 XML scene path, procedural:SEED or procedural:studio:SEED; for a shot "
                                 "also a per-frame XML pattern (scene.%%04d.xml)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel (or --seconds)")
    p.add_argument("--seconds", default=None, metavar="T",
                   help="render the best frame this machine makes in T seconds of wall time for the whole command "
                        "(process start, scene load, kernel compile, passes, write), stopping at pass granularity; "
                        "instead of --spp. The header records the spp, the plan and the time spent")
    p.add_argument("--width", type=int, default=None, help="override the scene's film width")
    p.add_argument("--height", type=int, default=None, help="override the scene's film height")
    p.add_argument("--max-depth", type=int, default=None,
                   help="Mitsuba's convention: 2 = direct light only, -1 = unbounded (default: the scene's)")
    p.add_argument("--seed", type=int, default=0, help="sampler seed")
    p.add_argument("--layers", default=",".join(SEPARATED_LAYERS),
                   help="comma-separated illumination layers to render: direct, indirect (default both); "
                        "color alone renders the unseparated image")
    p.add_argument("--shift", choices=("hybrid", "replay"), default=None,
                   help="shift mapping: hybrid (reconnection + replay, the default) or replay")
    p.add_argument("--gradients", choices=("all", "direct", "none", "auto"), default=None,
                   help="which layers carry gradients: auto (the default with --seconds: a checkpoint on the frame's "
                        "halves predicts each plan's reconstructed error at the budget, or at --spp, and renders "
                        "the lower, see docs/renderer.md); all (the default with --spp: serves every method); "
                        "direct (the direct layer's only: offset "
                        "paths stop after the first visible vertex's light, the indirect layer is a plain primal; "
                        "what the default oidn-l1 method uses); none (primal-only)")
    p.add_argument("--offsets", choices=OFFSET_CHOICES, default="all",
                   help="offset paths per sample: all four (the default); alternate (one per axis, neighbouring "
                        "pixels paired: ~0.7x the cost, gradients from half the samples; cheaper samples for "
                        "oidn-l1, see docs/renderer.md); pair, single")
    p.add_argument("--gradient-spp", type=int, default=None, metavar="K",
                   help="trace offsets on K of the --spp samples only (1 <= K <= --spp; default all): the other "
                        "samples are primal-only, the bases and features average all --spp samples, the gradients "
                        "the K G-PT ones (see docs/renderer.md, \"Split samples\")")
    p.add_argument("--no-gradients", action="store_true",
                   help="primal-only, the same as --gradients none: the same layers and features, no offset paths "
                        "and no gradients (about the cost of a plain path tracer)")
    p.add_argument("-D", "--define", action="append", default=[], metavar="NAME=VALUE",
                   help="override a <default> parameter of the XML scene (repeatable)")
    p.add_argument("--plan-cache", default=None, metavar="DIR",
                   help="with --gradients auto: a folder the frames of a shot share (default $GRADSEP_PLAN_CACHE); "
                        "the first frame's checkpoint writes its choice for this scene, size, layers, budget and "
                        "CPU, and the next frames render that plan with no checkpoint (docs/renderer.md)")
    p.add_argument("--plan-key", default=None, metavar="KEY",
                   help="the shot's name in the plan cache (default: the scene file's content and -D defines, or "
                        "the procedural spec): frames of one shot whose scene files differ share a decision")
    p.add_argument("--frames", default=None, metavar="A-B",
                   help="render a shot: frames A to B, both included (farm numbering, e.g. 1001-1100), one file "
                        "each; the output (and a per-frame scene) names each frame with %%04d, %%d or #### "
                        "(docs/renderer.md, \"Shots\")")
    p.add_argument("--animate", action="append", default=[], metavar="NAME=START:END",
                   help="with --frames: a <default> parameter $NAME of the XML scene, linear from START on the "
                        "first frame to END on the last; a number, or a comma-separated vector (x,y,z:x,y,z) "
                        "interpolated component by component (repeatable)")
    p.add_argument("--shard", default=None, metavar="i/n",
                   help="with --frames: render only shard i of n (0 <= i < n): the i-th of n contiguous chunks "
                        "of the shot's frames")
    p.add_argument("-o", "--output", required=True,
                   help="output frame (.exr); for a shot, a pattern such as out.%%04d.exr or out.####.exr")
    p.set_defaults(func=render_command)


def _add_reference_parsers(sub: argparse._SubParsersAction) -> None:
    from gradsep.renderer.reference import DEFAULT_SAMPLER, SAMPLERS  # numpy only: no Mitsuba at parser time

    p = sub.add_parser("reference", help="render a reference with Mitsuba's path integrator (R G B + layers)")
    p.add_argument("scene", help="Mitsuba 3 XML scene path, procedural:SEED or procedural:studio:SEED")
    p.add_argument("--spp", type=int, required=True, help="samples per pixel")
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--max-depth", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tile-spp", type=int, default=None,
                   help="samples per pass; passes are averaged so large spp fits in memory")
    p.add_argument("-D", "--define", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--sampler", choices=SAMPLERS, default=DEFAULT_SAMPLER,
                   help=f"Mitsuba sampler of every pass (default {DEFAULT_SAMPLER}: stratified, lower noise per "
                        "second than independent; all are unbiased)")
    p.add_argument("--shard", default=None, metavar="K/N",
                   help="render only shard K of N of this job's passes (same seeds as the whole job); combine "
                        "the N files with `gradsep reference-merge`")
    p.add_argument("-o", "--output", required=True, help="output reference (.exr)")
    p.set_defaults(func=reference_command)

    p = sub.add_parser("reference-merge", help="combine the N --shard K/N files of one reference job")
    p.add_argument("parts", nargs="+", help="the shard files (.exr), shards 1..N of one job, any order")
    p.add_argument("-o", "--output", required=True, help="output reference (.exr)")
    p.set_defaults(func=reference_merge_command)


def _add_dataset_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dataset", help="render N procedural frames plus a manifest (shardable, resumable)")
    p.add_argument("--count", type=int, required=True, help="number of frames in the whole dataset")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel of every frame (or --seconds)")
    p.add_argument("--seconds", default=None, metavar="T",
                   help="instead of --spp: render each frame (and each --pairs target) in T seconds of wall time, "
                        "from its scene's load to its file in place, with the render planner of `gradsep render "
                        "--seconds` and every layer's gradients (what training reads); each record keeps its spp")
    p.add_argument("--size", default="256x256", help="WxH")
    p.add_argument("--first-seed", type=int, default=1000, help="seed of frame 0; frame i uses first-seed + i")
    p.add_argument("--max-depth", type=int, default=None)
    p.add_argument("--shard", default="0/1", help="i/n: render frames i, i+n, i+2n, ...")
    p.add_argument("--pairs", action="store_true",
                   help="also render an independent second realization of every frame (another sampler seed): "
                        "the Noise2Noise targets `gradsep train` uses when present")
    p.add_argument("--family", default="mixed", choices=("mixed", "studio"),
                   help="procedural family: mixed (rooms, procedural:SEED; the default) or studio (objects and "
                        "lights in an empty background, procedural:studio:SEED)")
    p.add_argument("-o", "--output", required=True, help="dataset folder")
    p.set_defaults(func=dataset_command)
