"""The gradient-domain path tracer (G-PT, Kettunen et al. 2015) on Mitsuba 3 / Dr.Jit, with the direct/indirect
illumination separation of Ma et al. 2024.

This module runs a render: passes of wavefront lanes (one lane per pixel sample), each pass one compiled kernel
(its loop: renderer/gpt_loop.py), whose per-pixel sums it adds and turns into the layers' primal images, their
variance, the gradients and the features. The pieces, one job each:

* renderer/gpt_settings.py -- what to render (:class:`GptSettings`) and the result (:class:`GptResult`);
* renderer/lanes.py -- a lane's sub-pixel position, the offsets it traces and its primary rays;
* renderer/vertex.py -- one path vertex, as Mitsuba's ``path`` integrator traces it;
* renderer/shift_protocol.py -- the interface of a shift mapping (how an offset path follows its base path);
  the shifts themselves: renderer/shift.py (random replay) and renderer/hybrid.py;
* renderer/gpt_loop.py -- the symbolic loop over path vertices.

Estimators (see docs/renderer.md for the derivation):

* **Primal**: the base paths alone, i.e. an ordinary path tracer (next-event estimation + BSDF sampling combined
  with the power heuristic, Russian roulette from vertex ``rr_depth`` on as in Mitsuba). It is unbiased and its noise is
  independent from pixel to pixel, which the unsupervised denoiser relies on; the MIS combination of all five
  paths would lower the primal's variance but correlate neighbouring pixels. Sub-pixel positions are stratified
  within each pixel (a jittered grid over the pass's samples), which keeps pixels independent.
* **Gradients**: each contribution ("event": emission found at vertex d, next-event estimation at vertex d) of a
  base path at pixel p gives ``w * (f_offset - f_base)``, an estimate of ``I(p + delta) - I(p)``. The same pixel
  pair is also estimated from the base path at ``p + delta`` with the opposite shift; ``w`` is the MIS weight of
  the pair between these two techniques and is supplied by the shift (1/2 for random replay when both paths
  exist, 1 when only this technique can produce the pair). ``dx(p)`` therefore sums the ``+x`` estimate of the
  samples of pixel p and the negated ``-x`` estimate of the samples of pixel p+1: both directions, no double
  counting.
* **Russian roulette** is decided on the base path and applied to the whole lane (the offsets are divided by the
  base path's continuation probability too), so it cancels in the MIS weights.
* **Separation**: events at the first camera-visible vertex (emission seen directly; next-event estimation from
  that vertex; emission found by the BSDF sample leaving it) go to ``direct``, all later events to ``indirect``.
  Offsets have the same length as their base path, so each gradient term lands in its base term's layer and
  ``direct + indirect`` is exactly the unseparated estimate.
* **Features** (base path only): at the first vertex that is not specular (delta lobes, and glossy samples with a
  pdf above ``gpt_loop.NEAR_SPECULAR_PDF``, are followed): albedo, camera-space normal, distance along the chain.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from gradsep.model.frame import VARIANCE_MAX
from gradsep.model.policy import LUMINANCE
from gradsep.renderer.gpt_loop import LoopState, drop_non_finite, run_loops, start_lanes
from gradsep.renderer.gpt_settings import Film, GptResult, GptSettings, channel_layout
from gradsep.renderer.lanes import OFFSET_GROUPS, SHIFT_OFFSETS
from gradsep.renderer.shift_protocol import Shift

# A sample's squared luminance is capped at the contract's VARIANCE_MAX (and so is the variance it feeds): a 1e20
# firefly squared would overflow float32 to Inf; capped, its pixel still reads as "very noisy", which is what the
# variance is for.
SQUARE_CAP = VARIANCE_MAX

# Lanes per pass. A lane's state lives in the kernel's registers, not in memory, so a pass needs only its
# per-pixel sums; every further pass pays the loop's recording, a launch and the float64 read-back and sum again,
# so a pass is made as large as memory allows (docs/decisions.md, "Lanes per pass"). The lane index is a UInt32:
# render_pass refuses 2^32 lanes.
MAX_LANES_PER_PASS = 1 << 26


def _pixel_sums(settings: GptSettings, s: LoopState, pixel: mi.UInt32, width: int, height: int,
                gradients: bool, offset_targets: list[mi.UInt32] | None = None) -> dict[str, np.ndarray]:
    """Scatter-add every lane's sums and features into per-pixel buffers (one launch, fused with the loops)."""
    sums, invalid = (s.sums, s.invalid) if gradients else drop_non_finite(s.sums)
    feat = s.feat
    n_pixels = width * height
    layout = channel_layout(settings, gradients)
    values: dict[str, Sequence[mi.Float]] = {}
    for layer, ls in sums.items():
        values[f"{layer}.base"] = [ls.base.x, ls.base.y, ls.base.z]
        y = LUMINANCE[0] * ls.base.x + LUMINANCE[1] * ls.base.y + LUMINANCE[2] * ls.base.z
        values[f"{layer}.sq"] = [dr.minimum(y * y, SQUARE_CAP)]
        for i, g in enumerate(ls.grads):
            values[f"{layer}.grad{i}"] = [g.x, g.y, g.z]
    values["albedo"] = [feat.albedo.x * feat.hit, feat.albedo.y * feat.hit, feat.albedo.z * feat.hit]
    values["normal"] = [feat.normal.x, feat.normal.y, feat.normal.z]
    values["depth"] = [feat.distance * feat.hit]
    values["hit"] = [feat.hit]
    values["invalid"] = [dr.select(invalid, 1.0, 0.0)]
    n_channels = sum(layout.values())
    target = dr.zeros(mi.Float, n_channels * n_pixels)
    channel = 0
    for name, width_c in layout.items():
        for comp in values.get(name, [])[:width_c]:
            index = pixel + channel * n_pixels
            if offset_targets is not None and ".grad" in name:
                # fewer offsets per lane: its k-th estimate belongs to offset offset_targets[k] (grad channels: 3 each)
                k = int(name.rsplit(".grad", 1)[1])
                index = index + (offset_targets[k] - k) * (3 * n_pixels)
            dr.scatter_reduce(dr.ReduceOp.Add, target, comp, index)
            channel += 1
        channel += width_c - len(values.get(name, [])[:width_c])
    dr.eval(target)
    flat = target.numpy().reshape(n_channels, height, width)
    out: dict[str, np.ndarray] = {}
    channel = 0
    for name, width_c in layout.items():
        out[name] = np.moveaxis(flat[channel:channel + width_c], 0, -1).astype(np.float64)
        channel += width_c
    return out


def render_pass(scene: mi.Scene, shift: Shift | None, settings: GptSettings, width: int, height: int, spp: int,
                seed: int) -> dict[str, np.ndarray]:
    """Trace ``width*height*spp`` lanes in one kernel; returns per-pixel *sums* (not means) per channel group.

    ``shift`` None renders the primal alone: the base paths with the same routing and features, no offsets.
    Sizes, seed and depth limits enter the kernel as opaque values, so one compiled kernel serves every seed and
    sample count of a scene; not every resolution: the scene is loaded with its film at the frame's size, and a
    scene loaded at another size compiles again, so a farm pays one compile per scene and frame size.
    """
    lanes = width * height * spp
    if lanes >= 1 << 32:
        raise ValueError(f"{lanes} samples in one pass exceed 2^32; use fewer samples per pass")
    kernel, state, pixel = start_lanes(scene, shift, settings, width, height, spp, seed)
    state = run_loops(kernel, state)
    return _pixel_sums(settings, state, pixel, width, height, kernel.gradients, kernel.offset_targets)


def pass_plan(width: int, height: int, spp: int, max_lanes: int = MAX_LANES_PER_PASS) -> list[int]:
    """Samples per pass: as many as fit in ``max_lanes`` lanes, at least one."""
    per_pass = max(1, min(spp, max_lanes // max(1, width * height)))
    plan = [per_pass] * (spp // per_pass)
    if spp % per_pass:
        plan.append(spp % per_pass)
    return plan


def pass_seed(seed: int, index: int) -> int:
    """A 32-bit seed for pass ``index`` of a render seeded ``seed`` (splitmix-style mix: distinct streams)."""
    z = (seed * 0x9E3779B97F4A7C15 + (index + 1) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return (z ^ (z >> 31)) & 0xFFFFFFFF


def render_gpt(scene: mi.Scene, shift: Shift | None, settings: GptSettings, film: Film,
               progress: Callable[[int, int], None] | None = None, max_lanes: int = MAX_LANES_PER_PASS) -> GptResult:
    """Render ``film.spp`` samples per pixel in passes and combine them into per-layer base/dx/dy images + features.

    ``shift`` None is the primal-only mode: the same base paths, layers and features, no offsets and no
    gradients (each layer carries ``base`` alone).

    ``film.gradient_spp`` K (default ``spp``; needs a shift): only K of the ``spp`` samples trace offsets; the other
    ``spp - K`` are primal-only samples. The primal-only mode's bases and features are the same estimator as
    G-PT's primal, so the layers' bases and the features are per-pixel sums over all ``spp`` samples (the
    spp-weighted mean of the two renders, features normalised by their combined hit counts exactly as one
    render's), and the gradients come from the K G-PT samples alone. The primal-only passes continue the pass
    index after the G-PT passes, so every pass has its own seed stream (``pass_seed``). K == ``spp`` is the
    plain render, bit for bit."""
    settings.validate()
    width, height, spp = film.width, film.height, film.spp
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    k = spp if film.gradient_spp is None else int(film.gradient_spp)
    if not 1 <= k <= spp:
        raise ValueError(f"gradient_spp must be in [1, spp={spp}], got {film.gradient_spp}")
    if shift is None and k != spp:
        raise ValueError("gradient_spp needs gradients: the primal-only mode traces no offsets")
    if shift is not None and settings.gradients == "direct":
        shift = getattr(shift, "for_direct_layer", lambda: shift)()
    plan = [(shift, settings, n) for n in pass_plan(width, height, k, max_lanes)]
    if k < spp:  # the primal-only mode's own settings (what render_frame's gradients="none" passes)
        primal = dataclasses.replace(settings, gradients="all", offsets="all")
        plan += [(None, primal, n) for n in pass_plan(width, height, spp - k, max_lanes)]
    totals: dict[str, np.ndarray] | None = None
    done = 0
    for i, (pass_shift, pass_settings, n) in enumerate(plan):
        sums = render_pass(scene, pass_shift, pass_settings, width, height, n, pass_seed(film.seed, i))
        # a primal-only pass has no gradient sums: those stay the G-PT passes' (keys of the first pass)
        totals = sums if totals is None else {key: v + sums[key] if key in sums else v for key, v in totals.items()}
        done += n
        if progress is not None:
            progress(done, spp)
    assert totals is not None
    return finish(totals, settings, spp, len(plan), k)


def mean_variance(sums: np.ndarray, squares: np.ndarray, spp: int) -> np.ndarray | None:
    """The variance of each pixel's mean luminance, from the per-pixel sums of its ``spp`` samples' RGB and
    squared luminance: the unbiased sample variance over ``spp``, float32 (H, W), or None for one sample (no
    estimate). Rounding can leave a tiny negative difference for a pixel whose samples are all equal: that is 0. A
    pixel with a sample whose square was capped (SQUARE_CAP) has the largest variance, SQUARE_CAP."""
    if spp < 2:
        return None
    y = np.asarray(sums, np.float64) @ np.array(LUMINANCE)
    sq = np.asarray(squares, np.float64)[..., 0]
    spread = np.maximum(sq - y * y / spp, 0.0)
    var = np.where(sq >= SQUARE_CAP, SQUARE_CAP, np.minimum(spread / (spp * (spp - 1.0)), SQUARE_CAP))
    return var.astype(np.float32)


def finish(t: dict[str, np.ndarray], settings: GptSettings, spp: int, passes: int,
           gradient_spp: int | None = None) -> GptResult:
    """Added :func:`render_pass` sums -> a GptResult: per-pixel sums -> means; the two one-sided gradient estimates
    -> dx, dy per the frame contract. The bases and features are sums over ``spp`` samples, the gradients (where
    ``t`` has them) over ``gradient_spp`` (default ``spp``). renderer/passes.py runs passes itself and calls it."""
    layers: dict[str, dict[str, np.ndarray]] = {}
    for layer in settings.layer_names():
        variance = mean_variance(t[f"{layer}.base"], t[f"{layer}.sq"], spp)
        if f"{layer}.grad0" not in t:  # primal-only render
            layers[layer] = {"base": (t[f"{layer}.base"] / spp).astype(np.float32), "var": variance}
            continue
        g = [t[f"{layer}.grad{i}"] for i in range(len(SHIFT_OFFSETS))]  # right, left, down, up
        dx = g[0].copy()
        dx[:, :-1] -= g[1][:, 1:]  # base at x+1 shifted left estimates I(x) - I(x+1) = -dx(x)
        dx[:, -1] = 0.0
        dy = g[2].copy()
        dy[:-1, :] -= g[3][1:, :]
        dy[-1, :] = 0.0
        # fewer offsets per sample: each traced its group with probability 1/groups, so its terms count groups times
        per_axis = (spp if gradient_spp is None else gradient_spp) / OFFSET_GROUPS[settings.offsets]
        layers[layer] = {"base": (t[f"{layer}.base"] / spp).astype(np.float32), "var": variance,
                         "dx": (dx / per_axis).astype(np.float32), "dy": (dy / per_axis).astype(np.float32)}
    hits = t["hit"][..., 0]
    safe = np.maximum(hits, 1.0)[..., None]
    albedo = np.clip(t["albedo"] / safe, 0.0, 1.0)
    normal = t["normal"]
    norm = np.linalg.norm(normal, axis=-1, keepdims=True)
    facing = np.broadcast_to(np.array([0.0, 0.0, 1.0]), normal.shape)
    normal = np.where(norm > 1e-6, normal / np.maximum(norm, 1e-12), facing)
    depth = np.where(hits > 0, t["depth"][..., 0] / np.maximum(hits, 1.0), 0.0)
    invalid = int(round(float(t["invalid"].sum())))
    warnings = []
    if invalid:
        warnings.append(f"{invalid} samples produced non-finite values; their contributions were set to 0")
    return GptResult(layers=layers, albedo=albedo.astype(np.float32), normal=normal.astype(np.float32),
                     depth=depth.astype(np.float32), spp=spp, invalid_samples=invalid, passes=passes,
                     warnings=warnings)
