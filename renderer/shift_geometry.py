"""What the hybrid shift (renderer/hybrid.py) reads off a vertex and a scene: the vertex classes its strategies
are chosen by (rough, specular, glossy, curved mirror), the scene checks that decide which strategies a kernel
compiles, the half-vector copy, and small helpers shared with the manifold reconnection (renderer/manifold.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

# Float32-safe thresholds. Every threshold that decides whether a shift *exists* is applied to a quantity that is
# symmetric in the pair (base path, offset path), so the shift from the neighbour's base path back to this one
# makes the same decision and the two MIS weights of a pair still sum to 1 (an asymmetric cut-off would bias).
MIN_DISTANCE2 = 1e-12  # squared distances below this (coinciding points) are clamped, not divided by
MIN_HALF_COSINE = 1e-4  # half-vector copy fails where either path's direction grazes the microfacet: there the
#                         Jacobian is a ratio of two float32 cosines that carry absolute errors of ~1e-7
FOLLOW_CURVATURE = 0.5  # move onto a specular vertex where curvature * segment exceeds this (follows)


def is_rough(flags: mi.UInt32) -> mi.Bool:
    """A vertex a reconnection may start or end at: its BSDF (``flags``) has a non-delta lobe. Mitsuba exposes
    no roughness; delta lobes are the specular ones, every other lobe is treated as rough: a classification by
    lobe type (the reference implementation's threshold, roughness 0.001, is nearly the same line)."""
    return mi.has_flag(flags, mi.BSDFFlags.Smooth)


def is_specular(flags: mi.UInt32, valid: mi.Bool) -> mi.Bool:
    """A surface vertex whose BSDF has delta lobes only (smooth mirror, glass, a null interface)."""
    return valid & mi.has_flag(flags, mi.BSDFFlags.Delta) & ~mi.has_flag(flags, mi.BSDFFlags.Smooth)


def curvature(si: mi.SurfaceInteraction3f) -> mi.Float:
    """Largest normal curvature along the surface's parameter directions, |dn/du| / |dp/du| (and v): 1/R on a
    sphere of radius R, 0 on flat geometry (needs ``RayFlags.dNSdUV``; 0 where the parameterization degenerates)."""
    def along(dn: mi.Vector3f, dp: mi.Vector3f) -> mi.Float:
        dp2 = dr.squared_norm(dp)
        k = dr.sqrt(dr.squared_norm(dn) / dr.maximum(dp2, 1e-30))
        return dr.select((dp2 > 1e-20) & dr.isfinite(k), k, 0.0)
    return dr.maximum(along(si.dn_du, si.dp_du), along(si.dn_dv, si.dp_dv))


def curved_enough(si: mi.SurfaceInteraction3f, a: mi.Point3f, b: mi.Point3f) -> mi.Bool:
    """The curvature rule of :func:`follows`: curvature at ``si`` times the shorter of the segments from the
    pair of vertices ``a``, ``b`` to it exceeds FOLLOW_CURVATURE (symmetric in ``a`` and ``b``)."""
    d_min = dr.sqrt(dr.minimum(dr.squared_norm(si.p - a), dr.squared_norm(si.p - b)))
    return curvature(si) * d_min > FOLLOW_CURVATURE


def follows(flags: mi.UInt32, valid: mi.Bool, si: mi.SurfaceInteraction3f, a: mi.Point3f, b: mi.Point3f) -> mi.Bool:
    """Whether an offset moves onto this specular vertex rather than replaying towards it.

    Replay sends a ray parallel to the base path's, offset by the pixel footprint ``delta``; after a curved
    interface of curvature k it diverges by ~2 k delta (mirror). Moving onto the base vertex keeps the point and
    turns the direction by ~delta / d (``d`` the segment to the vertex). Moving on wins where k d > 1/2
    (FOLLOW_CURVATURE): never on flat mirrors or panes (replay stays exactly parallel there), nor where the BSDF
    passes light straight through (a null lobe: thin dielectrics), for which replay is exact. A function of the
    vertex and of the two segments' shorter length only, so the pair decides alike from either side."""
    return is_specular(flags, valid) & ~mi.has_flag(flags, mi.BSDFFlags.Null) & curved_enough(si, a, b)


def is_mirror(flags: mi.UInt32, valid: mi.Bool) -> mi.Bool:
    """A smooth mirror: delta reflection only (no transmission, no null lobe, nothing non-delta)."""
    return (is_specular(flags, valid) & mi.has_flag(flags, mi.BSDFFlags.DeltaReflection)
            & ~mi.has_flag(flags, mi.BSDFFlags.DeltaTransmission) & ~mi.has_flag(flags, mi.BSDFFlags.Null))


def is_glossy(flags: mi.UInt32) -> mi.Bool:
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
    """Whether any shape's BSDF is glossy in the sense of :func:`is_glossy`: only then does the kernel need the
    half-vector copy's code, which costs time per sample even where unused."""
    glossy, diffuse = int(mi.BSDFFlags.Glossy), int(mi.BSDFFlags.Diffuse)
    return _scene_has(scene, lambda flags: bool(flags & glossy) and not flags & diffuse)


def scene_has_specular_vertices(scene: mi.Scene) -> bool:
    """Whether any shape's BSDF has delta lobes only (:func:`is_specular`): only then does the kernel need the
    follow strategy and the surfaces' normal derivatives (:func:`curvature`)."""
    delta, smooth = int(mi.BSDFFlags.Delta), int(mi.BSDFFlags.Smooth)
    return _scene_has(scene, lambda flags: bool(flags & delta) and not flags & smooth)


def scene_has_curved_mirrors(scene: mi.Scene) -> bool:
    """Whether any shape that could be curved (not a rectangle or disk) has a mirror BSDF (:func:`is_mirror`): only
    then does the kernel need the manifold reconnection, whose symbolic branch costs time per sample even where
    no offset takes it. Instances and shapes without a BSDF count as "maybe"."""
    reflect = int(mi.BSDFFlags.DeltaReflection)
    others = int(mi.BSDFFlags.Smooth | mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.Null)
    return _scene_has(scene, lambda flags: bool(flags & reflect) and not flags & others, flat_ok=False)


def bsdf_id(bsdf: mi.BSDFPtr) -> mi.UInt32:
    """The BSDF instance's registry id: equal ids mean the same material (and so the same index of refraction)."""
    return dr.reinterpret_array(mi.UInt32, bsdf)


def as_interaction(si: mi.SurfaceInteraction3f) -> mi.Interaction3f:
    it = dr.zeros(mi.Interaction3f)
    it.t, it.time, it.p, it.n = si.t, si.time, si.p, si.n
    return it


def emitter_hit(scene: mi.Scene, si: mi.SurfaceInteraction3f, ref: mi.Interaction3f,
                 active: mi.Bool) -> mi.DirectionSample3f:
    """``mi.DirectionSample3f(scene, si, ref)`` (the emitter found by a ray from ``ref``), looked up only where
    ``active``: the constructor has no mask, and each lookup is a call on the shape."""
    d = si.p - ref.p
    dist = dr.norm(d)
    d = dr.select(si.is_valid(), d / dist, -si.wi)  # a miss keeps its world-space wi, as in Mitsuba
    return mi.DirectionSample3f(si.p, si.sh_frame.n, si.uv, si.time, mi.Float(0.0), mi.Bool(False), d, dist,
                                si.emitter(scene, active))


def balance(ratio: mi.Float) -> mi.Float:
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

