"""How each evaluated row (evaluation/methods.py) turns a scene + G-PT frame into an image and timings:
:func:`run_method` by the row's kind, with the loaded networks (:class:`NetworkPool`).

The planned row (``gpt-auto``) is not searched: it renders once to a :class:`~renderer.budget.Deadline` that starts
when the row starts and has the whole budget, whose tail (``Deadline.tail``, what must be left when the last pass
ends) is the measured cost of reconstructing the frame: the slowest of the candidates' default reconstructions,
each timed like a searched row's post-processing (:meth:`PathRenderer.planner_tail`). It starts warm, as the
searched rows do: each plan's pass costs and the reconstruction's rate are measured beforehand, untimed, once per
scene (:meth:`PathRenderer.planner_priors`, renderer.passes.Priors), so that where no checkpoint fits its first pass
is sized from them instead of probing with a 1-spp pass. Everything it does is charged:
the checkpoint (its passes, which stay in the frame, and its tile reconstructions), the passes that fill the
deadline and the reconstruction. It keeps one try (``attempts`` 1); a total outside ±5 % records why
(``time_note``: pass granularity, a pass or the reconstruction slower than predicted, a budget below one pass).
Its ``extra`` records the plan chosen, each judged plan's predicted RelMSE and the chosen one's
(``predicted_relmse``; None with ``predicted_note`` where no checkpoint fitted and the planner rendered its
fallback).

Timings exclude one-time costs on both sides: each network is run once untimed per frame size (ONNX
Runtime's allocation on a new shape), Mitsuba's kernels are compiled before the timed render. The G-PT
render time is the renderer's own (``gradsep.render_seconds``), which includes its per-frame tracing. The planned
row's kernels (one per candidate) and its reconstruction (on the frame's and the pilot tiles' sizes) are run once
untimed per scene; its per-frame tracing is timed.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.evaluation.baselines import PathRenderer, denoise, sanitise, split_features
from gradsep.evaluation.methods import FEATURE_SPP, BracketOutput, MethodOutput, MethodSpec
from gradsep.evaluation.timesearch import TIME_SEARCH, Attempt
from gradsep.model import methods as table
from gradsep.model.frame import Frame

__all__ = ["MethodContext", "NetworkPool", "run_method"]


# ------------------------------------------------------------------------------------------------ networks


class NetworkPool:
    """Loaded ONNX reconstructors by folder, with the untimed warm-up runs per frame size.

    A model that exists but cannot be served (corrupt, exported for another layer) is an error the user has to
    fix, raised as ``ModelError`` -- not a method silently skipped.
    """

    def __init__(self) -> None:
        self._loaded: dict[Path, Any] = {}
        self._warm: set[tuple[Path, str, tuple[int, int]]] = set()

    def loaded(self, models_dir: Path, method: str) -> table.LoadedModels:
        """The model sets the table's ``method`` needs, each loaded once from ``models_dir`` by its own loader."""
        sets: dict[str, Any] = {}
        for name in table.get(method).model_sets:
            key = (models_dir.resolve() / f"<{name}>")
            if key not in self._loaded:
                self._loaded[key] = table.resolve(table.MODEL_SETS[name].loader)(models_dir)
            sets[name] = self._loaded[key]
        return table.LoadedModels(**sets)

    def get(self, folder: Path) -> Any:
        """The folder's network models (the paper's baselines and ablations: ``network`` rows)."""
        folder = folder.resolve()
        if folder not in self._loaded:
            from gradsep.model.infer import NetworkReconstructor

            self._loaded[folder] = NetworkReconstructor.load(folder)
        return self._loaded[folder]

    def warm_up(self, folder: Path, run: Callable[[], object], key: str, shape: tuple[int, int]) -> None:
        """Run ``run`` once untimed the first time ``key`` meets a frame of ``shape`` in ``folder``."""
        tag = (folder.resolve(), key, shape)
        if tag not in self._warm:
            run()
            self._warm.add(tag)


# ------------------------------------------------------------------------------------------------ running


@dataclass
class MethodContext:
    """Everything a method may need for one (scene, spp)."""

    frame: Frame
    render_seconds: float  # G-PT render time of ``frame``
    spp: int
    seed: int
    alpha: float
    models_dir: Path
    networks: NetworkPool
    path: Callable[[], PathRenderer]  # lazily built per scene (loads Mitsuba integrators)
    budget_seconds: float | None = None  # equal-time budget of the EQUAL_TIME_KINDS methods
    budget_method: str | None = None


def run_method(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """Run one method; ModelError for a model that exists but cannot be served."""
    runner = {"primal": _run_primal, "network": _run_network, "recon": _run_recon, "path": _run_path,
              "oidn": _run_oidn, "sep-oidn": _run_sep_oidn, "gpt-equal": _run_gpt_equal,
              "gpt-auto": _run_gpt_auto}[spec.kind]
    return runner(spec, ctx)


def _run_primal(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    layers = {name: sanitise(layer.base) for name, layer in ctx.frame.layers.items()}
    image = sanitise(sum(layers.values()))
    return MethodOutput(image, layers, ctx.render_seconds, 0.0, ctx.spp)


def _run_network(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    from gradsep.model.reconstruct import reconstruct

    folder = ctx.models_dir / (spec.models or "")
    network = ctx.networks.get(folder)
    frame = ctx.frame
    shape = (frame.height, frame.width)
    if spec.separated:
        def run() -> Any:
            return reconstruct(frame, "network", models=table.LoadedModels(network=network))

        ctx.networks.warm_up(folder, run, "separated", shape)
        start = time.perf_counter()
        result = run()
        seconds = time.perf_counter() - start
        return MethodOutput(result.image, result.layers, ctx.render_seconds, seconds, ctx.spp,
                            warnings=list(result.warnings))

    def run_combined() -> np.ndarray:
        return sanitise(network.reconstruct_layer("color", frame.combined(), frame.features))

    ctx.networks.warm_up(folder, run_combined, "color", shape)
    start = time.perf_counter()
    image = run_combined()
    seconds = time.perf_counter() - start
    return MethodOutput(image, {}, ctx.render_seconds, seconds, ctx.spp)


def _run_recon(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """``reconstruct(frame, method)`` with the model sets the method needs (model/methods.py). A method that needs
    models or OIDN is run once untimed per frame size first (ONNX Runtime's allocation on a new shape, the OIDN
    device); a model that exists but cannot be served raises ModelError at load."""
    from gradsep.model.reconstruct import reconstruct

    method = table.get(str(spec.method))
    models = ctx.networks.loaded(ctx.models_dir, method.name)

    def run() -> Any:
        return reconstruct(ctx.frame, method.name, ctx.alpha, models)

    if method.models:
        folder = ctx.models_dir / (spec.models or "")
        ctx.networks.warm_up(folder, run, f"recon:{method.name}", (ctx.frame.height, ctx.frame.width))
    start = time.perf_counter()
    result = run()
    seconds = time.perf_counter() - start
    return MethodOutput(result.image, result.layers, ctx.render_seconds, seconds, ctx.spp,
                        extra={"alpha": ctx.alpha} if method.alpha else {}, warnings=list(result.warnings))


def _budget(ctx: MethodContext) -> float:
    if ctx.budget_seconds is None:
        raise RuntimeError("equal-time methods need a budget (the G-PT render + reconstruction time)")
    return ctx.budget_seconds


def _run_path(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    renderer = ctx.path()
    target = _budget(ctx)
    got = renderer.render_within("path", target, ctx.seed)
    return MethodOutput(sanitise(got.output[..., :3]), {}, got.render_seconds, 0.0, got.spp,
                        extra=_equal_time_extra(ctx, target, got, renderer.max_spp),
                        bracket=_bracket_outputs(got, lambda raw: (sanitise(raw[..., :3]), {})))


def _run_oidn(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """``path`` + OIDN: a timed :data:`FEATURE_SPP`-spp feature pass, then ``path`` + the denoiser call tried
    at spp bisected until both together fit what is left of the budget."""
    renderer = ctx.path()
    target = _budget(ctx)
    renderer.warm("features")
    features, feature_seconds = renderer.render("features", FEATURE_SPP, ctx.seed ^ 0x5EED)
    albedo, normal = split_features(features)
    colour = np.ones(albedo.shape, np.float32)
    estimate = renderer.post_seconds("path-oidn", lambda: denoise(colour, albedo, normal))
    got = renderer.render_within("path", max(1e-6, target - feature_seconds), ctx.seed,
                                 post=lambda raw: denoise(raw[..., :3], albedo, normal), post_estimate=estimate)
    extra = _equal_time_extra(ctx, target, got, renderer.max_spp)
    extra["feature_spp"] = FEATURE_SPP
    return MethodOutput(got.output, {}, got.render_seconds + feature_seconds, got.post_seconds, got.spp, extra=extra,
                        bracket=_bracket_outputs(got, lambda image: (image, {}), extra_render=feature_seconds))


def _run_sep_oidn(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """The primal-only G-PT render (separated layers, first-hit features, no gradients) reconstructed with the
    ``oidn`` method (OIDN on each layer, summed: model/oidn.py), render + reconstruction bisected to the budget."""
    return _run_frame_within(spec, ctx, "primal", "oidn")


def _run_gpt_equal(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """Our G-PT render (``--gradients direct``, :data:`EQUAL_TIME_OFFSETS`) reconstructed with ``spec.method``
    (``oidn-l1``), render + reconstruction bisected to the budget like the baselines'."""
    return _run_frame_within(spec, ctx, "gpt-direct", str(spec.method))


def _run_frame_within(spec: MethodSpec, ctx: MethodContext, kind: str, method: str) -> MethodOutput:
    """A Frame-producing renderer ``kind`` + ``reconstruct(frame, method)`` at the spp whose measured total fits
    the budget (:meth:`PathRenderer.render_within`)."""
    from gradsep.model.reconstruct import reconstruct

    renderer = ctx.path()
    target = _budget(ctx)
    renderer.warm(kind)
    sample, _ = renderer.render(kind, 1, 23)
    estimate = renderer.post_seconds(spec.name, lambda: reconstruct(sample, method))
    got = renderer.render_within(kind, target, ctx.seed, post=lambda frame: reconstruct(frame, method),
                                 post_estimate=estimate)
    result = got.output
    return MethodOutput(result.image, result.layers, got.render_seconds, got.post_seconds, got.spp,
                        extra=_equal_time_extra(ctx, target, got, renderer.max_spp), warnings=list(result.warnings),
                        bracket=_bracket_outputs(got, lambda r: (r.image, dict(r.layers))))


#: How the planned row meets its budget (recorded per row as ``time_search``, like the searched rows' TIME_SEARCH).
PLANNED_TIME = "one render to the planner's deadline"


@dataclass(frozen=True)
class PlannedTimes:
    """What the planned row's time note reads: the budget, the render's and the reconstruction's seconds, the
    reconstruction's reserve (``tail``), why the budget was refused ("" when it was not), the chosen plan's
    assessment (None without one), its name and the checkpoint's (``pilot``) seconds."""

    target: float
    render: float
    post: float
    tail: float
    refused: str
    chosen: Any
    plan: str
    pilot: float


def _run_gpt_auto(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """The render planner at equal time: ``render_planned`` (checkpoint, then passes) to a deadline that starts
    now with the whole budget and keeps the measured reconstruction time as its tail, then the default method the
    frame names. One shot: the measured total is recorded against the budget with the reason of a miss. A budget
    below the planner's start-up (CommandError: one pass and the reconstruction do not fit) renders 1 spp of the
    fallback plan regardless, recorded as such; a frame without a checkpoint records why, with no prediction."""
    from gradsep.model.header_keys import PLAN_METHOD_KEY
    from gradsep.model.reconstruct import reconstruct
    from gradsep.renderer.planned_frame import frame_check

    renderer = ctx.path()
    target = _budget(ctx)
    layers = tuple(ctx.frame.layers)
    tail = renderer.planner_tail(layers)
    priors = renderer.planner_priors(layers)
    start = time.perf_counter()
    planned, deadline, refused = _render_planned_row(renderer, layers, int(ctx.seed) % (1 << 32), target, tail,
                                                     priors)
    frame, plan = planned.frame, planned.judgement
    frame.metadata = plan.metadata(layers) if plan is not None else {}
    if plan is not None and plan.assessments:
        frame_check(planned, frame.metadata)
    rendered = time.perf_counter()
    result = reconstruct(frame, frame.metadata.get(PLAN_METHOD_KEY))
    done = time.perf_counter()
    times = PlannedTimes(target, rendered - start, done - rendered, deadline.tail or tail, refused, None,
                         planned.plan.name, plan.pilot_seconds if plan is not None else 0.0)
    extra = _planned_extra(ctx, planned, result.method, times, layers)
    return MethodOutput(result.image, result.layers, times.render, times.post, planned.spp, extra=extra,
                        warnings=[*frame.warnings, *result.warnings])


def _render_planned_row(renderer: PathRenderer, layers: tuple[str, ...], seed: int, target: float, tail: float,
                        priors: Any) -> tuple[Any, Any, str]:
    """(the planned render, its deadline, why the budget was refused: "" when it was not)."""
    from gradsep.model.errors import CommandError
    from gradsep.renderer.budget import Deadline
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.planned_frame import FrameCheckSizer, FrameShape
    from gradsep.renderer.planner import CheckpointChoice, FixedChoice, PlannerOptions, render_planned
    from gradsep.renderer.plans import fallback_plan

    width, height = renderer.loaded.width, renderer.loaded.height
    deadline = Deadline(target, tail=tail)
    try:  # the frame's own error estimate as the command makes it, with the default OIDN setting (as served here)
        sizer = FrameCheckSizer(FrameShape(width, height, layers), target, farm_setting=False)
        planned = render_planned(renderer.loaded, layers, CheckpointChoice(), FrameBudget(deadline), seed=seed,
                                 options=PlannerOptions(check=sizer, priors=priors))
    except CommandError:  # not one pass + the reconstruction fit: what `gradsep render --seconds` refuses
        refused = (f"the budget is below the planner's start-up here (its first pass, then {tail:.3g} s of "
                   f"reconstruction): 1 spp of `{fallback_plan(layers).name}` rendered regardless")
        return render_planned(renderer.loaded, layers, FixedChoice(fallback_plan(layers)), FrameBudget(spp=1),
                              seed=seed), deadline, refused
    return planned, deadline, ""


def _planned_extra(ctx: MethodContext, planned: Any, method: str, times: PlannedTimes,
                   layers: tuple[str, ...]) -> dict[str, Any]:
    """What the planned row records of its plan, its prediction and its time (PLAN_ROW_KEYS and the timing keys)."""
    from gradsep.model.header_keys import PREDICTED_FROM_KEY, PREDICTED_RELMSE_KEY
    from gradsep.renderer.plans import plan_layers_text

    frame, plan, chosen = planned.frame, planned.judgement, planned.plan
    assessed = {a.name: a for a in plan.assessments} if plan is not None else {}
    predicted = float(frame.metadata.get(PREDICTED_RELMSE_KEY, "nan")) if assessed else math.nan
    times = dataclasses.replace(times, chosen=assessed.get(chosen.name))
    extra: dict[str, Any] = {
        "target_seconds": times.target, "budget_method": ctx.budget_method, "attempts": 1,
        "time_search": PLANNED_TIME, "time_tries": [(planned.spp, times.render + times.post)],
        "gradients": chosen.gradients, "time_note": _planned_time_note(times),
        "plan": chosen.name, "plan_layers": plan_layers_text(chosen, layers), "plan_method": method,
        "plan_candidates": {name: _finite_or_none(a.predicted_relmse) for name, a in assessed.items()},
        "predicted_relmse": _finite_or_none(predicted), "predicted_from": frame.metadata.get(PREDICTED_FROM_KEY),
        "pilot_seconds": times.pilot,
        "plan_note": plan.note if plan is not None else "", "gradient_spp": planned.gradient_spp,
    }
    if extra["predicted_relmse"] is None:
        extra["predicted_note"] = (times.refused or (plan.note if plan is not None and not assessed else "")
                                   or "the chosen plan's prediction is not finite")
    return extra


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _planned_time_note(t: PlannedTimes) -> str:
    """Why the planned row's total is outside ±TOLERANCE of ``t.target`` ("" when it is within): the budget was
    below the planner's start-up (``refused``), the render ended early (pass granularity: the planner starts no
    pass predicted to end past the deadline) or late (the ``pilot`` alone ran past it, or a pass was slower than
    predicted), and/or the reconstruction took other than the ``tail`` reserved for it."""
    target, render, post, tail, chosen, pilot = t.target, t.render, t.post, t.tail, t.chosen, t.pilot
    total = render + post
    if abs(total / target - 1.0) <= PathRenderer.TOLERANCE:
        return ""
    if t.refused:  # the refused attempt's time is in the render's
        return f"{t.refused} (render {render:.3g} s, the refused attempt included)"
    parts = []
    early = (target - tail) - render  # time the render left unused before the reconstruction's reserve
    significant = 0.01 * target
    if early > significant:
        per = f" ({chosen.per_sample:.3g} s per spp)" if chosen is not None else ""
        parts.append(f"the render stopped {early:.3g} s before the budget less the reconstruction's reserve: the "
                     f"next pass of `{t.plan}`{per} was predicted not to fit (pass granularity)")
    elif early < -significant:
        why = (f"the checkpoint alone took {pilot:.3g} s: its passes and reconstructions are not cut short"
               if pilot > target - tail else "a pass slower than predicted")
        parts.append(f"the render ended {-early:.3g} s past the budget less the reconstruction's reserve ({why})")
    if abs(post - tail) > significant:
        parts.append(f"the reconstruction took {post:.3g} s against the {tail:.3g} s reserved")
    return "; ".join(parts) or "several small overruns"


def _bracket_outputs(got: Attempt, convert: Callable[[Any], tuple[np.ndarray, dict[str, np.ndarray]]],
                     extra_render: float = 0.0) -> list[BracketOutput]:
    """The attempt's bracket as outputs (``convert``: a try's output -> (image, layers)); [] without one.
    ``extra_render``: time every try also paid on the render side (path + OIDN's feature pass)."""
    if got.bracket is None:
        return []
    return [BracketOutput(b.spp, b.render_seconds + extra_render, b.post_seconds, *convert(b.output))
            for b in got.bracket]


def _equal_time_extra(ctx: MethodContext, target: float, got: Attempt, max_spp: int) -> dict[str, Any]:
    extra: dict[str, Any] = {"target_seconds": target, "budget_method": ctx.budget_method,
                             "attempts": got.attempts, "time_search": TIME_SEARCH, "time_tries": got.tries,
                             "time_note": got.note}
    if got.spp >= max_spp:
        extra["capped"] = f"spp capped at {max_spp} (Mitsuba's 2^32 samples per launch)"
    return extra
