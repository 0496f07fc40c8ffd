"""The primal-only render mode (`gradsep render --no-gradients`, ``render_frame(..., gradients=False)``): the base
paths of G-PT with the same direct/indirect routing and first-hit features, no offset paths, no gradients.

Its energy is checked against Mitsuba's `path` with the same tolerances as G-PT's (tests/renderer/test_gpt.py),
and it is checked to be exactly G-PT's primal (random replay draws the same random numbers per lane), which ties
it to every other primal test of the renderer.
"""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from gradsep.cli import main  # noqa: E402
from gradsep.model.errors import CommandError  # noqa: E402
from gradsep.model.exr_read import read_frame  # noqa: E402
from gradsep.model.exr_write import write_frame  # noqa: E402
from gradsep.renderer.gpt import render_gpt  # noqa: E402
from gradsep.renderer.gpt_settings import Film, GptSettings  # noqa: E402
from gradsep.renderer.render import parse_layers, render_frame  # noqa: E402
from gradsep.renderer.scene import load_scene  # noqa: E402
from gradsep.renderer.shift import ReplayShift  # noqa: E402
from tests.renderer.scenes import resolve  # noqa: E402
from tests.renderer.test_gpt import (  # noqa: E402  the G-PT tests' scenes, loaded once per worker
    SCENE_DEPTHS,
    SIZE,
    Z_MAX,
    two_sample_z,
    z_against_reference,
)
from tests.renderer.test_gpt import load_test_scene as scene_of  # noqa: E402

pytestmark = pytest.mark.render

CBOX = str(resolve("cbox"))
TEAPOT = str(resolve("teapot"))
SEEDS = 16
SPP = 8
REF_CHUNKS = 8
REF_SPP = 512


def path_render(scene, spp: int, seed: int, max_depth: int) -> np.ndarray:
    integrator = mi.load_dict({"type": "path", "max_depth": max_depth})
    return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed), dtype=np.float64)[..., :3]


def primal_renders(name: str) -> dict[str, np.ndarray]:
    """layer -> (SEEDS, H, W, 3) primal-only renders."""
    scene = scene_of(name)
    results = [render_gpt(scene, None, GptSettings(max_depth=SCENE_DEPTHS[name]), Film(SIZE, SIZE, SPP, seed))
               for seed in range(SEEDS)]
    for r in results:
        assert all(set(layer) == {"base", "var"} for layer in r.layers.values())
    return {layer: np.stack([r.layers[layer]["base"] for r in results]).astype(np.float64)
            for layer in results[0].layers}


@pytest.mark.parametrize("name", ["cbox", "teapot", "sky"])
def test_primal_energy_matches_path(name):
    """The same checks as G-PT's primal: image means of the total and of the direct layer against `path` at the
    scene's depth and at depth 2 (per-seed means, z < 4.5), direct layer per pixel against a high-spp reference,
    and the indirect layer against path(depth) - path(2)."""
    scene, depth = scene_of(name), SCENE_DEPTHS[name]
    ours = primal_renders(name)
    low = {d: np.stack([path_render(scene, SPP, 20_000 + i, d) for i in range(SEEDS)]) for d in (depth, 2)}
    total = sum(ours.values())
    z = two_sample_z(total.mean(axis=(1, 2)), low[depth].mean(axis=(1, 2)))
    assert np.all(np.abs(z) < 4.5), f"{name}: image mean differs from path: z={z}"
    z = two_sample_z(ours["direct"].mean(axis=(1, 2)), low[2].mean(axis=(1, 2)))
    assert np.all(np.abs(z) < 4.5), f"{name}: direct layer mean differs from path max_depth=2: z={z}"
    ref2 = np.stack([path_render(scene, REF_SPP, 10_000 + i, 2) for i in range(REF_CHUNKS)])
    zp = z_against_reference(ours["direct"], ref2, floor=1e-3)
    assert np.mean(np.abs(zp) > Z_MAX) < 0.01
    if "indirect" in ours:
        rest = (low[depth] - low[2]).mean(axis=(1, 2))
        assert np.all(np.abs(two_sample_z(ours["indirect"].mean(axis=(1, 2)), rest)) < 4.5)
    if name == "cbox":
        assert ours["indirect"].mean() > 0.02


@pytest.mark.parametrize("gradients", [False, True])
def test_variance_channel_is_the_variance_of_the_mean(gradients):
    """Each layer's ``var`` is the variance of its pixel's mean luminance: averaged over the image it matches the
    spread of that mean over independent seeds, and it is written as ``L.var.Y``. One sample has no estimate."""
    scene = scene_of("cbox")
    settings = GptSettings(max_depth=SCENE_DEPTHS["cbox"])
    shift = ReplayShift() if gradients else None
    runs = [render_gpt(scene, shift, settings, Film(SIZE, SIZE, SPP, 500 + seed)) for seed in range(SEEDS)]
    weights = np.array([0.2126, 0.7152, 0.0722])
    for layer in runs[0].layers:
        means = np.stack([r.layers[layer]["base"] for r in runs]).astype(np.float64) @ weights
        spread = means.var(axis=0, ddof=1).mean()  # across seeds
        claimed = np.stack([r.layers[layer]["var"] for r in runs]).astype(np.float64).mean()
        assert 0.75 < claimed / spread < 1.33, (layer, claimed, spread)
    one = render_gpt(scene, shift, settings, Film(SIZE, SIZE, 1, 7))
    assert all(layer["var"] is None for layer in one.layers.values())


def test_a_firefly_sample_caps_its_variance():
    from gradsep.renderer.gpt import SQUARE_CAP, mean_variance

    sums = np.zeros((1, 2, 3))
    sums[0, 0] = 1e20  # one sample of 1e20 and three of 0: its square overflows float32, the scatter caps it
    squares = np.array([[[SQUARE_CAP], [0.0]]])
    var = mean_variance(sums, squares, 4)
    assert var[0, 0] == np.float32(SQUARE_CAP) and var[0, 1] == 0.0  # very noisy, never 0 or Inf


@pytest.mark.parametrize("name", ["cbox", "sky"])
def test_primal_is_exactly_the_gpt_primal(name):
    """Per lane the primal-only mode draws the random numbers G-PT's base path draws, so with the same seed its
    layers and features are G-PT's (replay) to rounding: every energy test of G-PT's primal applies to it."""
    scene = scene_of(name)
    settings = GptSettings(max_depth=SCENE_DEPTHS[name], rr_depth=2)
    for seed in (1, 2):
        gpt = render_gpt(scene, ReplayShift(), settings, Film(SIZE, SIZE, 4, seed))
        primal = render_gpt(scene, None, settings, Film(SIZE, SIZE, 4, seed))
        assert list(primal.layers) == list(gpt.layers) == ["direct", "indirect"]
        for layer in gpt.layers:
            np.testing.assert_allclose(primal.layers[layer]["base"], gpt.layers[layer]["base"], rtol=1e-5,
                                       atol=1e-6, err_msg=layer)
        for key in ("albedo", "normal", "depth"):
            np.testing.assert_allclose(getattr(primal, key), getattr(gpt, key), rtol=1e-5, atol=1e-6, err_msg=key)


@pytest.mark.parametrize("gradients", [False, True])
def test_color_layer_is_the_sum_of_the_layers(gradients):
    """Separation off (``layers="color"``): one layer carrying every event, equal to direct + indirect."""
    loaded = load_scene(CBOX, width=16, height=12)
    sep = render_frame(loaded, spp=4, seed=3, gradients=gradients)
    col = render_frame(loaded, spp=4, seed=3, layers="color", gradients=gradients)
    assert list(col.layers) == ["color"] and list(sep.layers) == ["direct", "indirect"]
    keys = ("base", "dx", "dy") if gradients else ("base",)
    for key in keys:
        np.testing.assert_allclose(getattr(col.layers["color"], key), getattr(sep.combined(), key),
                                   rtol=1e-5, atol=1e-6, err_msg=key)
    assert col.layers["color"].has_gradients is gradients
    assert col.metadata["gradsep.layers"] == "color"


def test_color_layer_cannot_be_mixed_with_separated_layers():
    assert parse_layers("color") == ("color",)
    with pytest.raises(CommandError, match="unseparated"):
        parse_layers("color,direct")


def test_primal_frame_round_trips_without_gradients(tmp_path):
    loaded = load_scene(CBOX, width=16, height=12)
    frame = render_frame(loaded, spp=2, seed=1, gradients=False)
    assert frame.metadata["gradsep.integrator"] == "primal" and frame.metadata["gradsep.shift"] == "none"
    for layer in frame.layers.values():
        assert not layer.has_gradients and layer.dx is None and layer.dy is None
    path = tmp_path / "p.exr"
    write_frame(path, frame)
    back = read_frame(path)
    assert list(back.layers) == ["direct", "indirect"]
    for name, layer in frame.layers.items():
        assert not back.layers[name].has_gradients
        np.testing.assert_array_equal(back.layers[name].base, layer.base)
        np.testing.assert_array_equal(back.layers[name].var, layer.var)
        assert layer.var.shape == (12, 16) and (layer.var >= 0).all()
    np.testing.assert_array_equal(back.features.albedo, frame.features.albedo)


def test_no_gradients_command(tmp_path, capsys):
    out = tmp_path / "p.exr"
    rc = main(["render", CBOX, "--spp", "2", "--width", "16", "--height", "12", "--no-gradients", "-o", str(out)])
    assert rc == 0
    frame = read_frame(out)
    assert list(frame.layers) == ["direct", "indirect"]
    assert all(not layer.has_gradients for layer in frame.layers.values())
    assert frame.features is not None and frame.metadata["gradsep.integrator"] == "primal"
    rc = main(["render", CBOX, "--spp", "1", "--width", "8", "--height", "8", "--no-gradients", "--shift", "replay",
               "-o", str(tmp_path / "x.exr")])
    assert rc == 2 and "--no-gradients" in capsys.readouterr().err
    assert not (tmp_path / "x.exr").exists()


def test_which_scenes_can_skip_the_last_ray():
    """Only a scene lit by delta lights alone (the teapot's point lights) skips the ray after the last next-event
    vertex; an area light (cbox) or an environment (sky) can be found by that ray."""
    from gradsep.renderer.gpt_loop import scene_has_hittable_emitters

    assert not scene_has_hittable_emitters(scene_of("teapot"))
    assert scene_has_hittable_emitters(scene_of("cbox"))
    assert scene_has_hittable_emitters(scene_of("sky"))
