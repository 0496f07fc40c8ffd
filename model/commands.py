"""`gradsep reconstruct`: argparse only; the handler imports the solvers lazily (`gradsep evaluate` lives in
evaluation/commands.py)."""

from __future__ import annotations

import argparse

from model.policy import DEFAULT_PREFERENCE, METHODS


def _reconstruct(args: argparse.Namespace) -> int:
    from model.reconstruct import reconstruct_command

    return reconstruct_command(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct", help="reconstruct a frame's illumination layers and write their sum")
    p.add_argument("frame", help="input frame (.exr) per docs/frame-format.md")
    p.add_argument("-o", "--output", required=True, help="output .exr (R G B, plus layers with --layers)")
    p.add_argument("--method", choices=METHODS, default=None,
                   help="reconstruction method (default: the best that serves the frame -- "
                        + " > ".join(DEFAULT_PREFERENCE) + "; a plain frame without gradients gets oidn)")
    p.add_argument("--alpha", type=float, default=0.2, help="screened Poisson data weight (l1/l2)")
    p.add_argument("--half", action="store_true", help="write half floats instead of float32")
    p.add_argument("--layers", action="store_true", help="also write each reconstructed layer (direct.R, ...)")
    p.add_argument("--models", default=None, help="folder of exported models (default: $GRADSEP_MODELS or models/)")
    p.add_argument("--nonfinite", choices=("reject", "zero"), default="reject",
                   help="policy for NaN/Inf radiance or gradients (features are always zeroed)")
    p.set_defaults(func=_reconstruct)
