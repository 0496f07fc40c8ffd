"""The evaluation's figures: RelMSE against wall time per scene, and the crop comparison of the paper's Fig. 6.

matplotlib with the Agg backend (no display needed); every figure is rendered into memory and written
atomically, so a killed run never leaves a truncated PNG behind.

Crop comparison display: all panels share one exposure, chosen from the reference so that its 99th-percentile
luminance maps to 1 (a frame dominated by a dark room still shows its detail; the light source may clip), then
the display tonemap of model/metrics.py (clip to [0, 1], gamma 1/2.2). The crop is picked from the reference
alone -- the square window with the most tonemapped gradient energy (edges, shadow boundaries, texture) -- so
it is the same for every method and not chosen to favour any of them (the luminance is smoothed with a σ = 1
pixel Gaussian first, so the reference's own residual noise does not count as detail).
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.evaluation.results import row_seconds
from gradsep.model.exr_write import write_bytes_atomic
from gradsep.model.metrics import tonemap

__all__ = ["METHOD_STYLES", "CropPanels", "exposure_for", "plot_crops", "plot_error_vs_time", "select_crop", "style_of"]

_LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)

#: (colour, line style, marker) per method; ablation variants are thin grey-blue lines.
METHOD_STYLES: dict[str, tuple[str, str, str]] = {
    "gpt-primal": ("#7f7f7f", ":", "o"),
    "l2": ("#bcbd22", "--", "v"),
    "l1": ("#ff7f0e", "--", "^"),
    "gradnet": ("#2ca02c", "-.", "s"),
    "ablation/combined-noattn": ("#9ecae1", "-", "x"),
    "ablation/separated-noattn": ("#6baed6", "-", "+"),
    "ablation/combined-attn": ("#4292c6", "-", "1"),
    "ablation/separated-attn": ("#2171b5", "-", "2"),
    "ours": ("#d62728", "-", "D"),
    "path": ("#8c564b", ":", "o"),
    "path-oidn": ("#9467bd", "--", "P"),
    "path-sep-oidn": ("#e377c2", "-", "X"),
    "oidn": ("#17becf", "-.", "h"),
    "oidn-l1": ("#bcbd22", "-", "v"),
    "fused": ("#000000", "-", "*"),
    "gpt-oidn-l1": ("#ff7f0e", "--", "v"),
    "gpt-auto": ("#1f77b4", "--", "p"),
}


#: Styles of methods without an entry above (a method added to the table), picked by name so each keeps its own.
_FALLBACK_COLOURS = ("#8dd3c7", "#fb8072", "#80b1d3", "#fdb462", "#b3de69", "#fccde5", "#bc80bd", "#ccebc5")
_FALLBACK_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*")


def style_of(method: str) -> tuple[str, str, str]:
    """(colour, line style, marker) of ``method``: its entry in METHOD_STYLES, else one derived from its name."""
    if method in METHOD_STYLES:
        return METHOD_STYLES[method]
    import zlib

    h = zlib.crc32(method.encode())
    return _FALLBACK_COLOURS[h % len(_FALLBACK_COLOURS)], "-", _FALLBACK_MARKERS[(h >> 8) % len(_FALLBACK_MARKERS)]


def _figure(figsize: tuple[float, float]) -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, dpi=100)  # a bare Figure draws with Agg and touches no global pyplot state


def _save(fig: Any, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, buffer.getvalue())
    return path


def plot_error_vs_time(scene: str, rows: Sequence[Mapping[str, Any]], labels: Mapping[str, str], path: Path,
                       floor: float | None = None) -> Path:
    """RelMSE against total seconds, log-log, one curve per method (points in spp order, labelled for ours).

    RelMSE is the product estimate with the references' noise removed; ``floor`` (what a perfect method would
    score against one reference) is drawn as a grey line for scale. An estimate at or below zero (an error the
    references cannot resolve) is drawn at the bottom of the axis, a tenth of the floor."""
    bottom = floor / 10 if floor and floor > 0 else 1e-8
    fig = _figure((7.5, 5.0))
    ax = fig.add_subplot(1, 1, 1)
    by_method: dict[str, list[Mapping[str, Any]]] = {}
    for row in rows:
        by_method.setdefault(str(row["method"]), []).append(row)
    for method, items in by_method.items():
        items = sorted(items, key=lambda r: int(r["spp"]))
        x = [max(row_seconds(r), 1e-4) for r in items]  # an interpolated row stands at its budget
        y = [max(float(r["relmse"]), bottom) for r in items]
        colour, style, marker = style_of(method)
        thin = method.startswith("ablation/")
        ax.plot(x, y, linestyle=style, marker=marker, color=colour, linewidth=1.0 if thin else 1.8,
                markersize=4 if thin else 6, label=labels.get(method, method))
        if method == "ours":
            for xi, yi, r in zip(x, y, items, strict=True):
                ax.annotate(f"{r['spp']}", (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=7,
                            color=colour)
    if floor and floor > 0:
        ax.axhline(floor, color="#999999", linestyle="--", linewidth=1.0, label="reference floor (one reference)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("total wall time per frame [s] (render + reconstruction)")
    ax.set_ylabel("RelMSE (reference noise removed)")
    ax.set_title(f"{scene}: error against time (labels on ours: G-PT spp)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return _save(fig, path)


def exposure_for(reference: np.ndarray) -> float:
    """Scale that maps the reference's 99th-percentile luminance to 1 (1 for a black reference)."""
    lum = np.asarray(reference, dtype=np.float64).reshape(-1, 3) @ _LUMINANCE
    p = float(np.percentile(lum, 99)) if lum.size else 0.0
    return 1.0 / p if p > 0 and math.isfinite(p) else 1.0


def select_crop(reference: np.ndarray, size: int | None = None) -> tuple[int, int, int]:
    """(y0, x0, size): the square window of the reference with the largest sum of (smoothed) tonemapped gradient
    magnitude.

    The window side defaults to a third of the shorter image side (at least 8 pixels, at most the image).
    """
    h, w = reference.shape[:2]
    side = size if size is not None else max(8, min(h, w) // 3)
    side = max(1, min(side, h, w))
    from scipy.ndimage import gaussian_filter

    # smoothed first: in a reference with a few hundred spp, isolated noisy pixels (caustic fireflies) would
    # otherwise outweigh real edges
    lum = gaussian_filter(tonemap(reference * exposure_for(reference)) @ _LUMINANCE, 1.0, mode="nearest")
    energy = np.zeros((h, w), dtype=np.float64)
    energy[:, :-1] += np.abs(np.diff(lum, axis=1))
    energy[:-1, :] += np.abs(np.diff(lum, axis=0))
    integral = np.zeros((h + 1, w + 1), dtype=np.float64)
    integral[1:, 1:] = energy.cumsum(0).cumsum(1)
    sums = (integral[side:, side:] - integral[:-side, side:] - integral[side:, :-side] + integral[:-side, :-side])
    y0, x0 = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(y0), int(x0), side


@dataclass(frozen=True)
class CropPanels:
    """What the crop comparison shows: the methods in their order, their labels and their RelMSE (over the frame)."""

    names: Sequence[str]
    labels: Mapping[str, str]
    metrics: Mapping[str, float]


def plot_crops(scene: str, reference: np.ndarray, images: Mapping[str, np.ndarray], crops: CropPanels, spp: int,
               path: Path) -> Path:
    """The Fig. 6 layout: the full frame (ours, else the reference) with the crop marked, then one crop per
    method of ``crops.names`` (a grey "not evaluated" panel for a missing one) and the reference's crop last."""
    panels, labels, metrics = crops.names, crops.labels, crops.metrics
    y0, x0, side = select_crop(reference)
    scale = exposure_for(reference)

    def display(image: np.ndarray) -> np.ndarray:
        return tonemap(np.asarray(image, dtype=np.float64) * scale)

    full_name = "ours" if "ours" in images else "reference"
    full = images.get("ours", reference)
    columns = len(panels) + 2
    fig = _figure((2.2 * columns, 2.9))
    ax = fig.add_subplot(1, columns, 1)
    ax.imshow(display(full), interpolation="nearest")
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle((x0 - 0.5, y0 - 0.5), side, side, fill=False, edgecolor="yellow", linewidth=1.2))
    ax.set_title(f"{labels.get(full_name, full_name)}\nfull frame", fontsize=8)
    ax.axis("off")
    for i, name in enumerate([*panels, "reference"], start=2):
        ax = fig.add_subplot(1, columns, i)
        source = reference if name == "reference" else images.get(name)
        title = labels.get(name, name)
        if source is None:
            ax.imshow(np.full((side, side, 3), 0.5), interpolation="nearest")
            title += "\n(not evaluated)"
        else:
            ax.imshow(display(source[y0:y0 + side, x0:x0 + side]), interpolation="nearest")
            if name in metrics:
                title += f"\nRelMSE {metrics[name]:.4g}"
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.suptitle(f"{scene}, {spp} spp (G-PT; equal time for path + OIDN); exposure ×{scale:.3g}, "
                 "clip + gamma 2.2; RelMSE over the full frame", fontsize=8)
    return _save(fig, path)
