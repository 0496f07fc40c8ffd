"""renderer/manifold.py: the ray differentials through a curved mirror that the manifold reconnection's Newton
steps and Jacobian read. (That the frames it takes part in are unbiased: tests/renderer/test_gpt.py.)"""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from gradsep.renderer.manifold import mirror_transfer  # noqa: E402
from gradsep.renderer.variant import select_variant  # noqa: E402

pytestmark = pytest.mark.render


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
