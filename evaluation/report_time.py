"""report.md's equal-time sections: the equal-time table (G-PT + reconstruction against Mitsuba path, path + OIDN
and separated path + OIDN, each row's time search and misses) and the planner's choice (the ``gpt-auto`` row's plan,
predicted against measured error, against the best fixed pipeline)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from gradsep.evaluation.report_cells import bold_best, by_method, fmt, spp_cell, stderr_cell
from gradsep.evaluation.results import row_seconds

if TYPE_CHECKING:
    from gradsep.evaluation.results import Evaluation

__all__ = ["EQUAL_TIME", "FIXED_EQUAL_TIME", "GPT_EQUAL_TIME", "PREDICTION_FACTOR", "PlannedFrame", "equal_time",
           "over_budget", "planned_frames", "planner_choice", "time_interpolations", "time_misses"]


EQUAL_TIME: tuple[tuple[str, str], ...] = (("gpt-oidn-l1", "G-PT+oidn-l1"), ("gpt-auto", "G-PT auto"), ("path", "path"),
                                           ("path-oidn", "path+OIDN"), ("path-sep-oidn", "sep. path+OIDN/layer"))
#: The equal-time rows that are G-PT methods themselves (counted in *best G-PT*), not baselines.
GPT_EQUAL_TIME: frozenset[str] = frozenset({"gpt-oidn-l1", "gpt-auto"})
#: An equal-time row is flagged when its measured total misses its budget by more than this.
TIME_TOLERANCE = 0.05


def over_budget(row: Mapping[str, Any]) -> bool:
    """An equal-time row that took more than TIME_TOLERANCE over its budget (:func:`row_seconds`: an interpolated
    row stands for its budget): it does not count as a G-PT result at equal time (*best G-PT*, the equal-time
    targets), as it had more time than the rows it would be compared with. The planned row, not searched, is the
    one this happens to (a checkpoint or a pass running past its deadline)."""
    target = row.get("target_seconds")
    return bool(target) and float(target) > 0 and row_seconds(row) > float(target) * (1 + TIME_TOLERANCE)


def time_misses(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Every equal-time row whose measured total is outside ±5 % of its budget and whose metrics were not
    interpolated to the budget (:func:`time_interpolations`), as sentences."""
    out = []
    for r in rows:
        target = r.get("target_seconds")
        if target in (None, "") or not float(target) > 0 or r.get("time_interpolated"):
            continue
        miss = float(r["total_seconds"]) / float(target) - 1.0
        if abs(miss) > TIME_TOLERANCE:
            reason = r.get("time_note") or "no reason recorded"
            tries = r.get("attempts", "?")
            out.append(f"{r['scene']}, {r['spp']} spp, {r['method']}: {float(r['total_seconds']):.3g} s for a "
                       f"{float(target):.3g} s budget ({miss:+.0%}; {tries} {'try' if tries == 1 else 'tries'}, "
                       f"kept {r['method_spp']} spp): {reason}")
    return out


def time_interpolations(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Every equal-time row whose metrics are interpolated to its budget between two tries, as sentences."""
    return [f"{r['scene']}, {r['spp']} spp, {r['method']}: budget {float(r['target_seconds']):.3g} s, between "
            f"{r['time_interpolated']} ({r.get('time_note') or 'no reason recorded'})"
            for r in rows if r.get("target_seconds") and r.get("time_interpolated")]


def _seeds_sentence(rows: Sequence[Mapping[str, Any]]) -> str:
    """What the equal-time cells are over: one seed, or ``--time-seeds`` N."""
    seeds = sorted({int(r.get("seeds") or 1) for r in rows if r.get("target_seconds")})
    if seeds in ([], [1]):
        return ("Each equal-time cell is one seed: rerunning the same code can move a row's RelMSE by tens of "
                "percent (`--time-seeds N` averages N). ")
    return (f"Each equal-time cell is the mean over {'/'.join(map(str, seeds))} seeds (`--time-seeds`), every seed "
            "with its own time search and render at the budget; its spp is the seeds' median (* when a seed was "
            "interpolated to the budget), its time their mean, and ±SE the standard error of the mean RelMSE "
            "(results.json keeps each seed's `seed_relmse`, `seed_spp`, `seed_seconds`); the budget row is the "
            "G-PT frame's one seed. ")


def _search_method(rows: Sequence[Mapping[str, Any]]) -> str:
    """How the rows' equal-time spp were found (each row records it; cached rows may predate the search)."""
    methods = sorted({str(r.get("time_search") or "bisected") for r in rows
                      if r.get("target_seconds") and "plan" not in r})  # the planned row is not searched
    return " / ".join(methods) or "interpolated on the measured time curve"


def equal_time(evaluation: Evaluation) -> list[str]:
    """The section "Equal time": how the rows were timed, one table row per scene and G-PT spp, the misses."""
    lines = _equal_time_intro(evaluation.rows)
    any_row = False
    for scene in evaluation.scenes:
        scene_rows = [r for r in evaluation.rows if r["scene"] == scene.entry.name]
        for spp in sorted({int(r["spp"]) for r in scene_rows}):
            line = _equal_time_row(scene.entry.name, spp, by_method(scene_rows, spp))
            if line is not None:
                any_row = True
                lines.append(line)
    if not any_row:
        lines.append("| (equal-time methods not evaluated) |" + " |" * (4 + len(EQUAL_TIME)))
    return [*lines, *_equal_time_misses(evaluation.rows), ""]


def _equal_time_intro(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    return ["## Equal time: G-PT + reconstruction against Mitsuba path, path + OIDN and separated path + OIDN", "",
             f"Each equal-time method's spp is {_search_method(rows)} until its measured total time "
             "(render, feature pass and denoising) is within ±5 % of the time of the G-PT render + the "
             "reconstruction by the product's default method for a G-PT frame (the first of "
             "the methods table's default preference that ran; ours, then L1, when none did; column *budget*): a line "
             "time = overhead + per-spp cost is fitted to the renders already measured and solved for the budget "
             "(a secant step; bisection of the closest bracket when the line points at a tried spp), tries under "
             "2 s or off the line's prediction by over 15 % are timed three times and their median used, at most "
             "8 tries per row. The times shown are the measured ones. "
             "The G-PT render of a method that integrates only the direct layer's gradients (`oidn-l1`; "
             "results.csv `gradients` = direct) is `gradsep render --gradients direct` with the same seed: its "
             "direct layer and indirect base equal those of the full render, its offsets stop after the direct "
             "layer's vertices, and its render time is that mode's. "
             "path + OIDN gets its albedo and normal from a separate feature pass (Mitsuba `aov`, spp in results.csv "
             "`feature_spp`) whose time is counted; separated path + OIDN is the renderer's primal-only mode "
             "(direct and indirect apart, first-hit features, no gradients) with OIDN on each layer. "
             "Cells: spp / seconds / RelMSE; lowest RelMSE per row in bold (budget method and equal-time "
             "methods). *best G-PT* is the lowest RelMSE of any reconstruction of the same G-PT frame, whatever "
             "its time, and of the G-PT rows at equal time not over their budget by more than 5 %: G-PT+oidn-l1, "
             "our renderer in `--gradients direct` mode (offsets `alternate`: one offset per axis, both MIS "
             "techniques per pixel pair on half the samples) at the spp the budget buys, reconstructed with "
             "`oidn-l1`, found like the baselines' spp; and G-PT auto, `gradsep render --seconds T --gradients "
             "auto` in process, one render to a deadline of the budget with the measured reconstruction time kept "
             "free (its checkpoint, which chooses the plan, charged), starting from each plan's pass costs and "
             "the reconstruction's rate measured beforehand, untimed, like the searched rows' cost lines, then the "
             "default method the frame names: not searched, so its time is what the planner's deadline gave (see "
             "The planner's choice). "
             + _seeds_sentence(rows), "",
             "| Scene | G-PT spp | budget | budget s | budget RelMSE | best G-PT | "
             + " | ".join(label for _, label in EQUAL_TIME) + " |",
             "|---|---:|---|---:|---:|---|" + "---:|" * len(EQUAL_TIME)]


def _equal_time_row(scene: str, spp: int, table: dict[str, Mapping[str, Any]]) -> str | None:
    """The table row of one scene and G-PT spp (None: no equal-time method ran there)."""
    present = [table[m] for m, _ in EQUAL_TIME if m in table]
    if not present:
        return None
    anchor = present[0]
    budget = anchor.get("budget_method") or ""
    values = {m: (float(table[m]["relmse"]) if m in table else None) for m in (budget, *dict(EQUAL_TIME))}
    cells = bold_best(values, higher=False)
    parts = [f"{spp_cell(table[m])} / {fmt(row_seconds(table[m]), 3)} s / {cells[m]}{stderr_cell(table[m])}"
             if m in table else "–" for m, _ in EQUAL_TIME]
    baselines = set(dict(EQUAL_TIME)) - GPT_EQUAL_TIME
    gpt = {m: float(r["relmse"]) for m, r in table.items()
           if m not in baselines and m not in ("gpt-primal", "path") and r.get("relmse") is not None
           and not over_budget(r)}
    best = min(gpt, key=gpt.__getitem__) if gpt else None
    best_cell = f"{fmt(gpt[best], 4)} ({best})" if best else "–"
    return (f"| {scene} | {spp} | {budget or '–'} | {fmt(anchor.get('target_seconds'), 3)} | "
            f"{cells.get(budget, '–')} | {best_cell} | " + " | ".join(parts) + " |")


def _equal_time_misses(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The rows outside the tolerance, and those interpolated to their budget."""
    misses = time_misses(rows)
    lines = ["", "Equal-time rows outside ±5 % of their budget: " + ("none." if not misses else ""), ""]
    lines += [f"- {m}" for m in misses]
    interpolated = time_interpolations(rows)
    if interpolated:
        lines += ["", "Rows marked * (spp `a–b*`): no spp landed within ±5 % of the budget (one sample costs more "
                  "than 5 % of it, or the timings were too noisy), so every metric of the row is interpolated to the "
                  "budget between the slowest too-fast and the fastest too-slow try, in log time (RelMSE and FLIP "
                  "in log value: an error falling as a power of time is a line there; SSIM and PSNR linearly); "
                  "the time shown is the budget. The issue allows this for rows the spp cannot resolve. Crops show "
                  "the try closer to the budget.", ""]
        lines += [f"- {m}" for m in interpolated]
    return lines


#: The planned row's prediction counts as right within this factor of the measured RelMSE.
PREDICTION_FACTOR = 1.5
#: The fixed pipelines the planned row is compared with at equal time (the budget method's row, at the budget's
#: own time, joins them): G-PT direct/alternate + oidn-l1, path + OIDN on the sum, separated path + OIDN per layer.
FIXED_EQUAL_TIME: tuple[str, ...] = ("gpt-oidn-l1", "path-oidn", "path-sep-oidn")


@dataclass(frozen=True)
class PlannedFrame:
    """One frame of a ``gpt-auto`` row (one per seed with ``--time-seeds``): what the planner chose and predicted."""

    label: str  # "" for a single-seed row, else "seed k"
    plan: str | None
    predicted: float | None  # the chosen plan's predicted RelMSE; None: no checkpoint ran (``note`` says why)
    note: str | None
    measured: float
    spp: int
    seconds: float

    @property
    def ratio(self) -> float | None:
        """predicted / measured, or None where either is missing or the measured RelMSE is not positive."""
        if self.predicted is None or not self.measured > 0:
            return None
        return float(self.predicted) / self.measured


def planned_frames(row: Mapping[str, Any]) -> list[PlannedFrame]:
    """The frames of a ``gpt-auto`` row: each seed's of a multi-seed row (evaluation.scores.seed_mean keeps them),
    else the row's own."""
    if int(row.get("seeds") or 1) > 1 and isinstance(row.get("seed_plan"), list):
        n = len(row["seed_plan"])
        notes = row.get("seed_predicted_note") or [None] * n
        return [PlannedFrame(f"seed {k}", row["seed_plan"][k], row["seed_predicted_relmse"][k], notes[k],
                             float(row["seed_relmse"][k]), int(row["seed_spp"][k]), float(row["seed_seconds"][k]))
                for k in range(n)]
    return [PlannedFrame("", row.get("plan"), row.get("predicted_relmse"), row.get("predicted_note"),
                         float(row["relmse"]), int(row["method_spp"]), row_seconds(row))]


def planner_choice(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The section "The planner's choice": per scene and G-PT spp (budget), the plan the ``gpt-auto`` row chose,
    each judged plan's and the chosen plan's predicted RelMSE against the measured one (within PREDICTION_FACTOR
    or not), and the row against the best fixed pipeline at equal time; a summary of both, and why a row has no
    prediction."""
    planned = [r for r in rows if r["method"] == "gpt-auto"]
    lines = ["## The planner's choice", ""]
    if not planned:
        return [*lines, "The planned row (`gpt-auto`) was not evaluated (see skipped methods).", ""]
    lines += _PLANNER_INTRO
    frames: list[PlannedFrame] = []
    missing: list[str] = []
    ratios: list[float] = []
    for r in planned:
        lines += _planner_rows(r, rows, frames, missing, ratios)
    return [*lines, *_planner_summary(frames, ratios), *_planner_missing(missing), ""]


#: The planner's section's explanation and table header.
_PLANNER_INTRO: list[str] = [
              "`gpt-auto` is `gradsep render --seconds T --gradients auto` at equal time (T the budget of the "
              "Equal time section, its checkpoint charged), reconstructed with the default method the frame names. "
              "The frame starts as `direct-alternate`; at a checkpoint its halves predict, from the frame alone, "
              "each plan's RelMSE after reconstruction at the samples the rest of the budget buys it, and the rest "
              "is `primal` only where that is clearly lower. *predicted* is the frame's own "
              "estimate from its two halves (renderer/check.py) where it fits the budget, else the checkpoint's "
              "prediction for the chosen plan. *predicted / measured* compares it with the RelMSE measured "
              "against the references (within "
              f"{PREDICTION_FACTOR:g}× counts as right); *best fixed* is the lowest RelMSE of the fixed pipelines at "
              "equal time (the budget method's row on the G-PT frame, "
              + ", ".join(f"`{m}`" for m in FIXED_EQUAL_TIME) + ") and *auto / best* the planned row against it "
              "(a multi-seed row by its mean). A frame without a prediction had no checkpoint: it is "
              "`direct-alternate` throughout (listed below with why). The plans' predictions and plan layers are "
              "those of the row's first seed.", "",
              "| Scene | G-PT spp | budget s | auto s | plan | plan layers | spp | checkpoint s | plans' predicted "
              "RelMSE | predicted | measured | predicted / measured | within | best fixed | auto / best |",
              "|---|---:|---:|---:|---|---|---:|---:|---|---:|---:|---:|---|---|---:|"]


def _planner_rows(r: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], frames: list[PlannedFrame],
                  missing: list[str], ratios: list[float]) -> list[str]:
    """The table rows of one ``gpt-auto`` row (one per frame); its frames, its frames without a prediction and its
    ratio to the best fixed pipeline are added to ``frames``, ``missing`` and ``ratios``."""
    lines = []
    table = {str(o["method"]): o for o in rows if o["scene"] == r["scene"] and int(o["spp"]) == int(r["spp"])}
    fixed = {m: float(table[m]["relmse"]) for m in (r.get("budget_method"), *FIXED_EQUAL_TIME)
             if m in table and table[m].get("relmse") is not None}
    best = min(fixed, key=fixed.__getitem__) if fixed else None
    best_cells = "– | –"
    if best is not None and fixed[best] > 0:
        ratios.append(float(r["relmse"]) / fixed[best])
        best_cells = f"{fmt(fixed[best])} ({best}) | {ratios[-1]:.3f}×"
    candidates = ", ".join(f"{name} {fmt(v)}" for name, v in (r.get("plan_candidates") or {}).items()) or "–"
    for f in planned_frames(r):
        frames.append(f)
        scene = f"{r['scene']}{f' ({f.label})' if f.label else ''}"
        ratio = f.ratio
        if f.predicted is None:
            verdict = "no prediction"
            missing.append(f"{scene}, {r['spp']} spp: {f.note or 'no reason recorded'}")
        elif ratio is None:
            verdict = "**no** (measured ≤ 0)"
        else:
            verdict = "yes" if _within(ratio) else "**no**"
        lines.append(f"| {scene} | {r['spp']} | {fmt(r.get('target_seconds'), 3)} | {fmt(f.seconds, 3)} | "
                     f"{f.plan or '–'} | {r.get('plan_layers') or '–'} | {f.spp} | "
                     f"{fmt(r.get('pilot_seconds'), 3)} | {candidates} | {fmt(f.predicted)} | "
                     f"{fmt(f.measured)} | {'–' if ratio is None else f'{ratio:.2f}'} | {verdict} | "
                     f"{best_cells} |")
    return lines


def _planner_summary(frames: list[PlannedFrame], ratios: list[float]) -> list[str]:
    """How often the prediction was right, and the planned rows against the best fixed pipeline."""
    predicted = [f for f in frames if f.predicted is not None]
    within = sum(f.ratio is not None and _within(f.ratio) for f in predicted)
    lines = ["", f"The chosen plan's predicted RelMSE is within {PREDICTION_FACTOR:g}× of the measured one on "
             f"{within} of {len(predicted)} frames with a prediction"
             + (f" ({within / len(predicted):.0%})" if predicted else "")
             + f"; {len(frames) - len(predicted)} of {len(frames)} frames have none."]
    positive = [x for x in ratios if x > 0]  # a measured RelMSE can be <= 0 (below the references' resolution)
    if positive:
        geo = math.exp(sum(math.log(x) for x in positive) / len(positive))
        lines.append(f"Against the best fixed pipeline at equal time: at most 1.05× on "
                     f"{sum(x <= 1.05 for x in ratios)} of {len(ratios)} rows; geometric mean of auto / best "
                     f"{fmt(geo, 3)}× (over the {len(positive)} rows with a positive RelMSE).")
    return lines


def _planner_missing(missing: list[str]) -> list[str]:
    return ["", "Frames without a prediction:", "", *(f"- {m}" for m in missing)] if missing else []


def _within(ratio: float) -> bool:
    return 1 / PREDICTION_FACTOR <= ratio <= PREDICTION_FACTOR
