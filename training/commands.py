"""`gradsep train | export`: the argument parsers and their handlers.

Only argparse and the import-light model modules at module level: the handlers import torch (through
training.train / training.export) when they run, so ``gradsep --help`` and ``gradsep serve`` work without torch.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from gradsep.model.errors import CommandError
from gradsep.model.policy import ILLUMINATION_LAYERS

if TYPE_CHECKING:
    from gradsep.training.train import TrainConfig


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The typed training configuration of `gradsep train`'s flags (None = the config's default)."""
    from gradsep.model.network import NetworkConfig
    from gradsep.training.train import TrainConfig

    network = NetworkConfig(use_attention=not args.no_attention)
    extra: dict[str, Any] = {}
    for name in ("patch", "batch", "lr", "patches_per_frame"):
        value = getattr(args, name)
        if value is not None:
            extra[name] = value
    if getattr(args, "data_weight", None) is not None:
        extra["alpha"] = args.data_weight
    if getattr(args, "prior_alpha", None) is not None:
        extra["prior_alpha"] = args.prior_alpha
    return TrainConfig(data=args.data, layer=args.layer, output=args.output, network=network,
                       epochs=args.epochs, minutes=args.minutes, seed=args.seed,
                       init=getattr(args, "init", None), **extra)


def train_command(args: argparse.Namespace) -> int:
    """`gradsep train`: bad settings or data become a one-line CommandError."""
    from gradsep.training.train import TrainingError, train

    try:
        cfg = config_from_args(args)
        train(cfg)
    except (ValueError, TrainingError) as exc:  # DatasetError is a ValueError
        raise CommandError(str(exc)) from exc
    return 0


def export_command(args: argparse.Namespace) -> int:
    """`gradsep export RUN -o OUT.onnx`: export, check ONNX Runtime against PyTorch, print a summary."""
    from gradsep.training.export import ExportError, export_run

    try:
        summary = export_run(args.run, args.output)
    except ExportError as exc:
        raise CommandError(str(exc)) from exc
    print(f"wrote {summary['path']} ({summary['bytes'] / 1e6:.1f} MB): layer {summary['layer']}, attention "
          f"{'on' if summary['attention'] else 'off'}, {summary['epochs']} epochs / {summary['steps']} steps, "
          f"ORT-vs-PyTorch relative error {summary['parity_relative_error']:.1e}")
    return 0


def _add_train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, help="dataset folder made by `gradsep dataset`")
    p.add_argument("--layer", choices=ILLUMINATION_LAYERS, required=True,
                   help="color = direct+indirect summed (the no-separation baseline)")
    p.add_argument("--no-attention", action="store_true", help="drop CBAM (GradNet-style ablation)")
    p.add_argument("--minutes", type=float, default=None, help="wall-clock training budget")
    p.add_argument("--epochs", type=int, default=None, help="stop after this many epochs")
    p.add_argument("--patch", type=int, default=None, help="training patch size")
    p.add_argument("--batch", type=int, default=None, help="mini-batch size")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate (default 1e-4, as the paper)")
    p.add_argument("--patches-per-frame", type=int, default=None,
                   help="random crops per training frame per epoch (defines an epoch)")
    p.add_argument("--data-weight", type=float, default=None,
                   help="weight of the data term against the gradient term in the loss (default 1, the paper's)")
    p.add_argument("--prior-alpha", type=float, default=None, metavar="A",
                   help="screening alpha of the Poisson prior the network refines (default: the shipped models'); "
                        "recorded in the model, which is served with it")
    p.add_argument("--init", default=None, metavar="MODEL",
                   help="start from these weights instead of at random: an exported .onnx (models/direct.onnx) or "
                        "a run's checkpoint (.pt); its layer, network and prior kind must match this run's (its prior "
                        "alpha may differ: a warm start onto another prior)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--output", required=True, help="run folder (config, checkpoints, log, curves)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the unsupervised reconstruction network for one layer")
    _add_train_arguments(p)
    p.set_defaults(func=train_command)

    p = sub.add_parser("export", help="export a trained run to ONNX with metadata")
    p.add_argument("run", help="run folder made by `gradsep train`")
    p.add_argument("-o", "--output", required=True, help="output .onnx")
    p.set_defaults(func=export_command)


def train_main(argv: Sequence[str] | None = None) -> int:
    """``torchrun -m gradsep.training ARGS`` (training/__main__.py): `gradsep train ARGS` without the command-line
    package (each torchrun worker runs it); bad input is one line on stderr and exit status 2, as under ``gradsep``."""
    parser = argparse.ArgumentParser(prog="gradsep.training", description="same as `gradsep train`")
    _add_train_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return train_command(args)
    except CommandError as exc:
        print(f"gradsep train: error: {exc}", file=sys.stderr)
        return 2
