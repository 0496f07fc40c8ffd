"""The render plans: which layers of a frame trace gradients, with which offsets, and the header keys that name a
planned frame's plan.

A plan here is only *what a pass traces*. Which plan a frame renders is chosen by a
:class:`renderer.planner.PlanChoice` (a fixed plan, the ``auto`` checkpoint, or the plan cache); how the checkpoint
judged the plans is a :class:`renderer.checkpoint.Judgement`.
"""

from __future__ import annotations

from dataclasses import dataclass

from gradsep.model.errors import CommandError

#: Header keys of a planned frame (all strings, like every ``gradsep.*`` attribute).
PLAN_KEY = "gradsep.plan"  # the rendered plan's name
PLAN_LAYERS_KEY = "gradsep.plan_layers"  # per layer: what traces gradients, e.g. "direct=alternate,indirect=none"
CANDIDATES_KEY = "gradsep.plan_candidates"  # each judged plan's predicted RelMSE at the budget, "name=value,..."
BUDGET_KEY = "gradsep.budget_seconds"  # --seconds
PILOT_SECONDS_KEY = "gradsep.pilot_seconds"  # wall time up to the checkpoint's choice (its passes stay in the frame)
ELAPSED_KEY = "gradsep.elapsed_seconds"  # the command's wall time when the frame was encoded (from process start)
#: With --plan-cache (renderer/plancache.py): "read NAME" (the plan an earlier frame judged, no checkpoint here),
#: "wrote NAME" (this frame's checkpoint judged and shared it), "not written", or "nothing to share: ...".
PLAN_CACHE_KEY = "gradsep.plan_cache"
#: The checkpoint's figures (JSON: its samples, each judged plan's estimated RelMSE at the halves' samples with its
#: standard error, seconds per sample and per pass, exponent and the samples the budget buys it, the paired
#: difference of the carried estimates with its standard error, and the plan chosen): why, for a farm to read.
TRACE_KEY = "gradsep.plan_trace"


@dataclass(frozen=True)
class RenderPlan:
    """What a frame's passes trace: which layers carry gradients (``--gradients``) and which offsets
    (``--offsets``)."""

    name: str
    gradients: str  # renderer.render.GRADIENT_CHOICES
    offsets: str = "all"  # renderer.render.OFFSET_CHOICES

    @property
    def traces_gradients(self) -> bool:
        return self.gradients != "none"


#: The named render plans (what ``--gradients`` and ``--offsets`` make of a fixed plan). The checkpoint judges the
#: fallback against ``primal`` (:func:`judged_plans`); ``direct`` (every offset) and ``all`` are fixed plans only:
#: the default method, ``oidn-l1``, reads only the direct layer's gradients, and a third judged plan's passes would
#: cost more than it gained on held-out scenes (docs/decisions.md). A farm serving a method that reads every
#: layer's gradients renders ``--gradients all``.
PLANS: tuple[RenderPlan, ...] = (
    RenderPlan("primal", "none"),
    RenderPlan("direct-alternate", "direct", "alternate"),
    RenderPlan("direct", "direct", "all"),
    RenderPlan("all", "all"),  # only for an unseparated (colour) frame, whose one layer is all there is
)
#: What fills the end of a --seconds frame whose plan traces gradients, in the gap too small for one more pass of
#: the plan: primal passes, which cost a fraction of a G-PT pass (their samples join the bases, as the
#: --gradient-spp rule's; the gradients keep the plan's passes' samples).
FILLER = "primal"
#: The plan a frame starts with and keeps unless primal is clearly better at the checkpoint (:func:`fallback_plan`:
#: ``all`` for an unseparated frame), and the plan rendered where no checkpoint fits: the best fixed plan at equal
#: time on held-out scenes (docs/decisions.md, benchmarks/bench_planner.py validate).
FALLBACK = "direct-alternate"


def plan_named(name: str) -> RenderPlan:
    """The plan of PLANS called ``name``; a user error for any other name."""
    for plan in PLANS:
        if plan.name == name:
            return plan
    raise CommandError(f"unknown plan {name!r}; expected one of {', '.join(p.name for p in PLANS)}")


def fixed_plan(gradients: str, offsets: str) -> RenderPlan:
    """The plan of ``--gradients G --offsets O`` (G one of all, direct, none): ``primal``, ``all``, ``direct``, or
    ``G-O`` where the offsets are fewer than all."""
    if gradients == "none":
        return RenderPlan("primal", "none")
    return RenderPlan(gradients if offsets == "all" else f"{gradients}-{offsets}", gradients, offsets)


def plan_layers_text(plan: RenderPlan, layers: tuple[str, ...]) -> str:
    """``direct=alternate,indirect=none``: what each layer of the frame traces (its offsets, or none)."""
    def traced(layer: str) -> str:
        if not plan.traces_gradients or (plan.gradients == "direct" and layer != "direct"):
            return "none"
        return plan.offsets
    return ",".join(f"{layer}={traced(layer)}" for layer in layers)


def judged_plans(layers: tuple[str, ...]) -> tuple[RenderPlan, RenderPlan]:
    """The plans the checkpoint judges for a frame of these layers: its :func:`fallback_plan` and ``primal``."""
    return fallback_plan(layers), plan_named("primal")


def fallback_plan(layers: tuple[str, ...]) -> RenderPlan:
    """FALLBACK, or ``all`` for a frame without a separated direct layer."""
    return plan_named(FALLBACK if "direct" in layers else "all")
