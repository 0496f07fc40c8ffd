"""Gradient-domain refinement of a denoised layer: the second stage of the ``oidn-l1`` method.

OIDN sees one noisy image and the frame's albedo and normal; a G-PT frame also carries each layer's sampled
gradients, which OIDN cannot use. Here OIDN's result becomes the *data term* of the L1 screened Poisson problem
(model/poisson.py ``solve_l1``)::

    argmin_I  Σ α‖I − data‖ + Σ ‖(H_x I − dx, H_y I − dy)‖

so the solution keeps the data where the gradients disagree with it only by noise (the L1 norm lets isolated noisy
gradients go) and takes the gradients' detail where they agree with each other: edges and texture that OIDN
blurred, light that it smeared. Only the **direct** layer is refined: the indirect layer's gradients come from
longer paths whose shifts fail more often, so they are noisier than OIDN's own estimate; a ``color`` layer (a frame
rendered without separation) mixes both and is left as OIDN returns it.

The data term and α come from the *trust rule* (:func:`trust_terms`; ``refine_layer`` without an explicit α). OIDN's
own error (bias, over-smoothing) dominates a layer that is only a little noisy; there the frame's base with its
gradients is the better anchor, and where the base is noisy OIDN's image is. Per pixel, the rule reads how well the
base agrees with the sampled gradients next to the detail they carry, and mixes ``w·base + (1 − w)·OIDN``; per
layer, the same ratio over the whole image (winsorised, so no single pixel decides it) gives the frame weight w_f,
which raises every pixel's w to at least w_f and lowers α towards TRUST_ALPHA_BASE. On a layer clean as a whole
(w_f > 0) α also varies per pixel: lower (TRUST_ALPHA_CLEAN), so the gradients carry more of the detail, except
where the base is exactly 0 and base and gradients agree it is black (an umbra, the background), which is pinned
to it (TRUST_ALPHA_ZERO); that solve starts from the exact L2 solution at the lower α. A noisy layer gets the
plain refinement at α = REFINE_ALPHA with OIDN's image as the data. Callers that pass α (model/fused.py's pinned
candidates) keep it and skip the rule.

The solve runs at a normalised exposure (the layer divided by the robust level of OIDN's image, model/robust.py),
because the IRLS regulariser of ``solve_l1`` is an absolute radiance: a 1e-6 frame and a 1e6 frame of the same scene
are refined alike. The result is scaled back, so every exposure returns the frame's own energy. The rule's settings
were chosen on held-out procedural frames, never on the evaluation's scenes (docs/decisions.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gradsep.model.frame import FLOAT32_MAX, Layer
from gradsep.model.oidn import input_scale
from gradsep.model.poisson import L1Options, solve_l1
from gradsep.model.preprocess import scaled_image
from gradsep.model.robust import box_mean, winsorised_sum

#: The layers whose gradients refine OIDN's result (the rest keep OIDN's).
REFINED_LAYERS: frozenset[str] = frozenset({"direct"})
#: α of the refinement on a noisy layer: the weight of OIDN's image against the gradients.
REFINE_ALPHA = 1.0
#: IRLS passes (pass 0 is the exact L2 solve, which lets every noisy gradient through).
REFINE_ITERATIONS = 8
#: Each pass runs multigrid-V-cycle-preconditioned CG until its residual fell to REFINE_CG_TOLERANCE of the pass's
#: start (relative, so scene- and exposure-independent), at most REFINE_MAX_CG_STEPS steps. Callers that pass
#: ``cg_steps`` (the fused models' candidates, pinned to what they were trained with) get that fixed budget instead.
REFINE_PRECONDITIONER = "mg"
REFINE_CG_TOLERANCE = 0.1
REFINE_MAX_CG_STEPS = 4

#: The per-pixel trust rule: in a (2·TRUST_RADIUS+1)² window around each pixel, r = box(‖∇base − g‖²) / box(‖g‖²)
#: (mean over RGB) is small where the base is nearly noise-free next to the detail the gradients carry and large
#: where its noise dominates; the base's weight w is 1 at r ≤ TRUST_R_LOW, 0 at r ≥ TRUST_R_HIGH, log-linear between.
#: A base that is not finite is not mixed.
TRUST_RADIUS = 3
TRUST_R_LOW = 0.1
TRUST_R_HIGH = 1.0
#: Keeps r finite where the window's gradients are all zero (r is then 0 for an exact base, huge for a noisy one).
TRUST_FLOOR = 1e-12
#: The frame-wide part: the same r over the whole layer (each pixel weighted by 1/(lum(OIDN)² + 0.01) so dark and
#: bright parts count alike; winsorised sums) gives w_f (1 at r ≤ TRUST_FRAME_R[0], 0 at r ≥ TRUST_FRAME_R[1],
#: log-linear between); each pixel's weight is at least w_f, and
#: α = REFINE_ALPHA − (REFINE_ALPHA − TRUST_ALPHA_BASE)·w_f.
TRUST_FRAME_R: tuple[float, float] = (0.05, 0.2)
TRUST_ALPHA_BASE = 0.5
#: On a layer clean as a whole (w_f > 0) the data weight moves per pixel, as far as w_f goes, from α towards
#: TRUST_ALPHA_CLEAN (the gradients carry more of the detail), but towards TRUST_ALPHA_ZERO where the base is exactly
#: 0 (no sample found light), as far as base and gradients agree it is black in a (2·TRUST_PIN_RADIUS+1)² window (the
#: per-pixel rule's weight): a true umbra stays pinned to 0, a black pixel that a hard shadow or silhouette edge
#: crosses (missed by every primal sample while the gradients' shifted samples found its lit part) is not. A low α
#: alone would leak the bright side of shadow edges into black pixels, where a relative error weighs every unit
#: a hundredfold.
TRUST_ALPHA_CLEAN = 0.2
TRUST_ALPHA_ZERO = 2.0
TRUST_PIN_RADIUS = 1



def _forward_differences(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = np.zeros_like(image)
    gy = np.zeros_like(image)
    np.subtract(image[:, 1:], image[:, :-1], out=gx[:, :-1])
    np.subtract(image[1:], image[:-1], out=gy[:-1])
    return gx, gy


def _disagreement_maps(base: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, RGB means: (‖∇base − g‖², ‖g‖²), float32 (H, W), for one layer at level-1 exposure (float32 is
    ample there; an overflow gives inf, which the rule reads as "do not trust")."""
    b = np.asarray(base, np.float32)
    g_x, g_y = np.asarray(dx, np.float32), np.asarray(dy, np.float32)
    bx, by = _forward_differences(b)
    with np.errstate(over="ignore", invalid="ignore"):
        bx -= g_x
        by -= g_y
        residual = np.mean(np.square(bx, out=bx) + np.square(by, out=by), axis=-1)
        signal = np.mean(np.square(g_x) + np.square(g_y), axis=-1)
    return residual, signal


def trust_weights(base: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                  maps: tuple[np.ndarray, np.ndarray] | None = None, radius: int | None = None) -> np.ndarray:
    """The trust rule's per-pixel weight of the base, (H, W, 1) float32 in [0, 1], for one layer at mean-1
    exposure (see TRUST_RADIUS): 1 where the base agrees with the gradients (an exact layer, or a flat one with
    zero gradients), 0 where its disagreement is TRUST_R_HIGH of the gradients' energy or more. Finite inputs.
    ``maps``: _disagreement_maps of the same layer, if the caller has them; ``radius``: the window's (default
    TRUST_RADIUS)."""
    residual, signal = maps if maps is not None else _disagreement_maps(base, dx, dy)
    size = 2 * (TRUST_RADIUS if radius is None else radius) + 1
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        # direct sums (robust.box_mean): a firefly's squared gradient must not reach past its own window
        r = box_mean(residual, size) / (box_mean(signal, size) + np.float32(TRUST_FLOOR))
        w = np.log(np.float32(TRUST_R_HIGH) / np.maximum(r, np.float32(TRUST_FLOOR)))
    w *= np.float32(1.0 / math.log(TRUST_R_HIGH / TRUST_R_LOW))
    return np.clip(np.nan_to_num(w, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0).astype(np.float32)[..., None]


def _log_ramp(r: float, low: float, high: float) -> float:
    """1 at r ≤ low, 0 at r ≥ high (and for NaN), log-linear between."""
    if r <= low:
        return 1.0
    if not r < high:
        return 0.0
    return math.log(high / r) / math.log(high / low)


def frame_disagreement(base: np.ndarray, prior: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                       maps: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """The frame-wide r (TRUST_FRAME_R) at level-1 exposure: Σ ω‖∇base − g‖² / Σ ω‖g‖² (winsorised sums, so no
    single pixel decides it), ω = 1/(lum(prior)² + 0.01); 0 for an exact (or flat, agreeing) layer, inf when the
    gradients are all zero but the base is not. ``maps``: _disagreement_maps of the same layer, if the caller has
    them."""
    residual, signal = maps if maps is not None else _disagreement_maps(base, dx, dy)
    weight = 1.0 / (np.square(np.mean(np.asarray(prior, np.float32), axis=-1)) + np.float32(1e-2))
    with np.errstate(over="ignore", invalid="ignore"):  # winsorised: no single pixel's disagreement decides w_f
        res = winsorised_sum(np.nan_to_num(weight * residual, nan=np.inf))
        sig = winsorised_sum(np.nan_to_num(weight * signal, nan=np.inf))
    if sig > 0.0 and math.isfinite(sig):
        return res / sig
    return 0.0 if res == 0.0 else math.inf


def trusted_data(base: np.ndarray, prior: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, float]:
    """(the trust rule's data term w·base + (1 − w)·prior, its α), all at level-1 exposure, finite inputs; the
    data term is ``prior`` itself, at REFINE_ALPHA, where the base is nowhere trusted."""
    data, alpha, _ = trust_terms(base, prior, dx, dy)
    return data, alpha


def trust_terms(base: np.ndarray, prior: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                ) -> tuple[np.ndarray, float, np.ndarray | None]:
    """:func:`trusted_data` and the clean layer's per-pixel factor on α (TRUST_ALPHA_CLEAN; solve_l1's
    ``alpha_map``), None on a layer that is not clean as a whole."""
    maps = _disagreement_maps(base, dx, dy)
    w = trust_weights(base, dx, dy, maps)
    frame = _log_ramp(frame_disagreement(base, prior, dx, dy, maps), *TRUST_FRAME_R)
    if frame > 0.0:
        w = np.maximum(w, np.float32(frame))
    if not np.any(w > 0):
        return prior, REFINE_ALPHA, None
    alpha = REFINE_ALPHA - (REFINE_ALPHA - TRUST_ALPHA_BASE) * frame
    data = (prior + w * (np.asarray(base, np.float32) - prior)).astype(np.float32)
    if frame <= 0.0:
        return data, alpha, None
    zero = np.all(np.asarray(base) == 0, axis=-1)
    pin = np.float32(TRUST_ALPHA_ZERO)
    if zero.any():  # pinned as far as base and gradients agree it is black
        agree = trust_weights(base, dx, dy, maps, TRUST_PIN_RADIUS)[..., 0]
        pin = TRUST_ALPHA_CLEAN + agree * np.float32(TRUST_ALPHA_ZERO - TRUST_ALPHA_CLEAN)
    target = np.where(zero, pin, TRUST_ALPHA_CLEAN) / alpha
    return data, alpha, (1.0 - (1.0 - target) * frame).astype(np.float32)


def clean_weight(prior: np.ndarray, layer: Layer) -> float:
    """The frame-wide weight w_f in [0, 1] the trust rule gives this layer (TRUST_FRAME_R): 1 for a layer clean as
    a whole, 0 for a noisy one, a layer without gradients or a base that is not finite. ``prior``: OIDN's image of
    the layer at the frame's exposure (refine_layer's). model.fused's clean-layer average reads it: how far a
    second, gradient-domain estimate may be averaged in."""
    if not layer.has_gradients or not np.all(np.isfinite(layer.base)):
        return 0.0
    scale = input_scale(prior)
    r = frame_disagreement(*(scaled_image(a, scale) for a in (layer.base, prior, layer.dx, layer.dy)))
    return _log_ramp(r, *TRUST_FRAME_R)


def _frame_weight(alpha: float) -> float:
    """w_f from the α trust_terms chose: the inverse of its α = REFINE_ALPHA − (REFINE_ALPHA − TRUST_ALPHA_BASE)·w_f
    (exact at w_f = 0 and 1; float rounding between)."""
    span = REFINE_ALPHA - TRUST_ALPHA_BASE
    if span == 0.0:
        return 0.0
    return min(max((REFINE_ALPHA - alpha) / span, 0.0), 1.0)


@dataclass(frozen=True)
class RefineSolve:
    """How :func:`refine_layer` solves: ``preconditioner`` (None: REFINE_PRECONDITIONER); ``cg_steps`` /
    ``cg_tolerance`` (None and None: each pass to the relative residual REFINE_CG_TOLERANCE in at most
    REFINE_MAX_CG_STEPS steps; ``cg_steps`` alone: that fixed budget at solve_l1's own tolerance); ``passes``
    (None: REFINE_ITERATIONS). A model trained on refinements of another solve, such as the fused models, passes
    the one it was trained with."""

    preconditioner: str | None = None
    cg_steps: int | None = None
    cg_tolerance: float | None = None
    passes: int | None = None

    def solver_keywords(self) -> dict:
        """solve_l1's CG and preconditioner keywords."""
        if self.cg_steps is not None:  # the pinned fixed budget; a tolerance only if one is asked for
            budget = {"cg_iterations": self.cg_steps} | (
                {} if self.cg_tolerance is None else {"cg_tolerance": self.cg_tolerance})
        else:
            budget = {"cg_iterations": REFINE_MAX_CG_STEPS,
                      "cg_tolerance": REFINE_CG_TOLERANCE if self.cg_tolerance is None else self.cg_tolerance}
        return budget | {"preconditioner": self.preconditioner or REFINE_PRECONDITIONER}


def refine_layer(name: str, prior: np.ndarray, layer: Layer, alpha: float | None = None, *,
                 solve: RefineSolve | None = None, report: dict[str, float] | None = None) -> np.ndarray:
    """``prior`` (OIDN's denoise of ``layer.base``) refined by the layer's gradients when ``name`` is one of
    REFINED_LAYERS and the layer carries gradients; otherwise ``prior`` unchanged. float32 (H, W, 3), ≥ 0.
    ``alpha`` None: the trust rule's data term and α; a number: OIDN's image at that α. ``solve``: how the L1
    problem is solved (:class:`RefineSolve`; None: the defaults).
    ``report``: when given, ``report["clean_weight"]`` is set to the layer's w_f as the trust rule computed it here
    (what :func:`clean_weight` would recompute, to float rounding; 0 wherever the rule did not run), so a caller
    that needs both does not pay for the frame statistic twice."""
    solve = solve or RefineSolve()
    if report is not None:
        report["clean_weight"] = 0.0  # until the trust rule says otherwise
    if name not in REFINED_LAYERS or not layer.has_gradients:
        return prior
    scale = input_scale(prior)  # robust level 1, as OIDN's own input is normalised; 1.0 for a black prior
    dx, dy = scaled_image(layer.dx, scale), scaled_image(layer.dy, scale)
    data = scaled_image(prior, scale)
    alpha_map = None
    if alpha is None:  # the trust rule: per pixel, how far the frame's own base is trusted beside OIDN's image
        alpha = REFINE_ALPHA
        if np.all(np.isfinite(layer.base)):  # (the frame policy keeps NaN/Inf out; a direct caller may not)
            data, alpha, alpha_map = trust_terms(scaled_image(layer.base, scale), data, dx, dy)
            if report is not None:
                report["clean_weight"] = _frame_weight(alpha)
    # a clean layer's L2 start at its non-black pixels' α (the map's smallest): solve_l1's pass 0, a DCT solve,
    # cannot take a per-pixel map, and the truncated CG passes after it move the image only part of the way
    start = alpha * float(np.min(alpha_map)) if alpha_map is not None else None
    options = L1Options(solve.passes or REFINE_ITERATIONS, **solve.solver_keywords())
    solved, _ = solve_l1(data, dx, dy, alpha, options, alpha_map=alpha_map, start_alpha=start)
    out = np.asarray(solved, np.float64) / scale
    return np.clip(out, 0.0, FLOAT32_MAX).astype(np.float32)
