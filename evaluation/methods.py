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
                            process (renderer.plan.render_planned: a checkpoint on the frame's halves keeps
                            direct-alternate or goes on with primal, passes fill the deadline), reconstructed with
                            the default method the frame names (``gradsep.plan_method``); one shot, see below
==========================  ===============================================================================

Equal time: the budget of a G-PT spp is the G-PT render time plus the reconstruction time of the product's default
method for a G-PT frame (the first of the methods table's default preference that was evaluated, ``oidn-l1``:
evaluation.run._budget_method; the report names it). Each equal-time
renderer's cost on the scene is measured first as ``seconds = overhead + per_spp · spp``, a line fitted to warm
renders (after an untimed 1-spp render that pays the JIT compilation, which a user rendering a sequence pays once:
1, 4, 16, ... spp, each the faster of two, until one takes a quarter second; every later render adds a point). A
*try* is a render plus its post-processing (the OIDN call(s)), timed together; ``path-oidn``'s feature pass is
rendered once per row and taken off the budget first. The spp is *interpolated on the measured time curve*
(:class:`TimeSearch`): the first try at the line's prediction (for the budget less a pre-measured post-processing
time); while a try's measured total misses the target by more than :data:`PathRenderer.TOLERANCE` (5 %), a line time
= a + b · spp through the tries so far is solved for the target (a secant step anchored at the closest try; the
bracket's midpoint when it points at a tried spp), short or surprising tries timed three times (median), at most
:data:`PathRenderer.MAX_ATTEMPTS` tries. The row keeps the try closest to the target and records its tries and, when
it is still outside ±5 %, why (1 spp already over budget, the spp cap, integer granularity, timing noise); the
report lists every such row with that reason. Such a row with tries on both sides of the budget keeps both
(:attr:`Attempt.bracket`, :attr:`MethodOutput.bracket`) and its metrics are interpolated to the budget in log time
(evaluation.run.interpolated_scores; the report marks it). The time in the results is the time the kept try actually
took (the median of its timings), not the prediction.

The planned row (``gpt-auto``) is not searched: it renders once to a :class:`~renderer.budget.Deadline` that starts
when the row starts and has the whole budget, whose tail (``Deadline.tail``, what must be left when the last pass
ends) is the measured cost of reconstructing the frame: the slowest of the candidates' default reconstructions,
each timed like a searched row's post-processing (:meth:`PathRenderer.planner_tail`). It starts warm, as the
searched rows do: each plan's pass costs and the reconstruction's rate are measured beforehand, untimed, once per
scene (:meth:`PathRenderer.planner_priors`, renderer.plan.Priors), so that where no checkpoint fits its first pass
is sized from them instead of probing with a 1-spp pass. Everything it does is charged:
the checkpoint (its passes, which stay in the frame, and its tile reconstructions), the passes that fill the
deadline and the reconstruction. It keeps one try (``attempts`` 1); a total outside ±5 % records why
(``time_note``: pass granularity, a pass or the reconstruction slower than predicted, a budget below one pass).
Its ``extra`` records the plan chosen, each judged plan's predicted RelMSE and the chosen one's
(``predicted_relmse``; None with ``predicted_note`` where no checkpoint fitted and the planner rendered its
fallback).

Timings exclude one-time costs on both sides: each network is run once untimed per frame size (ONNX
Runtime's allocation on a new shape), Mitsuba's kernels are compiled before the timed render. The G-PT
render time is the renderer's own (``gradsep.render_seconds``), which includes its per-frame tracing. The planned
row's kernels (one per candidate) and its reconstruction (on the frame's and the pilot tiles' sizes) are run once
untimed per scene; its per-frame tracing is timed.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.evaluation.cache import REPO_ROOT
from gradsep.model import methods as table
from gradsep.model.frame import Frame

__all__ = [
    "ABLATION_VARIANTS",
    "EVALUATION_NAMES",
    "evaluated_methods",
    "MethodContext",
    "MethodOutput",
    "MethodSpec",
    "NetworkPool",
    "EQUAL_TIME_KINDS",
    "Attempt",
    "Bracketed",
    "BracketOutput",
    "interpolate_at",
    "TIME_SEARCH",
    "TimeSearch",
    "FEATURE_SPP",
    "PLANNER_SOURCES",
    "PLAN_ROW_KEYS",
    "PathRenderer",
    "CostModel",
    "unavailable",
    "method_by_name",
    "run_method",
]

_F32_MAX = float(np.finfo(np.float32).max)
MAX_WAVEFRONT = (1 << 32) - 1  # Mitsuba's samples per launch
#: Samples per pixel of the feature pass that gives ``path-oidn`` its albedo and normal: a production renderer
#: writes them nearly for free; 4 spp antialiases edges well enough for OIDN, which prefilters them anyway.
FEATURE_SPP = 4
#: Source files whose changes alter a method's images or scores (part of every result's cache key): every module
#: of model/, so that a helper a method reaches (the exposure rule, the back-off) cannot be left out of the key,
#: and evaluation/run.py, which sets the process every row is timed in (what stays loaded: a change there once
#: made every pass several times dearer, and cached rows would have kept the old timings).
METHOD_SOURCES: tuple[str, ...] = ("evaluation/methods.py", "evaluation/run.py",
                                   *sorted(f"model/{p.name}" for p in (REPO_ROOT / "model").glob("*.py")))
#: The render planner's source files: part of the ``gpt-auto`` row's cache key (with the renderer's), so a planner
#: change recomputes that row, and only that row.
PLANNER_SOURCES: tuple[str, ...] = ("renderer/plan.py", "renderer/budget.py", "renderer/estimate.py",
                                     "renderer/check.py", "renderer/render.py")
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


# ------------------------------------------------------------------------------------------------ networks


class NetworkPool:
    """Loaded ONNX reconstructors by folder, with the untimed warm-up runs per frame size.

    A model that exists but cannot be served (corrupt, exported for another layer) is an error the user has to
    fix, raised as ``ModelError`` -- not a method silently skipped.
    """

    def __init__(self) -> None:
        self._loaded: dict[Path, Any] = {}
        self._warm: set[tuple[Path, str, tuple[int, int]]] = set()

    def loaded(self, models_dir: Path, method: str) -> table.LoadedModels:
        """The model sets the table's ``method`` needs, each loaded once from ``models_dir`` by its own loader."""
        sets: dict[str, Any] = {}
        for name in table.get(method).model_sets:
            key = (models_dir.resolve() / f"<{name}>")
            if key not in self._loaded:
                self._loaded[key] = table.resolve(table.MODEL_SETS[name].loader)(models_dir)
            sets[name] = self._loaded[key]
        return table.LoadedModels(**sets)

    def get(self, folder: Path, fused: bool = False) -> Any:
        """The folder's network models, or with ``fused`` its fused blend models (model.fused)."""
        folder = folder.resolve()
        if folder not in self._loaded:
            if fused:
                from gradsep.model.fused import BlendModelError, FusedReconstructor
                from gradsep.model.infer import ModelError

                try:
                    self._loaded[folder] = FusedReconstructor.load(folder)
                except BlendModelError as exc:
                    raise ModelError(str(exc)) from exc
            else:
                from gradsep.model.infer import NetworkReconstructor

                self._loaded[folder] = NetworkReconstructor.load(folder)
        return self._loaded[folder]

    def warm_up(self, folder: Path, run: Callable[[], object], key: str, shape: tuple[int, int]) -> None:
        """Run ``run`` once untimed the first time ``key`` meets a frame of ``shape`` in ``folder``."""
        tag = (folder.resolve(), key, shape)
        if tag not in self._warm:
            run()
            self._warm.add(tag)


def _sanitise(image: np.ndarray) -> np.ndarray:
    """Finite and >= 0, as model.reconstruct does for its outputs (the combined-model path bypasses it)."""
    out = np.nan_to_num(np.asarray(image, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(out, 0.0, _F32_MAX)


# ------------------------------------------------------------------------------------------- Mitsuba path


class CostModel:
    """seconds ≈ overhead + per_spp · spp for one integrator on one scene and film, fitted to measured renders.

    Every timed render adds a sample, so predictions get better as the run goes on; a least-squares line
    through all samples (overhead clamped at 0, slope kept positive) is robust to one noisy measurement.
    """

    def __init__(self, max_spp: int) -> None:
        self.max_spp = max_spp
        self.samples: list[tuple[int, float]] = []

    def add(self, spp: int, seconds: float) -> None:
        if spp >= 1 and math.isfinite(seconds) and seconds >= 0:
            self.samples.append((int(spp), float(seconds)))

    @property
    def largest_sampled(self) -> int:
        return max((s for s, _ in self.samples), default=0)

    def fit(self) -> tuple[float, float]:
        """(overhead, per_spp); with a single distinct spp the overhead is taken as 0."""
        if not self.samples:
            raise RuntimeError("cost model has no measurements")
        x = np.array([s for s, _ in self.samples], dtype=np.float64)
        y = np.array([t for _, t in self.samples], dtype=np.float64)
        per_spp = 0.0
        if np.ptp(x) > 0:
            per_spp = float(np.polyfit(x, y, 1)[0])
        if not per_spp > 0:  # one spp only, or noise made the larger render faster: no overhead
            per_spp = max(float(np.sum(y) / np.sum(x)), 1e-9)
        overhead = max(0.0, float(np.mean(y - per_spp * x)))
        return overhead, per_spp

    def spp_for(self, seconds: float) -> int:
        """The largest spp whose predicted time fits ``seconds`` (at least 1, at most ``max_spp``)."""
        if not math.isfinite(seconds):
            return 1
        overhead, per_spp = self.fit()
        # a quotient a rounding error short of a whole spp counts as that spp
        spp = math.floor((seconds - overhead) / per_spp + 1e-9)
        return int(min(self.max_spp, max(1, spp)))


@dataclass
class Attempt:
    """The try :meth:`PathRenderer.render_within` kept: its output (after ``post``), times, spp, tries made."""

    output: Any
    render_seconds: float
    post_seconds: float
    spp: int
    attempts: int
    miss: float  # |measured / target - 1|
    tries: list[tuple[int, float]] = field(default_factory=list)  # (spp, measured total) of every try
    note: str = ""  # why the kept try is outside the tolerance ("" when it is within)
    # When the kept try is outside the tolerance: the closest too-fast and too-slow tries (the budget lies
    # between their measured times), so the row's error can be interpolated to the budget (see interpolate_at).
    bracket: tuple[Bracketed, Bracketed] | None = None


@dataclass
class Bracketed:
    """One side of an :class:`Attempt`'s bracket: a try's spp, median timing and output (after ``post``)."""

    spp: int
    render_seconds: float
    post_seconds: float
    output: Any

    @property
    def seconds(self) -> float:
        return self.render_seconds + self.post_seconds


def interpolate_at(target: float, low: tuple[float, float], high: tuple[float, float], *, log_value: bool) -> float:
    """The value at time ``target`` on the line through ``low`` and ``high`` = (seconds, value), in log time
    and, with ``log_value``, log value (an error falling as a power of time is a straight line there: RelMSE
    ∝ 1/spp and time ≈ a + b·spp); linear in the value where it is not positive. ``target`` is expected between
    the two times; outside, the line is extended."""
    (t0, v0), (t1, v1) = low, high
    if not (t0 > 0 and t1 > 0 and target > 0) or t0 == t1:
        return v0 if abs(target - t0) <= abs(target - t1) else v1
    w = (math.log(target) - math.log(t0)) / (math.log(t1) - math.log(t0))
    if log_value and v0 > 0 and v1 > 0:
        return math.exp((1 - w) * math.log(v0) + w * math.log(v1))
    return (1 - w) * v0 + w * v1


#: How the equal-time spp is found (recorded per row and stated by the report).
TIME_SEARCH = "interpolated on the measured time curve"


@dataclass
class _Timed:
    """One try: the spp, its kept output, and the timings of each repeat (render, post)."""

    spp: int
    output: Any
    timings: list[tuple[float, float]]

    @property
    def totals(self) -> list[float]:
        return [r + p for r, p in self.timings]

    @property
    def seconds(self) -> float:
        return float(np.median(self.totals))

    def median_timing(self) -> tuple[float, float]:
        """The (render, post) repeat whose total is the median (lower median for an even count)."""
        order = sorted(range(len(self.timings)), key=lambda i: self.totals[i])
        return self.timings[order[(len(order) - 1) // 2]]


class TimeSearch:
    """The spp whose measured time (render + post-processing) is within ``tolerance`` of ``target``.

    Time is modelled as ``a + b · spp`` (a: fixed per-render cost, launch + denoiser; b: cost per sample). The
    slope comes from the renderer's calibration (``slope``, with ``overhead`` its expected fixed cost: any excess
    of the first try over that line is read as a steeper slope, the cautious reading) until this search has
    measured two spp far enough apart to fit its own; the line is then anchored at the measured try closest to
    the target and solved for it (a secant step on the measured curve: a fixed overhead or a mis-predicted
    slope costs one try, not a bisection). When the line points at an spp already tried, the next try bisects
    the closest too-fast/too-slow bracket, or re-times that spp. Short tries (under ``repeat_below`` seconds,
    where a load spike is a large share of the time) and any try more than 3 x the tolerance off the line's
    prediction (a spike, or a wrong line) are timed ``repeats`` times and their median used, so one noisy
    timing neither stops the search nor walls off the right spp. It gives up, saying why, when the target is
    impossible (1 spp already too slow, the spp cap too fast), when two adjacent spp straddle it (integer
    granularity, or noise when the jump is larger than one sample's cost), or after ``max_tries`` tries.
    """

    def __init__(self, target: float, slope: float, max_spp: int, *, overhead: float = 0.0,
                 tolerance: float = 0.05, max_tries: int = 8, repeat_below: float = 2.0, repeats: int = 3) -> None:
        self.target, self.slope, self.max_spp = target, max(slope, 1e-12), max_spp
        self.overhead = max(0.0, overhead)
        self.tolerance, self.max_tries = tolerance, max_tries
        self.repeat_below, self.repeats = repeat_below, repeats
        self.tried: dict[int, _Timed] = {}
        self.made = 0  # tries made, re-timings of a tried spp included

    def miss(self, seconds: float) -> float:
        return seconds / self.target - 1.0 if self.target > 0 else math.inf

    def run(self, measure: Callable[[int], tuple[Any, float, float]], first_spp: int) -> Attempt:
        """Search from ``first_spp``; ``measure(spp)`` -> (output, render seconds, post seconds)."""
        spp: int | None = max(1, min(self.max_spp, int(first_spp)))
        note = ""
        predicted = self.overhead + self.slope * spp
        while spp is not None and self.made < self.max_tries:
            timed = self._measure(measure, spp, predicted)
            if abs(self.miss(timed.seconds)) <= self.tolerance:
                break
            spp, note = self._next(spp)
            predicted = self.target  # the line was solved for the target at the next spp
        else:
            if spp is not None:
                note = self._exhausted()
        best = min(self.tried.values(), key=lambda t: abs(self.miss(t.seconds)))
        render, post = best.median_timing()
        miss = abs(self.miss(render + post))
        tries = [(t.spp, round(t.seconds, 4)) for t in self.tried.values()]
        outside = miss > self.tolerance
        return Attempt(best.output, render, post, best.spp, self.made, miss, tries, note if outside else "",
                       self._bracket() if outside else None)

    def _bracket(self) -> tuple[Bracketed, Bracketed] | None:
        """The slowest too-fast and the fastest too-slow try, when there are both (the budget between them)."""
        fast = [t for t in self.tried.values() if t.seconds < self.target]
        slow = [t for t in self.tried.values() if t.seconds > self.target]
        if not fast or not slow:
            return None
        sides = (max(fast, key=lambda t: t.seconds), min(slow, key=lambda t: t.seconds))
        return tuple(Bracketed(t.spp, *t.median_timing(), t.output) for t in sides)  # type: ignore[return-value]

    def _measure(self, measure: Callable[[int], tuple[Any, float, float]], spp: int, predicted: float) -> _Timed:
        self.made += 1
        if spp in self.tried:  # a re-timing: more repeats of a spp whose median sits on the wrong side
            timed = self.tried[spp]
            timed.timings += [measure(spp)[1:] for _ in range(self.repeats - 1)]
            return timed
        output, render, post = measure(spp)
        timed = _Timed(spp, output, [(render, post)])
        surprise = abs((render + post) / max(predicted, 1e-12) - 1.0) > 3 * self.tolerance
        if render + post < self.repeat_below or surprise:
            timed.timings += [measure(spp)[1:] for _ in range(self.repeats - 1)]
        self.tried[spp] = timed
        return timed

    def _fit_slope(self) -> float:
        """The per-spp slope near the target: least squares over the (up to) three tries closest to it when their
        spp span at least 5 % of the largest (local, because the time curve bends: caches, a denoiser's fixed
        cost), kept within [1/3, 3] x the calibrated slope so noise cannot flip or explode it; with one try, its
        excess over the calibrated line read as slope; else the calibrated slope."""
        near = sorted(self.tried.values(), key=lambda t: abs(self.miss(t.seconds)))[:3]  # local: the curve bends
        spps = np.array([t.spp for t in near], dtype=np.float64)
        if len(spps) >= 2 and np.ptp(spps) >= 0.05 * spps.max():
            seconds = np.array([t.seconds for t in near])
            fitted = float(np.polyfit(spps, seconds, 1)[0])
            return float(np.clip(fitted, self.slope / 3, self.slope * 3))
        if len(self.tried) == 1:  # one try slower than the calibrated line: its excess is read as slope
            (spp, timed), = self.tried.items()
            return float(np.clip((timed.seconds - self.overhead) / spp, self.slope, self.slope * 3))
        return self.slope

    def _next(self, spp: int) -> tuple[int | None, str]:
        """The next spp to try after ``spp`` missed (None: stop, with the reason)."""
        seconds = self.tried[spp].seconds
        if spp <= 1 and seconds > self.target:
            return None, f"1 spp alone takes {seconds:.3g} s (render + post-processing), over the budget"
        if spp >= self.max_spp and seconds < self.target:
            return None, f"the spp cap ({self.max_spp}) takes only {seconds:.3g} s"
        anchor = min(self.tried.values(), key=lambda t: abs(self.miss(t.seconds)))
        guess = anchor.spp + (self.target - anchor.seconds) / self._fit_slope()
        following = int(max(1, min(self.max_spp, round(guess))))
        if following in self.tried:  # the line points at a tried spp: step to its neighbour towards the target
            step = 1 if self.tried[following].seconds < self.target else -1
            following = max(1, min(self.max_spp, following + step))
        straddle = self._straddle()
        if straddle:
            low, high = straddle
            t0, t1 = self.tried[low].seconds, self.tried[high].seconds
            # one sample's cost above the tolerance band is granularity; a larger jump than the slope allows is noise
            if self._fit_slope() >= self.tolerance * self.target:
                return None, f"spp granularity: {low} spp takes {t0:.3g} s, {high} spp {t1:.3g} s"
            # a jump larger than one sample costs is noise: re-time the side further off, once
            retime = max((low, high), key=lambda s: abs(self.miss(self.tried[s].seconds)))
            if len(self.tried[retime].timings) <= self.repeats:
                return retime, ""
            return None, f"timing noise (adjacent spp): {low} spp takes {t0:.3g} s, {high} spp {t1:.3g} s"
        if following in self.tried:
            return self._bracket_or_retime(following)
        return following, ""

    def _bracket_or_retime(self, spp: int) -> tuple[int | None, str]:
        """The line points at tried ``spp``: bisect the closest too-fast / too-slow bracket when it has an untried
        spp inside, else re-time ``spp`` (once: its repeats may have been unlucky), else stop."""
        fast = [s for s, t in self.tried.items() if t.seconds < self.target]
        slow = [s for s, t in self.tried.items() if t.seconds > self.target]
        if fast and slow and max(fast) < min(slow):
            middle = (max(fast) + min(slow)) // 2
            if middle not in self.tried:
                return middle, ""
        if len(self.tried[spp].timings) <= self.repeats:
            return spp, ""
        return None, f"timing noise: the measured time curve is flat near {spp} spp"

    def _straddle(self) -> tuple[int, int] | None:
        """Two adjacent spp, one too fast and one too slow (no integer spp lands within the tolerance)."""
        for s, t in self.tried.items():
            above = self.tried.get(s + 1)
            if above is not None and t.seconds < self.target < above.seconds:
                return s, s + 1
        return None

    def _exhausted(self) -> str:
        spread = max((max(t.totals) - min(t.totals)) / t.seconds for t in self.tried.values())
        noisy = spread > 2 * self.tolerance
        return (f"{self.max_tries} tries" + (f"; repeated timings of one spp differed by up to {spread:.0%} "
                                             "(timing noise)" if noisy else ""))


class PathRenderer:
    """The equal-time renderers on one loaded scene, each with its cost model.

    Kinds: ``path`` (Mitsuba ``path``, raw colour), ``features`` (Mitsuba ``aov``: albedo and shading normal
    only, the cheap pass feeding OIDN), ``primal`` (our renderer's primal-only mode, a gradient-free Frame) and
    ``gpt-direct`` (our G-PT renderer, ``--gradients direct``, offsets :data:`EQUAL_TIME_OFFSETS`: a Frame).
    """

    #: Calibration renders grow ×4 from 1 spp until one takes this long: shorter ones are all noise and
    #: overhead on a busy machine.
    CALIBRATION_SECONDS = 0.25
    #: A prediction more than this many times the largest measured spp is probed at a quarter first.
    EXTRAPOLATION = 8
    #: A render is accepted when its measured time is within this fraction of its target.
    TOLERANCE = 0.05
    #: Tries (distinct spp) per row before the one closest to the target is kept.
    MAX_ATTEMPTS = 8
    #: Tries shorter than this are timed REPEATS times and their median used (noise is a larger share of them).
    REPEAT_BELOW = 2.0
    REPEATS = 3

    def __init__(self, loaded: Any) -> None:
        import mitsuba as mi

        self.loaded = loaded
        path = {"type": "path", "max_depth": int(loaded.max_depth), "rr_depth": int(loaded.rr_depth)}
        self.integrators = {
            "path": mi.load_dict(path),
            # albedo and shading normal only (no nested integrator): what a production renderer writes cheaply
            "features": mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal"}),
        }
        self.max_spp = max(1, MAX_WAVEFRONT // max(1, loaded.width * loaded.height))
        self._costs: dict[str, CostModel] = {}
        self._post_seconds: dict[str, float] = {}
        self._warm: set[str] = set()
        self._priors: dict[tuple[str, ...], Any] = {}  # layers -> renderer.plan.Priors (planner_priors)

    def render(self, kind: str, spp: int, seed: int) -> tuple[Any, float]:
        """The raw render (an (H, W, C) float32 array, or a Frame for ``primal``) and its wall seconds (recorded
        in the cost model once calibrated)."""
        start = time.perf_counter()
        if kind == "primal":
            from gradsep.renderer.render import render_frame

            output: Any = render_frame(self.loaded, spp=int(spp), seed=int(seed) % (1 << 32), gradients=False)
        elif kind == "gpt-direct":
            from gradsep.renderer.render import render_frame

            output = render_frame(self.loaded, spp=int(spp), seed=int(seed) % (1 << 32), gradients="direct",
                                  offsets=EQUAL_TIME_OFFSETS)
        else:
            import mitsuba as mi

            image = mi.render(self.loaded.scene, sensor=self.loaded.sensor, integrator=self.integrators[kind],
                              spp=int(spp), seed=int(seed) % (1 << 32))
            output = np.array(image, dtype=np.float32)
        seconds = time.perf_counter() - start
        if kind in self._costs:
            self._costs[kind].add(spp, seconds)
        return output, seconds

    def warm(self, kind: str) -> None:
        """One untimed 1-spp render: Dr.Jit's kernel compilation, paid once per scene and kind."""
        if kind not in self._warm:
            self.render(kind, 1, 7)
            self._warm.add(kind)

    def planner_tail(self, layers: tuple[str, ...]) -> float:
        """The planned row's reconstruction time on this scene: the slowest of the planner's candidates' default
        reconstructions (model.reconstruct's default for the candidate's frame: ``oidn-l1`` with gradients,
        ``oidn`` for a plain frame; the plan is not known before its pilot), each measured by
        :meth:`post_seconds` on a 1-spp frame of that candidate. Measured once per scene; the first call also
        compiles each candidate's kernel and runs the reconstruction once on the pilot's tile size (one-time
        costs, untimed like every row's)."""
        from gradsep.model.reconstruct import reconstruct
        from gradsep.renderer.plan import Passes, applicable, as_frame, crop, tiles

        seconds = []
        for c in applicable(layers):
            name = f"gpt-auto:{c.name}"
            if name not in self._post_seconds:
                passes = Passes(self.loaded, layers, seed=29)
                passes.run(c, 1)  # compiles (or loads) the candidate's kernel
                frame = as_frame(passes.frame_result(c))
                reconstruct(crop(frame, tiles(frame.width, frame.height)[0]))  # the pilot's tile size
                self.post_seconds(name, lambda frame=frame: reconstruct(frame))
            seconds.append(self._post_seconds[name])
        return max(seconds)

    def planner_priors(self, layers: tuple[str, ...]) -> Any:
        """What the planned row starts from (renderer.plan.Priors), measured once per scene like every searched
        row's cost model (:meth:`cost`), untimed: each candidate's warm passes, from 1 spp doubling until one takes
        :data:`CALIBRATION_SECONDS` (each size twice, the faster kept; the last two sizes make its cost line), and
        the reconstruction's seconds per pixel (:meth:`planner_tail`'s slowest, over the frame's pixels)."""
        from gradsep.renderer.budget import PassCosts
        from gradsep.renderer.plan import Passes, Priors, applicable

        if layers not in self._priors:
            priors = Priors(reconstruct_rate=self.planner_tail(layers) / (self.loaded.width * self.loaded.height),
                            reconstruct_seconds={c.name: self._post_seconds[f"gpt-auto:{c.name}"]
                                                 for c in applicable(layers)})
            for c in applicable(layers):
                passes = Passes(self.loaded, layers, seed=37)
                passes.run(c, 1)  # its kernel (loaded from Dr.Jit's cache: planner_tail compiled it)

                def timed(spp: int, passes: Any = passes, c: Any = c) -> float:
                    start = time.perf_counter()
                    passes.run(c, spp)
                    return time.perf_counter() - start

                sizes = self._calibration(lambda spp: min(timed(spp), timed(spp)), passes.max_spp, growth=2)
                costs = PassCosts(first_pass=passes.kind(c).costs.first_pass)
                for size, took in sizes[-2:]:
                    costs.record(size, took)
                priors.costs[c.name] = costs
            self._priors[layers] = priors
        return self._priors[layers]

    def cost(self, kind: str) -> CostModel:
        """The cost model of ``kind``, measured once per scene after an untimed compile render.

        Each calibration spp is rendered twice and the faster time kept: on a shared machine noise only ever
        adds time. At least two spp are measured, the last taking :data:`CALIBRATION_SECONDS` or more.
        """
        if kind not in self._costs:
            self.warm(kind)
            model = CostModel(self.max_spp)
            for spp, seconds in self._calibration(
                    lambda spp: min(self.render(kind, spp, 11)[1], self.render(kind, spp, 13)[1]), self.max_spp,
                    growth=4):
                model.add(spp, seconds)
            self._costs[kind] = model
        return self._costs[kind]

    def _calibration(self, seconds_at: Callable[[int], float], max_spp: int, growth: int) -> list[tuple[int, float]]:
        """(spp, seconds) of calibration renders (``seconds_at(spp)``, the caller's timing: the faster of two),
        from 1 spp growing ``growth``-fold until one takes :data:`CALIBRATION_SECONDS` or more with two sizes
        measured, or ``max_spp`` is reached."""
        sizes: list[tuple[int, float]] = []
        spp = 1
        while True:
            seconds = seconds_at(spp)
            sizes.append((spp, seconds))
            if (seconds >= self.CALIBRATION_SECONDS and len(sizes) >= 2) or spp >= max_spp:
                return sizes
            spp = min(max_spp, spp * growth)

    def spp_for(self, kind: str, seconds: float) -> int:
        """The spp of ``kind`` that fits ``seconds``; far extrapolations are checked by a render at a quarter of
        the prediction first (its cost is a fraction of the final render's)."""
        model = self.cost(kind)
        spp = model.spp_for(seconds)
        while spp > self.EXTRAPOLATION * model.largest_sampled:
            self.render(kind, max(1, spp // 4), 19)
            spp = model.spp_for(seconds)
        return spp

    def render_within(self, kind: str, seconds: float, seed: int, post: Callable[[Any], Any] | None = None,
                      post_estimate: float = 0.0) -> Attempt:
        """Render ``kind`` (then run ``post`` on the render, e.g. the denoiser) at the spp whose measured time,
        render + ``post``, is within :data:`TOLERANCE` of ``seconds``: :class:`TimeSearch` from the cost line's
        prediction (``post_estimate`` off the budget), with the line's slope. The try closest to the target is
        kept, with the reason when it is still outside the tolerance."""
        first = self.spp_for(kind, max(1e-6, seconds - post_estimate))
        overhead, per_spp = self.cost(kind).fit()
        search = TimeSearch(seconds, per_spp, self.max_spp, overhead=overhead + post_estimate, tolerance=self.TOLERANCE,
                            max_tries=self.MAX_ATTEMPTS, repeat_below=self.REPEAT_BELOW, repeats=self.REPEATS)

        def measure(spp: int) -> tuple[Any, float, float]:
            output, took = self.render(kind, spp, seed)
            start = time.perf_counter()
            result = post(output) if post is not None else output
            return result, took, (time.perf_counter() - start if post is not None else 0.0)

        return search.run(measure, first)

    def post_seconds(self, name: str, run: Callable[[], object]) -> float:
        """The time of a row's fixed post-processing ``run`` (a denoiser call) on this scene's frame size,
        measured once per scene on a warm device (the first call initialises it): the faster of two, as noise
        on a shared machine only adds time."""
        if name not in self._post_seconds:
            run()
            timings = []
            for _ in range(2):
                start = time.perf_counter()
                run()
                timings.append(time.perf_counter() - start)
            self._post_seconds[name] = min(timings)
        return self._post_seconds[name]


def split_features(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """albedo, normal of an ``aov(albedo, sh_normal)`` render: the 6 AOV channels come last (Mitsuba puts
    any film channels, e.g. RGB(A) of a nested integrator, before them)."""
    if image.ndim != 3 or image.shape[-1] < 6:
        raise RuntimeError(f"aov render has shape {image.shape}; expected albedo + normal channels last")
    return np.ascontiguousarray(image[..., -6:-3]), np.ascontiguousarray(image[..., -3:])


def denoise(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Intel Open Image Denoise as model/oidn.py runs it for the ``oidn`` method (one definition): the RT filter
    on HDR input at the method's setting (model.oidn.method_setting: auxiliary images, quality), exact exposure
    scaling, on OIDN's own library whatever ``$GRADSEP_OIDN_RUNTIME`` gives our methods: the baseline is OIDN as
    its users run it."""
    from gradsep.model.frame import Features
    from gradsep.model.oidn import method_setting, shared_denoiser

    denoiser = shared_denoiser(method_setting(), "library")  # the baseline is OIDN as its users run it
    aux = denoiser.prefilter(Features(np.ascontiguousarray(albedo, np.float32),
                                      np.ascontiguousarray(normal, np.float32),
                                      np.zeros(color.shape[:2], np.float32)))
    return _sanitise(denoiser.denoise(np.ascontiguousarray(color, np.float32), aux))


# ------------------------------------------------------------------------------------------------ running


@dataclass
class MethodContext:
    """Everything a method may need for one (scene, spp)."""

    frame: Frame
    render_seconds: float  # G-PT render time of ``frame``
    spp: int
    seed: int
    alpha: float
    models_dir: Path
    networks: NetworkPool
    path: Callable[[], PathRenderer]  # lazily built per scene (loads Mitsuba integrators)
    budget_seconds: float | None = None  # equal-time budget of the EQUAL_TIME_KINDS methods
    budget_method: str | None = None


def run_method(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """Run one method; ModelError for a model that exists but cannot be served."""
    runner = {"primal": _run_primal, "network": _run_network, "recon": _run_recon, "path": _run_path,
              "oidn": _run_oidn, "sep-oidn": _run_sep_oidn, "gpt-equal": _run_gpt_equal,
              "gpt-auto": _run_gpt_auto}[spec.kind]
    return runner(spec, ctx)


def _run_primal(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    layers = {name: _sanitise(layer.base) for name, layer in ctx.frame.layers.items()}
    image = _sanitise(sum(layers.values()))
    return MethodOutput(image, layers, ctx.render_seconds, 0.0, ctx.spp)


def _run_network(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    from gradsep.model.reconstruct import reconstruct

    folder = ctx.models_dir / (spec.models or "")
    network = ctx.networks.get(folder)
    frame = ctx.frame
    shape = (frame.height, frame.width)
    if spec.separated:
        def run() -> Any:
            return reconstruct(frame, "network", models=table.LoadedModels(network=network))

        ctx.networks.warm_up(folder, run, "separated", shape)
        start = time.perf_counter()
        result = run()
        seconds = time.perf_counter() - start
        return MethodOutput(result.image, result.layers, ctx.render_seconds, seconds, ctx.spp,
                            warnings=list(result.warnings))

    def run_combined() -> np.ndarray:
        return _sanitise(network.reconstruct_layer("color", frame.combined(), frame.features))

    ctx.networks.warm_up(folder, run_combined, "color", shape)
    start = time.perf_counter()
    image = run_combined()
    seconds = time.perf_counter() - start
    return MethodOutput(image, {}, ctx.render_seconds, seconds, ctx.spp)


def _run_recon(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """``reconstruct(frame, method)`` with the model sets the method needs (model/methods.py). A method that needs
    models or OIDN is run once untimed per frame size first (ONNX Runtime's allocation on a new shape, the OIDN
    device); a model that exists but cannot be served raises ModelError at load."""
    from gradsep.model.reconstruct import reconstruct

    method = table.get(str(spec.method))
    models = ctx.networks.loaded(ctx.models_dir, method.name)

    def run() -> Any:
        return reconstruct(ctx.frame, method.name, ctx.alpha, models)

    if method.models:
        folder = ctx.models_dir / (spec.models or "")
        ctx.networks.warm_up(folder, run, f"recon:{method.name}", (ctx.frame.height, ctx.frame.width))
    start = time.perf_counter()
    result = run()
    seconds = time.perf_counter() - start
    return MethodOutput(result.image, result.layers, ctx.render_seconds, seconds, ctx.spp,
                        extra={"alpha": ctx.alpha} if method.alpha else {}, warnings=list(result.warnings))


def _budget(ctx: MethodContext) -> float:
    if ctx.budget_seconds is None:
        raise RuntimeError("equal-time methods need a budget (the G-PT render + reconstruction time)")
    return ctx.budget_seconds


def _run_path(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    renderer = ctx.path()
    target = _budget(ctx)
    got = renderer.render_within("path", target, ctx.seed)
    return MethodOutput(_sanitise(got.output[..., :3]), {}, got.render_seconds, 0.0, got.spp,
                        extra=_equal_time_extra(ctx, target, got, renderer.max_spp),
                        bracket=_bracket_outputs(got, lambda raw: (_sanitise(raw[..., :3]), {})))


def _run_oidn(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """``path`` + OIDN: a timed :data:`FEATURE_SPP`-spp feature pass, then ``path`` + the denoiser call tried
    at spp bisected until both together fit what is left of the budget."""
    renderer = ctx.path()
    target = _budget(ctx)
    renderer.warm("features")
    features, feature_seconds = renderer.render("features", FEATURE_SPP, ctx.seed ^ 0x5EED)
    albedo, normal = split_features(features)
    colour = np.ones(albedo.shape, np.float32)
    estimate = renderer.post_seconds("path-oidn", lambda: denoise(colour, albedo, normal))
    got = renderer.render_within("path", max(1e-6, target - feature_seconds), ctx.seed,
                                 post=lambda raw: denoise(raw[..., :3], albedo, normal), post_estimate=estimate)
    extra = _equal_time_extra(ctx, target, got, renderer.max_spp)
    extra["feature_spp"] = FEATURE_SPP
    return MethodOutput(got.output, {}, got.render_seconds + feature_seconds, got.post_seconds, got.spp, extra=extra,
                        bracket=_bracket_outputs(got, lambda image: (image, {}), extra_render=feature_seconds))


def _run_sep_oidn(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """The primal-only G-PT render (separated layers, first-hit features, no gradients) reconstructed with the
    ``oidn`` method (OIDN on each layer, summed: model/oidn.py), render + reconstruction bisected to the budget."""
    return _run_frame_within(spec, ctx, "primal", "oidn")


def _run_gpt_equal(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """Our G-PT render (``--gradients direct``, :data:`EQUAL_TIME_OFFSETS`) reconstructed with ``spec.method``
    (``oidn-l1``), render + reconstruction bisected to the budget like the baselines'."""
    return _run_frame_within(spec, ctx, "gpt-direct", str(spec.method))


def _run_frame_within(spec: MethodSpec, ctx: MethodContext, kind: str, method: str) -> MethodOutput:
    """A Frame-producing renderer ``kind`` + ``reconstruct(frame, method)`` at the spp whose measured total fits
    the budget (:meth:`PathRenderer.render_within`)."""
    from gradsep.model.reconstruct import reconstruct

    renderer = ctx.path()
    target = _budget(ctx)
    renderer.warm(kind)
    sample, _ = renderer.render(kind, 1, 23)
    estimate = renderer.post_seconds(spec.name, lambda: reconstruct(sample, method))
    got = renderer.render_within(kind, target, ctx.seed, post=lambda frame: reconstruct(frame, method),
                                 post_estimate=estimate)
    result = got.output
    return MethodOutput(result.image, result.layers, got.render_seconds, got.post_seconds, got.spp,
                        extra=_equal_time_extra(ctx, target, got, renderer.max_spp), warnings=list(result.warnings),
                        bracket=_bracket_outputs(got, lambda r: (r.image, dict(r.layers))))


#: How the planned row meets its budget (recorded per row as ``time_search``, like the searched rows' TIME_SEARCH).
PLANNED_TIME = "one render to the planner's deadline"


def _run_gpt_auto(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """The render planner at equal time: ``render_planned`` (checkpoint, then passes) to a deadline that starts
    now with the whole budget and keeps the measured reconstruction time as its tail, then the default method the
    frame names. One shot: the measured total is recorded against the budget with the reason of a miss. A budget
    below the planner's start-up (CommandError: one pass and the reconstruction do not fit) renders 1 spp of the
    fallback plan regardless, recorded as such; a frame without a checkpoint records why, with no prediction."""
    from gradsep.model.errors import CommandError
    from gradsep.model.frame import PLAN_METHOD_KEY, PREDICTED_FROM_KEY, PREDICTED_RELMSE_KEY
    from gradsep.model.reconstruct import reconstruct
    from gradsep.renderer.budget import Deadline
    from gradsep.renderer.plan import fallback, plan_layers_text, render_planned
    from gradsep.renderer.render import check_budget, frame_check

    renderer = ctx.path()
    target = _budget(ctx)
    layers = tuple(ctx.frame.layers)
    tail = renderer.planner_tail(layers)
    priors = renderer.planner_priors(layers)
    seed = int(ctx.seed) % (1 << 32)
    width, height = renderer.loaded.width, renderer.loaded.height
    start = time.perf_counter()
    deadline = Deadline(target, tail=tail)
    refused = ""
    try:  # the frame's own error estimate as the command makes it, with the default OIDN setting (as served here)
        planned = render_planned(renderer.loaded, layers, seed=seed, shift=None, fixed=None, deadline=deadline,
                                 check=lambda rate, plan, before: check_budget(rate, plan, width, height, layers,
                                                                               target, farm_setting=False,
                                                                               before=before),
                                 priors=priors)
    except CommandError:  # not one pass + the reconstruction fit: what `gradsep render --seconds` refuses
        refused = (f"the budget is below the planner's start-up here (its first pass, then {tail:.3g} s of "
                   f"reconstruction): 1 spp of `{fallback(layers).name}` rendered regardless")
        planned = render_planned(renderer.loaded, layers, seed=seed, shift=None, fixed=fallback(layers), spp=1)
    frame, plan = planned.frame, planned.plan
    frame.metadata = plan.metadata(layers) if plan is not None else {}
    if plan is not None and plan.assessments:
        frame_check(planned, frame.metadata)
    rendered = time.perf_counter()
    result = reconstruct(frame, frame.metadata.get(PLAN_METHOD_KEY))
    done = time.perf_counter()
    render_seconds, post_seconds = rendered - start, done - rendered
    total = render_seconds + post_seconds

    chosen = planned.candidate
    assessed = {a.name: a for a in plan.assessments} if plan is not None else {}
    predicted = float(frame.metadata.get(PREDICTED_RELMSE_KEY, "nan")) if assessed else math.nan
    extra: dict[str, Any] = {
        "target_seconds": target, "budget_method": ctx.budget_method, "attempts": 1, "time_search": PLANNED_TIME,
        "time_tries": [(planned.spp, total)], "gradients": chosen.gradients,
        "time_note": _planned_time_note(target, render_seconds, post_seconds, deadline.tail or tail, refused,
                                        assessed.get(chosen.name), chosen.name,
                                        plan.pilot_seconds if plan is not None else 0.0),
        "plan": chosen.name, "plan_layers": plan_layers_text(chosen, layers), "plan_method": result.method,
        "plan_candidates": {name: _finite_or_none(a.predicted_relmse) for name, a in assessed.items()},
        "predicted_relmse": _finite_or_none(predicted), "predicted_from": frame.metadata.get(PREDICTED_FROM_KEY),
        "pilot_seconds": plan.pilot_seconds if plan is not None else 0.0,
        "plan_note": plan.note if plan is not None else "", "gradient_spp": planned.gradient_spp,
    }
    if extra["predicted_relmse"] is None:
        extra["predicted_note"] = (refused or (plan.note if plan is not None and not assessed else "")
                                   or "the chosen plan's prediction is not finite")
    return MethodOutput(result.image, result.layers, render_seconds, post_seconds, planned.spp, extra=extra,
                        warnings=[*frame.warnings, *result.warnings])


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _planned_time_note(target: float, render: float, post: float, tail: float, refused: str,
                       chosen: Any, plan: str, pilot: float) -> str:
    """Why the planned row's total is outside ±TOLERANCE of ``target`` ("" when it is within): the budget was
    below the planner's start-up (``refused``), the render ended early (pass granularity: the planner starts no
    pass predicted to end past the deadline) or late (the ``pilot`` alone ran past it, or a pass was slower than
    predicted), and/or the reconstruction took other than the ``tail`` reserved for it."""
    total = render + post
    if abs(total / target - 1.0) <= PathRenderer.TOLERANCE:
        return ""
    if refused:  # the refused attempt's time is in the render's
        return f"{refused} (render {render:.3g} s, the refused attempt included)"
    parts = []
    early = (target - tail) - render  # time the render left unused before the reconstruction's reserve
    significant = 0.01 * target
    if early > significant:
        per = f" ({chosen.per_sample:.3g} s per spp)" if chosen is not None else ""
        parts.append(f"the render stopped {early:.3g} s before the budget less the reconstruction's reserve: the "
                     f"next pass of `{plan}`{per} was predicted not to fit (pass granularity)")
    elif early < -significant:
        why = (f"the checkpoint alone took {pilot:.3g} s: its passes and reconstructions are not cut short"
               if pilot > target - tail else "a pass slower than predicted")
        parts.append(f"the render ended {-early:.3g} s past the budget less the reconstruction's reserve ({why})")
    if abs(post - tail) > significant:
        parts.append(f"the reconstruction took {post:.3g} s against the {tail:.3g} s reserved")
    return "; ".join(parts) or "several small overruns"


def _bracket_outputs(got: Attempt, convert: Callable[[Any], tuple[np.ndarray, dict[str, np.ndarray]]],
                     extra_render: float = 0.0) -> list[BracketOutput]:
    """The attempt's bracket as outputs (``convert``: a try's output -> (image, layers)); [] without one.
    ``extra_render``: time every try also paid on the render side (path + OIDN's feature pass)."""
    if got.bracket is None:
        return []
    return [BracketOutput(b.spp, b.render_seconds + extra_render, b.post_seconds, *convert(b.output))
            for b in got.bracket]


def _equal_time_extra(ctx: MethodContext, target: float, got: Attempt, max_spp: int) -> dict[str, Any]:
    extra: dict[str, Any] = {"target_seconds": target, "budget_method": ctx.budget_method,
                             "attempts": got.attempts, "time_search": TIME_SEARCH, "time_tries": got.tries,
                             "time_note": got.note}
    if got.spp >= max_spp:
        extra["capped"] = f"spp capped at {max_spp} (Mitsuba's 2^32 samples per launch)"
    return extra
