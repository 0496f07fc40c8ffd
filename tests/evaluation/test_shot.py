"""`gradsep evaluate --shot`: the shot scores on constructed shots whose answers are known (evaluation/shot_metrics.py),
the command's bad input (one line, exit 2, nothing written), and one tiny real shot end to end through the CLI."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from gradsep.cli import main
from gradsep.evaluation.shot_metrics import (
    ShotTruth,
    after_change_ratio,
    changed_frames,
    flicker_pairs,
    geomean,
    ratio,
    score_pipeline,
)
from gradsep.model.frame import Motion
from gradsep.model.metrics import RELMSE_EPSILON

REPO = Path(__file__).resolve().parents[2]
MOVING = REPO / "tests" / "data" / "shot" / "moving.xml"
H, W = 24, 32


class _Frame:
    """What the scores read of a frame: its motion vectors."""

    def __init__(self, motion: Motion | None) -> None:
        self.motion = motion


def _motion(shift: int, first: bool, last: bool, invalid: np.ndarray | None = None) -> Motion:
    """Every pixel's content moved ``shift`` pixels right since the previous frame (so the backward vector is
    -shift), and will move as much by the next; ``invalid`` marks pixels without a correspondence."""
    valid = np.ones((H, W), bool) if invalid is None else ~invalid
    back = np.zeros((H, W, 2), np.float32)
    back[..., 0] = -shift
    if shift:
        valid = valid.copy()
        valid[:, :shift] = False  # came from off screen
    return Motion(None if first else back, None if last else -back, None if first else valid,
                  None if last else valid)


def _static_truth(frames: int, level: float = 0.5, noise: float = 0.0, seed: int = 0) -> ShotTruth:
    rng = np.random.default_rng(seed)
    truth = np.full((H, W, 3), level, np.float32)
    first = [truth + noise * rng.standard_normal(truth.shape).astype(np.float32) for _ in range(frames)]
    second = [truth + noise * rng.standard_normal(truth.shape).astype(np.float32) for _ in range(frames)]
    motions = [_Frame(_motion(0, t == 0, t == frames - 1)) for t in range(frames)]
    return ShotTruth(first, second, motions)


def test_geomean_and_ratio():
    assert geomean([1.0, 4.0]) == pytest.approx(2.0)
    assert geomean([0.0, 1.0]) > 0  # an unresolvable error counts as tiny, not as -inf
    assert ratio(1.0, 2.0) == 0.5
    assert ratio(1.0, 0.0) is None and ratio(None, 1.0) is None and ratio(1.0, -1.0) is None


def test_relmse_and_flicker_on_a_static_shot_with_known_errors():
    truth = _static_truth(4)
    level = 0.5
    d = 0.1
    steady = [np.full((H, W, 3), level + d, np.float32) for _ in range(4)]  # the same error every frame
    alternating = [np.full((H, W, 3), level + (d if t % 2 else -d), np.float32) for t in range(4)]
    expected = d * d / (level * level + RELMSE_EPSILON)
    s = score_pipeline("steady", steady, truth)
    assert s.errors == pytest.approx([expected] * 4)
    assert s.relmse == pytest.approx(expected)
    assert s.flicker == pytest.approx(0.0, abs=1e-12)  # an error that stays put is not flicker
    a = score_pipeline("alternating", alternating, truth)
    assert a.relmse == pytest.approx(expected)  # the same error per frame ...
    assert a.flicker == pytest.approx(4 * expected)  # ... changing by 2d every frame
    assert a.flickers[0] is None and len(a.flickers) == 4


def test_reference_noise_is_removed_in_expectation():
    truth = _static_truth(3, noise=0.05, seed=1)
    d = 0.1
    images = [np.full((H, W, 3), 0.5 + (d if t % 2 else -d), np.float32) for t in range(3)]
    s = score_pipeline("x", images, truth)
    expected = d * d / (0.25 + RELMSE_EPSILON)
    assert s.relmse == pytest.approx(expected, rel=0.1)  # one reference alone would add 0.05² / 0.26 ≈ 0.1 × it
    assert s.flicker == pytest.approx(4 * expected, rel=0.1)


def test_flicker_follows_the_motion():
    """Content and its error moving one pixel right per frame: no flicker along the motion (the warp is exact for
    whole pixels), while the same images compared pixel by pixel change everywhere."""
    frames = 3
    rng = np.random.default_rng(2)
    base = 0.2 + rng.random((H, W + frames, 3)).astype(np.float32)
    error = 0.05 * rng.standard_normal((H, W + frames, 3)).astype(np.float32)
    truths = [base[:, frames - t:frames - t + W] for t in range(frames)]  # content moves right
    images = [(base + error)[:, frames - t:frames - t + W] for t in range(frames)]
    moving = ShotTruth(truths, truths, [_Frame(_motion(1, t == 0, t == frames - 1)) for t in range(frames)])
    assert score_pipeline("x", images, moving).flicker == pytest.approx(0.0, abs=1e-10)
    still = ShotTruth(truths, truths, [_Frame(_motion(0, t == 0, t == frames - 1)) for t in range(frames)])
    assert score_pipeline("x", images, still).flicker > 1e-3


def test_disoccluded_error_is_pooled_over_the_pixels_without_a_correspondence():
    frames = 3
    hole = np.zeros((H, W), bool)
    hole[4:12, 4:12] = True  # 64 pixels per middle frame
    truth = _static_truth(frames)
    truth.frames = [_Frame(_motion(0, t == 0, t == frames - 1, hole)) for t in range(frames)]
    images = [np.full((H, W, 3), 0.5, np.float32) for _ in range(frames)]
    images[1][hole] += 0.2  # error only where there is no correspondence
    s = score_pipeline("x", images, truth)
    assert s.disoccluded == pytest.approx(0.04 / 0.26)
    clean = score_pipeline("clean", [np.full((H, W, 3), 0.5, np.float32)] * frames, truth)
    assert clean.disoccluded == pytest.approx(0.0)
    small = np.zeros((H, W), bool)
    small[0, 0] = True  # too few pixels for an estimate
    truth.frames = [_Frame(_motion(0, t == 0, t == frames - 1, small)) for t in range(frames)]
    assert score_pipeline("x", images, truth).disoccluded is None


def test_a_light_switched_off_is_found_and_noise_is_not():
    frames = 4
    truth = _static_truth(frames, noise=0.1, seed=3)
    assert changed_frames(truth) == []  # noisy references of a still truth: no change
    for t in (2, 3):  # the lamp goes off before frame 2: the room keeps 40 % of its light
        truth.first[t] = 0.4 * truth.first[t]
        truth.second[t] = 0.4 * truth.second[t]
    assert changed_frames(truth) == [2]
    per = score_pipeline("per", [np.full((H, W, 3), 0.5 if t < 2 else 0.25, np.float32) for t in range(4)], truth)
    worse = score_pipeline("tem", [np.full((H, W, 3), 0.5 if t < 3 else 0.25, np.float32) for t in range(4)], truth)
    # after the switch (frames 2 and 3) the ghost of the lamp in frame 2 makes the temporal row worse there
    assert after_change_ratio(worse, per, [2]) > 1.5
    assert after_change_ratio(per, per, [2]) == pytest.approx(1.0)


def test_flicker_pairs_without_vectors_are_left_out():
    truth = _static_truth(3)
    truth.frames = [_Frame(None)] * 3
    images = [np.full((H, W, 3), 0.6, np.float32)] * 3
    assert flicker_pairs(images, truth) == [None, None, None]
    assert score_pipeline("x", images, truth).flicker is None


# ------------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize("argv, message", [
    (["--frames", "1-3"], "--frames applies to a shot"),
    (["--shot", str(MOVING)], "--shot needs --frames"),
    (["--shot", str(MOVING), "--frames", "3-1", "--spp", "2"], "reversed"),
    (["--shot", str(MOVING), "--frames", "1-x", "--spp", "2"], "--frames"),
    (["--shot", str(MOVING), "--frames", "1-3", "--spp", "2", "--animate", "nope=0:1"], "nope"),
    (["--shot", str(MOVING), "--frames", "1-3"], "exactly one of --seconds"),
    (["--shot", str(MOVING), "--frames", "1-3", "--spp", "2", "--seconds", "4"], "exactly one of --seconds"),
    (["--shot", str(MOVING), "--frames", "1-3", "--spp", "2,4"], "one sample count"),
    (["--shot", str(MOVING), "--frames", "1-3", "--spp", "2", "--window", "4"], "--window"),
    (["--shot", str(MOVING), "--frames", "1-3", "--spp", "2", "--methods", "oidn"], "--methods applies"),
    (["--shot", str(MOVING), "--frames", "1-1", "--spp", "2"], "at least two frames"),
    (["--shot", "missing.%04d.xml", "--frames", "1-3", "--spp", "2"], "scene file not found"),
    (["--shot", str(MOVING), "--frames", "1-3", "--seconds", "-1"], "--seconds"),
    (["--shot", str(MOVING), "--frames", "1-3", "--spp", "2", "--ref-spp", "8", "--ref-spp-cap", "4"],
     "--ref-spp-cap 4 is below"),
])
def test_bad_shot_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys, argv, message):
    out, cache = tmp_path / "report", tmp_path / "cache"
    assert main(["evaluate", *argv, "--cache", str(cache), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not out.exists() and not cache.exists()


# --------------------------------------------------------------------------------------------- end to end


@pytest.mark.slow
@pytest.mark.render
def test_a_tiny_shot_end_to_end(tmp_path, capsys):
    out, cache = tmp_path / "report", tmp_path / "cache"
    argv = ["evaluate", "--shot", str(MOVING), "--frames", "1-3", "--animate", "pos=-0.3,0.5,0:0.3,0.5,0",
            "--size", "32x24", "--spp", "2", "--ref-spp", "8", "--ref-spp-cap", "16", "--window", "3", "--cache",
            str(cache), "-o", str(out)]
    assert main(argv) == 0
    assert "4 pipelines" in capsys.readouterr().out
    for name in ("report.md", "shot.csv", "shot.json", "crops.png", "plots/error.png", "plots/flicker.png"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "shot.json").read_text())
    rows = {r["pipeline"]: r for r in summary["summary"]}
    assert set(rows) == {"primal", "primal+temporal", "plan", "plan+temporal"}
    assert rows["primal"]["flicker_vs_primal_oidn"] == pytest.approx(1.0)
    best = min(rows[n]["relmse"] for n in ("primal", "plan"))
    for row in rows.values():
        assert math.isfinite(row["relmse"]) and row["relmse"] > 0
        assert row["relmse_vs_best_per_frame"] == pytest.approx(row["relmse"] / best)
        assert math.isfinite(row["seconds_per_frame"])
    assert summary["frames"] == [1, 2, 3]
    assert summary["ref_spp"] in (8, 16)  # raised in passes of 8 while the floor is too high, up to the cap
    with open(out / "shot.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 4 * 3
    from PIL import Image

    with Image.open(out / "crops.png") as animation:
        assert getattr(animation, "n_frames", 1) == 3  # one image per frame of the shot
    report = (out / "report.md").read_text()
    assert "× primal + OIDN" in report and "primal + " in report
    # a rerun takes every frame and reference from the cache and gives the same errors
    frames_before = sorted(p.stat().st_mtime_ns for p in cache.rglob("*.exr"))
    assert main(argv) == 0
    assert sorted(p.stat().st_mtime_ns for p in cache.rglob("*.exr")) == frames_before
    again = {r["pipeline"]: r for r in json.loads((out / "shot.json").read_text())["summary"]}
    assert again["plan"]["relmse"] == pytest.approx(rows["plan"]["relmse"])


def test_the_report_of_a_constructed_shot(tmp_path):
    """The report's ratios, files and animation from a shot built here (no rendering): the temporal row halves the
    error change of its per-frame row, the other plan doubles the error."""
    from PIL import Image

    from gradsep.evaluation.shot_report import summary_rows, write_shot_report
    from gradsep.evaluation.shots import ShotConfig, ShotResult

    frames = 4
    truth = _static_truth(frames)
    d = 0.1
    images = {"primal": [np.full((H, W, 3), 0.5 + (d if t % 2 else -d), np.float32) for t in range(frames)],
              "primal+temporal": [np.full((H, W, 3), 0.5 + (d if t % 2 else -d) / 2, np.float32)
                                  for t in range(frames)],
              "plan": [np.full((H, W, 3), 0.5 + 2 * d, np.float32) for t in range(frames)]}
    rows = []
    for name, outs in images.items():
        row = score_pipeline(name, outs, truth)
        row.seconds, row.method = [1.0] * frames, "oidn"
        rows.append(row)
    config = ShotConfig(scene="procedural:1", frames="1-4", output=tmp_path / "r", cache_dir=tmp_path / "c",
                        models_dir=tmp_path, spp=1, window=3)
    result = ShotResult(config, [1001, 1002, 1003, 1004], rows, images, truth, [1e-4] * frames, [], "primal",
                        {"primal": "primal", "primal+temporal": "primal", "plan": "plan"}, 8,
                        pooled=[[1001, 1002, 1003, 1004]])
    summary = {r["pipeline"]: r for r in summary_rows(result)}
    assert summary["primal"]["best_per_frame"] == "primal"
    assert summary["primal+temporal"]["relmse_vs_best_per_frame"] == pytest.approx(0.25)
    assert summary["primal+temporal"]["flicker_vs_primal_oidn"] == pytest.approx(0.25)
    assert summary["plan"]["relmse_vs_best_per_frame"] == pytest.approx(4.0)
    assert summary["plan"]["flicker_vs_primal_oidn"] == pytest.approx(0.0, abs=1e-9)  # a steady error
    assert summary["plan"]["after_change_vs_per_frame"] is None  # no change in this shot
    paths = write_shot_report(result, "gradsep evaluate --shot procedural:1 ...")
    assert all(p.is_file() for p in paths.values())
    data = json.loads(paths["json"].read_text())
    assert data["frames"] == [1001, 1002, 1003, 1004] and data["ref_spp"] == 8
    assert data["per_frame"]["primal"]["flicker"][0] is None  # no pair ends at the first frame
    with Image.open(paths["crops"]) as animation:
        assert animation.n_frames == frames
    report = paths["report"].read_text()
    assert "| primal + oidn, temporal (3 frames) | " in report
    assert "pooled over the frames of one scene (every parameter equal: 1001-1004)" in report
    assert data["pooled_references"] == [[1001, 1002, 1003, 1004]]


def test_a_procedural_familys_references_are_keyed_by_the_frames_instant_not_its_number(tmp_path: Path) -> None:
    """Frame 5 of an 8-frame and of a 16-frame dolly is another instant (t): its cached references must differ."""
    from gradsep.evaluation.cache import EvalCache
    from gradsep.evaluation.shots import ShotConfig, ShotReferences, check_shot_config

    scenes = []
    for frames in ("1-8", "1-16"):
        config = ShotConfig(scene="procedural:dolly:3", frames=frames, output=tmp_path / frames,
                            cache_dir=tmp_path / "c", models_dir=tmp_path, spp=1, window=3)
        references = ShotReferences(config, check_shot_config(config), EvalCache(tmp_path / "c"), print)
        scenes.append(references.sources[4].key["scene"])
    assert scenes[0] != scenes[1] and all("t=" in s for s in scenes)


@pytest.mark.render
def test_the_references_of_frames_of_one_scene_are_pooled(tmp_path: Path) -> None:
    """A light-off shot of four frames: the lamp is on in frames 1-2 and off in 3-4, nothing else changes, so each
    pair is one scene and shares the mean of its references (twice the samples: about half the floor); a moving
    object's frames are all different scenes and keep their own."""
    from gradsep.evaluation.cache import EvalCache
    from gradsep.evaluation.shots import ShotConfig, ShotReferences, check_shot_config
    from gradsep.model.metrics import reference_floor

    def references(scene: str) -> ShotReferences:
        config = ShotConfig(scene=scene, frames="1-4", output=tmp_path / "r", cache_dir=tmp_path / "c",
                            models_dir=tmp_path, spp=1, size=(12, 8), ref_spp=4)
        return ShotReferences(config, check_shot_config(config), EvalCache(tmp_path / "c"), lambda m: None)

    assert references("procedural:moving:3").same_scene() == []
    lightoff = references("procedural:lightoff:3")
    assert lightoff.same_scene() == [[0, 1], [2, 3]]
    frames = [_FakeFrame(8, 12)] * 4
    truth, floors = lightoff.truth(4, frames)
    own = [source.pair(4) for source in lightoff.sources]
    for group in ([0, 1], [2, 3]):
        for k in group:
            np.testing.assert_allclose(truth.first[k], np.mean([own[j].first["total"] for j in group], axis=0),
                                       rtol=1e-6)
            np.testing.assert_allclose(truth.second[k], np.mean([own[j].second["total"] for j in group], axis=0),
                                       rtol=1e-6)
            assert floors[k] == pytest.approx(reference_floor(truth.first[k], truth.second[k]))
    assert not np.array_equal(truth.first[1], truth.first[2])  # the lamp switched off between them


@pytest.mark.render
def test_a_scenes_content_hash_does_not_see_the_addresses_that_name_unnamed_objects() -> None:
    """procedural:lightoff:71014's room has unnamed nested objects, which Mitsuba names by their address: two loads
    of one frame, and two frames before the switch, hash alike; after the switch, not."""
    from gradsep.evaluation.shots import scene_content
    from gradsep.renderer.scene import load_scene

    def content(t: str) -> str | None:
        return scene_content(load_scene("procedural:lightoff:71014", width=12, height=8, defines={"t": t}))

    first = content("0")
    assert first is not None and first == content("0") == content("0.2") != content("0.6")


class _FakeFrame:
    """What ShotReferences.truth reads of a rendered frame: its size."""

    def __init__(self, h: int, w: int) -> None:
        self.shape = (h, w, 3)

    def combined(self) -> _FakeFrame:
        return self

    @property
    def base(self) -> np.ndarray:
        return np.zeros(self.shape, np.float32)
