"""A row's scores against the scene's reference pair: RelMSE (total and per layer, the product estimator), SSIM, PSNR
and HDR-FLIP against the pair's mean (model/metrics.py); an equal-time row's interpolated to its budget between two
tries; a multi-seed row's mean over its seeds."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.evaluation.methods import BracketOutput, MethodSpec
from gradsep.evaluation.references import ReferencePair
from gradsep.evaluation.results import row_seconds
from gradsep.evaluation.timesearch import interpolate_at
from gradsep.model.policy import SEPARATED_LAYERS

__all__ = ["LOG_INTERPOLATED", "Output", "SEED_MEAN_METRICS", "image_scores", "interpolated_scores", "seed_mean"]

@dataclass
class Output:
    """One method's output on one (scene, spp): the row without scores, its images, its cache key hash."""

    spec: MethodSpec
    spp: int
    row: dict[str, Any]
    image: np.ndarray
    layers: dict[str, np.ndarray]
    tag: str
    bracket: list[BracketOutput] = field(default_factory=list)  # see MethodOutput.bracket
    #: The same equal-time row rendered with the other ``--time-seeds`` seeds (each its own time search), or the
    #: same fixed-spp method on the other ``--frame-seeds`` frames; the row's metrics are the mean over this
    #: output and these (:func:`seed_mean`).
    replicas: list[Output] = field(default_factory=list)

    def interpolation(self) -> tuple[float, BracketOutput, BracketOutput] | None:
        """(budget, too-fast try, too-slow try) when this row's metrics are interpolated to its budget, else None."""
        target = self.row.get("target_seconds")
        if len(self.bracket) != 2 or not target:
            return None
        return float(target), self.bracket[0], self.bracket[1]


#: Metrics interpolated in log value (errors: a power of time is a line in log-log); the others (SSIM, PSNR,
#: already a logarithm) linearly in value. Both in log time.
LOG_INTERPOLATED = ("relmse", "flip", *(f"relmse_{layer}" for layer in SEPARATED_LAYERS))


def image_scores(image: np.ndarray, layers: dict[str, np.ndarray], pair: ReferencePair) -> dict[str, Any]:
    """RelMSE (total and per layer) by the product estimator; SSIM, PSNR and FLIP against the pair's mean."""
    from gradsep.model.metrics import flip, psnr, relmse_unbiased, ssim

    mean = pair.mean()
    scores: dict[str, Any] = {"relmse": relmse_unbiased(image, pair.first["total"], pair.second["total"]),
                              "ssim": ssim(image, mean), "psnr": psnr(image, mean), "flip": flip(image, mean)}
    for layer in SEPARATED_LAYERS:
        have = layer in layers and layer in pair.first
        scores[f"relmse_{layer}"] = (relmse_unbiased(layers[layer], pair.first[layer], pair.second[layer])
                                     if have else None)
    return scores


def interpolated_scores(target: float, bracket: list[BracketOutput], pair: ReferencePair) -> dict[str, Any]:
    """An equal-time row that no spp could bring within the tolerance (one sample costs more than 5 % of the
    budget, or the timings were too noisy): every metric of its two bracketing tries, interpolated to the budget
    ``target`` in log time (errors in log value, :data:`LOG_INTERPOLATED`). ``time_interpolated`` says between
    what it was interpolated."""
    low, high = bracket
    sides = [image_scores(b.image, b.layers, pair) for b in bracket]
    scores: dict[str, Any] = {}
    for name, v0 in sides[0].items():
        v1 = sides[1][name]
        if v0 is None or v1 is None or not (math.isfinite(v0) and math.isfinite(v1)):
            scores[name] = v0 if abs(target - low.total_seconds) <= abs(target - high.total_seconds) else v1
            continue
        scores[name] = interpolate_at(target, (low.total_seconds, float(v0)), (high.total_seconds, float(v1)),
                                      log_value=name in LOG_INTERPOLATED)
    scores["time_interpolated"] = (f"{low.spp} spp ({low.total_seconds:.3g} s, RelMSE {sides[0]['relmse']:.4g}) and "
                                   f"{high.spp} spp ({high.total_seconds:.3g} s, RelMSE {sides[1]['relmse']:.4g})")
    return scores


#: Metrics a multi-seed row averages (the others are the first seed's, with the per-seed values beside them).
SEED_MEAN_METRICS = ("relmse", "ssim", "psnr", "flip", *(f"relmse_{layer}" for layer in SEPARATED_LAYERS))


def seed_mean(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One row from the same row rendered with several seeds (an equal-time row's ``--time-seeds``, each its own
    time search; a fixed-spp row's ``--frame-seeds``, each its own G-PT frame; every row already scored): every
    metric of :data:`SEED_MEAN_METRICS` is the mean over the seeds (None when
    a seed has none), the time the mean of the seeds' times (:func:`row_seconds`: the budget for a seed
    interpolated to it), ``method_spp`` the seeds' median. ``seeds``, ``seed_relmse``, ``seed_spp`` and
    ``seed_seconds`` keep the seeds' own values, ``relmse_stderr`` the standard error of the mean RelMSE (sample
    standard deviation / √seeds). A seed interpolated to the budget is named in ``time_interpolated``. The planned
    row (``gpt-auto``) also keeps each seed's ``seed_plan``, ``seed_predicted_relmse`` and ``seed_predicted_note``;
    its ``plan`` is the seeds' plans (``primal/all`` where they differ), its ``predicted_relmse`` their mean (None
    when a seed has none), like its RelMSE."""
    import statistics

    first = rows[0]
    out = dict(first)
    for name in SEED_MEAN_METRICS:
        values = [r.get(name) for r in rows]
        out[name] = (float(np.mean([float(v) for v in values]))
                     if all(v is not None and math.isfinite(float(v)) for v in values) else None)
    seconds = [row_seconds(r) for r in rows]
    relmse = [float(r["relmse"]) for r in rows]
    out.update({"seeds": len(rows), "seed_relmse": relmse, "seed_spp": [int(r["method_spp"]) for r in rows],
                "seed_seconds": seconds, "total_seconds": float(np.mean(seconds)),
                "render_seconds": float(np.mean([float(r["render_seconds"]) for r in rows])),
                "reconstruct_seconds": float(np.mean([float(r["reconstruct_seconds"]) for r in rows])),
                "method_spp": int(statistics.median_low([int(r["method_spp"]) for r in rows])),
                "relmse_stderr": statistics.stdev(relmse) / math.sqrt(len(rows)) if len(rows) > 1 else 0.0})
    if any("plan" in r for r in rows):  # the planned row: each seed's own plan and prediction
        predicted = [r.get("predicted_relmse") for r in rows]
        out.update({"seed_plan": [r.get("plan") for r in rows], "seed_predicted_relmse": predicted,
                    "seed_predicted_note": [r.get("predicted_note") for r in rows],
                    "plan": "/".join(dict.fromkeys(str(r.get("plan")) for r in rows)),
                    "predicted_relmse": (float(np.mean(predicted)) if all(p is not None for p in predicted)
                                         else None)})
    interpolated = [f"seed {k}: {r['time_interpolated']}" for k, r in enumerate(rows) if r.get("time_interpolated")]
    out.pop("time_interpolated", None)
    out.pop("time_bracket", None)
    if interpolated:
        out["time_interpolated"] = "; ".join(interpolated)
    return out
