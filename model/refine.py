"""Gradient-domain refinement of a denoised layer: the second stage of the ``oidn-l1`` method.

OIDN sees one noisy image and the frame's albedo and normal; a G-PT frame also carries each layer's sampled
gradients, which OIDN cannot use. Here OIDN's result becomes the *data term* of the L1 screened Poisson problem
(model/poisson.py ``solve_l1``)::

    argmin_I  Σ α‖I − OIDN(base)‖ + Σ ‖(H_x I − dx, H_y I − dy)‖

so the solution keeps OIDN's image where the gradients disagree with it only by noise (the L1 norm lets
isolated noisy gradients go) and takes the gradients' detail where they agree with each other: edges and texture
that OIDN blurred, light that it smeared. α is the weight of OIDN's image against the gradients.

Only the **direct** layer is refined, with α = 1. Both were chosen on held-out procedural seeds (81001-81008,
320x240, G-PT 1, 4, 16 and 64 spp, two independent 1024-spp references, product estimator; docs/network.md
"The oidn-l1 method"), never on the evaluation's scenes. Refining the direct layer lowered the frame's RelMSE
against OIDN alone in all 12 (seed, spp) cases at 16 and 64 spp and in 10 of 12 at 1 and 4 spp (2 % and 0.7 %
worse in the other two). α = 0.5 was a little better at 16-64 spp but once four times worse than OIDN at 4 spp;
α = 1 never was. Refining the indirect layer made it worse at α ≤ 1 and changed nothing at α = 5: its gradients
come from longer paths whose shifts fail more often, so they are noisier than OIDN's own estimate. A ``color``
layer (a frame rendered without separation) mixes both and is left as OIDN returns it.

Since issue 14's trust rule (``trusted_data``; docs/network.md "The trust rule"), ``refine_layer`` without an
explicit α mixes the frame's own base into that data term where the frame shows it is clean: per pixel, from how
well the base agrees with the sampled gradients next to the detail they carry, and per frame, from the same ratio
over the whole layer (which also lowers α). OIDN's own error (bias, over-smoothing) dominates a layer that is only
a little noisy; there the base with its gradients (the ``l1`` method's data) is the better anchor. A noisy layer
gets the plain refinement above, bit for bit. Callers that pass α (model/fused.py's pinned candidates) keep it.
On a layer clean as a whole the data weight also varies per pixel (``TRUST_ALPHA_CLEAN``, session 17): lower, so
the gradients carry more detail, except where the base is exactly 0, which is pinned to it as far as the gradients
around it agree it is black (``TRUST_PIN_RADIUS``, session 18); and its solve starts from the exact L2 solution at
that lower α (``TRUST_CLEAN_START``, session 18).

The solve runs at a normalised exposure (the layer divided by the mean of OIDN's image), because the IRLS
regulariser of ``solve_l1`` is an absolute radiance: without it a 1e-6 frame and a 1e6 frame of the same scene
would be refined differently. The result is scaled back, so every exposure returns the frame's own energy.
"""

from __future__ import annotations

import math

import numpy as np

from gradsep.model.frame import Layer
from gradsep.model.oidn import input_scale
from gradsep.model.poisson import solve_l1
from gradsep.model.preprocess import scaled_image
from gradsep.model.robust import winsorised_sum

#: The layers whose gradients refine OIDN's result (the rest keep OIDN's).
REFINED_LAYERS: frozenset[str] = frozenset({"direct"})
#: α of the refinement: the weight of OIDN's image against the gradients (held-out seeds, see the docstring).
REFINE_ALPHA = 1.0
#: IRLS passes of the refinement (pass 0 is the exact L2 solve, which lets every noisy gradient through). 8 passes:
#: on the held-out study 1.5 % above 20 passes' RelMSE (geo. mean 0.773 vs 0.761 of oidn's) at 40 % of the cost.
REFINE_ITERATIONS = 8
#: CG steps per IRLS pass, and their preconditioner (model.poisson.solve_l1): 2 steps of the multigrid V-cycle.
#: Chosen on the same held-out study (benchmarks/study_refine.py error --family speed; docs/network.md "The
#: oidn-l1 method"): RelMSE / oidn 0.768 (worst 1.02, 31/32 better) against 0.773 (1.03, 30/32) for the former
#: 4 DCT-preconditioned steps, at 0.89 s instead of 1.06 s per 1280x720 layer (study_refine.py time, same run).
#: Fewer passes or one V-cycle per pass were cheaper still (0.58-0.60 s) but 3-7 % worse on average and up to
#: 2.7x oidn's error on single frames. Since issue 14's tolerance rule below, this fixed budget is used only when
#: REFINE_CG_TOLERANCE is None (it under-converged on some frames: cbox 64 spp).
REFINE_CG_STEPS = 2
REFINE_PRECONDITIONER = "mg"
#: The default solve's CG rule (issue 14, since the fixed 2 steps under-converged on some frames): each IRLS pass
#: takes V-cycle-preconditioned CG steps until the residual fell to REFINE_CG_TOLERANCE of the pass's start, at most
#: REFINE_MAX_CG_STEPS. Relative, so scene- and exposure-independent. Chosen on the held-out study (docs/network.md
#: "The oidn-l1 method", benchmarks/study_refine.py error --family tolerance). Callers that pass ``cg_steps`` (the
#: fused models, pinned to what they were trained with) keep the fixed-budget solve: solve_l1's own tolerance.
REFINE_CG_TOLERANCE: float | None = 0.1
#: Was 8; 4 since issue 15's held-out frontier (benchmarks/study_fused_speed.py error --per-frame, variants
#: oidn-l1 vs oidn-l1@DIRECT_CG, with the trust rule): same geometric-mean RelMSE (1.0001x), every frame within
#: 1 % (worst 81004 @ 64 spp, 1.008x), about 2.7 -> 1.7 CPU-seconds for a real 720p direct solve, where every pass
#: after the second used all 8 steps.
REFINE_MAX_CG_STEPS = 4
#: Start the IRLS from OIDN's image instead of the exact L2 solve. Measured and rejected: the first weights then
#: come from OIDN's image, whose smoothed edges the L1 norm keeps, so less of the gradients' detail returns
#: (0.81 at 8 passes, 0.89 at 3, against 0.77 from the L2 start); never worse than oidn, though (worst 0.98).
REFINE_WARM_START = False

#: The trust rule (issue 14; ``refine_layer`` without an explicit α). OIDN's own error (its bias and
#: over-smoothing) dominates once a layer is only a little noisy, and there the frame's base with its gradients is
#: the better data term (the ``l1`` method's); where the base is noisy OIDN's image is. The rule reads, in a
#: (2·TRUST_RADIUS+1)² window around each pixel, how well the base agrees with the sampled gradients relative to
#: the gradients' own size, r = box(‖∇base − g‖²) / box(‖g‖²) (mean over RGB): small where the base is nearly
#: noise-free next to the detail the gradients carry, large where its noise dominates. The data term becomes
#: w·base + (1 − w)·OIDN per pixel, w = 1 at r ≤ TRUST_R_LOW, 0 at r ≥ TRUST_R_HIGH, log-linear between, solved
#: like the plain refinement (α lowered by the frame-wide part below). A base that is not finite is not mixed.
#: Chosen on held-out procedural seeds only (docs/network.md "The trust rule", benchmarks/study_direct_trust.py),
#: against either part alone; never on cbox, the teapot or the evaluation seeds.
TRUST_RADIUS = 3
TRUST_R_LOW = 0.1
TRUST_R_HIGH = 1.0
#: Keeps r finite where the window's gradients are all zero (r is then 0 for an exact base, huge for a noisy one).
TRUST_FLOOR = 1e-12
#: The frame-wide part of the rule: the same r over the whole layer (its two terms summed over the image,
#: each pixel weighted by 1/(lum(OIDN)² + 0.01) so dark and bright parts count alike) gives a weight w_f (1 at
#: r ≤ TRUST_FRAME_R[0], 0 at r ≥ TRUST_FRAME_R[1], log-linear between); each pixel's weight is at least w_f,
#: and α = REFINE_ALPHA − (REFINE_ALPHA − TRUST_ALPHA_BASE)·w_f: a layer clean as a whole leans on its base with
#: the gradients taking over more of the detail (the ``l1`` method's regime). None: no frame-wide part.
TRUST_FRAME_R: tuple[float, float] | None = (0.05, 0.2)
TRUST_ALPHA_BASE = 0.5
#: The clean layer's per-pixel α (issue 14, session 17, design 14 of docs/network.md "Closing the teapot gap"): on a
#: layer the frame-wide part calls clean (w_f > 0) the data weight falls further, per pixel, from α towards
#: TRUST_ALPHA_CLEAN (the product's Poisson α, model/policy.py DEFAULT_ALPHA) as far as w_f goes, so the gradients
#: carry more of the detail; but where the base is exactly 0 (no sample found light: an umbra, the background
#: behind an object) it rises towards TRUST_ALPHA_ZERO instead, which pins those pixels to their base. A lower α
#: alone (design 1) leaked the bright side of shadow edges into such black pixels, where a relative error weighs
#: every unit a hundredfold. Chosen on held-out seeds only (design 81001-81008, validation 84001-84004; the test
#: seeds 85001-85004 reported). None: no per-pixel α (the rule before).
TRUST_ALPHA_CLEAN: float | None = 0.2
TRUST_ALPHA_ZERO = 2.0
#: How far a zero pixel is pinned (issue 14, session 18, design 22 of docs/network.md "Designs 15-18" and its rounds):
#: only as far as its base agrees with the sampled gradients around it, the trust rule's weight in a
#: (2·TRUST_PIN_RADIUS+1)² window (pinned at r ≤ TRUST_R_LOW, TRUST_ALPHA_CLEAN at r ≥ TRUST_R_HIGH). A true umbra
#: (base and gradients agree it is black) stays pinned; a black pixel that a hard shadow or silhouette edge crosses,
#: missed by every primal sample while the gradients' shifted samples found its lit part, is not. Chosen by a rule
#: written before scoring; held-out direct RelMSE 0.999× (room design), 0.922× (studio design), 0.996× / 0.979×
#: (validation), 0.899× / 0.889× (test sets), no frame more than 2 % worse. None: the full pin (session 17's rule).
TRUST_PIN_RADIUS: int | None = 1
#: Start a clean layer's IRLS from the exact L2 solve at the clean per-pixel α (the smallest α·m: that of its
#: non-black pixels) instead of at the layer's scalar α (solve_l1's pass 0, a DCT solve, cannot take a per-pixel
#: map). The truncated CG of the passes after it (REFINE_MAX_CG_STEPS at tolerance 0.1) moves the image only part of
#: the way from its start, so with the scalar start a clean layer ended between the α 0.5 and α 0.2 solutions.
#: Issue 14, session 18, design 17 of docs/network.md "Designs 15-18", the one of four adopted by a rule written
#: before scoring: direct-layer RelMSE 0.998× (design), 0.998× (validation), 0.980× (the new studio design set:
#: objects against an empty background), no frame more than 1 % worse; test sets 0.980× and 0.985×. False: the
#: scalar start (the rule of session 17).
TRUST_CLEAN_START = True

_F32_MAX = float(np.finfo(np.float32).max)


def _forward_differences(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = np.zeros_like(image)
    gy = np.zeros_like(image)
    np.subtract(image[:, 1:], image[:, :-1], out=gx[:, :-1])
    np.subtract(image[1:], image[:-1], out=gy[:-1])
    return gx, gy


def _disagreement_maps(base: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, RGB means: (‖∇base − g‖², ‖g‖²), float32 (H, W), for one layer at mean-1 exposure (float32 is
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
    from scipy.ndimage import uniform_filter

    residual, signal = maps if maps is not None else _disagreement_maps(base, dx, dy)
    size = 2 * (TRUST_RADIUS if radius is None else radius) + 1
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        r = (np.maximum(uniform_filter(residual, size, mode="nearest"), 0.0)
             / (np.maximum(uniform_filter(signal, size, mode="nearest"), 0.0) + np.float32(TRUST_FLOOR)))
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
    """The frame-wide r (TRUST_FRAME_R) at mean-1 exposure: Σ ω‖∇base − g‖² / Σ ω‖g‖², ω = 1/(lum(prior)² +
    0.01); 0 for an exact (or flat, agreeing) layer, inf when the gradients are all zero but the base is not.
    ``maps``: _disagreement_maps of the same layer, if the caller has them."""
    residual, signal = maps if maps is not None else _disagreement_maps(base, dx, dy)
    weight = 1.0 / (np.square(np.mean(np.asarray(prior, np.float32), axis=-1)) + np.float32(1e-2))
    with np.errstate(over="ignore", invalid="ignore"):  # winsorised: no single pixel's disagreement decides w_f
        res = winsorised_sum(np.nan_to_num(weight * residual, nan=np.inf))
        sig = winsorised_sum(np.nan_to_num(weight * signal, nan=np.inf))
    if sig > 0.0 and math.isfinite(sig):
        return res / sig
    return 0.0 if res == 0.0 else math.inf


def trusted_data(base: np.ndarray, prior: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, float]:
    """(the trust rule's data term w·base + (1 − w)·prior, its α), all at mean-1 exposure, finite inputs; the
    data term is ``prior`` itself, at REFINE_ALPHA, where the base is nowhere trusted."""
    data, alpha, _ = trust_terms(base, prior, dx, dy)
    return data, alpha


def trust_terms(base: np.ndarray, prior: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                ) -> tuple[np.ndarray, float, np.ndarray | None]:
    """:func:`trusted_data` and the clean layer's per-pixel factor on α (TRUST_ALPHA_CLEAN; solve_l1's
    ``alpha_map``), None on a layer that is not clean as a whole."""
    maps = _disagreement_maps(base, dx, dy)
    w = trust_weights(base, dx, dy, maps)
    frame = 0.0 if TRUST_FRAME_R is None else _log_ramp(frame_disagreement(base, prior, dx, dy, maps),
                                                         *TRUST_FRAME_R)
    if frame > 0.0:
        w = np.maximum(w, np.float32(frame))
    if not np.any(w > 0):
        return prior, REFINE_ALPHA, None
    alpha = REFINE_ALPHA - (REFINE_ALPHA - TRUST_ALPHA_BASE) * frame
    data = (prior + w * (np.asarray(base, np.float32) - prior)).astype(np.float32)
    if frame <= 0.0 or TRUST_ALPHA_CLEAN is None:
        return data, alpha, None
    zero = np.all(np.asarray(base) == 0, axis=-1)
    pin = np.float32(TRUST_ALPHA_ZERO)
    if TRUST_PIN_RADIUS is not None and zero.any():  # pinned as far as base and gradients agree it is black
        agree = trust_weights(base, dx, dy, maps, TRUST_PIN_RADIUS)[..., 0]
        pin = TRUST_ALPHA_CLEAN + agree * np.float32(TRUST_ALPHA_ZERO - TRUST_ALPHA_CLEAN)
    target = np.where(zero, pin, TRUST_ALPHA_CLEAN) / alpha
    return data, alpha, (1.0 - (1.0 - target) * frame).astype(np.float32)


def clean_weight(prior: np.ndarray, layer: Layer) -> float:
    """The frame-wide weight w_f in [0, 1] the trust rule gives this layer (TRUST_FRAME_R): 1 for a layer clean as
    a whole, 0 for a noisy one, a layer without gradients, a base that is not finite or no frame-wide part.
    ``prior``: OIDN's image of the layer at the frame's exposure (refine_layer's). model.fused's clean-layer
    average (design 25) reads it: how far a second, gradient-domain estimate may be averaged in."""
    if TRUST_FRAME_R is None or not layer.has_gradients or not np.all(np.isfinite(layer.base)):
        return 0.0
    scale = input_scale(prior)
    r = frame_disagreement(*(scaled_image(a, scale) for a in (layer.base, prior, layer.dx, layer.dy)))
    return _log_ramp(r, *TRUST_FRAME_R)


def _frame_weight(alpha: float) -> float:
    """w_f from the α trust_terms chose: the inverse of its α = REFINE_ALPHA − (REFINE_ALPHA − TRUST_ALPHA_BASE)·w_f
    (exact at w_f = 0 and 1; float rounding between)."""
    span = REFINE_ALPHA - TRUST_ALPHA_BASE
    if TRUST_FRAME_R is None or span == 0.0:
        return 0.0
    return min(max((REFINE_ALPHA - alpha) / span, 0.0), 1.0)


def _cg_budget(cg_steps: int | None, cg_tolerance: float | None) -> dict:
    """solve_l1's CG keywords for refine_layer's arguments (module settings read at call time)."""
    if cg_steps is not None:  # the pinned fixed budget; a tolerance only if one is asked for
        return {"cg_iterations": cg_steps} | ({} if cg_tolerance is None else {"cg_tolerance": cg_tolerance})
    tolerance = REFINE_CG_TOLERANCE if cg_tolerance is None else cg_tolerance
    if tolerance is None:  # no tolerance rule configured: the fixed REFINE_CG_STEPS of before
        return {"cg_iterations": REFINE_CG_STEPS}
    return {"cg_iterations": REFINE_MAX_CG_STEPS, "cg_tolerance": tolerance}


def refine_layer(name: str, prior: np.ndarray, layer: Layer, alpha: float | None = None, *,
                 preconditioner: str | None = None, cg_steps: int | None = None,
                 cg_tolerance: float | None = None, passes: int | None = None,
                 warm_start: bool | None = None, report: dict[str, float] | None = None) -> np.ndarray:
    """``prior`` (OIDN's denoise of ``layer.base``) refined by the layer's gradients when ``name`` is one of
    REFINED_LAYERS and the layer carries gradients; otherwise ``prior`` unchanged. float32 (H, W, 3), ≥ 0.
    ``preconditioner``/``cg_steps`` select the solve (None: the module's REFINE_PRECONDITIONER / REFINE_CG_STEPS,
    read at call time, the ``oidn-l1`` method's; a model trained on refinements of another solve, such as the
    fused models, passes the one it was trained with). Without ``cg_steps`` each pass runs to the relative residual
    ``cg_tolerance`` (None: REFINE_CG_TOLERANCE) in at most REFINE_MAX_CG_STEPS steps; with ``cg_steps`` and no
    ``cg_tolerance`` the solve is the fixed budget of before (solve_l1's default tolerance), bit for bit.
    ``passes`` / ``warm_start``: IRLS passes and the starting iterate (None: REFINE_ITERATIONS /
    REFINE_WARM_START), for callers that pin their whole solve (model.fused's candidates).
    ``report``: when given, ``report["clean_weight"]`` is set to the layer's w_f as the trust rule computed it here
    (what :func:`clean_weight` would recompute, to float rounding; 0 wherever the rule did not run), so a caller
    that needs both does not pay for the frame statistic twice."""
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
    warm = REFINE_WARM_START if warm_start is None else warm_start
    # A clean layer's L2 start at its non-black pixels' α (the map's smallest), not the scalar α.
    start = alpha * float(np.min(alpha_map)) if alpha_map is not None and TRUST_CLEAN_START else None
    solved, _ = solve_l1(data, dx, dy, alpha, passes or REFINE_ITERATIONS, **_cg_budget(cg_steps, cg_tolerance),
                         preconditioner=preconditioner or REFINE_PRECONDITIONER, initial=data if warm else None,
                         alpha_map=alpha_map, start_alpha=start)
    out = np.asarray(solved, np.float64) / scale
    return np.clip(out, 0.0, _F32_MAX).astype(np.float32)
