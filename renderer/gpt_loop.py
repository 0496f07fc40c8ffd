"""The G-PT integrator's loop (Kettunen et al. 2015, with the direct/indirect separation of Ma et al. 2024): one
pass of wavefront lanes, each carrying the base path x̄ of its pixel sample and one offset path ȳ per pixel shift
through one symbolic Dr.Jit loop (one compiled kernel, one iteration per path vertex). Laid out as Mitsuba 3's
``prb.py``: the loop state is declared once (:class:`LoopState`), then one section per stage of an iteration.
renderer/gpt.py runs the passes and turns their sums into images; docs/renderer.md derives the estimators.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi

from gradsep.renderer.gpt_settings import GptSettings
from gradsep.renderer.lanes import (
    OFFSET_GROUPS,
    SHIFT_OFFSETS,
    alternate_offsets,
    camera_rays,
    offset_group,
    offsets_by_index,
)
from gradsep.renderer.shift_protocol import ConnectingShift, OffsetEvents, Shift
from gradsep.renderer.vertex import PathState, Vertex, VertexSamples, trace_vertex

# Vertices whose events belong to the direct layer (emission at depth <= 1, NEE at depth 0): _route's rule.
DIRECT_VERTICES = 2

# A glossy lobe whose sampled direction has a solid-angle pdf above this is treated as a mirror when looking for
# the feature vertex: a GGX lobe reaches ~100 sr^-1 near alpha 0.05, where reflections are still sharp images.
NEAR_SPECULAR_PDF = 100.0

# Mitsuba's convention for an unbounded path length.
UNBOUNDED = 0xFFFFFFFF


# ---------------------------------------------------------------------------------------------------------------
# Loop state: declared once for both loops
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class LayerSums:
    """Per-lane sums of one illumination layer: base radiance and one gradient estimate per shift."""

    base: mi.Spectrum
    grads: list[mi.Spectrum]

    @staticmethod
    def zeros(n_offsets: int = len(SHIFT_OFFSETS)) -> LayerSums:
        """Zero sums, one gradient estimate per traced offset (none: the layer carries the base radiance only)."""
        return LayerSums(base=mi.Spectrum(0.0), grads=[mi.Spectrum(0.0) for _ in range(n_offsets)])


@dataclass
class FeatureState:
    """The feature vertex search along the base path (loop state)."""

    pending: mi.Bool  # still following a specular chain
    albedo: mi.Color3f
    normal: mi.Vector3f  # camera space, facing the viewer
    distance: mi.Float  # along the chain so far / to the feature vertex
    hit: mi.Float  # 1 when the chain ended on a surface, 0 on a miss

    @staticmethod
    def start() -> FeatureState:
        return FeatureState(pending=mi.Bool(True), albedo=mi.Color3f(0.0), normal=mi.Vector3f(0.0, 0.0, 1.0),
                            distance=mi.Float(0.0), hit=mi.Float(0.0))


@dataclass
class LoopState:
    """Loop state of one wavefront lane (one pixel sample), declared once for both G-PT loops (Dr.Jit traverses
    dataclasses: this is the tuple Mitsuba's ``prb.py`` spells out as its loop state). Kettunen et al.'s names:
    the base path x̄ of the lane's pixel and one offset path ȳ per pixel shift."""

    sampler: mi.Sampler          # the lane's random stream (u)
    depth: mi.UInt32             # k: the index of the vertex x_k this iteration finds (0: the camera ray's hit)
    base: PathState              # x̄, the base path
    offsets: list[Any]           # ȳ per traced pixel shift: the shift's state (first loop) or its summary (second)
    sums: dict[str, LayerSums]   # per layer: the base path's f(x̄) and one gradient estimate per shift
    feat: FeatureState           # the feature-vertex search along x̄
    invalid: mi.Bool             # some event of the lane was not finite (and was zeroed)


@dataclass
class PassKernel:
    """What the loop body of one pass reads and never changes: the scene, the shift and the opaque limits."""

    scene: mi.Scene
    shift: Shift | None  # None: primal only (no offsets)
    settings: GptSettings
    max_depth: mi.UInt32  # opaque: one compiled kernel serves every depth limit
    rr_depth: mi.UInt32
    to_camera: mi.Transform4f  # world -> camera, for the normal feature
    ray_flags: mi.RayFlags
    strict_light_pdf: bool
    hittable: bool  # some emitter can be found by a ray (scene_has_hittable_emitters)
    # per lane and traced offset, the index in SHIFT_OFFSETS whose gradient sums it feeds; None: all four, in order
    offset_targets: list[mi.UInt32] | None

    @property
    def gradients(self) -> bool:
        return self.shift is not None


# How an offset advances by one base vertex: the shift's full step, or the second loop's connected step.
OffsetStep = Callable[[Any, Vertex, Any, VertexSamples], tuple[Any, OffsetEvents]]  # (offset, vertex, depth, samples)


# ---------------------------------------------------------------------------------------------------------------
# Features: the first non-specular vertex of the base path x̄
# ---------------------------------------------------------------------------------------------------------------


def _camera_normal(to_camera: mi.Transform4f, si: mi.SurfaceInteraction3f, ray_d: mi.Vector3f) -> mi.Vector3f:
    """Shading normal turned towards the incoming ray, in camera space with x right, y up, z towards the viewer.

    Mitsuba's camera frame looks along +z with +x to the left; flipping x and z gives the usual right-handed
    view space in which surfaces facing the camera have z > 0.
    """
    n = si.sh_frame.n
    n = dr.select(dr.dot(n, ray_d) > 0, -n, n)
    local = to_camera @ n
    return dr.normalize(mi.Vector3f(-local.x, local.y, -local.z))


def _update_features(feat: FeatureState, base_active: mi.Bool, v: Vertex, ray_d: mi.Vector3f,
                     to_camera: mi.Transform4f) -> FeatureState:
    """Record features at this base vertex if the specular-chain search is still on; continue past mirrors."""
    rec = feat.pending & base_active
    valid = v.si.is_valid()
    flags = v.bsdf_flags
    has_diffuse = mi.has_flag(flags, mi.BSDFFlags.Diffuse)
    # Diffuse reflectance where the BSDF has a diffuse lobe; elsewhere the sampled weight, a one-sample estimate
    # of the directional albedo that averages to the right colour over the pixel's samples (metals, glass).
    diffuse = v.bsdf.eval_diffuse_reflectance(v.si, rec & valid & has_diffuse)
    albedo = dr.clip(dr.select(has_diffuse, diffuse, v.sample_weight), 0.0, 1.0)
    albedo = dr.select(dr.isfinite(albedo), albedo, 0.0)  # clip keeps NaN (a broken BSDF): 0, as the reader does
    sampled = v.sample.sampled_type
    specular = ~has_diffuse & (mi.has_flag(sampled, mi.BSDFFlags.Delta)
                               | (mi.has_flag(sampled, mi.BSDFFlags.Glossy) & (v.sample.pdf > NEAR_SPECULAR_PDF)))
    distance = feat.distance + dr.select(rec & valid, v.si.t, 0.0)
    normal = _camera_normal(to_camera, v.si, ray_d)
    stop = rec & (~valid | ~specular)
    return FeatureState(
        pending=feat.pending & ~stop,
        albedo=dr.select(rec, dr.select(valid, albedo, 0.0), feat.albedo),
        normal=dr.select(rec & valid, normal, dr.select(rec, mi.Vector3f(0.0, 0.0, 1.0), feat.normal)),
        distance=dr.select(rec & ~valid, 0.0, distance),
        hit=dr.select(rec, dr.select(valid, 1.0, 0.0), feat.hit),
    )


# ---------------------------------------------------------------------------------------------------------------
# Events into the layers' sums
# ---------------------------------------------------------------------------------------------------------------


def _route(sums: dict[str, LayerSums], depth: mi.UInt32, settings: GptSettings, hit_value: mi.Spectrum,
           nee_value: mi.Spectrum, hit_grads: list[mi.Spectrum], nee_grads: list[mi.Spectrum]) -> None:
    """Add one vertex's events to their layer: emission at depth <= 1 and NEE at depth 0 are direct light; an
    unseparated render (``color``) takes every event. A layer's gradient sums take the offsets' terms when this
    vertex has any (``hit_grads`` empty: no offsets are traced any more; a layer without gradients has none)."""
    if "color" in sums:
        s = sums["color"]
        s.base = s.base + hit_value + nee_value
        for i in range(len(s.grads) if hit_grads else 0):
            s.grads[i] = s.grads[i] + hit_grads[i] + nee_grads[i]
        return
    hit_direct = depth <= 1
    nee_direct = depth == 0
    for layer, sel_hit, sel_nee in (("direct", hit_direct, nee_direct), ("indirect", ~hit_direct, ~nee_direct)):
        if layer not in sums:
            continue
        s = sums[layer]
        s.base = s.base + dr.select(sel_hit, hit_value, 0.0) + dr.select(sel_nee, nee_value, 0.0)
        for i in range(len(s.grads) if hit_grads else 0):
            s.grads[i] = s.grads[i] + dr.select(sel_hit, hit_grads[i], 0.0) + dr.select(sel_nee, nee_grads[i], 0.0)


def _finite(x: Any) -> tuple[Any, mi.Bool]:
    """Zero non-finite values (degenerate geometry); returns the cleaned value and a per-lane 'was bad' mask."""
    ok = dr.isfinite(x)
    bad = ~dr.all(ok) if dr.size_v(x) > 1 else ~ok
    return dr.select(ok, x, 0.0), bad


def scene_has_hittable_emitters(scene: mi.Scene) -> bool:
    """Whether a ray can find emission: an area light or an environment. Point, spot and directional lights
    (delta in position or direction) are reached only by next-event estimation, so in a scene lit by them alone
    the last ray of a path (traced only to look for emission) can be skipped, by `path` and G-PT alike."""
    delta = int(mi.EmitterFlags.DeltaPosition | mi.EmitterFlags.DeltaDirection)
    return any(not int(emitter.flags()) & delta for emitter in scene.emitters())


def drop_non_finite(sums: dict[str, LayerSums]) -> tuple[dict[str, LayerSums], mi.Bool]:
    """Primal-only lanes: a sample whose sum is not finite (degenerate geometry) contributes 0 to every layer;
    returns the cleaned sums and the per-lane 'was bad' mask."""
    bad = mi.Bool(False)
    for s in sums.values():
        bad |= ~dr.all(dr.isfinite(s.base))
    for s in sums.values():
        s.base = dr.select(bad, 0.0, s.base)
    return sums, bad



# ---------------------------------------------------------------------------------------------------------------
# Lanes: each one's sampler stream, primary rays and zero sums
# ---------------------------------------------------------------------------------------------------------------


def start_lanes(scene: mi.Scene, shift: Shift | None, settings: GptSettings, width: int, height: int, spp: int,
                 seed: int) -> tuple[PassKernel, LoopState, mi.UInt32]:
    """One lane per pixel sample: its sampler stream, primary rays (base and offsets) and zero sums. Sizes, seed
    and depth limits enter as opaque values. Returns the pass's constants, the initial state and each lane's
    pixel index."""
    sensor = scene.sensors()[0]
    lanes = width * height * spp
    w_o = dr.opaque(mi.Int32, width)
    h_o = dr.opaque(mi.Int32, height)
    spp_o = dr.opaque(mi.UInt32, spp)
    max_depth = settings.effective_max_depth()
    gradients = shift is not None
    kernel = PassKernel(
        scene=scene, shift=shift, settings=settings,
        max_depth=dr.opaque(mi.UInt32, UNBOUNDED if max_depth < 0 else max_depth),
        rr_depth=dr.opaque(mi.UInt32, settings.rr_depth), to_camera=sensor.world_transform().inverse(),
        ray_flags=shift.ray_flags(scene) if gradients else mi.RayFlags.All,
        strict_light_pdf=shift.reuses_light_samples if gradients else False,
        hittable=scene_has_hittable_emitters(scene), offset_targets=None)

    seed_o = dr.opaque(mi.UInt32, seed & 0xFFFFFFFF)
    sampler = mi.load_dict({"type": "independent", "sample_count": spp})
    sampler.seed(seed_o, lanes)
    idx = dr.arange(mi.UInt32, lanes)
    pixel = idx // spp_o
    py = mi.Int32(pixel // mi.UInt32(w_o))
    px = mi.Int32(pixel) - py * w_o
    strata_o = dr.opaque(mi.UInt32, math.isqrt(spp))
    sample = idx % spp_o
    shifts: Sequence[tuple[int | mi.Int32, int | mi.Int32]] = SHIFT_OFFSETS if gradients else ()
    groups = OFFSET_GROUPS[settings.offsets]
    with_gradients = settings.gradient_layer_names() if gradients else ()
    if gradients and settings.offsets == "alternate":
        kernel.offset_targets = list(alternate_offsets(px, py, sample, strata_o, seed_o))
        shifts = offsets_by_index(kernel.offset_targets)
    elif gradients and groups > 1:
        group = offset_group(pixel, sample, strata_o, seed_o, groups)
        per_group = len(SHIFT_OFFSETS) // groups
        # the k-th offset of the lane's group
        kernel.offset_targets = [group * per_group + k for k in range(per_group)]
        shifts = offsets_by_index(kernel.offset_targets)
    rays, _ = camera_rays(sensor, sampler, (px, py), (w_o, h_o), sample, strata_o, shifts)
    state = LoopState(
        sampler=sampler, depth=mi.UInt32(0), base=PathState.start(*rays[0]),
        offsets=[shift.start(*r) for r in rays[1:]] if shift is not None else [],
        sums={name: LayerSums.zeros(len(shifts) if name in with_gradients else 0) for name in settings.layer_names()},
        feat=FeatureState.start(), invalid=mi.Bool(False))
    return kernel, state, pixel


# ---------------------------------------------------------------------------------------------------------------
# One iteration: x̄ and every ȳ advance one vertex; Russian roulette
# ---------------------------------------------------------------------------------------------------------------


def _offset_events(k: PassKernel, s: LoopState, v: Vertex, samples: VertexSamples,
                   step_offset: OffsetStep) -> tuple[list[mi.Spectrum], list[mi.Spectrum], mi.Bool]:
    """Advance every offset by the base vertex ``v`` (in place in ``s.offsets``); returns per offset the
    gradient terms ``w (f_offset - f_base)`` of the emission and next-event events, zeroed where not finite,
    and the lane's 'was not finite' mask."""
    hit_grads, nee_grads = [], []
    bad = mi.Bool(False)
    for i, off in enumerate(s.offsets):
        s.offsets[i], ev = step_offset(off, v, s.depth, samples)
        # An event the base path does not have belongs to the mirrored technique alone (weight 1 there).
        off_nee = dr.select(v.has_nee, ev.nee, 0.0)
        gh, bad_h = _finite(ev.w_hit * (ev.emitted - v.emitted))
        gn, bad_n = _finite(ev.w_nee * (off_nee - v.nee))
        bad |= bad_h | bad_n
        hit_grads.append(gh)
        nee_grads.append(gn)
    return hit_grads, nee_grads, bad


def _russian_roulette(k: PassKernel, s: LoopState) -> None:
    """Russian roulette on the base path (Mitsuba's rule), applied to the whole lane: the offsets are scaled by
    the same 1/q and die with their base path (in place)."""
    base = s.base
    q = dr.minimum(dr.max(base.throughput) * base.eta * base.eta, 0.95)
    # Mitsuba's rule: roulette from the rr_depth-th vertex on (its `path` counts the vertex just found before
    # comparing with rr_depth; rr_depth 1 may end a path at the first visible surface).
    rr_active = base.active & (s.depth + 1 >= k.rr_depth)
    survive = s.sampler.next_1d() < q
    inv_q = dr.select(rr_active, dr.rcp(q), 1.0)
    base.throughput = base.throughput * inv_q
    dead = rr_active & ~survive
    base.active = base.active & ~dead
    if k.shift is not None:
        s.offsets = [k.shift.kill(k.shift.scale(o, inv_q, rr_active), dead) for o in s.offsets]


def _vertex(k: PassKernel, s: LoopState, step_offset: OffsetStep) -> LoopState:
    """One loop iteration: the base path's next vertex, every offset's, their events into the layer sums, the
    feature search, Russian roulette."""
    samples = VertexSamples.draw(s.sampler)
    ray_d = mi.Vector3f(s.base.ray.d)
    base_active = mi.Bool(s.base.active)
    s.base, v = trace_vertex(k.scene, s.base, s.depth, k.max_depth, samples, k.strict_light_pdf, k.ray_flags)
    if k.gradients:
        hit_grads, nee_grads, bad = _offset_events(k, s, v, samples, step_offset)
        hit_value, bad_h = _finite(v.emitted)
        nee_value, bad_n = _finite(v.nee)
        bad |= bad_h | bad_n
    else:  # checked once per lane after the loop (drop_non_finite): one check instead of two per vertex
        hit_grads, nee_grads = [], []
        hit_value, nee_value, bad = v.emitted, v.nee, mi.Bool(False)
    _route(s.sums, s.depth, k.settings, hit_value, nee_value, hit_grads, nee_grads)
    s.feat = _update_features(s.feat, base_active, v, ray_d, k.to_camera)
    if not k.hittable:
        # No emitter can be found by a ray: the next vertex is needed only for next-event estimation there (or to
        # continue the feature search past a mirror); its emission event is always 0.
        s.base.active &= (s.depth + 2 < k.max_depth) | s.feat.pending
    _russian_roulette(k, s)
    s.depth = s.depth + 1
    s.invalid = s.invalid | bad
    return s


# ---------------------------------------------------------------------------------------------------------------
# The loops
# ---------------------------------------------------------------------------------------------------------------


def run_loops(k: PassKernel, s: LoopState) -> LoopState:
    """The symbolic loops over path vertices. With a :class:`ConnectingShift`: a first loop while some offset of
    the lane still has vertices of its own, then a second, cheap one carrying the settled offsets' summaries."""
    shift = k.shift

    def loop(state: LoopState, cond: Callable[[LoopState], mi.Bool], step_offset: OffsetStep,
             label: str, peel: bool = False, step_later: OffsetStep | None = None) -> LoopState:
        if peel:
            # The first vertex outside the symbolic loop (same kernel): its depth is the literal 0 there, so
            # everything the shift does only after the primary ray (transitions, replays, reconnection rays, BSDF
            # calls masked by ``depth > 0``) folds away instead of running masked in every SIMD packet; inside
            # the loop every vertex is a later one (``step_later``: the primary-ray code folds away there).
            state = _vertex(k, state, step_offset)
        body_step = step_later if peel and step_later is not None else step_offset
        (state,) = dr.while_loop(state=(state,), cond=cond, body=lambda st: (_vertex(k, st, body_step),),
                                 label=label)
        return state

    # The primal-only mode's loop is not peeled: its small body gains nothing from it and its kernel grows
    # (docs/decisions.md, "Tracing the first vertex before the loop").
    peel = shift is not None

    def full_step(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        assert shift is not None  # only called for offsets, which exist only with a shift
        return shift.step(k.scene, off, v, depth, k.max_depth, samples)

    def later_step(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        assert shift is not None
        return shift.step(k.scene, off, v, depth, k.max_depth, samples, later=True)

    def base_alive(st: LoopState) -> mi.Bool:
        return st.base.active

    if k.settings.gradients == "direct" and shift is not None:
        return _run_direct_gradient_loops(k, s, loop, base_alive)
    if not isinstance(shift, ConnectingShift):
        return loop(s, base_alive, full_step, "gpt", peel=peel, step_later=later_step)

    def unsettled(st: LoopState) -> mi.Bool:
        settled = mi.Bool(True)
        for off in st.offsets:
            settled &= shift.settled(off)
        return st.base.active & ~settled

    def connected_step(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        return shift.step_connected(off, v, depth, k.max_depth)

    s = loop(s, unsettled, full_step, "gpt", peel=peel, step_later=later_step)
    s.offsets = [shift.summarize(off) for off in s.offsets]
    return loop(s, base_alive, connected_step, "gpt_connected")


LoopRunner = Callable[..., LoopState]  # (state, cond, step, label, peel=False)


def _run_direct_gradient_loops(k: PassKernel, s: LoopState, loop: LoopRunner,
                               base_alive: Callable[[LoopState], mi.Bool]) -> LoopState:
    """Gradients of the direct layer alone (``GptSettings.gradients == "direct"``): every offset takes the
    shift's full step at the first DIRECT_VERTICES vertices -- the direct layer's events are emission at depth
    0 and 1 and next-event estimation at depth 0 -- and is then dropped; the base path continues alone for the
    indirect layer's primal, in a loop with no offset work at all.

    The offsets take the very step (and random numbers) of an ``all`` render there, so the direct layer's base
    and gradients are that render's. Their depth limit is capped at DIRECT_VERTICES: the offsets' next-event
    estimate at depth 1 (an indirect event, whose gradient is not kept) is not evaluated (no emitter sample
    reconnection, no shadow ray); nothing the direct layer reads depends on that limit (the emission found at
    depth 1 does not, and the next-event estimate at depth 0 needs only ``1 < limit``). In a scene where no ray can
    find emission (point, spot and directional lights only: ``k.hittable`` False) the emission event at depth 1
    is 0 for base and offsets alike, so the offsets stop after vertex 0 (the ``all`` render adds 0 there too).
    render_gpt hands this mode the shift's ``for_direct_layer()`` where it has one.
    """
    shift = k.shift
    assert shift is not None
    offset_max_depth = dr.minimum(k.max_depth, mi.UInt32(DIRECT_VERTICES))
    vertices = DIRECT_VERTICES if k.hittable else 1

    def direct_step(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        return shift.step(k.scene, off, v, depth, offset_max_depth, samples)

    def direct_later(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        return shift.step(k.scene, off, v, depth, offset_max_depth, samples, later=True)

    def direct_vertices(st: LoopState) -> mi.Bool:
        return st.base.active & (st.depth < vertices)

    def no_offsets(*_: Any) -> tuple[Any, OffsetEvents]:
        raise AssertionError("no offsets are traced past the direct layer's vertices")

    s = loop(s, direct_vertices, direct_step, "gpt_direct", peel=True, step_later=direct_later)
    s.offsets = []
    return loop(s, base_alive, no_offsets, "gpt_base")


