"""The `gradsep` console command: one subcommand per job.

Each package registers its own subcommands in a light ``commands.py`` (argparse only, no heavy imports at
module level), so `gradsep serve` works on a serving host without torch or mitsuba installed.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from gradsep import __version__

# Packages whose `commands.register(subparsers)` adds subcommands, in help order.
COMMAND_MODULES = ("renderer.commands", "training.commands", "model.commands", "evaluation.commands",
                   "service.commands")


class CommandError(Exception):
    """A user-facing failure: printed as one line on stderr, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gradsep", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"gradsep {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a package not present in this install
            if exc.name and name.startswith(exc.name):
                continue
            raise
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from model.frame import FrameError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (CommandError, FrameError) as exc:
        print(f"gradsep {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gradsep {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
