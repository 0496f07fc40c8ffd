"""The render planner: a frame rendered to a budget (``gradsep render --seconds T``) or to a sample count, with a
plan that is fixed, chosen by the ``auto`` checkpoint on the frame itself, or read from the plan cache.

Three parts, each its own module:

- the budget, one object (renderer.frame_budget.FrameBudget): the deadline or the sample count, and what must be
  left free after the last pass;
- the choice of plan, one small interface (:class:`PlanChoice`): :class:`FixedChoice` (``--gradients
  all|direct|none``, and the plan cache's entry) and :class:`CheckpointChoice` (``auto``:
  renderer.checkpoint.run_checkpoint);
- the passes (renderer.passes.Passes), rendered by one loop (:func:`render_planned`) that the chosen plan drives:
  to the sample count, or to the deadline with primal passes filling the gap too small for one more of the plan's
  (renderer.budget.fill_with_filler).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from gradsep.model.frame import Frame
from gradsep.renderer import reconstruction_cost
from gradsep.renderer.budget import LAST_PASS_MARGIN, Clock, fill_with_filler
from gradsep.renderer.check import Half
from gradsep.renderer.checkpoint import CHECKPOINT_MIN_SPP, Judgement, run_checkpoint
from gradsep.renderer.frame_budget import FrameBudget, startup_error
from gradsep.renderer.passes import Passes, Priors, as_frame
from gradsep.renderer.plans import FILLER, RenderPlan, fallback_plan, plan_named
from gradsep.renderer.scene import LoadedScene

#: The fewest passes the rest of a --spp frame is rendered in once it is split for its check.
SPLIT_PASSES = 8

#: Sizes the frame's own error estimate (renderer/check.py): given a reconstruction's seconds per pixel, the plan
#: and the seconds the sizing itself costs beforehand, the seconds the check needs after the last pass (held back
#: from the passes), or None for no check.
CheckSizer = Callable[[float, RenderPlan, float], "float | None"]


@dataclass
class PlannerOptions:
    """What a caller may add to a planned frame: ``progress(done, total)`` after each pass (total 0 with a
    deadline); ``check``, the frame's own error estimate's sizer (None: no estimate); ``priors``, what earlier
    renders in this process measured on the scene; ``clock``, the passes' clock."""

    progress: Callable[[int, int], None] | None = None
    check: CheckSizer | None = None
    priors: Priors | None = None
    clock: Clock = time.monotonic


@dataclass
class PlannedFrame:
    """A rendered frame and how it was planned."""

    frame: Frame
    plan: RenderPlan  # the plan the frame's gradients (if any) come from
    judgement: Judgement | None  # the checkpoint's (or the plan cache's); None: a fixed plan
    spp: int
    gradient_spp: int  # samples that traced the plan's gradients (0 for a plain frame)
    passes: int
    #: the frame's two halves for its own error estimate (renderer/check.py), with their samples; None: no check
    halves: list[Half] | None = None
    check_seconds: float | None = None  # what was held back for the check after the last pass


class PlannerRun:
    """One planned frame in progress: its passes, its budget and the caller's options."""

    def __init__(self, passes: Passes, budget: FrameBudget, options: PlannerOptions) -> None:
        self.passes, self.budget, self.options = passes, budget, options
        budget.bind(passes)

    def size_check(self, rate: float, plan: RenderPlan, before: float = 0.0) -> float | None:
        """Ask the caller's sizer for the check; where it fits, hold its time back and split the passes from now
        on."""
        if self.options.check is None:
            return None
        held = self.options.check(rate, plan, before)
        self.budget.held = held
        if held is not None:
            self.passes.start_split()
        return held

    def render_pass(self, plan: RenderPlan, spp: int, total: int = 0) -> None:
        """One pass of ``plan``, then the caller's progress (``total``: the sample count, 0 with a deadline)."""
        self.passes.run(plan, spp)
        if self.options.progress is not None:
            self.options.progress(self.passes.spp, total)


class PlanChoice(Protocol):
    """How a planned frame's plan is chosen. :meth:`choose` may render passes (they stay in the frame) and
    returns the plan the rest of the frame renders with the judgement it was chosen by (None: none)."""

    def choose(self, run: PlannerRun) -> tuple[RenderPlan, Judgement | None]: ...


@dataclass(frozen=True)
class FixedChoice:
    """A plan given beforehand: ``--gradients all|direct|none``, or the plan cache's entry (``judgement``: the
    earlier frame's, carried in this frame's header)."""

    plan: RenderPlan
    judgement: Judgement | None = None

    def choose(self, run: PlannerRun) -> tuple[RenderPlan, Judgement | None]:
        return self.plan, self.judgement


@dataclass(frozen=True)
class CheckpointChoice:
    """``--gradients auto``: the checkpoint on the frame's own first passes (renderer/checkpoint.py), where the
    budget has room for one; else the fallback plan."""

    def choose(self, run: PlannerRun) -> tuple[RenderPlan, Judgement | None]:
        budget = run.budget
        if budget.deadline is not None or (budget.spp or 0) >= CHECKPOINT_MIN_SPP:
            judgement = run_checkpoint(run.passes, budget)
        else:
            judgement = Judgement(fallback_plan(run.passes.layers), [], 0.0,
                                  f"{budget.spp} spp is too few for a checkpoint")
        assessed = judgement.assessment()
        if assessed is not None:  # the check sized from the checkpoint's own reconstruction rate
            run.size_check(assessed.reconstruct_rate, judgement.chosen)
        return judgement.chosen, judgement


def render_planned(loaded: LoadedScene, layers: tuple[str, ...], choice: PlanChoice, budget: FrameBudget, *,
                   seed: int, shift: str | None = None, options: PlannerOptions | None = None) -> PlannedFrame:
    """Render ``loaded`` to the ``budget`` with the plan ``choice`` makes. Raises CommandError (nothing rendered is
    kept) when a deadline cannot fit one pass and the write. The frame's metadata is the caller's
    (renderer.render.render_metadata) plus :meth:`Judgement.metadata`.

    With ``options.check``, the frame's own error estimate is sized once the plan is chosen, from the
    checkpoint's reconstruction rate; for a fixed plan with a deadline, after its first pass, from the rate
    measured on a tile of it (renderer.reconstruction_cost.reconstruct_rate), where CHECK_PRIOR_RATE and the
    reconstruction's start-up say the check could fit; :attr:`PlannedFrame.halves` then holds the halves.

    With ``options.priors`` and a caller's own tail (Deadline.tail: nothing to write, so no write to measure on a
    first pass), a deadline whose plan's cost line is known sizes its first pass from that line instead of probing
    with a 1-spp one: at sub-second budgets a pass's fixed cost is most of a small pass."""
    options = options or PlannerOptions()
    run = PlannerRun(Passes(loaded, layers, seed, shift, options.clock, options.priors), budget, options)
    plan, judgement = choice.choose(run)
    budget.written.append(plan)
    if budget.has_tail and options.priors is not None:  # the tail kept free becomes the plan's reconstruction's
        budget.deadline.tail = options.priors.reconstruct_seconds.get(  # type: ignore[union-attr]
            plan.name, budget.deadline.tail)  # type: ignore[union-attr]
    if budget.deadline is None:
        _to_sample_count(run, plan)
    else:
        _start_to_deadline(run, plan)
        _fill_to_deadline(run, plan)
    passes = run.passes
    return PlannedFrame(as_frame(passes.frame_result(plan)), plan, judgement, passes.spp, passes.gradient_spp(plan),
                        passes.index, passes.halves(plan) if budget.held is not None else None, budget.held)


def _to_sample_count(run: PlannerRun, plan: RenderPlan) -> None:
    """The plan's passes up to ``budget.spp``; a split frame's rest in SPLIT_PASSES passes or more, so that each
    half gets groups of its own."""
    passes, target = run.passes, int(run.budget.spp)  # type: ignore[arg-type]
    step = passes.max_spp if passes.split is None else max(1, -(-(target - passes.spp) // SPLIT_PASSES))
    while passes.spp < target:
        run.render_pass(plan, min(passes.max_spp, step, target - passes.spp), target)
        if passes.index == 1:
            run.budget.after_first_pass(plan)


def _start_to_deadline(run: PlannerRun, plan: RenderPlan) -> None:
    """Where no checkpoint rendered a pass, the start-up check: from the plan's known cost line (Priors, with a
    caller's tail), else after a first 1-spp pass, which compiles the kernel; and the check, sized for a fixed
    plan."""
    passes, budget, priors = run.passes, run.budget, run.options.priors
    deadline = budget.deadline
    assert deadline is not None
    if passes.index != 0:
        return
    if priors is not None and priors.warm(plan.name) and budget.has_tail:
        costs = passes.kind(plan).costs
        if deadline.left() < budget.reserve() + LAST_PASS_MARGIN * costs.predict(1):
            raise startup_error(deadline.seconds, deadline.elapsed() + budget.reserve() + costs.predict(1))
        if priors.reconstruct_rate:
            run.size_check(priors.reconstruct_rate, plan)
        return
    passes.run(plan, 1)
    budget.after_first_pass(plan)
    check = run.options.check
    startup = reconstruction_cost.reconstruct_startup()
    if check is not None and check(reconstruction_cost.CHECK_PRIOR_RATE, plan, startup) is not None:
        run.size_check(reconstruction_cost.reconstruct_rate(as_frame(passes.frame_result(plan))), plan)


def _fill_to_deadline(run: PlannerRun, plan: RenderPlan) -> None:
    """The plan's passes to the deadline, then primal passes (FILLER) in the gap too small for one more of them."""
    passes, budget = run.passes, run.budget
    filler = plan_named(FILLER)
    fill_with_filler(budget.deadline, passes.kind(plan).costs,  # type: ignore[arg-type]
                     lambda n: run.render_pass(plan, n), passes.kind(filler).costs if plan.traces_gradients else None,
                     lambda n: run.render_pass(filler, n), budget.reserve, passes.max_spp)
