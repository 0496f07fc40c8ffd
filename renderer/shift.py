"""Shift mappings for the G-PT integrator (renderer/gpt.py): how an offset path is built from its base path.

A shift implements the small :class:`renderer.gpt.Shift` protocol: ``start`` makes the offset's loop state from
its primary ray, ``step`` advances it by one base-path vertex and returns the offset's contributions for that
vertex's two events together with the MIS weights of the pixel pair, ``scale``/``kill`` apply the base path's
Russian roulette. The integrator never looks inside an offset state: :class:`ReplayShift` and
:class:`HybridShift` (reconnection at rough vertices, replay elsewhere; issue 4) are interchangeable.

Random replay
-------------
The offset path of pixel ``p + delta`` consumes exactly the base path's random numbers: it *is* the path that the
base path of pixel ``p + delta`` would trace from those numbers. Seen in primary sample space (the unit hypercube
of random numbers ``u``), the shift is the identity, so its Jacobian is 1 and both techniques that can estimate a
pixel pair -- base at ``p`` shifted by ``+delta``, and base at ``p + delta`` shifted by ``-delta`` -- sample the
pair's ``u`` with the same density 1. (Path-space densities differ, ``p(x) = 1/|dx/du|`` and
``p(x') = 1/|dx'/du|``, but the path-space Jacobian ``|dx'/dx| = |dx'/du| / |dx/du|`` makes ``p(x') |dx'/dx| =
p(x)``: the same statement.) Russian roulette multiplies each technique's density by its own base path's
continuation probabilities and divides its contributions by them, so it cancels in expectation and needs no
place in the weights. The balance heuristic therefore gives each technique weight 1/2 for every event both can
produce. An event that only this technique produces -- the offset path has already ended (left the scene, hit a
zero BSDF, reached no surface for next-event estimation), so the neighbour's base path has no such event -- gets
weight 1, and the offset contributes 0 to it. The two weights of every pair sum to 1, which is all unbiasedness
needs; offset paths are traced with the very function the base path uses, so "the path has this event" is the
same predicate in both techniques.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from renderer.gpt import OffsetEvents, PathState, Shift, Vertex, VertexSamples, mis_power, trace_vertex

SHIFT_NAMES: tuple[str, ...] = ("replay", "hybrid")


class ReplayShift:
    """Random replay: the offset path re-runs the path tracer with the base path's random numbers."""

    name = "replay"
    reuses_light_samples = False

    def start(self, ray: mi.Ray3f, weight: mi.Spectrum, active: mi.Bool) -> PathState:
        return PathState.start(ray, weight, active)

    def step(self, scene: mi.Scene, offset: PathState, base: Vertex, depth: mi.UInt32, max_depth: mi.UInt32,
             samples: VertexSamples) -> tuple[PathState, OffsetEvents]:
        offset, v = trace_vertex(scene, offset, depth, max_depth, samples)
        events = OffsetEvents(
            emitted=v.emitted,
            nee=v.nee,
            w_hit=dr.select(v.has_hit, 0.5, 1.0),
            w_nee=dr.select(v.has_nee, 0.5, 1.0),
        )
        return offset, events

    def scale(self, offset: PathState, factor: mi.Float, active: mi.Bool) -> PathState:
        offset.throughput = dr.select(active, offset.throughput * factor, offset.throughput)
        return offset

    def kill(self, offset: PathState, dead: mi.Bool) -> PathState:
        offset.active = offset.active & ~dead
        return offset


# ---------------------------------------------------------------------------------------------------------------
# Hybrid shift: reconnection at rough vertices, random replay elsewhere
# ---------------------------------------------------------------------------------------------------------------

NOT_CONNECTED, RECENTLY_CONNECTED, CONNECTED = 0, 1, 2
MIN_DISTANCE2 = 1e-12  # squared distances below this (coinciding points) are degenerate, not divided by


@dataclass
class HybridState:
    """Loop state of one hybrid offset path.

    ``si`` is the offset's vertex of the *previous* iteration, with the offset's own incoming direction (for a
    recently connected offset: the base path's vertex seen from the offset's previous vertex); the ``b_*`` fields
    stash what the transition into the next vertex needs from the base path's previous vertex.
    """

    active: mi.Bool
    status: mi.UInt32
    throughput: mi.Spectrum  # f(offset prefix) * Jacobians / p(base prefix), with the base's roulette
    ratio: mi.Float  # p(offset prefix as a base path) * Jacobians / p(base prefix); roulette excluded
    ray: mi.Ray3f  # primary ray (first iteration only)
    si: mi.SurfaceInteraction3f
    lobe: mi.Float  # the base path's random numbers of the previous vertex, for replay at a specular vertex
    direction: mi.Point2f
    b_pdf: mi.Float  # base: pdf of the direction leaving its previous vertex
    b_weight: mi.Spectrum  # base: BSDF weight of that direction
    b_dir: mi.Vector3f  # base: that direction, world space
    b_delta: mi.Bool  # base: that direction came from a delta lobe
    b_rough_vertex: mi.Bool  # base: its previous vertex has a non-delta lobe


def _rough_vertex(bsdf: mi.BSDFPtr) -> mi.Bool:
    """A vertex a reconnection may start or end at: its BSDF has a non-delta lobe (Mitsuba exposes no
    roughness; delta lobes are the specular ones, every other lobe is treated as rough)."""
    return mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)


def _interaction(si: mi.SurfaceInteraction3f) -> mi.Interaction3f:
    it = dr.zeros(mi.Interaction3f)
    it.t, it.time, it.p, it.n = si.t, si.time, si.p, si.n
    return it


def _balance(ratio: mi.Float) -> mi.Float:
    """Weight 1 / (1 + p_other / p_this) of this technique; 0 where the ratio is not finite (p_this ~ 0)."""
    w = dr.rcp(1.0 + ratio)
    return dr.select(dr.isfinite(w) & dr.isfinite(ratio), w, 0.0)


class HybridShift:
    """Kettunen et al.'s hybrid shift, adapted to Mitsuba 3: reconnect where possible, replay elsewhere.

    The offset path starts from its own primary ray. Leaving each vertex, it *reconnects* to the base path's next
    vertex when the base path sampled a non-delta lobe there, the offset vertex has a non-delta lobe and the base
    path's next vertex has one too (or is the sky: reconnection at infinity); the Jacobian of moving the next
    vertex is ``|cos' d^2| / |cos d'^2|`` (cosines at the shared vertex, squared distances to the previous
    vertices) and occlusion of the new segment fails the shift. Otherwise the offset replays the base path's random
    numbers at its own vertex -- for a smooth mirror or smooth glass that *is* the half-vector copy, and in
    primary sample space its Jacobian is 1 -- and traces its own ray; if the reverse shift would have reconnected
    there, the shift is not invertible and fails. Once reconnected, the offset shares every later vertex: one BSDF
    evaluation at the reconnection vertex for its own incoming direction, afterwards the base path's own BSDF
    weights, and no further rays. Next-event estimation on a not yet connected offset reuses the base path's
    light sample (same point on the emitter; same direction for emitters at infinity) with the Jacobian of that
    reconnection and its own shadow ray; on shared vertices it reuses the base path's visibility.

    MIS between base and offset: the balance heuristic over path densities, ``w = 1 / (1 + R)`` with ``R`` the
    offset path's density (as a base path of its pixel) times the shift's Jacobian over the base path's density,
    tracked as a running ratio. Within each path, emitter sampling and BSDF sampling are combined with the power
    heuristic exactly as in the base path tracer; the shift maps light-sampled paths to light-sampled paths and
    BSDF-sampled to BSDF-sampled, so the two levels of weights compose. A failed shift sets the offset's
    contribution and density to 0 (``w = 1`` for the base path), which keeps the estimator unbiased.
    """

    name = "hybrid"
    reuses_light_samples = True

    def start(self, ray: mi.Ray3f, weight: mi.Spectrum, active: mi.Bool) -> HybridState:
        return HybridState(
            active=mi.Bool(active), status=mi.UInt32(NOT_CONNECTED), throughput=mi.Spectrum(weight),
            ratio=mi.Float(1.0), ray=mi.Ray3f(ray), si=dr.zeros(mi.SurfaceInteraction3f), lobe=mi.Float(0.0),
            direction=mi.Point2f(0.0), b_pdf=mi.Float(1.0), b_weight=mi.Spectrum(1.0),
            b_dir=mi.Vector3f(0.0, 0.0, 1.0), b_delta=mi.Bool(False), b_rough_vertex=mi.Bool(False))

    def step(self, scene: mi.Scene, off: HybridState, base: Vertex, depth: mi.UInt32, max_depth: mi.UInt32,
             samples: VertexSamples) -> tuple[HybridState, OffsetEvents]:
        ctx = mi.BSDFContext()
        first = depth == 0
        active = mi.Bool(off.active)
        throughput = mi.Spectrum(off.throughput)
        ratio = mi.Float(off.ratio)
        status = mi.UInt32(off.status)
        prev_si = off.si
        prev_bsdf = prev_si.bsdf()
        base_valid = base.si.is_valid()

        # ---- transition into this vertex ------------------------------------------------------------------
        not_connected = active & (status == NOT_CONNECTED) & ~first
        recent = active & (status == RECENTLY_CONNECTED)
        connected = active & (status == CONNECTED)
        reconnect = (not_connected & ~off.b_delta & _rough_vertex(prev_bsdf)
                     & (~base_valid | _rough_vertex(base.bsdf)))
        replay = not_connected & ~reconnect

        # Reconnection to the base path's vertex (or to its direction, at infinity). Segments are measured from
        # the rays' actual origins (the surface point pushed off by Mitsuba's ray epsilon), as the base path's
        # ray was: for coinciding vertices the shift is then the identity to rounding, Jacobian 1.
        origin = prev_si.spawn_ray(base.si.p - prev_si.p).o
        to_base = base.si.p - origin
        dist2_off = dr.maximum(dr.squared_norm(to_base), MIN_DISTANCE2)
        wo_rc = dr.select(base_valid, to_base * dr.rsqrt(dist2_off), off.b_dir)
        shadow = dr.select(base_valid, prev_si.spawn_ray_to(base.si.p), prev_si.spawn_ray(off.b_dir))
        visible = ~scene.ray_test(shadow, reconnect)
        # Everything per unit *area* at the shared vertex: the base path's density of having found it,
        # b_pdf * cos / t^2, and the offset's geometry term cos' / d'^2. Their ratio is the Jacobian over the
        # base's solid-angle pdf, without forming either one (grazing hits make both blow up in float32).
        area_pdf_base = off.b_pdf * dr.abs(dr.dot(base.si.n, off.b_dir)) / dr.square(base.si.t)
        geometry_off = dr.abs(dr.dot(base.si.n, wo_rc)) / dist2_off
        area_ok = area_pdf_base > 0.0
        conv_rc = dr.select(base_valid, geometry_off / dr.select(area_ok, area_pdf_base, 1.0), dr.rcp(off.b_pdf))

        # One BSDF evaluation at the offset's previous vertex serves both a new reconnection (towards the base
        # path's vertex) and a reconnection made one vertex earlier (towards the base path's next direction).
        eval_dir = dr.select(reconnect, wo_rc, off.b_dir)
        val, pdf = prev_bsdf.eval_pdf(ctx, prev_si, prev_si.to_local(eval_dir), reconnect | recent)
        conv = dr.select(reconnect, conv_rc, dr.rcp(off.b_pdf))  # = Jacobian / base pdf
        step_f = dr.select(reconnect | recent, val * conv, 1.0)
        step_r = dr.select(reconnect | recent, pdf * conv, 1.0)
        fail = reconnect & (~visible | (base_valid & ~area_ok) | ~(off.b_pdf > 0.0))
        fail |= recent & ~(off.b_pdf > 0.0)
        fail |= recent & off.b_delta  # a delta direction of the base path is not one for the offset's own wi

        # Replay at the offset's own vertex (also the primary ray in the first iteration).
        bs, bs_weight = prev_bsdf.sample(ctx, prev_si, off.lobe, off.direction, replay)
        own_ray = dr.select(first, off.ray, prev_si.spawn_ray(prev_si.to_world(bs.wo)))
        traced = (first & active) | replay
        si_own = scene.ray_intersect(own_ray, ray_flags=mi.RayFlags.All, coherent=first, active=traced)
        reverse_reconnects = (~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta) & off.b_rough_vertex
                              & (~si_own.is_valid() | _rough_vertex(si_own.bsdf())))
        fail |= replay & (reverse_reconnects | (dr.max(bs_weight) == 0.0))
        step_f = dr.select(replay, bs_weight, step_f)
        step_f = dr.select(connected, off.b_weight, step_f)

        throughput = dr.select(active, throughput * step_f, throughput)
        ratio = dr.select(active, ratio * step_r, ratio)
        active &= ~fail
        throughput = dr.select(active, throughput, 0.0)
        ratio = dr.select(active, ratio, 0.0)

        # The offset's vertex here, and how it arrived (for its own emitter/BSDF MIS).
        si_base_wi = mi.SurfaceInteraction3f(base.si)
        si_base_wi.wi = dr.select(reconnect & base_valid, base.si.to_local(-wo_rc), base.si.wi)
        own = (first & active) | replay
        si = dr.select(own, si_own, si_base_wi)
        shared = active & ~own  # this vertex is the base path's
        status = dr.select(reconnect, RECENTLY_CONNECTED, dr.select(recent, CONNECTED, status))
        prev_it = _interaction(prev_si)
        prev_pdf = dr.select(replay, bs.pdf, dr.select(reconnect | recent, pdf, off.b_pdf))
        prev_delta = dr.select(replay, mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta),
                               dr.select(reconnect | recent, False, off.b_delta))
        prev_delta |= first

        # ---- emission found at this vertex ------------------------------------------------------------------
        ds = mi.DirectionSample3f(scene, si=si, ref=prev_it)
        em_pdf = scene.pdf_emitter_direction(prev_it, ds, active & ~prev_delta)
        emitted = dr.select(active, throughput * mis_power(prev_pdf, em_pdf) * ds.emitter.eval(si, active), 0.0)
        w_hit = dr.select(active, _balance(ratio), 1.0)

        # ---- next-event estimation: the base path's light sample ------------------------------------------
        has_vertex = active & si.is_valid()
        light = base.light
        nee_on = has_vertex & base.nee_sampled & (depth + 1 < max_depth)
        bsdf = si.bsdf()
        can_nee = nee_on & _rough_vertex(bsdf)
        infinite = mi.has_flag(light.emitter.flags(), mi.EmitterFlags.Infinite)
        to_light = light.p - si.p
        dist_off = dr.norm(to_light)
        # (spelled out: the one-argument constructor resolves to the PositionSample3f overload and drops emitter)
        ds_off = mi.DirectionSample3f(light.p, light.n, light.uv, light.time, light.pdf, light.delta,
                                      dr.select(infinite, light.d, to_light / dr.maximum(dist_off, 1e-12)),
                                      dr.select(infinite, light.dist, dist_off), light.emitter)
        own_shadow = dr.select(infinite, si.spawn_ray(light.d), si.spawn_ray_to(light.p))
        light_visible = dr.select(shared, base.light_visible,
                                  ~scene.ray_test(own_shadow, can_nee & ~shared))
        le = scene.eval_emitter_direction(_interaction(si), ds_off, can_nee)
        light_pdf = scene.pdf_emitter_direction(_interaction(si), ds_off, can_nee & ~light.delta)
        # Per unit area on an area emitter (see the reconnection above); delta and infinitely distant emitters
        # keep the point (or direction), so the Jacobian is 1 and solid-angle pdfs compare directly.
        on_area = ~light.delta & ~infinite
        area_pdf_light = light.pdf * dr.abs(dr.dot(light.n, light.d)) / dr.square(light.dist)
        geometry_l = dr.abs(dr.dot(light.n, ds_off.d)) / dr.maximum(dr.square(dist_off), MIN_DISTANCE2)
        conv_l = dr.select(on_area, geometry_l / area_pdf_light, dr.rcp(light.pdf))  # = Jacobian / base pdf
        # The offset produces this event only where its own emitter-sampling density is finite and nonzero
        # (a vertex in the emitter's plane, or behind it, cannot): then the weight is the base path's alone.
        can_nee &= light.delta | (dr.isfinite(light_pdf) & (light_pdf > 0.0))
        b_val, b_pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds_off.d), can_nee)
        mis_l = dr.select(light.delta, 1.0, mis_power(light_pdf, b_pdf))
        nee = throughput * mis_l * b_val * le * conv_l
        nee = dr.select(can_nee & light_visible, nee, 0.0)
        r_light = dr.select(light.delta, 1.0, light_pdf * conv_l)
        w_nee = dr.select(can_nee, _balance(ratio * r_light), 1.0)

        # ---- stash what the next transition needs --------------------------------------------------------
        continues = has_vertex & (depth + 1 < max_depth)
        new = HybridState(
            active=continues, status=status, throughput=throughput, ratio=ratio, ray=off.ray, si=si,
            lobe=mi.Float(samples.lobe), direction=mi.Point2f(samples.direction), b_pdf=base.sample.pdf,
            b_weight=base.sample_weight, b_dir=base.si.to_world(base.sample.wo),
            b_delta=mi.has_flag(base.sample.sampled_type, mi.BSDFFlags.Delta),
            b_rough_vertex=_rough_vertex(base.bsdf))
        return new, OffsetEvents(emitted=emitted, nee=nee, w_hit=w_hit, w_nee=w_nee)

    def scale(self, offset: HybridState, factor: mi.Float, active: mi.Bool) -> HybridState:
        offset.throughput = dr.select(active, offset.throughput * factor, offset.throughput)
        return offset

    def kill(self, offset: HybridState, dead: mi.Bool) -> HybridState:
        offset.active = offset.active & ~dead
        return offset


DEFAULT_SHIFT = "hybrid"


def make_shift(name: str | None) -> Shift:
    """The shift called ``name`` (None = the default). Raises ValueError for a shift that is not available."""
    name = name or DEFAULT_SHIFT
    if name == "replay":
        return ReplayShift()
    if name == "hybrid":
        return HybridShift()
    raise ValueError(f"unknown shift {name!r}; expected one of {SHIFT_NAMES}")
