"""The evaluation's written outputs: results.csv / results.json, the plots, and report.md.

report.md reads top to bottom as: how it was made (command, machine, software, settings, models, skipped
methods), the paper's Table 1 (input, L1, GradNet-style, ours) and Fig. 7 ablation, the equal-time comparison
with Mitsuba ``path`` and OIDN, the planner's choice (the ``gpt-auto`` row's plan, predicted against measured
error), where ours loses, and the full RelMSE-by-spp tables. Nothing in it is written by
hand: every sentence that compares methods is computed from the rows, so a rerun with other models says what
is true for those.
"""

from __future__ import annotations

import csv
import datetime
import io
import json
import math
import os
import platform
import shlex
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gradsep.evaluation.cache import slug
from gradsep.evaluation.config import EvalSettings, crop_methods
from gradsep.evaluation.methods import ABLATION_VARIANTS, evaluated_methods
from gradsep.evaluation.plots import CropPanels, plot_crops, plot_error_vs_time
from gradsep.evaluation.references import REFERENCE_SAMPLER
from gradsep.evaluation.report_cells import bold_best, by_method, fmt, stderr_cell
from gradsep.evaluation.report_time import GPT_EQUAL_TIME, equal_time, over_budget, planner_choice
from gradsep.evaluation.results import machine_summary, row_seconds
from gradsep.model.exr_write import write_bytes_atomic
from gradsep.model.policy import DEFAULT_ALPHA, MODELS_ENV

if TYPE_CHECKING:
    from gradsep.evaluation.config import EvalConfig
    from gradsep.evaluation.results import Evaluation

__all__ = ["CSV_COLUMNS", "losses_of_ours", "write_outputs"]

CSV_COLUMNS: tuple[str, ...] = (
    "scene", "method", "spp", "method_spp", "width", "height", "render_seconds", "reconstruct_seconds",
    "total_seconds", "relmse", "ssim", "psnr", "flip", "relmse_direct", "relmse_indirect", "target_seconds",
    "budget_method", "attempts", "feature_spp", "time_note", "gradients", "time_interpolated", "seeds",
    "relmse_stderr", "plan", "predicted_relmse",
)
def labels() -> dict[str, str]:
    """Every evaluated method's label (evaluation.methods, which reads the table of methods)."""
    return {m.name: m.label for m in evaluated_methods()}


def table1() -> tuple[tuple[str, str], ...]:
    """The rows of Table 1, (method, short label): the methods the crops show, in their order."""
    short = {m.name: m.short or m.label for m in evaluated_methods()}
    return tuple((name, short.get(name, name)) for name in crop_methods())


#: (metric, header, higher is better)
TABLE1_METRICS: tuple[tuple[str, str, bool], ...] = (("ssim", "SSIM ↑", True), ("relmse", "RelMSE ↓", False),
                                                     ("flip", "FLIP ↓", False), ("psnr", "PSNR dB ↑", True))
PAPER_FIG7 = {"combined-noattn": 0.0262, "separated-noattn": 0.0208, "combined-attn": 0.0235,
              "separated-attn": 0.0177}


# ------------------------------------------------------------------------------------------------- files


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "inf" if math.isinf(value) else f"{value:.6g}"
    return str(value)


def write_csv(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """One row per (scene, method, spp), the columns of :data:`CSV_COLUMNS`; empty cells where n/a."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for row in rows:
        writer.writerow([_cell(row.get(c)) for c in CSV_COLUMNS])
    write_bytes_atomic(path, buffer.getvalue().encode())
    return path


def write_outputs(evaluation: Evaluation) -> dict[str, Path]:
    """Write results.csv, results.json, plots/, crops/ and report.md; return their paths."""
    out = evaluation.config.output
    paths: dict[str, Path] = {"csv": write_csv(evaluation.rows, out / "results.csv")}
    for scene in evaluation.scenes:
        name = scene.entry.name
        scene_rows = [r for r in evaluation.rows if r["scene"] == name]
        if scene_rows:
            paths[f"plot:{name}"] = plot_error_vs_time(name, scene_rows, labels(), out / "plots" / f"{slug(name)}.png",
                                                       scene.floor.get("total"))
        table = by_method(scene_rows, evaluation.config.crop_spp)
        metrics = {m: float(r["relmse"]) for m, r in table.items()}
        crops = CropPanels(crop_methods(), _crop_labels(), metrics)
        paths[f"crop:{name}"] = plot_crops(name, scene.reference, scene.crop_images, crops, evaluation.config.crop_spp,
                                           out / "crops" / f"{slug(name)}.png")
    paths["json"] = out / "results.json"
    write_bytes_atomic(paths["json"], json.dumps(_summary(evaluation), indent=1, default=str).encode())
    paths["report"] = out / "report.md"
    write_bytes_atomic(paths["report"], render_report(evaluation).encode())
    return paths


def _crop_labels() -> dict[str, str]:
    return {**dict(table1()), "reference": "Reference (mean of 2)"}


def _summary(evaluation: Evaluation) -> dict[str, Any]:
    c = evaluation.config
    return {
        "command": invocation(), "reproduce": reproduce_command(c), "created": _now(), "machine": machine(),
        "software": software(),
        "config": {"scenes": [s.entry.spec for s in evaluation.scenes], "spp": list(c.spp), "size": [c.width, c.height],
                   "ref_spp": c.ref_spp, "ref_spp_cap": c.reference_cap,
                   "ref_seconds": c.ref_seconds, "seed": c.seed, "max_depth": c.max_depth,
                   "alpha": c.alpha,
                   "table_spp": c.crop_spp, "methods": list(c.methods), "quick": c.quick, "time_seeds": c.time_seeds,
                   "frame_seeds": c.frame_seeds,
                   "models_dir": str(c.models_dir)},
        "references": {s.entry.name: {"spp_each": s.reference_spp, "sampler": REFERENCE_SAMPLER,
                                      "region": s.reference_region, "region_spp_each": s.region_spp,
                                      "floor": s.floor, "smallest_ranked": s.smallest,
                                      "capped": s.capped, "cap_reason": s.cap_reason,
                                      "render_seconds": s.reference_seconds}
                       for s in evaluation.scenes},
        "models": evaluation.models, "skipped": evaluation.skipped, "notes": evaluation.notes,
        "rows": evaluation.rows,
    }


# ---------------------------------------------------------------------------------------- provenance


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def invocation() -> str:
    """The command line as typed, when this process is `gradsep evaluate`; else the Python entry."""
    args = sys.argv[1:]
    if "evaluate" in args:
        return shlex.join(["gradsep", *args[args.index("evaluate"):]])
    return shlex.join([Path(sys.argv[0]).name, *args]) if sys.argv and sys.argv[0] else "(library call)"


def reproduce_command(c: EvalConfig) -> str:
    """A command that reproduces this run with every setting explicit (the options as GRADSEP_EVAL_* variables,
    the names evaluation.config.EvalSettings reads)."""
    var = EvalSettings.variable
    env = {MODELS_ENV: str(c.models_dir), var("size"): f"{c.width}x{c.height}", var("ref_spp"): str(c.ref_spp),
           var("ref_spp_cap"): str(c.reference_cap), var("ref_seconds"): f"{c.ref_seconds or 0:g}",
           var("seed"): str(c.seed), var("methods"): ",".join(c.methods)}
    if c.max_depth is not None:
        env[var("max_depth")] = str(c.max_depth)
    if c.alpha != DEFAULT_ALPHA:
        env[var("alpha")] = f"{c.alpha:g}"
    if c.time_seeds != 1:
        env[var("time_seeds")] = str(c.time_seeds)
    if c.frame_seeds != 1:
        env[var("frame_seeds")] = str(c.frame_seeds)
    args = ["gradsep", "evaluate"]
    if c.scenes:
        args += ["--scenes", *c.scenes]
    args += ["--spp", ",".join(str(s) for s in c.spp)]
    if c.quick:
        args.append("--quick")
    args += ["-o", str(c.output)]
    return " ".join(f"{k}={shlex.quote(v)}" for k, v in env.items()) + " " + shlex.join(args)


def machine() -> str:
    mem = ""
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        mem = f", {pages * size / 2**30:.0f} GiB RAM"
    except (ValueError, OSError, AttributeError):
        pass
    return f"{machine_summary()}{mem}; {platform.system()} {platform.release()}"


def software() -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version()}
    providers: dict[str, list[str]] | None = None
    for package in ("mitsuba", "drjit", "numpy", "onnxruntime", "pyoidn", "flip-evaluator"):
        try:
            out[package] = metadata.version(package)
            continue
        except metadata.PackageNotFoundError:
            pass
        # The module may come from another distribution of the same name (onnxruntime-openvino, -gpu, ...
        # all install the `onnxruntime` module): report the one that provides it.
        providers = metadata.packages_distributions() if providers is None else providers
        dists = providers.get(package.replace("-", "_"), [])
        out[package] = f"{metadata.version(dists[0])} ({dists[0]})" if dists else "not installed"
    try:
        import mitsuba as mi

        out["mitsuba variant"] = str(mi.variant())
    except ImportError:
        pass
    return out


# -------------------------------------------------------------------------------------------- analysis


def losses_of_ours(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Every (scene, spp) where some other method has a lower RelMSE than ours, as sentences."""
    out = []
    scenes = sorted({str(r["scene"]) for r in rows}, key=lambda s: [str(r["scene"]) for r in rows].index(s))
    for scene in scenes:
        for spp in sorted({int(r["spp"]) for r in rows if r["scene"] == scene}):
            table = by_method((r for r in rows if r["scene"] == scene), spp)
            if "ours" not in table:
                continue
            ours = float(table["ours"]["relmse"])
            better = sorted(((float(r["relmse"]), m) for m, r in table.items()
                             if m != "ours" and float(r["relmse"]) < ours))
            if better:
                who = ", ".join(f"{m} {v:.4g}" for v, m in better)
                out.append(f"{scene}, {spp} spp: ours {ours:.4g}; lower: {who}")
    return out


# --------------------------------------------------------------------------------------------- report


def render_report(evaluation: Evaluation) -> str:
    """The whole report.md as a string."""
    c = evaluation.config
    rows = evaluation.rows
    spp = c.crop_spp
    lines: list[str] = ["# gradsep evaluation", ""]
    lines += _provenance(evaluation)
    lines += _floors(evaluation)
    lines += _table1(evaluation, spp)
    lines += _ablation(evaluation, spp)
    lines += equal_time(evaluation)
    lines += planner_choice(evaluation.rows)
    lines += ["## Error against time", "",
              "RelMSE against total wall time per frame (render + reconstruction), log–log, one curve per method; "
              "a curve further down-left is better at equal time. Each point is one G-PT spp of the list above; "
              "the equal-time methods' points are their measured times for the budget of that spp (labels on "
              "ours give the spp).", ""]
    for scene in evaluation.scenes:
        lines.append(f"![{scene.entry.name}: RelMSE against time](plots/{slug(scene.entry.name)}.png)")
    lines += ["", f"## Crop comparison ({spp} spp)", "",
              ", ".join(_crop_labels().get(m, m) for m in crop_methods()) + " (equal-time methods at their "
              "equal-time spp), and the reference. All panels share one exposure (the reference's "
              "99th-percentile luminance maps to 1), then clip to "
              "[0, 1] and gamma 2.2. The crop is the square window of the reference with the most (smoothed) "
              "gradient energy (chosen from the reference alone, identical for every method).", ""]
    for scene in evaluation.scenes:
        lines.append(f"![{scene.entry.name}: crops](crops/{slug(scene.entry.name)}.png)")
    lines += ["", "## Where ours loses", ""]
    losses = losses_of_ours(rows)
    if not any(r["method"] == "ours" for r in rows):
        lines.append("Ours was not evaluated (see skipped methods).")
    elif losses:
        lines.append("Every (scene, spp) at which another method has a lower RelMSE than ours:")
        lines.append("")
        lines += [f"- {loss}" for loss in losses]
    else:
        lines.append("No evaluated method has a lower RelMSE than ours at any scene and spp.")
    lines += ["", *_table1_losses(evaluation, spp), *_targets(rows), *_fused_and_equal_time_targets(rows)]
    lines += _relmse_tables(evaluation)
    lines += _notes(evaluation)
    return "\n".join(lines) + "\n"


def _provenance(evaluation: Evaluation) -> list[str]:
    c = evaluation.config
    sw = software()
    lines = [f"Produced {_now()} by `{invocation()}`.", "",
             "Reproduce with every setting explicit:", "", "```sh", reproduce_command(c), "```", "",
             f"- Machine: {machine()}",
             "- Software: " + ", ".join(f"{k} {v}" for k, v in sw.items()),
             f"- Frames: {c.width}×{c.height}, G-PT at {', '.join(str(s) for s in c.spp)} spp, seed {c.seed}; "
             f"references: two independent Mitsuba `path` renders per scene (box filter, same max depth, "
             f"`{REFERENCE_SAMPLER}` sampler), "
             f"{c.ref_spp} spp each to start, raised up to {c.reference_cap} within "
             f"{'no time limit' if c.ref_seconds is None else f'{c.ref_seconds:g} s of new rendering per scene'} "
             "(see Reference floor)"
             + (" (--quick)" if c.quick else ""),
             f"- Tables at {c.crop_spp} spp; Poisson α = {c.alpha:g}", "",
             "| scene | spec | max depth | layers |", "|---|---|---|---|"]
    for scene in evaluation.scenes:
        lines.append(f"| {scene.entry.name} | `{display_spec(scene.entry.spec)}` | {scene.max_depth} | "
                     f"{', '.join(scene.layers)} |")
    lines += ["", f"Models folder `{c.models_dir}`:", ""]
    if evaluation.models:
        lines += [f"- `{name}` sha256 `{sha[:16]}…`" for name, sha in evaluation.models.items()]
    else:
        lines.append("- no model files found")
    lines += ["", "Skipped methods:", ""]
    if evaluation.skipped:
        for method, reasons in evaluation.skipped.items():
            lines.append(f"- **{method}** ({labels().get(method, method)}): " + "; ".join(reasons))
    else:
        lines.append("- none")
    return [*lines, ""]


def _table1(evaluation: Evaluation, spp: int) -> list[str]:
    lines = [f"## Table 1: reconstruction quality at {spp} spp", "",
             "In the form of the paper's Table 1 (which reports SSIM and LPIPS; LPIPS is not computed here, "
             "RelMSE, HDR-FLIP and PSNR are), with the strongest baselines added below the paper's four rows: OIDN "
             "on each layer of the same G-PT frame, the fused network, and the two OIDN baselines at equal time "
             "(the time of this G-PT frame + the budget method, the product's default: see Equal time). Best per "
             "scene in bold. "
             "SSIM and PSNR on the display tonemap "
             "against the mean of the two references, RelMSE on linear radiance with the reference noise removed "
             "(model/metrics.py). " + _frame_seeds_sentence(evaluation.config.frame_seeds), "",
             "| Scene | Method | " + " | ".join(h for _, h, _ in TABLE1_METRICS) + " |",
             "|---|---|" + "---:|" * len(TABLE1_METRICS)]
    for scene in evaluation.scenes:
        table = by_method((r for r in evaluation.rows if r["scene"] == scene.entry.name), spp)
        cells = {}
        for metric, _, higher in TABLE1_METRICS:
            values = {m: (float(table[m][metric]) if m in table else None) for m, _ in table1()}
            cells[metric] = bold_best(values, higher)
        for i, (method, label) in enumerate(table1()):
            name = scene.entry.name if i == 0 else ""
            shown = label if method in table else f"{label} (skipped)"
            lines.append(f"| {name} | {shown} | " + " | ".join(cells[m][method] for m, _, _ in TABLE1_METRICS) + " |")
    return [*lines, ""]


def _ablation(evaluation: Evaluation, spp: int) -> list[str]:
    names = [f"ablation/{v}" for v, _, _ in ABLATION_VARIANTS]
    headers = ["(a) no separation, no attention", "(b) separation, no attention", "(c) no separation, attention",
               "(d) separation, attention"]
    lines = [f"## Ablation (paper Fig. 7): RelMSE at {spp} spp", "",
             "The four variants trained with one identical budget (models/ablation/<variant>/). Lowest per scene "
             "in bold.", "", "| Scene | " + " | ".join(headers) + " |", "|---|" + "---:|" * 4]
    per_variant: dict[str, list[float]] = {n: [] for n in names}
    complete_scenes = 0
    for scene in evaluation.scenes:
        table = by_method((r for r in evaluation.rows if r["scene"] == scene.entry.name), spp)
        values = {n: (float(table[n]["relmse"]) if n in table else None) for n in names}
        cells = bold_best(values, higher=False)
        lines.append(f"| {scene.entry.name} | " + " | ".join(cells[n] for n in names) + " |")
        if all(v is not None for v in values.values()):
            complete_scenes += 1
            for n in names:
                per_variant[n].append(float(values[n]))  # type: ignore[arg-type]
    if complete_scenes:
        means = {n: sum(v) / len(v) for n, v in per_variant.items()}
        cells = bold_best(means, higher=False)  # type: ignore[arg-type]
        lines.append(f"| mean ({complete_scenes} scenes) | " + " | ".join(cells[n] for n in names) + " |")
    lines.append("| paper (its scenes) | " + " | ".join(fmt(PAPER_FIG7[v]) for v, _, _ in ABLATION_VARIANTS) + " |")
    lines.append("")
    lines += _ablation_verdicts(evaluation, spp)
    return [*lines, ""]


def _ablation_verdicts(evaluation: Evaluation, spp: int) -> list[str]:
    """How often separation and attention each lowered RelMSE, over scenes and the two settings of the other."""
    pairs = {"separation": [("combined-noattn", "separated-noattn"), ("combined-attn", "separated-attn")],
             "attention": [("combined-noattn", "combined-attn"), ("separated-noattn", "separated-attn")]}
    lines = []
    for factor, comparisons in pairs.items():
        wins = total = 0
        for scene in evaluation.scenes:
            table = by_method((r for r in evaluation.rows if r["scene"] == scene.entry.name), spp)
            for without, with_ in comparisons:
                a, b = table.get(f"ablation/{without}"), table.get(f"ablation/{with_}")
                if a is not None and b is not None:
                    total += 1
                    wins += float(b["relmse"]) < float(a["relmse"])
        if total:
            lines.append(f"- {factor.capitalize()} lowered RelMSE in {wins} of {total} comparisons.")
    if not lines:
        evaluated = any(str(r["method"]).startswith("ablation/") for r in evaluation.rows)
        lines.append("- No with/without pair of ablation variants was evaluated, so neither factor can be judged"
                     if evaluated else "- The ablation models were not evaluated (see skipped methods).")
    return lines


def _frame_seeds_sentence(frame_seeds: int) -> str:
    """What the fixed-spp cells are over: one G-PT frame, or ``--frame-seeds`` N."""
    if frame_seeds <= 1:
        return "Each fixed-spp cell is one G-PT frame (one render seed; `--frame-seeds N` averages N)."
    return (f"Each fixed-spp cell is the mean over {frame_seeds} G-PT frames, each rendered with its own seed "
            "(`--frame-seeds`); results.json keeps each frame's `seed_relmse` and the RelMSE's standard error "
            "(`relmse_stderr`); crops show the first frame, and the equal-time budgets are the first frame's.")


def display_spec(spec: str) -> str:
    """A scene spec as the report shows it: a file in or beside the repository (the shared scenes) relative to the
    repository's root, e.g. ``../shared/scenes/cbox/cbox.xml``, so that the report does not name this machine's
    checkout; anything else (``procedural:N``, a file elsewhere) as given."""
    from gradsep.evaluation.cache import REPO_ROOT

    if ":" in spec and not Path(spec).exists():
        return spec
    for path in (Path(os.path.abspath(spec)), Path(spec).resolve()):  # as given (a linked folder), then resolved
        for root, prefix in ((REPO_ROOT, ""), (REPO_ROOT.parent, "../")):
            if path.is_relative_to(root):
                return prefix + path.relative_to(root).as_posix()
    return spec


def _floors(evaluation: Evaluation) -> list[str]:
    """The reference floor per scene against the smallest ranked RelMSE, with a warning where the cap was hit."""
    from gradsep.evaluation.config import FLOOR_FRACTION

    c = evaluation.config
    lines = ["## Reference floor", "",
             f"Two independent references per scene (different seeds; Mitsuba `path` with the stratified "
             f"`{REFERENCE_SAMPLER}` sampler, unbiased like the independent one, lower noise per second). "
             "The *floor* is the RelMSE a perfect method "
             "would score against one of them, estimated as RelMSE(r1, r2) / 2 (normalised by the mean of the "
             "two): what a one-reference evaluation would add to every error. The product estimator used for "
             "every RelMSE here removes it in expectation; the references are still raised (doubling, cached "
             f"passes re-used, from {c.ref_spp} up to {c.reference_cap} spp each, and only while the passes not yet "
             f"cached render within {'any time' if c.ref_seconds is None else f'{c.ref_seconds:g} s'}) until "
             "the floor "
             "is under "
             f"{FLOOR_FRACTION:.0%} of the scene's smallest ranked RelMSE (over every method and spp). Where the "
             "full passes stop short of that, *region passes* add samples over the one rectangle where a pilot "
             "render (seeds of its own, in neither reference) places most of the floor, as many as the floor "
             "there is predicted to need, up to the cap more and within the same time budget; inside it a pixel "
             "is the mean of all its samples (docs/evaluation.md, \"Region passes\").", "",
             "| Scene | spp per reference | floor (total) | floor direct | floor indirect | smallest ranked RelMSE | "
             "floor / smallest | reference s |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    warnings = []
    for scene in evaluation.scenes:
        floor = scene.floor.get("total", math.nan)
        ratio = floor / scene.smallest if scene.smallest > 0 else math.inf
        flag = " ⚠" if scene.capped else ""
        spp = f"{scene.reference_spp}"
        if scene.reference_region and scene.region_spp:
            x, y, w, h = scene.reference_region
            share = w * h / (scene.width * scene.height)
            spp += f" + {scene.region_spp} in {w}×{h} at ({x}, {y}) ({share:.0%} of the pixels)"
        lines.append(f"| {scene.entry.name} | {spp} | {fmt(floor, 3)} | "
                     f"{fmt(scene.floor.get('direct'), 3)} | {fmt(scene.floor.get('indirect'), 3)} | "
                     f"{fmt(scene.smallest, 3)} | {ratio:.1%}{flag} | {scene.reference_seconds:.0f} |")
        if scene.capped:
            warnings.append(f"**Warning: {scene.entry.name}: the references stopped at {scene.reference_spp} spp "
                            f"each ({scene.cap_reason}) with the floor at {ratio:.0%} of the smallest ranked "
                            f"RelMSE** (target {FLOOR_FRACTION:.0%}). Its RelMSE values are still unbiased, but "
                            "noisier; raise --ref-spp-cap / --ref-seconds for a tighter estimate, or render the "
                            "passes on N machines (`gradsep evaluate --references-only --shard K/N`, "
                            "docs/evaluation.md).")
    return [*lines, "", *warnings, *([""] if warnings else [])]


def _table1_losses(evaluation: Evaluation, spp: int) -> list[str]:
    """Per scene, the Table 1 metrics on which ours is not the best of the Table 1 methods."""
    lines = []
    for scene in evaluation.scenes:
        table = by_method((r for r in evaluation.rows if r["scene"] == scene.entry.name), spp)
        if "ours" not in table:
            continue
        for metric, header, higher in TABLE1_METRICS:
            ours = float(table["ours"][metric])
            better = [(label, float(table[m][metric])) for m, label in table1() if m != "ours" and m in table
                      and (float(table[m][metric]) > ours if higher else float(table[m][metric]) < ours)]
            if better:
                who = ", ".join(f"{label} {fmt(v)}" for label, v in better)
                lines.append(f"- Table 1, {scene.entry.name}: {header.split()[0]} of ours {fmt(ours)}; better: {who}")
    if lines:
        lines = [f"Table 1 metrics ({spp} spp) on which ours is not the best of the Table 1 rows:", "",
                 *lines, ""]
    return lines


def _targets(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The paper's quality ordering at 16 and 64 spp: RelMSE(ours) < RelMSE(L1) < RelMSE(G-PT primal)."""
    lines = ["Quality target (RelMSE ours < L1 < input, per scene):", ""]
    found = False
    for scene in dict.fromkeys(str(r["scene"]) for r in rows):
        for spp in (16, 64):
            table = by_method((r for r in rows if r["scene"] == scene), spp)
            if all(m in table for m in ("ours", "l1", "gpt-primal")):
                found = True
                o, l1, p = (float(table[m]["relmse"]) for m in ("ours", "l1", "gpt-primal"))
                verdict = "met" if o < l1 < p else "**not met**"
                lines.append(f"- {scene}, {spp} spp: ours {o:.4g}, L1 {l1:.4g}, input {p:.4g}: {verdict}")
    if not found:
        lines.append("- not checked (needs ours, L1 and the input at 16 or 64 spp)")
    return [*lines, ""]


#: The fused method's target: below each of these on every scene at 16 and 64 spp.
FUSED_RIVALS: tuple[str, ...] = ("oidn", "l1", "ours")


def _ratio_cell(value: float, rival: float) -> str:
    ratio = value / rival if rival > 0 else math.inf
    return f"{fmt(value)} / {fmt(rival)} = {ratio:.3f}×"


def _fused_and_equal_time_targets(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The fused and equal-time targets from the rows, at 16 and 64 spp: ``fused`` below ``oidn``, ``l1`` and
    ``ours`` (the paper's network) per scene; at equal time, the best G-PT row not over the budget by more than
    5 % (:func:`over_budget`: the budget method's own row, G-PT+oidn-l1, G-PT auto) below path + OIDN, and
    (stretch) below separated path + OIDN per layer."""
    lines = ["Fused and equal-time targets (RelMSE, per scene, at 16 and 64 spp; a multi-seed row counts by its "
             "mean):", ""]
    found = False
    for scene in dict.fromkeys(str(r["scene"]) for r in rows):
        for spp in (16, 64):
            table = by_method((r for r in rows if r["scene"] == scene), spp)
            if "fused" in table and all(m in table for m in FUSED_RIVALS):
                found = True
                best = min(FUSED_RIVALS, key=lambda m: float(table[m]["relmse"]))
                fused, rival = float(table["fused"]["relmse"]), float(table[best]["relmse"])
                verdict = "below all three" if fused < rival else "**not below**"
                lines.append(f"- {scene}, {spp} spp: `fused` against the best of "
                             f"{', '.join(f'`{m}`' for m in FUSED_RIVALS)} (`{best}`): "
                             f"{_ratio_cell(fused, rival)} ({verdict})")
            budget = next((str(r.get("budget_method")) for r in table.values() if r.get("budget_method")), None)
            candidates = {m: float(table[m]["relmse"]) for m in (budget, *GPT_EQUAL_TIME)
                          if m in table and table[m].get("relmse") is not None and not over_budget(table[m])}
            if candidates and "path-oidn" in table:
                found = True
                best = min(candidates, key=candidates.__getitem__)
                words = []
                for baseline in ("path-oidn", "path-sep-oidn"):
                    if baseline in table:
                        value = float(table[baseline]["relmse"])
                        below = "below" if candidates[best] < value else "**not below**"
                        words.append(f"{below} `{baseline}` ({_ratio_cell(candidates[best], value)})")
                lines.append(f"- {scene}, {spp} spp, equal time: the best G-PT row (`{best}`) is "
                             + "; ".join(words))
    if not found:
        lines.append("- not checked (needs fused, oidn, l1 and ours, or the equal-time rows, at 16 or 64 spp)")
    return [*lines, ""]


def _relmse_tables(evaluation: Evaluation) -> list[str]:
    lines = ["## RelMSE and time by spp, all methods", "",
             "Cells: RelMSE (± its standard error over a multi-seed row's seeds) / total seconds (*: interpolated "
             "to the equal-time budget, see Equal time). Per-layer RelMSE (direct, indirect) is in results.csv. "
             + _frame_seeds_sentence(evaluation.config.frame_seeds), ""]
    for scene in evaluation.scenes:
        scene_rows = [r for r in evaluation.rows if r["scene"] == scene.entry.name]
        spps = sorted({int(r["spp"]) for r in scene_rows})
        methods = [m.name for m in evaluated_methods() if any(r["method"] == m.name for r in scene_rows)]
        lines += [f"### {scene.entry.name}", "", "| Method | " + " | ".join(f"{s} spp" for s in spps) + " |",
                  "|---|" + "---:|" * len(spps)]
        for method in methods:
            cells = []
            for s in spps:
                r = next((r for r in scene_rows if r["method"] == method and int(r["spp"]) == s), None)
                star = "*" if r is not None and r.get("time_interpolated") else ""
                cell = f"{fmt(r['relmse'])}{stderr_cell(r)} / {fmt(row_seconds(r), 3)} s{star}" if r else "–"
                cells.append(cell)
            lines.append(f"| {labels().get(method, method)} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def _notes(evaluation: Evaluation) -> list[str]:
    c = evaluation.config
    lines = ["## Notes", "",
             "- Timings are wall-clock seconds on the machine above, single frames, one run each: noisy on a "
             "shared machine. Rows taken from the cache keep the timings of the run that computed them "
             "(results.json records the machine per row).",
             "- One-time costs are excluded on both sides: ONNX Runtime's first run on a frame size and Mitsuba's "
             "kernel compilation. The G-PT time is the renderer's own, including its per-frame tracing.",
             "- RelMSE (total and per layer) is the product estimator over two independent references, "
             "mean((x − r1)(x − r2) / (r̄² + 0.01)): the references' own noise is removed (unbiased up to the "
             "normaliser r̄², which uses both); an estimate can be slightly negative for an image closer to the "
             "truth than the references resolve. SSIM, PSNR and FLIP are scored against the mean of the two "
             "references and so remain slightly biased by its noise."]
    machines = sorted({str(r.get("machine")) for r in evaluation.rows if r.get("machine")})
    if len(machines) > 1:
        lines.append("- Rows were computed on more than one machine: " + "; ".join(machines))
    lines += [f"- {note}" for note in evaluation.notes]
    computed = evaluation.computed
    lines.append(f"- This run computed {computed['frames']} frames, {computed['references']} references and "
                 f"{computed['results']} results; the rest came from the cache ({c.cache_dir / 'evaluate'}).")
    return [*lines, ""]
