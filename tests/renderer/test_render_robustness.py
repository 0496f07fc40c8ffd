"""The G-PT renderer on degenerate film sizes and on a scene whose samples go non-finite.

Built from a scene dictionary of its own (nothing from the shared scenes): a sphere on a floor under a sky and a
small lamp. The NaN scene gives the sphere a NaN reflectance: every sample whose path evaluates it is non-finite,
which the renderer must zero *per sample*, count, and report. Compared with the same scene where the sphere is
black (reflectance 0: the same geometry, the same random numbers, contributions exactly 0 instead of NaN), the
base images and features must then be equal -- a guard that drops too much (a whole pixel or lane) or too little
(NaN left in a sum) fails that comparison.
"""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from gradsep.renderer.gpt import render_gpt  # noqa: E402
from gradsep.renderer.gpt_settings import Film, GptSettings  # noqa: E402
from gradsep.renderer.shift import make_shift  # noqa: E402
from gradsep.renderer.variant import select_variant  # noqa: E402

pytestmark = pytest.mark.render


def scene_dict(width: int, height: int, sphere_reflectance: float) -> dict:
    tf = mi.ScalarTransform4f
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": tf().look_at(origin=[0, 1.5, 5], target=[0, 0.3, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.4, 0.5, 0.7]}},
        "sphere": {"type": "sphere", "center": [0, 0.5, 0], "radius": 0.5,
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [sphere_reflectance] * 3}}},
        "floor": {"type": "rectangle", "to_world": tf().rotate([1, 0, 0], -90).scale(1.5),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}},
        "lamp": {"type": "rectangle", "to_world": tf().translate([1.0, 2.0, 0.5]).rotate([1, 0, 0], 90).scale(0.3),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [20, 18, 15]}}},
    }


def render(width: int, height: int, reflectance: float, shift: str = "replay", spp: int = 4, depth: int = 4):
    select_variant()
    scene = mi.load_dict(scene_dict(width, height, reflectance))
    return render_gpt(scene, make_shift(shift), GptSettings(max_depth=depth), Film(width, height, spp, 5))


def _all_arrays(result) -> dict[str, np.ndarray]:
    out = {f"{layer}.{k}": v for layer, d in result.layers.items() for k, v in d.items()}
    out.update(albedo=result.albedo, normal=result.normal, depth=result.depth)
    return out


@pytest.mark.parametrize("size", [(1, 1), (1, 7), (7, 1), (3, 5), (17, 11)], ids=lambda s: f"{s[0]}x{s[1]}")
def test_degenerate_and_odd_film_sizes(size: tuple[int, int]) -> None:
    """Any width x height: the contract's shapes, zero in dx's last column and dy's last row, finite, and the
    same light as the same view rendered larger (the image mean of a 1-pixel film is the centre pixel's)."""
    width, height = size
    result = render(width, height, 0.5)
    assert result.invalid_samples == 0 and not result.warnings
    for name, array in _all_arrays(result).items():
        assert array.shape[:2] == (height, width), name
        assert np.isfinite(array).all(), name
    for layer in result.layers.values():
        assert (layer["base"] >= 0).all()
        assert not layer["dx"][:, -1].any() and not layer["dy"][-1, :].any()
    base = sum(layer["base"] for layer in result.layers.values())
    assert base.mean() > 0  # every size sees the lit scene (sphere, floor or sky)


@pytest.mark.parametrize("shift", ["replay", "hybrid"])
def test_nan_samples_are_zeroed_counted_and_reported(shift: str) -> None:
    nan = render(16, 12, float("nan"), shift)
    black = render(16, 12, 0.0, shift)
    # ~1/6 of the pixels see the sphere; at 4 spp and depth 4 hundreds of samples touch it
    assert nan.invalid_samples > 50, nan.invalid_samples
    assert black.invalid_samples == 0
    assert nan.warnings == [f"{nan.invalid_samples} samples produced non-finite values; their contributions "
                            "were set to 0"]
    got, want = _all_arrays(nan), _all_arrays(black)
    for name in want:
        assert np.isfinite(got[name]).all(), name
        if name.endswith((".dx", ".dy")):
            # A gradient event whose base or offset path touched the sphere is dropped whole (the black sphere
            # keeps the other path's light there): equal except on those pixel pairs, a few % of the values.
            same = np.isclose(got[name], want[name], rtol=1e-5, atol=1e-6)
            assert same.mean() > 0.9, (name, same.mean())
        else:  # primal radiance and features: the NaN contributions zeroed, everything else kept exactly
            np.testing.assert_allclose(got[name], want[name], rtol=1e-5, atol=1e-6, err_msg=name)
    assert sum(layer["base"] for layer in nan.layers.values()).mean() > 0
