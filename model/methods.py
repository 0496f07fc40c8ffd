"""The table of reconstruction methods: each method declared once, and every front end reads it.

A method is a :class:`Method`: its name, what the frame must carry (gradients and feature groups), the model sets it
needs (:data:`MODEL_SETS`), how its layers are scheduled, the function that reconstructs one layer, its place in
the default preference and a one-line description. The command line (``gradsep reconstruct --method`` and
``gradsep client --method``), the service (its served list, its OpenAPI enum, ``/v1/models``), the default policy
(:func:`default_method`, model.reconstruct.choose_method), the demo and the evaluation all read :func:`methods`;
none keeps a list of its own. A new method is one :func:`register` call (here for the shipped ones), plus its own
module holding its layer function.

Import-light on purpose (standard library only): argument parsers and the service's settings read the names
without loading numpy; a method's function is named by a dotted path and imported on first use
(:func:`layer_function`).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Literal

from gradsep.model.policy import FEATURE_GROUPS

#: What a method needs of the frame's gradients: ``none`` (a plain path-traced frame serves), ``direct`` (the
#: direct layer's, when the frame has one; other layers may be plain), ``all`` (every layer's).
Gradients = Literal["none", "direct", "all"]
GRADIENT_NEEDS: tuple[str, ...] = ("none", "direct", "all")
#: How a frame's layers are scheduled (model.reconstruct._run_layers): one after the other; in worker threads
#: (``$GRADSEP_LAYER_THREADS`` at once); or ``pipelined``: each layer's OIDN image in the calling thread (the
#: denoiser already uses every core), the rest of the layer in a worker beside the next layer's denoise.
Schedule = Literal["sequential", "concurrent", "pipelined"]
SCHEDULES: tuple[str, ...] = ("sequential", "concurrent", "pipelined")
#: Which OIDN setting a method's denoiser runs: the ``oidn`` method's (model.oidn.method_setting, $GRADSEP_OIDN_
#: SETTING) or the one the method's loaded model was trained with (its ``oidn_setting``).
DenoiserSetting = Literal["method", "model"]


@dataclass(frozen=True)
class ModelSet:
    """Something a method needs loaded: a folder of exported models, or a runtime library.

    ``loader`` (``module:function``) takes the models folder and returns the loaded object, or None/False where
    it is absent (a missing folder, a package not installed); it raises for models that exist but cannot be
    served. A set with ``folder`` None is a runtime, detected whenever it is asked for and not given.
    """

    name: str
    loader: str
    description: str
    folder: str | None = None  # where its files live, relative to the models folder (for messages)
    #: ``module:function`` naming the model files (``NAME.onnx`` stems, in ``folder``) a frame with these layers
    #: needs: ``fn(layers) -> tuple[str, ...]``; None: one per layer (``direct.onnx``, ``indirect.onnx``...)
    files: str | None = None
    #: ``module:function`` naming files (relative to ``folder``) the set reads when present and does without
    #: otherwise: ``fn(layers) -> tuple[str, ...]``; None: none
    optional_files: str | None = None

    def model_files(self, layers: Iterable[str]) -> tuple[str, ...]:
        """The ``NAME.onnx`` stems this set needs for a frame with ``layers`` (none for a runtime)."""
        if self.folder is None:
            return ()
        return tuple(resolve(self.files)(tuple(layers))) if self.files else tuple(layers)

    def optional_model_files(self, layers: Iterable[str]) -> tuple[str, ...]:
        """Files (relative to ``folder``) this set reads for a frame with ``layers`` when they are there."""
        return tuple(resolve(self.optional_files)(tuple(layers))) if self.optional_files else ()


#: The model sets the shipped methods need, by name.
MODEL_SETS: dict[str, ModelSet] = {
    "network": ModelSet("network", "gradsep.model.reconstruct:load_network",
                        "the per-layer networks, models/{direct,indirect,color}.onnx", folder="."),
    "fused": ModelSet("fused", "gradsep.model.reconstruct:load_fused",
                      "the per-layer blend networks, models/fused/*.onnx (needs pyoidn)", folder="fused",
                      files="gradsep.model.builtin_methods:fused_files",
                      optional_files="gradsep.model.builtin_methods:fused_optional_files"),
    "oidn": ModelSet("oidn", "gradsep.model.reconstruct:load_oidn",
                     "Intel Open Image Denoise (pip install pyoidn)"),
}


@dataclass(frozen=True)
class Method:
    """One reconstruction method (docs/methods.md shows this table)."""

    name: str
    description: str
    #: ``module:function`` reconstructing one layer: ``fn(name, layer, ctx, denoised) -> (H, W, 3) array``
    #: (model.reconstruct.LayerFunction; ``denoised`` is the layer's OIDN image when the caller computed it).
    function: str
    gradients: Gradients = "all"
    uses: tuple[str, ...] = ()  # feature groups it reads when the frame has them
    requires: tuple[str, ...] = ()  # feature groups it cannot run without (a subset of ``uses``)
    models: tuple[str, ...] = ()  # MODEL_SETS it needs loaded; the first model folder is its own
    schedule: Schedule = "sequential"
    #: place in the default preference (lower first); None: never chosen by default, only when named
    preference: int | None = None
    alpha: bool = False  # takes the screened Poisson data weight ``alpha``
    denoiser: DenoiserSetting | None = None  # runs OIDN on each layer's base first (needs the ``oidn`` set)
    #: keep each layer's extreme outliers out of the method and spread their excess back near them
    #: (model/robust.py): for methods whose frame-wide statistics, CNN receptive field or solver steps one pixel
    #: could move; the screened Poisson solvers see the frame as it is (their reach is measured, docs/methods.md)
    split_outliers: bool = True
    #: cap each layer's bright sources (a light in view) before the method and add their excess back in place
    #: (model.robust.split_sources): for ``oidn``, which smears them; ``oidn-l1``'s refinement restores them from
    #: the direct layer's gradients itself
    split_sources: bool = False

    def __post_init__(self) -> None:
        problems = []
        if not self.name or self.name != self.name.strip() or "," in self.name:
            problems.append("a name without spaces at its ends or commas")
        if ":" not in self.function:
            problems.append(f"function {self.function!r} as 'module:function'")
        if self.gradients not in GRADIENT_NEEDS:
            problems.append(f"gradients in {GRADIENT_NEEDS}, not {self.gradients!r}")
        unknown = [g for g in (*self.uses, *self.requires) if g not in FEATURE_GROUPS]
        if unknown:
            problems.append(f"feature groups from {tuple(FEATURE_GROUPS)}, not {unknown}")
        if not set(self.requires) <= set(self.uses):
            problems.append("required feature groups among the used ones")
        if self.schedule not in SCHEDULES:
            problems.append(f"schedule in {SCHEDULES}, not {self.schedule!r}")
        if self.schedule == "pipelined" and self.denoiser is None:
            problems.append("a denoiser for a pipelined schedule (its layers start from an OIDN image)")
        if self.denoiser is not None and "oidn" not in self.models:
            problems.append("the 'oidn' model set for a method that runs OIDN")
        if problems:
            raise ValueError(f"method {self.name!r} needs " + "; ".join(problems))

    @property
    def model_sets(self) -> tuple[str, ...]:
        """Its model sets that are model folders (not runtimes), e.g. ``("fused",)``."""
        return tuple(m for m in self.models if MODEL_SETS[m].folder is not None)

    def summary(self) -> dict[str, Any]:
        """What /v1/models and the docs show of it."""
        return {"name": self.name, "description": self.description, "gradients": self.gradients,
                "features_used": list(self.uses), "features_required": list(self.requires),
                "models": list(self.models), "schedule": self.schedule, "preference": self.preference,
                "alpha": self.alpha, "split_outliers": self.split_outliers, "split_sources": self.split_sources}


_TABLE: dict[str, Method] = {}


def register(method: Method, *, replace: bool = False) -> Method:
    """Add ``method`` to the table (after the others: served lists keep declaration order)."""
    if method.name in _TABLE and not replace:
        raise ValueError(f"method {method.name!r} is already registered")
    unknown = [m for m in method.models if m not in MODEL_SETS]
    if unknown:
        raise ValueError(f"method {method.name!r} needs unknown model set(s) {unknown}; known: {list(MODEL_SETS)}")
    _TABLE[method.name] = method
    return method


def unregister(name: str) -> None:
    _TABLE.pop(name, None)


@contextmanager
def registered(method: Method, model_set: ModelSet | None = None) -> Iterator[Method]:
    """``method`` (and its own ``model_set``) in the table for the duration of the block, replacing a method of
    the same name, which is restored afterwards (tests, plug-ins, benchmarks measuring another schedule)."""
    previous_set = MODEL_SETS.get(model_set.name) if model_set is not None else None
    if model_set is not None:
        MODEL_SETS[model_set.name] = model_set
    previous = _TABLE.get(method.name)
    register(method, replace=True)
    try:
        yield method
    finally:
        if previous is None:
            unregister(method.name)
        else:
            _TABLE[method.name] = previous
        if model_set is not None:
            if previous_set is None:
                MODEL_SETS.pop(model_set.name, None)
            else:
                MODEL_SETS[model_set.name] = previous_set


def methods() -> tuple[Method, ...]:
    """Every method, in declaration order (the order of served lists and ``--method`` choices)."""
    return tuple(_TABLE.values())


def names() -> tuple[str, ...]:
    return tuple(_TABLE)


def get(name: str) -> Method:
    """The method ``name``; ValueError naming the known ones otherwise."""
    try:
        return _TABLE[name]
    except KeyError:
        raise ValueError(f"unknown reconstruction method {name!r}; expected one of {', '.join(_TABLE)}") from None


def preference_order() -> tuple[str, ...]:
    """Every method, best first: those with a preference by rank, then the others in declaration order."""
    ranked = sorted((m for m in _TABLE.values() if m.preference is not None), key=lambda m: m.preference)  # type: ignore[arg-type, return-value]
    return (*(m.name for m in ranked), *(m.name for m in _TABLE.values() if m.preference is None))


def default_preference() -> tuple[str, ...]:
    """The methods the default policy may pick, best first."""
    return tuple(n for n in preference_order() if _TABLE[n].preference is not None)


def default_method(served: Iterable[str], *, gradients: bool = True) -> str | None:
    """The default among ``served`` (methods that can serve a frame): the first of :func:`default_preference`;
    for a plain frame (``gradients`` False) only methods that need no gradients count. None when none serves."""
    served = set(served)
    return next((n for n in default_preference()
                 if n in served and (gradients or _TABLE[n].gradients == "none")), None)


def help_text() -> str:
    """One line for ``--method``'s help: the default order and each method's description."""
    return ("default: the first that serves the frame of " + " > ".join(default_preference()) + ". "
            + "; ".join(f"{m.name}: {m.description}" for m in _TABLE.values()))


def resolve(dotted: str) -> Callable[..., Any]:
    """The callable named ``module:function`` (imported now)."""
    module, _, attr = dotted.partition(":")
    return getattr(importlib.import_module(module), attr)


def layer_function(method: Method) -> Callable[..., Any]:
    return resolve(method.function)


class LoadedModels:
    """The model sets a command or replica has loaded, by :data:`MODEL_SETS` name: what ``reconstruct`` takes.

    ``LoadedModels(network=..., fused=...)`` holds what was given; a runtime set (``oidn``) not given is detected
    when first asked for. A set given as None (or False) is not loaded.
    """

    def __init__(self, **sets: Any) -> None:
        unknown = [n for n in sets if n not in MODEL_SETS]
        if unknown:
            raise ValueError(f"unknown model set(s) {unknown}; known: {list(MODEL_SETS)}")
        self._sets: dict[str, Any] = dict(sets)

    @classmethod
    def load(cls, models_dir: str | os.PathLike[str] | None, sets: Iterable[str] | None = None) -> LoadedModels:
        """Load ``sets`` (default: every known set) from the models folder with their loaders."""
        return cls(**{n: resolve(MODEL_SETS[n].loader)(models_dir) for n in (MODEL_SETS if sets is None else sets)})

    def get(self, name: str) -> Any:
        """The loaded set ``name``, or None."""
        if name not in self._sets and name in MODEL_SETS and MODEL_SETS[name].folder is None:
            self._sets[name] = resolve(MODEL_SETS[name].loader)(None)
        value = self._sets.get(name)
        return None if value is None or value is False else value

    def has(self, name: str) -> bool:
        return self.get(name) is not None

    def missing(self, method: Method) -> list[str]:
        """The model sets ``method`` needs that are not loaded."""
        return [n for n in method.models if not self.has(n)]

    def serves(self) -> tuple[str, ...]:
        """The methods whose model sets are all loaded, in declaration order."""
        return tuple(m.name for m in methods() if not self.missing(m))

    def loaded(self) -> dict[str, Any]:
        """The loaded model-folder sets (not runtimes), by name."""
        return {n: self.get(n) for n in MODEL_SETS if MODEL_SETS[n].folder is not None and self.has(n)}


# ------------------------------------------------------------------------------------------------ the table

_BUILTIN = "gradsep.model.builtin_methods"

register(Method(
    "network", "the paper's GradNet-style network with attention refining a truncated L1 solve, per layer",
    f"{_BUILTIN}:network_layer", gradients="all", uses=("albedo", "normal", "depth"),
    requires=("albedo", "normal", "depth"), models=("network",), schedule="concurrent", preference=4))
register(Method(
    "l1", "screened Poisson solve with an L1 data term (robust to outliers)", f"{_BUILTIN}:l1_layer",
    gradients="all", schedule="concurrent", preference=5, alpha=True, split_outliers=False))
register(Method(
    "l2", "screened Poisson solve with an L2 data term (linear, one DCT solve)", f"{_BUILTIN}:l2_layer",
    gradients="all", alpha=True, split_outliers=False))
register(Method(
    "oidn", "Intel Open Image Denoise on each layer (the method for a plain frame)", f"{_BUILTIN}:oidn_layer",
    gradients="none", uses=("albedo", "normal"), models=("oidn",), preference=2, denoiser="method",
    split_sources=True))
register(Method(
    "oidn-l1", "oidn, then the direct layer refined by its gradients (L1 solve on OIDN's image)",
    f"{_BUILTIN}:oidn_l1_layer", gradients="direct", uses=("albedo", "normal"), models=("oidn",),
    schedule="pipelined", preference=1, denoiser="method"))
register(Method(
    "fused", "per-pixel learned blend of OIDN's image and its gradient-domain refinements",
    f"{_BUILTIN}:fused_layer", gradients="all", uses=("albedo", "normal", "depth"),
    requires=("albedo", "normal", "depth"), models=("fused", "oidn"), schedule="pipelined", preference=3,
    denoiser="model"))
