"""`gradsep render --frames` (renderer/shot.py): bad input is one line, exit 2 and no file; a shot's frames, their
headers and seeds; a re-run skips complete frames; shards make the whole shot; --animate; the plan cache."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from gradsep.cli import main
from gradsep.model.exr_read import read_frame, read_header
from gradsep.model.shot import frame_seed

pytestmark = pytest.mark.render

DATA = Path(__file__).resolve().parents[1] / "data" / "shot"
MOVING = str(DATA / "moving.xml")
PER_FRAME = str(DATA / "frame.%04d.xml")
TINY = ["--width", "16", "--height", "12", "--spp", "2"]


def _render(tmp_path: Path, *args: str, output: str = "out.%04d.exr") -> int:
    return main(["render", *args, *TINY, "-o", str(tmp_path / output)])


@pytest.mark.parametrize(("args", "output", "message"), [
    ([MOVING, "--frames", ""], "out.%04d.exr", "--frames is empty"),
    ([MOVING, "--frames", "5-3"], "out.%04d.exr", "is reversed"),
    ([MOVING, "--frames", "1-b"], "out.%04d.exr", "expected A-B"),
    ([MOVING, "--frames", "1.5"], "out.%04d.exr", "expected A-B"),
    ([MOVING, "--frames", "1-3"], "out.exr", "has no frame-number field"),
    ([MOVING], "out.%04d.exr", "give --frames A-B"),
    ([MOVING], "out.####.exr", "give --frames A-B"),
    ([PER_FRAME], "out.exr", "give --frames A-B"),
    ([MOVING, "--animate", "pos=0,0,0:1,0,0"], "out.exr", "give --frames A-B"),
    ([MOVING, "--frames", "1-3", "--animate", "nothere=0:1"], "out.%04d.exr", "no <default> parameter named"),
    ([MOVING, "--frames", "1-3", "--animate", "pos=0,0,0"], "out.%04d.exr", "expected NAME=START:END"),
    ([MOVING, "--frames", "1-3", "--animate", "pos=0,0:1,0,0"], "out.%04d.exr", "components"),
    ([MOVING, "--frames", "1-3", "--animate", "pos=0,0,0:1,0,0", "-D", "pos=1,1,1"], "out.%04d.exr",
     "--animate and -D both set pos"),
    ([PER_FRAME, "--frames", "1-4"], "out.%04d.exr", "scene file not found"),
    ([PER_FRAME, "--frames", "0-2"], "out.%04d.exr", "frame.0000.xml"),
    ([MOVING, "--frames", "1-3", "--shard", "2/2"], "out.%04d.exr", "--shard must be i/n"),
    (["procedural:3", "--frames", "1-3", "--animate", "x=0:1"], "out.%04d.exr", "XML scenes only"),
    ([MOVING, "--frames", "1-3"], "out.%04d.png", "must end in .exr"),
    ([MOVING, "--frames", "1-3"], "nofolder/out.%04d.exr", "does not exist"),
])
def test_bad_input_is_one_line_exit_2_and_no_file(tmp_path, capsys, args, output, message):
    assert _render(tmp_path, *args, output=output) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []


def test_a_per_frame_shot_writes_its_frames_and_a_rerun_skips_them(tmp_path, capsys):
    assert _render(tmp_path, PER_FRAME, "--frames", "1-3", "--seed", "5") == 0
    paths = [tmp_path / f"out.{n:04d}.exr" for n in (1, 2, 3)]
    frames = [read_frame(p) for p in paths]
    for n, frame in zip((1, 2, 3), frames, strict=True):
        meta = frame.metadata
        assert meta["gradsep.frame"] == str(n) and meta["gradsep.shot"] == "1-3"
        assert meta["gradsep.seed"] == str(frame_seed(5, n))
        assert meta["gradsep.scene"] == str(DATA / f"frame.{n:04d}.xml")
        assert frame.width == 16 and frame.height == 12
        assert all(np.isfinite(v).all() for v in frame.to_channels().values())
    assert len({f.metadata["gradsep.seed"] for f in frames}) == 3
    capsys.readouterr()
    stamps = [p.stat().st_mtime_ns for p in paths]
    assert _render(tmp_path, PER_FRAME, "--frames", "1-3", "--seed", "5") == 0
    assert "3 complete on disk, 0 to render" in capsys.readouterr().out
    assert [p.stat().st_mtime_ns for p in paths] == stamps
    # another shot's settings at these paths: refused before anything renders, nothing overwritten
    assert _render(tmp_path, PER_FRAME, "--frames", "1-3", "--seed", "6") == 2
    assert "holds frame 1 of shot 1-3 with other settings" in capsys.readouterr().err
    assert [p.stat().st_mtime_ns for p in paths] == stamps


def test_frames_of_a_static_scene_have_distinct_noise(tmp_path):
    assert _render(tmp_path, MOVING, "--frames", "1001-1003") == 0
    images = [read_frame(tmp_path / f"out.{n}.exr").layers["direct"].base for n in (1001, 1002, 1003)]
    assert not np.array_equal(images[0], images[1]) and not np.array_equal(images[1], images[2])


def test_shards_together_make_the_whole_shot(tmp_path, capsys):
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    whole.mkdir()
    parts.mkdir()
    assert _render(whole, MOVING, "--frames", "1-3", output="f.####.exr") == 0
    assert _render(parts, MOVING, "--frames", "1-3", "--shard", "0/2", output="f.####.exr") == 0
    assert sorted(p.name for p in parts.glob("*.exr")) == ["f.0001.exr"]
    assert _render(parts, MOVING, "--frames", "1-3", "--shard", "1/2", output="f.####.exr") == 0
    assert sorted(p.name for p in parts.glob("*.exr")) == ["f.0001.exr", "f.0002.exr", "f.0003.exr"]
    for n in (1, 2, 3):
        a, b = read_frame(whole / f"f.{n:04d}.exr"), read_frame(parts / f"f.{n:04d}.exr")
        assert np.array_equal(a.layers["direct"].base, b.layers["direct"].base)
        assert read_header(parts / f"f.{n:04d}.exr").attributes["gradsep.shot"] == "1-3"


def test_animated_values_land_in_headers_and_change_the_image(tmp_path):
    static, moving = tmp_path / "static", tmp_path / "moving"
    static.mkdir()
    moving.mkdir()
    assert _render(static, MOVING, "--frames", "1-3") == 0
    assert _render(moving, MOVING, "--frames", "1-3", "--animate", "pos=-1,0.5,0:1,0.5,0",
                   "--animate", "radius=0.3:0.6") == 0
    for n, (pos, radius) in zip((1, 2, 3), (("-1, 0.5, 0", "0.3"), ("0, 0.5, 0", "0.45"), ("1, 0.5, 0", "0.6")),
                                strict=True):
        meta = read_header(moving / f"out.{n:04d}.exr").attributes
        assert meta["gradsep.animate.pos"] == pos and meta["gradsep.animate.radius"] == radius
        a = read_frame(static / f"out.{n:04d}.exr").layers["direct"].base
        b = read_frame(moving / f"out.{n:04d}.exr").layers["direct"].base
        assert a.shape == b.shape and not np.array_equal(a, b)


def test_the_plan_cache_key_is_the_shots_not_each_frames(tmp_path):
    import argparse

    from gradsep.renderer.shot import HIDDEN_PLAN_CACHE, checked_shot, plan_cache_of

    for n in (1, 2, 3):
        shutil.copy(DATA / f"frame.{n:04d}.xml", tmp_path / f"s.{n:04d}.xml")
    args = argparse.Namespace(scene=str(tmp_path / "s.%04d.xml"), output=str(tmp_path / "o.%04d.exr"),
                              frames="1-3", shard=None, animate=[], define=[], plan_key=None)
    shot, shard = checked_shot(args)
    cache = plan_cache_of(shot, args, None, "auto")
    assert cache.folder == tmp_path / HIDDEN_PLAN_CACHE
    assert not cache.folder.exists()  # made by the first judgement stored: a shot that fails first leaves nothing
    assert "shot:1-3" in cache.scene
    assert plan_cache_of(shot, args, None, "all") is None


def test_a_shot_that_fails_to_start_leaves_nothing_beside_its_outputs(tmp_path, capsys):
    for n in (1, 2):  # valid XML that Mitsuba cannot instantiate: the failure comes after the shot's checks
        (tmp_path / f"s.{n:04d}.xml").write_text('<scene version="3.0.0"><shape type="nosuchplugin"/></scene>')
    code = main(["render", str(tmp_path / "s.%04d.xml"), "--frames", "1-2", "--spp", "4", "--width", "8",
                 "--height", "8", "--gradients", "auto", "-o", str(tmp_path / "o.%04d.exr")])
    assert code == 2 and "nosuchplugin" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.0001.xml", "s.0002.xml"]


@pytest.mark.slow
def test_gradients_auto_judges_once_per_shot(tmp_path, capsys):
    assert main(["render", MOVING, "--width", "16", "--height", "12", "--spp", "64", "--gradients", "auto",
                 "--frames", "1-2", "-o", str(tmp_path / "a.%04d.exr")]) == 0
    out = capsys.readouterr().out
    assert "plan cache: wrote" in out and "judged by an earlier frame" in out
    assert len(list((tmp_path / ".gradsep-plans").glob("plan-*.json"))) == 1
    assert read_header(tmp_path / "a.0002.exr").attributes["gradsep.plan_cache"].startswith("read ")
