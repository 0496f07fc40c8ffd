"""The report of `gradsep evaluate --shot`: a table, error and flicker over the shot, an animation of crops.

Written into the report folder, each file atomically:

* ``report.md`` -- the table (per pipeline: geometric-mean RelMSE and its ratio to the best per-frame pipeline,
  flicker and its ratio to primal + OIDN per frame, the disoccluded-pixel and after-a-change error ratios to the
  same frames reconstructed per frame, seconds per frame), the figures, the references' floors, the command;
* ``shot.csv`` -- per frame and pipeline: RelMSE, flicker of the pair ending at the frame, seconds;
* ``shot.json`` -- the table's figures, the per-frame figures, the configuration and the machine;
* ``plots/error.png``, ``plots/flicker.png`` -- RelMSE and flicker per frame, one line per pipeline;
* ``crops.png`` -- an animated PNG: per frame, the same crop of the reference and of every pipeline side by side
  (evaluation/plots.py's crop choice and exposure, from the middle frame's reference, fixed over the shot).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.evaluation.plots import _figure, _save, exposure_for, select_crop
from gradsep.evaluation.shot_metrics import after_change_ratio, median_seconds, ratio
from gradsep.evaluation.shots import ShotResult
from gradsep.model.exr_write import write_bytes_atomic
from gradsep.model.metrics import tonemap

__all__ = ["row_label", "summary_rows", "write_shot_report"]

#: Each crop panel is drawn at least this many pixels wide (small frames are enlarged, nearest neighbour).
PANEL_PIXELS = 160
#: One colour per plan (its per-frame row dashed, its temporal row solid).
PLAN_COLOURS = ("#9467bd", "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#8c564b")
#: Milliseconds each frame of the animation shows.
FRAME_MS = 250


def row_label(result: ShotResult, name: str) -> str:
    """``primal + oidn``, ``default plan + oidn-l1, temporal (5 frames)``: the plan, the method, the window."""
    row = next(r for r in result.rows if r.name == name)
    plan = name.split("+")[0]
    label = {"primal": "primal", "plan": "default plan"}.get(plan, plan)
    text = f"{label} + {row.method}"
    return text + f", temporal ({result.config.window} frames)" if name.endswith("+temporal") else text + " per frame"


def _scene_name(result: ShotResult) -> str:
    """The shot's scene as titles show it: a procedural spec as it is, a file by its name."""
    scene = result.config.scene
    return scene if scene.startswith("procedural:") else Path(scene).name


def _fmt(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def summary_rows(result: ShotResult) -> list[dict[str, Any]]:
    """The table's figures per pipeline (None where a figure does not apply)."""
    by_name = {r.name: r for r in result.rows}
    per_frame = [r for r in result.rows if result.per_frame_of[r.name] == r.name]
    best = min(per_frame, key=lambda r: r.relmse)
    baseline = by_name[result.baseline]
    out = []
    for row in result.rows:
        own = by_name[result.per_frame_of[row.name]]
        out.append({"pipeline": row.name, "label": row_label(result, row.name), "method": row.method,
                    "relmse": row.relmse, "relmse_vs_best_per_frame": ratio(row.relmse, best.relmse),
                    "best_per_frame": best.name, "flicker": row.flicker,
                    "flicker_vs_primal_oidn": ratio(row.flicker, baseline.flicker),
                    "disoccluded_relmse": row.disoccluded,
                    "disoccluded_vs_per_frame": ratio(row.disoccluded, own.disoccluded),
                    "after_change_vs_per_frame": after_change_ratio(row, own, result.changes)
                    if result.changes else None,
                    "seconds_per_frame": median_seconds(row.seconds), "spp": row.spp})
    return out


def _table(result: ShotResult, rows: Sequence[dict[str, Any]]) -> list[str]:
    lines = ["| pipeline | RelMSE (geomean) | × best per-frame | flicker | × primal + OIDN | disoccluded × per-frame "
             "| after a change × per-frame | s / frame | spp |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['label']} | {_fmt(r['relmse'], 4)} | {_fmt(r['relmse_vs_best_per_frame'])} | "
                     f"{_fmt(r['flicker'], 4)} | {_fmt(r['flicker_vs_primal_oidn'])} | "
                     f"{_fmt(r['disoccluded_vs_per_frame'])} | {_fmt(r['after_change_vs_per_frame'])} | "
                     f"{_fmt(r['seconds_per_frame'])} | {_fmt(r['spp'], 4)} |")
    return lines


def _budget_text(result: ShotResult) -> str:
    c = result.config
    return (f"{c.seconds:g} render seconds per frame" if c.seconds is not None
            else f"{c.spp} spp per frame (equal samples, not equal time)")


def _markdown(result: ShotResult, rows: Sequence[dict[str, Any]], command: str) -> str:
    c = result.config
    first, last = result.numbers[0], result.numbers[-1]
    changes = ", ".join(str(result.numbers[t]) for t in result.changes) or "none"
    floor = float(np.median(result.floors))
    smallest = min(r.relmse for r in result.rows)
    lines = [f"# Shot evaluation: {c.scene}, frames {first}-{last}", "",
             f"{len(result.numbers)} frames, {_budget_text(result)}, temporal window {c.window}; two independent "
             f"references of {result.ref_spp} spp per frame (Mitsuba's path tracer){_pooled_text(result)}. "
             "RelMSE has the references' noise "
             "removed (product estimator) and is the geometric mean over the frames; flicker is the same estimator "
             "on the frame-to-frame change of the error along the motion, the mean over consecutive pairs. "
             "Disoccluded and after-a-change figures are ratios to the same frames reconstructed per frame; a "
             "change is a frame where the light changes (docs/evaluation.md, \"Shots\"). Seconds per frame: the "
             "render as its budget counts it plus the reconstruction (median over frames); spp: the frames' median.",
             "",
             *_table(result, rows), "",
             f"Best per-frame pipeline: {rows[0]['best_per_frame']}. Frames where the light changes: {changes}. "
             f"Reference floor (median over frames, one reference): {floor:.3g}"
             + (f" -- above 10 % of the smallest RelMSE ({smallest:.3g}): raise --ref-spp or --ref-spp-cap."
                if floor > 0.1 * smallest
                else "."), "",
             "![RelMSE per frame](plots/error.png)", "", "![flicker per frame](plots/flicker.png)", "",
             "Crops, animated (reference first): ![crops](crops.png)", "",
             f"Made with `{command}` on {_machine()}."]
    return "\n".join(lines) + "\n"


def _pooled_text(result: ShotResult) -> str:
    """The clause naming the frames whose references were pooled (one scene), or nothing."""
    if not result.pooled:
        return ""
    groups = ", ".join(f"{g[0]}-{g[-1]}" if g == list(range(g[0], g[-1] + 1)) else " ".join(map(str, g))
                       for g in result.pooled)
    return f", pooled over the frames of one scene (every parameter equal: {groups})"


def _machine() -> str:
    from gradsep.evaluation.results import machine_summary

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    return f"{machine_summary()}, load average {load:.2f}"


def _csv(result: ShotResult) -> bytes:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["frame", "pipeline", "relmse", "flicker", "seconds"])
    for row in result.rows:
        for t, n in enumerate(result.numbers):
            writer.writerow([n, row.name, f"{row.errors[t]:.6g}", _fmt(row.flickers[t], 6),
                             f"{row.seconds[t]:.4g}" if t < len(row.seconds) else ""])
    return buffer.getvalue().encode()


def _json(result: ShotResult, rows: Sequence[dict[str, Any]], command: str) -> bytes:
    c = result.config
    data = {"command": command, "machine": _machine(), "scene": c.scene, "frames": result.numbers,
            "seconds": c.seconds, "spp": c.spp, "ref_spp": result.ref_spp, "window": c.window, "seed": c.seed,
            "size": c.size, "animate": list(c.animate), "defines": list(c.defines), "summary": rows,
            "changes": [result.numbers[t] for t in result.changes], "reference_floors": result.floors,
            "pooled_references": result.pooled,
            "per_frame": {r.name: {"relmse": r.errors, "flicker": r.flickers, "seconds": r.seconds}
                          for r in result.rows}}
    return json.dumps(_finite(data), indent=1, default=str, allow_nan=False).encode()


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def _plot(result: ShotResult, values: dict[str, Sequence[float | None]], ylabel: str, title: str,
          path: Path) -> Path:
    fig = _figure((7.5, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    for name, ys in values.items():
        points = [(n, y) for n, y in zip(result.numbers, ys, strict=True) if y is not None and y > 0]
        if not points:
            continue
        plans = list(dict.fromkeys(result.per_frame_of.values()))
        colour = PLAN_COLOURS[plans.index(result.per_frame_of[name]) % len(PLAN_COLOURS)]
        temporal = name.endswith("+temporal")
        ax.plot(*zip(*points, strict=True), linestyle="-" if temporal else "--", marker="D" if temporal else "o",
                color=colour, linewidth=1.6, markersize=4, label=row_label(result, name))
    for t in result.changes:
        ax.axvline(result.numbers[t], color="#999999", linestyle=":", linewidth=1.0)
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_yscale("log")
    ax.set_xlabel("frame")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return _save(fig, path)


def _panel(image: np.ndarray, box: tuple[int, int, int], scale: float, zoom: int) -> np.ndarray:
    y0, x0, side = box
    crop = tonemap(np.asarray(image[y0:y0 + side, x0:x0 + side], np.float64) * scale)
    return np.repeat(np.repeat((crop * 255 + 0.5).astype(np.uint8), zoom, axis=0), zoom, axis=1)


def animation_bytes(result: ShotResult) -> bytes:
    """The animated PNG of side-by-side crops (reference mean first, then each pipeline), one image per frame."""
    from PIL import Image, ImageDraw

    middle = len(result.numbers) // 2
    reference = 0.5 * (result.truth.first[middle].astype(np.float64) + result.truth.second[middle])
    box = select_crop(reference, max(8, min(reference.shape[:2]) // 2))
    scale = exposure_for(reference)
    zoom = max(1, math.ceil(PANEL_PIXELS / box[2]))
    names = ["reference", *(r.name for r in result.rows)]
    images = []
    for t, n in enumerate(result.numbers):
        sources = [0.5 * (result.truth.first[t].astype(np.float64) + result.truth.second[t]),
                   *(result.images[r.name][t] for r in result.rows)]
        panels = [_panel(s, box, scale, zoom) for s in sources]
        side = panels[0].shape[0]
        canvas = Image.new("RGB", (len(panels) * (side + 4), side + 40), (255, 255, 255))
        draw = ImageDraw.Draw(canvas)
        for k, (name, panel) in enumerate(zip(names, panels, strict=True)):
            canvas.paste(Image.fromarray(panel), (k * (side + 4), 40))
            lines = ["reference", "(two, averaged)"] if name == "reference" else \
                row_label(result, name).replace(", temporal", "\ntemporal").replace(" per frame", "\nper frame") \
                .splitlines()
            for i, line in enumerate([*lines, f"frame {n}"]):
                draw.text((k * (side + 4) + 2, 1 + 13 * i), line, fill=(0, 0, 0) if i < 2 else (90, 90, 90))
        images.append(canvas)
    buffer = io.BytesIO()
    images[0].save(buffer, format="PNG", save_all=True, append_images=images[1:], duration=FRAME_MS, loop=0)
    return buffer.getvalue()


def write_shot_report(result: ShotResult, command: str | None = None) -> dict[str, Path]:
    """Write the report (see the module docstring) into the configured folder; the paths written."""
    command = command or " ".join(["gradsep", *sys.argv[1:]])
    out = result.config.output
    out.mkdir(parents=True, exist_ok=True)
    rows = summary_rows(result)
    paths = {"report": out / "report.md", "csv": out / "shot.csv", "json": out / "shot.json",
             "crops": out / "crops.png"}
    write_bytes_atomic(paths["csv"], _csv(result))
    write_bytes_atomic(paths["json"], _json(result, rows, command))
    paths["error"] = _plot(result, {r.name: r.errors for r in result.rows}, "RelMSE (reference noise removed)",
                           f"{_scene_name(result)}: error per frame, {_budget_text(result)}",
                           out / "plots" / "error.png")
    paths["flicker"] = _plot(result, {r.name: r.flickers for r in result.rows},
                             "flicker (change of the error from the previous frame)",
                             f"{_scene_name(result)}: flicker per frame along the motion",
                             out / "plots" / "flicker.png")
    write_bytes_atomic(paths["crops"], animation_bytes(result))
    write_bytes_atomic(paths["report"], _markdown(result, rows, command).encode())
    return paths
