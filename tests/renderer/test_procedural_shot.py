"""Procedural animated shots (renderer/procedural_shot.py): ``procedural:moving|dolly|orbit|lightoff:SEED``, their
grammar and errors, what each family moves over the shot, motion vectors that pass the warp check, and a seeded
shot rendered, sharded and re-run through `gradsep render --frames`."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from gradsep.cli import main
from gradsep.renderer.errors import SceneError
from gradsep.renderer.procedural import ProceduralSpec, generate, parse_procedural
from gradsep.renderer.procedural_shot import LAMP_ID, MOVER_ID, SHOT_FAMILIES, SWITCH_AT

SEEDS = (3, 5, 7)
TINY = ["--width", "16", "--height", "12", "--spp", "2"]


def _camera(plan: dict) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's origin and forward direction."""
    to_world = np.asarray(plan["sensor"]["to_world"])
    return to_world[:3, 3], to_world[:3, 2]


def _without(plan: dict, *names: str) -> str:
    return repr({k: v for k, v in plan.items() if k not in names})


def test_the_grammar_names_each_family_and_keeps_the_still_specs():
    for family in SHOT_FAMILIES:
        spec = parse_procedural(f"procedural:{family}:12")
        assert spec == ProceduralSpec(12, family) and spec.animated and str(spec) == f"procedural:{family}:12"
    assert not parse_procedural("procedural:12").animated and not parse_procedural("procedural:studio:12").animated
    with pytest.raises(SceneError, match="unknown procedural family 'zoom'.*procedural:moving|dolly"):
        parse_procedural("procedural:zoom:3")
    for bad in ("procedural:dolly:x", "procedural:dolly:-1", "procedural:dolly:studio:3"):
        with pytest.raises(SceneError):
            parse_procedural(bad)
    with pytest.raises(ValueError, match="only a shot family has it"):
        generate(3, t=0.5)


@pytest.mark.parametrize("family", SHOT_FAMILIES)
def test_a_shot_is_its_seeds_room_with_the_familys_motion(family):
    """The room of procedural:SEED, drawn the same way; only the family's part changes with t, linearly for the
    moving and dolly families, and the header values say where."""
    for seed in SEEDS:
        still = generate(seed, 32, 32).plan
        frames = [generate(seed, 32, 32, family=family, t=t) for t in (0.0, 0.5, 1.0)]
        plans = [f.plan for f in frames]
        assert [f.animation["t"] for f in frames] == ["0", "0.5", "1"]
        origins = [_camera(p)[0] for p in plans]
        if family in ("moving", "lightoff"):  # a static camera: the still's, and its room plus one shape
            added = MOVER_ID if family == "moving" else LAMP_ID
            assert all(_without(p, added) == _without(still) for p in plans)
        else:  # the camera moves; nothing else does
            assert all(_without(p, "sensor") == _without(still, "sensor") for p in plans)
            assert np.linalg.norm(origins[2] - origins[0]) > 0.1
            assert [f.animation["camera_origin"] for f in frames] == \
                [", ".join(f"{v:.9g}" for v in o) for o in origins]
        if family == "moving":
            centres = [np.asarray(p[MOVER_ID]["center"]) for p in plans]
            assert np.linalg.norm(centres[2] - centres[0]) > 0.1
            np.testing.assert_allclose(centres[1], (centres[0] + centres[2]) / 2, atol=1e-9)
            assert centres[0][1] == centres[2][1]  # sideways, at one height over the floor
        if family == "dolly":  # along the view, which does not turn
            np.testing.assert_allclose(origins[1], (origins[0] + origins[2]) / 2, atol=1e-9)
            forward = [_camera(p)[1] for p in plans]
            np.testing.assert_allclose(forward[2], forward[0], atol=1e-9)
            step = origins[2] - origins[0]
            assert abs(abs(np.dot(step, forward[0])) - np.linalg.norm(step)) < 1e-9
        if family == "orbit":  # at one height, about a vertical axis the camera keeps looking at
            assert len({round(float(o[1]), 9) for o in origins}) == 1
            forward = [_camera(p)[1] for p in plans]
            assert not np.allclose(forward[0], forward[2])
        if family == "lightoff":
            radiance = [p[LAMP_ID]["emitter"]["radiance"]["value"] for p in plans]
            assert min(radiance[0]) > 0 and radiance[1] == radiance[2] == [0.0, 0.0, 0.0]
            assert [f.animation["lamp"] for f in frames] == ["1", "0", "0"]


#: What each shot family makes of seed 7 at t = 0.5, at GENERATOR_VERSION 1 (see test_procedural.PINNED_PLANS: a
#: change to a shot family's scenes must bump the version too).
PINNED_SHOTS = {"moving": "380de2fc3dab4667", "dolly": "0ec8110737d418c2", "orbit": "72294f4c4bf887fc",
                "lightoff": "278090f107223377"}


def test_shot_families_are_pinned_to_the_generator_version():
    from gradsep.renderer.procedural_builder import GENERATOR_VERSION
    from tests.renderer.test_procedural import fingerprint

    assert GENERATOR_VERSION == 1, "GENERATOR_VERSION changed: re-pin PINNED_SHOTS"
    got = {family: fingerprint(generate(7, family=family, t=0.5).plan) for family in SHOT_FAMILIES}
    assert got == PINNED_SHOTS, "a procedural shot family's scene changed without a GENERATOR_VERSION bump"


def test_a_shot_frame_is_the_same_plan_every_time():
    assert repr(generate(9, family="orbit", t=0.25).plan) == repr(generate(9, family="orbit", t=0.25).plan)
    assert repr(generate(9, family="orbit", t=0.25).plan) != repr(generate(10, family="orbit", t=0.25).plan)


# ---------------------------------------------------------------------------------------------------------------
# Through Mitsuba
# ---------------------------------------------------------------------------------------------------------------


def _diffuse_items(plan: dict) -> set[str]:
    """The plan's shapes with a (possibly two-sided) diffuse BSDF and no emitter: their albedo does not depend on
    the view, so warping it is the warp check (a glossy surface's reflection moves otherwise)."""
    out = set()
    for name, item in plan.items():
        if isinstance(item, dict) and "bsdf" in item and "emitter" not in item:
            bsdf = item["bsdf"]
            while bsdf.get("type") == "twosided":
                bsdf = bsdf["bsdf"]
            if bsdf["type"] == "diffuse":
                out.add(name)
    return out


@pytest.mark.render
@pytest.mark.parametrize("family", ["moving", "dolly", "orbit"])
def test_motion_vectors_of_a_procedural_shot_pass_the_warp_check(family):
    """Frame t-1's albedo warped onto t with ``backward`` leaves less error than not warping, in valid pixels on
    diffuse shapes (issue 53's check; <= 0.25x over the three seeds together)."""
    pytest.importorskip("mitsuba")
    from gradsep.renderer.motion import primary_hits, render_motion
    from gradsep.renderer.scene import load_scene
    from tests.renderer.test_motion import albedo, bilinear

    res, warped_total, unwarped_total = 32, 0.0, 0.0
    for seed in SEEDS:
        spec = f"procedural:{family}:{seed}"
        current = load_scene(spec, width=res, height=res, defines={"t": "1"})
        previous = load_scene(spec, width=res, height=res, defines={"t": "0.5"})
        motion = render_motion(current, previous, None)
        rows, cols, valid = motion.warp_source("backward")
        names = np.array([s.id() for s in current.scene.shapes()] + [""])[primary_hits(current).shape]
        keep = valid & np.isin(names.reshape(res, res), sorted(_diffuse_items(generate(seed, family=family).plan)))
        now, before = albedo(current), albedo(previous)
        warped = np.sum((bilinear(before, rows, cols) - now)[keep] ** 2)
        unwarped = np.sum((before - now)[keep] ** 2)
        assert keep.sum() > 0.05 * res * res and warped < unwarped, (seed, warped, unwarped)
        warped_total, unwarped_total = warped_total + warped, unwarped_total + unwarped
    assert warped_total <= 0.25 * unwarped_total, (warped_total, unwarped_total)


@pytest.mark.render
def test_the_light_off_frames_after_the_switch_are_darker():
    mi = pytest.importorskip("mitsuba")
    from gradsep.renderer.scene import load_scene

    for seed in SEEDS:
        means = []
        for t in (0.0, SWITCH_AT - 0.01, SWITCH_AT, 1.0):
            loaded = load_scene(f"procedural:lightoff:{seed}", width=16, height=16, defines={"t": str(t)})
            means.append(float(np.mean(mi.render(loaded.scene, spp=32, seed=1))))
        on, off = means[:2], means[2:]
        assert max(off) < 0.95 * min(on), (seed, means)


# ---------------------------------------------------------------------------------------------------------------
# The command line
# ---------------------------------------------------------------------------------------------------------------


def _render(folder: Path, *args: str, output: str = "f.%04d.exr") -> int:
    return main(["render", *args, *TINY, "-o", str(folder / output)])


@pytest.mark.parametrize(("args", "message"), [
    (["procedural:dolly:3", "--frames", "1-3", "--animate", "x=0:1"], "has no parameter named x"),
    (["procedural:dolly:3", "--frames", "1-3", "-D", "x=1"], "has no parameter named x"),
    (["procedural:dolly:3", "--frames", "1-3", "--animate", "t=0:2"], "outside [0, 1]"),
    (["procedural:dolly:3", "--frames", "1-3", "-D", "t=abc"], "is not a number"),
    (["procedural:dolly:3", "--frames", "1-3", "-D", "t=nan"], "outside [0, 1]"),
    (["procedural:dolly:3", "--frames", "1-3", "--animate", "t=0,0:1,1"], "is a number, not a vector"),
    (["procedural:dolly:3", "--frames", "1-3", "--animate", "t=0:1", "-D", "t=0.5"], "both set t"),
    (["procedural:3", "--frames", "1-3", "-D", "t=0.5"], "--define applies to XML scenes only"),
    (["procedural:studio:3", "--frames", "1-3", "--animate", "t=0:1"], "procedural:studio:3 has no parameters"),
    (["procedural:zoom:3", "--frames", "1-3"], "unknown procedural family 'zoom'"),
    (["procedural:dolly:x", "--frames", "1-3"], "integer seed"),
    (["procedural:dolly:3", "-D", "t=2"], "outside [0, 1]"),
])
def test_bad_shot_specs_are_one_line_exit_2_and_no_file(tmp_path, capsys, args, message):
    output = "f.exr" if "--frames" not in args else "f.%04d.exr"
    assert _render(tmp_path, *args, output=output) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []


def _shot(scene: str, frames: str, *extra: str) -> tuple:
    from gradsep.renderer.shot import checked_shot

    args = argparse.Namespace(scene=scene, output="/tmp/o.%04d.exr", frames=frames, shard=None, animate=list(extra),
                              define=[], plan_key=None)
    return checked_shot(args)


def test_t_over_the_shot_a_one_frame_shot_and_a_part_of_the_motion():
    """t is 0 on the first frame and 1 on the last, whatever the frame numbers; a one-frame shot is t = 0 (its
    first frame, as --animate does); --animate t=A:B renders a part of the motion; the plan cache keys the shot."""
    from gradsep.renderer.shot import plan_cache_of

    shot, _ = _shot("procedural:orbit:4", "1001-1005")
    assert [shot.defines_of(n)["t"] for n in shot.frames] == ["0", "0.25", "0.5", "0.75", "1"]
    assert [shot.header(n)["gradsep.animate.t"] for n in (1001, 1005)] == ["0", "1"]
    one, _ = _shot("procedural:orbit:4", "7")
    assert one.defines_of(7) == {"t": "0"}
    part, _ = _shot("procedural:orbit:4", "1-3", "t=0.5:1")
    assert [part.defines_of(n)["t"] for n in (1, 2, 3)] == ["0.5", "0.75", "1"]
    assert part.header(1)["gradsep.shot_settings"] != shot.header(1001)["gradsep.shot_settings"]
    cache = plan_cache_of(shot, argparse.Namespace(plan_key=None), Path("/tmp"), "auto")
    assert "procedural:orbit:4" in cache.scene and "animate:t=" in cache.scene


@pytest.mark.render
def test_a_seeded_procedural_shot_renders_shards_and_reruns(tmp_path, capsys):
    """A 3-frame light-off shot: t, the lamp and motion vectors in each header; the frame after the switch is
    darker; shard 1/3 renders frame 2 bit for bit as the whole shot did (a seeded frame is reproducible); a re-run
    skips the complete frames."""
    from gradsep.model.exr_read import read_frame

    whole, part = tmp_path / "whole", tmp_path / "part"
    whole.mkdir()
    part.mkdir()
    spec = "procedural:lightoff:3"
    assert _render(whole, spec, "--frames", "1-3", "--seed", "4") == 0
    frames = [read_frame(whole / f"f.{n:04d}.exr") for n in (1, 2, 3)]
    assert [f.metadata["gradsep.animate.t"] for f in frames] == ["0", "0.5", "1"]
    assert [f.metadata["gradsep.animate.lamp"] for f in frames] == ["1", "0", "0"]
    assert frames[0].motion.backward is None and frames[0].motion.forward is not None
    assert frames[2].motion.backward is not None and frames[2].motion.forward is None
    brightness = [float(sum(layer.base.mean() for layer in f.layers.values())) for f in frames]
    assert max(brightness[1:]) < brightness[0], brightness
    assert _render(part, spec, "--frames", "1-3", "--seed", "4", "--shard", "1/3") == 0
    assert sorted(p.name for p in part.glob("*.exr")) == ["f.0002.exr"]
    again = read_frame(part / "f.0002.exr")
    for name, layer in frames[1].layers.items():
        np.testing.assert_array_equal(again.layers[name].base, layer.base)
    np.testing.assert_array_equal(again.motion.backward, frames[1].motion.backward)
    capsys.readouterr()
    assert _render(whole, spec, "--frames", "1-3", "--seed", "4") == 0
    assert "3 complete on disk, 0 to render" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.render
def test_gradients_auto_judges_a_procedural_shot_once(tmp_path, capsys):
    assert main(["render", "procedural:moving:3", "--width", "16", "--height", "12", "--spp", "64", "--gradients",
                 "auto", "--frames", "1-2", "-o", str(tmp_path / "a.%04d.exr")]) == 0
    out = capsys.readouterr().out
    assert "plan cache: wrote" in out and "judged by an earlier frame" in out
    assert len(list((tmp_path / ".gradsep-plans").glob("plan-*.json"))) == 1
