"""`gradsep train | export`: argparse only; handlers import torch lazily."""

from __future__ import annotations

import argparse


def _train(args: argparse.Namespace) -> int:
    from training.train import train_command

    return train_command(args)


def _export(args: argparse.Namespace) -> int:
    from training.export import export_command

    return export_command(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the unsupervised reconstruction network for one layer")
    p.add_argument("--data", required=True, help="dataset folder made by `gradsep dataset`")
    p.add_argument("--layer", choices=("direct", "indirect", "color"), required=True,
                   help="color = direct+indirect summed (the no-separation baseline)")
    p.add_argument("--no-attention", action="store_true", help="drop CBAM (GradNet-style ablation)")
    p.add_argument("--minutes", type=float, default=None, help="wall-clock training budget")
    p.add_argument("--epochs", type=int, default=None, help="stop after this many epochs")
    p.add_argument("--patch", type=int, default=None, help="training patch size")
    p.add_argument("--batch", type=int, default=None, help="mini-batch size")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate (default 1e-4, as the paper)")
    p.add_argument("--patches-per-frame", type=int, default=None,
                   help="random crops per training frame per epoch (defines an epoch)")
    p.add_argument("--prior", choices=("l1", "oidn"), default=None,
                   help="what the network refines: l1 = truncated Poisson solve (the network method, default); "
                        "oidn = OIDN's denoise at a normalised exposure (the fused method)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--output", required=True, help="run folder (config, checkpoints, log, curves)")
    p.set_defaults(func=_train)

    p = sub.add_parser("export", help="export a trained run to ONNX with metadata")
    p.add_argument("run", help="run folder made by `gradsep train`")
    p.add_argument("-o", "--output", required=True, help="output .onnx")
    p.set_defaults(func=_export)
