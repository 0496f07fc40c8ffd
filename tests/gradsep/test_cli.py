"""The `gradsep` command line (gradsep/cli.py): the roof that parses and dispatches.

Dispatch to each package's handler, the exit statuses (0, 2 for user errors, 130 for ^C, argparse's 2 for bad
flags), the help listing every command, and command modules that are missing or broken being an error.
"""

from __future__ import annotations

import argparse
import importlib.machinery
import subprocess
import sys
import types
from pathlib import Path

import pytest

from gradsep import cli
from gradsep.model.errors import ChannelError, CommandError

REPO = Path(__file__).resolve().parents[2]
EVERY_COMMAND = ("render", "reference", "dataset", "train", "export", "reconstruct", "evaluate", "serve", "client")


def fake_module(monkeypatch: pytest.MonkeyPatch, name: str, handler) -> None:
    """Install ``name`` (a command module) whose one subcommand ``fake`` runs ``handler``."""
    module = types.ModuleType(name)
    module.__spec__ = importlib.machinery.ModuleSpec(name, None, origin="<test>")

    def register(sub: argparse._SubParsersAction) -> None:
        p = sub.add_parser("fake", help="a test command")
        p.add_argument("--value", type=int, default=0)
        p.set_defaults(func=handler)

    module.register = register  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.setattr(cli, "COMMAND_MODULES", (*cli.COMMAND_MODULES, name))


def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        cli.main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    missing = [c for c in EVERY_COMMAND if f"\n    {c} " not in out and f"\n    {c}\n" not in out]
    assert missing == [], out


@pytest.mark.parametrize("command", EVERY_COMMAND)
def test_each_command_has_help_and_a_handler(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    parser = cli.build_parser()
    with pytest.raises(SystemExit) as info:
        parser.parse_args([command, "--help"])
    assert info.value.code == 0 and "usage: gradsep " + command in capsys.readouterr().out
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    handler = sub.choices[command].get_default("func")
    assert callable(handler) and handler.__module__.endswith(".commands"), handler


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.model import __version__

    with pytest.raises(SystemExit) as info:
        cli.main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"gradsep {__version__}"


def test_dispatch_passes_the_parsed_arguments_and_returns_the_handler_status(monkeypatch) -> None:
    seen: list[argparse.Namespace] = []

    def handler(args: argparse.Namespace) -> int:
        seen.append(args)
        return 75

    fake_module(monkeypatch, "tests_fake_commands", handler)
    assert cli.main(["fake", "--value", "3"]) == 75
    assert seen[0].value == 3 and seen[0].command == "fake"


@pytest.mark.parametrize("error", [CommandError("bad --value"), ChannelError("missing channels direct.R")])
def test_user_errors_are_one_line_and_exit_2(monkeypatch, capsys, error: Exception) -> None:
    def handler(args: argparse.Namespace) -> int:
        raise error

    fake_module(monkeypatch, "tests_fake_commands", handler)
    assert cli.main(["fake"]) == 2
    err = capsys.readouterr().err
    assert err == f"gradsep fake: error: {error}\n"


def test_interrupt_exits_130(monkeypatch, capsys) -> None:
    def handler(args: argparse.Namespace) -> int:
        raise KeyboardInterrupt

    fake_module(monkeypatch, "tests_fake_commands", handler)
    assert cli.main(["fake"]) == 130
    assert "interrupted" in capsys.readouterr().err


def test_other_exceptions_are_not_swallowed(monkeypatch) -> None:
    """A bug is a traceback (exit 1), not a one-line 'user error'."""
    def handler(args: argparse.Namespace) -> int:
        raise RuntimeError("a bug")

    fake_module(monkeypatch, "tests_fake_commands", handler)
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main(["fake"])


def test_bad_flags_and_no_command_are_usage_errors(capsys) -> None:
    for argv in ([], ["no-such-command"], ["reconstruct"]):
        with pytest.raises(SystemExit) as info:
            cli.main(argv)
        assert info.value.code == 2, argv
    assert "usage: gradsep" in capsys.readouterr().err


def test_a_missing_command_module_of_an_installed_package_is_an_error(monkeypatch) -> None:
    """`model` is installed, `model.no_such_commands` is not: an error, not a silently absent command."""
    monkeypatch.setattr(cli, "COMMAND_MODULES", (*cli.COMMAND_MODULES, "gradsep.model.no_such_commands"))
    with pytest.raises(cli.CommandModuleError, match="gradsep.model.no_such_commands"):
        cli.build_parser()


def test_a_broken_command_module_is_an_error(monkeypatch, tmp_path: Path) -> None:
    package = tmp_path / "tests_broken_pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "commands.py").write_text("import argparse\nimport no_such_dependency_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(cli, "COMMAND_MODULES", (*cli.COMMAND_MODULES, "tests_broken_pkg.commands"))
    with pytest.raises(cli.CommandModuleError, match="no_such_dependency_xyz"):
        cli.build_parser()


def test_a_command_module_without_register_is_an_error(monkeypatch) -> None:
    module = types.ModuleType("tests_empty_commands")
    module.__spec__ = importlib.machinery.ModuleSpec("tests_empty_commands", None, origin="<test>")
    monkeypatch.setitem(sys.modules, "tests_empty_commands", module)
    monkeypatch.setattr(cli, "COMMAND_MODULES", (*cli.COMMAND_MODULES, "tests_empty_commands"))
    with pytest.raises(cli.CommandModuleError, match="no register"):
        cli.build_parser()


def test_a_package_left_out_of_the_install_drops_only_its_commands(monkeypatch) -> None:
    """The serving image installs gradsep/, model/ and service/ only (Dockerfile): the other roles' packages are
    absent there, and their commands with them; the rest of the CLI works."""
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("gradsep.model.commands", "tests_absent_package_xyz.commands"))
    parser = cli.build_parser()
    assert parser.parse_args(["reconstruct", "f.exr", "-o", "o.exr"]).command == "reconstruct"


def test_a_same_named_data_folder_is_not_taken_for_a_package(monkeypatch, tmp_path: Path) -> None:
    """On a serving host `python -m gradsep` run in a folder holding e.g. `tests_data_folder/` (no __init__.py)
    must not try to load commands from it."""
    (tmp_path / "tests_data_folder").mkdir()
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("gradsep.model.commands", "tests_data_folder.commands"))
    assert "reconstruct" in cli.build_parser().format_help()


def test_python_dash_m_gradsep_runs_the_same_cli() -> None:
    run = subprocess.run([sys.executable, "-m", "gradsep", "reconstruct", str(REPO / "no-such.exr"), "-o",
                          str(REPO / "no-such-folder" / "o.exr")], cwd=REPO, capture_output=True, text=True,
                         timeout=120, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 2, run.stderr
    assert run.stderr.startswith("gradsep reconstruct: error: output folder") and run.stderr.count("\n") == 1
