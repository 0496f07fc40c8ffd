"""The methods `gradsep evaluate` compares, and how each one turns a scene + G-PT frame into an image and timings.

Every method produces (image, per-layer images where it has them, render seconds, reconstruction seconds):

==========================  ===============================================================================
``gpt-primal``              the G-PT frame's primal image, Σ layers' base: the input every reconstruction sees
*each method of the table*  ``reconstruct(frame, method)`` for every method of model/methods.py (``l1``,
                            ``l2``, ``oidn``, ``oidn-l1``, ``fused``, and ``network`` as ``ours``), with the
                            model sets it needs loaded from the models folder; a method needing only the direct
                            layer's gradients (``oidn-l1``) reconstructs the ``--gradients direct`` render of
                            the same seed; skipped, listing the missing files, without its models
``l2``, ``l1``              screened Poisson (model.poisson via model.reconstruct), per layer, summed
``gradnet``                 the ``color`` model (no separation, no attention: the GradNet-style baseline) run
                            on the frame's combined layer, ``Frame.combined()``
``ablation/<variant>``      the four ablation models of the paper's Fig. 7, ``models/ablation/<variant>/``:
                            ``combined-*`` run ``color.onnx`` on the combined layer, ``separated-*`` run
                            ``direct.onnx`` + ``indirect.onnx`` per layer; ``-attn`` / ``-noattn`` say whether
                            the network has CBAM attention
``ours``                    the table's ``network``: the shipped pair ``models/direct.onnx`` +
                            ``models/indirect.onnx`` (separation + attention), per layer, summed
``oidn``                    OIDN on each layer of the G-PT frame, summed
``oidn-l1``                 ``oidn``, then the direct layer refined by its gradients (model/refine.py)
``fused``                   the fused blend of ``models/fused/<layer>.onnx`` (the indirect layer's; the direct layer
                            needs none, model.fused.FIXED_LAYERS)
``path``                    Mitsuba's own ``path`` integrator at *equal time* (below)
``path-oidn``               ``path`` denoised by Intel Open Image Denoise (model/oidn.py) with albedo and normal
                            from a separate :data:`FEATURE_SPP`-spp feature pass (Mitsuba ``aov``) whose time
                            is counted; equal time
``path-sep-oidn``           the renderer's primal-only mode (``render_frame(..., gradients=False)``: G-PT's
                            direct/indirect routing and first-hit features, no offset paths), OIDN on each
                            layer (``reconstruct(frame, "oidn")``), summed; equal time. A method this host
                            cannot run (no pyoidn) is skipped with that reason (:func:`unavailable`)
``gpt-oidn-l1``             G-PT at *equal time*: the ``--gradients direct`` render (offsets
                            :data:`EQUAL_TIME_OFFSETS`) at the spp the budget buys, reconstructed with ``oidn-l1``
                            -- what a farm gets from our renderer + service in the time the baselines are given
                            (the G-PT rows above are at equal spp, each at its own time)
``gpt-auto``                G-PT *planned* at equal time: ``gradsep render --seconds T --gradients auto`` in
                            process (renderer.planner.render_planned: a checkpoint on the frame's halves keeps
                            direct-alternate or goes on with primal, passes fill the deadline), reconstructed with
                            the default method the frame names (``gradsep.plan_method``); one shot, see below
==========================  ===============================================================================

How each row is run: evaluation/runners.py; the equal-time spp search: evaluation/timesearch.py; the
equal-time renderers (Mitsuba path, OIDN, the primal-only and direct-gradient G-PT renders): evaluation/baselines.py.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.evaluation.cache import REPO_ROOT
from gradsep.model import methods as table

__all__ = [
    "ABLATION_VARIANTS",
    "EVALUATION_NAMES",
    "evaluated_methods",
    "evaluation_name",
    "MethodOutput",
    "MethodSpec",
    "EQUAL_TIME_KINDS",
    "EQUAL_TIME_OFFSETS",
    "BracketOutput",
    "FEATURE_SPP",
    "METHOD_SOURCES",
    "PLANNER_SOURCES",
    "PLAN_ROW_KEYS",
    "unavailable",
    "method_by_name",
]

#: Samples per pixel of the feature pass that gives ``path-oidn`` its albedo and normal: a production renderer
#: writes them nearly for free; 4 spp antialiases edges well enough for OIDN, which prefilters them anyway.
FEATURE_SPP = 4
#: Source files whose changes alter a method's images or scores (part of every result's cache key): every module
#: of model/, so that a helper a method reaches (the exposure rule, the back-off) cannot be left out of the key,
#: the modules that run the rows, and evaluation/run.py, which sets the process every row is timed in (what stays
#: loaded changes the timings).
METHOD_SOURCES: tuple[str, ...] = ("evaluation/methods.py", "evaluation/runners.py", "evaluation/timesearch.py",
                                   "evaluation/baselines.py", "evaluation/run.py",
                                   *sorted(f"model/{p.name}" for p in (REPO_ROOT / "model").glob("*.py")))
#: The render planner's source files: part of the ``gpt-auto`` row's cache key (with the renderer's), so a planner
#: change recomputes that row, and only that row.
PLANNER_SOURCES: tuple[str, ...] = ("renderer/planner.py", "renderer/plans.py", "renderer/passes.py",
                                     "renderer/checkpoint.py", "renderer/frame_budget.py",
                                     "renderer/reconstruction_cost.py", "renderer/budget.py", "renderer/estimate.py",
                                     "renderer/check.py", "renderer/render.py", "renderer/planned_frame.py")
#: What a ``gpt-auto`` row records of its plan (MethodOutput.extra -> the row; evaluation/report.py reads them).
PLAN_ROW_KEYS: tuple[str, ...] = ("plan", "plan_layers", "plan_method", "plan_candidates", "predicted_relmse",
                                  "predicted_note", "predicted_from", "pilot_seconds", "plan_note",
                                  "gradient_spp")


@dataclass(frozen=True)
class MethodSpec:
    """One compared method. ``models`` is the folder under the models directory that holds its ONNX files."""

    name: str
    label: str
    kind: str  # primal | recon | network | path | oidn | sep-oidn | gpt-equal | gpt-auto
    method: str | None = None  # recon, gpt-equal: the method of the table (model/methods.py) it runs
    models: str | None = None
    short: str = ""  # its label in Table 1 and the crops (default: ``label``)
    separated: bool | None = None  # network: per-layer models (True) or the color model on the sum (False)
    attention: bool | None = None  # for the ablation table
    #: G-PT render mode of the frame it reconstructs (``gradsep render --gradients``): ``direct`` for a method
    #: that integrates only the direct layer's gradients, so its frame traces no offsets past the direct
    #: layer's vertices and its render time (which the equal-time budget counts) is that mode's.
    gradients: str = "all"

    @property
    def model_sets(self) -> tuple[str, ...]:
        """The model-folder sets (model.methods.MODEL_SETS) of the table method a ``recon`` row runs."""
        return table.get(self.method).model_sets if self.kind == "recon" and self.method else ()

    def model_names(self, layers: tuple[str, ...]) -> tuple[str, ...]:
        """The model files (``NAME.onnx``) this method needs for a frame with ``layers``: a ``recon`` row's, what
        its own model set (the first model folder of the table's method) declares (model.methods.ModelSet)."""
        if self.model_sets:
            return table.MODEL_SETS[self.model_sets[0]].model_files(layers)
        if self.kind != "network":
            return ()
        return tuple(layers) if self.separated else ("color",)

    def optional_model_files(self, layers: tuple[str, ...]) -> tuple[str, ...]:
        """Model files (relative to the models folder) this method reads when they are there and does without
        otherwise, as its model set declares them (``fused``'s clean-layer average reads the ``network`` method's
        direct model). Their checksums join the result's cache key; their absence skips nothing."""
        if not self.model_sets:
            return ()
        files = table.MODEL_SETS[self.model_sets[0]].optional_model_files(layers)
        return tuple(os.path.normpath(Path(self.models or "") / f) for f in files)


ABLATION_VARIANTS: tuple[tuple[str, bool, bool], ...] = (
    # (variant, separated, attention) in the order of the paper's Fig. 7 (a)-(d)
    ("combined-noattn", False, False),
    ("separated-noattn", True, False),
    ("combined-attn", False, True),
    ("separated-attn", True, True),
)

#: The evaluation's name of a method of the table where the paper's name differs: the network is "ours".
EVALUATION_NAMES: dict[str, str] = {"network": "ours"}
#: (label, short label) of the table's methods in the report; a method without one is labelled by its name and
#: description.
_LABELS: dict[str, tuple[str, str]] = {
    "network": ("Ours (separated + attention)", "Ours"),
    "l1": ("L1 Poisson", "L1"),
    "l2": ("L2 Poisson", "L2"),
    "oidn": ("G-PT + OIDN per layer", "G-PT + OIDN per layer"),
    "oidn-l1": ("G-PT + OIDN, direct refined by its gradients (L1)", "OIDN + gradients (direct)"),
    "fused": ("Fused network", "Fused"),
}


def evaluation_name(method: str) -> str:
    """The row name of the table's method ``method`` (``network`` is ``ours``)."""
    return EVALUATION_NAMES.get(method, method)


def _table_row(method: table.Method) -> MethodSpec:
    """The row of one method of the table: ``reconstruct(frame, method)`` on the G-PT frame its gradients need."""
    label, short = _LABELS.get(method.name, (f"{method.name}: {method.description}", method.name))
    folder = next((table.MODEL_SETS[n].folder for n in method.model_sets), None)
    return MethodSpec(evaluation_name(method.name), label, "recon", method=method.name,
                      models=None if folder is None else "" if folder == "." else folder, short=short,
                      gradients="direct" if method.gradients == "direct" else "all")


def evaluated_methods() -> tuple[MethodSpec, ...]:
    """Every compared method, in the report's order: the input, each method of the table (model/methods.py, as
    it stands when called), the paper's baselines and ablations, then the equal-time rows."""
    return (
        MethodSpec("gpt-primal", "Input (G-PT primal)", "primal", short="Input"),
        *(_table_row(m) for m in table.methods()),
        MethodSpec("gradnet", "GradNet-style (color model)", "network", models="", separated=False, attention=False,
                   short="GradNet-style"),
        *(MethodSpec(f"ablation/{v}", f"Ablation {v}", "network", models=f"ablation/{v}", separated=s, attention=a)
          for v, s, a in ABLATION_VARIANTS),
        MethodSpec("path", "Mitsuba path (equal time)", "path"),
        MethodSpec("path-oidn", "Mitsuba path + OIDN (equal time)", "oidn", short="path + OIDN (equal time)"),
        MethodSpec("path-sep-oidn", "Separated path + OIDN per layer (equal time)", "sep-oidn",
                   short="sep. path + OIDN per layer (equal time)"),
        MethodSpec("gpt-oidn-l1", "G-PT (direct gradients) + oidn-l1 (equal time)", "gpt-equal", method="oidn-l1",
                   gradients="direct", short="G-PT + oidn-l1 (equal time)"),
        MethodSpec("gpt-auto", "G-PT planned (--gradients auto) + default method (equal time)", "gpt-auto",
                   short="G-PT auto (equal time)"),
    )


#: Methods rendered to a time budget rather than reconstructing the G-PT frame.
EQUAL_TIME_KINDS: tuple[str, ...] = ("path", "oidn", "sep-oidn", "gpt-equal", "gpt-auto")
#: Offsets of the equal-time G-PT row's render (``gradsep render --offsets``): ``alternate`` traces one offset per
#: axis (every pixel pair keeps both MIS techniques on half the samples), so the budget buys more samples; chosen
#: on held-out procedural scenes, docs/evaluation.md "Equal-time G-PT".
EQUAL_TIME_OFFSETS = "alternate"


def unavailable(spec: MethodSpec) -> str | None:
    """Why ``spec`` cannot run on this host (None: it can). Model files are checked separately."""
    needs_oidn = spec.kind in ("oidn", "sep-oidn", "gpt-equal", "gpt-auto") or (
        spec.kind == "recon" and "oidn" in table.get(str(spec.method)).models)
    if needs_oidn and not table.LoadedModels().has("oidn"):
        return "pyoidn is not installed (pip install 'gradsep[evaluate]')"
    return None


def method_by_name(name: str) -> MethodSpec:
    for spec in evaluated_methods():
        if spec.name == name:
            return spec
    raise KeyError(name)


@dataclass
class MethodOutput:
    """What one method produced for one (scene, spp)."""

    image: np.ndarray
    layers: dict[str, np.ndarray]
    render_seconds: float
    reconstruct_seconds: float
    method_spp: int
    extra: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    # An equal-time row outside the tolerance whose budget lies between two tries: both tries' outputs, the
    # too-fast one first, so the row's metrics can be interpolated to the budget (evaluation.run scores them).
    bracket: list[BracketOutput] = field(default_factory=list)


@dataclass
class BracketOutput:
    """One try of an equal-time row's bracket, as the row would be had it been kept."""

    spp: int
    render_seconds: float
    reconstruct_seconds: float
    image: np.ndarray
    layers: dict[str, np.ndarray]

    @property
    def total_seconds(self) -> float:
        return self.render_seconds + self.reconstruct_seconds
