"""`gradsep evaluate`: options, the equal-time cost model, crop selection, the report's verdicts, and one tiny real
run (procedural scene, 32×32, 1-2 spp, real Mitsuba/ONNX Runtime/OIDN) with its cache behaviour.

The network methods run real ONNX Runtime sessions on small hand-built ONNX graphs (a 3×3 blur of the
log-encoded base, with the gradsep metadata model/infer.py checks): trained models are not needed to test the
plumbing, and a different graph is a different file, which is what the cache must notice.
"""

from __future__ import annotations

import argparse
import csv
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from gradsep.cli import main
from gradsep.evaluation.baselines import split_features
from gradsep.evaluation.commands import config_from_args, evaluate_command
from gradsep.evaluation.config import (
    QUICK,
    EvalConfig,
    parse_methods,
    parse_size,
    parse_spp,
    resolve_scenes,
    table_spp_for,
)
from gradsep.evaluation.methods import method_by_name
from gradsep.evaluation.plots import select_crop
from gradsep.evaluation.report import CSV_COLUMNS, losses_of_ours
from gradsep.evaluation.report_time import time_misses
from gradsep.evaluation.run import run_evaluation
from gradsep.evaluation.timesearch import CostModel
from gradsep.model.errors import CommandError

SCENE = "procedural:90001"
SPP = (1, 2)
METHODS = ("gpt-primal", "l1", "gradnet", "ablation/separated-attn", "oidn", "oidn-l1", "ours", "path",
           "path-oidn", "path-sep-oidn", "gpt-oidn-l1", "gpt-auto")
EQUAL_TIME_METHODS = {"path", "path-oidn", "path-sep-oidn", "gpt-oidn-l1", "gpt-auto"}


def _runnable(methods) -> tuple[str, ...]:
    """The methods this code base can run (the others are skipped with a stated reason)."""
    from gradsep.evaluation.methods import method_by_name, unavailable

    return tuple(m for m in methods if unavailable(method_by_name(m)) is None)


# --------------------------------------------------------------------------------------------- options


def test_parse_spp_sorts_dedupes_and_rejects_bad_counts():
    assert parse_spp("16, 1,4,4") == (1, 4, 16)
    for bad in ("1,x", "0,2", "-1", "", " , "):
        with pytest.raises(CommandError):
            parse_spp(bad)


def test_parse_size_and_methods():
    assert parse_size("320x240") == (320, 240)
    for bad in ("320", "0x5", "axb"):
        with pytest.raises(CommandError):
            parse_size(bad)
    assert parse_methods("l1,ours") == ("ours", "l1")  # canonical order: the table's (ours is its network)
    assert len(parse_methods("ablation")) == 4
    with pytest.raises(CommandError, match="unknown method 'nope'"):
        parse_methods("l1,nope")


def test_table_spp_prefers_16_else_nearest_in_log2():
    assert table_spp_for((1, 2, 4, 8, 16, 32, 64)) == 16
    assert table_spp_for((1, 4)) == 4
    assert table_spp_for((64, 256)) == 64
    assert table_spp_for((8, 32)) == 32  # equally far: the larger


def _args(**kw) -> argparse.Namespace:
    base = {"scenes": None, "spp": "1,2,4,8,16,32,64", "quick": False, "output": "out"}
    base.update(kw)
    return argparse.Namespace(**base)


def test_quick_replaces_the_default_spp_but_keeps_an_explicit_one(monkeypatch):
    for name in ("GRADSEP_EVAL_SIZE", "GRADSEP_EVAL_REF_SPP", "GRADSEP_EVAL_METHODS", "GRADSEP_EVAL_TABLE_SPP"):
        monkeypatch.delenv(name, raising=False)
    quick = config_from_args(_args(quick=True))
    assert quick.spp == QUICK.spp and (quick.width, quick.height) == (QUICK.width, QUICK.height)
    assert quick.ref_spp == QUICK.ref_spp and quick.reference_cap == QUICK.ref_spp_cap
    assert quick.ref_seconds == QUICK.ref_seconds
    assert config_from_args(_args(quick=True, ref_seconds=0)).ref_seconds is None  # 0: no time limit
    with pytest.raises(CommandError, match="--ref-spp-cap 64 is below --ref-spp 128"):
        config_from_args(_args(quick=True, ref_spp_cap=64))
    assert config_from_args(_args(quick=True, spp="2,8")).spp == (2, 8)
    monkeypatch.setenv("GRADSEP_EVAL_SIZE", "40x30")
    monkeypatch.setenv("GRADSEP_EVAL_REF_SPP", "64")
    config = config_from_args(_args(spp="1,4"))
    assert (config.width, config.height, config.ref_spp) == (40, 30, 64)
    monkeypatch.setenv("GRADSEP_EVAL_TABLE_SPP", "16")
    with pytest.raises(CommandError, match="--table-spp 16 is not one of"):
        config_from_args(_args(spp="1,4"))
    monkeypatch.setenv("GRADSEP_EVAL_TABLE_SPP", "4")
    monkeypatch.setenv("GRADSEP_EVAL_REF_SPP", "0")
    with pytest.raises(CommandError, match="--ref-spp must be >= 1"):
        config_from_args(_args(spp="1,4"))


def test_command_line_flags_win_over_the_environment(monkeypatch):
    """The flags model/commands.py will get (--size, --ref-spp, ...) are read first when the parser has them."""
    monkeypatch.setenv("GRADSEP_EVAL_SIZE", "40x30")
    monkeypatch.setenv("GRADSEP_EVAL_METHODS", "l2")
    config = config_from_args(_args(spp=None, size="64x48", ref_spp=32, seed=0, methods="ours,l1", models="m",
                                    cache="c", max_depth=3, alpha=0.5, table_spp=4))
    assert (config.width, config.height, config.ref_spp, config.seed) == (64, 48, 32, 0)
    assert config.methods == ("ours", "l1") and config.max_depth == 3 and config.alpha == 0.5
    assert config.spp == (1, 2, 4, 8, 16, 32, 64) and config.crop_spp == 4  # --spp None: the preset's list
    assert str(config.models_dir) == "m" and str(config.cache_dir) == "c"
    with pytest.raises(CommandError, match="--alpha must be"):
        config_from_args(_args(alpha=float("nan")))


def test_time_seeds_from_the_flag_or_the_environment_with_their_range(monkeypatch):
    """--time-seeds N (or GRADSEP_EVAL_TIME_SEEDS): 1 by default, refused below 1 and above the cap, and named in
    the reproduce line only when it is not 1 (the committed reports' lines stay as they were)."""
    from gradsep.evaluation.config import MAX_TIME_SEEDS
    from gradsep.evaluation.report import reproduce_command

    assert config_from_args(_args()).time_seeds == 1
    assert "TIME_SEEDS" not in reproduce_command(config_from_args(_args()))
    assert config_from_args(_args(time_seeds=3)).time_seeds == 3
    monkeypatch.setenv("GRADSEP_EVAL_TIME_SEEDS", "4")
    config = config_from_args(_args())
    assert config.time_seeds == 4 and "GRADSEP_EVAL_TIME_SEEDS=4" in reproduce_command(config)
    for bad in (0, -2, MAX_TIME_SEEDS + 1):
        with pytest.raises(CommandError, match="--time-seeds must be"):
            config_from_args(_args(time_seeds=bad))


def test_frame_seeds_from_the_flag_or_the_environment_with_their_range(monkeypatch):
    """--frame-seeds N (or GRADSEP_EVAL_FRAME_SEEDS): 1 by default, refused below 1 and above the cap, and named in
    the reproduce line only when it is not 1."""
    from gradsep.evaluation.config import MAX_FRAME_SEEDS
    from gradsep.evaluation.report import reproduce_command

    monkeypatch.delenv("GRADSEP_EVAL_FRAME_SEEDS", raising=False)
    assert config_from_args(_args()).frame_seeds == 1
    assert "FRAME_SEEDS" not in reproduce_command(config_from_args(_args()))
    assert config_from_args(_args(frame_seeds=3)).frame_seeds == 3
    monkeypatch.setenv("GRADSEP_EVAL_FRAME_SEEDS", "4")
    config = config_from_args(_args())
    assert config.frame_seeds == 4 and "GRADSEP_EVAL_FRAME_SEEDS=4" in reproduce_command(config)
    assert config_from_args(_args(frame_seeds=2)).frame_seeds == 2  # the flag wins
    for bad in (0, -2, MAX_FRAME_SEEDS + 1):
        with pytest.raises(CommandError, match="--frame-seeds must be"):
            config_from_args(_args(frame_seeds=bad))


def test_seed_mean_averages_the_metrics_and_keeps_each_seed():
    """The multi-seed row: metrics are means over the seeds, the time their mean (an interpolated seed counts at
    its budget), the spp their median, the standard error of the mean RelMSE from the seeds' spread."""
    from gradsep.evaluation.report_cells import spp_cell, stderr_cell
    from gradsep.evaluation.results import row_seconds
    from gradsep.evaluation.scores import seed_mean

    def row(relmse, spp, seconds, **more):
        return {"method": "path", "spp": 16, "method_spp": spp, "relmse": relmse, "ssim": 0.9, "psnr": 30.0,
                "flip": 0.1, "relmse_direct": None, "relmse_indirect": None, "render_seconds": seconds,
                "reconstruct_seconds": 0.0, "total_seconds": seconds, "target_seconds": 2.0, **more}

    rows = [row(0.004, 50, 2.02), row(0.002, 48, 1.97),
            row(0.003, 52, 2.5, time_interpolated="40 spp (1.9 s) and 60 spp (2.6 s)",
                time_bracket=[{"spp": 40}, {"spp": 60}])]
    out = seed_mean(rows)
    assert out["relmse"] == pytest.approx(0.003) and out["ssim"] == pytest.approx(0.9)
    assert out["relmse_direct"] is None  # a metric no seed has stays empty
    assert out["seed_relmse"] == [0.004, 0.002, 0.003] and out["seed_spp"] == [50, 48, 52]
    assert out["method_spp"] == 50 and out["seeds"] == 3
    assert out["seed_seconds"] == [2.02, 1.97, 2.0]  # the interpolated seed stands at its budget
    assert row_seconds(out) == pytest.approx((2.02 + 1.97 + 2.0) / 3)
    assert out["relmse_stderr"] == pytest.approx(0.001 / math.sqrt(3))
    assert out["time_interpolated"].startswith("seed 2: 40 spp") and "time_bracket" not in out
    assert spp_cell(out) == "50*" and stderr_cell(out) == " ±0.00058"
    assert stderr_cell(rows[0]) == "" and seed_mean(rows[:1])["relmse_stderr"] == 0.0


def test_environment_is_loaded_once_typed_and_named_in_errors(monkeypatch):
    """GRADSEP_EVAL_* go through one pydantic-settings class: a malformed value names its variable, an empty
    one counts as unset, and the report's reproduce line uses the same names."""
    from gradsep.evaluation.config import EvalSettings, load_settings
    from gradsep.evaluation.report import reproduce_command

    monkeypatch.setenv("GRADSEP_EVAL_REF_SPP", "lots")
    with pytest.raises(CommandError, match="GRADSEP_EVAL_REF_SPP: Input should be a valid integer"):
        config_from_args(_args(spp="1,4"))
    monkeypatch.setenv("GRADSEP_EVAL_REF_SPP", "")
    monkeypatch.setenv("GRADSEP_EVAL_ALPHA", "0.5")
    assert load_settings(seed=3).model_dump(exclude_none=True) == {"seed": 3, "alpha": 0.5}
    config = config_from_args(_args(spp="1,4"))
    assert config.ref_spp == 512 and config.alpha == 0.5
    line = reproduce_command(config)
    assert "GRADSEP_EVAL_ALPHA=0.5" in line and "GRADSEP_EVAL_REF_SPP=512" in line
    assert {f"GRADSEP_EVAL_{n.upper()}" for n in EvalSettings.model_fields} >= {
        name.split("=")[0] for name in line.split() if name.startswith("GRADSEP_EVAL_")}


def test_scene_resolution(tmp_path):
    entries, _ = resolve_scenes(["procedural:7", "procedural:7"])
    assert [e.name for e in entries] == ["procedural:7"]  # repeats dropped
    for bad in ("procedural:x", "procedural:-3", str(tmp_path / "missing.xml")):
        with pytest.raises(CommandError):
            resolve_scenes([bad])
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "scene.xml").write_text("<scene version='3.0.0'/>")
    entries, _ = resolve_scenes([str(tmp_path / "a" / "scene.xml"), str(tmp_path / "b")])
    assert [e.name for e in entries] == ["a", "b"]  # a generic scene.xml is labelled by its folder
    (tmp_path / "a" / "lamp.xml").write_text("<scene version='3.0.0'/>")
    entries, _ = resolve_scenes([str(tmp_path / "a" / "lamp.xml")])
    assert [e.name for e in entries] == ["lamp"]  # a named file keeps its own name
    for parent in ("x", "y"):  # two folders of the same name: told apart by the folder above
        (tmp_path / parent / "room").mkdir(parents=True)
        (tmp_path / parent / "room" / "scene.xml").write_text("<scene version='3.0.0'/>")
    entries, _ = resolve_scenes([str(tmp_path / p / "room" / "scene.xml") for p in ("x", "y")])
    assert [e.name for e in entries] == ["x/room", "y/room"]
    defaults, _ = resolve_scenes([])
    assert {"procedural:90001", "procedural:90002"} <= {e.name for e in defaults}


def test_command_refuses_bad_input_before_rendering(tmp_path, capsys):
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    with pytest.raises(CommandError, match="not a folder"):
        evaluate_command(_args(output=str(not_a_folder), scenes=[SCENE]))
    assert main(["evaluate", "--spp", "1,zero", "-o", str(tmp_path / "r")]) == 2
    assert "is not an integer" in capsys.readouterr().err
    assert main(["evaluate", "--scenes", str(tmp_path / "nope.xml"), "-o", str(tmp_path / "r")]) == 2
    assert "not found" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------- equal time


def test_cost_model_fits_the_line_and_picks_the_largest_spp_in_budget():
    model = CostModel(max_spp=10_000)
    for spp in (1, 8, 64):
        model.add(spp, 0.5 + 0.01 * spp)
    overhead, per_spp = model.fit()
    assert overhead == pytest.approx(0.5) and per_spp == pytest.approx(0.01)
    assert model.spp_for(1.5) == 100
    assert model.spp_for(0.1) == 1  # never below 1
    assert model.spp_for(1e6) == 10_000  # capped (Mitsuba's samples per launch)


def test_cost_model_survives_noise_that_inverts_the_slope():
    model = CostModel(max_spp=1000)
    model.add(1, 0.3)
    model.add(8, 0.2)  # the larger render measured faster
    overhead, per_spp = model.fit()
    assert per_spp > 0 and overhead >= 0
    assert 1 <= model.spp_for(1.0) <= 1000


def test_split_features_takes_the_last_six_channels():
    image = np.arange(2 * 2 * 10, dtype=np.float32).reshape(2, 2, 10)  # R G B A + albedo + normal
    albedo, normal = split_features(image)
    assert np.array_equal(albedo, image[..., 4:7]) and np.array_equal(normal, image[..., 7:])
    with pytest.raises(RuntimeError):
        split_features(image[..., :5])


# ----------------------------------------------------------------------------------------- report logic


def test_crop_selects_the_detailed_region():
    reference = np.full((60, 80, 3), 0.3, np.float32)
    yy, xx = np.mgrid[0:20, 0:20]
    reference[35:55, 50:70] = (((yy + xx) % 2) * 0.8 + 0.1)[..., None]  # a checkerboard: all the detail
    y0, x0, side = select_crop(reference)
    assert side == 20
    assert abs(y0 - 35) <= 1 and abs(x0 - 50) <= 1


def test_losses_of_ours_lists_every_better_method():
    rows = [{"scene": "s", "method": m, "spp": spp, "relmse": v}
            for spp, values in ((1, {"ours": 0.1, "l1": 0.2, "path-oidn": 0.05}), (4, {"ours": 0.01, "l1": 0.02}))
            for m, v in values.items()]
    assert losses_of_ours(rows) == ["s, 1 spp: ours 0.1; lower: path-oidn 0.05"]


# ------------------------------------------------------------------------------------------ a real run


def _blur_model(path: Path, layer: str, kernel: int) -> None:
    """An ONNX graph that averages the log-encoded base over kernel×kernel pixels, with gradsep metadata."""
    import onnx
    from onnx import TensorProto, helper

    from gradsep.model.preprocess import DATA_INPUTS, GRADIENT_INPUTS, describe_preprocessing

    nodes = [
        helper.make_node("Constant", [], ["starts"], value=helper.make_tensor("s", TensorProto.INT64, [1], [0])),
        helper.make_node("Constant", [], ["ends"], value=helper.make_tensor("e", TensorProto.INT64, [1], [3])),
        helper.make_node("Constant", [], ["axes"], value=helper.make_tensor("a", TensorProto.INT64, [1], [1])),
        helper.make_node("Slice", ["data", "starts", "ends", "axes"], ["base"]),
        helper.make_node("AveragePool", ["base"], ["radiance_log"], kernel_shape=[kernel, kernel],
                         pads=[kernel // 2] * 4, count_include_pad=0),
    ]
    graph = helper.make_graph(
        nodes, "blur",
        [helper.make_tensor_value_info("data", TensorProto.FLOAT, ["n", len(DATA_INPUTS), "h", "w"]),
         helper.make_tensor_value_info("gradient", TensorProto.FLOAT, ["n", len(GRADIENT_INPUTS), "h", "w"])],
        [helper.make_tensor_value_info("radiance_log", TensorProto.FLOAT, ["n", 3, "h", "w"])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=10)
    import json

    helper.set_model_props(model, {
        "gradsep.layer": layer, "gradsep.alignment": "4",
        "gradsep.inputs": json.dumps({"data": list(DATA_INPUTS), "gradient": list(GRADIENT_INPUTS)}),
        "gradsep.preprocessing": json.dumps(describe_preprocessing()),
    })
    onnx.checker.check_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(model, str(path))


def _config(root: Path, output: str = "report") -> EvalConfig:
    return EvalConfig(scenes=(SCENE,), spp=SPP, width=32, height=32, ref_spp=16, output=root / output,
                      cache_dir=root / "cache", models_dir=root / "models", methods=METHODS, seed=3)


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaluate")
    models = root / "models"
    for layer in ("direct", "indirect", "color"):
        _blur_model(models / f"{layer}.onnx", layer, 3)
    for layer in ("direct", "indirect"):
        _blur_model(models / "ablation" / "separated-attn" / f"{layer}.onnx", layer, 5)
    evaluation = run_evaluation(_config(root), progress=False, log=lambda message: None)
    return root, evaluation


@pytest.mark.slow
@pytest.mark.render
def test_run_writes_every_output_with_finite_consistent_rows(first_run):
    root, evaluation = first_run
    report = root / "report"
    rows = _read_csv(report / "results.csv")
    assert list(rows[0]) == list(CSV_COLUMNS)
    ran = _runnable(METHODS)
    assert sorted((r["method"], int(r["spp"])) for r in rows) == sorted((m, s) for m in ran for s in SPP)
    for r in rows:
        values = [float(r[c]) for c in ("render_seconds", "reconstruct_seconds", "total_seconds", "relmse", "ssim",
                                        "psnr", "flip")]
        assert all(math.isfinite(v) for v in values), r
        assert float(r["total_seconds"]) == pytest.approx(float(r["render_seconds"]) + float(r["reconstruct_seconds"]),
                                                          rel=1e-4, abs=1e-5)
        assert 0 <= float(r["ssim"]) <= 1 and 0 <= float(r["flip"]) <= 1
    for name in ("results.json", "report.md", "plots/procedural-90001.png", "crops/procedural-90001.png"):
        assert (report / name).is_file(), name
    for png in ("plots/procedural-90001.png", "crops/procedural-90001.png"):
        assert (report / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # two references of one 16-spp pass each (the cap equals the start here)
    # one G-PT frame per spp, and one more per spp in the `direct` render mode when oidn-l1 ran
    modes = {method_by_name(m).gradients for m in ran}
    assert evaluation.computed == {"frames": len(modes) * len(SPP), "references": 2,
                                   "results": len(ran) * len(SPP)}
    text = (report / "report.md").read_text()
    assert "## Reference floor" in text and "RelMSE(r1, r2) / 2" in text


@pytest.mark.render
def test_rows_are_scored_with_the_product_estimator_over_the_cached_references(first_run):
    """The input's RelMSE recomputed from the files in the cache: the row scores what was rendered, against
    both references (the product estimator), and SSIM against their mean."""
    from gradsep.model.exr_read import read_frame
    from gradsep.model.metrics import relmse_unbiased, ssim
    from gradsep.renderer.reference import load_reference

    root, evaluation = first_run
    frames = [f for f in sorted((root / "cache" / "evaluate" / "frames").rglob("*spp2-*.exr"))
              if "-direct" not in f.name]
    passes = [sorted((root / "cache" / "evaluate" / "references").rglob(f"*pass{i}-*.exr")) for i in (0, 1)]
    assert len(frames) == 1 and [len(p) for p in passes] == [1, 1]
    frame = read_frame(str(frames[0]))
    r1, r2 = (load_reference(str(p[0])) for p in passes)
    assert not np.array_equal(r1.total, r2.total)  # independent seeds
    primal = sum(layer.base for layer in frame.layers.values())
    row = next(r for r in evaluation.rows if r["method"] == "gpt-primal" and r["spp"] == 2)
    assert row["relmse"] == pytest.approx(relmse_unbiased(primal, r1.total, r2.total), rel=1e-6)
    assert row["relmse_direct"] == pytest.approx(relmse_unbiased(frame.layers["direct"].base, r1.direct, r2.direct),
                                                 rel=1e-6)
    assert row["ssim"] == pytest.approx(ssim(primal, 0.5 * (r1.total.astype(np.float64) + r2.total)), rel=1e-5)
    assert row["render_seconds"] == pytest.approx(float(frame.metadata["gradsep.render_seconds"]))
    scene = evaluation.scenes[0]
    assert scene.reference_spp == 16 and scene.floor["total"] > 0


@pytest.mark.render
def test_equal_time_methods_use_the_default_method_as_the_budget(first_run):
    """The budget is the G-PT frame + the product's default reconstruction (the methods table's default
    preference, whose ``network`` is the evaluation's ``ours``): the first of them this run computed."""
    from gradsep.model import methods as table

    _, evaluation = first_run
    by = {(r["method"], r["spp"]): r for r in evaluation.rows}
    ran = {r["method"] for r in evaluation.rows}
    budget = next(n for n in ("ours" if m == "network" else m for m in (*table.default_preference(), "network"))
                  if n in ran)
    for spp in SPP:
        anchor = by[(budget, spp)]
        for method in EQUAL_TIME_METHODS & set(_runnable(METHODS)):
            row = by[(method, spp)]
            assert row["budget_method"] == budget
            assert row["target_seconds"] == pytest.approx(anchor["total_seconds"])
            assert row["method_spp"] >= 1 and row["attempts"] >= 1
        assert by[("path-oidn", spp)]["reconstruct_seconds"] > 0  # the denoiser's time is counted
        assert by[("path-oidn", spp)]["feature_spp"] >= 1  # and the feature pass's, in render_seconds
        assert by[("ours", spp)]["relmse_indirect"] is not None
        if "gpt-oidn-l1" in _runnable(METHODS):  # our renderer at equal time: the direct-gradient render, rebought
            row = by[("gpt-oidn-l1", spp)]
            assert row["gradients"] == "direct" and row["reconstruct_seconds"] > 0
            assert row["relmse_direct"] is not None and row["relmse_indirect"] is not None


@pytest.mark.render
def test_frame_seeds_add_frames_to_the_fixed_spp_rows_only(first_run):
    """--frame-seeds 2 over the first run's cache: one more G-PT frame per (spp, render mode) and every fixed-spp
    method on it are computed; each such row is the mean over two different frames (the first the single-frame
    run's own), the equal-time rows (their budgets from the first frame) are unchanged, and the report says what
    its cells are."""
    import dataclasses
    import json

    from gradsep.evaluation.methods import EQUAL_TIME_KINDS, method_by_name

    root, first = first_run
    config = dataclasses.replace(_config(root, "report-frames"), frame_seeds=2)
    two = run_evaluation(config, progress=False, log=lambda message: None)
    fixed = [m for m in _runnable(METHODS) if method_by_name(m).kind not in EQUAL_TIME_KINDS]
    modes = {"all"} | {method_by_name(m).gradients for m in fixed}
    assert two.computed == {"frames": len(modes) * len(SPP), "references": 0, "results": len(fixed) * len(SPP)}
    before = {(r["method"], r["spp"]): r for r in first.rows}
    for r in two.rows:
        old = before[(r["method"], r["spp"])]
        if r["method"] not in fixed:
            assert r["relmse"] == old["relmse"] and "seeds" not in r
            continue
        assert r["seeds"] == 2 and r["seed_relmse"][0] == pytest.approx(old["relmse"])
        if r["method"] != "gpt-primal" or r["spp"] > 1:
            assert r["seed_relmse"][0] != r["seed_relmse"][1]  # another frame, another image
        assert r["relmse"] == pytest.approx(sum(r["seed_relmse"]) / 2)
        assert r["relmse_stderr"] == pytest.approx(abs(r["seed_relmse"][0] - r["seed_relmse"][1]) / 2)
        assert r["method_spp"] == r["spp"]
    summary = json.loads((root / "report-frames" / "results.json").read_text())
    assert summary["config"]["frame_seeds"] == 2 and "GRADSEP_EVAL_FRAME_SEEDS=2" in summary["reproduce"]
    text = (root / "report-frames" / "report.md").read_text()
    assert "mean over 2 G-PT frames" in text and " ±" in text
    assert "Each fixed-spp cell is one G-PT frame" in (root / "report" / "report.md").read_text()
    shutil.rmtree(root / "report-frames", ignore_errors=True)


@pytest.mark.render
def test_time_seeds_add_seeds_to_the_equal_time_rows_only(first_run):
    """--time-seeds 2 over the first run's cache: only the equal-time rows' second seeds are computed (the first
    seed is the single-seed run's own, cached), each such row is the mean of two different seeds, and every other
    row is unchanged; the report says what its cells are."""
    import dataclasses
    import json

    root, first = first_run
    config = dataclasses.replace(_config(root, "report-seeds"), time_seeds=2)
    two = run_evaluation(config, progress=False, log=lambda message: None)
    equal_time = EQUAL_TIME_METHODS & set(_runnable(METHODS))
    assert two.computed == {"frames": 0, "references": 0, "results": len(equal_time) * len(SPP)}
    before = {(r["method"], r["spp"]): r for r in first.rows}
    for r in two.rows:
        old = before[(r["method"], r["spp"])]
        if r["method"] not in equal_time:
            assert r["relmse"] == old["relmse"] and "seeds" not in r
            continue
        assert r["seeds"] == 2 and r["seed_relmse"][0] == pytest.approx(old["relmse"])
        assert r["seed_relmse"][0] != r["seed_relmse"][1]  # another seed, another image
        assert r["relmse"] == pytest.approx(sum(r["seed_relmse"]) / 2)
        assert r["relmse_stderr"] == pytest.approx(abs(r["seed_relmse"][0] - r["seed_relmse"][1]) / 2)
        assert all(s >= 1 for s in r["seed_spp"]) and len(r["seed_seconds"]) == 2
    summary = json.loads((root / "report-seeds" / "results.json").read_text())
    assert summary["config"]["time_seeds"] == 2 and "GRADSEP_EVAL_TIME_SEEDS=2" in summary["reproduce"]
    text = (root / "report-seeds" / "report.md").read_text()
    assert "mean over 2 seeds" in text and " ±" in text
    assert "Each equal-time cell is one seed" in (root / "report" / "report.md").read_text()
    shutil.rmtree(root / "report-seeds", ignore_errors=True)


@pytest.mark.render
def test_oidn_l1_reconstructs_a_direct_gradient_render_with_the_same_image(first_run):
    """oidn-l1 integrates only the direct layer's gradients, so its row reconstructs the `--gradients direct`
    render of the same seed (cheaper: no indirect offsets) and counts that render's time; its image is what the
    method gives on the full frame (same direct layer, same indirect base), to float rounding."""
    from gradsep.model.exr_read import read_frame
    from gradsep.model.reconstruct import reconstruct

    root, evaluation = first_run
    if "oidn-l1" not in _runnable(METHODS):
        pytest.skip("oidn-l1 cannot run here (pyoidn missing)")
    frames = sorted((root / "cache" / "evaluate" / "frames").rglob("*spp2-*.exr"))
    full = read_frame(str(next(f for f in frames if "-direct" not in f.name)))
    direct = read_frame(str(next(f for f in frames if "-direct" in f.name)))
    assert direct.metadata["gradsep.gradients"] == "direct" and direct.layers["indirect"].dx is None
    row = next(r for r in evaluation.rows if r["method"] == "oidn-l1" and r["spp"] == 2)
    assert row["gradients"] == "direct"
    assert row["render_seconds"] == pytest.approx(float(direct.metadata["gradsep.render_seconds"]))
    np.testing.assert_allclose(reconstruct(direct, "oidn-l1").image, reconstruct(full, "oidn-l1").image,
                               rtol=1e-4, atol=1e-6)
    assert next(r for r in evaluation.rows if r["method"] == "oidn" and r["spp"] == 2)["gradients"] == "all"


@pytest.mark.render
def test_missing_models_and_packages_are_skipped_with_the_reason(first_run):
    root, evaluation = first_run
    for method in set(METHODS) - set(_runnable(METHODS)):
        assert method in evaluation.skipped and evaluation.skipped[method][0]  # a stated reason, no row
        assert not any(r["method"] == method for r in evaluation.rows)
    report = (root / "report" / "report.md").read_text()
    for text in ("Table 1", "Ablation (paper Fig. 7)", "Equal time", "Where ours loses", "Skipped methods"):
        assert text in report
    config = _config(root, output="report-all")
    config = EvalConfig(**{**config.__dict__, "methods": ("gpt-primal", "ablation/combined-attn"), "spp": (1,)})
    evaluation = run_evaluation(config, progress=False, log=lambda message: None)
    assert list(evaluation.skipped) == ["ablation/combined-attn"]
    assert evaluation.skipped["ablation/combined-attn"][0].endswith("ablation/combined-attn/color.onnx")
    assert "ablation/combined-attn/color.onnx" in (root / "report-all" / "report.md").read_text()
    assert evaluation.computed["frames"] == 0  # the 1-spp frame came from the cache


@pytest.mark.slow
@pytest.mark.render
def test_rerun_computes_only_what_changed(first_run, monkeypatch):
    root, first = first_run
    csv_before = (root / "report" / "results.csv").read_bytes()

    def no_rendering(*args, **kwargs):
        raise AssertionError("a cached frame or reference was rendered again")

    monkeypatch.setattr("gradsep.renderer.render.render_frame", no_rendering)
    monkeypatch.setattr("gradsep.renderer.reference.render_loaded", no_rendering)
    again = run_evaluation(_config(root), progress=False, log=lambda message: None)
    assert again.computed == {"frames": 0, "references": 0, "results": 0}
    assert (root / "report" / "results.csv").read_bytes() == csv_before

    # a new `ours` model: ours is recomputed, and so are the equal-time methods when ours sets their budget
    # (the separated path + OIDN renders through render_frame again, so rendering is allowed from here on)
    monkeypatch.undo()
    _blur_model(root / "models" / "direct.onnx", "direct", 5)
    # and a damaged cache entry is recomputed rather than trusted
    damaged = next(p for p in (root / "cache" / "evaluate" / "results").rglob("l1-*spp1-*.json")
                   if "-r1-" not in p.name)  # the first frame's, not a --frame-seeds replica's
    damaged.write_text("{ truncated")
    changed = run_evaluation(_config(root), progress=False, log=lambda message: None)
    equal_time = len(EQUAL_TIME_METHODS & set(_runnable(METHODS)))
    if next(r["budget_method"] for r in first.rows if r["method"] == "path") != "ours":
        equal_time = 0
    assert changed.computed == {"frames": 0, "references": 0, "results": (1 + equal_time) * len(SPP) + 1}
    old = {(r["method"], r["spp"]): r["relmse"] for r in first.rows}
    new = {(r["method"], r["spp"]): r["relmse"] for r in changed.rows}
    assert new[("gradnet", 1)] == old[("gradnet", 1)]
    assert new[("ours", 1)] != old[("ours", 1)]
    shutil.rmtree(root / "report-all", ignore_errors=True)


def test_references_are_raised_additively_until_the_floor_criterion_holds(first_run):
    """A higher cap: the references grow from the cached 16-spp passes (only the new passes are rendered), then
    add region passes, and stop at the cap when the floor stays over 10 % of the smallest error, with the
    report's warning. A 32×32
    frame at 1-2 spp is near the boundary (the floor of two 16-spp references is ~1/8 of a 2-spp error): when the
    criterion already holds at 16 spp nothing is rendered, and that is checked too."""
    root, _ = first_run
    config = EvalConfig(**{**_config(root, output="report-raise").__dict__, "methods": ("gpt-primal",),
                           "ref_spp_cap": 64})
    evaluation = run_evaluation(config, progress=False, log=lambda message: None)
    scene = evaluation.scenes[0]
    assert scene.reference_spp in (16, 32, 64)
    region_passes = scene.region_spp // 16  # per reference, over the pilot's rectangle (evaluation/region.py)
    if region_passes:  # only once the full passes stopped at the cap short of the criterion
        assert scene.reference_spp == 64 and scene.reference_region is not None
    # passes 0 and 1 re-used; the pilot's 8 passes and both references' region passes are new
    assert evaluation.computed["references"] == (2 * (scene.reference_spp // 16) - 2
                                                 + (8 + 2 * region_passes if region_passes else 0))
    text = (root / "report-raise" / "report.md").read_text()
    if scene.capped:
        assert scene.reference_spp == 64 and scene.region_spp == 64  # region passes up to the cap more
        assert "Warning: procedural:90001: the references stopped at 64 spp each (the spp cap" in text
        assert "region passes at their cap" in text
    else:
        assert scene.floor["total"] <= 0.1 * scene.smallest
    shutil.rmtree(root / "report-raise", ignore_errors=True)


@pytest.mark.slow
@pytest.mark.render
def test_quick_command_end_to_end(tmp_path, capsys):
    """`gradsep evaluate --quick` through the CLI (one scene, one spp, references capped low to stay fast)."""
    code = main(["evaluate", "--quick", "--scenes", SCENE, "--spp", "1", "--ref-spp-cap", "128",
                 "--methods", "gpt-primal,l1,path,path-oidn", "--models", str(tmp_path / "none"),
                 "--cache", str(tmp_path / "cache"), "-o", str(tmp_path / "quick")])
    assert code == 0, capsys.readouterr().err
    rows = _read_csv(tmp_path / "quick" / "results.csv")
    assert {r["method"] for r in rows} == {"gpt-primal", "l1", "path", "path-oidn"}
    assert {(int(r["width"]), int(r["height"])) for r in rows} == {(QUICK.width, QUICK.height)}
    assert "## Reference floor" in (tmp_path / "quick" / "report.md").read_text()


class _ClockedRenderer:
    """PathRenderer's budgeting logic over a simulated clock: seconds = cost(spp) × a factor the test can change
    to model a busy machine; the default cost is a line, others are not (the fitted line then mispredicts)."""

    def __init__(self, cost=lambda spp: 0.05 + 0.002 * spp) -> None:
        from gradsep.evaluation.baselines import PathRenderer

        self.renderer = PathRenderer.__new__(PathRenderer)  # no Mitsuba: only the budgeting is under test
        self.renderer.max_spp = 100_000
        self.renderer._costs = {}
        self.renderer._post_seconds = {}
        self.renderer._warm = set()
        self.cost = cost
        self.factor = 1.0
        self.calls: list[int] = []
        self.renderer.render = self.render  # type: ignore[method-assign]

    def render(self, kind: str, spp: int, seed: int):
        seconds = self.cost(spp) * self.factor
        self.calls.append(spp)
        if kind in self.renderer._costs:
            self.renderer._costs[kind].add(spp, seconds)
        return np.zeros((1, 1, 3), np.float32), seconds


def test_equal_time_render_fits_the_budget():
    clock = _ClockedRenderer()
    got = clock.renderer.render_within("path", 1.05, seed=0)
    assert got.spp == 500 and got.render_seconds == pytest.approx(1.05) and got.attempts == 1 and not got.note
    # calibration grew ×4 from 1 spp until a render took a quarter second (each measured twice); the one try,
    # shorter than REPEAT_BELOW, was timed REPEATS times
    repeats = clock.renderer.REPEATS
    assert clock.calls[:1] == [1] and 256 in clock.calls and clock.calls[-repeats:] == [500] * repeats
    assert max(clock.calls[:-repeats]) < 500


@pytest.mark.parametrize("budget", [0.3, 1.0, 3.7, 20.0])
@pytest.mark.parametrize("cost", [
    lambda spp: 0.02 + 0.001 * spp ** 1.25,  # super-linear (cache pressure): the line under-predicts
    lambda spp: 0.2 + 0.01 * spp ** 0.8,  # sub-linear: the line over-predicts
    lambda spp: 0.01 * spp + (0.3 if spp > 300 else 0.0),  # a step (a second launch past a wavefront limit)
])
def test_equal_time_bisection_lands_within_5_percent(cost, budget):
    clock = _ClockedRenderer(cost)
    got = clock.renderer.render_within("path", budget, seed=0)
    assert abs(got.render_seconds / budget - 1) <= 0.05, got
    assert got.attempts <= clock.renderer.MAX_ATTEMPTS


def test_equal_time_render_is_redone_until_within_5_percent_when_the_machine_slowed_down():
    clock = _ClockedRenderer()
    clock.renderer.cost("path")
    clock.factor = 2.0  # everything now takes twice as long: the first render misses the budget by 100 %
    got = clock.renderer.render_within("path", 1.05, seed=0)
    assert got.tries[0][0] == 500 and got.spp < 500 and got.attempts > 1  # redone at a smaller spp
    assert abs(got.render_seconds / 1.05 - 1) <= 0.05


def test_equal_time_counts_the_post_processing_of_every_try():
    """A post-processing step after each try (a denoiser): its *measured* time counts, not its estimate. Here
    the estimate (0.2 s) is far too high for a step that takes microseconds: the first try (at the spp for
    1.05 - 0.2 s) is too fast, and the bisection recovers the spp that fills the budget. The output kept is the
    post-processed one."""
    clock = _ClockedRenderer()
    got = clock.renderer.render_within("path", 1.05, seed=0, post=lambda image: image + 1.0, post_estimate=0.2)
    assert abs((got.render_seconds + got.post_seconds) / 1.05 - 1) <= 0.05
    assert got.tries[0][0] == 400 and got.attempts > 1 and got.spp > 470
    assert float(got.output.mean()) == 1.0


def test_time_misses_flags_rows_outside_5_percent():
    rows = [{"scene": "s", "spp": 1, "method": "path", "method_spp": 9, "total_seconds": 0.72, "target_seconds": 1.0,
             "attempts": 5, "time_note": "spp granularity: 9 spp takes 0.72 s, 10 spp 1.1 s"},
            {"scene": "s", "spp": 2, "method": "path", "method_spp": 9, "total_seconds": 1.04, "target_seconds": 1.0},
            {"scene": "s", "spp": 2, "method": "ours", "method_spp": 2, "total_seconds": 9.0, "target_seconds": None}]
    misses = time_misses(rows)
    assert len(misses) == 1 and "-28%" in misses[0]
    assert misses[0].endswith("granularity: 9 spp takes 0.72 s, 10 spp 1.1 s")  # the reason is reported


def test_oidn_environment_choices_are_part_of_the_result_key(monkeypatch) -> None:
    """$GRADSEP_OIDN_SETTING changes the OIDN methods' images without a code change: a run under it must not reuse
    outputs cached under the default (whose keys stay as they were)."""
    from gradsep.evaluation.cache import oidn_key
    from gradsep.model import oidn

    monkeypatch.delenv(oidn.SETTING_ENV, raising=False)
    assert oidn_key() == {}
    monkeypatch.setenv(oidn.SETTING_ENV, "prefiltered-high")
    assert oidn_key() == {"oidn_setting": "prefiltered-high"}


def test_issue14_targets_are_read_from_the_rows():
    """The report's issue-14 lines: fused against the best of oidn/l1/ours, and at equal time the best G-PT row
    within the budget (the budget method's own row, G-PT+oidn-l1) against path + OIDN and the separated baseline;
    a scene without the methods is 'not checked'."""
    from gradsep.evaluation.report import _fused_and_equal_time_targets

    def row(method, spp, relmse, **extra):
        return {"scene": "s", "method": method, "spp": spp, "relmse": relmse, **extra}

    rows = [row("oidn", 16, 3.0), row("l1", 16, 2.0), row("ours", 16, 4.0), row("fused", 16, 2.2),
            row("oidn-l1", 16, 1.5), row("gpt-oidn-l1", 16, 1.2, budget_method="oidn-l1"),
            row("path-oidn", 16, 1.4, budget_method="oidn-l1"), row("path-sep-oidn", 16, 1.1, budget_method="oidn-l1"),
            row("oidn", 64, 3.0), row("l1", 64, 2.0), row("ours", 64, 4.0), row("fused", 64, 1.0)]
    text = "\n".join(_fused_and_equal_time_targets(rows))
    assert ("s, 16 spp: `fused` against the best of `oidn`, `l1`, `ours` (`l1`): 2.2 / 2 = 1.100× (**not below**)"
            in text)
    assert "s, 64 spp: `fused`" in text and "0.500× (below all three)" in text
    equal = next(line for line in text.splitlines() if "equal time" in line)
    assert "(`gpt-oidn-l1`) is below `path-oidn` (1.2 / 1.4 = 0.857×)" in equal
    assert "**not below** `path-sep-oidn` (1.2 / 1.1 = 1.091×)" in equal
    assert "not checked" in "\n".join(_fused_and_equal_time_targets([row("l1", 16, 1.0)]))


@pytest.mark.render
def test_scenes_are_validated_up_front_and_evaluated_one_loaded_at_a_time(tmp_path, monkeypatch):
    """A loaded scene's objects stay registered with Dr.Jit and every render traces its virtual calls over all of
    them, so while a scene is evaluated no other scene may be alive; a bad scene is still refused before any work."""
    import gc
    from types import SimpleNamespace

    from gradsep.evaluation import run
    from gradsep.evaluation.config import EvalConfig
    from gradsep.renderer.scene import LoadedScene

    seen: list[tuple[str, int]] = []

    def fake_run_scene(runner, entry, loaded, methods, bar):
        gc.collect()
        seen.append((entry.name, sum(isinstance(o, LoadedScene) for o in gc.get_objects())))
        if len(seen) == 2:
            raise StopIteration  # nothing is evaluated: the test is about the scenes' lifetimes
        return SimpleNamespace(), []

    monkeypatch.setattr(run, "_run_scene", fake_run_scene)
    config = EvalConfig(scenes=("procedural:7", "procedural:8"), spp=(1,), width=8, height=8, ref_spp=1,
                        output=tmp_path / "out", cache_dir=tmp_path / "cache", models_dir=tmp_path / "models",
                        methods=("gpt-primal",))
    with pytest.raises(StopIteration):
        run.run_evaluation(config, progress=False, log=lambda message: None)
    assert seen == [("procedural:7", 1), ("procedural:8", 1)]


def test_the_report_names_scene_files_relative_to_the_repository_not_this_machines_checkout(tmp_path, monkeypatch):
    from gradsep.evaluation import cache
    from gradsep.evaluation.report import display_spec

    repo, scenes = tmp_path / "checkout", tmp_path / "elsewhere" / "scenes"
    repo.mkdir()
    scenes.mkdir(parents=True)
    (tmp_path / "shared").symlink_to(scenes.parent)  # a worktree's ../shared, linked to the real folder
    monkeypatch.setattr(cache, "REPO_ROOT", repo)
    assert display_spec(str(tmp_path / "shared" / "scenes" / "cbox.xml")) == "../shared/scenes/cbox.xml"
    assert display_spec(str(repo / "examples" / "scene.xml")) == "examples/scene.xml"
    assert display_spec("procedural:90001") == "procedural:90001"
    assert display_spec("/nowhere/room.xml") == "/nowhere/room.xml"
