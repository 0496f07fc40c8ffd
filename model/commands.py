"""`gradsep reconstruct`: the argument parser and its handler (`gradsep evaluate` lives in evaluation/commands.py).

argparse and the import-light policy module only at module level: the handler imports the solvers lazily, so
building the parser (``gradsep --help``, ``gradsep serve``) costs nothing.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Any

import gradsep.model.methods as table
from gradsep.model.channels import DEFAULT_LAYOUT, choices_text, layouts_text
from gradsep.model.errors import CommandError
from gradsep.model.policy import DEFAULT_ALPHA, MODELS_ENV, models_dir_from


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct", help="reconstruct a frame's illumination layers and write their sum")
    p.add_argument("frame", help="input frame (.exr) per docs/frame-format.md; with --frames a shot's per-frame "
                                 "pattern (shot.%%04d.exr or shot.####.exr)")
    p.add_argument("-o", "--output", required=True, help="output .exr (R G B, plus layers with --layers); with "
                                                         "--frames a pattern with a frame field")
    p.add_argument("--frames", default=None, metavar="A-B",
                   help="reconstruct a shot's frames A to B (both included) temporally, each from a window of "
                        "frames around it through their motion vectors (docs/methods.md, temporal)")
    p.add_argument("--window", type=int, default=5, metavar="N",
                   help="with --frames: frames per window, odd (default 5; 1 is the per-frame method)")
    p.add_argument("--method", choices=table.names(), default=None,
                   help="reconstruction method (" + table.help_text() + ")")
    p.add_argument("--alpha", type=float, default=DEFAULT_ALPHA, help="screened Poisson data weight (methods "
                   + "/".join(m.name for m in table.methods() if m.alpha) + ")")
    p.add_argument("--half", action="store_true", help="write half floats instead of float32")
    p.add_argument("--layers", action="store_true", help="also write each reconstructed layer (direct.R, ...)")
    p.add_argument("--models", default=None, help=f"folder of exported models (default: ${MODELS_ENV} or models/)")
    p.add_argument("--nonfinite", choices=("reject", "zero"), default="reject",
                   help="policy for NaN/Inf radiance or gradients (features are always zeroed)")
    p.add_argument("--channels", default=DEFAULT_LAYOUT, metavar="LAYOUT",
                   help=f"channel layout of the input: {choices_text()} (auto: the one layout the file matches; "
                        f"{layouts_text()})")
    p.set_defaults(func=reconstruct_command)


def _check_output(path: Path) -> None:
    """Fail before the (possibly long) solve when the output cannot be written at all."""
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise CommandError(f"output {str(path)!r} is a directory")
    if not folder.is_dir():
        raise CommandError(f"output folder {str(folder)!r} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CommandError(f"output folder {str(folder)!r} is not writable")


def _resolve_models(models: str | None, method: str | None) -> Any:
    """The loaded models (model.methods.LoadedModels) of the named method (required: a missing set is an error
    naming its folder) or of every method (for the default: optional)."""
    folder = models_dir_from(models)
    wanted = table.get(method).models if method is not None else tuple(table.MODEL_SETS)
    loaded = table.LoadedModels.load(folder, wanted)
    for name in loaded.missing(table.get(method)) if method is not None else ():
        model_set = table.MODEL_SETS[name]
        if model_set.folder is None:  # a runtime library, not a models folder
            raise CommandError(f"--method {method} needs {model_set.description}, which is not installed here")
        raise CommandError(f"--method {method} needs {model_set.description}, but none was found in "
                           f"{str(folder / model_set.folder)!r} (set --models or ${MODELS_ENV}, or use another "
                           "--method)")
    return loaded


def _checked_alpha_layout(args: argparse.Namespace) -> tuple[float, str]:
    from gradsep.model.channels import check_layout

    alpha = float(args.alpha)
    if not (math.isfinite(alpha) and alpha > 0):
        raise CommandError(f"--alpha must be a finite number > 0, got {args.alpha}")
    layout = getattr(args, "channels", DEFAULT_LAYOUT)
    try:
        check_layout(layout)
    except ValueError as exc:
        raise CommandError(f"--channels: {exc}") from None
    return alpha, layout


def _answer_channels(result: Any, layers: bool) -> dict[str, Any]:
    from gradsep.model.frame import rgb_channels

    channels = dict(rgb_channels("", result.image))
    if layers:
        for name, image in result.layers.items():
            channels.update(rgb_channels(name, image))
    return channels


def _answer_metadata(result: Any, source: str, alpha: float) -> dict[str, str]:
    from gradsep.model.header_keys import OIDN_SETTING_KEY

    metadata = {"gradsep.method": result.method, "gradsep.layers": ",".join(result.layers), "gradsep.source": source}
    if table.get(result.method).alpha:
        metadata["gradsep.alpha"] = f"{alpha:g}"
    if result.oidn_setting:
        metadata[OIDN_SETTING_KEY] = result.oidn_setting
    return metadata


def _write(output: Path, data: bytes) -> None:
    from gradsep.model.exr_write import write_bytes_atomic

    try:
        write_bytes_atomic(output, data)
    except OSError as exc:
        raise CommandError(f"cannot write {str(output)!r}: {exc.strerror or exc}") from exc


def reconstruct_command(args: argparse.Namespace) -> int:
    """``gradsep reconstruct FRAME -o OUT``: read, reconstruct every layer, write ``R G B`` (+ layers) atomically.

    Bad input raises FrameError/CommandError (the dispatcher prints one line and exits 2) before anything is
    written; the output appears only complete (temporary file + rename).
    """
    from gradsep.model.errors import FrameError
    from gradsep.model.exr_read import read_frame
    from gradsep.model.exr_write import encode_answer
    from gradsep.model.reconstruct import reconstruct

    if getattr(args, "frames", None) is not None:
        return reconstruct_shot(args)
    output = Path(args.output)
    alpha, layout = _checked_alpha_layout(args)
    _check_output(output)
    frame = read_frame(args.frame, nonfinite=args.nonfinite, layout=layout)
    models = _resolve_models(getattr(args, "models", None), args.method)
    try:
        result = reconstruct(frame, args.method, alpha, models)
    except ValueError as exc:
        if isinstance(exc, FrameError):
            raise
        raise CommandError(str(exc)) from exc
    metadata = _answer_metadata(result, Path(args.frame).name, alpha)
    warnings = [*frame.warnings, *result.warnings]
    data = encode_answer(frame, _answer_channels(result, args.layers), half=bool(args.half), metadata=metadata,
                         warnings=warnings)
    _write(output, data)
    for warning in warnings:
        print(f"gradsep reconstruct: warning: {warning}", file=sys.stderr)
    per_layer = ", ".join(f"{name} {seconds:.2f} s" for name, seconds in result.timings.items())
    print(f"reconstructed {frame.width}x{frame.height} with {result.method}: {per_layer}; "
          f"total {sum(result.timings.values()):.2f} s -> {output}")
    return 0


# ------------------------------------------------------------------------------------------------ shots


#: The header key naming the frames whose samples reached a temporally reconstructed frame.
NEIGHBOURS_KEY = "gradsep.temporal.neighbours"
WINDOW_KEY = "gradsep.temporal.window"


def _shot_inputs(args: argparse.Namespace) -> tuple[range, Any, Any, int]:
    """The shot's frames, input and output patterns and window, checked (CommandError naming what is wrong)."""
    from gradsep.model.shot import FramePattern, parse_frames

    frames = parse_frames(args.frames)
    source = FramePattern(args.frame).require_field("input")
    output = FramePattern(args.output).require_field("output")
    window = int(args.window)
    if window < 1 or window % 2 == 0:
        raise CommandError(f"--window must be an odd number of frames >= 1, got {args.window}")
    missing = [str(source.path(n)) for n in frames if not source.path(n).is_file()]
    if missing:
        raise CommandError(f"frame {missing[0]} of the shot is missing" + (f" (and {len(missing) - 1} more)"
                                                                           if len(missing) > 1 else ""))
    for n in frames:
        _check_output(output.path(n))
    return frames, source, output, window


def _check_headers(paths: list[Path]) -> None:
    """Every frame of the shot has the first frame's size and channels (read from the headers, before any work).
    Motion vectors are left out of the comparison: a shot's first and last frames carry one side only."""
    from gradsep.model.exr_read import read_header
    from gradsep.model.frame import shot_layout

    first = None
    for path in paths:
        info = read_header(path)
        signature = (info.width, info.height, shot_layout(info.channels))
        if first is None:
            first = (path, signature)
        elif signature[:2] != first[1][:2]:
            raise CommandError(f"frame {path} is {info.width}x{info.height}, but {first[0]} is "
                               f"{first[1][0]}x{first[1][1]}: the frames of one shot must have one size")
        elif signature != first[1]:
            extra = sorted(set(signature[2]) ^ set(first[1][2]))
            raise CommandError(f"frame {path} carries other channels than {first[0]} (differing: "
                               f"{', '.join(extra[:6])}): the frames of one shot must have one layout")


def reconstruct_shot(args: argparse.Namespace) -> int:
    """``gradsep reconstruct 'shot.%04d.exr' --frames A-B -o 'out.%04d.exr' [--window N]``: each frame from its
    window (model/temporal.py), each output written atomically as it is done, its header naming the frames used.
    Neighbours outside A-B are used where their files exist (a chunk of a longer shot joins its neighbours); a
    missing one is a warning, and the frame uses what it has."""
    from gradsep.model.errors import FrameError
    from gradsep.model.exr_read import read_frame
    from gradsep.model.temporal import ShotReconstructor

    alpha, layout = _checked_alpha_layout(args)
    frames, source, output, window = _shot_inputs(args)
    radius = window // 2
    around = range(max(0, frames.start - radius), frames.stop + radius)
    _check_headers([source.path(n) for n in around if source.path(n).is_file()])
    models = _resolve_models(getattr(args, "models", None), args.method)

    def load(n: int) -> Any:
        path = source.path(n) if n >= 0 else None
        return read_frame(path, nonfinite=args.nonfinite, layout=layout) if path and path.is_file() else None

    shot = ShotReconstructor(load, window, args.method, alpha, models)
    for n in frames:
        try:
            result = shot.reconstruct(n)
        except ValueError as exc:
            if isinstance(exc, FrameError):
                raise
            raise CommandError(f"{source.path(n)}: {exc}") from exc
        _write_shot_frame(args, n, result, load(n), (source, output, window, alpha))
    return 0


def _write_shot_frame(args: argparse.Namespace, n: int, result: Any, frame: Any, shot: tuple) -> None:
    """Write frame ``n``'s answer atomically with the temporal header keys; print its warnings and a line."""
    from gradsep.model.exr_write import encode_answer

    source, output, window, alpha = shot
    radius = window // 2
    absent = [n + o for o in range(-radius, radius + 1) if o and n + o >= 0 and not source.path(n + o).is_file()]
    warnings = [*frame.warnings, *(w for w in result.warnings if not w.startswith("neighbour(s) "))]
    if window > 1 and getattr(frame, "motion", None) is None:
        warnings.append("the frame has no motion vectors: reconstructed on its own (the per-frame method)")
    elif absent:
        warnings.append("neighbour frame(s) " + ", ".join(map(str, absent)) + " missing: reconstructed from the "
                        "frames it has")
    metadata = _answer_metadata(result, source.path(n).name, alpha)
    metadata[NEIGHBOURS_KEY] = ",".join(str(n + o) for o in result.neighbours)
    metadata[WINDOW_KEY] = str(window)
    data = encode_answer(frame, _answer_channels(result, args.layers), half=bool(args.half), metadata=metadata,
                         warnings=warnings)
    path = output.path(n)
    _write(path, data)
    for warning in warnings:
        print(f"gradsep reconstruct: frame {n}: warning: {warning}", file=sys.stderr)
    used = metadata[NEIGHBOURS_KEY] or "none"
    print(f"reconstructed frame {n} ({frame.width}x{frame.height}) with {result.method} from frames {used} and "
          f"itself -> {path}")
