"""A training run folder's record: the code version, atomic writes, ``log.jsonl`` and the ``losses.png`` curves
(training/train.py writes ``config.json`` and the checkpoints through them)."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
from pathlib import Path
from typing import Any

import torch


def code_version() -> str:
    """gradsep version plus the git commit of this checkout when there is one (for metadata)."""
    from gradsep.model import __version__

    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).resolve().parent, timeout=5, check=False).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return f"{__version__}+{commit}" if commit else __version__


def atomic_torch_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def append_log(run: Path, record: dict[str, Any]) -> None:
    with open(run / "log.jsonl", "a", encoding="utf-8") as fh:
        fh.write(json.dumps(record) + "\n")


def read_log(run: Path) -> list[dict[str, Any]]:
    path = run / "log.jsonl"
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        with contextlib.suppress(json.JSONDecodeError):  # a kill may cut the last line
            out.append(json.loads(line))
    return out


def plot_curves(run: Path) -> Path | None:
    """RUN_DIR/losses.png: each loss term against the step, per-step training values and per-epoch means."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state, safe in any process

    records = read_log(run)
    steps = {r["step"]: r for r in records if r.get("kind") == "step"}  # last write wins after a resume
    epochs = {r["epoch"]: r for r in records if r.get("kind") == "epoch"}
    if not steps and not epochs:
        return None
    fig = Figure(figsize=(10, 7), layout="constrained")
    axes = fig.subplots(2, 2)
    for ax, key, title in zip(axes.flat, ("data", "grad", "first", "gbranch"),
                              ("L_data", "L_grad", "L_1st", "G-branch L_1st"), strict=True):
        if key != "gbranch" and steps:
            xs = sorted(steps)
            ax.plot(xs, [steps[s][key] for s in xs], color="0.75", lw=0.8, label="train (step)")
        ep = [epochs[e] for e in sorted(epochs)]
        if key == "gbranch":
            ax.plot([r["step"] for r in ep], [r["gbranch"] for r in ep], "o-", label="train (epoch)")
        else:
            ax.plot([r["step"] for r in ep], [r["train"][key] for r in ep], "o-", label="train (epoch)")
            val = [(r["step"], r["val"][key]) for r in ep if r.get("val")]
            if val:
                ax.plot(*zip(*val, strict=True), "s--", label="validation")
        ax.set_title(title)
        ax.set_xlabel("step")
        ax.set_yscale("log")
        ax.legend(fontsize=8)
    fig.suptitle(f"{run.name}: losses")
    out = run / "losses.png"
    tmp = run / "losses.tmp.png"
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, out)
    return out
