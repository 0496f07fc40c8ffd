"""The procedural scene generator: deterministic per seed, varied, loadable and renderable by Mitsuba."""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from typing import Any

import numpy as np
import pytest

from gradsep.renderer.errors import SceneError
from gradsep.renderer.procedural import (
    ProceduralSpec,
    describe,
    generate,
    parse_procedural,
    procedural_scene,
)
from gradsep.renderer.procedural_builder import GENERATOR_VERSION

DISTRIBUTION_SEEDS = range(300)  # plan generation only (no rendering): ~1 s


def canonical(node: Any) -> Any:
    """Plans and Mitsuba dicts as plain comparable values (numpy arrays, transforms, bitmaps -> lists)."""
    if isinstance(node, dict):
        return {k: canonical(v) for k, v in node.items()}
    if isinstance(node, (list, tuple)):
        return [canonical(v) for v in node]
    if isinstance(node, np.ndarray):
        return node.astype(np.float64).round(12).tolist()
    if isinstance(node, (np.floating, np.integer)):
        return node.item()
    if hasattr(node, "matrix"):  # mi.ScalarTransform4f / 3f
        return np.array(node.matrix, dtype=np.float64).round(6).tolist()
    if type(node).__name__ == "Bitmap":
        return np.array(node, dtype=np.float64).round(6).tolist()
    return node


def emitters_of(plan: dict) -> list[str]:
    names = [k for k, v in plan.items() if isinstance(v, dict) and "emitter" in v]
    names += [k for k, v in plan.items()
              if isinstance(v, dict) and v.get("type") in ("spot", "point", "constant", "envmap")]
    return names


# -- determinism ---------------------------------------------------------------------------------------------

def fingerprint(node: Any) -> str:
    """A short hash of a plan or Mitsuba dict, floats to 9 significant digits (so a last-ulp difference of another
    CPU's libm does not count)."""
    def rounded(n: Any) -> Any:
        if isinstance(n, dict):
            return {k: rounded(v) for k, v in n.items()}
        if isinstance(n, list):
            return [rounded(v) for v in n]
        return float(f"{n:.9g}") if isinstance(n, float) else n
    text = json.dumps(rounded(canonical(node)), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


#: What each (family, seed) generates at GENERATOR_VERSION 1. The evaluation's cache keys a procedural scene by
#: seed, family and version, not by this module's source (evaluation/run.py): a change that alters any scene must
#: bump GENERATOR_VERSION (and then these), or cached frames and references would be reused for another scene.
PINNED_PLANS = {("mixed", 0): "aa5346b8e33b679c", ("mixed", 1): "96e994b5b5950398", ("mixed", 7): "19c67e3e38c59547",
                ("mixed", 90001): "86549a5c7c78b975", ("mixed", 90002): "a370ea185bd8d6ca",
                ("studio", 0): "42da06e460074e6d", ("studio", 86001): "abbf63c208d12161"}
PINNED_DICTS = {("mixed", 90001): "f10ca45eef1de4ea", ("studio", 86001): "96cb6caa3a3d5dbc"}  # at 64x48


def test_scenes_are_pinned_to_the_generator_version() -> None:
    assert GENERATOR_VERSION == 1, "GENERATOR_VERSION changed: re-pin PINNED_PLANS and PINNED_DICTS to its scenes"
    got = {key: fingerprint(generate(key[1], family=key[0]).plan) for key in PINNED_PLANS}
    assert got == PINNED_PLANS, ("a procedural scene changed without a GENERATOR_VERSION bump (the evaluation "
                                 "cache and datasets key scenes by seed + version)")


@pytest.mark.render
def test_mitsuba_dicts_are_pinned_to_the_generator_version() -> None:
    got = {key: fingerprint(procedural_scene(key[1], 64, 48, family=key[0])) for key in PINNED_DICTS}
    assert got == PINNED_DICTS, "the Mitsuba dict of a procedural scene changed without a GENERATOR_VERSION bump"


def test_same_seed_same_plan_and_different_seeds_differ() -> None:
    for seed in (0, 7, 123456):
        assert canonical(generate(seed).plan) == canonical(generate(seed).plan)
        assert describe(seed) == describe(seed)
    plans = [canonical(generate(seed).plan) for seed in range(6)]
    assert all(plans[i] != plans[j] for i in range(6) for j in range(i + 1, 6))


@pytest.mark.render
def test_mitsuba_dict_is_deterministic() -> None:
    a, b = procedural_scene(42, 64, 48), procedural_scene(42, 64, 48)
    assert canonical(a) == canonical(b)
    assert canonical(a) != canonical(procedural_scene(43, 64, 48))


def test_film_size_and_depth_do_not_change_the_scene() -> None:
    small, large = generate(5, 32, 24).plan, generate(5, 640, 480, max_depth=3).plan
    assert small["sensor"]["film"]["width"] == 32 and large["sensor"]["film"]["height"] == 480
    assert small["integrator"] == {"type": "path", "max_depth": 8}
    assert large["integrator"] == {"type": "path", "max_depth": 3}
    strip = ("sensor", "integrator")
    assert canonical({k: v for k, v in small.items() if k not in strip}) == \
        canonical({k: v for k, v in large.items() if k not in strip})
    assert np.array_equal(small["sensor"]["to_world"], large["sensor"]["to_world"])


def test_sensor_is_perspective_with_box_filter() -> None:
    sensor = generate(3, 80, 60).plan["sensor"]
    assert sensor["type"] == "perspective"
    assert sensor["film"]["rfilter"] == {"type": "box"}
    assert (sensor["film"]["width"], sensor["film"]["height"]) == (80, 60)


@pytest.mark.parametrize("kwargs", [{"seed": -1}, {"seed": 1.5}, {"seed": True}, {"seed": 0, "width": 0},
                                    {"seed": 0, "height": -3}, {"seed": 0, "max_depth": 0},
                                    {"seed": 0, "max_depth": -2}])
def test_bad_arguments_are_clear_errors(kwargs: dict) -> None:
    with pytest.raises(ValueError, match="seed|width|height|max_depth"):
        generate(**kwargs)


# -- distribution ------------------------------------------------------------------------------------------

def test_the_one_spec_parser() -> None:
    assert parse_procedural("procedural:42") == ProceduralSpec(42) and parse_procedural("procedural:0").seed == 0
    assert parse_procedural("procedural:studio:7") == ProceduralSpec(7, "studio")
    assert [str(parse_procedural(s)) for s in ("procedural:42", "procedural:studio:7")] == \
        ["procedural:42", "procedural:studio:7"]
    assert parse_procedural("scenes/cbox.xml") is None and parse_procedural("procedural.xml") is None
    with pytest.raises(SceneError, match="integer seed"):
        parse_procedural("procedural:x")
    with pytest.raises(SceneError, match="must be >= 0"):
        parse_procedural("procedural:-3")
    for spec in ("procedural:room:3", "procedural:mixed:3", "procedural::3", "procedural:studio:studio:3"):
        with pytest.raises(SceneError, match="unknown procedural family"):
            parse_procedural(spec)
    with pytest.raises(ValueError, match="family"):
        generate(3, family="attic")


# -- the studio family -----------------------------------------------------------------------------------------

STUDIO_SEEDS = range(200)


def test_studio_scenes_have_no_room_ground_or_sky_and_keep_their_seed() -> None:
    for seed in STUDIO_SEEDS:
        scene = generate(seed, family="studio")
        plan = scene.plan
        assert scene.summary["room"]["kind"] == "studio"
        assert not any(k.startswith(("floor", "ceiling", "wall_", "environment")) for k in plan), seed
        assert emitters_of(plan) and all(k.startswith("light_") for k in emitters_of(plan)), seed
        assert any(k.startswith("object_") for k in plan), seed
        assert np.isfinite(plan["sensor"]["to_world"]).all()
        assert describe(seed, "studio").startswith(f"procedural:studio:{seed} ")
    a, b = generate(9, family="studio"), generate(9, family="studio")
    assert canonical(a.plan) == canonical(b.plan) and generate(9, family="studio").summary == a.summary
    assert canonical(a.plan) != canonical(generate(9).plan)  # its own stream, not the mixed seed's


def test_studio_camera_frames_the_cluster() -> None:
    """The objects' centre lies in front of the camera and inside its field of view."""
    for seed in STUDIO_SEEDS:
        scene = generate(seed, 64, 64, family="studio")
        to_world = scene.plan["sensor"]["to_world"]
        centres = [np.array(v["center"]) if v["type"] == "sphere" else np.asarray(v["to_world"])[:3, 3]
                   for k, v in scene.plan.items() if k.startswith("object_") and not k.endswith("_cap")
                   and ("center" in v or "to_world" in v)]
        if not centres:
            continue
        local = np.linalg.inv(to_world) @ np.append(np.mean(centres, axis=0), 1.0)
        assert local[2] > 0, seed
        half = np.radians(scene.plan["sensor"]["fov"] / 2)
        assert abs(local[0] / local[2]) < np.tan(half) * 1.01 and abs(local[1] / local[2]) < np.tan(half) * 1.01


def test_every_seed_has_an_emitter_and_a_camera_inside_the_room() -> None:
    for seed in DISTRIBUTION_SEEDS:
        scene = generate(seed)
        assert emitters_of(scene.plan), f"seed {seed} has no emitter"
        origin = scene.plan["sensor"]["to_world"][:3, 3]
        room = scene.summary["room"]
        if room["kind"] == "room":
            wx, h, wz = room["size"]
            assert abs(origin[0]) < wx / 2 and abs(origin[2]) < wz / 2 and 0 < origin[1] < h, seed
        assert np.isfinite(scene.plan["sensor"]["to_world"]).all()


def test_distribution_covers_materials_lights_rooms_and_textures() -> None:
    materials: Counter[str] = Counter()
    lights: Counter[str] = Counter()
    kinds: Counter[str] = Counter()
    occluders: Counter[str] = Counter()
    open_rooms = textured = checker = 0
    for seed in DISTRIBUTION_SEEDS:
        scene = generate(seed)
        s = scene.summary
        assert s["generator_version"] == GENERATOR_VERSION
        materials.update({k.removesuffix("-textured"): v for k, v in s["materials"].items()})
        lights.update(s["lights"])
        kinds[s["room"]["kind"]] += 1
        occluders.update(s["occluders"])
        open_rooms += bool(s["room"]["open"])
        text = repr(scene.plan)
        textured += "'bitmap'" in text
        checker += "checkerboard" in text
    n = len(DISTRIBUTION_SEEDS)
    for material in ("diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "dielectric",
                     "roughdielectric", "thindielectric"):
        assert materials[material] >= n // 50, (material, materials)
    for light in ("ceiling", "wall_wash", "uplight", "sphere", "spot", "environment-constant", "environment-map"):
        assert lights[light] >= n // 50, (light, lights)
    assert set(occluders) == {"shelf", "partition", "pillar"}
    assert 0.05 * n < kinds["outdoor"] < 0.25 * n
    assert 0.2 * n < open_rooms < 0.8 * n
    assert textured > 0.2 * n and checker > 0.2 * n


def test_describe_names_the_seed_and_its_contents() -> None:
    text = describe(11)
    assert text.startswith("procedural:11 ")
    assert "lights:" in text and "materials:" in text
    summary = generate(11).summary
    assert all(light in text for light in summary["lights"])


# -- Mitsuba -------------------------------------------------------------------------------------------------

@pytest.mark.render
def test_a_studio_frame_has_an_empty_background() -> None:
    """Missed camera rays: depth 0 and no light (no sky), beside lit objects."""
    from gradsep.renderer.render import FrameOptions, render_frame

    frame = render_frame("procedural:studio:3", spp=4, seed=1, options=FrameOptions(width=40, height=30))
    miss = frame.features.depth == 0
    assert miss.any() and (~miss).any()
    total = sum(layer.base for layer in frame.layers.values())
    assert np.all(total[miss] == 0) and total[~miss].max() > 0 and np.isfinite(total).all()


@pytest.mark.render
@pytest.mark.parametrize("seed", [0, 3, 8, 1000])
def test_loads_and_renders_finite_nonzero_images(seed: int) -> None:
    import mitsuba as mi

    from gradsep.renderer.variant import select_variant

    select_variant()
    scene = mi.load_dict(procedural_scene(seed, 24, 16))
    assert len(scene.emitters()) >= 1
    image = np.array(mi.render(scene, spp=4, seed=1))
    assert image.shape == (16, 24, 3)
    assert np.isfinite(image).all()
    assert image.mean() > 1e-4, f"seed {seed} rendered black"
