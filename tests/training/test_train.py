"""training/train.py: smoke training, the run folder, resume, budgets, errors, DDP (the dataset: test_dataset.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gradsep.cli import main as cli_main  # noqa: E402
from gradsep.training.dataset import DatasetError  # noqa: E402
from gradsep.training.runlog import read_log  # noqa: E402
from gradsep.training.train import Trainer, TrainingError, train  # noqa: E402
from tests.training.conftest import tiny_config  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def _weights(run: Path) -> dict[str, torch.Tensor]:
    return torch.load(run / "checkpoints" / "last.pt", weights_only=True)["model"]


def _epochs(run: Path) -> list[dict]:
    return [r for r in read_log(run) if r["kind"] == "epoch"]


@pytest.mark.slow
@pytest.mark.train
def test_smoke_training_lowers_the_loss(make_config) -> None:
    cfg = make_config(epochs=6, lr=2e-3, log_every=1)
    progress = train(cfg, quiet=True)
    assert progress.epoch == 6 and progress.step == 30
    epochs = _epochs(Path(cfg.output))
    assert [e["epoch"] for e in epochs] == [1, 2, 3, 4, 5, 6]
    first, last = epochs[0], epochs[-1]
    # β is 0 in the first two epochs, so compare the β-free part of the objective
    def objective(e: dict, split: str) -> float:
        return e[split]["data"] + e[split]["grad"]
    assert objective(last, "train") < 0.9 * objective(first, "train")
    assert objective(last, "val") < 0.9 * objective(first, "val")
    assert last["beta"] > 0 and last["lr"] < cfg.lr                # β ramps, lr ×0.95 every other epoch
    assert all(np.isfinite(e["gbranch"]) for e in epochs)


@pytest.mark.train
def test_paired_training_validates_against_the_prior(tmp_path: Path) -> None:
    from tests.training.synthetic import make_synthetic_dataset

    from .conftest import tiny_config

    root = make_synthetic_dataset(tmp_path / "ds", frames=6, width=64, height=48, pairs=True)
    cfg = tiny_config(root, tmp_path / "run", epochs=1)
    train(cfg, quiet=True)
    val = _epochs(Path(cfg.output))[0]["val"]
    assert {"data", "grad", "total", "prior_data", "prior_grad", "prior_total"} <= set(val)
    assert all(np.isfinite(v) for v in val.values())
    # the network is C(prior) + a zero-initialised correction: one epoch moves it, but not far
    assert val["data"] == pytest.approx(val["prior_data"], rel=0.5)


@pytest.mark.train
def test_run_folder_contents(make_config) -> None:
    cfg = make_config(epochs=4, keep_epoch_checkpoints=2, log_every=2)
    train(cfg, quiet=True)
    run = Path(cfg.output)
    config = json.loads((run / "config.json").read_text())
    assert config["train"]["layer"] == "direct" and config["train"]["network"]["width"] == 4
    assert len(config["dataset_manifest_sha256"]) == 64 and config["preprocessing"]["mu"] == 16.0
    assert (run / "losses.png").stat().st_size > 1000
    assert sorted(p.name for p in (run / "checkpoints").glob("epoch_*.pt")) == ["epoch_0003.pt", "epoch_0004.pt"]
    steps = [r for r in read_log(run) if r["kind"] == "step"]
    assert [r["step"] for r in steps] == list(range(2, 21, 2))
    assert {"data", "grad", "first", "total", "beta", "lr"} <= set(steps[0])


@pytest.mark.slow
@pytest.mark.train
def test_resume_with_a_larger_budget_equals_an_uninterrupted_run(make_config) -> None:
    straight = make_config("straight", epochs=3)
    train(straight, quiet=True)
    resumed = make_config("resumed", epochs=1)
    train(resumed, quiet=True)
    train(make_config("resumed", epochs=3), quiet=True)
    a, b = _weights(Path(straight.output)), _weights(Path(resumed.output))
    assert all(torch.allclose(a[k], b[k], rtol=1e-5, atol=1e-7) for k in a)
    assert [e["epoch"] for e in _epochs(Path(resumed.output))] == [1, 2, 3]


@pytest.mark.slow
@pytest.mark.train
@pytest.mark.parametrize("stop_phase", ["main", "gbranch"])
def test_resume_in_the_middle_of_a_phase(make_config, monkeypatch: pytest.MonkeyPatch, stop_phase: str) -> None:
    """A run stopped after the 3rd batch of a phase (as a kill after a periodic checkpoint would leave it)
    continues from that batch and ends with exactly the uninterrupted run's weights."""
    straight = make_config("straight")
    train(straight, quiet=True)

    calls = {"n": 0}
    original = Trainer._out_of_time

    def stop_once(self: Trainer) -> bool:
        p = self.progress
        if p.epoch == 1 and p.phase == stop_phase and p.batch == 3 and calls["n"] == 0:
            calls["n"] += 1
            return True
        return original(self)

    monkeypatch.setattr(Trainer, "_out_of_time", stop_once)
    interrupted = make_config("interrupted")
    progress = train(interrupted, quiet=True)
    assert (progress.epoch, progress.phase, progress.batch) == (1, stop_phase, 3)
    state = torch.load(Path(interrupted.output) / "checkpoints" / "last.pt", weights_only=True)
    assert state["progress"]["batch"] == 3 and state["progress"]["phase"] == stop_phase
    progress = train(interrupted, quiet=True)
    assert progress.epoch == 2 and progress.step == 10
    a, b = _weights(Path(straight.output)), _weights(Path(interrupted.output))
    assert all(torch.allclose(a[k], b[k], rtol=1e-5, atol=1e-7) for k in a)
    # the stopped epoch's averages include the batches done before the stop
    assert _epochs(Path(interrupted.output))[-1]["train"] == pytest.approx(_epochs(Path(straight.output))[-1]["train"],
                                                                          rel=1e-4)


@pytest.mark.train
def test_time_budget_stops_and_a_spent_budget_does_nothing(make_config) -> None:
    cfg = make_config(epochs=None, minutes=1e-6)
    progress = train(cfg, quiet=True)
    assert progress.step == 0 and (Path(cfg.output) / "checkpoints" / "last.pt").is_file()
    again = train(cfg, quiet=True)
    assert again.step == 0


@pytest.mark.train
def test_a_different_run_in_the_same_folder_is_refused(make_config) -> None:
    train(make_config(epochs=1), quiet=True)
    with pytest.raises(TrainingError, match="seed"):
        train(make_config(epochs=1, seed=7), quiet=True)


@pytest.mark.train
def test_color_layer_and_training_config_validation(make_config) -> None:
    progress = train(make_config(layer="color", epochs=1), quiet=True)
    assert progress.epoch == 1
    with pytest.raises(ValueError, match="multiple of the network alignment"):
        make_config(patch=30)
    with pytest.raises(ValueError, match="layer"):
        make_config(layer="specular")


def test_the_prior_alpha_is_validated_recorded_and_part_of_the_run(make_config) -> None:
    """TrainConfig.prior_alpha (the model's gradsep.prior_alpha) must be a finite α > 0; a run folder made with one
    α refuses another; a run folder from before the key existed reads as UNRECORDED_PRIOR_ALPHA."""
    from gradsep.model.preprocess import UNRECORDED_PRIOR_ALPHA
    from gradsep.training.train import TrainConfig, prepare_run_dir

    for bad in (float("nan"), float("inf"), 0.0, -0.2):
        with pytest.raises(ValueError, match="prior_alpha must be a finite number > 0"):
            make_config(prior_alpha=bad)
    cfg = make_config()
    run = prepare_run_dir(cfg, "sha")
    assert run["train"]["prior_alpha"] == cfg.prior_alpha
    assert f"alpha={cfg.prior_alpha}" in run["preprocessing"]["prior"]
    with pytest.raises(TrainingError, match="prior_alpha"):
        prepare_run_dir(make_config(prior_alpha=2 * cfg.prior_alpha), "sha")
    config = Path(cfg.output) / "config.json"
    old = json.loads(config.read_text())
    del old["train"]["prior_alpha"]
    config.write_text(json.dumps(old))
    prepare_run_dir(make_config(prior_alpha=UNRECORDED_PRIOR_ALPHA), "sha")  # the same run: resumes
    assert TrainConfig.from_dict(old["train"]).prior_alpha == UNRECORDED_PRIOR_ALPHA


def test_train_flags_set_the_config(tmp_path: Path) -> None:
    """`gradsep train`'s optional flags reach TrainConfig (None keeps the config's default)."""
    import argparse

    from gradsep.training.commands import _add_train_arguments, config_from_args
    from gradsep.training.train import TrainConfig

    parser = argparse.ArgumentParser()
    _add_train_arguments(parser)
    base = ["--data", str(tmp_path), "--layer", "indirect", "-o", str(tmp_path / "run")]
    default = config_from_args(parser.parse_args(base))
    assert default.prior_alpha == TrainConfig.prior_alpha and default.alpha == TrainConfig.alpha
    cfg = config_from_args(parser.parse_args([*base, "--prior-alpha", "0.45", "--data-weight", "2", "--lr", "3e-4"]))
    assert (cfg.prior_alpha, cfg.alpha, cfg.lr, cfg.layer) == (0.45, 2.0, 3e-4, "indirect")


def test_train_command_reports_bad_data_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = cli_main(["train", "--data", str(tmp_path / "nope"), "--layer", "direct", "-o", str(tmp_path / "run")])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no manifest.json" in err[0]


def test_python_dash_m_training_is_gradsep_train(tmp_path: Path) -> None:
    """`torchrun -m gradsep.training ARGS` (each worker runs the package's __main__) takes `gradsep train`'s flags
    and reports bad input the same way, without the command-line package."""
    cmd = [sys.executable, "-m", "gradsep.training", "--data", str(tmp_path / "nope"), "--layer", "direct",
           "-o", str(tmp_path / "run")]
    proc = subprocess.run(cmd, env={**os.environ, "PYTHONPATH": str(REPO)}, cwd=REPO, capture_output=True,
                          text=True, timeout=120, check=False)
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1 and "no manifest.json" in err[0], proc.stderr


# ------------------------------------------------------------------------------------------------ torchrun


@pytest.mark.train
@pytest.mark.slow
def test_torchrun_two_process_gloo(tiny_dataset: Path, tmp_path: Path) -> None:
    """`torchrun --nproc-per-node 2 -m gradsep train ...` on CPU: gloo DDP, a DistributedSampler, one folder."""
    out = tmp_path / "ddp"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "gradsep", "train", "--data", str(tiny_dataset), "--layer", "direct", "--epochs", "1",
           "--patch", "32", "--batch", "2", "-o", str(out)]
    proc = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=240, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    epochs = _epochs(out)
    # 5 training frames × 8 patches = 40 patches, 20 per process, 10 batches of 2 each
    assert len(epochs) == 1 and epochs[0]["step"] == 10
    assert "2 process(es)" in proc.stderr
    state = torch.load(out / "checkpoints" / "last.pt", weights_only=True)
    assert not any(k.startswith("module.") for k in state["model"])   # saved unwrapped: export can read it


# ------------------------------------------------------------------------------------------- a failed start


def _tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def test_a_start_that_fails_leaves_no_run_folder(tmp_path: Path, tiny_dataset: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """The tiny dataset's 64x48 frames are smaller than the default 128-pixel patch: refused at once, and the
    run folder it would have made is not left behind (it would refuse the corrected retry as a different run)."""
    run = tmp_path / "run"
    rc = cli_main(["train", "--data", str(tiny_dataset), "--layer", "direct", "-o", str(run)])
    assert rc == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(errors) == 1 and "no usable training frames" in errors[0] and "patch 128" in errors[0], errors
    assert not run.exists()


def test_a_failed_start_in_an_existing_folder_removes_only_what_it_made(tmp_path: Path,
                                                                        tiny_dataset: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("the user's own file")
    with pytest.raises(DatasetError, match="no usable training frames"):
        train(tiny_config(tiny_dataset, run, patch=128), quiet=True)
    assert _tree(run) == ["notes.txt"]


@pytest.mark.train
def test_the_corrected_retry_after_a_failed_start_just_works(tmp_path: Path, tiny_dataset: Path) -> None:
    run = tmp_path / "run"
    with pytest.raises(DatasetError, match="no usable training frames"):
        train(tiny_config(tiny_dataset, run, patch=128), quiet=True)
    progress = train(tiny_config(tiny_dataset, run, patch=32, epochs=1), quiet=True)
    assert progress.epoch == 1 and (run / "config.json").is_file()
    # a refused resume of that run keeps the run exactly as it was
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*")}
    with pytest.raises(TrainingError, match="different run"):
        train(tiny_config(tiny_dataset, run, patch=32, epochs=2, seed=7), quiet=True)
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*")} == before
