"""Frame rendering front end: scene + settings -> a :class:`model.frame.Frame` (and `gradsep render`).

Decides which illumination layers a render needs (a max depth of 2 or less leaves no indirect light, so that
layer is neither traced nor written; ``--layers direct`` stops every path after its first vertex), runs the G-PT
integrator (renderer/gpt.py) with the chosen shift (renderer/shift.py), and packs the result with the frame
contract's metadata keys (``gradsep.*``). A frame rendered to a budget, or with the plan chosen on the frame
itself: renderer/planned_frame.py.
"""

from __future__ import annotations

import numbers
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from gradsep.model import __version__
from gradsep.model.errors import CommandError
from gradsep.model.frame import ILLUMINATION_LAYERS, Frame
from gradsep.model.policy import SEPARATED_LAYERS
from gradsep.renderer.scene import LoadedScene, load_scene


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


def check_offsets(offsets: str, mode: str) -> None:
    """``--offsets`` checked against OFFSET_CHOICES and the gradients mode."""
    if offsets not in OFFSET_CHOICES:
        raise CommandError(f"--offsets must be one of {', '.join(OFFSET_CHOICES)}, got {offsets!r}")
    if mode == "none" and offsets != "all":
        raise CommandError("--offsets has no effect without gradients (no offset paths are traced)")


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


@dataclass(frozen=True)
class FrameOptions:
    """The rest of :func:`render_frame`'s settings.

    ``offsets`` (``--offsets``): which offsets a sample traces, ``GptSettings.offsets`` (``all``, or fewer:
    ``alternate``, ``pair``, ``single``; the same channels, gradients counted with their inverse probability;
    recorded as ``gradsep.offsets`` unless ``all``). ``gradient_spp`` K (``--gradient-spp``; default ``spp``): only K
    of the ``spp`` samples trace offsets, the other ``spp - K`` are primal-only samples; the bases and features are
    the mean over all ``spp`` samples, the gradients the K G-PT samples' (``render_gpt``). K == ``spp`` is the plain
    render; a K below ``spp`` is recorded as ``gradsep.gradient_spp`` (``gradsep.spp`` stays the bases' sample
    count). ``progress(done, spp)`` after each pass. A scene given as a spec is loaded with ``width``, ``height``,
    ``max_depth`` and ``defines``; ``max_depth`` also overrides a loaded scene's."""

    offsets: str = "all"
    gradient_spp: int | None = None
    progress: Callable[[int, int], None] | None = None
    width: int | None = None
    height: int | None = None
    max_depth: int | None = None
    defines: Mapping[str, str] | None = None


def render_frame(scene: LoadedScene | str, *, spp: int, seed: int = 0,
                 layers: str | Iterable[str] = SEPARATED_LAYERS, shift: str | None = None,
                 gradients: bool | str = True, options: FrameOptions | None = None) -> Frame:
    """Render one G-PT frame: per requested layer base + dx + dy, features at the first non-specular vertex.

    ``scene`` is a loaded scene or a spec (XML path / ``procedural:SEED``, loaded with ``options``). ``layers``
    ``color`` renders the unseparated image. ``gradients`` (GRADIENT_CHOICES, or True = ``all`` / False =
    ``none``): ``none`` is the primal-only mode: the same base paths, layers and features, no offset paths; the
    frame's layers carry no gradients (``dx``/``dy`` None) and ``shift`` is ignored. ``direct`` gives the direct
    layer its gradients -- the same as an ``all`` render with this seed -- and the indirect layer none (its base is
    the primal-only render's): the offsets stop after the direct layer's vertices. The offsets, split samples and
    progress: :class:`FrameOptions`.
    """
    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.gpt_settings import Film
    from gradsep.renderer.passes import as_frame

    options = options or FrameOptions()
    if spp < 1:
        raise CommandError(f"--spp must be >= 1, got {spp}")
    if not 0 <= seed < 2**32:
        raise CommandError(f"--seed must be in [0, 2^32), got {seed}")
    scene = _loaded(scene, options)
    mode = gradients_mode(gradients)
    check_offsets(options.offsets, mode)
    gradient_spp = check_gradient_spp(options.gradient_spp, spp, mode)
    wanted, notes, shift_impl, settings = _frame_settings(scene, layers, shift, mode, options.offsets)
    start = time.perf_counter()
    film = Film(scene.width, scene.height, spp, seed, gradient_spp=gradient_spp)
    result = render_gpt(scene.scene, shift_impl, settings, film, options.progress)
    seconds = time.perf_counter() - start

    metadata = render_metadata(scene, RenderRecord(spp, seed, shift_impl.name if shift_impl else "none", wanted,
                                                   seconds, result.passes, mode))
    if options.offsets != "all":
        metadata["gradsep.offsets"] = options.offsets
    if gradient_spp < spp:
        metadata["gradsep.gradient_spp"] = str(gradient_spp)
    frame = as_frame(result)
    frame.metadata, frame.warnings = metadata, notes + frame.warnings
    return frame


def _loaded(scene: LoadedScene | str, options: FrameOptions) -> LoadedScene:
    """``scene`` loaded (a spec) or with ``options.max_depth`` as its depth limit."""
    if isinstance(scene, str):
        return load_scene(scene, width=options.width, height=options.height, max_depth=options.max_depth,
                          defines=options.defines)
    max_depth = options.max_depth
    if max_depth is None:
        return scene
    if max_depth == 0 or max_depth < -1:
        raise CommandError(f"--max-depth must be -1 (unbounded) or >= 1, got {max_depth}")
    return LoadedScene(scene.scene, scene.spec, scene.width, scene.height, max_depth, scene.rr_depth, scene.defines)


def _frame_settings(scene: LoadedScene, layers: str | Iterable[str], shift: str | None, mode: str,
                    offsets: str) -> tuple[tuple[str, ...], list[str], Any, Any]:
    """The layers to trace (with notes on those dropped), the shift and the integrator's settings of a frame, or
    a user error for a combination that cannot be rendered."""
    from gradsep.renderer.gpt_settings import GptSettings
    from gradsep.renderer.shift import make_shift  # imports Mitsuba

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
    return wanted, notes, shift_impl, settings


@dataclass(frozen=True)
class RenderRecord:
    """What a render did, for its header: its samples, seed, shift (``none`` without gradients), layers, wall
    seconds, passes and which layers carry gradients."""

    spp: int
    seed: int
    shift: str
    layers: tuple[str, ...]
    seconds: float
    passes: int
    gradients: bool | str = True


def render_metadata(scene: LoadedScene, record: RenderRecord) -> dict[str, str]:
    """The ``gradsep.*`` EXR header attributes of a rendered frame (all strings); the integrator is ``gpt``, or
    ``primal`` for the primal-only mode (shift ``none``); ``gradsep.gradients`` says which layers carry
    gradients (``all``, ``direct`` or ``none``)."""
    import mitsuba as mi

    mode = gradients_mode(record.gradients)
    return {
        "gradsep.version": __version__,
        "gradsep.integrator": "gpt" if mode != "none" else "primal",
        "gradsep.gradients": mode,
        **scene.scene_metadata(),
        "gradsep.spp": str(record.spp),
        "gradsep.seed": str(record.seed),
        "gradsep.max_depth": str(scene.max_depth),
        "gradsep.rr_depth": str(scene.rr_depth),
        "gradsep.shift": record.shift,
        "gradsep.layers": ",".join(record.layers),
        "gradsep.render_seconds": f"{record.seconds:.3f}",
        "gradsep.passes": str(record.passes),
        "gradsep.mitsuba_variant": str(mi.variant()),
        "gradsep.mitsuba_version": str(mi.__version__),
    }
