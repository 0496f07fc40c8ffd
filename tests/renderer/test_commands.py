"""`gradsep render --seconds T` and ``--gradients auto`` on the command line (renderer/commands.py): bad input is
one line, exit 2 and no file; the default plan; a budget below the start-up cost; a budgeted frame's header."""

from __future__ import annotations

import json

import pytest

from gradsep.cli import main
from gradsep.model.exr_read import read_frame
from gradsep.model.header_keys import OIDN_SETTING_KEY, PREDICTED_RELMSE_KEY
from gradsep.renderer import budget, reconstruction_cost
from gradsep.renderer.plans import PLAN_KEY
from tests.renderer.scenes import resolve

CBOX = str(resolve("cbox"))
SMALL = ["--width", "16", "--height", "12"]


@pytest.mark.parametrize(("args", "message"), [
    (["--spp", "4", "--seconds", "5"], "exactly one of --spp"),
    ([], "exactly one of --spp"),
    (["--seconds", "0"], "--seconds must be a finite number > 0"),
    (["--seconds", "-3"], "--seconds must be a finite number > 0"),
    (["--seconds", "nan"], "--seconds must be a finite number > 0"),
    (["--seconds", "inf"], "--seconds must be a finite number > 0"),
    (["--seconds", "soon"], "--seconds must be a number"),
    (["--seconds", "0.001"], "below this machine's start-up cost"),  # the process is older than that already
    (["--seconds", "5", "--gradient-spp", "2", "--gradients", "all"], "--gradient-spp needs --spp"),
    (["--spp", "8", "--gradients", "auto", "--offsets", "pair"], "--offsets is chosen by the plan"),
    (["--seconds", "5", "--offsets", "pair"], "with --gradients auto (the default with --seconds)"),
    (["--spp", "0", "--gradients", "auto"], "--spp must be >= 1"),
])
def test_bad_input_is_one_line_exit_2_and_no_file(tmp_path, capsys, args, message):
    out = tmp_path / "f.exr"
    assert main(["render", CBOX, *SMALL, *args, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("args", "gradients"), [
    (["--seconds", "5"], "auto"),  # a budget: the plan chosen per scene
    (["--spp", "4"], "all"),  # a sample count: the frame that serves every method
    (["--seconds", "5", "--gradients", "all"], "all"),
    (["--seconds", "5", "--no-gradients"], "none"),
    (["--spp", "4", "--gradients", "auto"], "auto"),
])
def test_the_default_plan_is_auto_with_a_budget_and_all_with_a_sample_count(args, gradients):
    import argparse

    from gradsep.renderer.commands import default_gradients, register

    sub = argparse.ArgumentParser().add_subparsers()
    register(sub)
    assert default_gradients(sub.choices["render"].parse_args([CBOX, *args, "-o", "f.exr"])) == gradients


@pytest.mark.render
def test_seconds_below_the_start_up_cost_after_loading_writes_nothing(tmp_path, capsys, monkeypatch):
    """With the process's own start-up not counted, a budget that one pass and the write cannot fit is still
    refused once the scene is loaded and the first pass measured: exit 2, nothing written."""
    monkeypatch.setattr(budget, "process_age", lambda: 0.0)
    out = tmp_path / "f.exr"
    assert main(["render", CBOX, *SMALL, "--seconds", "0.02", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "below this machine's start-up cost" in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.render
@pytest.mark.slow
def test_seconds_writes_a_frame_with_its_budget_in_the_header(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(budget, "process_age", lambda: 0.0)
    # the reconstruction's start-up as if paid (as after another test): the frame's check then fits 8 s
    monkeypatch.setattr(reconstruction_cost, "reconstruct_startup", lambda: 0.0)
    out = tmp_path / "f.exr"
    # 8 s: the kernel's compile and a second pass fit on a loaded 2-core machine (4 s left 1 pass at load ~6)
    assert main(["render", CBOX, *SMALL, "--seconds", "8", "--gradients", "direct", "--offsets", "alternate",
                 "-o", str(out)]) == 0
    assert "of 8 s" in capsys.readouterr().out
    frame = read_frame(out)
    meta = frame.metadata
    assert meta["gradsep.budget_seconds"] == "8" and float(meta["gradsep.elapsed_seconds"]) > 0
    assert meta[PLAN_KEY] == "direct-alternate" and meta["gradsep.offsets"] == "alternate"
    assert int(meta["gradsep.spp"]) >= 2 and int(meta["gradsep.passes"]) >= 2
    # a fixed plan has no pilot, but a frame this small fits its own check: its estimate; a frame with gradients
    # keeps the rule's setting (16x12 px: the better denoiser is free at 8 s), with no comparison
    check = json.loads(meta["gradsep.frame_check"])
    assert meta["gradsep.predicted_from"] == "frame" and float(meta[PREDICTED_RELMSE_KEY]) >= 0
    assert "options" not in check and meta["gradsep.plan_method"] == "oidn-l1"
    assert meta[OIDN_SETTING_KEY] == "prefiltered-high"
    assert frame.layers["direct"].has_gradients and not frame.layers["indirect"].has_gradients
    assert list(tmp_path.iterdir()) == [out]
