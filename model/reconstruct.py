"""The one reconstruction entry point that the CLI, the service and the evaluation all call.

A frame carries one or more illumination layers (``direct``/``indirect``, or ``color`` for a frame rendered
without separation). Each layer present is reconstructed on its own and the final image is their sum. Nothing
runs for an absent layer. The methods:

* ``l1``, ``l2`` -- screened Poisson solvers of the base and the gradients (model/poisson.py);
* ``network`` -- the paper's GradNet-style network with CBAM, refining a truncated L1 solve (models/*.onnx);
* ``oidn`` -- Intel Open Image Denoise on each layer's base with the frame's albedo/normal (model.oidn's method
  setting, docs/oidn.md); the one method for a plain path-traced frame (no gradients), and it needs no features;
* ``oidn-l1`` -- ``oidn``, then the direct layer refined by its gradients: an L1 screened Poisson solve with
  OIDN's image as the data term (model/refine.py); the indirect layer keeps OIDN's image;
* ``fused`` -- the paper's network architecture predicting per-pixel convex weights over candidate reconstructions
  (OIDN's image, its gradient-domain refinement, ...), trained unsupervised (model/fused.py, models/fused/*.onnx).

What a frame does not carry costs nothing: no gradients means no Poisson or network work (only ``oidn``
applies), no features means OIDN without auxiliary images, and the OIDN prefilter of albedo/normal runs once per
frame, shared by its layers (where the setting prefilters).

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
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from gradsep.model import policy
from gradsep.model.environment import env_int
from gradsep.model.frame import Features, Frame, Layer
from gradsep.model.poisson import solve_l1, solve_l2
from gradsep.model.policy import (
    DEFAULT_ALPHA,
    GRADIENT_METHODS,
    METHODS,
    MODEL_METHODS,
    OIDN_METHODS,
    POISSON_METHODS,
    models_dir_from,
)
from gradsep.model.robust import add_excess, outlier_count, split_frame

__all__ = [
    "METHODS",
    "NetworkLike",
    "Reconstruction",
    "choose_method",
    "load_fused",
    "load_network",
    "models_dir_from",
    "reconstruct",
]

_F32_MAX = float(np.finfo(np.float32).max)


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


def _sanitise(name: str, image: np.ndarray, shape: tuple[int, int, int], warnings: list[str]) -> np.ndarray:
    """Apply the output policy (finite, ≥ 0) to one reconstructed layer and check its shape."""
    out = np.asarray(image, dtype=np.float32)
    if out.shape != shape:
        raise RuntimeError(f"reconstruction of layer {name} has shape {out.shape}, expected {shape}")
    bad = int(np.count_nonzero(~np.isfinite(out)))
    if bad:
        warnings.append(f"reconstruction of {name} produced {bad} non-finite value(s), replaced with 0")
        out = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(out, 0.0, _F32_MAX)


@dataclass
class _Context:
    """What one frame's reconstruction shares between its layers."""

    method: str
    alpha: float
    models: Any  # the NetworkReconstructor of the method (network or fused), or None
    features: Features | None
    aux: Any = None  # the OIDN auxiliary features (model.oidn.CleanAux), computed once per frame when needed
    denoiser: Any = None  # the model.oidn.Denoiser of the method (oidn: its setting; fused: the prior's)


def _reconstruct_layer(name: str, layer: Layer, ctx: _Context, denoised: np.ndarray | None = None) -> np.ndarray:
    """One layer by ``ctx.method``; ``denoised``: the layer's OIDN image when already computed (OIDN methods)."""
    if ctx.method == "l1":
        return solve_l1(layer.base, layer.dx, layer.dy, ctx.alpha)[0]
    if ctx.method == "l2":
        return solve_l2(layer.base, layer.dx, layer.dy, ctx.alpha)
    if ctx.method in OIDN_METHODS:
        if denoised is None:
            denoised = ctx.denoiser.denoise(layer.base, ctx.aux)
        return _finish_oidn_layer(name, denoised, layer, ctx)
    if ctx.method == "fused":  # its candidates start from the layer's OIDN image, denoised here or by the caller
        return ctx.models.reconstruct_layer(name, layer, ctx.features, ctx.aux, denoised=denoised)
    if ctx.aux is not None:  # models refining an OIDN prior share the frame's prefiltered features
        return ctx.models.reconstruct_layer(name, layer, ctx.features, ctx.aux)
    return ctx.models.reconstruct_layer(name, layer, ctx.features)


#: ``$GRADSEP_LAYER_THREADS``: how many of a frame's layers are reconstructed at once (1: one after the other).
LAYER_THREADS_ENV = "GRADSEP_LAYER_THREADS"
#: The default: two layers at once, for the methods where that was measured to pay (CONCURRENT_METHODS).
DEFAULT_LAYER_THREADS = 2
#: Methods whose layers run concurrently. Their solves are independent and most of each runs single-threaded
#: (the compiled IRLS/multigrid kernels) or releases the GIL (DCTs, OIDN), but the 2 cores are shared, so it only
#: pays where one layer leaves a core idle. Measured in-process (benchmarks/bench_layers.py, 1280x720, 2 cores,
#: same-run medians, concurrent / sequential): l1 0.75-0.85 (four runs), oidn-l1 0.95-0.97 (its direct layer's
#: refinement beside the indirect layer's denoise), l2 1.7-2.3 (two DCTs per layer: thread start-up and contention
#: outweigh them). network: its prior solve (~0.5 s of a 720p layer) runs on one core, so the other layer's prior
#: fills the idle one; its ONNX graphs are serialised by NetworkReconstructor's graph lock (one graph already uses
#: both cores, two at once only contend). Issue 15 (netspeed helper, 2026-12-02, load
#: ~4, docs/network.md "Serving latency"): through the service, alternating, network p50 2.20/1.95 s sequential
#: against 2.15/1.74 s concurrent with the lock, and 2.16/1.72 against 1.84/1.87 s in a second hold (medians 2.06
#: against 1.85 s; before the lock 3.08/2.31 against 1.98/2.08 s; an earlier run without it had seen the opposite,
#: 1.86/1.69 against 1.93/2.01 s); in-process 0.92, 0.93. Cost: peak RSS 2.0 -> 3.5 GB with two
#: clients (four prior solves in flight); GRADSEP_LAYER_THREADS=1 gives it back.
#: fused is pipelined like oidn-l1 (each layer's OIDN image in this thread, the rest of the layer in a worker beside
#: the next denoise): a probe took a 720p frame from 4.16 to
#: 2.71 s, same output (fused3 helper, 2026-12-02, load ~4). Every other method runs its layers one after the
#: other. Output is bit-for-bit the same either way.
CONCURRENT_METHODS: frozenset[str] = frozenset({"l1", "oidn-l1", "fused", "network"})
#: Concurrent methods whose layers start from an OIDN image: denoised one after the other, then finished in workers.
_PIPELINED_METHODS: frozenset[str] = frozenset({*OIDN_METHODS, "fused"})


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


def _run_layers(frame: Frame, ctx: _Context) -> dict[str, tuple[np.ndarray, float]]:
    """Every layer's (image, seconds), one after the other or (CONCURRENT_METHODS) :func:`layer_threads` at once.

    Concurrent seconds are each layer's own wall time and overlap. For the OIDN methods and fused the denoiser is one
    device behind a lock that already uses every core, so the layers are denoised one after the other in this
    thread, in the frame's order with the refined layers first, and each refinement (the L1 solve of oidn-l1)
    (or fused's candidates and blend) runs in a worker beside the next layer's denoise; OIDN's own order is
    therefore fixed."""
    threads = min(layer_threads(), len(frame.layers))
    if threads <= 1 or ctx.method not in CONCURRENT_METHODS:
        return {name: _timed(_reconstruct_layer, name, layer, ctx) for name, layer in frame.layers.items()}
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="gradsep-layer") as pool:
        if ctx.method not in _PIPELINED_METHODS:
            futures = {name: pool.submit(_in_worker, _reconstruct_layer, name, layer, ctx)
                       for name, layer in frame.layers.items()}
            return {name: future.result() for name, future in futures.items()}
        from gradsep.model.refine import REFINED_LAYERS

        order = sorted(frame.layers, key=lambda n: n not in REFINED_LAYERS)  # stable: the frame's order otherwise
        pending: dict[str, tuple[Future, float]] = {}
        for name in order:
            layer = frame.layers[name]
            denoised, seconds = _timed(ctx.denoiser.denoise, layer.base, ctx.aux)
            pending[name] = (pool.submit(_in_worker, _reconstruct_layer, name, layer, ctx, denoised), seconds)
        out = {}
        for name, (future, denoise_seconds) in pending.items():
            image, seconds = future.result()
            out[name] = (image, denoise_seconds + seconds)
        return out


def _finish_oidn_layer(name: str, denoised: np.ndarray, layer: Layer, ctx: _Context) -> np.ndarray:
    """The second stage of an OIDN method for one layer: nothing for oidn, the gradient refinement for oidn-l1."""
    if ctx.method == "oidn":
        return denoised
    from gradsep.model.refine import refine_layer

    return refine_layer(name, denoised, layer)


def _serves(models: NetworkLike | None, frame: Frame) -> bool:
    return (models is not None and frame.features is not None
            and set(frame.layers) <= set(getattr(models, "layers", frame.layers)))


def available_methods(frame: Frame, network: NetworkLike | None = None, fused: NetworkLike | None = None,
                      oidn: bool | None = None) -> list[str]:
    """The methods that can serve this frame: model.policy.DEFAULT_PREFERENCE order, then the rest of METHODS."""
    if oidn is None:
        from gradsep.model.oidn import available

        oidn = available()
    usable = {"oidn"} if oidn else set()
    if oidn and refinable(frame):
        usable.add("oidn-l1")
    if frame.has_gradients:
        usable |= {"l1", "l2"}
        usable |= {"network"} if _serves(network, frame) else set()
        usable |= {"fused"} if _serves(fused, frame) else set()
    return [m for m in policy.preference_order() if m in usable]


def refinable(frame: Frame) -> bool:
    """Whether ``oidn-l1`` serves this frame: it carries gradients, and every layer it refines
    (model.refine.REFINED_LAYERS: the direct layer) that is present has them. So a frame with the direct layer's
    gradients and a plain indirect layer (``gradsep render --gradients direct``) is served, as is every frame with
    gradients on all layers; the other gradient methods need every layer's gradients."""
    from gradsep.model.refine import REFINED_LAYERS

    with_gradients = frame.gradient_layers
    return bool(with_gradients) and all(name in with_gradients for name in frame.layers if name in REFINED_LAYERS)


def missing_gradient_channels(frame: Frame, method: str) -> list[str]:
    """The gradient channels ``method`` needs and this frame lacks (empty: it has what the method needs)."""
    from gradsep.model.frame import layer_channels

    if method not in GRADIENT_METHODS or (method == "oidn-l1" and refinable(frame)):
        return []
    needed = list(frame.layers)  # a plain frame: every layer's (as the contract always named them)
    if method == "oidn-l1" and frame.gradient_layers:  # gradients on some layers, but not on the direct layer
        from gradsep.model.refine import REFINED_LAYERS

        needed = [name for name in frame.layers if name in REFINED_LAYERS]
    return [c for name in needed if name not in frame.gradient_layers for c in layer_channels(name)[3:]]


def choose_method(frame: Frame, network: NetworkLike | None = None, fused: NetworkLike | None = None) -> str:
    """The default method for this frame: the first of model.policy.DEFAULT_PREFERENCE that can serve it.

    As shipped: ``oidn`` whenever pyoidn is installed (for a plain frame and a G-PT frame alike), else
    ``network`` when its models cover the frame's layers and it has features, else ``l1``. Raises ChannelError
    for a gradient-free frame on a host without OIDN (nothing can serve it).
    """
    chosen = policy.default_method(available_methods(frame, network, fused), gradients=bool(frame.gradient_layers))
    if chosen is None:
        from gradsep.model.frame import ChannelError

        if frame.gradient_layers:  # gradients on some layers only: oidn and oidn-l1 serve it, both need pyoidn
            raise ChannelError(f"this frame carries gradients only for layer(s) {', '.join(frame.gradient_layers)}; "
                               "the methods that serve it (oidn, oidn-l1) need pyoidn, which is not installed here "
                               "(pip install pyoidn), and the others need every layer's gradients",
                               {"available_methods": [], "missing": missing_gradient_channels(frame, "l1")})
        raise ChannelError("this frame has no gradient channels, and the one method for a plain frame (oidn) "
                           "is not installed here (pip install pyoidn)", {"available_methods": []})
    return chosen


def _check_method(frame: Frame, method: str, alpha: float, models: NetworkLike | None) -> None:
    """Raise a clear error when ``method`` cannot serve ``frame`` (ChannelError names the channels)."""
    from gradsep.model.frame import FEATURE_CHANNELS, ChannelError

    if method not in METHODS:
        raise ValueError(f"unknown reconstruction method {method!r}; expected one of {', '.join(METHODS)}")
    if method in POISSON_METHODS and not (math.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha must be a finite number > 0, got {alpha}")
    missing = missing_gradient_channels(frame, method)
    if missing and not frame.gradient_layers:
        raise ChannelError(f"method {method!r} integrates gradients, which this frame lacks (a plain path-traced "
                           "frame); use method oidn, or send the L.dx.* / L.dy.* channels", {"missing": missing})
    if missing:
        alternatives = "oidn or oidn-l1" if refinable(frame) else "oidn"
        raise ChannelError(f"method {method!r} integrates the gradients of every layer; this frame carries them only "
                           f"for {', '.join(frame.gradient_layers)} (missing {', '.join(missing)}); use method "
                           f"{alternatives}, or send the missing channels", {"missing": missing})
    if method in OIDN_METHODS:
        from gradsep.model.oidn import available

        if not available():
            raise ValueError(f"method {method!r} needs pyoidn, which is not installed here (pip install pyoidn)")
    if method not in MODEL_METHODS:
        return
    if models is None:
        where = "models/fused" if method == "fused" else "models"
        raise ValueError(f"method {method!r} needs a loaded model set ({where}: none available); use oidn, l1 or l2")
    if frame.features is None:
        raise ChannelError(f"the {method} method needs the feature channels, which this frame lacks: "
                           + ", ".join(FEATURE_CHANNELS), list(FEATURE_CHANNELS))
    served = set(getattr(models, "layers", frame.layers))
    unserved = [name for name in frame.layers if name not in served]
    if unserved:
        raise ChannelError(f"no {method} model for layer(s) {', '.join(unserved)} (models loaded for: "
                           f"{', '.join(sorted(served)) or 'none'}); use method oidn, l1 or l2",
                           {"unserved_layers": unserved, "model_layers": sorted(served)})


def reconstruct(frame: Frame, method: str | None = None, alpha: float = DEFAULT_ALPHA,
                network: NetworkLike | None = None, fused: NetworkLike | None = None) -> Reconstruction:
    """Reconstruct every illumination layer of ``frame`` with ``method`` and sum them.

    ``method`` None picks :func:`choose_method`. ``alpha`` is the screened Poisson data weight (l1/l2 only).
    ``network`` (models/*.onnx) is required for ``"network"``, ``fused`` (models/fused/*.onnx) for ``"fused"``;
    both need the frame's feature channels, and every method but ``oidn`` needs its gradients. Raises ValueError
    for an unknown method, a bad alpha or a missing model set, and :class:`model.frame.ChannelError` for a frame
    that lacks what the method needs.
    """
    method = method or choose_method(frame, network, fused)
    models = fused if method == "fused" else network if method == "network" else None
    _check_method(frame, method, alpha, models)
    # the denoising methods never see a layer's extreme outliers: their excess is spread back near them below
    frame, excess = (frame, {}) if method in POISSON_METHODS else split_frame(frame)
    ctx = _Context(method, alpha, models, frame.features)
    shape = (frame.height, frame.width, 3)
    layers: dict[str, np.ndarray] = {}
    timings: dict[str, float] = {}
    warnings: list[str] = []
    total = np.zeros(shape, dtype=np.float64)
    needs_aux = method in OIDN_METHODS or bool(getattr(models, "needs_aux", False))
    if needs_aux:
        from gradsep.model.oidn import PRIOR_SETTING, method_setting, shared_denoiser

        # oidn runs at its chosen setting; model sets that use OIDN name the setting they were trained with
        ctx.denoiser = (shared_denoiser(method_setting()) if method in OIDN_METHODS
                        else shared_denoiser(getattr(models, "oidn_setting", PRIOR_SETTING)))
    if needs_aux and frame.features is not None:
        start = time.perf_counter()
        ctx.aux = ctx.denoiser.prefilter(frame.features)  # once per frame, shared by every layer
        timings["features"] = time.perf_counter() - start
    for name, (image, seconds) in _run_layers(frame, ctx).items():
        timings[name] = seconds
        if name in excess:
            image = add_excess(image, excess[name])
            warnings.append(f"layer {name}: {outlier_count(excess[name])} outlier pixel(s) kept out of the {method} "
                            "denoiser; their energy was spread over a few pixels around each")
        layers[name] = _sanitise(name, image, shape, warnings)
    for name in frame.layers:  # summed in the frame's order whatever order the layers finished in
        total += layers[name]
    image = np.clip(total, 0.0, _F32_MAX).astype(np.float32)
    return Reconstruction(image, layers, timings, method, warnings)


# ------------------------------------------------------------------------------------------------ models


#: The ``fused`` models live in this subfolder of the models folder (``models/fused/direct.onnx``, ...).
FUSED_SUBDIR = "fused"


def _load(folder: Path, priors: tuple[str, ...]) -> Any:
    if not folder.is_dir() or importlib.util.find_spec("gradsep.model.infer") is None:
        return None
    from gradsep.model.infer import ModelError, NetworkReconstructor  # type: ignore[import-not-found]

    models = NetworkReconstructor.load(folder)
    # a folder of fused blend models loads as model.fused.FusedReconstructor, whose models have no ``prior``
    wrong = [m.path.name for m in (models.models.values() if models else ())
             if getattr(m, "prior", "blend") not in priors]
    if wrong:
        raise ModelError(f"{folder}: {', '.join(wrong)} refine a different prior than {' or '.join(priors)} "
                         f"(the {'fused' if priors == ('oidn',) else 'network'} method's); re-export into the right "
                         "folder")
    return models


def load_network(models_dir: str | os.PathLike[str] | None) -> Any:
    """The ``network`` method's reconstructor (models/*.onnx), or None when there are no models or no inference
    module. Same contract as the service's loader: None for a folder without models, an exception for models
    that fail to load. Each model may refine any Poisson prior kind (model.preprocess.POISSON_PRIORS: the one
    its metadata names is what it is fed); models refining OIDN (the ``fused`` kind) are refused."""
    from gradsep.model.preprocess import POISSON_PRIORS

    return _load(models_dir_from(models_dir), tuple(POISSON_PRIORS))


def load_fused(models_dir: str | os.PathLike[str] | None) -> Any:
    """The ``fused`` method's reconstructor (models/fused/*.onnx: per-pixel blend models, model/fused.py), or None
    when the folder has no model or pyoidn is missing. A model of another prior kind there (an ``l1`` network
    model, or the earlier OIDN-residual ``oidn`` models) is refused with ModelError."""
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
