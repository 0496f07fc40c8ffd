"""Scene loading: XML and procedural scenes, forced box filter and film size, <default> overrides, refusals."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from gradsep.model.errors import CommandError  # noqa: E402
from gradsep.renderer.errors import SceneError  # noqa: E402
from gradsep.renderer.procedural import generate  # noqa: E402
from gradsep.renderer.scene import (  # noqa: E402
    _NON_MESH_SHAPES,
    force_film_dict,
    integrator_depths,
    load_scene,
    parse_defines,
)
from gradsep.renderer.variant import select_variant  # noqa: E402
from tests.renderer import scenes  # noqa: E402
from tests.renderer.scenes import resolve  # noqa: E402

pytestmark = pytest.mark.render


# The shared third-party scenes when present, else built-in equivalents (tests/renderer/scenes.py).
CBOX = resolve("cbox").path
TEAPOT = resolve("teapot").path


def write_scene(folder: Path, body: str, sensor: str | None = None) -> Path:
    """A small XML scene: a diffuse rectangle in front of a perspective camera plus ``body``."""
    sensor = sensor or """
        <sensor type="perspective">
            <transform name="to_world"><lookat origin="0,0,3" target="0,0,0" up="0,1,0"/></transform>
            <film type="hdrfilm"><integer name="width" value="20"/><integer name="height" value="10"/></film>
        </sensor>"""
    path = folder / "scene.xml"
    path.write_text(f"""<scene version="3.0.0">
        {sensor}
        <shape type="rectangle"><bsdf type="diffuse"/></shape>
        {body}
    </scene>""")
    return path


def test_test_scenes_load_with_box_filter_and_their_settings():
    cbox = load_scene(str(CBOX))
    assert (cbox.width, cbox.height) == (256, 256)  # the file's <default name="res">
    assert cbox.max_depth == 6 and cbox.rr_depth == 5
    assert cbox.sensor.film().rfilter().class_name() == "BoxFilter"  # the file asks for a tent filter
    teapot = load_scene(str(TEAPOT), width=32, height=16)
    assert (teapot.width, teapot.height) == (32, 16)
    assert teapot.max_depth == 2  # its integrator is `direct`
    assert teapot.sensor.film().rfilter().class_name() == "BoxFilter"


def test_one_dimension_keeps_the_aspect_ratio(tmp_path):
    path = write_scene(tmp_path, '<emitter type="constant"/>')
    loaded = load_scene(str(path), width=40)
    assert (loaded.width, loaded.height) == (40, 20)
    loaded = load_scene(str(path), height=5)
    assert (loaded.width, loaded.height) == (10, 5)


def test_defaults_can_be_overridden():
    loaded = load_scene(str(CBOX), defines={"max_depth": "3", "res": "16"})
    assert (loaded.width, loaded.height) == (16, 16)
    assert loaded.max_depth == 3
    assert loaded.defines == {"max_depth": "3", "res": "16"}
    # an explicit size wins over a define that only sized the film
    loaded = load_scene(str(CBOX), width=8, height=8, defines={"res": "16"})
    assert (loaded.width, loaded.height) == (8, 8)
    # an explicit max_depth wins over the scene's
    assert load_scene(str(CBOX), width=8, max_depth=-1).max_depth == -1


CUBE_OBJ = """v -1 -1 -1\nv 1 -1 -1\nv 1 1 -1\nv -1 1 -1\nv -1 -1 1\nv 1 -1 1\nv 1 1 1\nv -1 1 1
f 1 4 3 2\nf 5 6 7 8\nf 1 2 6 5\nf 2 3 7 6\nf 3 4 8 7\nf 4 1 5 8
"""


def test_relative_paths_resolve_from_the_scene_folder(tmp_path, monkeypatch):
    """A mesh named relative to the XML (as the shared scenes' meshes are) loads from any working directory."""
    folder = tmp_path / "scene"
    (folder / "meshes").mkdir(parents=True)
    (folder / "meshes" / "cube.obj").write_text(CUBE_OBJ)
    xml = folder / "scene.xml"
    xml.write_text("""<scene version="3.0.0">
        <sensor type="perspective">
            <transform name="to_world"><lookat origin="0,0,6" target="0,0,0" up="0,1,0"/></transform>
        </sensor>
        <shape type="obj"><string name="filename" value="meshes/cube.obj"/></shape>
        <emitter type="constant"/>
    </scene>""")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # the mesh is relative to the XML, not to the working directory
    loaded = load_scene(os.path.relpath(xml, elsewhere), width=8, height=8)
    assert len(loaded.scene.shapes()) == 1
    assert loaded.scene.shapes()[0].face_count() == 12  # six quads, triangulated
    # and the resolver is left as it was
    resolver = mi.file_resolver()
    assert str(folder) not in [str(resolver[i]) for i in range(len(resolver))]
    # the same file is not found without the scene's folder on the resolver
    with pytest.raises(SceneError, match="failed to load"):
        load_scene(str(write_scene(elsewhere, '<shape type="obj"><string name="filename" value="meshes/cube.obj"/>'
                                              '</shape><emitter type="constant"/>')))


@pytest.mark.parametrize("body, sensor, message", [
    ("", None, "no emitter"),
    ('<emitter type="constant"/>', """<sensor type="orthographic"><film type="hdrfilm"/></sensor>""",
     "unsupported sensor"),
    ("""<emitter type="constant"/>
        <shape type="sphere"><medium type="homogeneous" name="interior"/><bsdf type="null"/></shape>""", None,
     "participating media"),
    ('<emitter type="nosuchplugin"/>', None, "failed to load"),
    ('<shape type="obj"><string name="filename" value="missing.obj"/></shape><emitter type="constant"/>', None,
     "failed to load"),
])
def test_unrenderable_scenes_are_clear_errors(tmp_path, body, sensor, message):
    path = write_scene(tmp_path, body, sensor)
    with pytest.raises(SceneError, match=message) as info:
        load_scene(str(path))
    assert isinstance(info.value, CommandError)  # the CLI prints it as one line, exit status 2
    assert "\n" not in str(info.value)


def test_bad_files_and_arguments(tmp_path):
    with pytest.raises(SceneError, match="not found"):
        load_scene(str(tmp_path / "nope.xml"))
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene><shape></scene>")
    with pytest.raises(SceneError, match="not valid XML"):
        load_scene(str(bad))
    other = tmp_path / "other.xml"
    other.write_text("<html/>")
    with pytest.raises(SceneError, match="expected a Mitsuba <scene>"):
        load_scene(str(other))
    with pytest.raises(SceneError, match="no <default> parameter named nosuch"):
        load_scene(str(CBOX), defines={"nosuch": "1"})
    with pytest.raises(SceneError, match="width"):
        load_scene(str(CBOX), width=0)
    with pytest.raises(SceneError, match="max-depth"):
        load_scene(str(CBOX), max_depth=0)
    with pytest.raises(SceneError, match="exceeds"):
        load_scene(str(CBOX), width=9000, height=9000)


def test_parse_defines():
    assert parse_defines(["spp=16", " res = 64 "]) == {"spp": "16", "res": "64"}
    assert parse_defines(None) == {}
    for bad in ("spp", "=3", "1x=2", "a b=1"):
        with pytest.raises(SceneError, match="NAME=VALUE"):
            parse_defines([bad])


def test_integrator_depths():
    select_variant()
    for props, expected in (({"type": "path", "max_depth": 9, "rr_depth": 3}, (9, 3)),
                            ({"type": "path", "max_depth": -1}, (-1, 5)),
                            ({"type": "direct"}, (2, 5))):
        scene = mi.load_dict({"type": "scene", "integrator": props,
                              "light": {"type": "constant"}})
        assert integrator_depths(scene) == expected


def test_procedural_scenes_load_at_the_requested_size():
    pytest.importorskip("gradsep.renderer.procedural")
    loaded = load_scene("procedural:3", width=24, height=16)
    assert (loaded.width, loaded.height) == (24, 16)
    assert loaded.sensor.film().rfilter().class_name() == "BoxFilter"
    assert loaded.scene.emitters()
    with pytest.raises(SceneError, match="integer seed"):
        load_scene("procedural:abc")
    with pytest.raises(SceneError, match="XML scenes only"):
        load_scene("procedural:3", defines={"res": "8"})


def test_force_film_dict_rewrites_the_first_sensor():
    scene = {"type": "scene", "cam": {"type": "perspective",
                                      "film": {"type": "hdrfilm", "width": 5, "rfilter": {"type": "gaussian"},
                                               "crop_width": 2}}}
    force_film_dict(scene, 7, 3)
    film = scene["cam"]["film"]
    assert (film["width"], film["height"], film["rfilter"]) == (7, 3, {"type": "box"})
    assert "crop_width" not in film


def test_scene_lookup_prefers_gradsep_scenes_and_falls_back_to_builtins(tmp_path, monkeypatch):
    """$GRADSEP_SCENES is the only place looked at when set; without the scenes there, the built-ins are used."""
    monkeypatch.setenv(scenes.SCENES_ENV, str(tmp_path))
    for name in scenes.SCENE_NAMES:
        found = scenes.find(name)
        assert found.builtin and found.path.is_file() and found.path.name == f"{name}.xml"
    (tmp_path / "cbox").mkdir()
    (tmp_path / "cbox" / "cbox.xml").write_text("<scene version='3.0.0'/>")
    assert scenes.find("cbox") == scenes.ResolvedScene("cbox", tmp_path / "cbox" / "cbox.xml", builtin=False)
    assert scenes.find("teapot").builtin
    with pytest.raises(KeyError, match="no test scene"):
        scenes.find("sponza")


def test_builtin_scenes_stand_in_for_the_shared_ones():
    """The built-in scenes carry the settings the tests rely on, and the built-in Cornell box renders like the
    shared one (same room from rectangles instead of OBJ quads) when that is available to compare with."""
    cbox = load_scene(str(scenes.builtin_path("cbox")), width=16, height=16)
    assert cbox.max_depth == 6 and cbox.rr_depth == 5
    assert cbox.sensor.film().rfilter().class_name() == "BoxFilter"
    assert len(cbox.scene.emitters()) == 1  # (Mitsuba merges the three white walls into one mesh)
    assert load_scene(str(scenes.builtin_path("cbox")), defines={"res": "12"}).width == 12
    teapot = load_scene(str(scenes.builtin_path("teapot")), width=16, height=16)
    assert teapot.max_depth == 2 and len(teapot.scene.emitters()) == 2
    assert all(e.is_environment() is False for e in teapot.scene.emitters())
    shared = [folder / "cbox" / "cbox.xml" for folder in scenes.shared_candidates()
              if (folder / "cbox" / "cbox.xml").is_file()]
    if not shared:
        return  # nothing to compare with; the settings above are what the other tests need
    path = mi.load_dict({"type": "path", "max_depth": 6})
    means = [np.array(mi.render(load_scene(str(p), width=16, height=16).scene, integrator=path, spp=256, seed=3),
                      dtype=np.float64).mean(axis=(0, 1)) for p in (shared[0], scenes.builtin_path("cbox"))]
    np.testing.assert_allclose(means[1], means[0], rtol=0.03)


def _emitter_names(scene: mi.Scene) -> list[str]:
    return [e.get_shape().id() if e.get_shape() is not None else e.id() for e in scene.emitters()]


def test_emitters_come_in_declaration_order_and_meshes_are_still_merged(tmp_path):
    """Which light a sample picks follows the scene's emitter list. Mitsuba's mesh merge would list meshes -- area
    lights on rectangles among them -- in an order keyed by object addresses, different in every process; the
    loader keeps emitting meshes out of it: non-mesh emitters first, then emitting meshes, each as declared. Plain
    meshes sharing a material are still merged (many small meshes would otherwise slow every render)."""
    lamps = "".join(f"""
        <shape type="rectangle" id="lamp{i}">
            <transform name="to_world"><scale value="0.1"/><translate x="{0.2 * i - 0.5}" y="0.8"/></transform>
            <emitter type="area"><rgb name="radiance" value="{1 + i}"/></emitter>
        </shape>""" for i in range(6))
    body = f"""{lamps[:len(lamps) // 2]}
        <emitter type="point" id="bulb"><point name="position" x="0" y="1" z="1"/></emitter>
        <shape type="rectangle"><transform name="to_world"><translate z="-1"/></transform><bsdf type="diffuse"/></shape>
        <shape type="sphere" id="ball"><float name="radius" value="0.1"/><emitter type="area"/></shape>
        {lamps[len(lamps) // 2:]}"""
    loaded = load_scene(str(write_scene(tmp_path, body)), width=8, height=8)
    assert _emitter_names(loaded.scene) == ["bulb", "ball"] + [f"lamp{i}" for i in range(6)]
    assert len(loaded.scene.shapes()) == 8  # the two plain rectangles are one mesh, as Mitsuba merges them
    # procedural:7: a spot light (not a shape) and two emitting rectangles, light_0 and light_2
    assert _emitter_names(load_scene("procedural:7", width=8, height=8).scene) == ["light_1", "light_0", "light_2"]


def test_the_non_mesh_shape_plugins_are_not_meshes():
    """The loader keeps emitting meshes out of Mitsuba's merge by plugin name: a plugin this Mitsuba builds as a
    mesh (rectangles are meshes) must not be listed as a non-mesh shape, or its area lights go back to the merge."""
    assert {"sphere", "cylinder", "disk"} <= _NON_MESH_SHAPES
    for plugin in ("sphere", "cylinder", "disk", "rectangle", "cube"):
        shape = mi.load_dict({"type": plugin})
        assert isinstance(shape, mi.Mesh) == (plugin not in _NON_MESH_SHAPES), plugin


_RENDER_IN_A_PROCESS = """
import hashlib
from gradsep.renderer.render import render_frame
from gradsep.renderer.scene import load_scene
loaded = load_scene("procedural:152", width=12, height=10)  # three emitting rectangles
frame = render_frame(loaded, spp=2, seed=3, gradients="none")
print([e.get_shape().id() for e in loaded.scene.emitters()])
print(hashlib.sha256(b"".join(frame.layers[name].base.tobytes() for name in sorted(frame.layers))).hexdigest())
"""


@pytest.mark.slow
def test_a_seeded_render_is_the_same_in_every_process():
    """Two processes rendering one procedural frame with one seed get the same pixels bit for bit (in one process
    every render agreed even before; the emitter order differed between processes)."""
    lights = generate(152).summary["lights"]
    assert sum(kind in ("ceiling", "wall_wash", "uplight") for kind in lights) >= 2, lights  # area lights on meshes
    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(repo)}
    outputs = [subprocess.run([sys.executable, "-c", _RENDER_IN_A_PROCESS], env=env, cwd=repo, capture_output=True,
                              text=True, timeout=300, check=False) for _ in range(2)]
    for proc in outputs:
        assert proc.returncode == 0, proc.stderr[-2000:]
    assert outputs[0].stdout == outputs[1].stdout
