"""What an evaluation run produces, as the report reads it: one :class:`SceneRun` per scene and the
:class:`Evaluation` (rows, skipped methods, notes, outputs), plus where the timings were taken.

Its own module so that evaluation/run.py (which fills these in and then writes the report) and
evaluation/report.py (which reads them) do not import each other.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.evaluation.config import EvalConfig, SceneEntry

__all__ = ["Evaluation", "SceneRun", "machine_summary", "row_seconds"]


@dataclass
class SceneRun:
    """What the report needs about one evaluated scene."""

    entry: SceneEntry
    width: int
    height: int
    max_depth: int
    layers: tuple[str, ...]
    reference: np.ndarray  # (H, W, 3): the mean of the two references
    reference_spp: int = 0  # of each of the two references, in full passes
    reference_region: list[int] | None = None  # x, y, width, height of the region passes' rectangle, if any
    region_spp: int = 0  # extra spp of each reference inside that rectangle
    floor: dict[str, float] = field(default_factory=dict)  # layer -> reference floor (model.metrics)
    smallest: float = math.nan  # the smallest ranked RelMSE of the scene
    capped: bool = False  # the floor criterion was not met (see cap_reason)
    cap_reason: str = ""  # what stopped the references: the spp cap or the time budget
    reference_seconds: float = 0.0
    crop_images: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Evaluation:
    """The outcome of :func:`run_evaluation`: rows plus what the report says about how they were made."""

    config: EvalConfig
    rows: list[dict[str, Any]]
    scenes: list[SceneRun]
    skipped: dict[str, list[str]]  # method -> why it was skipped (missing model files, missing code)
    models: dict[str, str]  # model file (relative to the models folder) -> sha256
    notes: list[str]
    computed: dict[str, int]  # what this run computed rather than took from the cache
    outputs: dict[str, Path] = field(default_factory=dict)


def row_seconds(row: Mapping[str, Any]) -> float:
    """The time a row stands for: its equal-time budget when its metrics were interpolated to it
    (evaluation.scores.interpolated_scores), else its measured total; a multi-seed row (evaluation.scores.seed_mean):
    the mean over its seeds of this."""
    if int(row.get("seeds") or 1) > 1:
        return float(row["total_seconds"])
    if row.get("time_interpolated") and row.get("target_seconds"):
        return float(row["target_seconds"])
    return float(row["total_seconds"])


def machine_summary() -> str:
    """``CPU model, N logical cores`` (+ GPU variant when Mitsuba runs on CUDA): where a timing was taken."""
    from gradsep.model.environment import cpu_model

    return f"{cpu_model()}, {os.cpu_count()} logical cores"
