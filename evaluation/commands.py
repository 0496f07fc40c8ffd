"""`gradsep evaluate`: argparse and the import-light policy only at module level; the handler imports the harness
lazily."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from gradsep.model.errors import CommandError
from gradsep.model.policy import DEFAULT_ALPHA, MODELS_ENV

if TYPE_CHECKING:
    from gradsep.evaluation.config import EvalConfig


def config_from_args(args: argparse.Namespace) -> EvalConfig:
    """The run's configuration from the parsed flags (a flag not given: its GRADSEP_EVAL_* variable, else the
    preset); a Namespace without some flag counts it as not given."""
    from gradsep.evaluation.config import EvalSettings, load_settings, make_config

    settings = load_settings(**{name: getattr(args, name, None) for name in EvalSettings.model_fields})
    return make_config(settings, output=args.output, scenes=getattr(args, "scenes", None) or (),
                       spp=getattr(args, "spp", None), quick=bool(getattr(args, "quick", False)),
                       models=getattr(args, "models", None), cache=getattr(args, "cache", None))


def evaluate_command(args: argparse.Namespace) -> int:
    """``gradsep evaluate``: run the evaluation, print where the outputs are and which methods were skipped."""
    from gradsep.evaluation.run import run_evaluation

    if getattr(args, "shot", None) is not None or _given_shot_flags(args):
        return _shot_command(args)
    config = config_from_args(args)
    shard = getattr(args, "shard", None)
    if getattr(args, "references_only", False):
        return _references_only(config, shard)
    if shard is not None:
        raise CommandError("--shard applies to --references-only (a farm renders reference passes; one machine "
                           "then runs the evaluation on the combined cache)")
    start = time.perf_counter()
    evaluation = run_evaluation(config, progress=None)
    elapsed = time.perf_counter() - start
    for method, reasons in evaluation.skipped.items():
        print(f"gradsep evaluate: skipped {method}: {'; '.join(reasons)}", file=sys.stderr)
    for note in evaluation.notes:
        print(f"gradsep evaluate: note: {note}", file=sys.stderr)
    computed = evaluation.computed
    print(f"evaluated {len(evaluation.scenes)} scene(s), {len(evaluation.rows)} rows in {elapsed:.0f} s "
          f"(computed {computed['frames']} frames, {computed['references']} reference passes, "
          f"{computed['results']} results; the rest from {config.cache_dir / 'evaluate'}) -> "
          f"{evaluation.outputs['report']}")
    return 0


#: Flags of a shot evaluation only, and flags of the frame evaluation that a shot evaluation does not take.
_SHOT_ONLY = (("frames", "--frames"), ("animate", "--animate"), ("define", "-D"), ("seconds", "--seconds"),
              ("window", "--window"))
_FRAME_ONLY = (("scenes", "--scenes"), ("methods", "--methods"), ("table_spp", "--table-spp"),
               ("time_seeds", "--time-seeds"), ("frame_seeds", "--frame-seeds"), ("references_only",
                                                                                  "--references-only"),
               ("shard", "--shard"), ("alpha", "--alpha"), ("ref_seconds", "--ref-seconds"))


def _given(args: argparse.Namespace, names: tuple[tuple[str, str], ...]) -> list[str]:
    return [flag for name, flag in names if getattr(args, name, None) not in (None, False, [])]


def _given_shot_flags(args: argparse.Namespace) -> list[str]:
    return _given(args, _SHOT_ONLY)


def shot_config_from_args(args: argparse.Namespace) -> object:
    """The shot evaluation's configuration (evaluation.shots.ShotConfig) from the parsed flags; a CommandError
    names a flag that does not belong."""
    from gradsep.evaluation.cache import default_cache_dir
    from gradsep.evaluation.config import FULL, QUICK, load_settings, parse_size
    from gradsep.evaluation.shots import ShotConfig
    from gradsep.model.policy import models_dir_from

    if getattr(args, "shot", None) is None:
        raise CommandError(f"{_given_shot_flags(args)[0]} applies to a shot: give --shot SCENE --frames A-B")
    wrong = _given(args, _FRAME_ONLY)
    if wrong:
        raise CommandError(f"{wrong[0]} applies to the frame evaluation (--scenes), not to --shot")
    if args.frames is None:
        raise CommandError("--shot needs --frames A-B (the shot's frames, as gradsep render --frames)")
    spp = None
    if args.spp is not None:
        try:
            spp = int(args.spp)
        except ValueError:
            raise CommandError(f"--spp with --shot is one sample count per frame, got {args.spp!r}") from None
    settings = load_settings(size=args.size, ref_spp=args.ref_spp, ref_spp_cap=args.ref_spp_cap, seed=args.seed,
                             max_depth=args.max_depth)
    preset = QUICK if args.quick else FULL
    size = parse_size(settings.size) if settings.size else (preset.width, preset.height) if args.quick else None
    seconds = None
    if args.seconds is not None:
        from gradsep.renderer.budget import check_seconds

        seconds = check_seconds(args.seconds)
    return ShotConfig(scene=args.shot, frames=args.frames, output=Path(args.output),
                      cache_dir=Path(args.cache) if args.cache else default_cache_dir(),
                      models_dir=models_dir_from(args.models), seconds=seconds, spp=spp,
                      animate=tuple(args.animate or ()), defines=tuple(args.define or ()), size=size,
                      ref_spp=settings.ref_spp or preset.ref_spp, ref_spp_cap=settings.ref_spp_cap,
                      seed=settings.seed or 0,
                      max_depth=settings.max_depth, window=5 if args.window is None else args.window)


def _shot_command(args: argparse.Namespace) -> int:
    """``gradsep evaluate --shot SCENE --frames A-B``: the shot's pipelines at equal seconds (evaluation/shots.py)
    and the report (evaluation/shot_report.py)."""
    from gradsep.evaluation.shot_report import write_shot_report
    from gradsep.evaluation.shots import evaluate_shot

    config = shot_config_from_args(args)
    start = time.perf_counter()
    result = evaluate_shot(config)  # type: ignore[arg-type]
    paths = write_shot_report(result)
    print(f"evaluated shot {result.config.scene} frames {result.numbers[0]}-{result.numbers[-1]}: "
          f"{len(result.rows)} pipelines in {time.perf_counter() - start:.0f} s -> {paths['report']}")
    return 0


def _references_only(config: EvalConfig, shard_text: str | None) -> int:
    """``--references-only [--shard K/N]``: render (a shard of) the reference passes up to the cap, no methods."""
    from gradsep.evaluation.farm import render_reference_shard
    from gradsep.renderer.reference import parse_shard

    try:
        shard = parse_shard(shard_text) if shard_text else (1, 1)
    except ValueError as exc:
        raise CommandError(str(exc)) from exc
    reports = render_reference_shard(config, shard, progress=None, log=lambda m: print(m, file=sys.stderr))
    rendered = sum(r.rendered for r in reports)
    owned = sum(len(r.passes) + len(r.pilots) for r in reports)
    print(f"reference shard {shard[0]}/{shard[1]}: {rendered} passes rendered, "
          f"{owned - rendered} cached (pilot passes included), {len(reports)} scene(s), up to "
          f"{config.reference_cap} spp per reference -> {config.cache_dir / 'evaluate' / 'references'}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="error against run time for every method, with plots and tables")
    p.add_argument("--scenes", nargs="*", default=None, help="XML paths, procedural:SEED or procedural:studio:SEED")
    p.add_argument("--spp", default=None,
                   help="comma-separated sample counts (default 1,2,4,8,16,32,64; 1,4,16 with --quick); with "
                        "--shot one count per frame, instead of --seconds")
    p.add_argument("--quick", action="store_true", help="small CI-sized run (< 10 minutes)")
    p.add_argument("--models", default=None, help=f"folder of exported models (default: ${MODELS_ENV} or models/)")
    p.add_argument("--cache", default=None, help="cache folder (default: $GRADSEP_CACHE or ~/.cache/gradsep)")
    p.add_argument("--size", default=None, metavar="WxH",
                   help="frame size (default 320x240; 96x72 with --quick; with --shot the scene's film)")
    p.add_argument("--ref-spp", type=int, default=None,
                   help="starting samples per pixel of each of the two references; raised (cached, additive) "
                        "until the reference floor is under 10 %% of the scene's smallest ranked RelMSE or "
                        "--ref-spp-cap is reached (default 512; 128 with --quick)")
    p.add_argument("--ref-spp-cap", type=int, default=None,
                   help="most samples per pixel of each reference in full passes (default 4096; 1024 with "
                        "--quick); where the floor is still too high there, region passes add up to as many again "
                        "over the rectangle holding most of it (docs/evaluation.md); equal to --ref-spp: a fixed "
                        "reference spp, no region passes); with --shot each frame's references are raised in passes of "
                        "--ref-spp up to it (default: not raised)")
    p.add_argument("--ref-seconds", type=float, default=None,
                   help="budget of new reference rendering per scene (both references together): the reference "
                        "spp is not raised past what is predicted to fit; passes already in the cache cost "
                        "nothing (default 240; 20 with --quick; 0 = no limit)")
    p.add_argument("--seed", type=int, default=None, help="base seed of every render (default 0)")
    p.add_argument("--methods", default=None,
                   help="comma-separated subset of methods; 'ablation' = the four variants (default: all)")
    p.add_argument("--max-depth", type=int, default=None, help="override every scene's max path depth")
    p.add_argument("--table-spp", type=int, default=None,
                   help="spp of Table 1, the ablation and the crops (default 16 or nearest)")
    p.add_argument("--alpha", type=float, default=None,
                   help=f"screened Poisson data weight for l1/l2 (default {DEFAULT_ALPHA:g})")
    p.add_argument("--time-seeds", type=int, default=None, metavar="N",
                   help="seeds per equal-time row (default 1): each seed gets its own time search and render at "
                        "the budget, the row's metrics are their mean and the report adds the standard error of "
                        "the RelMSE; one seed's error moves by tens of percent between runs, so claims that one "
                        "method beats another at equal time want several")
    p.add_argument("--frame-seeds", type=int, default=None, metavar="N",
                   help="G-PT frames per scene and spp (default 1), each rendered with its own seed: every "
                        "fixed-spp method runs on each, its row is their mean and the report adds the standard "
                        "error of the RelMSE (a few-percent difference between methods on one frame can be that "
                        "frame's luck); the equal-time rows keep the first frame's budget")
    p.add_argument("--references-only", action="store_true",
                   help="render only the reference passes up to --ref-spp-cap and the pilot that places region "
                        "passes into the cache (no methods, no report; -o is still required and left untouched): a "
                        "farm's job, see --shard")
    p.add_argument("--shard", default=None, metavar="K/N",
                   help="with --references-only: render shard K of N of the passes; copy the N caches' "
                        "evaluate/references/ folders into one and run the evaluation there (cached passes cost no "
                        "--ref-seconds budget)")
    _add_shot_arguments(p)
    p.add_argument("-o", "--output", required=True, help="report folder")
    p.set_defaults(func=evaluate_command)


def _add_shot_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of a shot evaluation (docs/evaluation.md, "Shots"); the scene grammar is gradsep render's."""
    p.add_argument("--shot", default=None, metavar="SCENE",
                   help="evaluate a shot instead of frames: any scene gradsep render --frames takes (an XML with "
                        "--animate/-D, a per-frame XML pattern scene.%%04d.xml, procedural:...); per-frame "
                        "RelMSE and flicker of primal + OIDN, the default plan and both reconstructed temporally, "
                        "at equal --seconds per frame")
    p.add_argument("--frames", default=None, metavar="A-B", help="with --shot: the shot's frames, both included")
    p.add_argument("--animate", action="append", default=[], metavar="NAME=START:END",
                   help="with --shot: as gradsep render --animate (repeatable)")
    p.add_argument("-D", "--define", action="append", default=[], metavar="NAME=VALUE",
                   help="with --shot: override a <default> parameter of the XML scene (repeatable)")
    p.add_argument("--seconds", default=None, metavar="T",
                   help="with --shot: every pipeline renders each frame in T seconds (gradsep render --seconds); "
                        "or --spp N, one count, for equal samples instead")
    p.add_argument("--window", type=int, default=None, metavar="N",
                   help="with --shot: frames per temporal window, odd (default 5)")
