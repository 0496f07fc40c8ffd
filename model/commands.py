"""`gradsep reconstruct | evaluate`: argparse only; handlers import the solvers lazily."""

from __future__ import annotations

import argparse

from model.policy import DEFAULT_PREFERENCE, METHODS


def _reconstruct(args: argparse.Namespace) -> int:
    from model.reconstruct import reconstruct_command

    return reconstruct_command(args)


def _evaluate(args: argparse.Namespace) -> int:
    from model.evaluate import evaluate_command

    return evaluate_command(args)


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

    p = sub.add_parser("evaluate", help="error against run time for every method, with plots and tables")
    p.add_argument("--scenes", nargs="*", default=None, help="XML paths or procedural:SEED")
    p.add_argument("--spp", default=None,
                   help="comma-separated sample counts (default 1,2,4,8,16,32,64; 1,4,16 with --quick)")
    p.add_argument("--quick", action="store_true", help="small CI-sized run (< 10 minutes)")
    p.add_argument("--models", default=None, help="folder of exported models (default: $GRADSEP_MODELS or models/)")
    p.add_argument("--cache", default=None, help="cache folder (default: $GRADSEP_CACHE or ~/.cache/gradsep)")
    p.add_argument("--size", default=None, metavar="WxH", help="frame size (default 320x240; 96x72 with --quick)")
    p.add_argument("--ref-spp", type=int, default=None,
                   help="reference samples per pixel (default 1024; 256 with --quick)")
    p.add_argument("--seed", type=int, default=None, help="base seed of every render (default 0)")
    p.add_argument("--methods", default=None,
                   help="comma-separated subset of methods; 'ablation' = the four variants (default: all)")
    p.add_argument("--max-depth", type=int, default=None, help="override every scene's max path depth")
    p.add_argument("--table-spp", type=int, default=None,
                   help="spp of Table 1, the ablation and the crops (default 16 or nearest)")
    p.add_argument("--alpha", type=float, default=None, help="screened Poisson data weight for l1/l2 (default 0.2)")
    p.add_argument("-o", "--output", required=True, help="report folder")
    p.set_defaults(func=_evaluate)
