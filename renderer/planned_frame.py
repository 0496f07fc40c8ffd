"""The planned frame's front end (`gradsep render --seconds T` and/or ``--gradients auto``): the request checked,
the plan cache's entry read or written, the frame rendered by the planner (renderer/planner.py), and its header:
the plan's keys, the OIDN setting a budget asks for, and the frame's own error estimate (renderer/check.py)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from gradsep.model.errors import CommandError
from gradsep.model.frame import Frame
from gradsep.model.header_keys import OIDN_SETTING_KEY, PREDICTED_FROM_KEY, PREDICTED_RELMSE_KEY
from gradsep.model.oidn import SETTING_ENV
from gradsep.model.policy import SEPARATED_LAYERS
from gradsep.renderer.check import check_frame, check_seconds
from gradsep.renderer.estimate import ERROR_EXPONENT, at_budget
from gradsep.renderer.plans import (
    BUDGET_KEY,
    ELAPSED_KEY,
    PLAN_CACHE_KEY,
    PLAN_KEY,
    PLAN_LAYERS_KEY,
    RenderPlan,
    plan_layers_text,
)
from gradsep.renderer.render import (
    OFFSET_CHOICES,
    RenderRecord,
    gradients_mode,
    parse_layers,
    plan_layers,
    render_metadata,
)
from gradsep.renderer.scene import LoadedScene

if TYPE_CHECKING:
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.plancache import CacheFolder, PlanCache
    from gradsep.renderer.planner import FixedChoice, PlanChoice, PlannedFrame


#: The OIDN setting a ``--seconds`` plan asks for (model.frame.OIDN_SETTING_KEY) where its budget makes the extra
#: denoising cheap: prefiltered features and OIDN's large model, which served held-out frames with the direct
#: layer's gradients and no light in view better than the default ``raw-fast`` (docs/decisions.md, "The
#: reconstruction's setting at farm budgets"). A plain frame keeps the default: on ``oidn`` alone it smears a light
#: in view over its neighbours.
FARM_OIDN_SETTING = "prefiltered-high"
#: What FARM_OIDN_SETTING costs over ``raw-fast``, seconds per pixel per layer (the prefilter's two passes per
#: frame included, spread over two layers), with room for a slower machine (benchmarks/bench_oidn.py).
FARM_OIDN_EXTRA_SECONDS = 2.2e-6
#: FARM_OIDN_SETTING is asked for when its extra time is at most this share of the budget (and the frame has no
#: light in view: has_light_in_view).
FARM_OIDN_SHARE = 0.1
#: The frame's own error estimate (renderer/check.py: two reconstructions at the frame's size) is made when its
#: predicted time is at most this share of a ``--seconds`` budget; elsewhere the header keeps the pilot's
#: prediction. Large frames need a long budget for it.
CHECK_SHARE = 0.1


def farm_setting_affordable(width: int, height: int, layers: Iterable[str], seconds: float) -> bool:
    """Whether FARM_OIDN_SETTING's extra denoising time is at most FARM_OIDN_SHARE of a ``seconds`` budget."""
    return width * height * len(list(layers)) * FARM_OIDN_EXTRA_SECONDS <= FARM_OIDN_SHARE * seconds


def reconstruction_setting(width: int, height: int, layers: Iterable[str], gradients: str,
                           seconds: float, light_in_view: bool = False) -> str | None:
    """The OIDN setting a frame rendered to a ``seconds`` budget asks for (model.frame.OIDN_SETTING_KEY), or None
    for the default: FARM_OIDN_SETTING when the frame carries the direct layer's gradients (``oidn-l1`` serves
    it), has no light in view (``light_in_view``: see :func:`has_light_in_view`) and its extra denoising time is
    at most FARM_OIDN_SHARE of the budget."""
    layers = list(layers)
    if gradients not in ("all", "direct") or "direct" not in layers or light_in_view:
        return None
    return FARM_OIDN_SETTING if farm_setting_affordable(width, height, layers, seconds) else None


def has_light_in_view(frame: Frame) -> bool:
    """Whether the frame's direct layer holds a light in view as ``oidn`` sees it (model.outliers.light_in_view).
    With one, FARM_OIDN_SETTING's large model smears the light: the frame keeps the default setting."""
    from gradsep.model.outliers import light_in_view

    direct = frame.layers.get("direct")
    return direct is not None and light_in_view(direct)


@dataclass(frozen=True)
class FrameShape:
    """A frame's size and layers: what its reconstructions cost scales with."""

    width: int
    height: int
    layers: tuple[str, ...]


def check_budget(rate: float, plan: RenderPlan, shape: FrameShape, seconds: float | None, *,
                 farm_setting: bool = True, compare: bool = False, before: float = 0.0) -> float | None:
    """Seconds the frame's own error estimate (renderer/check.py) needs after the last pass, given a
    reconstruction's ``rate`` (seconds per pixel), or None where it does not fit CHECK_SHARE of a ``seconds``
    budget (no budget: always made). With ``farm_setting`` the frame's reconstruction is the one a budget asks for
    (:func:`reconstruction_setting`; the rate is the default setting's); with ``compare`` the check also
    reconstructs the halves with the other of the default and FARM_OIDN_SETTING. ``before``: seconds it costs
    ahead of the passes (a fixed plan's rate measurement), counted against the share."""
    pixels = shape.width * shape.height
    if seconds is None:
        return check_seconds(rate, pixels)
    farm = compare or (farm_setting and reconstruction_setting(shape.width, shape.height, shape.layers,
                                                               plan.gradients, seconds))
    extra = FARM_OIDN_EXTRA_SECONDS * len(shape.layers) if farm else 0.0
    needed = check_seconds(rate, pixels, extra, 2 if compare else 1)
    return needed if needed + before <= CHECK_SHARE * seconds else None


@dataclass
class FrameCheckSizer:
    """Sizes a planned frame's own error estimate (renderer.planner.CheckSizer) with :func:`check_budget`. Where
    ``can_compare`` (a budget that affords FARM_OIDN_SETTING, the setting not fixed by the operator), a plain
    frame's check also compares the two OIDN settings on its halves, time permitting: ``compare`` says whether
    the check last sized (the one the render holds time for) does. Frames with the direct layer's gradients keep
    the rule's setting: their halves never chose otherwise on held-out frames."""

    shape: FrameShape
    seconds: float | None
    farm_setting: bool = True
    can_compare: bool = False
    compare: bool = False

    def __call__(self, rate: float, plan: RenderPlan, before: float) -> float | None:
        self.compare = self.can_compare and not plan.traces_gradients
        held = check_budget(rate, plan, self.shape, self.seconds, farm_setting=self.farm_setting,
                            compare=self.compare, before=before)
        if held is None and self.compare:  # no time to compare: the estimate alone, where it fits
            self.compare = False
            held = check_budget(rate, plan, self.shape, self.seconds, farm_setting=self.farm_setting, before=before)
        return held


def frame_check(planned: PlannedFrame, metadata: dict[str, str], compare: bool = False) -> str:
    """The frame's own error estimate (renderer/check.py) into ``metadata`` (the frame's, with its plan method
    and OIDN setting) as its predicted RelMSE, where the render made its halves; else the pilot's (or the plan
    cache's) prediction, carried to the frame's samples. ``gradsep.predicted_from`` says which. With ``compare``
    the halves are also reconstructed with the other of the default OIDN setting and FARM_OIDN_SETTING, and the
    frame asks for that one (OIDN_SETTING_KEY) where it is clearly better (renderer.check.check_frame). Returns
    the summary's clause."""
    from gradsep.model.header_keys import PLAN_METHOD_KEY
    from gradsep.model.oidn import METHOD_SETTING
    from gradsep.model.reconstruct import choose_method

    if not planned.halves:
        return _carried_estimate(planned, metadata)
    # the method that serves the frame (a fixed plan's frame names none yet: the default for it, as the service
    # would choose); the prediction holds for it only (model.frame.encode_answer)
    method = metadata.get(PLAN_METHOD_KEY) or choose_method(planned.frame)
    metadata[PLAN_METHOD_KEY] = method
    assessed = planned.judgement.assessment() if planned.judgement is not None else None
    exponent = assessed.exponent if assessed is not None else ERROR_EXPONENT
    own = metadata.get(OIDN_SETTING_KEY) or METHOD_SETTING
    options = {own: _served(own, method, metadata)}
    if compare:
        other = METHOD_SETTING if own == FARM_OIDN_SETTING else FARM_OIDN_SETTING
        options[other] = _served(other, method, metadata)
    result = check_frame(planned.halves, planned.spp, exponent, options)
    result.predicted_seconds = planned.check_seconds
    clause = f"predicted RelMSE {result.relmse:.4g} (the frame's halves, {result.seconds:.2f} s)"
    if result.chosen != own:
        if result.chosen == METHOD_SETTING:
            metadata.pop(OIDN_SETTING_KEY, None)
        else:
            metadata[OIDN_SETTING_KEY] = result.chosen
        clause += f"; its halves chose OIDN {result.chosen} over {own}"
    metadata[PREDICTED_RELMSE_KEY] = f"{result.relmse:.6g}"
    metadata[PREDICTED_FROM_KEY] = "frame"
    metadata.update(result.metadata())
    return clause


def _served(setting: str | None, method: str, metadata: dict[str, str]) -> Callable[[Frame], np.ndarray]:
    """A half reconstructed as the service would serve the frame, with OIDN ``setting``."""
    from gradsep.model.oidn import METHOD_SETTING
    from gradsep.model.reconstruct import reconstruct

    def run(frame: Frame) -> np.ndarray:
        frame.metadata = {k: v for k, v in metadata.items() if k != OIDN_SETTING_KEY}
        if setting != METHOD_SETTING and setting is not None:
            frame.metadata[OIDN_SETTING_KEY] = setting
        return reconstruct(frame, method).image
    return run


def _carried_estimate(planned: PlannedFrame, metadata: dict[str, str]) -> str:
    """Without halves: the judging frame's own estimate from the plan cache, else the pilot's prediction, carried
    to the samples this frame got (a pilot slowed by a load spike predicts far fewer)."""
    from gradsep.renderer.plancache import FRAME_ESTIMATE

    judgement = planned.judgement
    assert judgement is not None
    assessed = judgement.assessment()
    earlier = judgement.trace.get(FRAME_ESTIMATE)
    if earlier and assessed is not None:
        # a plan from the plan cache: the estimate of the frame that judged it (its own halves), carried from its
        # samples to this frame's -- the same scene and budget, and far closer than the pilot's
        predicted = at_budget(earlier["relmse"], earlier["spp"], planned.spp, assessed.exponent)  # type: ignore[index]
        metadata[PREDICTED_RELMSE_KEY] = f"{predicted:.6g}"
        metadata[PREDICTED_FROM_KEY] = "plan-cache"
        return f"predicted RelMSE {predicted:.4g} (the judging frame's own, carried to this frame's samples)"
    predicted = (judgement.predicted() if assessed is None or not assessed.budget_spp > 0 else
                 at_budget(assessed.predicted_relmse, assessed.budget_spp, planned.spp, assessed.exponent))
    metadata[PREDICTED_RELMSE_KEY] = f"{predicted:.6g}"
    metadata[PREDICTED_FROM_KEY] = "pilot"
    return f"predicted RelMSE {predicted:.4g} (the pilot's: no time for the frame's own check)"


@dataclass(frozen=True)
class PlanRequest:
    """What a planned frame is asked for besides its budget: the sampler ``seed``, the ``layers``, the ``shift``,
    and the plan: ``gradients`` ``auto`` (the checkpoint, or the plan cache) or a fixed plan (``gradients`` and
    ``offsets`` as for :func:`render_frame`)."""

    seed: int = 0
    layers: str | Iterable[str] = SEPARATED_LAYERS
    shift: str | None = None
    gradients: str = "auto"
    offsets: str = "all"


def render_planned_frame(scene: LoadedScene, budget: FrameBudget, request: PlanRequest = PlanRequest(), *,
                         progress: Callable[[int, int], None] | None = None,
                         plan_cache: CacheFolder | None = None) -> tuple[Frame, str]:
    """`gradsep render --seconds T` and/or ``--gradients auto`` (renderer/planner.py): the frame, rendered to the
    ``budget`` (renderer.frame_budget.FrameBudget: a deadline or a sample count) with the ``request``'s plan, and
    a one-line summary of the plan. The metadata is :func:`render_metadata`'s plus the plan's keys
    (renderer.plans). ``plan_cache`` (``auto`` only; renderer/plancache.py): the plan an earlier frame's
    checkpoint chose for this scene, frame and budget is rendered as a fixed plan, with no checkpoint; a
    checkpoint's choice is written there."""
    from gradsep.renderer.planner import PlannerOptions, render_planned

    wanted, notes, choice, shift_name = _checked_request(scene, request)
    entry = None
    if request.gradients == "auto" and plan_cache is not None:
        entry, cached, why = _cache_entry(plan_cache, scene, wanted, shift_name, budget)
        notes += [why] if why else []
        choice = cached or choice
    sizer = FrameCheckSizer(FrameShape(scene.width, scene.height, wanted), budget.seconds,
                            can_compare=_can_compare(scene, wanted, budget))
    start = time.perf_counter()
    planned = render_planned(scene, wanted, choice, budget, seed=request.seed, shift=request.shift,
                             options=PlannerOptions(progress=progress, check=sizer))
    seconds = time.perf_counter() - start
    metadata, summary = _planned_metadata(scene, planned, wanted, (request.seed, shift_name), seconds)
    if entry is not None and choice is cached:
        metadata[PLAN_CACHE_KEY] = f"read {entry.path.name}"
    if planned.judgement is not None:
        metadata.update(planned.judgement.metadata(wanted))
        summary = planned.judgement.summary()
    if budget.deadline is not None:
        summary += _budget_setting(planned, metadata, wanted, budget.deadline.seconds)
    if planned.halves is not None or (planned.judgement is not None and planned.judgement.assessments):
        summary += "; " + frame_check(planned, metadata, compare=sizer.compare and planned.halves is not None)
    if entry is not None and choice is not cached:  # a checkpoint's choice, and the frame's own estimate, to share
        summary += _share(entry, planned, metadata, request.seed, notes)
    if budget.deadline is not None:
        metadata[ELAPSED_KEY] = f"{budget.deadline.elapsed():.3f}"
    frame = planned.frame
    frame.metadata = metadata
    frame.warnings = notes + frame.warnings
    return frame, summary


def _checked_request(scene: LoadedScene,
                     request: PlanRequest) -> tuple[tuple[str, ...], list[str], PlanChoice, str]:
    """The request checked against the scene: its layers (with notes on those dropped), its plan's choice and the
    shift's name; a user error for a bad request."""
    from gradsep.renderer.planner import CheckpointChoice, FixedChoice
    from gradsep.renderer.plans import fixed_plan
    from gradsep.renderer.shift import make_shift  # imports Mitsuba

    if not 0 <= request.seed < 2**32:
        raise CommandError(f"--seed must be in [0, 2^32), got {request.seed}")
    if request.offsets not in OFFSET_CHOICES:
        raise CommandError(f"--offsets must be one of {', '.join(OFFSET_CHOICES)}, got {request.offsets!r}")
    wanted, notes = plan_layers(parse_layers(request.layers), scene.max_depth)
    choice: PlanChoice = CheckpointChoice()
    if request.gradients != "auto":
        mode = gradients_mode(request.gradients)
        if mode == "none" and request.offsets != "all":
            raise CommandError("--offsets has no effect without gradients (no offset paths are traced)")
        if mode == "direct" and "direct" not in wanted:
            raise CommandError(f"--gradients direct needs the separated direct layer; --layers {','.join(wanted)} "
                               "has none (use --gradients all or none)")
        choice = FixedChoice(fixed_plan(mode, request.offsets))
    try:
        shift_name = make_shift(request.shift).name
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    return wanted, notes, choice, shift_name


def _cache_entry(plan_cache: CacheFolder, scene: LoadedScene, wanted: tuple[str, ...], shift_name: str,
                 budget: FrameBudget) -> tuple[PlanCache, FixedChoice | None, str | None]:
    """The plan cache's entry for this frame, the fixed choice it holds (None: none usable) and why an entry was
    not used."""
    from gradsep.renderer.plancache import FrameKey
    from gradsep.renderer.planner import FixedChoice

    entry = plan_cache.entry(FrameKey(scene.width, scene.height, wanted, scene.max_depth, shift_name,
                                      budget.seconds, budget.spp))
    cached, why = entry.load()
    return entry, FixedChoice(cached.chosen, cached) if cached is not None else None, why


def _can_compare(scene: LoadedScene, wanted: tuple[str, ...], budget: FrameBudget) -> bool:
    """Whether the frame's check may choose between FARM_OIDN_SETTING and the default: a budget that affords it,
    and no operator's fixed setting ($GRADSEP_OIDN_SETTING wins over the header anyway)."""
    return (budget.seconds is not None
            and farm_setting_affordable(scene.width, scene.height, wanted, budget.seconds)
            and not os.environ.get(SETTING_ENV, "").strip())


def _planned_metadata(scene: LoadedScene, planned: PlannedFrame, wanted: tuple[str, ...], seed_shift: tuple[int, str],
                      seconds: float) -> tuple[dict[str, str], str]:
    """The planned frame's header before its judgement and check (``seed_shift``: its seed and the shift's name),
    and the summary's start."""
    plan = planned.plan
    seed, shift_name = seed_shift
    metadata = render_metadata(scene, RenderRecord(planned.spp, seed, shift_name if plan.traces_gradients else "none",
                                                   wanted, seconds, planned.passes, plan.gradients))
    if plan.traces_gradients and plan.offsets != "all":
        metadata["gradsep.offsets"] = plan.offsets
    if 0 < planned.gradient_spp < planned.spp:
        metadata["gradsep.gradient_spp"] = str(planned.gradient_spp)
    metadata.update({PLAN_KEY: plan.name, PLAN_LAYERS_KEY: plan_layers_text(plan, wanted)})
    return metadata, f"plan {plan.name}"


def _budget_setting(planned: PlannedFrame, metadata: dict[str, str], wanted: tuple[str, ...], seconds: float) -> str:
    """A ``--seconds`` frame's budget and the OIDN setting it asks for into ``metadata``; the summary's clause."""
    metadata[BUDGET_KEY] = f"{seconds:g}"
    frame = planned.frame
    setting = reconstruction_setting(frame.width, frame.height, wanted, planned.plan.gradients, seconds)
    if setting and has_light_in_view(frame):
        return "; a light in view: the default OIDN setting"
    if setting:
        metadata[OIDN_SETTING_KEY] = setting
        return f"; reconstruct with OIDN {setting}"
    return ""


def _share(entry: PlanCache, planned: PlannedFrame, metadata: dict[str, str], seed: int, notes: list[str]) -> str:
    """A checkpoint's choice and the frame's own estimate written to the plan cache; the summary's clause."""
    judgement = planned.judgement
    if judgement is not None and judgement.assessments:
        own = None  # the frame's own estimate, where its halves made one
        if metadata.get(PREDICTED_FROM_KEY) == "frame":
            own = (float(metadata[PREDICTED_RELMSE_KEY]), planned.spp)
        failed = entry.store(judgement, seed, own)
        notes += [failed] if failed else []
        metadata[PLAN_CACHE_KEY] = "not written" if failed else f"wrote {entry.path.name}"
    else:
        metadata[PLAN_CACHE_KEY] = "nothing to share: no checkpoint judged"
    return f"; plan cache: {metadata[PLAN_CACHE_KEY]}"
