"""Held-out study behind the refinement's trust rule (model/refine.py ``trust``; docs/network.md "The trust rule"):
how far the direct layer's refinement should trust the frame's own noisy base against OIDN's image, per frame,
from what the frame carries (base, gradients, OIDN's image; no reference).

    python benchmarks/study_direct_trust.py render --seeds 84001-84004 --spp 4,16,64,256   # validation frames
    python benchmarks/study_direct_trust.py error                   # design + validation tables (cached frames)
    python benchmarks/study_direct_trust.py error --per-frame       # plus each frame's statistic r and ratios
    python benchmarks/study_direct_trust.py time                    # 1280x720 cost of the rule
    python benchmarks/study_direct_trust.py twins --cache DIR       # a second realization of each cached frame
    python benchmarks/study_direct_trust.py noise --caches DIR,...  # frame noise ratio against the best clean alpha

Two frame sets, both procedural seeds outside the evaluation's (90001, 90002) and the training range; nothing here
reads cbox or the teapot. **Design**: the ``oidn-l1`` study's frames (benchmarks/study_refine.py's cache, seeds
81001-81008 at 1, 4, 16, 64 spp), on which the rule's three constants were chosen. **Validation**: seeds
84001-84004 at 4, 16, 64 and 256 spp (256 spp: layers as clean as the least noisy frames a user renders), rendered
by this script into its own cache and not looked at while choosing. Frames: G-PT 320x240 (seed 7); references:
two independent 1024-spp Mitsuba ``path`` renders. Error: RelMSE with the references' noise removed
(model.metrics.relmse_unbiased) of the direct layer, and of the frame (direct + OIDN's indirect layer, which the
rule does not touch), as a ratio to the plain refinement (OIDN's image as the data term, α = 1: the rule before);
geometric means.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from unittest import mock

import numpy as np

CACHE_ROOT = Path(os.environ.get("GRADSEP_CACHE", Path.home() / ".cache" / "gradsep"))
DESIGN_CACHE = CACHE_ROOT / "refine-study"
VALIDATION_CACHE = CACHE_ROOT / "trust-study"
#: Rule variants measured beside the shipped constants: (TRUST_RADIUS, TRUST_R_LOW, TRUST_R_HIGH, TRUST_FRAME_R[,
#: TRUST_ALPHA_BASE]) (a missing α keeps the shipped one).
RULES: dict[str, tuple] = {
    "per pixel only (window 7, r 0.1-1)": (3, 0.1, 1.0, None),
    "per pixel only, window 17": (8, 0.1, 1.0, None),
    "per pixel only, r 0.05-0.5": (3, 0.05, 0.5, None),
    "per pixel only, r 0.2-2": (3, 0.2, 2.0, None),
    "per pixel + frame r 0.1-0.3": (3, 0.1, 1.0, (0.1, 0.3)),
    "shipped, clean-frame alpha 0.2": (3, 0.1, 1.0, (0.05, 0.2), 0.2),
    "shipped, clean-frame alpha 0.3": (3, 0.1, 1.0, (0.05, 0.2), 0.3),
    "shipped, clean-frame alpha 0.1": (3, 0.1, 1.0, (0.05, 0.2), 0.1),
}
#: Spatially varying α (session 15): on a clean layer (frame weight w_f) each pixel's data weight falls from the
#: shipped α towards this one as far as its own trust weight allows, α(x) = α_f − (α_f − α_lo)·w_f·w(x), so a
#: region whose base disagrees with its gradients keeps pinning the solve (a global low α lets its error drift).
SPATIAL_ALPHAS = (0.2, 0.1)
#: The seed of the second realization (``twins``); the cached frames are rendered with seed 7.
TWIN_SEED = 8


def _rule(constants: tuple | None) -> Callable:
    """f(denoised, layer): model.refine.refine_layer's default (the trust rule), its constants overridden."""
    from gradsep.model import refine

    names = ("TRUST_RADIUS", "TRUST_R_LOW", "TRUST_R_HIGH", "TRUST_FRAME_R", "TRUST_ALPHA_BASE")

    def run(denoised, layer):
        if constants is None:
            return refine.refine_layer("direct", denoised, layer)
        saved = {n: getattr(refine, n) for n in names}
        for n, value in zip(names, constants, strict=False):
            setattr(refine, n, value)
        try:
            return refine.refine_layer("direct", denoised, layer)
        finally:
            for n, value in saved.items():
                setattr(refine, n, value)
    return run


def _per_frame(denoised, layer):
    """Design (a): the refinement of w·base + (1 − w)·OIDN with one w per frame (the frame-wide r of
    model.refine.frame_disagreement, log-linear from 1 at 0.1 to 0 at 0.3), α = 1 − 0.5·w."""
    from gradsep.model import refine

    s = refine.input_scale(denoised)
    r = refine.frame_disagreement(*(refine.scaled_image(a, s) for a in (layer.base, denoised, layer.dx, layer.dy)))
    w = refine._log_ramp(r, 0.1, 0.3)
    data = (w * layer.base + (1 - w) * denoised).astype(np.float32)
    return refine.refine_layer("direct", data, layer, 1.0 - 0.5 * w)


def _solve_l1_alpha_map(data, dx, dy, alpha: float, m) -> np.ndarray:
    """gradsep.model.poisson.solve_l1's IRLS (mg preconditioner, the refinement's CG rule) with the data term's α
    multiplied per pixel by ``m`` (H, W): Σ α·m(x)‖I − data‖ + Σ ‖∇I − g‖. The L2 start keeps the scalar α. A
    study prototype on the solver's private pieces: m ≡ 1 gives refine_layer's solve to float rounding."""
    from gradsep.model import poisson, refine

    work = np.float32
    b, gx, gy = poisson._prepare(data, dx, dy, alpha, work)
    scale = max(float(np.abs(a).max()) for a in (b, gx, gy)) or 1.0
    for a in (b, gx, gy):
        a /= work(scale)
    m = np.ascontiguousarray(m, work)
    x = poisson._l2_core(b, gx, gy, alpha)

    class System(poisson._WeightedSystem):
        def set_weights(self, norms, reg):
            w0, wx, wy = (1.0 / (n + reg) for n in norms)
            total = sum(w.sum(dtype=np.float64) for w in (w0, wx, wy))
            s = self.dtype.type((w0.size + wx.size + wy.size) / total)
            self.w0, self.wx, self.wy = (np.ascontiguousarray(w * s, self.dtype) for w in (w0, wx, wy))
            self._a2w0 = np.ascontiguousarray(self.alpha2 * m * m * self.w0, self.dtype)
            self._aw0 = np.ascontiguousarray(self.alpha * m * self.w0, self.dtype)
            diag = self._a2w0.astype(np.float64)
            self._scatter_add(diag, self.wx, self.wy)
            self._multigrid = poisson._Multigrid(self._a2w0, self.wx, self.wy, self._gx.shape[0], diag)

    def residuals():
        (e0, ex, ey), (n0, nx, ny) = poisson._residuals_and_norms(x, b, gx, gy, alpha)
        return (e0 * m, ex, ey), (n0 * m, nx, ny)

    system = System(x.shape, alpha, np.dtype(work), "mg")
    res, norms = residuals()
    for k in range(1, refine.REFINE_ITERATIONS):
        system.set_weights(norms, reg=0.05 * 0.5 ** (k - 1) / scale)
        delta, _, _ = poisson._pcg(system, system.rhs(*res), refine.REFINE_MAX_CG_STEPS, refine.REFINE_CG_TOLERANCE)
        x += delta
        res, norms = residuals()
    return np.moveaxis(x * scale, 0, -1)


def _trust_parts(denoised, layer) -> tuple:
    """What the rule-based variants start from: (s, base, dx, dy, data, α, w_f) at mean-1 exposure (scale s),
    the trust rule's data term and α, and its frame weight w_f, from α = REFINE_ALPHA − (REFINE_ALPHA −
    TRUST_ALPHA_BASE)·w_f (the module constants as set when called)."""
    from gradsep.model import refine

    s = refine.input_scale(denoised)
    base, prior, dx, dy = (refine.scaled_image(a, s) for a in (layer.base, denoised, layer.dx, layer.dy))
    data, alpha = refine.trusted_data(base, prior, dx, dy)
    span = refine.REFINE_ALPHA - refine.TRUST_ALPHA_BASE
    return s, base, dx, dy, data, alpha, (refine.REFINE_ALPHA - alpha) / span if span else 0.0


def _spatial_rule(alpha_low: float) -> Callable:
    """f(denoised, layer): the shipped trust rule's data term, solved with a per-pixel α (SPATIAL_ALPHAS)."""
    from gradsep.model import refine

    def run(denoised, layer):
        s, base, dx, dy, data, alpha, frame = _trust_parts(denoised, layer)
        m = 1.0 - (1.0 - alpha_low / alpha) * frame * refine.trust_weights(base, dx, dy)[..., 0]
        return np.clip(_solve_l1_alpha_map(data, dx, dy, alpha, m) / s, 0.0, None).astype(np.float32)
    return run


#: Session 17: two fixes aimed at the L1 solve's own bias on clean layers (the G-PT gradients were checked
#: unbiased on 81004, docs/network.md): (reg floor c, low-frequency sigma, clean-layer α); each touches only
#: layers the trust rule calls clean (w_f > 0), a noisy layer stays the shipped refinement bit for bit.
CLEAN_FIXES: dict[str, tuple[float, float, float]] = {
    "H1: reg floor 1 x median gradient residual": (1.0, 0.0, 0.5),
    "H1a2: H1 + clean alpha 0.2": (1.0, 0.0, 0.2),
    "LF16: + w_f * G16 * (base - I)": (0.0, 16.0, 0.5),
    "LF16a2: LF16 + clean alpha 0.2": (0.0, 16.0, 0.2),
}


def _solve_l1_reg_floor(data, dx, dy, alpha: float, floor_c: float) -> np.ndarray:
    """solve_l1's IRLS as the refinement runs it (mg, the CG rule), with each pass's reg floored at ``floor_c``
    times the median RGB norm of the L2 start's gradient residuals: residuals within the gradients' own noise are
    weighted alike (L2, unbiased) and only the outliers get L1's down-weighting (a Huber-like norm)."""
    from gradsep.model import poisson, refine

    work = np.float32
    b, gx, gy = poisson._prepare(data, dx, dy, alpha, work)
    scale = max(float(np.abs(a).max()) for a in (b, gx, gy)) or 1.0
    for a in (b, gx, gy):
        a /= work(scale)
    x = poisson._l2_core(b, gx, gy, alpha)
    system = poisson._WeightedSystem(x.shape, alpha, np.dtype(work), "mg")
    res, norms = poisson._residuals_and_norms(x, b, gx, gy, alpha)
    floor = floor_c * float(np.median(np.concatenate([norms[1].ravel(), norms[2].ravel()])))
    for k in range(1, refine.REFINE_ITERATIONS):
        system.set_weights(norms, reg=max(0.05 * 0.5 ** (k - 1) / scale, floor))
        delta, _, _ = poisson._pcg(system, system.rhs(*res), refine.REFINE_MAX_CG_STEPS, refine.REFINE_CG_TOLERANCE)
        x += delta
        res, norms = poisson._residuals_and_norms(x, b, gx, gy, alpha)
    return np.moveaxis(x * scale, 0, -1)


def _clean_fix(floor_c: float, sigma: float, alpha_base: float) -> Callable:
    """f(denoised, layer): the trust rule at clean-layer α ``alpha_base``, with CLEAN_FIXES' changes on clean
    layers."""
    from scipy.ndimage import gaussian_filter

    from gradsep.model import refine

    def run(denoised, layer):
        saved = refine.TRUST_ALPHA_BASE
        refine.TRUST_ALPHA_BASE = alpha_base
        try:
            s, base, dx, dy, data, alpha, frame = _trust_parts(denoised, layer)
            if frame <= 0.0:
                return refine.refine_layer("direct", denoised, layer)
            if floor_c > 0.0:
                image = _solve_l1_reg_floor(data, dx, dy, alpha, floor_c)
            else:
                image = np.asarray(refine.refine_layer("direct", denoised, layer), np.float64) * s
            if sigma > 0.0:
                low = gaussian_filter(np.asarray(base, np.float64) - image, sigma=(sigma, sigma, 0), mode="nearest")
                image = image + frame * low
        finally:
            refine.TRUST_ALPHA_BASE = saved
        return np.clip(image / s, 0.0, None).astype(np.float32)
    return run


#: Session 17, design 13: a lower α only at occlusion boundaries. On the direct-only teapot nearly all of the gap
#: to ``l1`` sits on its silhouette pixels (1.3 % of the pixels), where the base's noise is the coverage's
#: (hit or miss per sample) and the gradients carry the edge; the held-out frames that punish a global lower α lose
#: it at *shading* edges instead (exactly black shadow pixels beside bright ones), which this map leaves alone.
#: Name -> the α at edge pixels (clean layers only, w_f > 0; elsewhere and on noisy layers the shipped rule).
EDGE_ALPHAS = {"G02: occlusion edges alpha 0.2": 0.2, "G01: occlusion edges alpha 0.1": 0.1}
#: What score_set is scoring (the variants that read the frame's features look here).
_CONTEXT: dict[str, object] = {}


def occlusion_edges(depth: np.ndarray, jump: float = 0.1) -> np.ndarray:
    """(H, W) bool: both pixels of every 4-neighbour pair across an occlusion boundary: one sees nothing (depth
    0) and the other something, or their depths differ by more than ``jump`` of the nearer."""
    d = np.asarray(depth, np.float64)
    edge = np.zeros(d.shape, bool)
    for a, b in ((d[:, 1:], d[:, :-1]), (d[1:], d[:-1])):
        miss = (a == 0) != (b == 0)
        both = (a > 0) & (b > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            far = both & (np.abs(a - b) > jump * np.minimum(a, b))
        e = miss | far
        if a.shape[1] < d.shape[1]:
            edge[:, 1:] |= e
            edge[:, :-1] |= e
        else:
            edge[1:] |= e
            edge[:-1] |= e
    return edge


def _edge_rule(alpha_edge: float) -> Callable:
    """f(denoised, layer): the shipped trust rule, with the data weight at occlusion-edge pixels lowered to
    ``alpha_edge`` on a clean layer (per-pixel α: _solve_l1_alpha_map)."""
    from gradsep.model import refine

    def run(denoised, layer):
        features = _CONTEXT.get("features")
        s, _, dx, dy, data, alpha, frame = _trust_parts(denoised, layer)
        if features is None or frame <= 0.0:
            return refine.refine_layer("direct", denoised, layer)
        edges = occlusion_edges(features.depth)
        m = np.where(edges, 1.0 - (1.0 - alpha_edge / alpha) * frame, 1.0)
        return np.clip(_solve_l1_alpha_map(data, dx, dy, alpha, m) / s, 0.0, None).astype(np.float32)
    return run


#: Session 17, design 14: design 1's lower clean-layer α, except at pixels whose base is exactly 0 (no sample found
#: light there), which keep the shipped α (or are pinned harder): design 1 loses its held-out frames by leaking the
#: bright side of a shadow edge into black shadow pixels, where the frame's relative error weighs every unit
#: 100-fold. Name -> (α elsewhere, the zero pixels' α) on clean layers.
ZERO_KEEP = {"Z02: alpha 0.2, zero-base pixels keep 0.5": (0.2, 0.5),
             "Z02p: alpha 0.2, zero-base pixels at 2": (0.2, 2.0)}


def _zero_keep_rule(alpha_low: float, alpha_zero: float) -> Callable:
    """f(denoised, layer): the shipped trust rule, and on a clean layer a per-pixel α falling from the shipped one
    to ``alpha_low`` (as far as w_f goes), but to ``alpha_zero`` where the base is exactly 0 in every channel."""
    from gradsep.model import refine

    def run(denoised, layer):
        s, _, dx, dy, data, alpha, frame = _trust_parts(denoised, layer)
        if frame <= 0.0:
            return refine.refine_layer("direct", denoised, layer)
        zero = np.all(np.asarray(layer.base) == 0, axis=-1)
        target = np.where(zero, alpha_zero, alpha_low) / alpha
        m = 1.0 - (1.0 - target) * frame
        return np.clip(_solve_l1_alpha_map(data, dx, dy, alpha, m) / s, 0.0, None).astype(np.float32)
    return run


#: Session 18, designs 15-18 (fixed before any was scored; docs/network.md "Designs 15-18"). Silhouettes against
#: nothing: on a clean layer, both pixels of every 4-neighbour pair where the camera ray missed on exactly one side
#: (the frame's depth 0); "unpin" gives them the clean α instead of the zero pin, "band" does that on the silhouette
#: grown by one pixel and pulls the data term to the base there (by w_f). "start": model.refine.TRUST_CLEAN_START,
#: the clean layer's L2 start at its clean α (design 17, adopted: the shipped rule since). Name -> (mode, start).
SILHOUETTE_DESIGNS = {"S-unpin: silhouette pixels not pinned": ("unpin", False),
                      "S-band: silhouette band, base data, not pinned": ("band", False),
                      "C-start: clean layers start at the clean alpha": (None, True),
                      "C+S: clean start and silhouettes not pinned": ("unpin", True)}


def silhouette_mask(depth: np.ndarray, grow: int = 0) -> np.ndarray:
    """(H, W) bool: both pixels of every 4-neighbour pair where the camera ray missed (depth 0) on exactly one
    side, grown by ``grow`` pixels (a (2·grow+1)² square); all False for a frame with no missed pixel."""
    from scipy.ndimage import maximum_filter

    miss = np.asarray(depth) == 0
    edge = np.zeros(miss.shape, bool)
    across_x, across_y = miss[:, 1:] != miss[:, :-1], miss[1:] != miss[:-1]
    edge[:, 1:] |= across_x
    edge[:, :-1] |= across_x
    edge[1:] |= across_y
    edge[:-1] |= across_y
    return maximum_filter(edge, size=2 * grow + 1, mode="nearest") if grow > 0 and edge.any() else edge


def _silhouette_rule(mode: str | None, start: bool) -> Callable:
    """f(denoised, layer): model.refine.refine_layer with TRUST_CLEAN_START = ``start`` and, for ``mode``, its
    trust_terms wrapped so that a clean layer's silhouette pixels (the frame's depth) are treated as above."""
    from gradsep.model import refine

    original = refine.trust_terms

    def terms(base, prior, dx, dy):
        data, alpha, m = original(base, prior, dx, dy)
        features = _CONTEXT.get("features")
        if m is None or features is None:
            return data, alpha, m
        edge = silhouette_mask(features.depth, grow=int(mode == "band"))
        clean = float(np.min(m))  # the clean factor (the zero pin is above it)
        m = np.where(edge, clean, m).astype(np.float32)
        if mode == "band":
            frame = (1.0 - clean) / (1.0 - refine.TRUST_ALPHA_CLEAN / alpha)  # w_f, from m = 1 − (1 − 0.2/α)·w_f
            pull = np.float32(frame) * edge[..., None]
            data = (data + pull * (np.asarray(base, np.float32) - data)).astype(np.float32)
        return data, alpha, m

    def run(denoised, layer):  # (measured with session 17's full zero pin)
        with mock.patch.multiple(refine, TRUST_CLEAN_START=start, TRUST_PIN_RADIUS=None,
                                 trust_terms=original if mode is None else terms):
            return refine.refine_layer("direct", denoised, layer)
    return run


#: Session 18, round 2 (designs 19-21, fixed before scoring; docs/network.md "Designs 15-18"): on the teapot the
#: shipped rule differs from ``l1`` by the zero pins and the solve's budget alone. 19: a clean layer solved with
#: ``l1``'s budget (DCT preconditioner, L1_CG_STEPS steps per pass to 1e-3) instead of the refinement's; 20: the
#: silhouettes of design 15 unpinned only on a layer clean as a whole (w_f = 1); 21: both.
ROUND2 = {"R19: clean layers with l1's CG budget": (True, False),
          "R20: silhouettes unpinned where w_f = 1": (False, True),
          "R21: R19 + R20": (True, True)}


def _round2_rule(l1_budget: bool, full_unpin: bool) -> Callable:
    from gradsep.model import refine
    from gradsep.model.poisson import L1_CG_STEPS

    original = refine.trust_terms

    def terms(base, prior, dx, dy):
        data, alpha, m = original(base, prior, dx, dy)
        features = _CONTEXT.get("features")
        if m is None or features is None or alpha != refine.TRUST_ALPHA_BASE:  # w_f < 1
            return data, alpha, m
        edge = silhouette_mask(features.depth)
        return data, alpha, np.where(edge, float(np.min(m)), m).astype(np.float32)

    def run(denoised, layer):
        s = refine.input_scale(denoised)
        clean = refine.trust_terms(*(refine.scaled_image(a, s) for a in (layer.base, denoised, layer.dx,
                                                                            layer.dy)))[2] is not None
        budget = {"preconditioner": "dct", "cg_steps": L1_CG_STEPS, "cg_tolerance": 1e-3} if l1_budget and clean \
            else {}
        with mock.patch.multiple(refine, TRUST_PIN_RADIUS=None, trust_terms=terms if full_unpin else original):
            return refine.refine_layer("direct", denoised, layer, **budget)
    return run


#: Session 18, round 3 (design 22, fixed before scoring; docs/network.md "Designs 15-18", round 3; shipped as
#: model.refine.TRUST_PIN_RADIUS, this prototype reproduces it): a zero pixel's pin only as far as the
#: base agrees with the sampled gradients around it (3×3 window, the trust rule's r and ramp), so a black pixel that
#: the gradients say is partly lit (a hard shadow or silhouette edge crossing the pixel, missed by every primal
#: sample) takes the clean α, and a true umbra (base and gradients agree it is black) stays pinned.
AGREEING_PIN = "R22: zero pixels pinned as far as base and gradients agree"


def _scaled_pin(keep: Callable) -> Callable:
    """model.refine.trust_terms with each exactly-black pixel's pin (its α factor above the clean layer's) scaled by
    ``keep(base, dx, dy)`` (H, W) in [0, 1]: the shape of designs 22 and 24."""
    from gradsep.model import refine

    original = refine.trust_terms

    def terms(base, prior, dx, dy):
        data, alpha, m = original(base, prior, dx, dy)
        zero = np.all(np.asarray(base) == 0, axis=-1)
        if m is None or not zero.any():
            return data, alpha, m
        clean = float(np.min(m))
        return data, alpha, np.where(zero, clean + keep(base, dx, dy) * (m - clean), m).astype(np.float32)
    return terms


def _agreeing_pin_rule() -> Callable:
    from gradsep.model import refine

    # the trust rule's ramp in a 3×3 window
    terms = _scaled_pin(lambda base, dx, dy: refine.trust_weights(base, dx, dy, radius=1)[..., 0])

    def run(denoised, layer):  # the prototype on session 17's full pin (what design 22 was measured as)
        with mock.patch.multiple(refine, TRUST_PIN_RADIUS=None, trust_terms=terms):
            return refine.refine_layer("direct", denoised, layer)
    return run


#: Session 19, design 23 (fixed before scoring; docs/network.md "Design 23"): the refinement's IRLS regulariser.
#: solve_l1 weights each residual by 1/(‖e‖ + reg_k), reg_k = reg_init·0.5^(k−1), reg_init 0.05 by default, in the
#: units of its input: `l1` solves in radiance units, the refinement at mean-1 exposure, so on a dim layer `l1`'s
#: regulariser is many times the refinement's relative one. name -> (reg_init at mean-1 exposure, clean layers only).
REG_DESIGNS = {"R23a: clean layers, IRLS reg 0.2": (0.2, True),
               "R23b: clean layers, IRLS reg 0.5": (0.5, True),
               "R23c: clean layers, IRLS reg 1.0": (1.0, True),
               "R23d: every refined layer, IRLS reg 0.5": (0.5, False)}


def _reg_rule(reg_init: float, clean_only: bool) -> Callable:
    from gradsep.model import refine

    original = refine.solve_l1

    def solve(*args, **kwargs):
        if not clean_only or kwargs.get("alpha_map") is not None:  # a clean layer carries its α map
            kwargs["reg_init"] = reg_init
        return original(*args, **kwargs)

    def run(denoised, layer):
        with mock.patch.object(refine, "solve_l1", solve):
            return refine.refine_layer("direct", denoised, layer)
    return run


#: Session 19, design 24 (fixed before scoring; docs/network.md "Design 24"): a zero pixel keeps its pin only as
#: far as its own gradients say it is black: q = max(ι, 0) / s from its lit neighbours (implied_ratio), full pin at
#: q ≤ q_lo, none at q ≥ q_hi, log-linear between. name -> (q_lo, q_hi).
IMPLIED_DESIGNS = {"R24a: pin kept as far as the implied value says black (0.1, 0.5)": (0.1, 0.5),
                   "R24b: pin kept as far as the implied value says black (0.2, 0.5)": (0.2, 0.5),
                   "R24c: pin kept as far as the implied value says black (0.1, 0.3)": (0.1, 0.3)}


def implied_ratio(base: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Per pixel, q = max(ι, 0) / s: ι the value its four gradients imply from each neighbour (base(n) ∓ g),
    weighted by the neighbours' luminance L_n, s = Σ L_n² / Σ L_n; 0 where no neighbour is lit. (H, W) float32."""
    lum, gx, gy = (np.asarray(a, np.float64).mean(axis=-1) for a in (base, dx, dy))
    weight = np.zeros_like(lum)
    value = np.zeros_like(lum)
    level = np.zeros_like(lum)
    for w_slice, n_slice, implied in (
            ((slice(None), slice(None, -1)), (slice(None), slice(1, None)), lum[:, 1:] - gx[:, :-1]),   # right
            ((slice(None), slice(1, None)), (slice(None), slice(None, -1)), lum[:, :-1] + gx[:, :-1]),  # left
            ((slice(None, -1), slice(None)), (slice(1, None), slice(None)), lum[1:] - gy[:-1]),         # down
            ((slice(1, None), slice(None)), (slice(None, -1), slice(None)), lum[:-1] + gy[:-1])):       # up
        n = lum[n_slice]
        weight[w_slice] += n
        value[w_slice] += n * implied
        level[w_slice] += n * n
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.maximum(value, 0.0) / level
    return np.nan_to_num(q, nan=0.0, posinf=0.0).astype(np.float32)


def _implied_pin_rule(q_lo: float, q_hi: float) -> Callable:
    from gradsep.model import refine

    def keep(base, dx, dy):  # 1 at q ≤ q_lo, 0 at q ≥ q_hi, log-linear between
        q = np.maximum(implied_ratio(base, dx, dy), 1e-30)
        return np.clip(np.log(q_hi / q) / math.log(q_hi / q_lo), 0.0, 1.0)

    terms = _scaled_pin(keep)

    def run(denoised, layer):
        with mock.patch.object(refine, "trust_terms", terms):
            return refine.refine_layer("direct", denoised, layer)
    return run


#: Session 20, design 25 (docs/network.md "Design 25"; model/fused.py CLEAN_AVERAGE, shipped in ``fused``): on a
#: clean layer (w_f > 0) the shipped refinement is averaged with the ``network`` method's image (models/direct.onnx)
#: where the two agree: + ½·w_f·g(ρ)·(net − refined), ρ the pixel's relative squared difference at the mean-1
#: exposure (box-filtered over a (2·window+1)² window for window > 0), g log-linear from 1 at lo to 0 at hi.
#: name -> (lo, hi, window), None: ungated. The first entry is the shipped design; the rest the design-set grid it
#: was chosen from (all windows with ε 1e-4 gave the same as ε 1e-2 to 3 digits and are not listed).
CLEAN_AVERAGE_DESIGNS: dict[str, tuple[float, float, int] | None] = {
    "R25: clean layer averaged with the network where they agree (0.01, 0.1)": (0.01, 0.1, 0),
    "R25 grid: (0.001, 0.01)": (0.001, 0.01, 0),
    "R25 grid: (0.003, 0.03)": (0.003, 0.03, 0),
    "R25 grid: window 1, (0.001, 0.01)": (0.001, 0.01, 1),
    "R25 grid: window 1, (0.01, 0.1)": (0.01, 0.1, 1),
    "R25 grid: window 3, (0.001, 0.01)": (0.001, 0.01, 3),
    "R25 grid: window 3, (0.01, 0.1)": (0.01, 0.1, 3),
    "R25 grid: ungated (½·w_f everywhere)": None,
}
_NETWORK: dict[str, object] = {}


#: Session 20, design 26 (docs/network.md "Design 26", rejected): design 25 with another second estimate, a direct
#: network of the same architecture and recipe trained on studio-family pairs. name -> the model file (relative to
#: the repository; ``$GRADSEP_STUDY_SECOND`` overrides it). Not shipped: the variant is scored only where the file
#: was made (``gradsep train --data data/n2n16-studio --layer direct --minutes 30 -o runs/s20-studio-direct``, then
#: ``gradsep export runs/s20-studio-direct -o models/fused/clean-direct.onnx``).
SECOND_MODELS: dict[str, str] = {
    "R26: clean average with a studio-trained second network": "models/fused/clean-direct.onnx"}


def _second_network(path: str | None) -> object:
    """The ``network`` reconstructor of the second estimate: models/ (the shipped direct model) or one file."""
    from gradsep.model.infer import NetworkReconstructor, load_model

    key = path or "models"
    if key not in _NETWORK:
        root = Path(__file__).resolve().parents[1]
        _NETWORK[key] = (NetworkReconstructor.load(root / "models") if path is None
                         else NetworkReconstructor({"direct": load_model(root / path, "direct")}))
    return _NETWORK[key]


def _refined_clean_second(denoised, layer, model: str | None) -> tuple[np.ndarray, float, np.ndarray | None]:
    """(the shipped refinement, the layer's clean weight w_f, the second network's image or None where w_f = 0)."""
    from gradsep.model import refine

    refined = refine.refine_layer("direct", denoised, layer)
    clean = refine.clean_weight(denoised, layer)
    if clean <= 0.0:
        return refined, clean, None
    return refined, clean, _second_network(model).reconstruct_layer("direct", layer, _CONTEXT["features"])


def _clean_average_rule(gate: tuple[float, float, int] | None, model: str | None = None) -> Callable:
    from scipy.ndimage import uniform_filter

    from gradsep.model import fused
    from gradsep.model.oidn import input_scale

    def run(denoised, layer):
        refined, clean, net = _refined_clean_second(denoised, layer, model)
        if net is None:
            return refined
        s = input_scale(denoised)
        if gate is None:
            g = np.ones(refined.shape[:2], np.float32)
        elif gate[2] == 0:
            g = fused.agreement_weights(refined, net, s, gate[:2])
        else:
            a, b = refined.astype(np.float64) * s, net.astype(np.float64) * s
            size = 2 * gate[2] + 1
            num = uniform_filter(np.mean((a - b) ** 2, -1), size, mode="nearest")
            den = uniform_filter(np.mean(((a + b) / 2) ** 2, -1), size, mode="nearest") + fused.CLEAN_AVERAGE_EPSILON
            lo, hi = gate[:2]
            g = np.clip(np.log(hi / np.maximum(num / den, 1e-300)) / math.log(hi / lo), 0.0, 1.0)
        return refined + (0.5 * clean * g)[..., None].astype(np.float32) * (net - refined)
    return run


#: Design 25's follow-ups (session 20, not shipped): the same per-pixel gate (0.01, 0.1), with the ``l1`` method's
#: image as a third estimate (⅓ each, each gated against the refinement), or ⅔ of the weight on the network.
CLEAN_AVERAGE_FOLLOWUPS = ("R25 follow-up: three-way with l1 (1/3 each)", "R25 follow-up: network weight 2/3")


def _clean_average_followup(name: str) -> Callable:
    from gradsep.model import fused
    from gradsep.model.oidn import input_scale
    from gradsep.model.poisson import solve_l1
    from gradsep.model.policy import DEFAULT_ALPHA

    def run(denoised, layer):
        refined, clean, net = _refined_clean_second(denoised, layer, None)
        if net is None:
            return refined
        s = input_scale(denoised)
        g_net = fused.agreement_weights(refined, net, s, (0.01, 0.1))[..., None]
        if "three-way" not in name:
            return refined + np.float32(2 / 3 * clean) * g_net * (net - refined)
        l1 = solve_l1(layer.base, layer.dx, layer.dy, DEFAULT_ALPHA)[0]
        g_l1 = fused.agreement_weights(refined, l1, s, (0.01, 0.1))[..., None]
        return refined + np.float32(clean / 3) * (g_net * (net - refined) + g_l1 * (l1 - refined))
    return run


#: Session 22, design 28 (docs/network.md "Design 28"): design 25's average with the second estimate passed once
#: more through OIDN (the frame's aux, the ``oidn`` method's setting). The network's image keeps a residual noise
#: that the Poisson solve leaves (low-frequency blotches and single-pixel spikes); OIDN, fed the albedo and normal,
#: may remove what of it the features explain. Variants: which image is re-denoised, and whether the gate compares
#: the refinement with the re-denoised image or with the network's own.
OIDN_SECOND_DESIGNS = ("R28: OIDN(network) as the second estimate", "R28: OIDN(network), gated on the network",
                       "R28: OIDN(network) alone on clean layers")


def _oidn_second_rule(name: str) -> Callable:
    from gradsep.model import fused
    from gradsep.model.oidn import input_scale

    def run(denoised, layer):
        refined, clean, net = _refined_clean_second(denoised, layer, None)
        if net is None:
            return refined
        den, aux = _CONTEXT["denoiser"], _CONTEXT["aux"]
        second = np.maximum(den.denoise(net, aux), 0.0).astype(np.float32)
        if "alone" in name:
            return refined + np.float32(clean) * (second - refined)
        s = input_scale(denoised)
        gated = net if "gated on the network" in name else second
        g = fused.agreement_weights(refined, gated, s, (0.01, 0.1))[..., None]
        return refined + np.float32(0.5 * clean) * g * (second - refined)
    return run


def _without_clean_map(run: Callable) -> Callable:
    """``run`` with the rule as it was before session 17 (model.refine.TRUST_ALPHA_CLEAN None: no per-pixel α on
    clean layers), so that the variants measured against that rule still measure what they did."""
    from gradsep.model import refine

    def wrapped(denoised, layer):
        with mock.patch.object(refine, "TRUST_ALPHA_CLEAN", None):
            return run(denoised, layer)
    return wrapped


def variants() -> dict[str, Callable]:
    """name -> f(denoised direct image, direct layer); 'plain refinement' is the ratio's denominator. Every variant
    but 'trust rule (shipped)' and session 18's (BEFORE_18, SILHOUETTE_DESIGNS) runs on the rule before session
    17 (its own changes on top); the Z02p prototype is what session 17's rule became, written out on the solver's
    internals (the two agree to float rounding)."""
    from gradsep.model import refine
    from gradsep.model.poisson import solve_l1
    from gradsep.model.policy import DEFAULT_ALPHA

    out: dict[str, Callable] = {
        "plain refinement (before)": lambda d, layer: refine.refine_layer("direct", d, layer, refine.REFINE_ALPHA),
        "oidn": lambda d, layer: d,
        "l1 (base + gradients)": lambda d, layer: solve_l1(layer.base, layer.dx, layer.dy, DEFAULT_ALPHA)[0],
        "trust rule before session 17 (no clean-layer alpha map)": _rule(None),
        "per-frame rule only (design a)": _per_frame,
    }
    out.update({k: _rule(v) for k, v in RULES.items()})
    out.update({f"spatial alpha {a} (per-pixel trust)": _spatial_rule(a) for a in SPATIAL_ALPHAS})
    out.update({k: _clean_fix(*v) for k, v in CLEAN_FIXES.items()})
    out.update({k: _edge_rule(v) for k, v in EDGE_ALPHAS.items()})
    out.update({k: _zero_keep_rule(*v) for k, v in ZERO_KEEP.items()})
    out = {k: _without_clean_map(v) for k, v in out.items()}
    out["trust rule (shipped)"] = _rule(None)
    out[BEFORE_18] = _silhouette_rule(None, False)
    out.update({k: _silhouette_rule(*v) for k, v in SILHOUETTE_DESIGNS.items()})
    out.update({k: _round2_rule(*v) for k, v in ROUND2.items()})
    out[AGREEING_PIN] = _agreeing_pin_rule()
    out.update({k: _reg_rule(*v) for k, v in REG_DESIGNS.items()})
    out.update({k: _implied_pin_rule(*v) for k, v in IMPLIED_DESIGNS.items()})
    out.update({k: _clean_average_rule(v) for k, v in CLEAN_AVERAGE_DESIGNS.items()})
    out.update({k: _clean_average_followup(k) for k in CLEAN_AVERAGE_FOLLOWUPS})
    out.update({k: _oidn_second_rule(k) for k in OIDN_SECOND_DESIGNS})
    root = Path(__file__).resolve().parents[1]
    for name, model in SECOND_MODELS.items():  # design 26 was rejected: its model is not shipped, so only where made
        model = os.environ.get("GRADSEP_STUDY_SECOND", model)
        if (root / model).is_file():
            out[name] = _clean_average_rule((0.01, 0.1, 0), model)
    return out


def _frames(cache: Path):
    """(label, frame path, reference 1, reference 2) of every cached frame with two references."""
    for folder in sorted(p for p in cache.glob("procedural-*") if p.is_dir()):
        refs = sorted(folder.glob("ref-*.npz"))
        if len(refs) < 2:
            continue
        r1, r2 = (np.load(p) for p in refs[:2])
        for path in sorted(folder.glob("gpt-*.exr"), key=lambda p: int(p.stem.split("-")[1])):
            yield f"{folder.name.removeprefix('procedural-')} {path.stem.removeprefix('gpt-')} spp", path, r1, r2


BASELINE = "plain refinement (before)"
#: The rule before session 18's clean start (design 17): the baseline of designs 15-18.
BEFORE_18 = "trust rule before session 18 (scalar L2 start)"
#: Always scored: the ratios' denominator (--baseline picks it) and the per-frame table's columns.
ALWAYS = (BASELINE, "oidn", "l1 (base + gradients)", "trust rule (shipped)",
          "trust rule before session 17 (no clean-layer alpha map)")


def score_set(cache: Path, per_frame: bool, only: tuple[str, ...] = (), baseline: str = BASELINE,
              ) -> tuple[dict[str, dict[str, list[float]]], list[str]]:
    """({'direct'|'frame': {variant: [ratio to ``baseline`` per frame]}}, the scored frames' labels) over one
    cache's frames (those with a nonzero ``baseline`` error); ``only``: substrings of the variants to score beside
    ALWAYS (empty: all of them)."""
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.oidn import METHOD_SETTING, Denoiser, input_scale
    from gradsep.model.preprocess import scaled_image
    from gradsep.model.refine import frame_disagreement, trust_weights

    den = Denoiser(METHOD_SETTING)
    runs = {k: v for k, v in variants().items()
            if not only or k in ALWAYS or k == baseline or any(o in k for o in only)}
    ratios: dict[str, dict[str, list[float]]] = {"direct": {}, "frame": {}}
    labels: list[str] = []
    for label, path, r1, r2 in _frames(cache):
        frame = read_frame(str(path))
        _CONTEXT["features"] = frame.features
        aux = den.prefilter(frame.features) if frame.features is not None else None
        _CONTEXT["denoiser"], _CONTEXT["aux"] = den, aux
        layer = frame.layers["direct"]
        denoised = den.denoise(layer.base, aux)
        indirect = den.denoise(frame.layers["indirect"].base, aux)
        scores = {}
        for name, run in runs.items():
            image = run(denoised, layer)
            scores[name] = (relmse_unbiased(image, r1["direct"], r2["direct"]),
                            relmse_unbiased(image + indirect, r1["total"], r2["total"]))
        before = scores[baseline]
        if not (before[0] > 0 and before[1] > 0):  # a frame with nothing to get wrong (black references)
            print(f"{label}: skipped, {baseline}'s RelMSE is 0 (direct {before[0]:.3g}, frame {before[1]:.3g})")
            continue
        labels.append(label)
        for name, (d, t) in scores.items():
            ratios["direct"].setdefault(name, []).append(d / before[0])
            ratios["frame"].setdefault(name, []).append(t / before[1])
        if per_frame:
            s = input_scale(denoised)
            scaled = [scaled_image(a, s) for a in (layer.base, denoised, layer.dx, layer.dy)]
            w = trust_weights(scaled[0], *scaled[2:])
            r = frame_disagreement(*scaled)
            shipped = scores["trust rule (shipped)"]
            print(f"| {label} | {r:.3g} | {float(w.mean()):.2f} | {before[0]:.3g} | {shipped[0] / before[0]:.3f} | "
                  f"{scores['oidn'][0] / before[0]:.2f} | {scores['l1 (base + gradients)'][0] / before[0]:.2f} | "
                  f"{shipped[1] / before[1]:.3f} |", flush=True)
    den.close()
    return ratios, labels


def _geo(values: list[float]) -> float:
    return math.exp(sum(math.log(max(v, 1e-12)) for v in values) / len(values))


def error(caches: dict[str, Path], per_frame: bool, only: tuple[str, ...] = (), baseline: str = BASELINE) -> None:
    for set_name, cache in caches.items():
        print(f"\n## {set_name}: {cache}\n")
        if per_frame:
            print("| frame | frame r | mean per-pixel w | plain refinement RelMSE (direct) | rule / plain (direct) | "
                  "oidn / plain | l1 / plain | rule / plain (frame) |\n|---|---:|---:|---:|---:|---:|---:|---:|")
        ratios, labels = score_set(cache, per_frame, only, baseline)
        spps = sorted({int(label.split()[1]) for label in labels})
        print(f"\n{len(labels)} frames; RelMSE / {baseline}'s (geometric mean, worst, frames better)\n")
        print("| variant | direct: geo | worst | better | frame: geo | worst | better | "
              + " | ".join(f"frame @{s}" for s in spps) + " |")
        print("|---|" + "---:|" * (6 + len(spps)))
        for name in ratios["direct"]:
            d, t = ratios["direct"][name], ratios["frame"][name]
            by_spp = [_geo([v for v, lab in zip(t, labels, strict=True) if int(lab.split()[1]) == s]) for s in spps]
            print(f"| {name} | {_geo(d):.3f} | {max(d):.2f} | {sum(v < 1 for v in d)}/{len(d)} | {_geo(t):.3f} | "
                  f"{max(t):.2f} | {sum(v < 1 for v in t)}/{len(t)} | " + " | ".join(f"{g:.3f}" for g in by_spp)
                  + " |", flush=True)


def time_rule(width: int, height: int, repeats: int) -> None:
    """Cost of the rule on one 1280x720 direct layer: its data term (weights and mix) alone, and the refinement
    with and without the rule (the mixed data term can change the IRLS/CG work), synthetic noisy data, medians."""
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_oidn import median_seconds

    from gradsep.model.frame import Layer, forward_differences

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:height, 0:width]
    truth = (1.0 + 0.5 * np.sin(xx / 37.0)[..., None] * np.cos(yy / 23.0)[..., None]
             * np.array([1.0, 0.8, 0.6])).astype(np.float32)
    truth[height // 3: height // 2, width // 4: width // 2] *= 0.2  # a shadow edge
    dx, dy = forward_differences(truth)
    for noise in (0.001, 0.3):  # a clean layer (the rule mixes the base in) and a noisy one (it does not)
        base = (truth * (1 + noise * rng.standard_normal(truth.shape))).clip(0).astype(np.float32)
        _time_one(Layer(base, dx, dy), (0.5 * truth + 0.5 * base).astype(np.float32), repeats, median_seconds,
                  f"{width}x{height}, base noise {noise}")


def _time_one(layer, prior: np.ndarray, repeats: int, median_seconds: Callable, label: str) -> None:
    from gradsep.model import refine

    s = refine.input_scale(prior)
    base, dx, dy = (refine.scaled_image(a, s) for a in (layer.base, layer.dx, layer.dy))
    stat = median_seconds(lambda: refine.trusted_data(base, refine.scaled_image(prior, s), dx, dy), repeats)
    plain = median_seconds(lambda: refine.refine_layer("direct", prior, layer, refine.REFINE_ALPHA), repeats)
    rule = median_seconds(lambda: refine.refine_layer("direct", prior, layer), repeats)
    print(f"{label}: mean base weight {float(refine.trust_weights(base, dx, dy).mean()):.2f}; the rule's data term "
          f"{stat:.3f} s; refinement {plain:.3f} s plain, {rule:.3f} s with the rule (medians of {repeats})",
          flush=True)


def twins(cache: Path) -> None:
    """Render a second, independent realization (seed TWIN_SEED) of every cached frame as twin-SPP.exr."""
    from study_refine import SIZE

    from gradsep.model.frame import write_frame
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    for folder in sorted(p for p in cache.glob("procedural-*") if p.is_dir()):
        loaded = load_scene(f"procedural:{folder.name.removeprefix('procedural-')}", width=SIZE[0], height=SIZE[1])
        for path in sorted(folder.glob("gpt-*.exr")):
            out = folder / f"twin-{path.stem.removeprefix('gpt-')}.exr"
            if not out.is_file():
                write_frame(out, render_frame(loaded, spp=int(path.stem.removeprefix("gpt-")), seed=TWIN_SEED))
        print(f"{folder}: twins cached", flush=True)


def noise(caches: list[Path]) -> None:
    """Per clean frame (w_f > 0): the frame-wide noise of the direct layer's base and gradients, estimated from the
    frame and its twin (E(a₁ − a₂)²/2, weighted like frame_disagreement), the α that ratio implies for
    independent Gaussian noise, √(σ²_g / σ²_b), against how a lower clean-frame α (0.2) does there (direct RelMSE
    / the shipped rule's). If the noise decided the best α, frames with a small √(σ²_g/σ²_b) would prefer 0.2."""
    from gradsep.model import refine
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.oidn import METHOD_SETTING, Denoiser, input_scale
    from gradsep.model.preprocess import scaled_image

    den = Denoiser(METHOD_SETTING)
    low = _rule((3, 0.1, 1.0, (0.05, 0.2), 0.2))
    print("| frame | w_f | √(σ²_g/σ²_b) | α 0.2 / shipped (direct) |\n|---|---:|---:|---:|")
    pairs = []
    for cache in caches:
        for label, path, r1, r2 in _frames(cache):
            twin = path.with_name(path.name.replace("gpt-", "twin-"))
            if not twin.is_file():
                continue
            frame, other = read_frame(str(path)), read_frame(str(twin))
            layer, layer2 = frame.layers["direct"], other.layers["direct"]
            denoised = den.denoise(layer.base, den.prefilter(frame.features) if frame.features else None)
            s = input_scale(denoised)
            b1, b2, x1, x2, y1, y2, prior = (scaled_image(a, s) for a in (
                layer.base, layer2.base, layer.dx, layer2.dx, layer.dy, layer2.dy, denoised))
            wf = refine._log_ramp(refine.frame_disagreement(b1, prior, x1, y1), *refine.TRUST_FRAME_R)
            if wf == 0.0:
                continue
            omega = 1.0 / (np.square(prior.mean(axis=-1)) + np.float32(1e-2))
            vb = float(np.sum(omega * np.square(b1 - b2).mean(axis=-1)))
            vg = float(np.sum(omega * (np.square(x1 - x2) + np.square(y1 - y2)).mean(axis=-1))) / 2.0
            shipped = relmse_unbiased(refine.refine_layer("direct", denoised, layer), r1["direct"], r2["direct"])
            ratio = relmse_unbiased(low(denoised, layer), r1["direct"], r2["direct"]) / shipped
            pairs.append((math.sqrt(vg / vb), ratio))
            print(f"| {cache.name} {label} | {wf:.2f} | {pairs[-1][0]:.3f} | {ratio:.3f} |", flush=True)
    den.close()
    if len(pairs) > 2:
        from scipy.stats import spearmanr

        rho = spearmanr([p[0] for p in pairs], [p[1] for p in pairs])
        print(f"\n{len(pairs)} clean frames; Spearman rank correlation {rho.statistic:.2f} (p = {rho.pvalue:.2f})")


def main() -> int:
    from study_refine import _seeds, render

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render validation frames and references into the cache")
    r.add_argument("--seeds", default="84001-84004")
    r.add_argument("--spp", default="4,16,64,256")
    r.add_argument("--ref-spp", type=int, default=1024)
    r.add_argument("--cache", type=Path, default=VALIDATION_CACHE)
    r.add_argument("--family", choices=("mixed", "studio"), default="mixed",
                   help="procedural family: rooms (procedural:SEED) or studio (procedural:studio:SEED)")
    e = sub.add_parser("error", help="the design and validation tables")
    e.add_argument("--design-cache", type=Path, default=DESIGN_CACHE)
    e.add_argument("--validation-cache", type=Path, default=VALIDATION_CACHE)
    e.add_argument("--sets", default="design,validation")
    e.add_argument("--extra", default="", help="more sets as NAME=DIR,... (e.g. studio=~/.cache/gradsep/studio-design)")
    e.add_argument("--per-frame", action="store_true")
    e.add_argument("--only", default="", help="comma-separated substrings: score only these variants (and the "
                   "ratios' baseline, oidn, l1 and the shipped rule)")
    e.add_argument("--baseline", default=BASELINE, help="the variant the ratios divide by (default: %(default)s)")
    t = sub.add_parser("time", help="1280x720 cost of the rule")
    t.add_argument("--width", type=int, default=1280)
    t.add_argument("--height", type=int, default=720)
    t.add_argument("--repeats", type=int, default=5)
    w = sub.add_parser("twins", help="a second realization (seed 8) of each cached frame, for `noise`")
    w.add_argument("--cache", type=Path, default=VALIDATION_CACHE)
    n = sub.add_parser("noise", help="frame noise ratio against the best clean-frame alpha")
    n.add_argument("--caches", default=f"{DESIGN_CACHE},{VALIDATION_CACHE}")
    args = parser.parse_args()
    if args.command == "render":
        render(_seeds(args.seeds), [int(s) for s in args.spp.split(",")], args.ref_spp, args.cache, args.family)
    elif args.command == "error":
        caches = {"design": args.design_cache, "validation": args.validation_cache}
        caches |= {n: Path(d).expanduser() for n, _, d in (x.partition("=") for x in args.extra.split(",") if x)}
        only = tuple(o for o in args.only.split(",") if o)
        error({k: caches[k] for k in args.sets.split(",")}, args.per_frame, only, args.baseline)
    elif args.command == "twins":
        twins(args.cache)
    elif args.command == "noise":
        noise([Path(p).expanduser() for p in args.caches.split(",")])
    else:
        time_rule(args.width, args.height, args.repeats)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    raise SystemExit(main())
