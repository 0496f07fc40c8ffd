"""The hybrid shift's manifold reconnection through a curved mirror: an offset that waited at the base path's
mirror vertex finds, by Newton's method on its outgoing direction, the mirror point that reflects it onto the
base path's vertex after the mirror, with ray differentials through the mirror (:func:`mirror_transfer`) as the
derivative and the shift's Jacobian.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from gradsep.renderer.hybrid_state import HybridState
from gradsep.renderer.shift_geometry import as_interaction, curved_enough, is_rough
from gradsep.renderer.vertex import Vertex

MANIFOLD_STEPS = 5  # Newton steps of the manifold reconnection through a mirror (each one ray cast)
MANIFOLD_TOLERANCE = 1e-4  # converged where the reflected ray misses its target by this fraction of the path length


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


def no_mirror_path(*_: object) -> tuple[mi.Bool, mi.Vector3f, mi.Float, mi.Spectrum, mi.Vector3f]:
    """The manifold reconnection's result where no offset waits at a mirror."""
    return mi.Bool(False), mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0), mi.Spectrum(0.0), mi.Vector3f(0.0, 0.0, 1.0)


def through_mirror(scene: mi.Scene, ray_flags: mi.RayFlags, off: HybridState, prev_si: mi.SurfaceInteraction3f,
                   base: Vertex, pending: mi.Bool) -> tuple[mi.Bool, mi.Vector3f, mi.Float, mi.Spectrum, mi.Vector3f]:
    """The manifold reconnection of the PENDING offsets (``pending``; ``prev_si`` their vertex ``y_k``): find the
    point ``y'`` of the base path's mirror that reflects ``y_k`` onto the base path's vertex after the mirror,
    ``x_{k+2}`` (``base``); ``ray_flags`` are the shift's for this scene.

    Newton's method on the direction leaving ``y_k`` (start: towards the base path's mirror point), with the
    ray differential through the mirror (:func:`mirror_transfer`) as the derivative, each step one ray cast.
    The shift's Jacobian is the ratio of the two paths' ``dA(x_{k+2}) / d omega`` through the mirror. It
    exists where ``x_{k+2}`` is rough or an emitter, Newton converged onto the same mirror shape, the
    reflected segment is unoccluded, and the reverse shift (from this offset as a base path) would wait at
    ``y'`` too (same curvature rule, its own segments). Returns (ok, direction leaving y_k, Jacobian over the
    base path's pdf at x_k, the mirror's weight for the offset, the offset's incoming direction at x_{k+2} in
    its local frame)."""
    ok = (pending & base.si.is_valid() & off.base_out_delta
          & (is_rough(base.bsdf_flags) | (dr.max(base.emission) > 0.0)))
    # A symbolic conditional: SIMD packets without a pending offset skip the solve (its seven ray casts and
    # the differentials cost as much as the rest of the step even when every lane is masked off). Its
    # arguments go through memory, so only what the solve needs is passed.
    origin = as_interaction(prev_si)
    found, direction, conv, weight, reflected = dr.if_stmt(
        args=(ok, origin, off.mirror_si, off.mirror_origin, off.mirror_origin_pdf, base.si.p, base.si.n), cond=ok,
        true_fn=lambda *a: solve_mirror(scene, ray_flags, MirrorQuery(*a)), false_fn=no_mirror_path)
    return found, direction, conv, weight, base.si.to_local(-reflected)


@dataclass
class MirrorQuery:
    """What the solve reads: the lanes that take it, the offset's vertex y_k, the base path's mirror vertex and
    the base path's vertex before it (with its pdf towards the mirror), and the target x_{k+2} with its normal."""

    ok: mi.Bool
    origin: mi.Interaction3f  # y_k
    mirror_si: mi.SurfaceInteraction3f  # the base path's mirror vertex x_{k+1}
    mirror_origin: mi.Point3f  # x_k
    mirror_origin_pdf: mi.Float  # the base path's pdf of the direction x_k -> x_{k+1}
    target: mi.Point3f  # x_{k+2}
    n_t: mi.Vector3f  # its normal


def solve_mirror(scene: mi.Scene, flags: mi.RayFlags,
                 q: MirrorQuery) -> tuple[mi.Bool, mi.Vector3f, mi.Float, mi.Spectrum, mi.Vector3f]:
    """:func:`through_mirror`'s solve, for the lanes ``q.ok``; returns the reflected direction in world space.
    Newton's steps run as a symbolic loop (one traced step, not MANIFOLD_STEPS unrolled copies: docs/decisions.md,
    "The manifold solve as a symbolic loop")."""
    ctx = mi.BSDFContext()
    ok, origin, mirror_si, mirror_origin, target, n_t = q.ok, q.origin, q.mirror_si, q.mirror_origin, q.target, q.n_t

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
    _, d = dr.while_loop(state=(mi.UInt32(0), d), cond=lambda i, _d: i < MANIFOLD_STEPS, body=newton_step,
                         label="manifold")
    ray = origin.spawn_ray(d)
    si_m = scene.ray_intersect(ray, ray_flags=flags, coherent=False, active=ok)
    tr = mirror_transfer(ray.o, si_m, target, n_t)
    length = dr.norm(si_m.p - ray.o) + dr.norm(target - si_m.p)
    ok &= si_m.is_valid() & (dr.norm(tr.q - target) < MANIFOLD_TOLERANCE * length)
    ok &= dr.reinterpret_array(mi.UInt32, si_m.shape) == dr.reinterpret_array(mi.UInt32, mirror_si.shape)
    ok &= dr.dot(target - si_m.p, tr.reflected) > 0.0
    ok &= curved_enough(si_m, origin.p, mirror_origin)
    ok &= ~scene.ray_test(si_m.spawn_ray_to(target), ok)
    _, weight = si_m.bsdf().sample(ctx, si_m, 0.0, mi.Point2f(0.5), ok)
    # Both paths' footprints from their surface points (not the epsilon-offset ray origins), alike, so that a
    # shift onto the same pixel has a Jacobian of 1 to rounding.
    base_footprint = mirror_transfer(mirror_origin, mirror_si, target, n_t).footprint(n_t)
    conv = base_footprint / mirror_transfer(origin.p, si_m, target, n_t).footprint(n_t) / q.mirror_origin_pdf
    ok &= dr.isfinite(conv) & (conv > 0.0) & (dr.max(weight) > 0.0)
    return mi.Bool(ok), mi.Vector3f(tr.direction), mi.Float(conv), mi.Spectrum(weight), mi.Vector3f(tr.reflected)

