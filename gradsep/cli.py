"""The `gradsep` console command: one subcommand per job.

The roof of the import graph: it parses arguments and dispatches, nothing else. Each package registers its own
subcommands and their handlers in a light ``commands.py`` (argparse and the import-light model modules only at
module level; the handlers import the heavy modules), so `gradsep serve` works on a serving host without torch
or mitsuba installed. No library module imports this package (tests/test_layering.py checks it).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
from collections.abc import Sequence

from gradsep.model import __version__
from gradsep.model.errors import CommandError


class CommandModuleError(ImportError):
    """An installed package's command module is missing or broken (not a user error: a traceback, exit 1)."""


# Packages whose `commands.register(subparsers)` adds subcommands, in help order.
COMMAND_MODULES = ("gradsep.renderer.commands", "gradsep.training.commands", "gradsep.model.commands",
                   "gradsep.evaluation.commands", "gradsep.service.commands")


def build_parser(modules: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser with every installed package's subcommands.

    A role-specific install may leave whole packages out (the serving image has no renderer/, training/ or
    evaluation/, Dockerfile): their commands are then absent. A package that is installed but whose command
    module is missing or fails to import is a broken install or a bug, and raises CommandModuleError instead of
    silently dropping commands (the modules import only argparse and model/, which every install has).
    """
    parser = argparse.ArgumentParser(prog="gradsep", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"gradsep {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES if modules is None else modules:
        try:
            spec = importlib.util.find_spec(name.rpartition(".")[0] or name)
        except ModuleNotFoundError:  # a parent package of it is absent too
            spec = None
        # The whole package is not part of this install. A folder of that name without __init__.py (a
        # namespace package) is not it.
        if spec is None or spec.origin is None:
            continue
        try:
            module = importlib.import_module(name)
        except ImportError as exc:
            raise CommandModuleError(f"command module {name} cannot be imported: {type(exc).__name__}: {exc}") \
                from exc
        register = getattr(module, "register", None)
        if not callable(register):
            raise CommandModuleError(f"command module {name} has no register(subparsers) function")
        register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from gradsep.model.allocator import configure_malloc
    from gradsep.model.errors import FrameError  # numpy + OpenEXR: not for the parser
    from gradsep.model.exr_write import configure_exr_threads

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        configure_malloc()  # one malloc arena for the frame-sized work of every command (model/allocator.py)
        configure_exr_threads()  # every command's EXR encoding and decoding on every core (the service: its setting)
    except ValueError as exc:
        print(f"gradsep {args.command}: error: {exc}", file=sys.stderr)
        return 2
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
