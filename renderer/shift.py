"""Shift mappings for the G-PT integrator (renderer/gpt.py): how an offset path is built from its base path.

A shift implements the small :class:`renderer.gpt.Shift` protocol: ``start`` makes the offset's loop state from
its primary ray, ``step`` advances it by one base-path vertex and returns the offset's contributions for that
vertex's two events together with the MIS weights of the pixel pair, ``scale``/``kill`` apply the base path's
Russian roulette. The integrator never looks inside an offset state: :class:`ReplayShift` and
:class:`HybridShift` (reconnection at rough vertices, moving onto curved specular ones, half-vector copy at glossy
ones, replay elsewhere)
are interchangeable; the hybrid shift also implements :class:`renderer.gpt.ConnectingShift`, which lets the
integrator carry connected offsets cheaply.

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

from collections.abc import Callable
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from gradsep.renderer.gpt import OffsetEvents, PathState, Shift, Vertex, VertexSamples, mis_power, trace_vertex

SHIFT_NAMES: tuple[str, ...] = ("replay", "hybrid")


class ReplayShift:
    """Random replay: the offset path re-runs the path tracer with the base path's random numbers."""

    name = "replay"
    reuses_light_samples = False

    def ray_flags(self, scene: mi.Scene) -> mi.RayFlags:
        return mi.RayFlags.All

    def start(self, ray: mi.Ray3f, weight: mi.Spectrum, active: mi.Bool) -> PathState:
        return PathState.start(ray, weight, active)

    def step(self, scene: mi.Scene, offset: PathState, base: Vertex, depth: mi.UInt32, max_depth: mi.UInt32,
             samples: VertexSamples, later: bool = False) -> tuple[PathState, OffsetEvents]:
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
# Hybrid shift: reconnection at rough vertices, half-vector copy at the others, replay after delta lobes
# ---------------------------------------------------------------------------------------------------------------

NOT_CONNECTED, RECENTLY_CONNECTED, CONNECTED, PENDING = 0, 1, 2, 3  # PENDING: waiting to connect past a mirror

# Float32-safe thresholds. Every threshold that decides whether a shift *exists* is applied to a quantity that is
# symmetric in the pair (base path, offset path), so the shift from the neighbour's base path back to this one
# makes the same decision and the two MIS weights of a pair still sum to 1 (an asymmetric cut-off would bias).
MIN_DISTANCE2 = 1e-12  # squared distances below this (coinciding points) are clamped, not divided by
MIN_HALF_COSINE = 1e-4  # half-vector copy fails where either path's direction grazes the microfacet: there the
#                         Jacobian is a ratio of two float32 cosines that carry absolute errors of ~1e-7
DEFAULT_FOLLOW_CURVATURE = 0.5  # move onto a specular vertex where curvature * segment exceeds this (_follows)
MANIFOLD_STEPS = 5  # Newton steps of the manifold reconnection through a mirror (each one ray cast)
MANIFOLD_TOLERANCE = 1e-4  # converged where the reflected ray misses its target by this fraction of the path length
MANIFOLD_LOOP = True  # the Newton steps as a symbolic loop (False: unrolled, kept to compare; docs/decisions.md)
DEFAULT_FOOTPRINT = 0.0  # reconnect only where the segment to the shared vertex is this many times longer than
#                          the distance between base and offset vertex (see HybridShift; 0 = no such condition)


def _rough(flags: mi.UInt32) -> mi.Bool:
    """A vertex a reconnection may start or end at: its BSDF (``flags``) has a non-delta lobe. Mitsuba exposes
    no roughness; delta lobes are the specular ones, every other lobe is treated as rough: a classification by
    lobe type (the reference implementation's threshold, roughness 0.001, is nearly the same line)."""
    return mi.has_flag(flags, mi.BSDFFlags.Smooth)


def _specular(flags: mi.UInt32, valid: mi.Bool) -> mi.Bool:
    """A surface vertex whose BSDF has delta lobes only (smooth mirror, glass, a null interface)."""
    return valid & mi.has_flag(flags, mi.BSDFFlags.Delta) & ~mi.has_flag(flags, mi.BSDFFlags.Smooth)


def _curvature(si: mi.SurfaceInteraction3f) -> mi.Float:
    """Largest normal curvature along the surface's parameter directions, |dn/du| / |dp/du| (and v): 1/R on a
    sphere of radius R, 0 on flat geometry (needs ``RayFlags.dNSdUV``; 0 where the parameterization degenerates)."""
    def along(dn: mi.Vector3f, dp: mi.Vector3f) -> mi.Float:
        dp2 = dr.squared_norm(dp)
        k = dr.sqrt(dr.squared_norm(dn) / dr.maximum(dp2, 1e-30))
        return dr.select((dp2 > 1e-20) & dr.isfinite(k), k, 0.0)
    return dr.maximum(along(si.dn_du, si.dp_du), along(si.dn_dv, si.dp_dv))


def _curved_enough(si: mi.SurfaceInteraction3f, a: mi.Point3f, b: mi.Point3f, threshold: float) -> mi.Bool:
    """The curvature rule of :func:`_follows`: curvature at ``si`` times the shorter of the segments from the
    pair of vertices ``a``, ``b`` to it exceeds ``threshold`` (symmetric in ``a`` and ``b``)."""
    d_min = dr.sqrt(dr.minimum(dr.squared_norm(si.p - a), dr.squared_norm(si.p - b)))
    return _curvature(si) * d_min > threshold


def _follows(flags: mi.UInt32, valid: mi.Bool, si: mi.SurfaceInteraction3f, a: mi.Point3f, b: mi.Point3f,
             threshold: float = 0.5) -> mi.Bool:
    """Whether an offset moves onto this specular vertex rather than replaying towards it.

    Replay sends a ray parallel to the base path's, offset by the pixel footprint ``delta``; after a curved
    interface of curvature k it diverges by ~2 k delta (mirror). Moving onto the base vertex keeps the point and
    turns the direction by ~delta / d (``d`` the segment to the vertex). Moving on wins where k d > 1/2
    (``threshold``): never on flat mirrors or panes (replay stays exactly parallel there), nor where the BSDF
    passes light straight through (a null lobe: thin dielectrics), for which replay is exact. A function of the
    vertex and of the two segments' shorter length only, so the pair decides alike from either side."""
    return _specular(flags, valid) & ~mi.has_flag(flags, mi.BSDFFlags.Null) & _curved_enough(si, a, b, threshold)


def _mirror(flags: mi.UInt32, valid: mi.Bool) -> mi.Bool:
    """A smooth mirror: delta reflection only (no transmission, no null lobe, nothing non-delta)."""
    return (_specular(flags, valid) & mi.has_flag(flags, mi.BSDFFlags.DeltaReflection)
            & ~mi.has_flag(flags, mi.BSDFFlags.DeltaTransmission) & ~mi.has_flag(flags, mi.BSDFFlags.Null))


@dataclass
class MirrorTransfer:
    """A ray from ``o`` to a mirror point, reflected there, meeting the plane through a target point."""

    direction: mi.Vector3f  # unit direction from o to the mirror point
    reflected: mi.Vector3f  # reflected direction
    q: mi.Point3f  # where the reflected ray meets the target's plane
    dq_a: mi.Vector3f  # derivatives of q with respect to the direction leaving o, along e_a and e_b (unit)
    dq_b: mi.Vector3f
    e_a: mi.Vector3f  # orthonormal basis perpendicular to ``direction``
    e_b: mi.Vector3f

    def footprint(self, n_target: mi.Vector3f) -> mi.Float:
        """|dA(q) / d omega|: area on the target's plane per unit solid angle leaving o."""
        return dr.abs(dr.dot(dr.cross(self.dq_a, self.dq_b), n_target))


def mirror_transfer(o: mi.Point3f, si_m: mi.SurfaceInteraction3f, target: mi.Point3f,
                    n_target: mi.Vector3f) -> MirrorTransfer:
    """Ray differentials through one mirror vertex ``si_m`` (which needs ``RayFlags.dNSdUV``).

    Perturbing the unit direction d leaving ``o`` by e (perpendicular to d) moves the hit point along the
    surface's tangent plane, dp = t (e - d (e.n_g) / (d.n_g)), turns the normal by dn = dn/du du + dn/dv dv with
    (du, dv) from dp in the surface parameterization, turns the reflection r = d - 2 (d.n) n by
    dr = e - 2 ((e.n) + (d.dn)) n - 2 (d.n) dn, and moves the reflected ray's crossing of the target's plane by
    dp + s dr projected along r onto that plane."""
    to_m = si_m.p - o
    t = dr.norm(to_m)
    d = to_m / dr.maximum(t, 1e-30)
    n = si_m.sh_frame.n
    e_a, e_b = mi.coordinate_system(d)
    d_n = dr.dot(d, n)
    r = d - 2.0 * d_n * n
    r_nt = dr.dot(r, n_target)
    s = dr.dot(target - si_m.p, n_target) / r_nt
    q = si_m.p + s * r
    a11, a12, a22 = (dr.dot(si_m.dp_du, si_m.dp_du), dr.dot(si_m.dp_du, si_m.dp_dv),
                     dr.dot(si_m.dp_dv, si_m.dp_dv))
    det = a11 * a22 - a12 * a12

    def derivative(e: mi.Vector3f) -> mi.Vector3f:
        dp = t * (e - d * (dr.dot(e, si_m.n) / dr.dot(d, si_m.n)))
        b1, b2 = dr.dot(dp, si_m.dp_du), dr.dot(dp, si_m.dp_dv)
        du, dv = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
        dn = si_m.dn_du * du + si_m.dn_dv * dv
        d_r = e - 2.0 * (dr.dot(e, n) + dr.dot(d, dn)) * n - 2.0 * d_n * dn
        w = dp + s * d_r
        return w - r * (dr.dot(n_target, w) / r_nt)

    return MirrorTransfer(direction=d, reflected=r, q=q, dq_a=derivative(e_a), dq_b=derivative(e_b), e_a=e_a,
                          e_b=e_b)


def _no_mirror_path(*_: object) -> tuple[mi.Bool, mi.Vector3f, mi.Float, mi.Spectrum, mi.Vector3f]:
    """The manifold reconnection's result where no offset waits at a mirror."""
    return mi.Bool(False), mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0), mi.Spectrum(0.0), mi.Vector3f(0.0, 0.0, 1.0)


def _glossy(flags: mi.UInt32) -> mi.Bool:
    """A vertex whose non-delta lobes are all glossy (no diffuse lobe): where a shift that does not reconnect
    copies the half-vector. Diffuse vertices replay instead: the same cosine-weighted random numbers give the
    offset the same local direction, which follows a diffuse base path more closely than a mirrored one."""
    return mi.has_flag(flags, mi.BSDFFlags.Glossy) & ~mi.has_flag(flags, mi.BSDFFlags.Diffuse)


def _scene_has(scene: mi.Scene, kind: Callable[[int], bool], flat_ok: bool = True) -> bool:
    """Whether any shape's BSDF flags satisfy ``kind`` (instances and shapes without a BSDF count as "maybe");
    ``flat_ok`` False skips rectangles and disks (shapes that cannot be curved)."""
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is None or shape.class_name() == "Instance":
            return True
        if kind(int(bsdf.flags())) and (flat_ok or shape.class_name() not in ("Rectangle", "Disk")):
            return True
    return False


def scene_has_glossy_vertices(scene: mi.Scene) -> bool:
    """Whether any shape's BSDF is glossy in the sense of :func:`_glossy`: only then does the kernel need the
    half-vector copy's code, which costs ~7% per sample even where unused."""
    glossy, diffuse = int(mi.BSDFFlags.Glossy), int(mi.BSDFFlags.Diffuse)
    return _scene_has(scene, lambda flags: bool(flags & glossy) and not flags & diffuse)


def scene_has_specular_vertices(scene: mi.Scene) -> bool:
    """Whether any shape's BSDF has delta lobes only (:func:`_specular`): only then does the kernel need the
    follow strategy and the surfaces' normal derivatives (:func:`_curvature`)."""
    delta, smooth = int(mi.BSDFFlags.Delta), int(mi.BSDFFlags.Smooth)
    return _scene_has(scene, lambda flags: bool(flags & delta) and not flags & smooth)


def scene_has_curved_mirrors(scene: mi.Scene) -> bool:
    """Whether any shape that could be curved (not a rectangle or disk) has a mirror BSDF (:func:`_mirror`): only
    then does the kernel need the manifold reconnection, whose symbolic branch costs ~15 % per sample even where
    no offset takes it. Instances and shapes without a BSDF count as "maybe"."""
    reflect = int(mi.BSDFFlags.DeltaReflection)
    others = int(mi.BSDFFlags.Smooth | mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.Null)
    return _scene_has(scene, lambda flags: bool(flags & reflect) and not flags & others, flat_ok=False)


def _bsdf_id(bsdf: mi.BSDFPtr) -> mi.UInt32:
    """The BSDF instance's registry id: equal ids mean the same material (and so the same index of refraction)."""
    return dr.reinterpret_array(mi.UInt32, bsdf)


def _interaction(si: mi.SurfaceInteraction3f) -> mi.Interaction3f:
    it = dr.zeros(mi.Interaction3f)
    it.t, it.time, it.p, it.n = si.t, si.time, si.p, si.n
    return it


def _emitter_hit(scene: mi.Scene, si: mi.SurfaceInteraction3f, ref: mi.Interaction3f,
                 active: mi.Bool) -> mi.DirectionSample3f:
    """``mi.DirectionSample3f(scene, si, ref)`` (the emitter found by a ray from ``ref``), looked up only where
    ``active``: the constructor has no mask, and each lookup is a call on the shape."""
    d = si.p - ref.p
    dist = dr.norm(d)
    d = dr.select(si.is_valid(), d / dist, -si.wi)  # a miss keeps its world-space wi, as in Mitsuba
    return mi.DirectionSample3f(si.p, si.sh_frame.n, si.uv, si.time, mi.Float(0.0), mi.Bool(False), d, dist,
                                si.emitter(scene, active))


def _balance(ratio: mi.Float) -> mi.Float:
    """Weight 1 / (1 + p_other / p_this) of this technique; 0 where the ratio is not finite (p_this ~ 0)."""
    w = dr.rcp(1.0 + ratio)
    return dr.select(dr.isfinite(w) & dr.isfinite(ratio), w, 0.0)


@dataclass
class HalfVectorShift:
    """Result of :func:`half_vector_shift`: the offset's outgoing direction (local frame), the solid-angle
    Jacobian ``|d wo' / d wo|`` and whether the shift exists."""

    wo: mi.Vector3f
    jacobian: mi.Float
    ok: mi.Bool


def half_vector_shift(wi: mi.Vector3f, wo: mi.Vector3f, eta: mi.Float, wi_off: mi.Vector3f,
                      eta_off: mi.Float) -> HalfVectorShift:
    """Copy the base path's (generalized) half-vector to the offset vertex, in the local shading frames.

    ``wi``/``wo``: the base path's directions at its vertex, ``eta`` the relative index of refraction of ``wo``'s
    side over ``wi``'s (Mitsuba's ``BSDFSample3f.eta``; 1 for a reflection); ``wi_off`` the offset's incoming
    direction and ``eta_off`` its relative index for a refraction. Reflection maps to reflection
    (``wo' = reflect(wi', h)``, Jacobian ``|wo'.h| / |wo.h|``) and refraction to refraction about the same
    microfacet normal (Jacobian ``(eta/eta')^2 |H'|^2 / |H|^2 * |wo.h| / |wo'.h|`` with ``H = wi + eta wo``, from
    Walter et al. 2007, eq. 16). The shift does not exist where the offset would switch between reflection and
    transmission (total internal reflection included), leave through the other side of the surface, or where a
    direction of either path grazes the microfacet (:data:`MIN_HALF_COSINE`); each condition reads the same from
    the other path, so the inverse shift fails in exactly the same cases.
    """
    refract = mi.Frame3f.cos_theta(wi) * mi.Frame3f.cos_theta(wo) < 0.0
    eta = dr.select(refract, eta, 1.0)
    eta_off = dr.select(refract, eta_off, 1.0)
    big_h = wi + eta * wo
    h2 = dr.squared_norm(big_h)
    h = big_h * dr.rsqrt(dr.maximum(h2, 1e-30))
    h = dr.select(dr.dot(h, wi) < 0.0, -h, h)
    cos_i = dr.dot(wi_off, h)
    # reflection about h
    wo_reflect = 2.0 * cos_i * h - wi_off
    # refraction through the microfacet h: tangential part scaled by 1/eta', Snell's law for the normal part
    sin2_t = (1.0 - dr.square(cos_i)) / dr.square(eta_off)
    cos_t = dr.safe_sqrt(1.0 - sin2_t)
    wo_refract = -wi_off / eta_off + (cos_i / eta_off - cos_t) * h
    wo_off = dr.normalize(dr.select(refract, wo_refract, wo_reflect))
    same_side = mi.Frame3f.cos_theta(wi_off) * mi.Frame3f.cos_theta(wo_off) > 0.0
    wo_h = dr.abs(dr.dot(wo, h))
    wo_off_h = dr.abs(dr.dot(wo_off, h))
    ok = (dr.minimum(dr.dot(wi, h), cos_i) > MIN_HALF_COSINE) & (dr.minimum(wo_h, wo_off_h) > MIN_HALF_COSINE)
    ok &= dr.select(refract, (sin2_t < 1.0) & ~same_side, same_side)
    h2_off = dr.squared_norm(wi_off + eta_off * wo_off)
    jacobian_t = dr.square(eta / eta_off) * (h2_off / dr.maximum(h2, 1e-30)) * (wo_h / dr.maximum(wo_off_h, 1e-30))
    jacobian = dr.select(refract, jacobian_t, wo_off_h / dr.maximum(wo_h, 1e-30))
    return HalfVectorShift(wo=wo_off, jacobian=dr.select(ok, jacobian, 0.0), ok=ok)


def offset_eta(wi: mi.Vector3f, eta: mi.Float, wi_off: mi.Vector3f) -> mi.Float:
    """The offset's relative index of refraction at the same material: the base path's ``eta`` where both
    arrive from the same side of the surface, its reciprocal where the offset arrives from the other side."""
    same_side = mi.Frame3f.cos_theta(wi) * mi.Frame3f.cos_theta(wi_off) > 0.0
    return dr.select(same_side, eta, dr.rcp(eta))


@dataclass
class HybridState:
    """Loop state of one hybrid offset path ȳ, between two iterations.

    In Kettunen et al.'s names: the offset sits at its vertex ``y_k`` (``vertex``, with the offset's own incoming
    direction; for a recently connected offset, the base path's vertex seen from the offset's previous vertex),
    and the base path has just left ``x_k``; the ``base_*`` fields stash what the transition into the next vertex
    needs from the base path's step out of ``x_k``. The ``mirror_*`` fields are set while the offset waits for a
    manifold reconnection through the base path's mirror vertex ``x_{k+1}``.
    """

    active: mi.Bool
    status: mi.UInt32  # NOT_CONNECTED, RECENTLY_CONNECTED, CONNECTED or PENDING (waiting at a mirror)
    throughput: mi.Spectrum  # f(offset prefix) * Jacobians / p(base prefix), with the base's roulette
    ratio: mi.Float  # p(offset prefix as a base path) * Jacobians / p(base prefix); roulette excluded
    ray: mi.Ray3f  # primary ray (first iteration only)
    vertex: mi.SurfaceInteraction3f  # y_k
    vertex_bsdf: mi.BSDFPtr  # the BSDF at y_k, and its flags
    vertex_flags: mi.UInt32
    replay_lobe: mi.Float  # the base path's random numbers at x_k, for a replay at y_k
    replay_direction: mi.Point2f
    base_point: mi.Point3f  # x_k
    base_flags: mi.UInt32  # BSDF flags at x_k
    base_bsdf_id: mi.UInt32  # the registry id of the BSDF at x_k (same id: same material, same IOR)
    base_wi: mi.Vector3f  # the base path's incoming and outgoing directions at x_k, in its local shading frame
    base_wo: mi.Vector3f
    base_out_dir: mi.Vector3f  # the outgoing direction in world space
    base_out_pdf: mi.Float  # its solid-angle pdf
    base_out_weight: mi.Spectrum  # its BSDF weight (value * cos / pdf)
    base_out_delta: mi.Bool  # it came from a delta lobe
    base_out_eta: mi.Float  # its relative index of refraction (1 for reflections)
    mirror_si: mi.SurfaceInteraction3f  # PENDING: the base path's mirror vertex x_{k+1}
    mirror_origin: mi.Point3f  # PENDING: the base path's vertex x_k before the mirror
    mirror_origin_pdf: mi.Float  # PENDING: the pdf of the base path's direction from x_k to the mirror


@dataclass
class ConnectedState:
    """A connected hybrid offset, summarised: its events are the base path's times its throughput."""

    active: mi.Bool
    throughput: mi.Spectrum
    ratio: mi.Float  # fixed once connected: the shared vertices have the same density in both paths
    next_weight: mi.Spectrum  # BSDF weight of the direction leaving the previous (shared) vertex: the base
    #                           path's, or, just after the reconnection, the offset's own for its incoming direction
    next_ratio: mi.Float  # density ratio of that direction: 1 (shared), or the offset's pdf / the base path's
    own_next_pdf: mi.Float  # just after the reconnection: the offset's pdf of that direction, for its emission MIS
    just_connected: mi.Bool  # just reconnected: the next vertex's emission is weighted with ``own_next_pdf``


@dataclass
class Strategy:
    """How each offset leaves its vertex ``y_k`` in this iteration (per-lane masks; see :class:`HybridShift`),
    and the vertex classes they were decided from."""

    first: mi.Bool  # the offset's primary ray (depth 0)
    recent: mi.Bool  # reconnected last iteration: its BSDF at the shared vertex for the base path's direction
    connected: mi.Bool  # shares every vertex: the base path's BSDF weight
    pending: mi.Bool  # waited at a mirror last iteration: manifold reconnection now
    reconnect: mi.Bool  # to the base path's next vertex x_{k+1} (or its direction, at infinity)
    follow: mi.Bool  # onto a curved specular x_{k+1}, staying on its own from there
    wait: mi.Bool  # at y_k, for a manifold reconnection through the mirror x_{k+1} next iteration
    copy: mi.Bool  # half-vector copy at y_k
    replay: mi.Bool  # the base path's random numbers at y_k
    base_rough: mi.Bool  # x_k has a non-delta lobe
    off_rough: mi.Bool  # y_k has one
    glossy_pair: mi.Bool  # both are glossy (:func:`_glossy`)

    @property
    def to_vertex(self) -> mi.Bool:
        """The offset moves onto the base path's vertex x_{k+1}."""
        return self.reconnect | self.follow


@dataclass
class Transition:
    """The offset's step from ``y_k`` into its next vertex: direction evaluated at ``y_k`` by a reconnection,
    follow, half-vector copy or manifold reconnection, the step's throughput factor and density ratio, and
    where the shift fails."""

    evaluated: mi.Bool  # the BSDF at y_k was evaluated for a direction not sampled by the offset
    pdf: mi.Float  # the offset's pdf of that direction
    step_f: mi.Spectrum  # throughput factor (BSDF value * Jacobian / base pdf)
    step_r: mi.Float  # density-ratio factor
    fail: mi.Bool
    reconnection_dir: mi.Vector3f  # y_k -> x_{k+1} (world)
    copy_dir: mi.Vector3f  # the half-vector copy's direction (world), where ``copy``
    mirror: mi.Bool  # the manifold reconnection through the mirror succeeded
    mirror_wi: mi.Vector3f  # after it: the offset's incoming direction at x_{k+2} (local)


@dataclass
class OwnVertex:
    """The vertex an offset finds by tracing its own ray (primary ray, replay, half-vector copy)."""

    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    flags: mi.UInt32
    sample: mi.BSDFSample3f  # the replayed BSDF sample at y_k
    weight: mi.Spectrum  # its BSDF weight


@dataclass
class Arrival:
    """Where an offset is after this iteration's transition, and how it arrived (for its emitter/BSDF MIS)."""

    active: mi.Bool
    throughput: mi.Spectrum
    ratio: mi.Float
    status: mi.UInt32
    si: mi.SurfaceInteraction3f  # its vertex (its own, the base path's with its own wi, or y_k while waiting)
    bsdf: mi.BSDFPtr
    flags: mi.UInt32
    prev: mi.Interaction3f  # y_k
    prev_pdf: mi.Float  # pdf of the direction that led here, and whether it was a delta lobe
    prev_delta: mi.Bool
    shared: mi.Bool  # this vertex is the base path's
    reuse: mi.Bool  # connected before this vertex: emission and next-event estimate are the base path's
    evaluate: mi.Bool  # its own events must be evaluated here


class HybridShift:
    """Kettunen et al.'s hybrid shift, adapted to Mitsuba 3: reconnect where possible, otherwise copy the
    half-vector, and replay the random numbers after a delta lobe.

    The offset path starts from its own primary ray. Leaving its vertex ``y_k`` (base path at ``x_k``):

    * **Reconnection** to the base path's next vertex ``x_{k+1}`` when the base path sampled a non-delta lobe at
      ``x_k``, both ``x_k`` and ``y_k`` have non-delta lobes, ``x_{k+1}`` has one too or is the sky
      (reconnection at infinity), and both segments ``x_k x_{k+1}`` and ``y_k x_{k+1}`` are at least
      ``footprint`` times longer than ``|x_k - y_k|`` (default 0: no length condition). The Jacobian of moving
      ``x_{k+1}`` is ``|cos' d^2| / |cos d'^2|``; occlusion of the new segment fails the shift. A positive
      ``footprint`` keeps reconnections out of corners, where ``x_{k+1}`` is so close that the Jacobian swings
      wildly between neighbouring pixels (hybrid noisier than replay along the foot of walls); it is symmetric
      in the pair, so the inverse shift makes the same choice. Measured, it removes that band but costs as much
      elsewhere (docs/renderer.md), hence off by default.
    * **Follow** when all of the above holds except that ``x_{k+1}`` has delta lobes only and lies on a curved
      surface (:func:`_follows`: curvature times the shorter segment to it above ``follow_curvature``, no null
      lobe): the offset moves onto ``x_{k+1}`` exactly as a reconnection does (visibility, Jacobian, density
      ratio) but stays on its own from there, replaying the delta lobe for its own incoming direction. A
      parallel replayed ray would meet a curved mirror or lens elsewhere and turn by ~2 k delta; moving onto the
      point turns it by ~delta / d. On flat mirrors and panes, and through thin dielectrics, replay is exact.
    * **Manifold reconnection** where the follow strategy would apply and ``x_{k+1}`` is a curved mirror: the
      offset waits one iteration, then solves for the mirror point that reflects ``y_k`` onto ``x_{k+2}`` and
      connects there (:meth:`_through_mirror`; compiled only for scenes with a possibly curved mirror).
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

    def __init__(self, footprint: float = DEFAULT_FOOTPRINT, half_vector: bool = True,
                 follow_specular: bool = True, follow_curvature: float = DEFAULT_FOLLOW_CURVATURE,
                 manifold: bool = True) -> None:
        if not footprint >= 0.0:
            raise ValueError(f"footprint must be >= 0, got {footprint}")
        if not follow_curvature >= 0.0:
            raise ValueError(f"follow_curvature must be >= 0, got {follow_curvature}")
        self.follow_curvature = float(follow_curvature)
        self.footprint = float(footprint)
        self.half_vector = bool(half_vector)  # False: replay wherever the shift does not reconnect (comparison)
        self.follow_specular = bool(follow_specular)  # False: replay towards specular vertices (comparison)
        self.manifold = bool(manifold)  # False: follow at mirrors too, instead of connecting past them (comparison)
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

    def _far(self, a: mi.Point3f, b: mi.Point3f, target: mi.Point3f, at_infinity: mi.Bool) -> mi.Bool:
        """Both segments a-target and b-target are ``footprint`` times longer than a-b (always, at infinity)."""
        sep2 = dr.squared_norm(a - b) * (self.footprint * self.footprint)
        return at_infinity | ((dr.squared_norm(target - a) > sep2) & (dr.squared_norm(target - b) > sep2))

    def for_direct_layer(self) -> HybridShift:
        """This shift as the ``--gradients direct`` mode runs it: without the manifold reconnection. There the
        offsets take their steps at the direct layer's vertices 0 and 1 only, and an offset that waits at a
        mirror x_1 (the solve's trigger; a mirror found at vertex 0 never waits, as the camera ray's direction is
        fixed by the pixel) would be solved at x_2, which that mode never reaches; waiting or following at x_1
        changes no event of the direct layer (the mirror is not an emitter, and the next-event estimate at vertex 1
        belongs to the indirect layer). So the solve could only cost recording, compilation and masked work
        (docs/decisions.md, "The manifold solve as a symbolic loop"; frames bit for bit equal,
        tests/renderer/test_gpt.py)."""
        if not self.manifold:
            return self
        return HybridShift(self.footprint, self.half_vector, self.follow_specular, self.follow_curvature,
                           manifold=False)

    def _features(self, scene: mi.Scene) -> tuple[bool, bool, bool]:
        """(half-vector copy, follow, manifold reconnection) compiled for this scene: only the strategies its
        materials and shapes can use (checked once per scene)."""
        if self._scene_features is None or self._scene_features[0] is not scene:
            follow = self.follow_specular and scene_has_specular_vertices(scene)
            self._scene_features = (scene, (self.half_vector and scene_has_glossy_vertices(scene), follow,
                                            follow and self.manifold and scene_has_curved_mirrors(scene)))
        return self._scene_features[1]

    def ray_flags(self, scene: mi.Scene) -> mi.RayFlags:
        """Surface data every intersection needs: normal derivatives where the follow strategy reads curvature."""
        return mi.RayFlags.All | mi.RayFlags.dNSdUV if self._features(scene)[1] else mi.RayFlags.All

    def _through_mirror(self, scene: mi.Scene, off: HybridState, prev_si: mi.SurfaceInteraction3f, base: Vertex,
                        pending: mi.Bool) -> tuple[mi.Bool, mi.Vector3f, mi.Float, mi.Spectrum, mi.Vector3f]:
        """The manifold reconnection of a PENDING offset: find the point ``y'`` of the base path's mirror that
        reflects the offset's vertex ``y_k`` onto the base path's vertex after the mirror, ``x_{k+2}``.

        Newton's method on the direction leaving ``y_k`` (start: towards the base path's mirror point), with the
        ray differential through the mirror (:func:`mirror_transfer`) as the derivative, each step one ray cast.
        The shift's Jacobian is the ratio of the two paths' ``dA(x_{k+2}) / d omega`` through the mirror. It
        exists where ``x_{k+2}`` is rough or an emitter, Newton converged onto the same mirror shape, the
        reflected segment is unoccluded, and the reverse shift (from this offset as a base path) would wait at
        ``y'`` too (same curvature rule, its own segments). Returns (ok, direction leaving y_k, Jacobian over the
        base path's pdf at x_k, the mirror's weight for the offset, the offset's incoming direction at x_{k+2} in
        its local frame)."""
        ok = (pending & base.si.is_valid() & off.base_out_delta
              & (_rough(base.bsdf_flags) | (dr.max(base.emission) > 0.0)))
        # A symbolic conditional: SIMD packets without a pending offset skip the solve (its seven ray casts and
        # the differentials cost as much as the rest of the step even when every lane is masked off). Its
        # arguments go through memory, so only what the solve needs is passed.
        origin = _interaction(prev_si)
        found, direction, conv, weight, reflected = dr.if_stmt(
            args=(ok, origin, off.mirror_si, off.mirror_origin, off.mirror_origin_pdf, base.si.p, base.si.n), cond=ok,
            true_fn=lambda *a: self._solve_mirror(scene, *a), false_fn=_no_mirror_path)
        return found, direction, conv, weight, base.si.to_local(-reflected)

    def _solve_mirror(self, scene: mi.Scene, ok: mi.Bool, origin: mi.Interaction3f, mirror_si: mi.SurfaceInteraction3f,
                      mirror_origin: mi.Point3f, mirror_origin_pdf: mi.Float, target: mi.Point3f,
                      n_t: mi.Vector3f) -> tuple[mi.Bool, mi.Vector3f, mi.Float, mi.Spectrum, mi.Vector3f]:
        """:meth:`_through_mirror`'s solve, for the lanes ``ok``; returns the reflected direction in world space."""
        ctx = mi.BSDFContext()
        flags = self.ray_flags(scene)

        def newton_step(i: mi.UInt32, d: mi.Vector3f) -> tuple[mi.UInt32, mi.Vector3f]:
            ray = origin.spawn_ray(d)
            si_m = scene.ray_intersect(ray, ray_flags=flags, coherent=False, active=ok)
            tr = mirror_transfer(ray.o, si_m, target, n_t)
            e = tr.q - target
            g11, g12, g22 = dr.dot(tr.dq_a, tr.dq_a), dr.dot(tr.dq_a, tr.dq_b), dr.dot(tr.dq_b, tr.dq_b)
            h1, h2 = dr.dot(tr.dq_a, e), dr.dot(tr.dq_b, e)
            det = g11 * g22 - g12 * g12
            step = ((g22 * h1 - g12 * h2) * tr.e_a + (g11 * h2 - g12 * h1) * tr.e_b) / det
            step *= dr.minimum(1.0, 0.25 / dr.maximum(dr.norm(step), 1e-30))  # at most ~14 degrees per step
            new_d = dr.normalize(tr.direction - step)
            return i + 1, dr.select(ok & si_m.is_valid() & dr.all(dr.isfinite(new_d)), new_d, d)

        d = dr.normalize(mirror_si.p - origin.p)
        if MANIFOLD_LOOP:
            # One traced Newton step in a symbolic loop instead of MANIFOLD_STEPS unrolled copies: the same
            # arithmetic per lane, a fraction of the code to record, hash and compile (docs/decisions.md,
            # "The manifold solve as a symbolic loop").
            _, d = dr.while_loop(state=(mi.UInt32(0), d), cond=lambda i, _d: i < MANIFOLD_STEPS, body=newton_step,
                                 label="manifold")
        else:
            for _ in range(MANIFOLD_STEPS):
                _, d = newton_step(mi.UInt32(0), d)
        ray = origin.spawn_ray(d)
        si_m = scene.ray_intersect(ray, ray_flags=flags, coherent=False, active=ok)
        tr = mirror_transfer(ray.o, si_m, target, n_t)
        length = dr.norm(si_m.p - ray.o) + dr.norm(target - si_m.p)
        ok &= si_m.is_valid() & (dr.norm(tr.q - target) < MANIFOLD_TOLERANCE * length)
        ok &= dr.reinterpret_array(mi.UInt32, si_m.shape) == dr.reinterpret_array(mi.UInt32, mirror_si.shape)
        ok &= dr.dot(target - si_m.p, tr.reflected) > 0.0
        ok &= _curved_enough(si_m, origin.p, mirror_origin, self.follow_curvature)
        ok &= ~scene.ray_test(si_m.spawn_ray_to(target), ok)
        _, weight = si_m.bsdf().sample(ctx, si_m, 0.0, mi.Point2f(0.5), ok)
        # Both paths' footprints from their surface points (not the epsilon-offset ray origins), alike, so that a
        # shift onto the same pixel has a Jacobian of 1 to rounding.
        base_footprint = mirror_transfer(mirror_origin, mirror_si, target, n_t).footprint(n_t)
        conv = base_footprint / mirror_transfer(origin.p, si_m, target, n_t).footprint(n_t) / mirror_origin_pdf
        ok &= dr.isfinite(conv) & (conv > 0.0) & (dr.max(weight) > 0.0)
        return mi.Bool(ok), mi.Vector3f(tr.direction), mi.Float(conv), mi.Spectrum(weight), mi.Vector3f(tr.reflected)

    def step(self, scene: mi.Scene, off: HybridState, base: Vertex, depth: mi.UInt32, max_depth: mi.UInt32,
             samples: VertexSamples, later: bool = False) -> tuple[HybridState, OffsetEvents]:
        """Advance the offset by the base path's vertex ``x_{k+1}`` (``base``): choose the strategy, make the
        transition, arrive, and evaluate the offset's two events there. ``later``: the vertex is known not to be
        the first, so the primary-ray case is a literal False (its code folds away)."""
        use_copy, use_follow, use_manifold = self._features(scene)
        st = self._choose(off, base, depth, use_follow, use_manifold, use_copy, later)
        tr = self._transition(scene, off, base, st, use_copy, use_manifold)
        own = self._trace_own(scene, off, base, st, tr, depth, use_copy, use_follow)
        at = self._arrive(off, base, st, tr, own, use_manifold)
        emitted, w_hit = self._emission(scene, base, st, at)
        nee, w_nee, has_vertex = self._next_event(scene, base, st, at, depth, max_depth)
        new = HybridState(
            active=has_vertex & (depth + 1 < max_depth), status=at.status, throughput=at.throughput,
            ratio=at.ratio, ray=off.ray, vertex=at.si, vertex_bsdf=at.bsdf, vertex_flags=at.flags,
            replay_lobe=mi.Float(samples.lobe), replay_direction=mi.Point2f(samples.direction),
            base_point=mi.Point3f(base.si.p), base_flags=base.bsdf_flags, base_bsdf_id=_bsdf_id(base.bsdf),
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
        off_rough = _rough(off.vertex_flags)
        base_rough = _rough(off.base_flags)
        rough_pair = not_connected & ~off.base_out_delta & base_rough & off_rough
        if self.footprint > 0.0:
            rough_pair &= self._far(off.base_point, off.vertex.p, base.si.p, ~base_valid)
        reconnect = rough_pair & (~base_valid | _rough(base.bsdf_flags))
        # A base vertex with delta lobes only (mirror, glass, null interface): move onto that very point and follow
        # the delta lobe from there with the offset's own incoming direction (replay at it), instead of replaying
        # from y_k -- which would send a parallel ray to another point of a curved mirror or lens.
        if use_follow:
            follow = rough_pair & _follows(base.bsdf_flags, base_valid, base.si, off.base_point, off.vertex.p,
                                           self.follow_curvature)
        else:
            follow = mi.Bool(False)
        # A curved mirror (not itself an emitter): wait here and, next iteration, connect to the vertex after it
        # through the mirror point that reflects this offset's vertex onto it (the manifold reconnection).
        if use_manifold:
            wait = follow & _mirror(base.bsdf_flags, base_valid) & ~(dr.max(base.emission) > 0.0)
            follow &= ~wait
        else:
            wait = mi.Bool(False)
        to_vertex = reconnect | follow
        glossy_pair = _glossy(off.base_flags) & _glossy(off.vertex_flags)
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
        ok = hv.ok & (~refracts | (_bsdf_id(off.vertex_bsdf) == off.base_bsdf_id))
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
            mani, mani_dir, mani_conv, mani_f, mirror_wi = self._through_mirror(scene, off, prev_si, base,
                                                                              st.pending)
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

    def _trace_own(self, scene: mi.Scene, off: HybridState, base: Vertex, st: Strategy, tr: Transition,
                   depth: mi.UInt32, use_copy: bool, use_follow: bool) -> OwnVertex:
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
        reverse_target = ~own_valid | _rough(own_flags)
        if use_follow:
            reverse_target |= _follows(own_flags, own_valid, si_own, prev_si.p, off.base_point,
                                       self.follow_curvature)
        reverse_reconnects = both_rough & reverse_target
        if self.footprint > 0.0:
            reverse_reconnects &= self._far(prev_si.p, off.base_point, si_own.p, ~own_valid)
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
                       flags=flags, prev=_interaction(off.vertex), prev_pdf=prev_pdf, prev_delta=prev_delta,
                       shared=active & ~own, reuse=reuse,
                       evaluate=active & ~reuse & ~st.wait)  # a waiting offset has no events (nor has the base)

    def _emission(self, scene: mi.Scene, base: Vertex, st: Strategy, at: Arrival) -> tuple[mi.Spectrum, mi.Float]:
        """The offset's contribution to the event "emission found at this vertex", and its MIS weight."""
        ds = _emitter_hit(scene, at.si, at.prev, at.evaluate)
        em_pdf = scene.pdf_emitter_direction(at.prev, ds, at.evaluate & ~at.prev_delta)
        em_pdf = dr.select(at.reuse, base.emitter_pdf, em_pdf)
        emission = dr.select(at.reuse, base.emission, ds.emitter.eval(at.si, at.evaluate))
        emitting = at.active & ~st.wait
        emitted = dr.select(emitting, at.throughput * mis_power(at.prev_pdf, em_pdf) * emission, 0.0)
        return emitted, dr.select(emitting, _balance(at.ratio), 1.0)

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
        can_nee = nee_on & _rough(at.flags) & ~at.reuse & ~st.wait
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
        le = scene.eval_emitter_direction(_interaction(si), ds_off, can_nee)
        light_pdf = scene.pdf_emitter_direction(_interaction(si), ds_off, can_nee & ~light.delta)
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
        w_nee = dr.select(can_nee, _balance(at.ratio * r_light), 1.0)
        reused_nee = at.reuse & nee_on
        nee = dr.select(reused_nee, at.throughput * base.nee_weight, nee)
        w_nee = dr.select(reused_nee, _balance(at.ratio), w_nee)
        return nee, w_nee, has_vertex

    # ---- connected offsets (renderer.gpt.ConnectingShift) ----------------------------------------------------

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
        weight = _balance(ratio)
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


DEFAULT_SHIFT = "hybrid"


def make_shift(name: str | None) -> Shift:
    """The shift called ``name`` (None = the default). Raises ValueError for a shift that is not available."""
    name = name or DEFAULT_SHIFT
    if name == "replay":
        return ReplayShift()
    if name == "hybrid":
        return HybridShift()
    raise ValueError(f"unknown shift {name!r}; expected one of {SHIFT_NAMES}")
