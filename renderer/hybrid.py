"""Kettunen et al.'s hybrid shift, adapted to Mitsuba 3 (:class:`HybridShift`): reconnection at rough
vertices, moving onto curved specular ones (and the manifold reconnection through curved mirrors:
renderer/manifold.py), half-vector copy at glossy ones, replay elsewhere. It also implements
:class:`renderer.shift_protocol.ConnectingShift`, which lets the integrator carry connected offsets cheaply.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from gradsep.renderer.hybrid_state import (
    CONNECTED,
    NOT_CONNECTED,
    PENDING,
    RECENTLY_CONNECTED,
    Arrival,
    ConnectedState,
    HybridState,
    OwnVertex,
    Strategy,
    Transition,
)
from gradsep.renderer.manifold import through_mirror
from gradsep.renderer.shift_geometry import (
    MIN_DISTANCE2,
    as_interaction,
    balance,
    bsdf_id,
    emitter_hit,
    follows,
    half_vector_shift,
    is_glossy,
    is_mirror,
    is_rough,
    offset_eta,
    scene_has_curved_mirrors,
    scene_has_glossy_vertices,
    scene_has_specular_vertices,
)
from gradsep.renderer.shift_protocol import OffsetEvents
from gradsep.renderer.vertex import Vertex, VertexSamples, mis_power


class HybridShift:
    """Kettunen et al.'s hybrid shift, adapted to Mitsuba 3: reconnect where possible, otherwise copy the
    half-vector, and replay the random numbers after a delta lobe.

    The offset path starts from its own primary ray. Leaving its vertex ``y_k`` (base path at ``x_k``):

    * **Reconnection** to the base path's next vertex ``x_{k+1}`` when the base path sampled a non-delta lobe at
      ``x_k``, both ``x_k`` and ``y_k`` have non-delta lobes, ``x_{k+1}`` has one too or is the sky
      (reconnection at infinity). The Jacobian of moving ``x_{k+1}`` is ``|cos' d^2| / |cos d'^2|``; occlusion
      of the new segment fails the shift.
    * **Follow** when all of the above holds except that ``x_{k+1}`` has delta lobes only and lies on a curved
      surface (:func:`follows`: curvature times the shorter segment to it above ``FOLLOW_CURVATURE``, no null
      lobe): the offset moves onto ``x_{k+1}`` exactly as a reconnection does (visibility, Jacobian, density
      ratio) but stays on its own from there, replaying the delta lobe for its own incoming direction. A
      parallel replayed ray would meet a curved mirror or lens elsewhere and turn by ~2 k delta; moving onto the
      point turns it by ~delta / d. On flat mirrors and panes, and through thin dielectrics, replay is exact.
    * **Manifold reconnection** where the follow strategy would apply and ``x_{k+1}`` is a curved mirror: the
      offset waits one iteration, then solves for the mirror point that reflects ``y_k`` onto ``x_{k+2}`` and
      connects there (:func:`renderer.manifold.through_mirror`; compiled only for scenes with a possibly curved mirror).
    * **Half-vector copy** otherwise, when the base path sampled a non-delta lobe and both vertices are glossy
      (non-delta lobes, none of them diffuse): :func:`half_vector_shift` reflects or refracts the offset about
      the base path's microfacet normal, copied in the local shading frame, and the offset traces its own ray. A
      refraction needs the same material at both vertices (its index of refraction), else the shift fails.
    * **Replay** everywhere else -- after a delta lobe of the base path, where ``y_k`` has only delta lobes, at
      diffuse vertices that do not reconnect: the offset samples its own BSDF with the base path's random
      numbers (for a smooth mirror or glass choosing the same lobe this is the half-vector copy; on a diffuse
      lobe it is the same local direction; in primary sample space its Jacobian is 1) and traces its own ray.

    Each strategy is invertible only if the shift from the offset back to the base path picks the same one, so the
    offset fails where it would not: after a half-vector copy or a replay, if the reverse shift would reconnect or
    follow (or, after a replay that sampled a non-delta lobe between glossy vertices, copy the half-vector). Once
    reconnected,
    the offset shares every later vertex: one BSDF evaluation at the reconnection vertex for its own incoming
    direction, afterwards the base path's own BSDF weights, and no further rays. Next-event estimation on a not yet
    connected offset reuses the base path's light sample (same point on the emitter; same direction for emitters at
    infinity) with the Jacobian of that reconnection and its own shadow ray; on shared vertices it reuses the base
    path's visibility.

    MIS between base and offset: the balance heuristic over path densities, ``w = 1 / (1 + R)`` with ``R`` the
    offset path's density (as a base path of its pixel) times the shift's Jacobian over the base path's density,
    tracked as a running ratio. Within each path, emitter sampling and BSDF sampling are combined with the power
    heuristic exactly as in the base path tracer; the shift maps light-sampled paths to light-sampled paths and
    BSDF-sampled to BSDF-sampled, so the two levels of weights compose. A failed shift sets the offset's
    contribution and density to 0 (``w = 1`` for the base path), which keeps the estimator unbiased; so does an
    offset whose BSDF value is 0 (its own base path would end there).
    """

    name = "hybrid"
    reuses_light_samples = True

    def __init__(self, manifold: bool = True) -> None:
        # False: no manifold reconnection (offsets follow at curved mirrors too): what :meth:`for_direct_layer`
        # makes, where the solve could change nothing
        self.manifold = manifold
        self._scene_features: tuple[mi.Scene, tuple[bool, bool, bool]] | None = None

    def start(self, ray: mi.Ray3f, weight: mi.Spectrum, active: mi.Bool) -> HybridState:
        return HybridState(
            active=mi.Bool(active), status=mi.UInt32(NOT_CONNECTED), throughput=mi.Spectrum(weight),
            ratio=mi.Float(1.0), ray=mi.Ray3f(ray), vertex=dr.zeros(mi.SurfaceInteraction3f),
            vertex_bsdf=dr.zeros(mi.BSDFPtr), vertex_flags=mi.UInt32(0), replay_lobe=mi.Float(0.0),
            replay_direction=mi.Point2f(0.0), base_point=mi.Point3f(0.0), base_flags=mi.UInt32(0),
            base_bsdf_id=mi.UInt32(0), base_wi=mi.Vector3f(0.0, 0.0, 1.0), base_wo=mi.Vector3f(0.0, 0.0, 1.0),
            base_out_dir=mi.Vector3f(0.0, 0.0, 1.0), base_out_pdf=mi.Float(1.0),
            base_out_weight=mi.Spectrum(1.0), base_out_delta=mi.Bool(False), base_out_eta=mi.Float(1.0),
            mirror_si=dr.zeros(mi.SurfaceInteraction3f), mirror_origin=mi.Point3f(0.0),
            mirror_origin_pdf=mi.Float(1.0))

    def for_direct_layer(self) -> HybridShift:
        """This shift as the ``--gradients direct`` mode runs it: without the manifold reconnection. There the
        offsets take their steps at the direct layer's vertices 0 and 1 only, and an offset that waits at a
        mirror x_1 (the solve's trigger; a mirror found at vertex 0 never waits, as the camera ray's direction is
        fixed by the pixel) would be solved at x_2, which that mode never reaches; waiting or following at x_1
        changes no event of the direct layer (the mirror is not an emitter, and the next-event estimate at vertex 1
        belongs to the indirect layer). So the solve could only cost recording, compilation and masked work
        (docs/decisions.md, "The manifold solve as a symbolic loop"; frames bit for bit equal,
        tests/renderer/test_gpt.py)."""
        return self if not self.manifold else HybridShift(manifold=False)

    def _features(self, scene: mi.Scene) -> tuple[bool, bool, bool]:
        """(half-vector copy, follow, manifold reconnection) compiled for this scene: only the strategies its
        materials and shapes can use (checked once per scene)."""
        if self._scene_features is None or self._scene_features[0] is not scene:
            follow = scene_has_specular_vertices(scene)
            self._scene_features = (scene, (scene_has_glossy_vertices(scene), follow,
                                            follow and self.manifold and scene_has_curved_mirrors(scene)))
        return self._scene_features[1]

    def ray_flags(self, scene: mi.Scene) -> mi.RayFlags:
        """Surface data every intersection needs: normal derivatives where the follow strategy reads curvature."""
        return mi.RayFlags.All | mi.RayFlags.dNSdUV if self._features(scene)[1] else mi.RayFlags.All

    def step(self, scene: mi.Scene, off: HybridState, base: Vertex, depth: mi.UInt32, max_depth: mi.UInt32,
             samples: VertexSamples, later: bool = False) -> tuple[HybridState, OffsetEvents]:
        """Advance the offset by the base path's vertex ``x_{k+1}`` (``base``): choose the strategy, make the
        transition, arrive, and evaluate the offset's two events there. ``later``: the vertex is known not to be
        the first, so the primary-ray case is a literal False (its code folds away)."""
        use_copy, use_follow, use_manifold = self._features(scene)
        st = self._choose(off, base, depth, use_follow, use_manifold, use_copy, later)
        tr = self._transition(scene, off, base, st, use_copy, use_manifold)
        own = self._trace_own(scene, off, st, tr, use_copy, use_follow)
        at = self._arrive(off, base, st, tr, own, use_manifold)
        emitted, w_hit = self._emission(scene, base, st, at)
        nee, w_nee, has_vertex = self._next_event(scene, base, st, at, depth, max_depth)
        new = HybridState(
            active=has_vertex & (depth + 1 < max_depth), status=at.status, throughput=at.throughput,
            ratio=at.ratio, ray=off.ray, vertex=at.si, vertex_bsdf=at.bsdf, vertex_flags=at.flags,
            replay_lobe=mi.Float(samples.lobe), replay_direction=mi.Point2f(samples.direction),
            base_point=mi.Point3f(base.si.p), base_flags=base.bsdf_flags, base_bsdf_id=bsdf_id(base.bsdf),
            base_wi=mi.Vector3f(base.si.wi), base_wo=mi.Vector3f(base.sample.wo),
            base_out_dir=base.si.to_world(base.sample.wo), base_out_pdf=base.sample.pdf,
            base_out_weight=base.sample_weight,
            base_out_delta=mi.has_flag(base.sample.sampled_type, mi.BSDFFlags.Delta),
            base_out_eta=mi.Float(base.sample.eta),
            mirror_si=dr.select(st.wait, base.si, off.mirror_si) if use_manifold else off.mirror_si,
            mirror_origin=dr.select(st.wait, off.base_point, off.mirror_origin) if use_manifold else off.mirror_origin,
            mirror_origin_pdf=(dr.select(st.wait, off.base_out_pdf, off.mirror_origin_pdf) if use_manifold
                               else off.mirror_origin_pdf))
        return new, OffsetEvents(emitted=emitted, nee=nee, w_hit=w_hit, w_nee=w_nee)

    def _choose(self, off: HybridState, base: Vertex, depth: mi.UInt32, use_follow: bool, use_manifold: bool,
                use_copy: bool, later: bool = False) -> Strategy:
        """The strategy out of ``y_k``. Every condition is a symmetric function of the pair (base vertex x_k,
        offset vertex y_k) and of the path being shifted, so the shift back from the offset's own base path
        chooses the same strategy."""
        first = mi.Bool(False) if later else depth == 0
        active = mi.Bool(off.active)
        status = mi.UInt32(off.status)
        base_valid = base.si.is_valid()
        not_connected = active & (status == NOT_CONNECTED) & ~first
        off_rough = is_rough(off.vertex_flags)
        base_rough = is_rough(off.base_flags)
        rough_pair = not_connected & ~off.base_out_delta & base_rough & off_rough
        reconnect = rough_pair & (~base_valid | is_rough(base.bsdf_flags))
        # A base vertex with delta lobes only (mirror, glass, null interface): move onto that very point and follow
        # the delta lobe from there with the offset's own incoming direction (replay at it), instead of replaying
        # from y_k -- which would send a parallel ray to another point of a curved mirror or lens.
        if use_follow:
            follow = rough_pair & follows(base.bsdf_flags, base_valid, base.si, off.base_point, off.vertex.p)
        else:
            follow = mi.Bool(False)
        # A curved mirror (not itself an emitter): wait here and, next iteration, connect to the vertex after it
        # through the mirror point that reflects this offset's vertex onto it (the manifold reconnection).
        if use_manifold:
            wait = follow & is_mirror(base.bsdf_flags, base_valid) & ~(dr.max(base.emission) > 0.0)
            follow &= ~wait
        else:
            wait = mi.Bool(False)
        to_vertex = reconnect | follow
        glossy_pair = is_glossy(off.base_flags) & is_glossy(off.vertex_flags)
        copy = (not_connected & ~to_vertex & ~wait & ~off.base_out_delta & off_rough & glossy_pair if use_copy
                else mi.Bool(False))
        return Strategy(first=first, recent=active & (status == RECENTLY_CONNECTED),
                        connected=active & (status == CONNECTED), pending=active & (status == PENDING),
                        reconnect=reconnect, follow=follow, wait=wait, copy=copy,
                        replay=not_connected & ~to_vertex & ~copy & ~wait, base_rough=base_rough,
                        off_rough=off_rough, glossy_pair=glossy_pair)

    def _reconnection(self, scene: mi.Scene, off: HybridState, base: Vertex,
                      to_vertex: mi.Bool) -> tuple[mi.Vector3f, mi.Float, mi.Bool]:
        """**Reconnection** (and the first half of **follow**): the direction from ``y_k`` to the base path's
        vertex ``x_{k+1}`` (or the base path's direction, at infinity), its Jacobian over the base path's
        solid-angle pdf at ``x_k``, and whether the segment exists (unoccluded, a positive base density)."""
        prev_si = off.vertex
        base_valid = base.si.is_valid()
        # Segments are measured from the rays' actual origins (the surface point pushed off by Mitsuba's ray
        # epsilon), as the base path's ray was: for coinciding vertices the shift is the identity to rounding.
        origin = prev_si.spawn_ray(base.si.p - prev_si.p).o
        to_base = base.si.p - origin
        dist2_off = dr.maximum(dr.squared_norm(to_base), MIN_DISTANCE2)
        wo_rc = dr.select(base_valid, to_base * dr.rsqrt(dist2_off), off.base_out_dir)
        shadow = dr.select(base_valid, prev_si.spawn_ray_to(base.si.p), prev_si.spawn_ray(off.base_out_dir))
        visible = ~scene.ray_test(shadow, to_vertex)
        # Everything per unit *area* at the shared vertex: the base path's density of having found it,
        # base_out_pdf * cos / t^2, and the offset's geometry term cos' / d'^2. Their ratio is the Jacobian over
        # the base's solid-angle pdf, without forming either one (grazing hits make both blow up in float32).
        area_pdf_base = off.base_out_pdf * dr.abs(dr.dot(base.si.n, off.base_out_dir)) / dr.square(base.si.t)
        geometry_off = dr.abs(dr.dot(base.si.n, wo_rc)) / dist2_off
        area_ok = area_pdf_base > 0.0
        conv_rc = dr.select(base_valid, geometry_off / dr.select(area_ok, area_pdf_base, 1.0),
                            dr.rcp(off.base_out_pdf))
        return wo_rc, conv_rc, visible & (~base_valid | area_ok)

    def _half_vector_copy(self, off: HybridState) -> tuple[mi.Bool, mi.Vector3f, mi.Float]:
        """**Half-vector copy** at ``y_k``: (exists, direction in world space, Jacobian). A refraction keeps the
        material's index of refraction (the base path's, or its reciprocal where the offset arrives from the
        other side): it needs the same BSDF at both vertices."""
        prev_si = off.vertex
        hv = half_vector_shift(off.base_wi, off.base_wo, off.base_out_eta, prev_si.wi,
                               offset_eta(off.base_wi, off.base_out_eta, prev_si.wi))
        refracts = mi.Frame3f.cos_theta(off.base_wi) * mi.Frame3f.cos_theta(off.base_wo) < 0.0
        ok = hv.ok & (~refracts | (bsdf_id(off.vertex_bsdf) == off.base_bsdf_id))
        return ok, prev_si.to_world(hv.wo), hv.jacobian

    def _transition(self, scene: mi.Scene, off: HybridState, base: Vertex, st: Strategy, use_copy: bool,
                    use_manifold: bool) -> Transition:
        """The strategies that evaluate the offset's BSDF at ``y_k`` for a direction they construct
        (reconnection, follow, half-vector copy, manifold reconnection) or for the base path's next direction
        (an offset reconnected last iteration): one BSDF evaluation serves them all; ``conv`` is the Jacobian
        over the base path's pdf, in solid angle at that vertex."""
        ctx = mi.BSDFContext()
        prev_si, prev_bsdf = off.vertex, off.vertex_bsdf
        to_vertex = st.to_vertex
        wo_rc, conv_rc, rc_ok = self._reconnection(scene, off, base, to_vertex)
        eval_dir = dr.select(to_vertex, wo_rc, off.base_out_dir)
        copy_dir = mi.Vector3f(0.0, 0.0, 1.0)
        if use_copy:
            hv_ok, copy_dir, hv_jacobian = self._half_vector_copy(off)
            eval_dir = dr.select(to_vertex, wo_rc, dr.select(st.copy, copy_dir, off.base_out_dir))
            conv = dr.select(to_vertex, conv_rc, dr.select(st.copy, hv_jacobian, 1.0) * dr.rcp(off.base_out_pdf))
        else:
            conv = dr.select(to_vertex, conv_rc, dr.rcp(off.base_out_pdf))
        mani = mi.Bool(False)
        mirror_wi = mi.Vector3f(0.0, 0.0, 1.0)
        if use_manifold:
            mani, mani_dir, mani_conv, mani_f, mirror_wi = through_mirror(scene, self.ray_flags(scene), off, prev_si,
                                                                          base, st.pending)
            eval_dir = dr.select(mani, mani_dir, eval_dir)
            conv = dr.select(mani, mani_conv, conv)
        evaluated = to_vertex | st.recent | st.copy | mani
        val, pdf = prev_bsdf.eval_pdf(ctx, prev_si, prev_si.to_local(eval_dir), evaluated)
        step_f = dr.select(evaluated, val * conv, 1.0)
        if use_manifold:
            step_f = dr.select(mani, step_f * mani_f, step_f)
        step_r = dr.select(evaluated, pdf * conv, 1.0)
        fail = evaluated & ~(off.base_out_pdf > 0.0)
        fail |= evaluated & ~(dr.max(val) > 0.0)  # the offset's own base path would end here: no such pair
        fail |= to_vertex & ~rc_ok
        fail |= st.recent & off.base_out_delta  # a delta direction of the base path is not one for the offset's wi
        fail |= st.pending & ~mani  # no path through the mirror (or the reverse shift would not take one)
        if use_copy:
            fail |= st.copy & ~hv_ok
        return Transition(evaluated=evaluated, pdf=pdf, step_f=step_f, step_r=step_r, fail=fail,
                          reconnection_dir=wo_rc, copy_dir=copy_dir, mirror=mani, mirror_wi=mirror_wi)

    def _trace_own(self, scene: mi.Scene, off: HybridState, st: Strategy, tr: Transition, use_copy: bool,
                   use_follow: bool) -> OwnVertex:
        """**Replay** at ``y_k`` (the base path's random numbers), and the ray of every offset that finds its next
        vertex itself (primary ray, replay, half-vector copy). Adds to ``tr.fail`` where the reverse shift, from
        this offset as a base path back to the base path, would pick another strategy: it reconnects (or
        follows) where the offset left a non-delta lobe towards a rough (or curved specular) vertex; after a
        replay with a non-delta lobe between two glossy vertices, it would copy the half-vector."""
        ctx = mi.BSDFContext()
        prev_si, prev_bsdf = off.vertex, off.vertex_bsdf
        bs, bs_weight = prev_bsdf.sample(ctx, prev_si, off.replay_lobe, off.replay_direction, st.replay)
        own_dir = prev_si.to_world(bs.wo)
        if use_copy:
            own_dir = dr.select(st.copy, tr.copy_dir, own_dir)
        own_ray = dr.select(st.first, off.ray, prev_si.spawn_ray(own_dir))
        traced = (st.first & off.active) | st.replay | st.copy
        si_own = scene.ray_intersect(own_ray, ray_flags=self.ray_flags(scene), coherent=st.first, active=traced)
        own_valid = si_own.is_valid()
        own_bsdf = si_own.bsdf()
        own_flags = dr.select(own_valid, own_bsdf.flags(), 0)
        own_nondelta = ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        if use_copy:
            own_nondelta |= st.copy
        both_rough = own_nondelta & st.base_rough & st.off_rough
        reverse_target = ~own_valid | is_rough(own_flags)
        if use_follow:
            reverse_target |= follows(own_flags, own_valid, si_own, prev_si.p, off.base_point)
        reverse_reconnects = both_rough & reverse_target
        reverse_strategy_differs = reverse_reconnects
        if use_copy:
            reverse_strategy_differs |= both_rough & st.glossy_pair
            tr.fail |= st.copy & reverse_reconnects
        tr.fail |= st.replay & (reverse_strategy_differs | (dr.max(bs_weight) == 0.0))
        tr.step_f = dr.select(st.replay, bs_weight, tr.step_f)
        tr.step_f = dr.select(st.connected, off.base_out_weight, tr.step_f)
        return OwnVertex(si=si_own, bsdf=own_bsdf, flags=own_flags, sample=bs, weight=bs_weight)

    def _arrive(self, off: HybridState, base: Vertex, st: Strategy, tr: Transition, own_vertex: OwnVertex,
                use_manifold: bool) -> Arrival:
        """Apply the transition: the offset's throughput, density ratio and status, and the vertex it arrives at
        -- its own, the base path's (with its own incoming direction), or ``y_k`` while it waits at a mirror."""
        active = mi.Bool(off.active)
        throughput = dr.select(active, off.throughput * tr.step_f, off.throughput)
        ratio = dr.select(active, off.ratio * tr.step_r, off.ratio)
        active &= ~tr.fail
        throughput = dr.select(active, throughput, 0.0)
        ratio = dr.select(active, ratio, 0.0)

        base_valid = base.si.is_valid()
        si_base_wi = mi.SurfaceInteraction3f(base.si)
        si_base_wi.wi = dr.select(st.to_vertex & base_valid, base.si.to_local(-tr.reconnection_dir), base.si.wi)
        own = (st.first & active) | st.replay | st.copy
        si = dr.select(own, own_vertex.si, si_base_wi)
        flags = dr.select(own, own_vertex.flags, base.bsdf_flags)
        bsdf = dr.select(own, own_vertex.bsdf, base.bsdf)
        if use_manifold:
            # a waiting offset stays where it is; one connected through the mirror arrives from the mirror point
            si_base_wi.wi = dr.select(tr.mirror, tr.mirror_wi, si_base_wi.wi)
            si = dr.select(st.wait, off.vertex, dr.select(tr.mirror, si_base_wi, si))
            flags = dr.select(st.wait, off.vertex_flags, flags)
            bsdf = dr.select(st.wait, off.vertex_bsdf, bsdf)
        status = dr.select(st.reconnect | tr.mirror, RECENTLY_CONNECTED,
                           dr.select(st.recent, CONNECTED, mi.UInt32(off.status)))
        status = dr.select(st.wait, PENDING, status)
        bs = own_vertex.sample
        prev_pdf = dr.select(st.replay, bs.pdf, dr.select(tr.evaluated, tr.pdf, off.base_out_pdf))
        prev_delta = dr.select(st.replay, mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta),
                               dr.select(tr.evaluated, False, off.base_out_delta))
        prev_delta |= st.first
        # arrived by the mirror's delta reflection: emission found there has MIS weight 1, as on the base path
        prev_pdf = dr.select(tr.mirror, 1.0, prev_pdf)
        prev_delta |= tr.mirror
        # An offset connected before this vertex arrived at the base path's vertex from the base path's previous
        # vertex and in its direction: the emission found and its emitter-sampling pdf are the base path's (only
        # the BSDF pdf of the MIS weight is the offset's own), and so is the next-event estimate per unit
        # throughput, with a light-sample density ratio of 1. Nothing to evaluate there.
        reuse = st.connected | st.recent
        return Arrival(active=active, throughput=throughput, ratio=ratio, status=status, si=si, bsdf=bsdf,
                       flags=flags, prev=as_interaction(off.vertex), prev_pdf=prev_pdf, prev_delta=prev_delta,
                       shared=active & ~own, reuse=reuse,
                       evaluate=active & ~reuse & ~st.wait)  # a waiting offset has no events (nor has the base)

    def _emission(self, scene: mi.Scene, base: Vertex, st: Strategy, at: Arrival) -> tuple[mi.Spectrum, mi.Float]:
        """The offset's contribution to the event "emission found at this vertex", and its MIS weight."""
        ds = emitter_hit(scene, at.si, at.prev, at.evaluate)
        em_pdf = scene.pdf_emitter_direction(at.prev, ds, at.evaluate & ~at.prev_delta)
        em_pdf = dr.select(at.reuse, base.emitter_pdf, em_pdf)
        emission = dr.select(at.reuse, base.emission, ds.emitter.eval(at.si, at.evaluate))
        emitting = at.active & ~st.wait
        emitted = dr.select(emitting, at.throughput * mis_power(at.prev_pdf, em_pdf) * emission, 0.0)
        return emitted, dr.select(emitting, balance(at.ratio), 1.0)

    def _next_event(self, scene: mi.Scene, base: Vertex, st: Strategy, at: Arrival, depth: mi.UInt32,
                    max_depth: mi.UInt32) -> tuple[mi.Spectrum, mi.Float, mi.Bool]:
        """The offset's next-event estimate with the base path's light sample (reconnected to the same emitter
        point, or the same direction at infinity) and its own shadow ray; on shared vertices the base path's
        estimate per unit throughput. Returns (contribution, MIS weight, the offset has a surface vertex)."""
        ctx = mi.BSDFContext()
        si = at.si
        has_vertex = at.active & si.is_valid()
        light = base.light
        nee_on = has_vertex & base.nee_sampled & (depth + 1 < max_depth)
        can_nee = nee_on & is_rough(at.flags) & ~at.reuse & ~st.wait
        infinite = base.light_infinite
        to_light = light.p - si.p
        dist_off = dr.norm(to_light)
        # (spelled out: the one-argument constructor resolves to the PositionSample3f overload and drops emitter)
        ds_off = mi.DirectionSample3f(light.p, light.n, light.uv, light.time, light.pdf, light.delta,
                                      dr.select(infinite, light.d, to_light / dr.maximum(dist_off, 1e-12)),
                                      dr.select(infinite, light.dist, dist_off), light.emitter)
        own_shadow = dr.select(infinite, si.spawn_ray(light.d), si.spawn_ray_to(light.p))
        light_visible = dr.select(at.shared, base.light_visible,
                                  ~scene.ray_test(own_shadow, can_nee & ~at.shared))
        le = scene.eval_emitter_direction(as_interaction(si), ds_off, can_nee)
        light_pdf = scene.pdf_emitter_direction(as_interaction(si), ds_off, can_nee & ~light.delta)
        # Per unit area on an area emitter (see the reconnection); delta and infinitely distant emitters keep the
        # point (or direction), so the Jacobian is 1 and solid-angle pdfs compare directly.
        on_area = ~light.delta & ~infinite
        area_pdf_light = light.pdf * dr.abs(dr.dot(light.n, light.d)) / dr.square(light.dist)
        geometry_l = dr.abs(dr.dot(light.n, ds_off.d)) / dr.maximum(dr.square(dist_off), MIN_DISTANCE2)
        conv_l = dr.select(on_area, geometry_l / area_pdf_light, dr.rcp(light.pdf))  # = Jacobian / base pdf
        # The offset produces this event only where its own emitter-sampling density is finite and nonzero
        # (a vertex in the emitter's plane, or behind it, cannot): then the weight is the base path's alone.
        can_nee &= light.delta | (dr.isfinite(light_pdf) & (light_pdf > 0.0))
        b_val, b_pdf = at.bsdf.eval_pdf(ctx, si, si.to_local(ds_off.d), can_nee)
        mis_l = dr.select(light.delta, 1.0, mis_power(light_pdf, b_pdf))
        nee = at.throughput * mis_l * b_val * le * conv_l
        nee = dr.select(can_nee & light_visible, nee, 0.0)
        r_light = dr.select(light.delta, 1.0, light_pdf * conv_l)
        w_nee = dr.select(can_nee, balance(at.ratio * r_light), 1.0)
        reused_nee = at.reuse & nee_on
        nee = dr.select(reused_nee, at.throughput * base.nee_weight, nee)
        w_nee = dr.select(reused_nee, balance(at.ratio), w_nee)
        return nee, w_nee, has_vertex

    # ---- connected offsets (renderer.shift_protocol.ConnectingShift) -----------------------------------------

    def settled(self, offset: HybridState) -> mi.Bool:
        """Finished, connected, or reconnected in the last iteration (:meth:`summarize` evaluates the one BSDF
        value the next step would, so such a lane leaves the expensive loop one iteration earlier)."""
        return ~offset.active | (offset.status == CONNECTED) | (offset.status == RECENTLY_CONNECTED)

    def summarize(self, offset: HybridState) -> ConnectedState:
        """A settled offset as a few numbers. A ``RECENTLY_CONNECTED`` one is at the base path's vertex with its
        own incoming direction: what :meth:`step` would do there next -- its BSDF value and pdf for the base
        path's outgoing direction, failing where that is 0 or the base path sampled a delta lobe -- is done here
        once and kept as the next step's weight, density ratio and emission-MIS pdf."""
        ctx = mi.BSDFContext()
        connected = offset.active & (offset.status == CONNECTED)
        recent = offset.active & (offset.status == RECENTLY_CONNECTED)
        val, pdf = offset.vertex_bsdf.eval_pdf(ctx, offset.vertex, offset.vertex.to_local(offset.base_out_dir),
                                                 recent)
        ok = recent & (offset.base_out_pdf > 0.0) & (dr.max(val) > 0.0) & ~offset.base_out_delta
        inv_pdf = dr.rcp(dr.select(ok, offset.base_out_pdf, 1.0))
        # A failed shift keeps this vertex's events (already counted) and contributes 0 from the next one on,
        # with weight 1 for the base path: a zero weight and density ratio give exactly that.
        return ConnectedState(active=connected | recent, throughput=offset.throughput, ratio=offset.ratio,
                              next_weight=dr.select(connected, offset.base_out_weight,
                                                    dr.select(ok, val * inv_pdf, 0.0)),
                              next_ratio=dr.select(recent, dr.select(ok, pdf * inv_pdf, 0.0), 1.0),
                              own_next_pdf=mi.Float(pdf), just_connected=mi.Bool(recent))

    def step_connected(self, off: ConnectedState, base: Vertex, depth: mi.UInt32,
                       max_depth: mi.UInt32) -> tuple[ConnectedState, OffsetEvents]:
        """:meth:`step` of a connected offset, without its (masked-out) work: the BSDF weight of the direction
        that led here, the base path's emission (MIS-weighted with the offset's own pdf right after the
        reconnection) and next-event estimate per unit throughput, the density ratio fixed from then on."""
        active = off.active
        throughput = dr.select(active, off.throughput * off.next_weight, 0.0)
        ratio = off.ratio * off.next_ratio
        weight = balance(ratio)
        has_vertex = active & base.si.is_valid()
        nee_on = has_vertex & base.nee_sampled & (depth + 1 < max_depth)
        emitted_weight = dr.select(off.just_connected, mis_power(off.own_next_pdf, base.emitter_pdf) * base.emission,
                                   base.emitted_weight)
        events = OffsetEvents(emitted=dr.select(active, throughput * emitted_weight, 0.0),
                              nee=dr.select(nee_on, throughput * base.nee_weight, 0.0),
                              w_hit=dr.select(active, weight, 1.0), w_nee=dr.select(nee_on, weight, 1.0))
        new = ConnectedState(active=has_vertex & (depth + 1 < max_depth), throughput=throughput, ratio=ratio,
                             next_weight=base.sample_weight, next_ratio=mi.Float(1.0), own_next_pdf=mi.Float(0.0),
                             just_connected=mi.Bool(False))
        return new, events

    def scale(self, offset: HybridState | ConnectedState, factor: mi.Float,
              active: mi.Bool) -> HybridState | ConnectedState:
        offset.throughput = dr.select(active, offset.throughput * factor, offset.throughput)
        return offset

    def kill(self, offset: HybridState | ConnectedState, dead: mi.Bool) -> HybridState | ConnectedState:
        offset.active = offset.active & ~dead
        return offset


