"""renderer/shift_geometry.py: the half-vector copy (conventions, Jacobian, invertibility) and the curvature the
follow strategy reads."""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from gradsep.renderer.shift_geometry import curvature, half_vector_shift, offset_eta  # noqa: E402
from gradsep.renderer.variant import select_variant  # noqa: E402

pytestmark = pytest.mark.render


def _vec(a: np.ndarray):
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


def _arr(v) -> np.ndarray:
    return np.stack([np.array(v.x), np.array(v.y), np.array(v.z)], axis=-1).astype(np.float64)


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def glossy_samples(n: int, seed: int = 0):
    """Base-path samples of a rough glass BSDF from both sides: (wi, wo, eta) exactly as the integrator gets them
    (Mitsuba's BSDFSample3f.eta is the relative index of wo's side over wi's; 1 for reflections)."""
    select_variant()
    rng = np.random.default_rng(seed)
    bsdf = mi.load_dict({"type": "roughdielectric", "alpha": 0.3, "int_ior": 1.5})
    wi = _unit(rng.normal(size=(n, 3)))
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = _vec(wi)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    bs, weight = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(n)), mi.Point2f(rng.random(n), rng.random(n)))
    valid = (np.array(bs.pdf) > 0) & (np.array(dr.max(weight)) > 0)
    return wi[valid], _arr(bs.wo)[valid], np.array(bs.eta, dtype=np.float64)[valid]


def test_half_vector_copy_follows_mitsubas_conventions():
    wi, wo, eta = glossy_samples(4000)
    refract = wi[:, 2] * wo[:, 2] < 0
    assert 0.2 < refract.mean() < 0.9
    np.testing.assert_allclose(eta[~refract], 1.0)
    np.testing.assert_allclose(np.sort(np.unique(np.round(eta[refract], 3))), [0.667, 1.5])
    # the generalized half-vector wi + eta wo is a microfacet normal: wi and wo obey Snell's law about it
    h = _unit(wi + np.where(refract, eta, 1.0)[:, None] * wo)
    sin_i = np.linalg.norm(np.cross(wi, h), axis=-1)
    sin_o = np.linalg.norm(np.cross(wo, h), axis=-1)
    np.testing.assert_allclose(sin_i[refract], (eta * sin_o)[refract], atol=2e-4)
    # the offset's relative index: the base path's from the same side, its reciprocal from the other side
    up, down = mi.Vector3f(0.3, 0.0, 0.9), mi.Vector3f(0.3, 0.0, -0.9)
    assert np.allclose([offset_eta(up, mi.Float(1.5), up)[0], offset_eta(up, mi.Float(1.5), down)[0],
                        offset_eta(down, mi.Float(1 / 1.5), up)[0]], [1.5, 1 / 1.5, 1.5])
    # the identity: the offset arriving as the base path did leaves as it did, with Jacobian 1
    res = half_vector_shift(_vec(wi), _vec(wo), mi.Float(eta), _vec(wi), offset_eta(_vec(wi), mi.Float(eta), _vec(wi)))
    ok = np.array(res.ok)
    assert ok.mean() > 0.99
    np.testing.assert_allclose(_arr(res.wo)[ok], wo[ok], atol=1e-5)
    np.testing.assert_allclose(np.array(res.jacobian)[ok], 1.0, rtol=1e-4)


def test_half_vector_copy_is_invertible_with_its_jacobian():
    """Shift (wi, wo) to another wi' -- a perturbed wi, or any direction on the microfacet's side, which is often
    on the other side of the surface -- then shift back: the base path's direction returns, the Jacobians
    multiply to 1, the inverse exists wherever the shift does, refractions obey Snell's law with the material's
    index on the offset's side, and the analytic Jacobian matches the ratio of solid angles of a small triangle
    of directions mapped through the shift."""
    wi, wo, eta = glossy_samples(6000, seed=1)
    rng = np.random.default_rng(2)
    refract = wi[:, 2] * wo[:, 2] < 0
    h = _unit(wi + np.where(refract, eta, 1.0)[:, None] * wo)
    h = np.where(np.einsum("ij,ij->i", h, wi)[:, None] < 0, -h, h)
    anywhere = _unit(rng.normal(size=wi.shape))
    anywhere = np.where(np.einsum("ij,ij->i", anywhere, h)[:, None] < 0, -anywhere, anywhere)
    near = _unit(wi + rng.normal(scale=0.15, size=wi.shape))
    wi2 = np.where((rng.random(len(wi)) < 0.5)[:, None], anywhere, near)
    eta2 = offset_eta(_vec(wi), mi.Float(eta), _vec(wi2))
    fwd = half_vector_shift(_vec(wi), _vec(wo), mi.Float(eta), _vec(wi2), eta2)
    ok = np.array(fwd.ok)
    wo2 = _arr(fwd.wo)
    other_side = wi[:, 2] * wi2[:, 2] < 0
    assert ok[refract].mean() > 0.3 and ok[~refract].mean() > 0.3 and not ok.all()
    assert (ok & other_side).sum() < 0.01 * len(ok)  # the microfacet faces the base path's side: rarely possible
    assert not (ok & ~refract & other_side).any()  # a reflection never crosses the surface
    # Snell's law about h with the relative index of the offset's side (glass 1.5 inside, air outside)
    true_eta = np.where(wi2[:, 2] > 0, 1.5, 1 / 1.5)
    sin_i = np.linalg.norm(np.cross(wi2, h), axis=-1)
    sin_o = np.linalg.norm(np.cross(wo2, h), axis=-1)
    np.testing.assert_allclose(sin_i[ok & refract], (true_eta * sin_o)[ok & refract], atol=1e-3)
    back = half_vector_shift(_vec(wi2), fwd.wo, eta2, _vec(wi), offset_eta(_vec(wi2), eta2, _vec(wi)))
    assert np.array(back.ok)[ok].all(), "the inverse of an existing shift must exist"
    np.testing.assert_allclose(_arr(back.wo)[ok], wo[ok], atol=2e-4)
    prod = np.array(fwd.jacobian)[ok] * np.array(back.jacobian)[ok]
    np.testing.assert_allclose(prod, 1.0, rtol=2e-3)
    # finite differences: a small triangle of directions around wo and its image
    eps = 3e-3
    t1 = _unit(np.cross(wo, np.array([0.3, 0.5, 0.8])))
    t2 = np.cross(wo, t1)
    corners = [wo, _unit(wo + eps * t1), _unit(wo + eps * t2)]
    images = [_arr(half_vector_shift(_vec(wi), _vec(c), mi.Float(eta), _vec(wi2), eta2).wo) for c in corners]

    def area(a, b, c):
        return np.abs(np.einsum("ij,ij->i", np.cross(b - a, c - a), a))

    rel = np.abs(area(*images) / area(*corners) / np.maximum(np.array(fwd.jacobian), 1e-12) - 1)
    for subset in (ok & ~refract, ok & refract):
        assert np.median(rel[subset]) < 3e-3 and np.percentile(rel[subset], 90) < 3e-2, np.median(rel[subset])


def test_half_vector_copy_fails_where_it_cannot_be_inverted():
    """Total internal reflection, a reflection that would leave through the surface, and grazing microfacet
    angles (where float32 Jacobians are meaningless) fail -- in both directions alike."""
    select_variant()
    # refraction from glass to air (eta 1/1.5) through the normal microfacet: an offset arriving at 60 degrees
    # from the normal inside the glass is beyond the critical angle (41.8 degrees)
    wi = np.array([[0.0, 0.0, -1.0]])
    wo = np.array([[0.0, 0.0, 1.0]])
    steep = np.array([[np.sin(np.radians(60)), 0.0, -np.cos(np.radians(60))]])
    tir = half_vector_shift(_vec(wi), _vec(wo), mi.Float(1 / 1.5), _vec(steep), mi.Float(1 / 1.5))
    assert not np.array(tir.ok)[0]
    # a reflection about a tilted microfacet that would send the offset below the surface
    wi = _unit(np.array([[0.0, 0.6, 0.8]]))
    wo = _unit(np.array([[0.0, -0.9, 0.1]]))
    low = _unit(np.array([[0.0, 0.99, 0.05]]))
    res = half_vector_shift(_vec(wi), _vec(wo), mi.Float(1.0), _vec(low), mi.Float(1.0))
    assert not np.array(res.ok)[0]
    # grazing: the offset meets the microfacet at cos 5e-5 < MIN_HALF_COSINE; the reverse fails too
    h = np.array([[0.0, 0.0, 1.0]])
    graze = _unit(np.array([[1.0, 0.0, 5e-5]]))
    wi = _unit(np.array([[0.3, 0.0, 1.0]]))
    wo = 2 * (wi * h).sum(-1, keepdims=True) * h - wi
    res = half_vector_shift(_vec(wi), _vec(wo), mi.Float(1.0), _vec(graze), mi.Float(1.0))
    assert not np.array(res.ok)[0]
    graze_out = 2 * (graze * h).sum(-1, keepdims=True) * h - graze
    back = half_vector_shift(_vec(graze), _vec(graze_out), mi.Float(1.0), _vec(wi), mi.Float(1.0))
    assert not np.array(back.ok)[0]


def test_curvature_of_spheres_and_planes():
    """The follow-or-replay decision at specular vertices reads the surface's curvature: 1/R on a sphere (any
    point, any radius), 0 on a plane and on a flat mesh."""
    select_variant()
    scene = mi.load_dict({"type": "scene",
                          "ball": {"type": "sphere", "center": [0, 0, 0], "radius": 0.25},
                          "plane": {"type": "rectangle",
                                    "to_world": mi.ScalarTransform4f().translate([0, 0, -3]).scale(10)},
                          "mesh": {"type": "cube",
                                   "to_world": mi.ScalarTransform4f().translate([4, 0, 0]).scale(0.5)}})
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.17, 0.17, (2, 64))  # inside the ball's silhouette (radius 0.25)
    origins = np.concatenate([np.stack([xy[0], xy[1], np.full(64, 5.0)]),
                              np.stack([xy[0] + 4, xy[1], np.full(64, 5.0)])], 1)
    ray = mi.Ray3f(mi.Point3f(*origins), mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All | mi.RayFlags.dNSdUV, coherent=False)
    k = np.array(curvature(si))
    np.testing.assert_allclose(k[:64], 4.0, rtol=1e-3)
    np.testing.assert_allclose(k[64:], 0.0, atol=1e-6)
    miss = scene.ray_intersect(mi.Ray3f(mi.Point3f(0, 0, 5), mi.Vector3f(0, 0, 1)),
                               ray_flags=mi.RayFlags.All | mi.RayFlags.dNSdUV, coherent=False)
    assert np.array(curvature(miss))[0] == 0.0
