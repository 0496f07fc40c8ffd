"""Motion vectors from the renderer (renderer/motion.py) on tiny shots whose answer is known
(tests/data/motion/shot.xml: a textured wall, a sphere and a cube; the camera and both objects can move)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from gradsep.renderer.motion import MISS, primary_hits, render_motion, specular_chains  # noqa: E402
from gradsep.renderer.scene import LoadedScene, load_scene  # noqa: E402

pytestmark = pytest.mark.render

SHOT = Path(__file__).resolve().parents[1] / "data" / "motion" / "shot.xml"
RES = 32
FOV = 40.0  # shot.xml's horizontal field of view
FOCAL = RES / (2.0 * math.tan(math.radians(FOV / 2)))  # pixels per unit of x / depth
WALL, BALL, BOX = "wall", "ball", "box"


def frame(res: int = RES, **values: float) -> LoadedScene:
    return load_scene(str(SHOT), defines={k: str(v) for k, v in values.items()}, width=res, height=res)


def shape_map(loaded: LoadedScene) -> np.ndarray:
    """Per pixel, the id of the shape its centre ray hits ("" for none)."""
    ids = np.array([s.id() for s in loaded.scene.shapes()] + [""])
    return ids[primary_hits(loaded).shape].reshape(loaded.height, loaded.width)


THIN_LENS = ('<sensor type="thinlens"><float name="aperture_radius" value="0.2"/>'
             '<float name="focus_distance" value="4"/>')


@pytest.mark.parametrize("sensor", ["perspective", "thinlens"])
def test_a_camera_translating_sideways_gives_the_known_constant_shift_on_the_wall(tmp_path, sensor: str) -> None:
    """The thin lens is projected through its lens centre, as its pixel-centre rays leave it."""
    shot = SHOT
    if sensor == "thinlens":
        shot = tmp_path / "thinlens.xml"
        shot.write_text(SHOT.read_text().replace('<sensor type="perspective">', THIN_LENS))
        assert type(load_scene(str(shot), width=RES, height=RES).sensor).__name__ != "PerspectiveCamera"
    current, previous = (load_scene(str(shot), defines={"cx": str(x), "cy": str(y)}, width=RES, height=RES)
                         for x, y in ((0.0, 0.0), (-0.1, -0.2)))
    motion = render_motion(current, previous, None)
    assert motion.forward is None and motion.forward_valid is None
    vectors, valid = motion.side("backward")
    on_wall = shape_map(current) == WALL
    # the wall is at depth 5; the previous camera sat 0.1 left and 0.2 lower: the wall appears right and higher
    expected = np.array([0.1 * FOCAL / 5.0, 0.2 * FOCAL / 5.0])
    np.testing.assert_allclose(vectors[on_wall & valid], np.broadcast_to(expected, vectors[on_wall & valid].shape),
                               atol=2e-3)
    rows, cols = np.indices(valid.shape)
    lands_off = (cols + 0.5 + expected[0] >= RES) | (rows + 0.5 - expected[1] < 0)
    assert not valid[lands_off].any()  # off screen in the previous frame
    assert np.count_nonzero(valid & on_wall) >= 0.85 * np.count_nonzero(on_wall & ~lands_off)
    assert np.all(vectors[~valid] == 0)


def test_an_object_moving_over_a_static_background() -> None:
    current, previous = frame(sx=0.4), frame(sx=0.1)
    vectors, valid = render_motion(current, previous, None).side("backward")
    here, there = shape_map(current), shape_map(previous)
    wall, ball = here == WALL, here == BALL
    np.testing.assert_allclose(vectors[wall], 0.0, atol=1e-4)  # static wall, static camera
    # a wall pixel is valid exactly where the previous frame saw the wall there (disocclusion: the ball covered it)
    assert np.count_nonzero(valid[wall] != (there[wall] == WALL)) <= 2
    assert np.count_nonzero(wall & (there == BALL)) >= 10  # the test has disoccluded pixels to check
    # the ball moved 0.3 to the right at depths 3.55..4.45: u = -0.3 * FOCAL / depth, v = 0
    u, v = vectors[ball & valid, 0], vectors[ball & valid, 1]
    assert np.all((u <= -0.3 * FOCAL / 4.45 + 1e-3) & (u >= -0.3 * FOCAL / 3.55 - 1e-3))
    np.testing.assert_allclose(v, 0.0, atol=2e-3)
    assert np.count_nonzero(ball & valid) >= 0.9 * np.count_nonzero(ball)
    box = here == BOX
    assert valid[box].all()
    np.testing.assert_allclose(vectors[box], 0.0, atol=1e-4)


def test_an_object_leaving_the_screen_is_invalid_on_that_side_only() -> None:
    current, previous, following = frame(sx=0.4), frame(sx=0.2), frame(sx=3.5)
    motion = render_motion(current, previous, following)
    here = shape_map(current)
    np.testing.assert_array_equal(motion.forward_valid, (here == WALL) | (here == BOX))
    assert motion.backward_valid[here == BALL].mean() > 0.9


def _dict_frame(ball_bsdf: dict, box: dict | None, eye: float = 0.0) -> LoadedScene:
    scene = {
        "type": "scene", "integrator": {"type": "path"}, "light": {"type": "constant"},
        "sensor": {"type": "perspective", "fov": FOV,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[eye, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "wall": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(4)},
        "ball": {"type": "sphere", "center": [0.5, 0, 1], "radius": 0.5, "bsdf": ball_bsdf},
    }
    if box is not None:
        scene["box"] = box
    return LoadedScene(mi.load_dict(scene), "dict", 16, 16, 3, 5)


def test_no_correspondence_for_missing_shapes_and_other_topology() -> None:
    cube = _cube()
    flat = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([-0.8, 0, 1]).scale(0.4)}
    diffuse = {"type": "diffuse"}
    current = _dict_frame(diffuse, cube)
    ids = np.array([s.id() for s in current.scene.shapes()] + [""])
    here = ids[primary_hits(current).shape].reshape(16, 16)
    assert np.count_nonzero(here == "box") > 4 and np.count_nonzero(here == "ball") > 4
    same = render_motion(current, _dict_frame(diffuse, cube), None)
    assert same.backward_valid[(here == "box") | (here == "ball")].all()
    other_topology = render_motion(current, _dict_frame(diffuse, flat), None)
    assert not other_topology.backward_valid[here == "box"].any()
    missing = render_motion(current, _dict_frame(diffuse, None), None)
    assert not missing.backward_valid[here == "box"].any() and missing.backward_valid[here == "ball"].all()


def _cube(y: float = 0.0) -> dict:
    return {"type": "cube", "to_world": mi.ScalarTransform4f().translate([-0.8, y, 1]).scale(0.4)}


def _chain_ends(loaded: LoadedScene) -> np.ndarray:
    """Per pixel, the id of the shape where its specular chain ends ("sky" where it leaves the scene)."""
    chains = specular_chains(loaded, np.arange(loaded.width * loaded.height))
    ids = np.array([s.id() for s in loaded.scene.shapes()] + ["sky", ""])
    last = chains.shape[np.arange(len(chains.length)), np.maximum(chains.length - 1, 0)]
    last = np.where(chains.length > 0, np.where(last == MISS, len(ids) - 2, last), len(ids) - 1)
    return ids[last].reshape(loaded.height, loaded.width)


@pytest.mark.parametrize("material", [{"type": "conductor"}, {"type": "dielectric"}])
def test_a_still_reflection_is_valid_with_vector_0(material: dict) -> None:
    """A mirror or glass ball first hit has no motion of its own: its chain is replayed in the other frame, and
    where nothing on it moved the pixel is valid with vector 0; the environment seen directly too."""
    current = _dict_frame(material, _cube())
    here = shape_map(current)
    on_ball = (_chain_ends(current) != "") & (here == "")
    # specular first hits that see a surface, which the old rule left invalid
    assert np.count_nonzero(on_ball & (_chain_ends(current) != "sky")) > 4
    motion = render_motion(current, _dict_frame(material, _cube()), _dict_frame(material, _cube()))
    for side in ("backward", "forward"):
        vectors, valid = motion.side(side)
        assert valid.all()
        assert np.all(vectors[on_ball] == 0)
        np.testing.assert_allclose(vectors, 0.0, atol=1e-4)  # the projected diffuse hits: float32 rounding


def test_a_reflection_moving_differently_from_its_mirror_is_invalid() -> None:
    """Issue 53's ghosting case: the mirror stands still while the cube it reflects moves, so the pixels that see
    the cube in the mirror are invalid and those that see the sky stay valid; a moving camera invalidates all the
    mirror's pixels (their image's motion is not traced)."""
    mirror = {"type": "conductor"}
    current = _dict_frame(mirror, _cube())
    ends = _chain_ends(current)
    first = shape_map(current)
    in_mirror = first == ""  # specular first hit or sky
    sees_cube = in_mirror & (ends == "box") & ~(np.asarray(primary_hits(current).shape) >= 0).reshape(16, 16)
    assert sees_cube.sum() >= 1, ends
    vectors, valid = render_motion(current, _dict_frame(mirror, _cube(0.1)), None).side("backward")
    assert not valid[sees_cube].any()
    assert valid[in_mirror & (ends == "sky")].all() and np.all(vectors[in_mirror & (ends == "sky")] == 0)
    _, valid = render_motion(current, _dict_frame(mirror, _cube(), eye=0.05), None).side("backward")
    assert not valid[in_mirror].any()


def albedo(loaded: LoadedScene) -> np.ndarray:
    """The noise-free albedo image (Mitsuba's aov integrator, enough samples to settle the pixel footprints)."""
    integrator = mi.load_dict({"type": "aov", "aovs": "a:albedo"})
    return np.asarray(mi.render(loaded.scene, integrator=integrator, spp=64, seed=1))[..., :3]


def bilinear(image: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``image`` sampled at fractional pixel indices (clamped at the border)."""
    h, w = image.shape[:2]
    r, c = np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)
    r0, c0 = np.minimum(np.floor(r).astype(int), h - 2), np.minimum(np.floor(c).astype(int), w - 2)
    fr, fc = (r - r0)[..., None], (c - c0)[..., None]
    top = image[r0, c0] * (1 - fc) + image[r0, c0 + 1] * fc
    bottom = image[r0 + 1, c0] * (1 - fc) + image[r0 + 1, c0 + 1] * fc
    return top * (1 - fr) + bottom * fr


def test_warping_the_previous_frame_with_backward_vectors_removes_most_of_the_difference() -> None:
    """The issue's target: on a moving shot (camera and both objects move), frame t-1 warped onto t with
    ``backward`` leaves <= 0.25x the error of not warping, in valid pixels."""
    res = 48
    current = frame(res, cx=0.0, cy=0.0, sx=0.4, bx=-0.9)
    previous = frame(res, cx=-0.25, cy=0.15, sx=0.1, bx=-0.7)
    motion = render_motion(current, previous, None)
    rows, cols, valid = motion.warp_source("backward")
    now, before = albedo(current), albedo(previous)
    warped = bilinear(before, rows, cols)
    error_warped = np.mean((warped - now)[valid] ** 2)
    error_unwarped = np.mean((before - now)[valid] ** 2)
    assert valid.mean() > 0.8
    assert error_warped <= 0.25 * error_unwarped, (error_warped, error_unwarped)


def test_shapes_without_an_id_are_matched_by_their_place(tmp_path) -> None:
    text = SHOT.read_text()
    for name in (WALL, BALL, BOX):
        text = text.replace(f' id="{name}"', "")
    unnamed = tmp_path / "unnamed.xml"
    unnamed.write_text(text)

    def load(**values: float) -> LoadedScene:
        return load_scene(str(unnamed), defines={k: str(v) for k, v in values.items()}, width=RES, height=RES)

    assert {s.id() for s in load().scene.shapes()} == {""}
    named = render_motion(frame(sx=0.4), frame(sx=0.1), None)
    plain = render_motion(load(sx=0.4), load(sx=0.1), None)
    np.testing.assert_array_equal(plain.backward_valid, named.backward_valid)
    np.testing.assert_allclose(plain.backward, named.backward, atol=1e-5)


def test_rendered_vectors_travel_through_a_frame_file(tmp_path) -> None:
    from gradsep.model.exr_read import read_frame
    from gradsep.model.exr_write import write_frame
    from gradsep.model.frame import Frame, Layer

    motion = render_motion(frame(sx=0.4), frame(sx=0.1, cx=-0.1), frame(sx=0.7, cy=0.1))
    out = Frame({"color": Layer(np.ones((RES, RES, 3), np.float32))}, motion=motion)
    write_frame(tmp_path / "f.exr", out, half=True)
    back = read_frame(tmp_path / "f.exr").motion
    for direction in ("backward", "forward"):
        np.testing.assert_array_equal(back.side(direction)[0], motion.side(direction)[0])
        np.testing.assert_array_equal(back.side(direction)[1], motion.side(direction)[1])
