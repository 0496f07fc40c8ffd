"""Planned frames (renderer/planned_frame.py): the header of a plan, the OIDN setting a budget asks
for, the frame's own error estimate and its sizing, and the layers a scene without indirect light plans."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gradsep.model.frame import Frame, Layer
from gradsep.model.header_keys import PREDICTED_RELMSE_KEY
from gradsep.renderer.estimate import at_budget
from gradsep.renderer.planned_frame import CHECK_SHARE, FrameCheckSizer, FrameShape, PlanRequest, check_budget
from gradsep.renderer.plans import PLAN_KEY, PLANS, judged_plans, plan_named
from tests.renderer.scenes import resolve

CBOX = str(resolve("cbox"))


def test_the_check_sizer_compares_settings_on_a_plain_frame_only_and_only_where_both_fit():
    """A plain frame whose budget affords FARM_OIDN_SETTING compares it with the default on its halves where both
    reconstructions fit the check's share; where only one fits, the estimate alone; a frame with gradients never
    compares. Without a budget the check is always made."""
    shape = FrameShape(64, 48, ("direct", "indirect"))
    alone = check_budget(1e-6, plan_named("primal"), shape, 20.0)
    both = check_budget(1e-6, plan_named("primal"), shape, 20.0, compare=True)
    assert alone is not None and both is not None and both > alone
    sizer = FrameCheckSizer(shape, 20.0, can_compare=True)
    assert sizer(1e-6, plan_named("primal"), 0.0) == both and sizer.compare
    assert sizer(1e-6, plan_named("direct-alternate"), 0.0) is not None and not sizer.compare
    tight = both / CHECK_SHARE * 0.9  # a budget whose share holds the estimate alone, not the comparison
    sizer = FrameCheckSizer(shape, tight, farm_setting=False, can_compare=True)
    held = sizer(1e-6, plan_named("primal"), 0.0)
    assert held is not None and held < both and not sizer.compare
    assert FrameCheckSizer(shape, 1e-3)(1e-6, plan_named("primal"), 0.0) is None  # no time for it
    assert FrameCheckSizer(shape, None)(1e-6, plan_named("primal"), 1e9) is not None  # --spp: always


def test_a_bad_request_is_a_user_error_before_anything_renders():
    from types import SimpleNamespace

    from gradsep.model.errors import CommandError
    from gradsep.renderer.planned_frame import _checked_request

    scene = SimpleNamespace(max_depth=5)
    for request, message in ((PlanRequest(seed=-1), "--seed"), (PlanRequest(offsets="three"), "--offsets"),
                             (PlanRequest(gradients="none", offsets="pair"), "--offsets has no effect"),
                             (PlanRequest(gradients="direct", layers="indirect"), "needs the separated direct")):
        with pytest.raises(CommandError, match=message):
            _checked_request(scene, request)  # type: ignore[arg-type]


def test_a_budget_asks_for_the_better_denoiser_where_it_is_cheap_and_serves_the_frame():
    """The plan asks for FARM_OIDN_SETTING only for a frame with the direct layer's gradients (oidn-l1 serves it;
    on a plain frame oidn would halo a light in view) and only where its extra time fits FARM_OIDN_SHARE of T."""
    from gradsep.renderer.planned_frame import (
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
    from gradsep.renderer.planned_frame import has_light_in_view

    rng = np.random.default_rng(2)
    base = (0.5 + rng.random((64, 80, 3))).astype(np.float32)
    lit = base.copy()
    lit[30:32, 40:43] = 1e5  # a 2x3-pixel light
    lone = base.copy()
    lone[30, 40] = 1e5  # a firefly: the outlier split's
    for image, expected in ((base, False), (lit, True), (lone, False)):
        assert has_light_in_view(Frame({"direct": Layer(image), "indirect": Layer(base)})) == expected
    assert not has_light_in_view(Frame({"indirect": Layer(lit)}))  # only the direct layer asks for the setting


mi = pytest.importorskip("mitsuba")


@pytest.mark.render
def test_no_indirect_light_plans_no_indirect_layer(small):
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.planned_frame import render_planned_frame
    from gradsep.renderer.scene import load_scene

    direct_only = load_scene(CBOX, width=16, height=12, max_depth=2)
    frame, _ = render_planned_frame(direct_only, FrameBudget(spp=3), PlanRequest(gradients="all"))
    assert tuple(frame.layers) == ("direct",)
    assert frame.metadata["gradsep.plan_layers"] == "direct=all"
    assert frame.metadata["gradsep.spp"] == "3" and frame.metadata["gradsep.layers"] == "direct"


@pytest.mark.render
@pytest.mark.slow
def test_auto_with_spp_renders_exactly_the_samples_and_records_the_plan(small):
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.planned_frame import render_planned_frame

    frame, summary = render_planned_frame(small, FrameBudget(spp=64), PlanRequest(seed=2))
    meta = frame.metadata
    assert meta["gradsep.spp"] == "64"
    assert meta[PLAN_KEY] in {p.name for p in PLANS} and meta[PLAN_KEY] in summary
    predicted = {k: float(v) for k, v in (p.split("=") for p in meta["gradsep.plan_candidates"].split(","))}
    assert set(predicted) == {p.name for p in judged_plans(("direct", "indirect"))}
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
@pytest.mark.slow
@pytest.mark.parametrize(("gradients", "operator_setting"),
                         [("none", None), ("none", "prefiltered-high"), ("auto", None)])
def test_a_budgeted_plain_frame_compares_the_oidn_settings_on_its_halves(monkeypatch, gradients, operator_setting):
    """A plain --seconds frame whose budget affords prefiltered-high has its halves reconstructed with both it and
    the default; the header's setting is the one the comparison chose, and the prediction is that setting's. An
    operator's $GRADSEP_OIDN_SETTING (which wins over the header when serving) leaves nothing to compare, and a
    frame with gradients keeps the rule's setting."""
    from gradsep.model.header_keys import OIDN_SETTING_KEY, PREDICTED_RELMSE_KEY
    from gradsep.model.oidn import METHOD_SETTING, SETTING_ENV
    from gradsep.renderer import planned_frame, reconstruction_cost
    from gradsep.renderer.budget import Deadline
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.planned_frame import render_planned_frame
    from gradsep.renderer.scene import load_scene

    monkeypatch.setattr(reconstruction_cost, "reconstruct_startup", lambda: 0.0)  # as if paid: the check fits 8 s
    # and whatever the machine's load makes of the pilot's timings (beside other tests, a loaded pilot predicted a
    # check past the budget's share, and the frame kept the pilot's estimate): the sizing is not what is tested here
    monkeypatch.setattr(planned_frame, "check_seconds", lambda *_args: 0.01)
    monkeypatch.setattr(planned_frame, "CHECK_SHARE", 1.0)
    if operator_setting:
        monkeypatch.setenv(SETTING_ENV, operator_setting)
    else:
        monkeypatch.delenv(SETTING_ENV, raising=False)
    scene = load_scene(str(resolve("cbox")), width=16, height=12, max_depth=5)
    frame, summary = render_planned_frame(scene, FrameBudget(Deadline(8.0)), PlanRequest(seed=4, gradients=gradients))
    meta = frame.metadata
    assert meta["gradsep.predicted_from"] == "frame" and "the frame's halves" in summary
    check = json.loads(meta["gradsep.frame_check"])
    if operator_setting or meta["gradsep.plan"] != "primal":
        assert "options" not in check
        return
    assert set(check["options"]) == {METHOD_SETTING, "prefiltered-high"} and check["chosen"] in check["options"]
    assert (meta.get(OIDN_SETTING_KEY) or METHOD_SETTING) == check["chosen"]
    assert all(len(h) == 2 for h in check["options"].values()) and len(check["differences"]) == 1
    assert float(meta[PREDICTED_RELMSE_KEY]) >= 0 and meta["gradsep.plan_method"] == "oidn"


def test_without_halves_the_pilots_prediction_is_carried_to_the_samples_the_frame_got():
    """A pilot slowed by a load spike predicts that the budget buys 49 spp and carries its estimate there; the
    frame then renders 543. Its header states the error at 543 spp (error ~ spp^-exponent), not at 49."""
    from gradsep.renderer.checkpoint import Assessment, Judgement
    from gradsep.renderer.planned_frame import frame_check
    from gradsep.renderer.planner import PlannedFrame

    chosen = Assessment("direct-alternate", 1, 0.08, 0.3, "oidn-l1", exponent=0.5, budget_spp=49.0,
                        predicted_relmse=0.012)
    other = Assessment("primal", 1, 0.07, 0.1, "oidn", exponent=0.5, budget_spp=131.0, predicted_relmse=0.007)
    judgement = Judgement(plan_named("direct-alternate"), [chosen, other], pilot_seconds=3.0)
    meta = judgement.metadata(("direct", "indirect"))
    planned = PlannedFrame(frame=None, plan=plan_named("direct-alternate"), judgement=judgement,  # type: ignore[arg-type]
                           spp=543, gradient_spp=538, passes=19)
    summary = frame_check(planned, meta)
    assert meta["gradsep.predicted_from"] == "pilot" and "the pilot's" in summary
    assert float(meta[PREDICTED_RELMSE_KEY]) == pytest.approx(at_budget(0.012, 49, 543, 0.5), rel=1e-5)
    assert float(meta[PREDICTED_RELMSE_KEY]) < 0.004
