"""The layer functions of the shipped methods (model/methods.py names them): one illumination layer in, its
reconstruction out, with the frame's shared context (model.reconstruct.LayerContext); and the model files their
model sets read (model.methods.ModelSet.files / optional_files).

Each is a thin call into the module that does the work; what a frame must carry was checked by
model.reconstruct before any of them runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from gradsep.model.frame import Layer

if TYPE_CHECKING:
    from gradsep.model.reconstruct import LayerContext


def l1_layer(name: str, layer: Layer, ctx: LayerContext, denoised: np.ndarray | None = None) -> np.ndarray:
    from gradsep.model.poisson import solve_l1

    return solve_l1(layer.base, layer.dx, layer.dy, ctx.alpha)[0]


def l2_layer(name: str, layer: Layer, ctx: LayerContext, denoised: np.ndarray | None = None) -> np.ndarray:
    from gradsep.model.poisson import solve_l2

    return solve_l2(layer.base, layer.dx, layer.dy, ctx.alpha)


def oidn_layer(name: str, layer: Layer, ctx: LayerContext, denoised: np.ndarray | None = None) -> np.ndarray:
    """OIDN on the layer's base with the frame's auxiliary images (prefiltered once per frame), backed off toward
    the base where the layer's variance channel says it was already converged (model/backoff.py)."""
    from gradsep.model.backoff import back_off

    # the lit level: the outlier detector's measurement of this base where it made one (None: OIDN measures it)
    image = ctx.denoiser.denoise(layer.base, ctx.aux, ctx.lit_levels.get(name)) if denoised is None else denoised
    return image if layer.var is None else back_off(layer.base, image, layer.var, ctx.pinned.get(name))


def oidn_l1_layer(name: str, layer: Layer, ctx: LayerContext, denoised: np.ndarray | None = None) -> np.ndarray:
    """OIDN's image, then (the direct layer) refined by the layer's gradients: model/refine.py."""
    from gradsep.model.refine import refine_layer

    return refine_layer(name, oidn_layer(name, layer, ctx, denoised), layer)


def network_layer(name: str, layer: Layer, ctx: LayerContext, denoised: np.ndarray | None = None) -> np.ndarray:
    return ctx.models.get("network").reconstruct_layer(name, layer, ctx.features)


def fused_layer(name: str, layer: Layer, ctx: LayerContext, denoised: np.ndarray | None = None) -> np.ndarray:
    """The blend's candidates start from the layer's OIDN image, denoised here or by the caller."""
    return ctx.models.get("fused").reconstruct_layer(name, layer, ctx.features, ctx.aux, denoised=denoised)


def fused_files(layers: tuple[str, ...]) -> tuple[str, ...]:
    """The blend models a frame with ``layers`` needs: none for the layers model.fused serves with one candidate
    alone (FIXED_LAYERS)."""
    from gradsep.model.fused import FIXED_LAYERS

    return tuple(name for name in layers if name not in FIXED_LAYERS)


def fused_optional_files(layers: tuple[str, ...]) -> tuple[str, ...]:
    """The ``network`` set's direct model, which fused's clean-layer average reads when it is there
    (model.fused.CLEAN_AVERAGE_MODEL, relative to the fused folder)."""
    from gradsep.model.fused import CLEAN_AVERAGE_MODEL, FIXED_LAYERS

    return (str(CLEAN_AVERAGE_MODEL),) if "direct" in layers and "direct" in FIXED_LAYERS else ()
