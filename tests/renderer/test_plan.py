"""The render planner (renderer/plan.py): `gradsep render --seconds T` and `--gradients auto`.

The deadline logic itself is tested against a fake clock in test_budget.py and the error estimate on synthetic
images in test_estimate.py; here: the command's bad input (exit 2, one line, no file), the passes of several
plans merged into one frame, the pilot's choice with a stand-in reconstruction whose errors are known, the
header, and the layers a scene without indirect light plans. Timing targets are benchmarks/bench_planner.py's.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gradsep.cli import main
from gradsep.model.exr_read import read_frame
from gradsep.model.frame import Frame, Layer
from gradsep.model.header_keys import OIDN_SETTING_KEY
from gradsep.renderer import budget
from gradsep.renderer.plan import (
    CANDIDATES,
    PLAN_KEY,
    PREDICTED_RELMSE_KEY,
    Candidate,
    applicable,
    candidate,
    fallback,
    plan_layers_text,
    tiles,
    warm_reconstruction,
    write_seconds,
)
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


def test_tiles_cover_small_frames_whole_and_spread_over_large_ones():
    assert tiles(64, 48) == [(slice(0, 48), slice(0, 64))]
    windows = tiles(1280, 720)
    assert len(windows) == 4
    for ys, xs in windows:
        assert ys.stop - ys.start == 128 and xs.stop - xs.start == 128
        assert 0 <= ys.start and ys.stop <= 720 and 0 <= xs.start and xs.stop <= 1280
    assert len({(w[0].start, w[1].start) for w in windows}) == 4


def test_the_write_is_timed_on_bands_that_use_every_thread_of_openexrs_pool():
    """ZIP encodes blocks of 16 rows, one per thread: a band of one block would time one core of a parallel write."""
    import OpenEXR

    rng = np.random.default_rng(0)
    frame = Frame(layers={"color": Layer(base=rng.random((200, 40, 3), dtype=np.float32))})
    asked: list[int] = []

    def band(window: tuple[slice, slice]) -> Frame:
        rows = window[0]
        asked.append(rows.stop - rows.start)
        return Frame(layers={"color": Layer(base=frame.layers["color"].base[rows])})

    before = OpenEXR.global_thread_count()
    try:
        for threads, rows in ((0, 16), (1, 16), (2, 32), (4, 64)):
            OpenEXR.set_global_thread_count(threads)
            asked.clear()
            assert write_seconds(band, 40, 200) > 0
            assert asked[1:] == [rows] * 3  # after the one-row warm-up
    finally:
        OpenEXR.set_global_thread_count(before)


def test_the_reconstruction_start_up_is_paid_in_the_background_both_ways_and_only_once(monkeypatch):
    """The checkpoint's first reconstruction pays the library's start-up: a thread pays it on a small tile, with
    gradients and as a plain frame, while passes render. An error there is left for the foreground to raise."""
    import sys

    rng = np.random.default_rng(0)
    grad = rng.random((16, 16, 3), dtype=np.float32)
    tile = Frame(layers={"direct": Layer(base=grad, dx=grad, dy=grad)})
    seen: list[bool] = []

    def fake(frame: Frame):
        seen.append(frame.layers["direct"].has_gradients)
        raise RuntimeError("the library failed")  # swallowed in the thread

    monkeypatch.delitem(sys.modules, "pyoidn", raising=False)
    thread = warm_reconstruction(tile, fake)
    assert thread is not None
    thread.join(timeout=10)
    assert seen == [True]  # the first call raised: the thread stopped there, quietly
    seen.clear()
    thread = warm_reconstruction(tile, lambda f: (seen.append(f.layers["direct"].has_gradients), ("", ""))[1])
    thread.join(timeout=10)
    assert seen == [True, False]
    monkeypatch.setitem(sys.modules, "pyoidn", object())
    assert warm_reconstruction(tile, fake) is None  # paid already


def test_candidates_and_their_layers():
    assert [c.name for c in applicable(("direct", "indirect"))] == ["direct-alternate", "primal"]
    assert [c.name for c in applicable(("direct",))] == ["direct-alternate", "primal"]
    assert [c.name for c in applicable(("color",))] == ["all", "primal"]  # no direct layer to trace alone
    assert [c.name for c in applicable(("indirect",))] == ["all", "primal"]
    assert fallback(("direct", "indirect")).name == "direct-alternate" and fallback(("color",)).name == "all"
    assert {c.name for c in CANDIDATES} == {"primal", "direct-alternate", "direct", "all"}
    assert plan_layers_text(candidate("direct-alternate"), ("direct", "indirect")) == "direct=alternate,indirect=none"
    assert plan_layers_text(candidate("primal"), ("direct",)) == "direct=none"
    assert plan_layers_text(candidate("direct"), ("direct", "indirect")) == "direct=all,indirect=none"


# --------------------------------------------------------------------------------------------- rendering

mi = pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def small():
    from gradsep.renderer.scene import load_scene

    return load_scene(CBOX, width=16, height=12, max_depth=5)


@pytest.mark.render
def test_passes_of_one_plan_are_render_gpt_bit_for_bit(small):
    from gradsep.renderer.gpt import GptSettings, render_gpt
    from gradsep.renderer.plan import Passes
    from gradsep.renderer.shift import make_shift

    passes = Passes(small, ("direct", "indirect"), seed=5)
    passes.run(Candidate("all", "all"), 3)
    mine = passes.frame_result(Candidate("all", "all"))
    ref = render_gpt(small.scene, make_shift("hybrid"), GptSettings(max_depth=5), 16, 12, 3, seed=5)
    for layer in ("direct", "indirect"):
        for key in ("base", "dx", "dy"):
            np.testing.assert_array_equal(mine.layers[layer][key], ref.layers[layer][key])
    np.testing.assert_array_equal(mine.albedo, ref.albedo)


@pytest.mark.render
def test_passes_of_several_plans_share_bases_and_keep_their_own_gradients(small):
    from gradsep.renderer.plan import Passes

    passes = Passes(small, ("direct", "indirect"), seed=1)
    primal = passes.run(candidate("primal"), 2)
    kept = {k: v.copy() for k, v in primal.items()}
    direct = passes.run(candidate("direct-alternate"), 1)
    full = passes.run(Candidate("all", "all"), 3)
    assert passes.spp == 6 and passes.index == 3
    for k, v in kept.items():  # the frame's sums are added in place, never into a pass's own
        np.testing.assert_array_equal(primal[k], v)
    r = passes.frame_result(Candidate("all", "all"))
    expected = (primal["direct.base"] + direct["direct.base"] + full["direct.base"]) / 6
    np.testing.assert_allclose(r.layers["direct"]["base"], expected.astype(np.float32), rtol=1e-6)
    assert passes.gradients["all"][1] == 3 and passes.gradients["direct-alternate"][1] == 1
    assert "dx" in r.layers["indirect"]  # from the all passes alone
    d = passes.frame_result(candidate("direct-alternate"))
    assert "dx" in d.layers["direct"] and "dx" not in d.layers["indirect"]
    p = passes.frame_result(candidate("primal"))
    assert all("dx" not in v for v in p.layers.values())


@pytest.mark.render
def test_the_checkpoint_judges_the_plans_on_the_frames_own_halves():
    """A stand-in reconstruction: a frame with gradients comes back as the truth (a 512-spp render), a plain one
    20 % too dark. At equal samples (--spp) the checkpoint must keep the plan with gradients, and the difference of
    its two reference-free estimates must be the true difference: the halves' groups are common to both
    reconstructions, so their noise cancels (each estimate alone carries it, see its standard error)."""
    from gradsep.model.metrics import relmse
    from gradsep.renderer.plan import CHECKPOINT_SHARE, FALLBACK, Passes, run_checkpoint
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    scene = load_scene(CBOX, width=48, height=36, max_depth=5)
    truth = render_frame(scene, spp=512, seed=99, gradients="none").combined().base

    def fake(frame: Frame) -> tuple[np.ndarray, str]:
        return (truth if frame.layers["direct"].has_gradients else 0.8 * truth), "fake"

    passes = Passes(scene, ("direct", "indirect"), seed=3)
    plan = run_checkpoint(passes, lambda a: 1024.0, spp=1024, reconstruct=fake)
    assert plan.chosen.name == FALLBACK
    by_name = {a.name: a for a in plan.assessments}
    assert set(by_name) == {"primal", FALLBACK}
    mean = 0.9  # the estimate's weights come from the two reconstructions' mean image
    true_difference = relmse(0.8 * truth / mean, truth / mean)
    difference = by_name["primal"].measured_relmse - by_name[FALLBACK].measured_relmse
    assert difference == pytest.approx(true_difference, rel=0.3)  # the groups' noise cancels in the difference
    assert all(math.isfinite(a.predicted_relmse) and a.predicted_relmse >= 0 for a in plan.assessments)
    assert passes.spp <= CHECKPOINT_SHARE * 1024 and passes.split is not None
    meta = plan.metadata(("direct", "indirect"))
    assert meta[PLAN_KEY] == FALLBACK and float(meta[PREDICTED_RELMSE_KEY]) == pytest.approx(
        by_name[FALLBACK].predicted_relmse, rel=1e-5)


@pytest.mark.render
def test_no_indirect_light_plans_no_indirect_layer(small):
    from gradsep.renderer.render import render_planned_frame
    from gradsep.renderer.scene import load_scene

    direct_only = load_scene(CBOX, width=16, height=12, max_depth=2)
    frame, _ = render_planned_frame(direct_only, deadline=None, spp=3, gradients="all")
    assert tuple(frame.layers) == ("direct",)
    assert frame.metadata["gradsep.plan_layers"] == "direct=all"
    assert frame.metadata["gradsep.spp"] == "3" and frame.metadata["gradsep.layers"] == "direct"


@pytest.mark.render
@pytest.mark.slow
def test_auto_with_spp_renders_exactly_the_samples_and_records_the_plan(small):
    from gradsep.renderer.render import render_planned_frame

    frame, summary = render_planned_frame(small, deadline=None, spp=64, seed=2, gradients="auto")
    meta = frame.metadata
    assert meta["gradsep.spp"] == "64"
    assert meta[PLAN_KEY] in {c.name for c in CANDIDATES} and meta[PLAN_KEY] in summary
    predicted = {k: float(v) for k, v in (p.split("=") for p in meta["gradsep.plan_candidates"].split(","))}
    assert set(predicted) == {c.name for c in applicable(("direct", "indirect"))}
    assert all(math.isfinite(v) and v >= 0 for v in predicted.values())
    # the frame's own estimate from its halves (renderer/check.py) replaces the checkpoint's, which stays per plan
    assert meta["gradsep.predicted_from"] == "frame"
    check = json.loads(meta["gradsep.frame_check"])
    assert [n for n, _, _ in check["halves"]] and sum(n for n, _, _ in check["halves"]) == 64
    predicted_frame = float(meta[PREDICTED_RELMSE_KEY])
    assert math.isfinite(predicted_frame) and predicted_frame >= 0
    assert meta["gradsep.plan_method"] in ("oidn", "oidn-l1")
    assert "the frame's halves" in summary
    if meta[PLAN_KEY] == "primal":
        assert meta["gradsep.gradients"] == "none" and not frame.gradient_layers
    else:
        assert 0 < int(meta["gradsep.gradient_spp"]) < 64  # the checkpoint's primal passes are in the bases
    for layer in frame.layers.values():
        assert np.isfinite(layer.base).all()


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
    from gradsep.renderer import plan

    monkeypatch.setattr(budget, "process_age", lambda: 0.0)
    # the reconstruction's start-up as if paid (as after another test): the frame's check then fits 8 s
    monkeypatch.setattr(plan, "reconstruct_startup", lambda: 0.0)
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


def test_a_budget_asks_for_the_better_denoiser_where_it_is_cheap_and_serves_the_frame():
    """The plan asks for FARM_OIDN_SETTING only for a frame with the direct layer's gradients (oidn-l1 serves it;
    on a plain frame oidn would halo a light in view) and only where its extra time fits FARM_OIDN_SHARE of T."""
    from gradsep.renderer.render import (
        FARM_OIDN_EXTRA_SECONDS,
        FARM_OIDN_SETTING,
        FARM_OIDN_SHARE,
        reconstruction_setting,
    )

    both = ("direct", "indirect")
    extra = 1280 * 720 * 2 * FARM_OIDN_EXTRA_SECONDS
    at = extra / FARM_OIDN_SHARE
    assert reconstruction_setting(1280, 720, both, "direct", at * 1.01) == FARM_OIDN_SETTING
    assert reconstruction_setting(1280, 720, both, "all", at * 1.01) == FARM_OIDN_SETTING
    assert reconstruction_setting(1280, 720, both, "direct", at * 0.99) is None  # a short budget: the default
    assert reconstruction_setting(1280, 720, both, "none", 1e6) is None  # a plain frame: oidn serves it
    assert reconstruction_setting(1280, 720, ("indirect",), "all", 1e6) is None  # no direct layer: no oidn-l1
    assert reconstruction_setting(1280, 720, ("color",), "all", 1e6) is None
    assert reconstruction_setting(1280, 720, both, "direct", 1e6, light_in_view=True) is None


def test_a_light_in_view_is_found_in_the_direct_layer_as_oidn_would_cap_it():
    from gradsep.renderer.render import has_light_in_view

    rng = np.random.default_rng(2)
    base = (0.5 + rng.random((64, 80, 3))).astype(np.float32)
    lit = base.copy()
    lit[30:32, 40:43] = 1e5  # a 2x3-pixel light
    lone = base.copy()
    lone[30, 40] = 1e5  # a firefly: the outlier split's
    for image, expected in ((base, False), (lit, True), (lone, False)):
        assert has_light_in_view(Frame({"direct": Layer(image), "indirect": Layer(base)})) == expected
    assert not has_light_in_view(Frame({"indirect": Layer(lit)}))  # only the direct layer asks for the setting
