"""The one reconstruction entry point that the CLI, the service and the evaluation all call.

A frame carries one or more illumination layers (``direct``/``indirect``, or ``color`` for a frame rendered
without separation). Each layer present is reconstructed on its own by the method's layer function and the final
image is their sum. Nothing runs for an absent layer. The methods, and what each needs of the frame and of the
loaded models, are the table in model/methods.py; this module checks a frame against a method's declaration,
shares the per-frame work between layers (OIDN's prefiltered auxiliary images, computed once) and schedules the
layers as the method declares.

What a frame does not carry costs nothing: no gradients means no Poisson or network work (only the methods that
need none apply), and a method sees only the feature groups it declares (``oidn`` with albedo and normal when the
frame has both, else the colour alone).

Output policy: every reconstructed layer is made finite (NaN/±Inf → 0, with a warning: a solver or network
that produced them has a bug, and a black pixel is easier to spot than a poisoned downstream average) and
clamped to [0, float32 max] (radiance is non-negative; the Poisson solutions ring slightly below 0 at sharp
edges). The image is the sum of these clamped layers, so ``image == Σ layers`` holds exactly for what is
written and the image is finite and ≥ 0 as well.
"""

from __future__ import annotations

import importlib.util
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from gradsep.model import methods as table
from gradsep.model import outliers
from gradsep.model.environment import env_int
from gradsep.model.errors import ChannelError
from gradsep.model.frame import FLOAT32_MAX, Features, Frame, Layer, feature_groups
from gradsep.model.methods import LoadedModels, Method
from gradsep.model.policy import DEFAULT_ALPHA, FEATURE_GROUPS, models_dir_from

__all__ = [
    "LayerContext",
    "LoadedModels",
    "NetworkLike",
    "Reconstruction",
    "available_methods",
    "choose_method",
    "load_fused",
    "load_network",
    "load_oidn",
    "models_dir_from",
    "reconstruct",
    "unavailable_reason",
]



class NetworkLike(Protocol):
    """What ``reconstruct`` needs of a network (``model.infer.NetworkReconstructor`` provides it)."""

    def reconstruct_layer(self, name: str, layer: Layer, features: Features) -> np.ndarray: ...


@dataclass
class Reconstruction:
    """The result of :func:`reconstruct`."""

    image: np.ndarray  # (H, W, 3) float32: the sum over layers; finite and >= 0
    layers: dict[str, np.ndarray]  # each reconstructed layer, (H, W, 3) float32, finite and >= 0
    timings: dict[str, float]  # seconds per layer name
    method: str
    warnings: list[str] = field(default_factory=list)  # non-finite values the output policy replaced
    oidn_setting: str | None = None  # the OIDN setting that ran (model.oidn.SETTINGS), None if no OIDN ran


def _sanitise(name: str, image: np.ndarray, shape: tuple[int, int, int], warnings: list[str]) -> np.ndarray:
    """Apply the output policy (finite, ≥ 0) to one reconstructed layer and check its shape."""
    out = np.asarray(image, dtype=np.float32)
    if out.shape != shape:
        raise RuntimeError(f"reconstruction of layer {name} has shape {out.shape}, expected {shape}")
    bad = int(np.count_nonzero(~np.isfinite(out)))
    if bad:
        warnings.append(f"reconstruction of {name} produced {bad} non-finite value(s), replaced with 0")
        out = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(out, 0.0, FLOAT32_MAX)


@dataclass
class LayerContext:
    """What one frame's reconstruction shares between its layers; a method's layer function reads it."""

    method: Method
    alpha: float
    models: LoadedModels
    features: Features | None  # the frame's feature groups that the method uses (None: none of them)
    aux: Any = None  # OIDN's auxiliary images (model.oidn.CleanAux), computed once per frame when the method runs OIDN
    denoiser: Any = None  # the model.oidn.Denoiser of a method that runs OIDN
    #: per layer, the pixels of a light in view the outlier detector kept out, and their rim (model/outliers.py): they
    #: come back as rendered, and the back-off (model/backoff.py) leaves them out of its windows
    pinned: dict[str, np.ndarray] = field(default_factory=dict)
    #: per layer, the lit level of the base the method sees where the detector already measured it
    #: (model.outliers.FrameSplit.lit_levels): OIDN's exposure for that layer, not measured again
    lit_levels: dict[str, float] = field(default_factory=dict)


#: A method's layer function (model/methods.py ``Method.function``): ``denoised`` is the layer's OIDN image when
#: the caller already computed it (a pipelined method), else None.
LayerFunction = Callable[[str, Layer, LayerContext, "np.ndarray | None"], np.ndarray]

#: ``$GRADSEP_LAYER_THREADS``: how many of a frame's layers are reconstructed, and searched for outliers
#: (model.outliers.split_frame), at once, and how many neighbours' rejection tests and layers' sums a temporal first
#: stage computes at once (model/temporal.py) (1: one after the other).
LAYER_THREADS_ENV = "GRADSEP_LAYER_THREADS"
#: The default: two layers at once, for the methods whose schedule is concurrent or pipelined (model/methods.py;
#: the schedules were measured with benchmarks/bench_layers.py).
DEFAULT_LAYER_THREADS = 2


def layer_threads() -> int:
    """The number of layers reconstructed concurrently: ``$GRADSEP_LAYER_THREADS`` (≥ 1) or the default."""
    return env_int(LAYER_THREADS_ENV, DEFAULT_LAYER_THREADS, 1, "1 runs the layers one after the other")


def _timed(fn: Callable[..., np.ndarray], *args: Any) -> tuple[np.ndarray, float]:
    start = time.perf_counter()
    image = fn(*args)
    return image, time.perf_counter() - start


def _in_worker(fn: Callable[..., np.ndarray], *args: Any) -> tuple[np.ndarray, float]:
    """:func:`_timed` in a layer thread: its DCTs on one thread (the other layer has the other core)."""
    from gradsep.model.poisson import fft_workers

    with fft_workers(1):
        return _timed(fn, *args)


def _run_layers(frame: Frame, ctx: LayerContext) -> dict[str, tuple[np.ndarray, float]]:
    """Every layer's (image, seconds), as the method's schedule says.

    Concurrent seconds are each layer's own wall time and overlap. A pipelined method's denoiser is one device
    behind a lock that already uses every core, so its layers are denoised one after the other in this thread, in
    the frame's order with the refined layers first, and the rest of each layer runs in a worker beside the next
    layer's denoise; OIDN's own order is therefore fixed. Output is bit-for-bit the same either way."""
    fn = table.layer_function(ctx.method)
    threads = min(layer_threads(), len(frame.layers))
    if threads <= 1 or ctx.method.schedule == "sequential":
        return {name: _timed(fn, name, layer, ctx, None) for name, layer in frame.layers.items()}
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="gradsep-layer") as pool:
        if ctx.method.schedule == "concurrent":
            futures = {name: pool.submit(_in_worker, fn, name, layer, ctx, None)
                       for name, layer in frame.layers.items()}
            return {name: future.result() for name, future in futures.items()}
        from gradsep.model.refine import REFINED_LAYERS

        order = sorted(frame.layers, key=lambda n: n not in REFINED_LAYERS)  # stable: the frame's order otherwise
        pending: dict[str, tuple[Future, float]] = {}
        for name in order:
            layer = frame.layers[name]
            denoised, seconds = _timed(ctx.denoiser.denoise, layer.base, ctx.aux)
            pending[name] = (pool.submit(_in_worker, fn, name, layer, ctx, denoised), seconds)
        out = {}
        for name, (future, denoise_seconds) in pending.items():
            image, seconds = future.result()
            out[name] = (image, denoise_seconds + seconds)
        return out


# ------------------------------------------------------------------------------------------------ what serves what


def _as_models(models: LoadedModels | None) -> LoadedModels:
    return LoadedModels() if models is None else models


def missing_gradient_channels(frame: Frame, method: str) -> list[str]:
    """The gradient channels ``method`` needs and this frame lacks (empty: it has what the method needs).

    ``gradients = "direct"`` (``oidn-l1``): a frame with gradients needs them on the layers the method refines
    (model.refine.REFINED_LAYERS) that it has; a plain frame lacks every layer's, as the contract names them."""
    from gradsep.model.frame import layer_channels

    spec = table.get(method)
    if spec.gradients == "none":
        return []
    needed = list(frame.layers)
    if spec.gradients == "direct" and frame.gradient_layers:
        from gradsep.model.refine import REFINED_LAYERS

        needed = [name for name in frame.layers if name in REFINED_LAYERS]
    return [c for name in needed if name not in frame.gradient_layers for c in layer_channels(name)[3:]]


def _gradients_met(frame: Frame) -> list[str]:
    """The methods whose gradient needs this frame meets, in declaration order (for error messages)."""
    return [name for name in table.names() if not missing_gradient_channels(frame, name)]


def missing_feature_groups(frame: Frame, method: str) -> list[str]:
    """The feature groups ``method`` requires and this frame lacks."""
    have = feature_groups(frame.features)
    return [g for g in table.get(method).requires if g not in have]


def _unserved_layers(method: Method, models: LoadedModels, frame: Frame) -> list[str]:
    """Layers of the frame that the method's own loaded models have no model for (model sets with ``layers``)."""
    for name in method.model_sets:
        served = getattr(models.get(name), "layers", None)
        if served is not None:
            return [layer for layer in frame.layers if layer not in set(served)]
    return []


def _serves(method: Method, frame: Frame, models: LoadedModels) -> bool:
    return (not models.missing(method) and not missing_gradient_channels(frame, method.name)
            and not missing_feature_groups(frame, method.name) and not _unserved_layers(method, models, frame))


def available_methods(frame: Frame, models: LoadedModels | None = None) -> list[str]:
    """The methods that can serve this frame with these models, best first (model.methods.preference_order)."""
    models = _as_models(models)
    return [name for name in table.preference_order() if _serves(table.get(name), frame, models)]


def choose_method(frame: Frame, models: LoadedModels | None = None) -> str:
    """The default method for this frame: the first of model.methods.default_preference that can serve it.

    Raises ChannelError naming what is missing when nothing can (e.g. a gradient-free frame on a host without
    OIDN)."""
    models = _as_models(models)
    chosen = table.default_method(available_methods(frame, models), gradients=bool(frame.gradient_layers))
    if chosen is not None:
        return chosen
    candidates = [table.get(n) for n in table.default_preference()]
    if not frame.gradient_layers:
        candidates = [m for m in candidates if m.gradients == "none"]
    reasons = [f"{m.name} ({unavailable_reason(m.name, frame, models)})" for m in candidates]
    raise ChannelError("no reconstruction method can serve this frame here: " + "; ".join(reasons),
                       {"available_methods": [],
                        "missing": missing_gradient_channels(frame, "l1") if frame.gradient_layers else []})


def unavailable_reason(name: str, frame: Frame, models: LoadedModels | None = None) -> str:
    """Why method ``name`` cannot serve ``frame`` with these models, in a few words ("" when it can)."""
    method, models = table.get(name), _as_models(models)
    missing = models.missing(method)
    if missing:
        return "needs " + ", ".join(table.MODEL_SETS[n].description for n in missing)
    channels = missing_gradient_channels(frame, method.name)
    if channels:
        return "needs the gradient channels " + ", ".join(channels)
    groups = missing_feature_groups(frame, method.name)
    if groups:
        return "needs the feature group(s) " + ", ".join(groups)
    unserved = _unserved_layers(method, models, frame)
    return "its models do not cover layer(s) " + ", ".join(unserved) if unserved else ""


def _check_method(frame: Frame, method: Method, alpha: float, models: LoadedModels) -> None:
    """Raise a clear error when ``method`` cannot serve ``frame`` (ChannelError names the channels or groups)."""
    name = method.name
    if method.alpha and not (math.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha must be a finite number > 0, got {alpha}")
    missing = missing_gradient_channels(frame, name)
    groups = missing_feature_groups(frame, name)
    features = [c for g in groups for c in FEATURE_GROUPS[g]]
    # everything the frame lacks is named at once, so a producer fixes it in one go
    also = (f"; it also needs the feature group(s) {', '.join(groups)} ({', '.join(features)})" if groups else "")
    details = {"missing": [*missing, *features], **({"missing_feature_groups": groups} if groups else {})}
    alternatives = " or ".join(_gradients_met(frame)) or "another method"
    if missing and not frame.gradient_layers:
        raise ChannelError(f"method {name!r} integrates gradients, which this frame lacks (a plain path-traced "
                           f"frame){also}; use method {alternatives}, or send the L.dx.* / L.dy.* channels", details)
    if missing:
        raise ChannelError(f"method {name!r} integrates the gradients of every layer; this frame carries them only "
                           f"for {', '.join(frame.gradient_layers)} (missing {', '.join(missing)}){also}; use "
                           f"method {alternatives}, or send the missing channels", details)
    absent = models.missing(method)
    if absent:
        raise ValueError(f"method {name!r} needs " + ", ".join(table.MODEL_SETS[n].description for n in absent)
                         + ", which " + ("is" if len(absent) == 1 else "are") + " not available here; use "
                         + (", ".join(n for n in available_methods(frame, models)) or "another method"))
    if groups:
        raise ChannelError(f"method {name!r} needs the feature group(s) {', '.join(groups)} (channels "
                           f"{', '.join(features)}), which this frame lacks; send them, or use a method that "
                           "does without: " + (", ".join(available_methods(frame, models)) or "none here"), details)
    unserved = _unserved_layers(method, models, frame)
    if unserved:
        served = sorted(set(frame.layers) - set(unserved))
        raise ChannelError(f"no {name} model for layer(s) {', '.join(unserved)} (models loaded for the others: "
                           f"{', '.join(served) or 'none'}); use method oidn, l1 or l2",
                           {"unserved_layers": unserved})


def _denoiser(method: Method, models: LoadedModels, frame: Frame, warnings: list[str]) -> Any:
    """The OIDN denoiser of a method that runs OIDN: at the one its loaded model was trained with (its
    ``oidn_setting``), else at the frame's (model.oidn.frame_setting: ``$GRADSEP_OIDN_SETTING``, the setting the
    frame's render plan asked for, or the ``oidn`` method's)."""
    from gradsep.model.oidn import frame_setting, shared_denoiser

    own = next((models.get(n) for n in method.model_sets), None) if method.denoiser == "model" else None
    pinned = getattr(own, "oidn_setting", None)
    if pinned:
        return shared_denoiser(pinned)
    setting, warning = frame_setting(frame.metadata)
    if warning:
        warnings.append(warning)
    return shared_denoiser(setting)


def reconstruct(frame: Frame, method: str | None = None, alpha: float = DEFAULT_ALPHA,
                models: LoadedModels | None = None) -> Reconstruction:
    """Reconstruct every illumination layer of ``frame`` with ``method`` and sum them.

    ``method`` None picks :func:`choose_method`. ``alpha`` is the screened Poisson data weight (methods that take
    it). ``models`` holds the loaded model sets (model.methods.LoadedModels); None has only the runtimes detected
    here (OIDN when pyoidn is installed). Raises ValueError for an unknown method, a bad alpha or a missing model
    set, and :class:`model.errors.ChannelError` for a frame that lacks what the method needs.
    """
    models = _as_models(models)
    spec = table.get(method or choose_method(frame, models))
    _check_method(frame, spec, alpha, models)
    # a denoising method never sees a layer's outliers (nor, for some, a light in view): their energy goes back
    # around where it landed below (model/outliers.py)
    frame, split = (outliers.split_frame(frame, spec.split_sources, layer_threads()) if spec.split_outliers
                    else (frame, outliers.FrameSplit()))
    features = frame.features.only(spec.uses) if frame.features is not None else None
    warnings: list[str] = []
    ctx = LayerContext(spec, alpha, models, features, pinned=split.pinned(), lit_levels=split.lit_levels)
    shape = (frame.height, frame.width, 3)
    layers: dict[str, np.ndarray] = {}
    timings: dict[str, float] = {}
    total = np.zeros(shape, dtype=np.float64)
    if spec.denoiser is not None:
        ctx.denoiser = _denoiser(spec, models, frame, warnings)
        pair = features is not None and features.albedo is not None and features.normal is not None
        if features is not None and not pair:
            # OIDN takes a normal only with an albedo, and model.oidn's auxiliary images are the pair
            warnings.append(f"method {spec.name} uses albedo and normal together; this frame has only "
                            f"{', '.join(g for g in features.groups if g in ('albedo', 'normal'))}, so OIDN runs "
                            "on the colour alone")
        if pair:
            start = time.perf_counter()
            ctx.aux = ctx.denoiser.prefilter(features)  # once per frame, shared by every layer
            timings["features"] = time.perf_counter() - start
    for name, (image, seconds) in _run_layers(frame, ctx).items():
        timings[name] = seconds
        image = split.restore(name, image)
        warnings.extend(split.warnings(name, spec.name))
        layers[name] = _sanitise(name, image, shape, warnings)
    for name in frame.layers:  # summed in the frame's order whatever order the layers finished in
        total += layers[name]
    image = np.clip(total, 0.0, FLOAT32_MAX).astype(np.float32)
    setting = ctx.denoiser.setting.name if ctx.denoiser is not None else None
    return Reconstruction(image, layers, timings, spec.name, warnings, setting)


# ------------------------------------------------------------------------------------------------ models


#: The ``fused`` models live in this subfolder of the models folder (``models/fused/direct.onnx``, ...).
FUSED_SUBDIR = "fused"


def load_oidn(models_dir: str | os.PathLike[str] | None = None) -> bool:
    """The ``oidn`` model set: whether Intel Open Image Denoise (pyoidn) is installed here (no folder)."""
    from gradsep.model.oidn import available

    return bool(available())


def load_network(models_dir: str | os.PathLike[str] | None) -> Any:
    """The ``network`` method's reconstructor (models/*.onnx), or None when there are no models or no inference
    module. Same contract as the service's loader: None for a folder without models, an exception for models
    that fail to load (model.infer refuses a model of any prior but ``l1``, and a fused blend model)."""
    folder = models_dir_from(models_dir)
    if not folder.is_dir() or importlib.util.find_spec("gradsep.model.infer") is None:
        return None
    from gradsep.model.infer import NetworkReconstructor  # type: ignore[import-not-found]

    return NetworkReconstructor.load(folder)


def load_fused(models_dir: str | os.PathLike[str] | None) -> Any:
    """The ``fused`` method's reconstructor (models/fused/*.onnx: per-pixel blend models, model/fused.py), or None
    when the folder has no model or pyoidn is missing. A model of another prior kind there (an ``l1`` network
    model) is refused with ModelError."""
    from gradsep.model.oidn import available

    folder = models_dir_from(models_dir) / FUSED_SUBDIR
    if not available() or not folder.is_dir():
        return None
    from gradsep.model.fused import BlendModelError, FusedReconstructor
    from gradsep.model.infer import ModelError  # type: ignore[import-not-found]

    try:
        return FusedReconstructor.load(folder)
    except BlendModelError as exc:
        raise ModelError(str(exc)) from exc
