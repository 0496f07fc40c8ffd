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
    p.add_argument("frame", help="input frame (.exr) per docs/frame-format.md")
    p.add_argument("-o", "--output", required=True, help="output .exr (R G B, plus layers with --layers)")
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


def reconstruct_command(args: argparse.Namespace) -> int:
    """``gradsep reconstruct FRAME -o OUT``: read, reconstruct every layer, write ``R G B`` (+ layers) atomically.

    Bad input raises FrameError/CommandError (the dispatcher prints one line and exits 2) before anything is
    written; the output appears only complete (temporary file + rename).
    """
    from gradsep.model.channels import check_layout
    from gradsep.model.errors import FrameError
    from gradsep.model.exr_read import read_frame
    from gradsep.model.exr_write import encode_answer, write_bytes_atomic
    from gradsep.model.frame import rgb_channels
    from gradsep.model.header_keys import OIDN_SETTING_KEY
    from gradsep.model.reconstruct import reconstruct

    output = Path(args.output)
    alpha = float(args.alpha)
    if not (math.isfinite(alpha) and alpha > 0):
        raise CommandError(f"--alpha must be a finite number > 0, got {args.alpha}")
    layout = getattr(args, "channels", DEFAULT_LAYOUT)
    try:
        check_layout(layout)
    except ValueError as exc:
        raise CommandError(f"--channels: {exc}") from None
    _check_output(output)
    frame = read_frame(args.frame, nonfinite=args.nonfinite, layout=layout)
    models = _resolve_models(getattr(args, "models", None), args.method)
    try:
        result = reconstruct(frame, args.method, alpha, models)
    except ValueError as exc:
        if isinstance(exc, FrameError):
            raise
        raise CommandError(str(exc)) from exc
    method = result.method

    channels = dict(rgb_channels("", result.image))
    if args.layers:
        for name, image in result.layers.items():
            channels.update(rgb_channels(name, image))
    metadata = {"gradsep.method": method, "gradsep.layers": ",".join(result.layers),
                "gradsep.source": Path(args.frame).name}
    if table.get(method).alpha:
        metadata["gradsep.alpha"] = f"{alpha:g}"
    if result.oidn_setting:
        metadata[OIDN_SETTING_KEY] = result.oidn_setting
    warnings = [*frame.warnings, *result.warnings]
    data = encode_answer(frame, channels, half=bool(args.half), metadata=metadata, warnings=warnings)
    try:
        write_bytes_atomic(output, data)
    except OSError as exc:
        raise CommandError(f"cannot write {str(output)!r}: {exc.strerror or exc}") from exc

    for warning in warnings:
        print(f"gradsep reconstruct: warning: {warning}", file=sys.stderr)
    per_layer = ", ".join(f"{name} {seconds:.2f} s" for name, seconds in result.timings.items())
    print(f"reconstructed {frame.width}x{frame.height} with {method}: {per_layer}; "
          f"total {sum(result.timings.values()):.2f} s -> {output}")
    return 0
