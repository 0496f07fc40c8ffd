"""The shift mappings of renderer/shift.py on their own: the half-vector copy (conventions, Jacobian,
invertibility), the curvature and mirror ray differentials the follow and manifold strategies read, which
strategies are compiled for which scene, the second loop for connected offsets, exactness of a shift onto the
same pixel on float32-hostile geometry, and that the hybrid strategies correlate what they are meant to.

The unbiasedness of every shift against Mitsuba's `path` lives with the integrator (tests/renderer/test_gpt.py),
which renders with each of them; the scenes and helpers are shared from there.
"""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from gradsep.renderer.gpt import ConnectingShift, GptSettings, render_gpt  # noqa: E402
from gradsep.renderer.scene import load_scene, select_variant  # noqa: E402
from gradsep.renderer.shift import (  # noqa: E402
    HybridShift,
    _curvature,
    half_vector_shift,
    make_shift,
    mirror_transfer,
    offset_eta,
)
from tests.renderer.test_gpt import (  # noqa: E402
    CBOX,
    ROBUSTNESS_SCENES,
    SEEDS,
    SHIFTS,
    SIZE,
    coarse_room,
    diffuse_room_dict,
)

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


class SinglePhaseHybrid(HybridShift):
    """The hybrid shift without the integrator's second loop for connected offsets (a protocol member set to None
    is absent for isinstance), so every vertex of every offset goes through the full step."""

    settled = None


@pytest.mark.slow
@pytest.mark.parametrize("scene_name", ["cbox", "glossy"])
def test_connected_offsets_loop_is_exact(scene_name):
    """Summarised connected offsets (renderer.gpt.ConnectingShift) give what the full step gives them."""
    assert isinstance(HybridShift(), ConnectingShift) and not isinstance(SinglePhaseHybrid(), ConnectingShift)
    scene = load_scene(CBOX, width=16, height=16).scene if scene_name == "cbox" else coarse_room(16, "glossy")
    settings = GptSettings(max_depth=-1, rr_depth=2)
    two = render_gpt(scene, HybridShift(), settings, 16, 16, 8, seed=5)
    one = render_gpt(scene, SinglePhaseHybrid(), settings, 16, 16, 8, seed=5)
    for layer in ("direct", "indirect"):
        for key in ("base", "dx", "dy"):
            np.testing.assert_allclose(two.layers[layer][key], one.layers[layer][key], rtol=1e-5, atol=1e-6,
                                       err_msg=f"{layer} {key}")
    assert np.abs(two.layers["indirect"]["dx"]).sum() > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["grazing", "tiny"])
def test_hybrid_shift_onto_the_same_pixel_is_exact_on_grazing_and_tiny_geometry(monkeypatch, name):
    """The identity test of above on geometry where float32 is tight: a reconnection that spuriously fails (a
    shadow ray caught by the target's own sliver triangle, a grazing Jacobian gone to 0 or inf) or a half-vector
    copy that does not reproduce its base direction leaves a nonzero gradient."""
    import gradsep.renderer.gpt as gpt

    monkeypatch.setattr(gpt, "SHIFT_OFFSETS", ((0, 0),) * 4)
    scene = ROBUSTNESS_SCENES[name](16)
    for shift in (HybridShift(), HybridShift(footprint=4.0), HybridShift(footprint=1e9)):
        res = render_gpt(scene, shift, GptSettings(max_depth=5, rr_depth=2), 16, 16, 4, seed=11)
        assert res.invalid_samples == 0
        for layer in ("direct", "indirect"):
            base = res.layers[layer]["base"]
            assert base.mean() > 0
            for key in ("dx", "dy"):
                worst = np.max(np.abs(res.layers[layer][key]) / (1.0 + base))
                assert worst <= 1e-5, (name, shift.footprint, layer, key, worst)


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
    k = np.array(_curvature(si))
    np.testing.assert_allclose(k[:64], 4.0, rtol=1e-3)
    np.testing.assert_allclose(k[64:], 0.0, atol=1e-6)
    miss = scene.ray_intersect(mi.Ray3f(mi.Point3f(0, 0, 5), mi.Vector3f(0, 0, 1)),
                               ray_flags=mi.RayFlags.All | mi.RayFlags.dNSdUV, coherent=False)
    assert np.array(_curvature(miss))[0] == 0.0


def test_manifold_code_only_for_scenes_with_curved_mirrors():
    """The manifold reconnection is compiled only where a shape that can be curved has a mirror BSDF (it costs
    even where no offset takes it); the follow strategy wherever a delta-only material exists."""
    select_variant()

    def features(shapes: dict) -> tuple[bool, bool, bool]:
        return HybridShift()._features(mi.load_dict({"type": "scene", **shapes}))

    mirror, glass = {"type": "conductor"}, {"type": "dielectric"}
    assert features({"a": {"type": "sphere", "bsdf": mirror}})[1:] == (True, True)
    assert features({"a": {"type": "rectangle", "bsdf": mirror}, "b": {"type": "disk", "bsdf": mirror}})[1:] == (
        True, False)
    assert features({"a": {"type": "sphere", "bsdf": glass}})[1:] == (True, False)
    assert features({"a": {"type": "sphere", "bsdf": {"type": "diffuse"}}})[1:] == (False, False)
    assert HybridShift(manifold=False)._features(
        mi.load_dict({"type": "scene", "a": {"type": "sphere", "bsdf": mirror}}))[1:] == (True, False)


@pytest.mark.slow
@pytest.mark.parametrize("radius", [0.25, 0.5, 2.0])
def test_mirror_transfer_matches_finite_differences(radius):
    """The manifold reconnection's Jacobian is a ratio of footprints |dA/d omega| through a mirror, from the ray
    differentials of ``mirror_transfer``: they must match central differences of tracing perturbed directions
    through the mirror onto the target's plane (curved mirrors of three sizes, oblique planes)."""
    select_variant()
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "center": [0, 0, 0], "radius": radius,
                                                    "bsdf": {"type": "conductor"}}})
    flags = mi.RayFlags.All | mi.RayFlags.dNSdUV
    rng = np.random.default_rng(int(radius * 100))
    checked = 0
    for _ in range(12):
        o = mi.Point3f(*map(float, rng.normal(size=3) * 0.3 + [0.0, 0.0, 3.0 * radius + 1.0]))
        aim = mi.Point3f(*map(float, rng.normal(size=3) * 0.3 * radius))
        target = mi.Point3f(*map(float, rng.normal(size=3) * radius + [0.0, 2.0 * radius + 1.0, 0.0]))
        n_t = dr.normalize(mi.Vector3f(*map(float, rng.normal(size=3))))
        d0 = dr.normalize(aim - o)

        def trace(d, o=o):
            return scene.ray_intersect(mi.Ray3f(o, d), ray_flags=flags, coherent=False)

        si = trace(d0)
        if not bool(np.array(si.is_valid())[0]):
            continue
        tr = mirror_transfer(o, si, target, n_t)
        eps = 1e-3 * radius
        for analytic, e in ((tr.dq_a, tr.e_a), (tr.dq_b, tr.e_b)):
            plus = mirror_transfer(o, trace(dr.normalize(d0 + eps * e)), target, n_t).q
            minus = mirror_transfer(o, trace(dr.normalize(d0 - eps * e)), target, n_t).q
            numeric = (np.array(plus) - np.array(minus)).ravel() / (2 * eps)
            scale = np.linalg.norm(numeric)
            np.testing.assert_allclose(np.array(analytic).ravel(), numeric, atol=2e-2 * scale)
        checked += 1
    assert checked >= 6


@pytest.mark.slow
def test_following_specular_vertices_correlates_caustics():
    """The Cornell box's walls are lit through its mirror ball and glass ball: an offset that moves onto the base
    path's point of the glass ball, or connects past the mirror through the point that reflects it onto the base
    path's next vertex, keeps finding the lamp where the base path does; a parallel replayed ray (which meets the
    curved surface elsewhere) often misses it. Both are unbiased (tests above); the caustics' gradients are much
    less noisy with the specular strategies (measured: 3.4-3.5x lower variance at 48^2 over two sets of seeds;
    2.1-2.2x with the follow strategy alone)."""
    size = 48
    scene = load_scene(CBOX, width=size, height=size).scene
    variance = {}
    for name, shift in (("follow", HybridShift()), ("replay-at-specular", HybridShift(follow_specular=False))):
        dx = np.stack([render_gpt(scene, shift, GptSettings(max_depth=6), size, size, 16, seed).layers[
            "indirect"]["dx"] for seed in range(12)]).astype(np.float64)
        variance[name] = dx.var(0).mean()
    gain = variance["replay-at-specular"] / variance["follow"]
    assert gain > 2.0, f"specular strategies/replay-at-specular variance gain on caustics only {gain:.2f}"


@pytest.mark.slow
def test_hybrid_shift_correlates_indirect_light_on_diffuse_walls():
    """Reconnection shares every vertex after the first bounce, so on a flat diffuse wall the indirect gradients
    are far less noisy than with random replay, whose offset paths drift apart (measured: ~5-10x lower
    variance on the back wall; both shifts are unbiased by the tests above)."""
    select_variant()
    scene = mi.load_dict(diffuse_room_dict())
    variance = {}
    for shift in SHIFTS:
        dx = np.stack([render_gpt(scene, make_shift(shift), GptSettings(max_depth=3), SIZE, SIZE, 4, seed).layers[
            "indirect"]["dx"] for seed in range(SEEDS)]).astype(np.float64)
        variance[shift] = dx.var(0).mean(-1)
    # the upper half of the back wall, away from the lamp's direct view and the ball
    window = (slice(SIZE // 4, SIZE * 11 // 24), slice(SIZE * 7 // 24, SIZE * 2 // 3))
    gain = np.median(variance["replay"][window] / np.maximum(variance["hybrid"][window], 1e-20))
    assert gain > 3.0, f"hybrid/replay variance gain on the back wall only {gain:.1f}"
