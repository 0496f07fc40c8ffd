"""Frame rendering front end: scene + settings -> a :class:`model.frame.Frame` (and `gradsep render`).

Decides which illumination layers a render needs (a max depth of 2 or less leaves no indirect light, so that
layer is neither traced nor written; ``--layers direct`` stops every path after its first vertex), runs the G-PT
integrator (renderer/gpt.py) with the chosen shift (renderer/shift.py), and packs the result with the frame
contract's metadata keys (``gradsep.*``).
"""

from __future__ import annotations

import numbers
import os
import time
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np

from gradsep.model import __version__
from gradsep.model.errors import CommandError
from gradsep.model.frame import (
    ILLUMINATION_LAYERS,
    OIDN_SETTING_KEY,
    PREDICTED_FROM_KEY,
    PREDICTED_RELMSE_KEY,
    SEPARATED_LAYERS,
    Frame,
)
from gradsep.model.oidn import SETTING_ENV
from gradsep.renderer.budget import Deadline
from gradsep.renderer.check import check_frame, check_seconds
from gradsep.renderer.estimate import at_budget
from gradsep.renderer.scene import LoadedScene, load_scene

if TYPE_CHECKING:
    from gradsep.renderer.plan import Candidate, Planned
    from gradsep.renderer.plancache import CacheFolder


def parse_layers(text: str | Iterable[str]) -> tuple[str, ...]:
    """``"direct,indirect"`` -> ("direct", "indirect") in contract order; ``color`` alone is the unseparated
    image (separation off); unknown names are a user error."""
    items = [t.strip() for t in (text.split(",") if isinstance(text, str) else text)]
    items = [t for t in items if t]
    unknown = sorted(set(items) - set(ILLUMINATION_LAYERS))
    if unknown:
        raise CommandError(f"unknown layer(s) {', '.join(unknown)}; expected a comma-separated subset of "
                           f"{','.join(SEPARATED_LAYERS)}, or color")
    if not items:
        raise CommandError("--layers is empty; expected direct, indirect, both, or color")
    if "color" in items:
        if set(items) != {"color"}:
            raise CommandError("--layers color is the unseparated image; it cannot be combined with direct or "
                               "indirect")
        return ("color",)
    return tuple(layer for layer in SEPARATED_LAYERS if layer in items)


def plan_layers(requested: tuple[str, ...], max_depth: int) -> tuple[tuple[str, ...], list[str]]:
    """The layers to trace given the depth limit, plus notes about layers dropped because no light reaches them."""
    notes: list[str] = []
    layers = requested
    if layers == ("color",):
        return layers, notes
    if "indirect" in requested and 0 < max_depth <= 2:
        layers = tuple(layer for layer in requested if layer != "indirect")
        notes.append(f"max_depth {max_depth} carries no indirect light: the indirect layer is not rendered")
    if not layers:
        raise CommandError(f"max_depth {max_depth} carries no indirect light; nothing to render for --layers indirect")
    return layers, notes


#: ``gradsep render --gradients``: which layers carry gradients. ``all`` (every layer, the default), ``direct``
#: (the direct layer's; offsets are traced only to the direct layer's vertices, the indirect layer is a plain
#: primal), ``none`` (the primal-only mode: no offset paths).
GRADIENT_CHOICES: tuple[str, ...] = ("all", "direct", "none")
#: ``gradsep render --offsets``: which offset paths a sample traces (``renderer.gpt.OFFSET_MODES``, which a test keeps
#: equal to this without importing Mitsuba here).
OFFSET_CHOICES: tuple[str, ...] = ("all", "pair", "single", "alternate")


def gradients_mode(gradients: bool | str) -> str:
    """``render_frame``'s ``gradients`` as one of GRADIENT_CHOICES (True = ``all``, False = ``none``)."""
    if isinstance(gradients, bool):
        return "all" if gradients else "none"
    if gradients not in GRADIENT_CHOICES:
        raise CommandError(f"--gradients must be one of {', '.join(GRADIENT_CHOICES)}, got {gradients!r}")
    return gradients


def check_gradient_spp(gradient_spp: int | None, spp: int, mode: str) -> int:
    """``--gradient-spp`` checked against ``--spp`` and the gradients mode; None -> ``spp`` (every sample)."""
    if gradient_spp is None:
        return spp
    if isinstance(gradient_spp, bool) or not isinstance(gradient_spp, numbers.Integral):
        raise CommandError(f"--gradient-spp must be an integer, got {gradient_spp!r}")
    gradient_spp = int(gradient_spp)
    if mode == "none":
        raise CommandError("--gradient-spp has no effect without gradients (no offset paths are traced)")
    if not 1 <= gradient_spp <= spp:
        raise CommandError(f"--gradient-spp must be between 1 and --spp ({spp}), got {gradient_spp}")
    return gradient_spp


def render_frame(scene: LoadedScene | str, *, spp: int, seed: int = 0,
                 layers: str | Iterable[str] = SEPARATED_LAYERS, shift: str | None = None,
                 max_depth: int | None = None, width: int | None = None, height: int | None = None,
                 defines: Mapping[str, str] | None = None,
                 progress: Callable[[int, int], None] | None = None, gradients: bool | str = True,
                 offsets: str = "all", gradient_spp: int | None = None) -> Frame:
    """Render one G-PT frame: per requested layer base + dx + dy, features at the first non-specular vertex.

    ``scene`` is a loaded scene or a spec (XML path / ``procedural:SEED``) loaded with ``width``, ``height``,
    ``max_depth`` and ``defines``. ``max_depth`` given here overrides the loaded scene's. ``layers`` ``color``
    renders the unseparated image. ``gradients`` (GRADIENT_CHOICES, or True = ``all`` / False = ``none``):
    ``none`` is the primal-only mode: the same base paths, layers and features, no offset paths; the frame's
    layers carry no gradients (``dx``/``dy`` None) and ``shift`` is ignored. ``direct`` gives the direct layer
    its gradients -- the same as an ``all`` render with this seed -- and the indirect layer none (its base is the
    primal-only render's): the offsets stop after the direct layer's vertices. ``offsets`` (``--offsets``): which
    offsets a sample traces, ``GptSettings.offsets`` (``all``, or fewer: ``alternate``, ``pair``, ``single``; the
    same channels, gradients counted with their inverse probability; recorded as ``gradsep.offsets`` unless ``all``).
    ``gradient_spp`` K (``--gradient-spp``; default ``spp``): only K of the ``spp`` samples trace offsets, the
    other ``spp - K`` are primal-only samples; the bases and features are the mean over all ``spp`` samples, the
    gradients the K G-PT samples' (``render_gpt``). K == ``spp`` is the plain render; a K below ``spp`` is recorded
    as ``gradsep.gradient_spp`` (``gradsep.spp`` stays the bases' sample count).
    """
    from gradsep.renderer.gpt import GptSettings, render_gpt
    from gradsep.renderer.plan import as_frame
    from gradsep.renderer.shift import make_shift  # imports Mitsuba

    if spp < 1:
        raise CommandError(f"--spp must be >= 1, got {spp}")
    if not 0 <= seed < 2**32:
        raise CommandError(f"--seed must be in [0, 2^32), got {seed}")
    if isinstance(scene, str):
        scene = load_scene(scene, width=width, height=height, max_depth=max_depth, defines=defines)
    elif max_depth is not None:
        if max_depth == 0 or max_depth < -1:
            raise CommandError(f"--max-depth must be -1 (unbounded) or >= 1, got {max_depth}")
        scene = LoadedScene(scene.scene, scene.spec, scene.width, scene.height, max_depth, scene.rr_depth,
                            scene.defines)
    mode = gradients_mode(gradients)
    if offsets not in OFFSET_CHOICES:
        raise CommandError(f"--offsets must be one of {', '.join(OFFSET_CHOICES)}, got {offsets!r}")
    if mode == "none" and offsets != "all":
        raise CommandError("--offsets has no effect without gradients (no offset paths are traced)")
    gradient_spp = check_gradient_spp(gradient_spp, spp, mode)
    wanted, notes = plan_layers(parse_layers(layers), scene.max_depth)
    if mode == "direct" and "direct" not in wanted:
        raise CommandError(f"--gradients direct needs the separated direct layer; --layers {','.join(wanted)} "
                           "has none (use --gradients all or none)")
    try:
        shift_impl = make_shift(shift) if mode != "none" else None
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    color = wanted == ("color",)
    settings = GptSettings(max_depth=scene.max_depth, rr_depth=scene.rr_depth, direct=color or "direct" in wanted,
                           indirect=color or "indirect" in wanted, separate=not color,
                           gradients="direct" if mode == "direct" else "all", offsets=offsets)
    start = time.perf_counter()
    result = render_gpt(scene.scene, shift_impl, settings, scene.width, scene.height, spp, seed, progress,
                        gradient_spp=gradient_spp)
    seconds = time.perf_counter() - start

    metadata = render_metadata(scene, spp=spp, seed=seed, shift=shift_impl.name if shift_impl else "none",
                               layers=wanted, seconds=seconds, passes=result.passes, gradients=mode)
    if offsets != "all":
        metadata["gradsep.offsets"] = offsets
    if gradient_spp < spp:
        metadata["gradsep.gradient_spp"] = str(gradient_spp)
    frame = as_frame(result)
    frame.metadata, frame.warnings = metadata, notes + frame.warnings
    return frame


def render_metadata(scene: LoadedScene, *, spp: int, seed: int, shift: str, layers: tuple[str, ...],
                    seconds: float, passes: int, gradients: bool | str = True) -> dict[str, str]:
    """The ``gradsep.*`` EXR header attributes of a rendered frame (all strings); the integrator is ``gpt``, or
    ``primal`` for the primal-only mode (shift ``none``); ``gradsep.gradients`` says which layers carry
    gradients (``all``, ``direct`` or ``none``)."""
    import mitsuba as mi

    mode = gradients_mode(gradients)
    meta = {
        "gradsep.version": __version__,
        "gradsep.integrator": "gpt" if mode != "none" else "primal",
        "gradsep.gradients": mode,
        **scene.scene_metadata(),
        "gradsep.spp": str(spp),
        "gradsep.seed": str(seed),
        "gradsep.max_depth": str(scene.max_depth),
        "gradsep.rr_depth": str(scene.rr_depth),
        "gradsep.shift": shift,
        "gradsep.layers": ",".join(layers),
        "gradsep.render_seconds": f"{seconds:.3f}",
        "gradsep.passes": str(passes),
        "gradsep.mitsuba_variant": str(mi.variant()),
        "gradsep.mitsuba_version": str(mi.__version__),
    }
    return meta


#: The OIDN setting a ``--seconds`` plan asks for (model.frame.OIDN_SETTING_KEY) where its budget makes the extra
#: denoising cheap: prefiltered features and OIDN's large model. On held-out frames with direct-layer gradients and
#: no light in view, served by ``oidn-l1``, it is 0.82x the RelMSE of the default ``raw-fast`` (geometric mean over
#: frames carrying their variance, worst frame 1.16x; benchmarks/bench_oidn_quality.py, docs/decisions.md "The
#: reconstruction's setting at farm budgets").
#: A plain frame keeps the default: on ``oidn`` alone it smears a light in view over its neighbours (up to 17x).
FARM_OIDN_SETTING = "prefiltered-high"
#: What FARM_OIDN_SETTING costs over ``raw-fast``, seconds per pixel per layer (the prefilter's two passes per
#: frame included, spread over two layers): 4.0 s more per 1280x720 two-layer frame (0.87 s against 4.88 s) on the
#: 2-core AMD EPYC development machine, `python benchmarks/bench_oidn.py --size 1280x720`.
FARM_OIDN_EXTRA_SECONDS = 2.2e-6
#: FARM_OIDN_SETTING is asked for when its extra time is at most this share of the budget (and the frame has no
#: light in view: has_light_in_view).
FARM_OIDN_SHARE = 0.1


#: The frame's own error estimate (renderer/check.py: two reconstructions at the frame's size) is made when its
#: predicted time is at most this share of a ``--seconds`` budget; elsewhere the header keeps the pilot's
#: prediction. At 192x192 it is ~3-5 % of a 20 s budget (OIDN prefiltered-high); a 1280x720 frame needs a minute
#: or more of budget for it.
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
    With one, FARM_OIDN_SETTING gained little on held-out frames (0.93x of ``raw-fast``'s RelMSE) and lost 1.46x
    on one studio: its large model smears the light."""
    from gradsep.model.outliers import light_in_view

    direct = frame.layers.get("direct")
    return direct is not None and light_in_view(direct)


def check_budget(rate: float, plan: Candidate, width: int, height: int, layers: Iterable[str],
                 seconds: float | None, farm_setting: bool = True, compare: bool = False,
                 before: float = 0.0) -> float | None:
    """Seconds the frame's own error estimate (renderer/check.py) needs after the last pass, given a
    reconstruction's ``rate`` (seconds per pixel), or None where it does not fit CHECK_SHARE of a ``seconds``
    budget (no budget: always made). With ``farm_setting`` the frame's reconstruction is the one a budget asks for
    (:func:`reconstruction_setting`; the rate is the default setting's); with ``compare`` the check also
    reconstructs the halves with the other of the default and FARM_OIDN_SETTING. ``before``: seconds it costs
    ahead of the passes (a fixed plan's rate measurement), counted against the share."""
    layers = list(layers)
    if seconds is None:
        return check_seconds(rate, width * height)
    farm = compare or (farm_setting and reconstruction_setting(width, height, layers, plan.gradients, seconds))
    extra = FARM_OIDN_EXTRA_SECONDS * len(layers) if farm else 0.0
    needed = check_seconds(rate, width * height, extra, 2 if compare else 1)
    return needed if needed + before <= CHECK_SHARE * seconds else None


def frame_check(planned: Planned, metadata: dict[str, str], compare: bool = False) -> str:
    """The frame's own error estimate (renderer/check.py) into ``metadata`` (the frame's, with its plan method
    and OIDN setting) as its predicted RelMSE, where the render made its halves; else the pilot's prediction
    stays. ``gradsep.predicted_from`` says which. With ``compare`` the halves are also reconstructed with the
    other of the default OIDN setting and FARM_OIDN_SETTING, and the frame asks for that one
    (OIDN_SETTING_KEY) where it is clearly better (renderer.check.check_frame). Returns the summary's clause."""
    from gradsep.model.frame import PLAN_METHOD_KEY
    from gradsep.model.oidn import METHOD_SETTING
    from gradsep.model.reconstruct import choose_method, reconstruct
    from gradsep.renderer.plan import EXPONENTS
    from gradsep.renderer.plancache import FRAME_ESTIMATE

    plan = planned.plan
    if not planned.halves:
        assert plan is not None
        # the pilot carried its estimate to the samples it predicted the budget buys; the frame has what it
        # actually got (a pilot slowed by a load spike predicts far fewer)
        assessed = plan.assessment()
        earlier = plan.trace.get(FRAME_ESTIMATE)
        if earlier and assessed is not None:
            # a plan from the plan cache: the estimate of the frame that judged it (its own halves), carried from
            # its samples to this frame's -- the same scene and budget, and far closer than the pilot's
            predicted = at_budget(earlier["relmse"], earlier["spp"], planned.spp, assessed.exponent)
            metadata[PREDICTED_RELMSE_KEY] = f"{predicted:.6g}"
            metadata[PREDICTED_FROM_KEY] = "plan-cache"
            return f"predicted RelMSE {predicted:.4g} (the judging frame's own, carried to this frame's samples)"
        predicted = (plan.predicted() if assessed is None or not assessed.budget_spp > 0 else
                     at_budget(assessed.predicted_relmse, assessed.budget_spp, planned.spp, assessed.exponent))
        metadata[PREDICTED_RELMSE_KEY] = f"{predicted:.6g}"
        metadata[PREDICTED_FROM_KEY] = "pilot"
        return f"predicted RelMSE {predicted:.4g} (the pilot's: no time for the frame's own check)"
    chosen = planned.candidate
    # the method that serves the frame (a fixed plan's frame names none yet: the default for it, as the service
    # would choose); the prediction holds for it only (model.frame.encode_answer)
    method = metadata.get(PLAN_METHOD_KEY) or choose_method(planned.frame)
    metadata[PLAN_METHOD_KEY] = method
    assessed = plan.assessment() if plan is not None else None
    exponent = assessed.exponent if assessed is not None else EXPONENTS.get(chosen.name, 0.5)

    def served(setting: str | None) -> Callable[[Frame], np.ndarray]:  # the half as the service would serve it
        def run(frame: Frame) -> np.ndarray:
            frame.metadata = {k: v for k, v in metadata.items() if k != OIDN_SETTING_KEY}
            if setting != METHOD_SETTING and setting is not None:
                frame.metadata[OIDN_SETTING_KEY] = setting
            return reconstruct(frame, method).image
        return run

    own = metadata.get(OIDN_SETTING_KEY) or METHOD_SETTING
    options = {own: served(own)}
    if compare:
        other = METHOD_SETTING if own == FARM_OIDN_SETTING else FARM_OIDN_SETTING
        options[other] = served(other)
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


def render_planned_frame(scene: LoadedScene, *, deadline: Deadline | None, spp: int | None, seed: int = 0,
                         layers: str | Iterable[str] = SEPARATED_LAYERS, shift: str | None = None,
                         gradients: str = "auto", offsets: str = "all",
                         progress: Callable[[int, int], None] | None = None,
                         plan_cache: CacheFolder | None = None) -> tuple[Frame, str]:
    """`gradsep render --seconds T` and/or ``--gradients auto`` (renderer/plan.py): the frame, rendered to the
    ``deadline`` (renderer.budget.Deadline) or to ``spp`` samples, with the given plan (``gradients`` and
    ``offsets`` as for :func:`render_frame`) or the plan a pilot chooses (``gradients`` ``auto``), and a one-line
    summary of the plan. The metadata is :func:`render_metadata`'s plus the plan's keys (renderer.plan).
    ``plan_cache`` (``auto`` only; renderer/plancache.py): the plan an earlier frame's checkpoint chose for this
    scene, frame and budget is rendered as a fixed plan, with no checkpoint; a checkpoint's choice is written
    there."""
    from gradsep.renderer.plan import (
        BUDGET_KEY,
        ELAPSED_KEY,
        PLAN_CACHE_KEY,
        PLAN_KEY,
        PLAN_LAYERS_KEY,
        Candidate,
        plan_layers_text,
        render_planned,
    )
    from gradsep.renderer.shift import make_shift  # imports Mitsuba

    if not 0 <= seed < 2**32:
        raise CommandError(f"--seed must be in [0, 2^32), got {seed}")
    if offsets not in OFFSET_CHOICES:
        raise CommandError(f"--offsets must be one of {', '.join(OFFSET_CHOICES)}, got {offsets!r}")
    wanted, notes = plan_layers(parse_layers(layers), scene.max_depth)
    fixed = None
    if gradients != "auto":
        mode = gradients_mode(gradients)
        if mode == "none" and offsets != "all":
            raise CommandError("--offsets has no effect without gradients (no offset paths are traced)")
        if mode == "direct" and "direct" not in wanted:
            raise CommandError(f"--gradients direct needs the separated direct layer; --layers {','.join(wanted)} "
                               "has none (use --gradients all or none)")
        name = "primal" if mode == "none" else mode if offsets == "all" else f"{mode}-{offsets}"
        fixed = Candidate(name, mode, offsets if mode != "none" else "all")
    try:
        shift_name = make_shift(shift).name
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    cached = None  # the plan cache's entry for this frame (renderer.plan.Plan), where it has a usable one
    entry = None
    if gradients == "auto" and plan_cache is not None:
        entry = plan_cache.entry(width=scene.width, height=scene.height, layers=wanted, max_depth=scene.max_depth,
                                 shift=shift_name, seconds=deadline.seconds if deadline is not None else None,
                                 spp=spp)
        cached, why = entry.load()
        notes += [why] if why else []
        fixed = cached.chosen if cached is not None else None
    # with a budget that affords FARM_OIDN_SETTING, the frame's check may also choose between it and the default
    # (unless the operator fixed the setting: $GRADSEP_OIDN_SETTING wins over the header anyway)
    can_compare = (deadline is not None
                   and farm_setting_affordable(scene.width, scene.height, wanted, deadline.seconds)
                   and not os.environ.get(SETTING_ENV, "").strip())
    compare = False  # whether the check that was last sized (the one the render holds time for) compares

    def check(rate: float, plan: Candidate, before: float) -> float | None:
        nonlocal compare
        budget = deadline.seconds if deadline is not None else None
        # plain frames only: on frames with the direct layer's gradients the rule's prefiltered-high was the better
        # setting on 22 of 29 held-out frames and the halves never switched from it (bench_planner.py predict)
        compare = can_compare and plan.gradients == "none"
        held = check_budget(rate, plan, scene.width, scene.height, wanted, budget, compare=compare, before=before)
        if held is None and compare:  # no time to compare: the estimate alone, where it fits
            compare = False
            held = check_budget(rate, plan, scene.width, scene.height, wanted, budget, before=before)
        return held

    start = time.perf_counter()
    planned = render_planned(scene, wanted, seed=seed, shift=shift, fixed=fixed, deadline=deadline, spp=spp,
                             progress=progress, check=check)
    seconds = time.perf_counter() - start
    chosen = planned.candidate
    metadata = render_metadata(scene, spp=planned.spp, seed=seed,
                               shift=shift_name if chosen.gradients != "none" else "none", layers=wanted,
                               seconds=seconds, passes=planned.passes, gradients=chosen.gradients)
    if chosen.gradients != "none" and chosen.offsets != "all":
        metadata["gradsep.offsets"] = chosen.offsets
    if 0 < planned.gradient_spp < planned.spp:
        metadata["gradsep.gradient_spp"] = str(planned.gradient_spp)
    metadata.update({PLAN_KEY: chosen.name, PLAN_LAYERS_KEY: plan_layers_text(chosen, wanted)})
    summary = f"plan {chosen.name}"
    if cached is not None:
        planned.plan = cached  # rendered as a fixed plan; the header carries the judgement it was chosen by
        metadata[PLAN_CACHE_KEY] = f"read {entry.path.name}"  # type: ignore[union-attr]
    if planned.plan is not None:
        metadata.update(planned.plan.metadata(wanted))
        summary = planned.plan.summary()
    if deadline is not None:
        metadata[BUDGET_KEY] = f"{deadline.seconds:g}"
        setting = reconstruction_setting(planned.frame.width, planned.frame.height, wanted, chosen.gradients,
                                         deadline.seconds)
        if setting and has_light_in_view(planned.frame):
            setting = None
            summary += "; a light in view: the default OIDN setting"
        if setting:
            metadata[OIDN_SETTING_KEY] = setting
            summary += f"; reconstruct with OIDN {setting}"
    if planned.halves is not None or (planned.plan is not None and planned.plan.assessments):
        summary += "; " + frame_check(planned, metadata, compare=compare and planned.halves is not None)
    if entry is not None and cached is None:  # a checkpoint's choice, and the frame's own estimate, to share
        if planned.plan is not None and planned.plan.assessments:
            own = None  # the frame's own estimate, where its halves made one
            if metadata.get(PREDICTED_FROM_KEY) == "frame":
                own = (float(metadata[PREDICTED_RELMSE_KEY]), planned.spp)
            failed = entry.store(planned.plan, seed, own)
            notes += [failed] if failed else []
            metadata[PLAN_CACHE_KEY] = "not written" if failed else f"wrote {entry.path.name}"
        else:
            metadata[PLAN_CACHE_KEY] = "nothing to share: no checkpoint judged"
        summary += f"; plan cache: {metadata[PLAN_CACHE_KEY]}"
    if deadline is not None:
        metadata[ELAPSED_KEY] = f"{deadline.elapsed():.3f}"
    frame = planned.frame
    frame.metadata = metadata
    frame.warnings = notes + frame.warnings
    return frame, summary
