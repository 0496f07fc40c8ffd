"""The ``auto`` checkpoint (``--gradients auto``): whether the rest of a frame traces gradients, judged on the frame
itself.

The frame starts as the fallback plan's (renderer.plans.fallback_plan), its passes dealt into the frame's two
halves (renderer/check.py), with primal passes of two sizes for primal's cost. At CHECKPOINT_SHARE of the budget
each half is reconstructed twice -- with its gradients (``oidn-l1``) and as a plain frame from the same passes'
bases (``oidn``) -- on a few tiles (:func:`tiles`), and each reconstruction's error is estimated against the other
half's groups, which are independent of it (renderer/estimate.py: no reference, bias included). Each estimate is
carried to the samples the rest of the budget buys that plan, with ``error ~ spp^-ERROR_EXPONENT`` and the plan's
cost read from its passes (:func:`pass_cost`); the rest of the frame is primal only when the paired difference of
the carried estimates -- same groups, same weights, so the groups' own noise cancels -- says primal is lower by
more than renderer.check.SWITCH_SE standard errors. Nothing is rendered for the judgement alone: every pass so far
stays in the frame whichever plan goes on.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from gradsep.model.header_keys import PLAN_METHOD_KEY, PREDICTED_RELMSE_KEY
from gradsep.renderer import reconstruction_cost
from gradsep.renderer.budget import fitted_line
from gradsep.renderer.check import CHECK_MARGIN, SWITCH_SE, Half
from gradsep.renderer.estimate import ERROR_EXPONENT, at_budget, cross_terms, mean_and_se, relative_weights
from gradsep.renderer.passes import Priors, as_frame, crop, without_gradients
from gradsep.renderer.plans import (
    CANDIDATES_KEY,
    PILOT_SECONDS_KEY,
    PLAN_KEY,
    PLAN_LAYERS_KEY,
    TRACE_KEY,
    RenderPlan,
    judged_plans,
    plan_layers_text,
)
from gradsep.renderer.reconstruction_cost import WARM_TILE, Reconstruct, reconstruct_default, warm_reconstruction

#: Share of the budget (of the frame's samples with --spp) rendered with the fallback plan before the checkpoint
#: judges the plans on the frame's halves. Those passes stay in the frame whatever the choice.
CHECKPOINT_SHARE = 0.15
#: Passes the frame is rendered in up to the checkpoint (each half needs two groups or more: renderer/check.py).
CHECKPOINT_PASSES = 8
#: The checkpoint's last passes: the rest of its share after the cost lines' passes, in this many passes. A G-PT
#: pass has a fixed cost (tracing, launch), so many small passes would spend the share on fixed costs.
CHECKPOINT_LAST_PASSES = 4
#: The fewest samples of a --spp frame that get a checkpoint (its passes up to it: 4 of 1 spp, then 4 or more).
CHECKPOINT_MIN_SPP = 64
#: Side of the blocks whose means give the checkpoint's paired difference its standard error: a denoiser's errors
#: are correlated between neighbouring pixels, so single pixels would understate it.
CHECKPOINT_BLOCK = 8
#: Tiles the checkpoint reconstructs (side, count) and the border of each left out of the estimate.
TILE = 128
TILE_COUNT = 4
TILE_BORDER = 8
#: Why a frame was not judged where its checkpoint's cost did not fit.
TOO_SMALL = "the budget is too small for a checkpoint"


class CheckpointBudget(Protocol):
    """What the checkpoint asks of the frame's budget (renderer.frame_budget.FrameBudget)."""

    @property
    def seconds(self) -> float | None: ...
    spp: int | None

    def checkpoint_allowance(self) -> float: ...
    def after_first_pass(self, plan: RenderPlan) -> None: ...
    def buys(self, assessment: Any) -> float: ...


def tiles(width: int, height: int, side: int = TILE, count: int = TILE_COUNT) -> list[tuple[slice, slice]]:
    """The windows the checkpoint reconstructs: the whole frame when it is small, else ``count`` tiles of ``side``
    centred in the frame's quadrants (spread over the frame, away from its edges)."""
    if width * height <= count * side * side or width < 2 * side or height < 2 * side:
        return [(slice(0, height), slice(0, width))]
    out = []
    for fy in (0.25, 0.75):
        for fx in (0.25, 0.75):
            y0 = min(max(0, round(fy * height - side / 2)), height - side)
            x0 = min(max(0, round(fx * width - side / 2)), width - side)
            out.append((slice(y0, y0 + side), slice(x0, x0 + side)))
    return out[:count]


def block_means(terms: np.ndarray, block: int = CHECKPOINT_BLOCK) -> np.ndarray:
    """The means of ``terms`` (rows, columns[, channels]) over ``block``-square blocks (the ragged edge left out;
    the whole array as one block when it is smaller than one)."""
    h, w = terms.shape[:2]
    if h < block or w < block:
        return np.asarray([float(np.mean(terms))])
    t = terms[:h - h % block, :w - w % block]
    t = t.reshape(h // block, block, w // block, block, -1)
    return t.mean(axis=(1, 3, 4)).ravel()


def pass_cost(warm: list[tuple[int, float]], fallback: float) -> tuple[float, float]:
    """(fixed seconds per pass, seconds per sample) of one kind of pass, for comparing plans: the least-squares
    line through its warm passes ``(spp, seconds)`` (renderer.budget.fitted_line) when they have two sizes or more
    (the fixed part clipped to [0, 0.95 x the smallest pass]); else no fixed part and ``fallback`` per sample.
    Unlike the deadline's conservative rate (renderer.budget.PassCosts.per_sample, the largest recent rate), this
    is the marginal cost: small passes are mostly fixed cost for G-PT (tracing the kernel), which must not be
    charged to every sample of the final frame's large passes."""
    line = fitted_line(warm)
    if line is None:
        return 0.0, fallback
    intercept, slope = line
    fixed = min(max(intercept, 0.0), 0.95 * min(y for _, y in warm))
    per = max((y - fixed) / x for x, y in warm) if slope <= 0 else slope  # a line gone flat or falling: noise
    return fixed, max(per, 1e-12)


@dataclass
class Assessment:
    """What the checkpoint measured of one plan (the plan cache stores it as it is: renderer/plancache.py)."""

    name: str
    pilot_spp: int  # samples of each half at the checkpoint (the halves' mean)
    measured_relmse: float  # estimated RelMSE of a half's reconstruction (at pilot_spp; the halves' mean)
    per_sample: float  # seconds per sample of the whole frame (warm, marginal: pass_cost)
    method: str  # the reconstruction method that serves its frame
    standard_error: float = 0.0  # of measured_relmse (the estimate's noise)
    exponent: float = ERROR_EXPONENT  # of the error-vs-spp law it is carried to the budget with
    budget_spp: float = 0.0
    predicted_relmse: float = math.inf
    predicted_se: float = 0.0  # of predicted_relmse (the estimate's noise carried to the budget)
    pass_seconds: float = 0.0  # fixed cost of one of its passes (pass_cost)
    reconstruct_rate: float = 0.0  # seconds per pixel of its reconstructions (the frame's check: renderer/check.py)

    def trace_entry(self) -> dict[str, float | str]:
        """This plan's entry in the checkpoint's figures (TRACE_KEY)."""
        return {"name": self.name, "spp": self.pilot_spp, "relmse": float(f"{self.measured_relmse:.4g}"),
                "se": float(f"{self.standard_error:.3g}"), "per_sample": float(f"{self.per_sample:.4g}"),
                "pass_seconds": float(f"{self.pass_seconds:.4g}"), "exponent": round(self.exponent, 3),
                "budget_spp": round(self.budget_spp)}


@dataclass
class Judgement:
    """How a frame's plan was judged: the checkpoint's choice with each judged plan's assessment, or the fallback
    where no checkpoint fitted (no assessments, ``note`` says why); the plan cache carries an earlier frame's."""

    chosen: RenderPlan
    assessments: list[Assessment]
    pilot_seconds: float
    note: str = ""
    trace: dict[str, object] = field(default_factory=dict)  # the checkpoint's figures (TRACE_KEY)

    def assessment(self) -> Assessment | None:
        """The chosen plan's assessment (None: no checkpoint judged it)."""
        return next((a for a in self.assessments if a.name == self.chosen.name), None)

    def predicted(self) -> float:
        a = self.assessment()
        return a.predicted_relmse if a is not None else math.nan

    def metadata(self, layers: tuple[str, ...]) -> dict[str, str]:
        meta = {PLAN_KEY: self.chosen.name, PLAN_LAYERS_KEY: plan_layers_text(self.chosen, layers),
                PILOT_SECONDS_KEY: f"{self.pilot_seconds:.3f}"}
        if self.assessments:
            meta[PREDICTED_RELMSE_KEY] = f"{self.predicted():.6g}"
            meta[CANDIDATES_KEY] = ",".join(f"{a.name}={a.predicted_relmse:.6g}" for a in self.assessments)
            meta[PLAN_METHOD_KEY] = self.assessment().method  # type: ignore[union-attr]
        if self.trace:
            meta[TRACE_KEY] = json.dumps(self.trace, separators=(",", ":"))
        return meta

    def summary(self) -> str:
        if not self.assessments:
            return f"plan {self.chosen.name} ({self.note})"
        parts = ", ".join(f"{a.name} {a.predicted_relmse:.4g} at {a.budget_spp:.0f} spp (slope {a.exponent:.2f})"
                          for a in self.assessments)
        where = self.note if self.trace.get("cached") else f"checkpoint {self.pilot_seconds:.2f} s, {self.note}"
        return (f"plan {self.chosen.name}: predicted RelMSE {parts} ({where}, method "
                f"{self.metadata(()).get(PLAN_METHOD_KEY, '?')})")


def checkpoint_work(priors: Priors | None, pixels: int) -> float:
    """The checkpoint's reconstructions, predicted: the library's start-up where unpaid and four reconstructions
    of ``pixels`` (at the rate measured in this process where known, with the check's margin)."""
    measured = priors.reconstruct_rate if priors is not None else None
    rate = CHECK_MARGIN * measured if measured else reconstruction_cost.CHECK_PRIOR_RATE
    return reconstruction_cost.reconstruct_startup() + 4 * pixels * rate


def run_checkpoint(passes: Any, budget: CheckpointBudget, reconstruct: Reconstruct = reconstruct_default) -> Judgement:
    """Render the fallback plan for CHECKPOINT_SHARE of the ``budget`` (its seconds, or its samples), its passes
    dealt into the frame's halves, with primal passes of two sizes for primal's cost; then judge on the halves
    whether the rest is better spent on the fallback's passes or on primal ones (see the module's docstring).
    When the checkpoint's own cost (the primal kernel, the reconstructions) is predicted past
    ``budget.checkpoint_allowance()``, nothing is judged and the fallback is rendered. ``passes`` is a
    renderer.passes.Passes (or a stand-in with its attributes)."""
    clock = passes.clock
    start = clock()
    default, primal = judged_plans(passes.layers)
    windows = tiles(passes.loaded.width, passes.loaded.height)
    pixels = sum((ys.stop - ys.start) * (xs.stop - xs.start) for ys, xs in windows)
    work = checkpoint_work(passes.priors, pixels)
    priors = passes.priors
    primal_warm = priors is not None and priors.warm(primal.name)
    if primal_warm and priors.warm(default.name) and work > budget.checkpoint_allowance():
        return Judgement(default, [], clock() - start, TOO_SMALL)  # known before any pass: the deadline sizes the first
    passes.run(default, 1)  # compiles (or loads) the fallback's kernel: the frame's first pass in any case
    budget.after_first_pass(default)
    kernel = 0.0 if primal_warm else passes.kind(default).costs.first_pass[1]
    if clock() - start + kernel + work > budget.checkpoint_allowance():
        return Judgement(default, [], clock() - start, TOO_SMALL)
    lines, warming = _pilot_passes(passes, budget, start, (default, primal), reconstruct)
    checkpoint_spp = passes.spp
    halves = passes.halves(default)
    if halves is None:
        return Judgement(default, [], clock() - start, "the checkpoint's halves were not ready")
    if warming is not None:
        warming.join()
    judging = clock()
    errors = _tile_errors(halves, windows, (default, primal), reconstruct)
    assessments = {c.name: _assess(c, lines[c.name], errors, pixels, budget) for c in (default, primal)}
    difference, difference_se = _paired_difference(errors, assessments[primal.name], assessments[default.name])
    chosen = primal if difference < -SWITCH_SE * difference_se else default
    trace: dict[str, object] = {"spp": checkpoint_spp, "seconds": round(clock() - judging, 3),
                                "plans": [a.trace_entry() for a in assessments.values()],
                                "difference": [float(f"{difference:.4g}"), float(f"{difference_se:.3g}")],
                                "chosen": chosen.name}
    return Judgement(chosen, [assessments[default.name], assessments[primal.name]], clock() - start,
                     f"checkpoint at {checkpoint_spp} spp", trace)


def _pilot_passes(passes: Any, budget: CheckpointBudget, start: float, plans: tuple[RenderPlan, RenderPlan],
                  reconstruct: Reconstruct) -> tuple[dict[str, tuple[list[tuple[int, float]], float]], Any]:
    """The checkpoint's passes after the first, split into the frame's halves: primal's kernel, a warm pass of the
    fallback, each plan at two sizes (its cost line), then the rest of the share in the fallback's last passes.
    Returns each plan's cost line (its warm passes and its per-sample rate) and the reconstruction's warm-up
    thread (or None)."""
    default, primal = plans
    passes.start_split()
    passes.run(primal, 1)  # primal's kernel (the filler's too)
    passes.run(default, 1)  # a warm pass of the fallback: its cost without the compile, to size the passes by
    if budget.seconds is not None:
        left = start + CHECKPOINT_SHARE * budget.seconds - passes.clock()
        n = max(1, int(left / CHECKPOINT_PASSES / max(passes.kind(default).costs.per_sample, 1e-9)))
    else:
        n = max(1, int(CHECKPOINT_SHARE * (budget.spp or 0)) // (CHECKPOINT_PASSES + 4))
    n = max(1, min(n, passes.max_spp // 2))
    # each plan at two sizes, n and 2n: its cost line (pass_cost) reads its fixed cost per pass (for G-PT, most of
    # a small pass) apart from its cost per sample, which decides how many samples the budget buys it
    for k in (n, 2 * n):
        passes.run(primal, k)
        passes.run(default, k)
    lines = {c.name: (list(passes.kind(c).costs.warm), passes.kind(c).costs.per_sample) for c in plans}
    # the reconstruction library's start-up, while the last passes render (not before: passes slowed by it would
    # read a plan's cost high)
    warming = None
    if reconstruct is reconstruct_default:
        side = (slice(0, min(WARM_TILE, passes.loaded.height)), slice(0, min(WARM_TILE, passes.loaded.width)))
        warming = warm_reconstruction(as_frame(passes.frame_result(default, side)))
    _last_passes(passes, budget, start, default)
    return lines, warming


def _last_passes(passes: Any, budget: CheckpointBudget, start: float, default: RenderPlan) -> None:
    """The rest of the checkpoint's share in CHECKPOINT_LAST_PASSES passes of the fallback (more, in pairs, where a
    pass's lanes cannot hold them), each sized as it starts from the time left and the rate of the largest recent
    pass, its fixed cost included: an upper bound on the cost per sample that a cost line fitted on passes slowed
    by a busy moment cannot undercut. The passes are a smaller and a larger in turn (about 2k/3 and 4k/3 for k per
    pass), so that the fallback's cost line stays readable."""
    costs = passes.kind(default).costs
    seconds, spp = budget.seconds, budget.spp or 0

    def rate() -> float:
        largest, seconds_taken = max(costs.warm)
        return seconds_taken / largest

    def rest() -> float:  # the share not yet rendered, in samples
        if seconds is not None:
            return (start + CHECKPOINT_SHARE * seconds - passes.clock()) / rate()
        return CHECKPOINT_SHARE * spp - passes.spp

    total = rest()
    count = CHECKPOINT_LAST_PASSES
    while total > count * 0.75 * passes.max_spp and count < 4 * CHECKPOINT_LAST_PASSES:
        count += 2
    for i in range(count):
        k = rest() / (count - i)
        k *= 2 / 3 if i % 2 == 0 else 1.0  # the pair's first pass the smaller (the second gets what is left)
        passes.run(default, max(1, min(int(k), passes.max_spp)))


@dataclass
class TileErrors:
    """The checkpoint's reconstructions of both halves, as each judged plan's error terms."""

    blocks: dict[str, list[np.ndarray]]  # per plan and half: block means of its error terms over the tiles
    samples: list[int]  # each half's samples
    methods: dict[str, str]  # per plan: the method that reconstructed its frame
    seconds: dict[str, float]  # per plan: the second half's reconstruction time (the first pays start-up)


def _tile_errors(halves: list[Half], windows: list[tuple[slice, slice]], plans: tuple[RenderPlan, RenderPlan],
                 reconstruct: Reconstruct) -> TileErrors:
    """Each half reconstructed as each plan's frame (primal's: the fallback's without its gradients) on each tile,
    and judged against the other half's groups with the same weights for both plans (their mean image), so the
    groups' noise cancels in the difference (renderer/estimate.py)."""
    default, primal = plans
    border = TILE_BORDER if len(windows) > 1 else 0
    errors = TileErrors({default.name: [], primal.name: []}, [n for _, n, _ in halves], {},
                        {default.name: 0.0, primal.name: 0.0})
    for i, (frame, _, groups) in enumerate(halves):
        frames = {default.name: frame, primal.name: without_gradients(frame)}
        terms: dict[str, list[np.ndarray]] = {default.name: [], primal.name: []}
        for ys, xs in windows:
            images = {}
            for name, f in frames.items():
                began = time.perf_counter()
                images[name], errors.methods[name] = reconstruct(crop(f, (ys, xs)))
                errors.seconds[name] += (time.perf_counter() - began) * (i == 1)
            batches = [(b[ys, xs], k) for b, k in groups]
            weights = relative_weights(0.5 * (images[default.name] + images[primal.name]))
            for name, image in images.items():
                t = cross_terms(image, batches, weights)
                terms[name].append(block_means(t[border:-border or None, border:-border or None] if border else t))
        for name in errors.blocks:
            errors.blocks[name].append(np.concatenate(terms[name]))
    return errors


def _assess(plan: RenderPlan, line: tuple[list[tuple[int, float]], float], errors: TileErrors, pixels: int,
            budget: CheckpointBudget) -> Assessment:
    """One plan's assessment: its halves' estimates, its cost line, and both carried to the samples the rest of
    the budget buys it (an estimate lost in the other half's noise counts as its noise)."""
    fixed, per = pass_cost(*line)
    values, ses = zip(*(mean_and_se(b) for b in errors.blocks[plan.name]), strict=True)
    a = Assessment(plan.name, round(float(np.mean(errors.samples))), float(np.mean(values)), per,
                   errors.methods[plan.name], float(np.hypot(*ses)) / 2, pass_seconds=fixed,
                   reconstruct_rate=errors.seconds[plan.name] / pixels)
    a.budget_spp = budget.buys(a)
    a.predicted_relmse = float(np.mean([at_budget(max(v, se), n, a.budget_spp, a.exponent)
                                        for v, se, n in zip(values, ses, errors.samples, strict=True)]))
    a.predicted_se = at_budget(a.standard_error, a.pilot_spp, a.budget_spp, a.exponent)
    return a


def _paired_difference(errors: TileErrors, primal: Assessment, default: Assessment) -> tuple[float, float]:
    """Primal's error terms less the fallback's, each carried to its samples at the budget: the mean and its
    standard error."""
    return mean_and_se(np.concatenate([
        at_budget(1.0, n, primal.budget_spp, primal.exponent) * tp
        - at_budget(1.0, n, default.budget_spp, default.exponent) * td
        for n, tp, td in zip(errors.samples, errors.blocks[primal.name], errors.blocks[default.name], strict=True)]))
