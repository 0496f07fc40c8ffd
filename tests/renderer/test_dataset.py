"""`gradsep dataset`: manifest content, resume, shards merging, locking, validation, manifest hash."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gradsep.renderer import dataset as ds
from gradsep.renderer.dataset import DatasetError, JobOptions, load_manifest, make_job, manifest_hash, run_dataset

SIZE = "32x32"


def job(shard: str = "0/1", count: int = 3, spp: int = 2, size: str = SIZE, first_seed: int = 1000,
        max_depth: int | None = None, pairs: bool = False) -> ds.Job:
    return make_job(JobOptions(count, spp, size, shard, first_seed, max_depth, pairs))


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real 3-frame dataset (32x32, 2 spp) rendered with the G-PT renderer, once per module."""
    root = tmp_path_factory.mktemp("dataset") / "real"
    run_dataset(root, job(), progress=False)
    return root


@pytest.fixture
def counting_renderer(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Replace the G-PT render with a cheap synthetic frame and record which seeds were rendered."""
    from gradsep.model.frame import Features, Frame, Layer

    calls: list[int] = []

    def fake(spec: str, *, spp: int, seed: int, options: Any) -> Frame:
        width, height, max_depth = options.width, options.height, options.max_depth
        scene_seed = int(spec.rsplit(":", 1)[1])  # procedural:SEED or procedural:FAMILY:SEED
        calls.append(scene_seed)
        rng = np.random.default_rng(scene_seed)
        zero = np.zeros((height, width, 3), np.float32)
        base = rng.random((height, width, 3), dtype=np.float32)
        layers = {"direct": Layer(base, zero, zero)}
        if max_depth is None or max_depth > 2:
            layers["indirect"] = Layer(base / 2, zero, zero)
        feats = Features(base.clip(0, 1), np.dstack([zero[..., :2], zero[..., :1] + 1]), zero[..., 0])
        return Frame(layers, feats, {"gradsep.render_seconds": "0.010", "gradsep.spp": str(spp)})


    monkeypatch.setattr("gradsep.renderer.render.render_frame", fake)
    return calls


# -- a real dataset ----------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.render
def test_manifest_content_of_a_real_dataset(rendered: Path) -> None:
    from gradsep.model.exr_read import read_frame

    data = json.loads((rendered / "manifest.json").read_text())
    assert data["version"] == 1 and data["spp"] == 2 and data["size"] == [32, 32]
    assert data["count"] == 3 and data["complete"] is True and data["missing"] == 0
    assert [f["seed"] for f in data["frames"]] == [1000, 1001, 1002]
    for item in data["frames"]:
        assert item["file"] == f"frames/proc_{item['seed']:06d}.exr"
        assert item["spp"] == 2 and item["shard"] == "0/1" and item["render_seconds"] > 0
        assert item["layers"] == ["direct", "indirect"]
        frame = read_frame(rendered / item["file"])
        assert (frame.width, frame.height) == (32, 32) and list(frame.layers) == ["direct", "indirect"]
        assert frame.features is not None
        assert frame.metadata["gradsep.scene"] == f"procedural:{item['seed']}"
    manifest = load_manifest(rendered)
    assert data["hash"] == manifest_hash(manifest) == manifest_hash(rendered) == manifest.hash
    assert [p.name for p in manifest.paths()] == ["proc_001000.exr", "proc_001001.exr", "proc_001002.exr"]
    assert not list(rendered.rglob("*.tmp")), "an atomic write left a temporary file"


@pytest.mark.render
def test_resume_skips_finished_frames_and_redoes_lost_ones(rendered: Path, tmp_path: Path,
                                                          counting_renderer: list[int]) -> None:
    root = tmp_path / "copy"
    shutil.copytree(rendered, root)
    before = {p.name: p.read_bytes() for p in (root / "frames").iterdir()}
    run_dataset(root, job(), progress=False)
    assert counting_renderer == [], "a finished frame was rendered again"
    assert {p.name: p.read_bytes() for p in (root / "frames").iterdir()} == before

    (root / "frames" / "proc_001001.exr").unlink()  # lost file: rendered again
    run_dataset(root, job(), progress=False)
    assert counting_renderer == [1001]
    assert load_manifest(root).to_json()["complete"]


@pytest.mark.render
def test_pairs_are_two_independent_realizations_of_one_frame(tmp_path: Path) -> None:
    from gradsep.model.exr_read import read_frame

    manifest = run_dataset(tmp_path, job(count=1, pairs=True), progress=False)
    rec = manifest.frames[0]
    assert manifest.pairs and rec.target == "frames/proc_001000.b.exr"
    assert rec.target_sampler_seed != rec.sampler_seed and rec.target_sha256 and rec.target_bytes > 0
    a, b = read_frame(tmp_path / rec.file), read_frame(tmp_path / rec.target)
    assert a.metadata["gradsep.scene"] == b.metadata["gradsep.scene"] == "procedural:1000"
    fa, fb = a.features, b.features
    assert fa is not None and fb is not None
    # features are averages over each pixel's jittered samples: equal up to the pixels an edge crosses
    assert np.mean(np.abs(fa.depth - fb.depth)) < 0.1 * np.mean(fa.depth), "the realizations show other scenes"
    for name in a.layers:  # same scene and settings, independent noise: equal in mean, different per pixel
        x, y = a.layers[name].base, b.layers[name].base
        assert not np.array_equal(x, y)
        assert abs(float(x.mean()) - float(y.mean())) < 0.5 * max(float(x.mean()), float(y.mean())) + 1e-6


# -- resume and records (synthetic frames) -------------------------------------------------------------------

def test_a_pair_without_its_target_is_rendered_again(tmp_path: Path, counting_renderer: list[int]) -> None:
    run_dataset(tmp_path, job(count=2, pairs=True), progress=False)
    assert counting_renderer == [1000, 1000, 1001, 1001]  # each frame twice: the frame and its target
    h = load_manifest(tmp_path).hash
    (tmp_path / "frames" / "proc_001001.b.exr").unlink()
    with pytest.raises(DatasetError, match=r"proc_001001\.b\.exr listed in the manifest is missing"):
        load_manifest(tmp_path)
    counting_renderer.clear()
    run_dataset(tmp_path, job(count=2, pairs=True), progress=False)
    assert counting_renderer == [1001, 1001]
    m = load_manifest(tmp_path)
    assert m.to_json()["complete"] and m.to_json()["pairs"] is True
    m.frames[0].target_sha256 = "0" * 64
    assert manifest_hash(m) != h, "the targets' content is part of the dataset's identity"


def test_pairs_cannot_be_mixed_with_single_frames(tmp_path: Path, counting_renderer: list[int]) -> None:
    run_dataset(tmp_path, job(count=1), progress=False)
    with pytest.raises(DatasetError, match="pairs"):
        run_dataset(tmp_path, job(count=1, pairs=True), progress=False)
    assert load_manifest(tmp_path).pairs is False


def test_exr_without_a_record_is_not_finished(tmp_path: Path, counting_renderer: list[int]) -> None:
    """Killed between rename and record: the EXR exists but no part lists it, so it is rendered again."""
    run_dataset(tmp_path, job(), progress=False)
    part = tmp_path / "manifest.d" / "shard-0-of-1.json"
    data = json.loads(part.read_text())
    data["frames"] = [f for f in data["frames"] if f["seed"] != 1002]
    part.write_text(json.dumps(data))
    counting_renderer.clear()
    run_dataset(tmp_path, job(), progress=False)
    assert counting_renderer == [1002]


def test_truncated_frame_is_rendered_again_and_refused_by_load_manifest(tmp_path: Path,
                                                                       counting_renderer: list[int]) -> None:
    run_dataset(tmp_path, job(), progress=False)
    frame = tmp_path / "frames" / "proc_001000.exr"
    frame.write_bytes(frame.read_bytes()[:100])
    with pytest.raises(DatasetError, match="proc_001000.exr has 100 bytes"):
        load_manifest(tmp_path)
    counting_renderer.clear()
    run_dataset(tmp_path, job(), progress=False)
    assert counting_renderer == [1000]
    load_manifest(tmp_path)


def test_interrupted_run_keeps_finished_frames(tmp_path: Path, counting_renderer: list[int],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import gradsep.renderer.render

    fake = gradsep.renderer.render.render_frame

    def dies_on_third(spec: str, **kw: object) -> object:
        if spec.endswith(":1002"):
            raise KeyboardInterrupt
        return fake(spec, **kw)

    monkeypatch.setattr("gradsep.renderer.render.render_frame", dies_on_third)
    with pytest.raises(KeyboardInterrupt):
        run_dataset(tmp_path, job(count=4), progress=False)
    data = json.loads((tmp_path / "manifest.json").read_text())  # merged on the way out
    assert [f["seed"] for f in data["frames"]] == [1000, 1001] and data["missing"] == 2
    monkeypatch.setattr("gradsep.renderer.render.render_frame", fake)
    counting_renderer.clear()
    run_dataset(tmp_path, job(count=4), progress=False)
    assert counting_renderer == [1002, 1003]


# -- shards ------------------------------------------------------------------------------------------------

def test_two_shards_merge_into_the_full_set(tmp_path: Path, counting_renderer: list[int]) -> None:
    first = run_dataset(tmp_path, job("0/2", count=5), progress=False)
    assert counting_renderer == [1000, 1002, 1004]
    assert [f.seed for f in first.frames] == [1000, 1002, 1004]
    assert json.loads((tmp_path / "manifest.json").read_text())["complete"] is False
    run_dataset(tmp_path, job("1/2", count=5), progress=False)
    assert counting_renderer == [1000, 1002, 1004, 1001, 1003]
    data = json.loads((tmp_path / "manifest.json").read_text())
    assert data["complete"] is True and [f["seed"] for f in data["frames"]] == list(range(1000, 1005))
    assert {f["seed"]: f["shard"] for f in data["frames"]} == {1000: "0/2", 1001: "1/2", 1002: "0/2",
                                                               1003: "1/2", 1004: "0/2"}
    assert sorted(p.name for p in (tmp_path / "manifest.d").glob("*.json")) == ["shard-0-of-2.json",
                                                                               "shard-1-of-2.json"]
    # A later single-shard run finds everything done, whoever rendered it.
    counting_renderer.clear()
    run_dataset(tmp_path, job("0/1", count=5), progress=False)
    assert counting_renderer == []


def test_concurrent_shards_on_one_folder(tmp_path: Path, counting_renderer: list[int],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """Four shards at once (threads: flock treats each open() as its own lock owner) leave a complete set."""
    import threading
    import time

    import gradsep.renderer.render

    fake = gradsep.renderer.render.render_frame

    def slow(spec: str, **kw: object) -> object:
        time.sleep(0.01)  # interleave the shards' renders, part writes and merges
        return fake(spec, **kw)

    monkeypatch.setattr("gradsep.renderer.render.render_frame", slow)
    monkeypatch.setattr(ds, "MERGE_INTERVAL_S", 0.0)  # merge after every frame: maximal contention
    errors: list[BaseException] = []

    def shard(i: int) -> None:
        try:
            run_dataset(tmp_path, job(f"{i}/4", count=12), progress=False)
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=shard, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert sorted(counting_renderer) == list(range(1000, 1012))  # each frame rendered exactly once
    data = json.loads((tmp_path / "manifest.json").read_text())
    assert data["complete"] is True and [f["seed"] for f in data["frames"]] == list(range(1000, 1012))
    assert data["hash"] == load_manifest(tmp_path).hash


def test_a_running_shard_cannot_be_started_twice(tmp_path: Path, counting_renderer: list[int]) -> None:
    (tmp_path / "manifest.d").mkdir(parents=True)
    fd = os.open(tmp_path / "manifest.d" / "shard-1-of-2.lock", os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # another process would hold this while rendering shard 1/2
        with pytest.raises(DatasetError, match="already being rendered"):
            run_dataset(tmp_path, job("1/2"), progress=False)
        run_dataset(tmp_path, job("0/2"), progress=False)  # other shards are not blocked
    finally:
        os.close(fd)
    assert counting_renderer == [1000, 1002]


def test_settings_cannot_be_mixed_in_one_folder(tmp_path: Path, counting_renderer: list[int]) -> None:
    run_dataset(tmp_path, job(count=1), progress=False)
    with pytest.raises(DatasetError, match="spp 2 \\(this run: 4\\)"):
        run_dataset(tmp_path, job(count=1, spp=4), progress=False)
    with pytest.raises(DatasetError, match="size"):
        run_dataset(tmp_path, job(count=1, size="16x16"), progress=False)
    run_dataset(tmp_path, job(count=2), progress=False)  # a larger count extends the same dataset
    assert counting_renderer == [1000, 1001]
    run_dataset(tmp_path, job(count=1), progress=False)  # a shorter rerun does not shrink it
    assert load_manifest(tmp_path).count == 2 and counting_renderer == [1000, 1001]


def test_the_studio_family_renders_its_scenes_and_is_recorded(tmp_path: Path, counting_renderer: list[int],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    import gradsep.renderer.render

    specs: list[str] = []
    fake = gradsep.renderer.render.render_frame
    monkeypatch.setattr("gradsep.renderer.render.render_frame",
                        lambda spec, **kw: (specs.append(spec), fake(spec, **kw))[1])
    studio_job = make_job(JobOptions(2, 2, "8x8", "0/1", 1000, None, family="studio"))
    studio = run_dataset(tmp_path / "s", studio_job, progress=False)
    assert specs == ["procedural:studio:1000", "procedural:studio:1001"]
    assert studio.family == "studio" and load_manifest(tmp_path / "s").family == "studio"
    rooms = run_dataset(tmp_path / "r", make_job(JobOptions(2, 2, "8x8", "0/1", 1000, None)), progress=False)
    assert specs[2:] == ["procedural:1000", "procedural:1001"] and rooms.family == "mixed"
    assert "family" not in json.loads((tmp_path / "r" / "manifest.json").read_text())  # room folders as before
    assert manifest_hash(studio) != manifest_hash(rooms)  # the same pixels (the fake), another family
    with pytest.raises(DatasetError, match="family 'studio' \\(this run: None\\)"):  # one family per folder
        run_dataset(tmp_path / "s", make_job(JobOptions(2, 2, "8x8", "0/1", 1000, None)), progress=False)
    with pytest.raises(DatasetError, match="--family"):
        make_job(JobOptions(2, 2, "8x8", "0/1", 1000, None, family="attic"))


def test_max_depth_two_records_direct_only(tmp_path: Path, counting_renderer: list[int]) -> None:
    manifest = run_dataset(tmp_path, job(count=1, max_depth=2), progress=False)
    assert manifest.frames[0].layers == ["direct"] and manifest.max_depth == 2


# -- hash and loading --------------------------------------------------------------------------------------

def test_manifest_hash_follows_content_not_timing_or_layout(tmp_path: Path, counting_renderer: list[int]) -> None:
    run_dataset(tmp_path, job(count=2), progress=False)
    m = load_manifest(tmp_path)
    h = manifest_hash(m)
    m.frames[0].render_seconds = 99.0
    m.frames[0].shard = "3/7"
    m.frames[0].finished_at = "yesterday"
    assert manifest_hash(m) == h
    m.frames[0].sha256 = "0" * 64
    assert manifest_hash(m) != h


def test_load_manifest_from_parts_and_errors(tmp_path: Path, counting_renderer: list[int]) -> None:
    with pytest.raises(DatasetError, match="not a dataset folder"):
        load_manifest(tmp_path)
    run_dataset(tmp_path, job(count=2), progress=False)
    merged = load_manifest(tmp_path)
    (tmp_path / "manifest.json").unlink()  # a copy without the merged file still loads from its parts
    assert load_manifest(tmp_path).hash == merged.hash
    (tmp_path / "manifest.json").write_text(json.dumps({"version": 99}))
    with pytest.raises(DatasetError, match="version 99"):
        load_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(DatasetError, match="cannot read"):
        load_manifest(tmp_path)


# -- command-line validation ------------------------------------------------------------------------------

@pytest.mark.parametrize(("text", "expected"), [("32x32", (32, 32)), ("640X480", (640, 480)), (" 8x4 ", (8, 4))])
def test_parse_size(text: str, expected: tuple[int, int]) -> None:
    assert ds.parse_size(text) == expected


@pytest.mark.parametrize(("text", "expected"), [("0/1", (0, 1)), ("3/4", (3, 4))])
def test_parse_shard(text: str, expected: tuple[int, int]) -> None:
    assert ds.parse_shard(text) == expected


@pytest.mark.parametrize(("argv", "message"), [
    (["--shard", "2/2"], "0 <= i < n"),
    (["--shard", "1/0"], "n >= 1"),
    (["--shard", "one/two"], "--shard must be i/n"),
    (["--shard", "-1/2"], "--shard must be i/n"),
    (["--size", "32"], "WIDTHxHEIGHT"),
    (["--size", "0x32"], "between 1 and"),
    (["--size", "32x99999"], "between 1 and"),
    (["--count", "0"], "--count"),
    (["--spp", "0"], "--spp"),
    (["--first-seed", "-5"], "--first-seed"),
    (["--max-depth", "0"], "--max-depth"),
])
def test_command_rejects_bad_options(argv: list[str], message: str, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    options = {"--count": "2", "--spp": "2", "--size": "8x8"}
    options.update(zip(argv[::2], argv[1::2], strict=True))
    args = [f"{flag}={value}" for flag, value in options.items()]  # "=" lets "-1/2" be a value
    assert main(["dataset", *args, "-o", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith("gradsep dataset: error:")
    assert not (tmp_path / "d" / "frames").exists()


def test_command_renders_and_reports(tmp_path: Path, counting_renderer: list[int],
                                     capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    assert main(["dataset", "--count", "3", "--spp", "2", "--size", "8x6", "--first-seed", "50",
                 "--shard", "1/2", "-o", str(tmp_path / "d")]) == 0
    assert counting_renderer == [51]
    out = capsys.readouterr().out
    assert "shard 1/2 has 1/1 frames; dataset 1/3" in out
    assert (tmp_path / "d" / "frames" / "proc_000051.exr").is_file()
    (tmp_path / "f").write_text("")
    assert main(["dataset", "--count", "1", "--spp", "1", "-o", str(tmp_path / "f")]) == 2
    assert "not a folder" in capsys.readouterr().err


# -- a failed start leaves nothing behind ---------------------------------------------------------------------

def _fails_at(monkeypatch: pytest.MonkeyPatch, seeds: set[int]) -> None:
    """The (counting) renderer raises for these scene seeds; an empty set restores it."""
    import gradsep.renderer.render

    fake = getattr(gradsep.renderer.render.render_frame, "unwrapped", gradsep.renderer.render.render_frame)

    def failing(spec: str, **kw: object) -> object:
        if int(spec.rsplit(":", 1)[1]) in seeds:
            raise RuntimeError("the renderer failed")
        return fake(spec, **kw)

    failing.unwrapped = fake  # type: ignore[attr-defined]
    monkeypatch.setattr("gradsep.renderer.render.render_frame", failing)


def _tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def test_a_run_that_fails_before_its_first_frame_leaves_no_folder(tmp_path: Path, counting_renderer: list[int],
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    root = tmp_path / "data"
    _fails_at(monkeypatch, {1000})
    with pytest.raises(RuntimeError, match="renderer failed"):
        run_dataset(root, job(), progress=False)
    assert not root.exists()
    _fails_at(monkeypatch, set())
    run_dataset(root, job(spp=4), progress=False)  # the corrected retry, other settings: not refused
    assert load_manifest(root).spp == 4


def test_a_failed_start_in_an_existing_folder_keeps_what_was_there(tmp_path: Path, counting_renderer: list[int],
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "README").write_text("the user's own file")
    _fails_at(monkeypatch, {1000})
    with pytest.raises(RuntimeError):
        run_dataset(tmp_path, job(), progress=False)
    assert _tree(tmp_path) == ["README"]


def test_a_failed_start_beside_another_shard_removes_only_its_own_part(tmp_path: Path, counting_renderer: list[int],
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    run_dataset(tmp_path, job("0/2", count=4), progress=False)
    before = json.loads((tmp_path / "manifest.json").read_text())
    _fails_at(monkeypatch, {1001})
    with pytest.raises(RuntimeError):
        run_dataset(tmp_path, job("1/2", count=4), progress=False)
    assert sorted(p.name for p in (tmp_path / "manifest.d").glob("*.json")) == ["shard-0-of-2.json"]
    after = json.loads((tmp_path / "manifest.json").read_text())
    assert after["frames"] == before["frames"] and after["hash"] == before["hash"]


def test_a_failure_after_the_first_frame_keeps_the_run(tmp_path: Path, counting_renderer: list[int],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    _fails_at(monkeypatch, {1001})
    with pytest.raises(RuntimeError):
        run_dataset(tmp_path / "data", job(), progress=False)
    assert [f.seed for f in load_manifest(tmp_path / "data", check_files=False).frames] == [1000]


# -- frames rendered to a time budget (--seconds) --------------------------------------------------------------

@pytest.fixture
def planned_renderer(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, float, str]]:
    """Replace the planned render (and the scene load) with a cheap frame whose spp follows the scene seed; record
    (scene seed, the deadline's budget, the plan asked for) per call."""
    from gradsep.model.frame import Features, Frame, Layer
    from gradsep.renderer import planned_frame, scene

    calls: list[tuple[int, float, str]] = []
    monkeypatch.setattr(scene, "load_scene", lambda spec, **kw: (spec, kw))

    def fake(loaded: tuple[str, dict[str, int]], budget: Any, request: Any) -> tuple[Frame, str]:
        spec, size = loaded
        scene_seed = int(spec.rsplit(":", 1)[1])
        deadline = budget.deadline
        calls.append((scene_seed, deadline.seconds, request.gradients))
        assert budget.spp is None and deadline.left() > 0
        h, w = size["height"], size["width"]
        ones = np.ones((h, w, 3), np.float32)
        feats = Features(ones / 2, np.dstack([ones[..., :2] * 0, ones[..., :1]]), ones[..., 0])
        frame = Frame({"direct": Layer(ones, ones * 0, ones * 0)}, feats,
                      {"gradsep.render_seconds": "0.5", "gradsep.spp": str(scene_seed % 7 + 3),
                       "gradsep.budget_seconds": f"{deadline.seconds:g}"})
        return frame, "plan all"

    monkeypatch.setattr(planned_frame, "render_planned_frame", fake)
    return calls


def test_seconds_renders_each_frame_to_its_budget_and_records_its_spp(tmp_path: Path,
                                                                      planned_renderer: list[tuple[int, float, str]],
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    assert main(["dataset", "--count", "3", "--seconds", "2.5", "--size", "8x6", "--pairs",
                 "-o", str(tmp_path / "d")]) == 0
    # every frame and every pair's target: its own budget, the plan training reads
    assert planned_renderer == [(s, 2.5, ds.DATASET_PLAN) for s in (1000, 1000, 1001, 1001, 1002, 1002)]
    spps = [s % 7 + 3 for s in (1000, 1001, 1002)]
    assert f"2.5 s per frame ({min(spps)}-{max(spps)} spp)" in capsys.readouterr().out
    data = json.loads((tmp_path / "d" / "manifest.json").read_text())
    assert data["seconds"] == 2.5 and data["spp"] is None
    assert [f["spp"] for f in data["frames"]] == spps
    manifest = load_manifest(tmp_path / "d")
    assert manifest.seconds == 2.5 and manifest.spp is None and manifest.hash == data["hash"]
    # a budgeted dataset is another dataset: no --spp run may add to it, and its hash names the budget
    with pytest.raises(DatasetError, match="seconds 2.5 \\(this run: None\\)"):
        run_dataset(tmp_path / "d", make_job(JobOptions(3, 4, "8x6", "0/1", 1000, None, pairs=True)), progress=False)
    manifest.seconds = 3.0
    assert manifest_hash(manifest) != data["hash"]


@pytest.mark.parametrize(("argv", "message"), [
    ([], "exactly one of --spp"),
    (["--spp", "2", "--seconds", "5"], "exactly one of --spp"),
    (["--seconds", "0"], "--seconds must be a finite number > 0"),
    (["--seconds", "-1"], "--seconds must be a finite number > 0"),
    (["--seconds", "nan"], "--seconds must be a finite number > 0"),
    (["--seconds", "inf"], "--seconds must be a finite number > 0"),
    (["--seconds", "soon"], "--seconds must be a number"),
])
def test_command_rejects_a_bad_budget(argv: list[str], message: str, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    assert main(["dataset", "--count", "2", "--size", "8x8", *argv, "-o", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith("gradsep dataset: error:") and err.count("\n") == 1
    assert not (tmp_path / "d").exists()


@pytest.mark.render
def test_a_budget_below_the_first_frames_start_up_leaves_nothing(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    assert main(["dataset", "--count", "2", "--seconds", "0.02", "--size", "16x12", "-o", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "below this machine's start-up cost" in err and err.count("\n") == 1
    assert not (tmp_path / "d").exists()


@pytest.mark.render
@pytest.mark.slow
def test_a_real_frame_rendered_to_its_budget(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from gradsep.model.exr_read import read_frame
    from gradsep.renderer import reconstruction_cost

    # the reconstruction's start-up as if paid (as after another test): the frame's check then fits 8 s
    monkeypatch.setattr(reconstruction_cost, "reconstruct_startup", lambda: 0.0)
    # 8 s: the kernel's compile and a second pass fit on a loaded 2-core machine (test_commands.py's budgeted frame)
    timed = make_job(JobOptions(1, None, "16x12", "0/1", 1000, None, seconds="8"))
    manifest = run_dataset(tmp_path / "d", timed, progress=False)
    (record,) = manifest.frames
    frame = read_frame(tmp_path / "d" / record.file)
    meta = frame.metadata
    assert meta["gradsep.budget_seconds"] == "8" and meta["gradsep.plan"] == ds.DATASET_PLAN
    assert record.spp == int(meta["gradsep.spp"]) >= 2 and int(meta["gradsep.passes"]) >= 2
    # what training reads: every layer with its gradients, and the features
    assert frame.features is not None and all(layer.has_gradients for layer in frame.layers.values())
    assert manifest.seconds == 8.0 and manifest.spp is None
