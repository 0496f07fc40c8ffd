"""The render plans (renderer/plans.py): what each plan traces per layer, the plans the checkpoint judges, and the
plan a fixed ``--gradients``/``--offsets`` pair names."""

from __future__ import annotations

import pytest

from gradsep.model.errors import CommandError
from gradsep.renderer.plans import (
    FALLBACK,
    PLANS,
    RenderPlan,
    fallback_plan,
    fixed_plan,
    judged_plans,
    plan_layers_text,
    plan_named,
)


def test_the_checkpoint_judges_the_fallback_against_primal():
    assert [p.name for p in judged_plans(("direct", "indirect"))] == [FALLBACK, "primal"]
    assert [p.name for p in judged_plans(("direct",))] == [FALLBACK, "primal"]
    assert [p.name for p in judged_plans(("color",))] == ["all", "primal"]  # no direct layer to trace alone
    assert [p.name for p in judged_plans(("indirect",))] == ["all", "primal"]
    assert fallback_plan(("direct", "indirect")).name == FALLBACK and fallback_plan(("color",)).name == "all"
    # every plan the planner can choose is a named one: the plan cache and the header name it
    assert all(plan_named(p.name) == p for layers in (("direct",), ("color",)) for p in judged_plans(layers))


def test_a_plans_layers_say_what_each_layer_traces():
    assert plan_layers_text(plan_named("direct-alternate"), ("direct", "indirect")) == "direct=alternate,indirect=none"
    assert plan_layers_text(plan_named("primal"), ("direct",)) == "direct=none"
    assert plan_layers_text(plan_named("direct"), ("direct", "indirect")) == "direct=all,indirect=none"
    assert plan_layers_text(plan_named("all"), ("color",)) == "color=all"
    assert [p.traces_gradients for p in PLANS] == [p.gradients != "none" for p in PLANS]


def test_an_unknown_plan_is_a_user_error_that_names_the_known_ones():
    with pytest.raises(CommandError, match="unknown plan 'some'.*direct-alternate"):
        plan_named("some")


@pytest.mark.parametrize(("gradients", "offsets", "expected"), [
    ("none", "all", RenderPlan("primal", "none", "all")),
    ("all", "all", RenderPlan("all", "all", "all")),
    ("direct", "all", RenderPlan("direct", "direct", "all")),
    ("direct", "alternate", RenderPlan("direct-alternate", "direct", "alternate")),
    ("all", "pair", RenderPlan("all-pair", "all", "pair")),
])
def test_a_fixed_plan_is_named_by_its_gradients_and_offsets(gradients, offsets, expected):
    plan = fixed_plan(gradients, offsets)
    assert plan == expected
    if plan.name in {p.name for p in PLANS}:  # the same plan as the named one the checkpoint may choose
        assert plan == plan_named(plan.name)
