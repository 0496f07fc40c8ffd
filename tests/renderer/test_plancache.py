"""The plan cache (renderer/plancache.py): `gradsep render --gradients auto --plan-cache DIR`.

Entries round-trip and name what must agree; an entry that cannot be used is judged afresh with a note; the
command refuses a cache it cannot use (exit 2, one line, no file); a frame that reads an entry renders its plan
with no checkpoint and carries the judging frame's estimate, and a frame whose checkpoint judged writes one.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from gradsep.cli import main
from gradsep.model.errors import CommandError
from gradsep.model.exr_read import read_frame
from gradsep.model.header_keys import PREDICTED_RELMSE_KEY
from gradsep.renderer.checkpoint import Assessment, Judgement
from gradsep.renderer.plancache import (
    CACHE_ENV,
    FRAME_ESTIMATE,
    CacheFolder,
    FrameKey,
    PlanCache,
    check_folder,
    entry_key,
    scene_identity,
)
from gradsep.renderer.plans import PLAN_CACHE_KEY, PLAN_KEY, plan_named
from tests.renderer.scenes import resolve

CBOX = str(resolve("cbox"))
SMALL = ["--width", "16", "--height", "12"]
LAYERS = ("direct", "indirect")


def key(**changes: object) -> dict[str, object]:
    fields: dict[str, object] = {"width": 16, "height": 12, "layers": LAYERS, "max_depth": 5, "shift": "hybrid",
                                 "seconds": 20.0, "spp": None}
    cpu = str(changes.pop("cpu", "a CPU x2"))
    fields.update(changes)
    return entry_key("procedural:7", FrameKey(**fields), cpu)  # type: ignore[arg-type]


def judged(chosen: str = "primal") -> Judgement:
    """A checkpoint's plan as run_checkpoint makes one."""
    assessments = [Assessment(name, 40, relmse, per_sample, method, 1e-4, 0.5, spp, relmse / 4, 1e-5, 0.02, 1e-6)
                   for name, relmse, per_sample, method, spp in (("direct-alternate", 2e-3, 0.02, "oidn-l1", 900),
                                                                  ("primal", 1e-3, 0.013, "oidn", 1400))]
    trace = {"spp": 80, "difference": [-1e-4, 2e-5], "chosen": chosen}
    return Judgement(plan_named(chosen), assessments, 3.0, "checkpoint at 80 spp", trace)


# -- entries ------------------------------------------------------------------------------------------------

def test_an_entry_round_trips_with_the_judging_frames_estimate(tmp_path):
    entry = PlanCache(tmp_path, key())
    assert entry.load() == (None, None)  # nothing yet: judged here, no note
    assert entry.store(judged("primal"), seed=3, estimate=(4e-4, 1200)) is None
    plan, note = PlanCache(tmp_path, key()).load()
    assert note is None and plan is not None
    assert plan.chosen == plan_named("primal") and plan.pilot_seconds == 0.0
    assert [a.name for a in plan.assessments] == ["direct-alternate", "primal"]
    assert plan.assessment().predicted_relmse == pytest.approx(1e-3 / 4)  # type: ignore[union-attr]
    assert plan.trace["cached"] == entry.path.name and plan.trace["difference"] == [-1e-4, 2e-5]
    assert plan.trace[FRAME_ESTIMATE] == {"relmse": 4e-4, "spp": 1200}
    assert "earlier frame" in plan.summary() and "checkpoint 0.00" not in plan.summary()
    data = json.loads(entry.path.read_text())
    assert data["judged"]["seed"] == 3 and data["key"] == key()
    assert [p.name for p in tmp_path.iterdir()] == [entry.path.name]  # written atomically: no temporary left


def test_an_entrys_name_and_key_keep_their_format():
    """Entries written by an earlier version stay readable: the key's fields and the file's name from them."""
    assert key() == {"scene": "procedural:7", "size": [16, 12], "layers": ["direct", "indirect"], "max_depth": 5,
                     "shift": "hybrid", "budget": "seconds=20", "cpu": "a CPU x2"}
    assert key(seconds=None, spp=64)["budget"] == "spp=64"
    assert PlanCache(Path("."), key()).path.name == "plan-65ad0d4a3c70466be73e.json"


@pytest.mark.parametrize("change", [{"seconds": 10.0}, {"seconds": None, "spp": 64}, {"width": 32},
                                    {"layers": ("direct",)}, {"max_depth": 2}, {"shift": "replay"},
                                    {"cpu": "another CPU x16"}])
def test_what_decides_the_plan_names_another_entry(tmp_path, change):
    assert PlanCache(tmp_path, key(**change)).path != PlanCache(tmp_path, key()).path


def test_a_scene_file_is_named_by_its_content_and_defines(tmp_path):
    scene = tmp_path / "shot.xml"
    scene.write_text("<scene version='3.0.0'/>")
    first = scene_identity(str(scene))
    assert first.startswith("sha256:") and scene_identity(str(scene)) == first
    moved = tmp_path / "elsewhere.xml"
    moved.write_bytes(scene.read_bytes())
    assert scene_identity(str(moved)) == first  # the same shot from another path or checkout
    assert scene_identity(str(scene), {"spp": "4"}) != first
    scene.write_text("<scene version='3.0.0'><!-- edited --></scene>")
    assert scene_identity(str(scene)) != first
    assert scene_identity("procedural:studio:9") == "procedural:studio:9"


@pytest.mark.parametrize(("content", "why"), [
    ("{", "not used"),
    (json.dumps({"version": 99}), "version 1"),
    ("[]", "version 1"),
    ("KEY", "key differs"),
    ("PLAN:all", "not one this frame can render"),
    ("ASSESS:nan", "not usable"),
    ("ASSESS:list", "not used"),
    ("ESTIMATE:-1", "frame estimate"),
])
def test_an_entry_that_cannot_be_used_is_judged_afresh_with_a_note(tmp_path, content, why):
    entry = PlanCache(tmp_path, key())
    entry.store(judged(), seed=1, estimate=(1e-3, 100))
    data = json.loads(entry.path.read_text())
    if content == "KEY":
        data["key"] = key(seconds=5.0)
    elif content.startswith("PLAN:"):
        data["chosen"] = content[5:]  # an unseparated frame's plan: not a candidate of a separated one
    elif content == "ASSESS:nan":
        data["assessments"][1]["predicted_relmse"] = math.nan
    elif content == "ASSESS:list":
        data["assessments"] = [[1, 2]]
    elif content.startswith("ESTIMATE:"):
        data[FRAME_ESTIMATE]["relmse"] = -1.0
    text = content if content[0] in "{[" else json.dumps(data)
    entry.path.write_text(text)
    plan, note = entry.load()
    assert plan is None and why in note and entry.path.name in note and "judged afresh" in note  # type: ignore


def test_the_folder_must_exist(tmp_path):
    with pytest.raises(CommandError, match="not a folder"):
        check_folder(tmp_path / "missing")
    (tmp_path / "file").write_text("")
    with pytest.raises(CommandError, match="not a folder"):
        check_folder(tmp_path / "file")
    assert check_folder(tmp_path) == tmp_path


# -- the command ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("extra", "message"), [
    (["--spp", "4", "--gradients", "all", "--plan-cache", "DIR"], "no effect with --gradients all"),
    (["--seconds", "5", "--no-gradients", "--plan-cache", "DIR"], "no effect with --gradients none"),
    (["--spp", "64", "--gradients", "auto", "--plan-key", "shot"], "give --plan-cache DIR"),
    (["--spp", "64", "--gradients", "auto", "--plan-cache", "DIR", "--plan-key", " "], "must not be empty"),
    (["--spp", "64", "--gradients", "auto", "--plan-cache", "MISSING"], "not a folder"),
])
def test_the_command_refuses_a_cache_it_cannot_use(tmp_path, capsys, monkeypatch, extra, message):
    monkeypatch.delenv(CACHE_ENV, raising=False)
    (tmp_path / "DIR").mkdir()
    extra = [str(tmp_path / a) if a in ("DIR", "MISSING") else a for a in extra]
    out = tmp_path / "f.exr"
    assert main(["render", CBOX, *SMALL, *extra, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not out.exists() and list((tmp_path / "DIR").iterdir()) == []


@pytest.mark.render
def test_a_farm_wide_folder_is_left_unused_by_a_fixed_plan(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "missing"))  # not even checked: there is no choice to keep
    out = tmp_path / "f.exr"
    assert main(["render", CBOX, *SMALL, "--spp", "2", "-o", str(out)]) == 0
    assert PLAN_CACHE_KEY not in read_frame(out).metadata


@pytest.mark.render
def test_a_frame_that_reads_an_entry_renders_its_plan_with_no_checkpoint(tmp_path, small):
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.planned_frame import PlanRequest, render_planned_frame

    folder = CacheFolder(tmp_path, "key:shot-12")
    entry = folder.entry(FrameKey(16, 12, LAYERS, small.max_depth, "hybrid", None, 64))
    entry.store(judged("primal"), seed=1, estimate=(2e-3, 32))
    frame, summary = render_planned_frame(small, FrameBudget(spp=64), PlanRequest(seed=2), plan_cache=folder)
    meta = frame.metadata
    assert meta[PLAN_KEY] == "primal" and meta["gradsep.gradients"] == "none" and not frame.gradient_layers
    assert meta[PLAN_CACHE_KEY] == f"read {entry.path.name}" and meta["gradsep.pilot_seconds"] == "0.000"
    assert meta["gradsep.spp"] == "64" and "gradsep.gradient_spp" not in meta  # no checkpoint's passes
    # no halves of its own at --spp: the judging frame's estimate carried from its 32 spp to 64 (exponent 0.5)
    assert meta["gradsep.predicted_from"] == "plan-cache"
    assert float(meta[PREDICTED_RELMSE_KEY]) == pytest.approx(2e-3 * (32 / 64) ** 0.5, rel=1e-4)
    assert json.loads(meta["gradsep.plan_trace"])["cached"] == entry.path.name
    assert "earlier frame" in summary


@pytest.mark.render
@pytest.mark.slow
def test_the_first_frame_judges_and_the_next_reads(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv(CACHE_ENV, raising=False)
    cache = tmp_path / "plans"
    cache.mkdir()
    args = ["render", CBOX, *SMALL, "--spp", "64", "--gradients", "auto", "--plan-cache", str(cache)]
    assert main([*args, "--seed", "1", "-o", str(tmp_path / "a.exr")]) == 0
    assert "plan cache: wrote plan-" in capsys.readouterr().out
    (written,) = cache.iterdir()
    first = read_frame(tmp_path / "a.exr").metadata
    assert first[PLAN_CACHE_KEY] == f"wrote {written.name}" and float(first["gradsep.pilot_seconds"]) > 0
    assert json.loads(written.read_text())[FRAME_ESTIMATE]["spp"] == 64  # its own halves' estimate
    monkeypatch.setenv(CACHE_ENV, str(cache))  # a farm's setting does the same as the flag
    assert main([*args[:-2], "--seed", "2", "-o", str(tmp_path / "b.exr")]) == 0
    second = read_frame(tmp_path / "b.exr").metadata
    assert second[PLAN_CACHE_KEY] == f"read {written.name}" and second["gradsep.pilot_seconds"] == "0.000"
    assert second[PLAN_KEY] == first[PLAN_KEY] and second["gradsep.plan_candidates"] == first["gradsep.plan_candidates"]
    assert list(cache.iterdir()) == [written]
    # another budget is another decision
    assert main([*args, "--seed", "3", "--spp", "65", "-o", str(tmp_path / "c.exr")]) == 0
    assert len(list(cache.iterdir())) == 2
