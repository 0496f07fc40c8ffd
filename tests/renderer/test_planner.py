"""The render planner (renderer/planner.py): one loop renders the passes of the plan a choice makes, to a sample
count or to a deadline. The deadline's logic is tested against a fake clock in test_budget.py and
test_frame_budget.py, the checkpoint with fakes in test_checkpoint.py; here: real passes, small frames."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.renderer.checkpoint import Judgement
from gradsep.renderer.frame_budget import FrameBudget
from gradsep.renderer.plans import FALLBACK, plan_named
from tests.renderer.scenes import resolve

mi = pytest.importorskip("mitsuba")

CBOX = str(resolve("cbox"))
LAYERS = ("direct", "indirect")


@pytest.mark.render
def test_a_fixed_plan_to_a_sample_count_is_render_gpt_bit_for_bit(small):
    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.gpt_settings import Film, GptSettings
    from gradsep.renderer.planner import FixedChoice, render_planned
    from gradsep.renderer.shift import make_shift

    planned = render_planned(small, LAYERS, FixedChoice(plan_named("all")), FrameBudget(spp=3), seed=5)
    assert planned.judgement is None and planned.plan == plan_named("all")
    assert planned.spp == planned.gradient_spp == 3 and planned.passes == 1 and planned.halves is None
    ref = render_gpt(small.scene, make_shift("hybrid"), GptSettings(max_depth=5), Film(16, 12, 3, 5))
    for layer in LAYERS:
        for key in ("base", "dx", "dy"):
            np.testing.assert_array_equal(getattr(planned.frame.layers[layer], key), ref.layers[layer][key])


@pytest.mark.render
def test_auto_with_too_few_samples_renders_the_fallback_and_says_why(small):
    from gradsep.renderer.planner import CheckpointChoice, PlannerOptions, render_planned

    asked: list[str] = []
    done: list[tuple[int, int]] = []
    options = PlannerOptions(progress=lambda n, total: done.append((n, total)),
                             check=lambda rate, plan, before: asked.append(plan.name))
    planned = render_planned(small, LAYERS, CheckpointChoice(), FrameBudget(spp=5), seed=1, options=options)
    assert planned.plan.name == FALLBACK and planned.spp == 5 and done[-1] == (5, 5)
    assert planned.judgement is not None and planned.judgement.assessments == []
    assert planned.judgement.note == "5 spp is too few for a checkpoint"
    assert asked == [] and planned.halves is None  # nothing judged: no rate to size the frame's check by
    assert planned.frame.layers["direct"].has_gradients and not planned.frame.layers["indirect"].has_gradients


@pytest.mark.render
def test_the_passes_a_choice_renders_stay_in_the_frame_and_the_loop_renders_the_rest(small):
    """Any PlanChoice drives the one loop: a choice that renders a primal pass before choosing its plan (as the
    checkpoint does) leaves that pass in the frame's bases; the loop renders the chosen plan's passes to the
    count, and the header names the judgement the choice returned (as the plan cache's entry)."""
    from gradsep.renderer.planner import PlannerRun, render_planned

    judged = Judgement(plan_named("direct-alternate"), [], 0.0, "judged elsewhere")

    class PrimalFirst:
        def choose(self, run: PlannerRun):  # noqa: ANN202
            run.passes.run(plan_named("primal"), 2)
            run.budget.after_first_pass(plan_named("primal"))
            return plan_named("direct-alternate"), judged

    planned = render_planned(small, LAYERS, PrimalFirst(), FrameBudget(spp=7), seed=2)
    assert planned.spp == 7 and planned.gradient_spp == 5 and planned.passes == 2
    assert planned.judgement is judged and planned.plan.name == "direct-alternate"
    assert planned.frame.layers["direct"].has_gradients


@pytest.mark.render
def test_a_deadline_below_the_start_up_cost_is_refused_after_the_first_pass(small):
    from gradsep.model.errors import CommandError
    from gradsep.renderer.budget import Deadline
    from gradsep.renderer.planner import FixedChoice, render_planned

    with pytest.raises(CommandError, match="below this machine's start-up cost"):
        render_planned(small, LAYERS, FixedChoice(plan_named("primal")), FrameBudget(Deadline(0.01)), seed=1)
