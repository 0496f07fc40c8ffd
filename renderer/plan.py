"""The render planner: `gradsep render --seconds T` (a frame to a wall-time budget) and `--gradients auto` (whether
the frame traces gradients, chosen per scene at a checkpoint on the frame itself).

**Passes.** A frame is the sum of render passes (renderer.gpt.render_pass: one compiled kernel, ``spp`` samples
of every pixel, each pass its own random stream ``pass_seed(seed, i)``). Passes of different plans mix: every
plan's base path is the same unbiased path tracer (the primal-only mode's bases and features are G-PT's), so the
frame's bases and features average the samples of every pass, and its gradients those of the chosen plan's passes
(the ``--gradient-spp`` rule of render_gpt).

**The checkpoint** (--gradients auto: :func:`run_checkpoint`). The frame starts as the fallback plan's
(FALLBACK, the best fixed plan on held-out scenes), its passes dealt into the frame's two halves
(renderer/check.py), with one warm primal pass per size for primal's cost. At CHECKPOINT_SHARE of the budget each
half is reconstructed twice -- with its gradients (``oidn-l1``) and as a plain frame from the same passes' bases
(``oidn``) -- on a few tiles (:func:`tiles`), and each reconstruction's error is estimated against the other
half's groups, which are independent of it (renderer/estimate.py: no reference, bias included). Each estimate is
carried to the samples the rest of the budget buys that plan, with ``error ~ spp^-exponent`` (EXPONENTS) and the
plan's cost read from its passes (:func:`pass_cost`); the rest of the frame is primal passes only when the paired
difference of the carried estimates -- same groups, same weights, so the groups' own noise cancels -- says
primal is lower by more than renderer.check.SWITCH_SE standard errors. Nothing is rendered for the judgement
alone: every pass so far stays in the frame whichever plan goes on, so the checkpoint costs its reconstructions
and, where primal wins, the gradients already traced.

**The deadline** (renderer/budget.py): passes are sized from their measured cost so that the last one ends, with
the write still to come, just before ``T``; nothing is started that is predicted to miss it. A plan that traces
gradients leaves a gap up to one of its passes wide; primal passes (FILLER), which the bases absorb, fill it.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gradsep.model.errors import CommandError
from gradsep.model.frame import Features, Frame, Layer
from gradsep.model.header_keys import PLAN_METHOD_KEY, PREDICTED_RELMSE_KEY
from gradsep.renderer.budget import LAST_PASS_MARGIN, Clock, Deadline, PassCosts, fill_with_filler, fitted_line
from gradsep.renderer.check import Half, Split
from gradsep.renderer.estimate import at_budget, cross_terms, mean_and_se, relative_weights
from gradsep.renderer.scene import LoadedScene

#: Header keys of a planned frame (all strings, like every ``gradsep.*`` attribute).
PLAN_KEY = "gradsep.plan"  # the chosen candidate's name
PLAN_LAYERS_KEY = "gradsep.plan_layers"  # per layer: what traces gradients, e.g. "direct=alternate,indirect=none"
CANDIDATES_KEY = "gradsep.plan_candidates"  # each judged plan's predicted RelMSE at the budget, "name=value,..."
BUDGET_KEY = "gradsep.budget_seconds"  # --seconds
PILOT_SECONDS_KEY = "gradsep.pilot_seconds"  # wall time up to the checkpoint's choice (its passes stay in the frame)
ELAPSED_KEY = "gradsep.elapsed_seconds"  # the command's wall time when the frame was encoded (from process start)
#: With --plan-cache (renderer/plancache.py): "read NAME" (the plan an earlier frame judged, no checkpoint here),
#: "wrote NAME" (this frame's checkpoint judged and shared it), "not written", or "nothing to share: ...".
PLAN_CACHE_KEY = "gradsep.plan_cache"
#: The checkpoint's figures (JSON: its samples, each candidate's estimated RelMSE at the halves' samples with its
#: standard error, seconds per sample and per pass, exponent and the samples the budget buys it, the paired
#: difference of the carried estimates with its standard error, and the plan chosen): why, for a farm to read.
TRACE_KEY = "gradsep.plan_trace"

#: The most the checkpoint's own cost (primal's kernel, the reconstructions' start-up and work) may take of the
#: budget: above it the fallback is rendered with no checkpoint.
PILOT_SHARE = 0.1
#: What the first reconstruction in a process costs before its work (importing pyoidn -- without torch:
#: model.oidn.import_pyoidn -- and the reconstruction modules, creating the OIDN device and its filters, loading
#: the compiled kernels): ~0.2 s + ~0.6 s measured on the 2-core development machine. Counted against the
#: checkpoint's share before it is paid, so that a budget too small for it falls back instead of overrunning.
RECONSTRUCT_STARTUP = 1.0
#: The interpreter's exit after the frame is written (part of the command's wall time): 0.05-0.13 s after
#: rendering alone (measured on 2 shared cores, load ~3, with a 1.2 margin); the reconstruction libraries add
#: little now that torch is not imported with them (its teardown alone was 0.3 s: model.oidn.import_pyoidn).
EXIT_SECONDS = (0.15, 0.3)
#: Tiles the checkpoint reconstructs (side, count) and the border of each left out of the estimate.
TILE = 128
TILE_COUNT = 4
TILE_BORDER = 8


@dataclass(frozen=True)
class Candidate:
    """One render plan: which layers trace gradients (``--gradients``) and which offsets (``--offsets``)."""

    name: str
    gradients: str  # renderer.render.GRADIENT_CHOICES
    offsets: str = "all"  # renderer.render.OFFSET_CHOICES


#: The render plans by name (what ``--gradients`` and ``--offsets`` make of a fixed plan). The checkpoint judges the
#: fallback against ``primal`` (:func:`applicable`); ``direct`` (every offset) and ``all`` are fixed plans: the
#: default method, ``oidn-l1``, reads only the direct layer's gradients, and an oracle choosing ``direct`` where it
#: was best was 3 % below one choosing between primal and ``direct-alternate`` on held-out scenes, less than a
#: third candidate's passes would cost. A farm serving a method that reads every layer's gradients renders
#: ``--gradients all``.
CANDIDATES: tuple[Candidate, ...] = (
    Candidate("primal", "none"),
    Candidate("direct-alternate", "direct", "alternate"),
    Candidate("direct", "direct", "all"),
    Candidate("all", "all"),  # only for an unseparated (colour) frame, whose one layer is all there is
)
#: What fills the end of a --seconds frame whose plan traces gradients, in the gap too small for one more pass of
#: the plan: primal passes (their samples join the bases, as the --gradient-spp rule's; the gradients keep the
#: plan's passes' samples). A 1-spp primal pass costs ~1/4 of an `all` pass (1280x720, 2 shared cores).
FILLER = "primal"
#: The plan a frame starts with and keeps unless primal is clearly better at the checkpoint (:func:`fallback`:
#: ``all`` for an unseparated frame), and the plan rendered where no checkpoint fits: the best fixed plan at equal
#: time on held-out scenes (benchmarks/bench_planner.py validate: 1.06x the best fixed plan's RelMSE on rooms,
#: 1.32x on studios, geometric means; ``direct`` 1.22x / 1.47x, ``all`` 1.38x / 1.52x).
FALLBACK = "direct-alternate"
#: Error-vs-spp exponent of each plan's reconstruction (RelMSE ~ spp^-exponent) the checkpoint's estimates are
#: carried to the budget with. A denoised frame's error falls far slower than a raw frame's 1/spp: measured
#: between two budgets (20 s and 40 s at 128x128, 350-3400 spp) on procedural:93101, 0.43 (primal + oidn), 0.37
#: (direct-alternate + oidn-l1), 0.54 (all + oidn-l1).
EXPONENTS: dict[str, float] = {"primal": 0.5, "direct-alternate": 0.5, "direct": 0.5, "all": 0.5}


def candidate(name: str) -> Candidate:
    for c in CANDIDATES:
        if c.name == name:
            return c
    raise CommandError(f"unknown plan {name!r}; expected one of {', '.join(c.name for c in CANDIDATES)}")


def plan_layers_text(c: Candidate, layers: tuple[str, ...]) -> str:
    """``direct=alternate,indirect=none``: what each layer of the frame traces (its offsets, or none)."""
    def traced(layer: str) -> str:
        if c.gradients == "none" or (c.gradients == "direct" and layer != "direct"):
            return "none"
        return c.offsets
    return ",".join(f"{layer}={traced(layer)}" for layer in layers)


def applicable(layers: tuple[str, ...]) -> tuple[Candidate, Candidate]:
    """The plans the checkpoint judges for a frame of these layers: its :func:`fallback` and ``primal``."""
    return fallback(layers), candidate("primal")


def fallback(layers: tuple[str, ...]) -> Candidate:
    """FALLBACK, or ``all`` for a frame without a separated direct layer."""
    return candidate(FALLBACK if "direct" in layers else "all")


# ------------------------------------------------------------------------------------------------- passes


@dataclass
class _Kind:
    settings: object  # renderer.gpt.GptSettings
    shift: object  # renderer.gpt.Shift or None
    costs: PassCosts = field(default_factory=PassCosts)


@dataclass
class Priors:
    """What earlier renders in this process measured on the same scene and frame size, for a planner that starts
    warm (a worker that renders the scene again, the evaluation's planned row after its untimed calibration): no
    probing pass is spent on what is known.

    ``costs``: per candidate name, its passes' measured cost (warm passes of two sizes or more: their kernel is
    compiled, so none of its passes is a compiling one); ``reconstruct_rate``: seconds per pixel of the default
    reconstruction, its start-up paid (what the checkpoint's and the frame check's reconstructions will take)."""

    costs: dict[str, PassCosts] = field(default_factory=dict)
    reconstruct_rate: float | None = None
    #: per candidate name, the seconds its frame's reconstruction takes: an in-process caller's Deadline.tail
    #: becomes the chosen plan's once it is chosen (a plain frame's `oidn` is quicker than `oidn-l1`)
    reconstruct_seconds: dict[str, float] = field(default_factory=dict)

    def warm(self, name: str) -> bool:
        """Whether candidate ``name``'s passes have a measured cost line (a pass can be sized without a probe)."""
        c = self.costs.get(name)
        return c is not None and len({spp for spp, _ in c.warm}) >= 2


class Passes:
    """Runs render passes of any candidate on one scene and keeps their sums for the final frame."""

    def __init__(self, loaded: LoadedScene, layers: tuple[str, ...], seed: int, shift: str | None = None,
                 clock: Clock = time.monotonic, priors: Priors | None = None) -> None:
        from gradsep.renderer.gpt import MAX_LANES_PER_PASS

        self.loaded, self.layers, self.seed, self.shift_name, self.clock = loaded, layers, seed, shift, clock
        self.priors = priors
        self.max_spp = max(1, MAX_LANES_PER_PASS // (loaded.width * loaded.height))
        self.kinds: dict[str, _Kind] = {}
        self.index = 0  # passes so far: the next pass's seed stream
        self.bases: dict[str, np.ndarray] | None = None  # base and feature sums over every pass
        self.spp = 0
        self.gradients: dict[str, tuple[dict[str, np.ndarray], int]] = {}  # candidate -> (gradient sums, spp)
        self._owned: list[np.ndarray] = []  # the sums arrays this object made (the others are a pass's own)
        #: once :meth:`start_split` ran: every pass also dealt into groups for the frame's own error estimate
        self.split: Split | None = None

    def kind(self, c: Candidate) -> _Kind:
        if c.name not in self.kinds:
            from gradsep.renderer.gpt import GptSettings
            from gradsep.renderer.shift import make_shift

            color = self.layers == ("color",)
            settings = GptSettings(max_depth=self.loaded.max_depth, rr_depth=self.loaded.rr_depth,
                                   direct=color or "direct" in self.layers,
                                   indirect=color or "indirect" in self.layers, separate=not color,
                                   gradients="direct" if c.gradients == "direct" else "all",
                                   offsets=c.offsets if c.gradients != "none" else "all")
            shift = None
            if c.gradients != "none":
                try:
                    shift = make_shift(self.shift_name)
                except ValueError as exc:
                    raise CommandError(str(exc)) from None
                if c.gradients == "direct":
                    shift = getattr(shift, "for_direct_layer", lambda: shift)()
            kind = _Kind(settings, shift)
            known = self.priors.costs.get(c.name) if self.priors is not None else None
            if known is not None:  # a copy: this frame's passes refine it without touching the caller's
                kind.costs = PassCosts(known.overhead, list(known.warm), known.first_pass)
            self.kinds[c.name] = kind
        return self.kinds[c.name]

    def run(self, c: Candidate, spp: int) -> dict[str, np.ndarray]:
        """Render one pass of ``spp`` samples with ``c``, add it to the frame, record its cost; returns its sums."""
        from gradsep.renderer.gpt import pass_seed, render_pass

        kind = self.kind(c)
        first = kind.costs.first_pass is None and not kind.costs.warm  # a kernel known warm (Priors) compiles nothing
        start = self.clock()
        sums = render_pass(self.loaded.scene, kind.shift, kind.settings, self.loaded.width, self.loaded.height,
                           spp, pass_seed(self.seed, self.index))
        bases = {k: v for k, v in sums.items() if ".grad" not in k}
        grads = {k: v for k, v in sums.items() if ".grad" in k}
        self.bases = self._added(self.bases, bases)
        if grads:
            have, n = self.gradients.get(c.name, (None, 0))
            self.gradients[c.name] = (self._added(have, grads), n + spp)
        if self.split is not None:
            self.split.add(c.name, bases, grads, spp)
        # the pass's cost includes adding it to the frame: what the deadline must budget for each pass
        seconds = self.clock() - start
        (kind.costs.first if first else kind.costs.record)(spp, seconds)
        self.index += 1
        self.spp += spp
        return sums

    def _added(self, total: dict[str, np.ndarray] | None, sums: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``total + sums``: the first pass's arrays as they are (a frame of one pass copies nothing), new arrays at
        the second (a pass's own sums are never written to: the caller may hold them), in place from then on (a
        1280x720 frame's sums are ~200 MB of float64: new arrays at every pass cost 0.3 s a pass)."""
        if total is None:
            return sums
        first = next(iter(total.values()))
        if not any(first is mine for mine in self._owned):
            total = {k: v + sums[k] for k, v in total.items()}
            self._owned.extend(total.values())
            return total
        for k, v in total.items():
            np.add(v, sums[k], out=v)
        return total

    def frame_result(self, c: Candidate, window: tuple[slice, slice] | None = None):  # -> renderer.gpt.GptResult
        """The frame so far as ``c``'s frame: every pass's bases and features, ``c``'s passes' gradients; only its
        ``window`` (rows, columns) when given (what :func:`write_seconds` times)."""
        from gradsep.renderer.gpt import finish

        assert self.bases is not None, "no pass rendered"
        grads, k = self.gradients.get(c.name, ({}, 0))
        sums = {**self.bases, **grads}
        if window is not None:
            sums = {key: v[window] for key, v in sums.items()}
        return finish(sums, self.kind(c).settings, self.spp, self.index, k or None)

    def start_split(self) -> None:
        """Deal every pass from now on into groups for the frame's own error estimate (renderer/check.py), the
        passes so far as one lump: splitting costs a copy of the frame's sums (0.5 s at 1280x720), so it starts
        only once the check is known to fit."""
        if self.split is None:
            self.split = Split()
            if self.bases is not None:
                self.split.add_lump(self.bases, self.gradients, self.spp, self.index)

    def halves(self, c: Candidate) -> list[Half] | None:
        """The frame's two halves as ``c``'s frames, with their samples and the other half's groups
        (renderer/check.py), or None when the passes were not split or a half lacks samples (or ``c``'s
        gradients)."""
        from gradsep.renderer.gpt import finish

        grads, k = self.gradients.get(c.name, ({}, 0))
        q = self.split
        if q is None or self.bases is None or not q.ready(c.name, c.gradients != "none", k):
            return None
        out = []
        for i, (sums, n, count, gradient_spp) in enumerate(q.halves(c.name, self.bases, grads, self.spp, k)):
            frame = as_frame(finish(sums, self.kind(c).settings, n, count, gradient_spp))
            frame.warnings = []
            out.append((frame, n, q.batches(i)))
        return out


def tiles(width: int, height: int, side: int = TILE, count: int = TILE_COUNT) -> list[tuple[slice, slice]]:
    """The windows the checkpoint reconstructs: the whole frame when it is small, else ``count`` tiles of ``side``
    centred in the frame's quadrants (spread over the frame, away from its edges)."""
    if width * height <= count * side * side or width < 2 * side or height < 2 * side:
        return [(slice(0, height), slice(0, width))]
    out = []
    for fy in (0.25, 0.75):
        for fx in (0.25, 0.75):
            y0 = min(max(0, round(fy * height - side / 2)), height - side)
            x0 = min(max(0, round(fx * width - side / 2)), width - side)
            out.append((slice(y0, y0 + side), slice(x0, x0 + side)))
    return out[:count]


def without_gradients(frame: Frame) -> Frame:
    """``frame`` as a plain frame: its bases, variances and features, no gradients (what a primal plan's frame of
    the same passes is: every plan's bases are the same path tracer's)."""
    return Frame(layers={n: Layer(v.base, var=v.var) for n, v in frame.layers.items()}, features=frame.features)


def crop(frame: Frame, window: tuple[slice, slice]) -> Frame:
    ys, xs = window

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else np.ascontiguousarray(a[ys, xs])

    f = frame.features
    features = None if f is None else Features(cut(f.albedo), cut(f.normal), cut(f.depth))
    return Frame(layers={n: Layer(cut(v.base), cut(v.dx), cut(v.dy), cut(v.var)) for n, v in frame.layers.items()},
                 features=features)


def reconstruct_startup() -> float:
    """RECONSTRUCT_STARTUP while this process has not reconstructed yet, else 0."""
    return 0.0 if "pyoidn" in sys.modules else RECONSTRUCT_STARTUP


def exit_seconds() -> float:
    """The interpreter's predicted exit time (EXIT_SECONDS) given what this process has loaded."""
    return EXIT_SECONDS[1] if "pyoidn" in sys.modules else EXIT_SECONDS[0]


def reconstruct_default(frame: Frame) -> tuple[np.ndarray, str]:
    """The one call into the reconstruction library: the default method that would serve this frame."""
    from gradsep.model.reconstruct import reconstruct

    result = reconstruct(frame)
    return result.image, result.method


#: Side of the tile the reconstruction library's start-up is paid on, in the background (warm_reconstruction).
WARM_TILE = 16


def warm_reconstruction(tile: Frame,
                        reconstruct: Callable[[Frame], tuple[np.ndarray, str]] = reconstruct_default,
                        ) -> threading.Thread | None:
    """Pay the reconstruction library's one-time start-up (RECONSTRUCT_STARTUP: its import, OIDN's device and
    filters) in a background thread, on a small ``tile`` of the frame both ways (with its gradients and as a
    plain frame), while the checkpoint's passes render: Dr.Jit's kernels and OIDN's set-up run outside the GIL,
    so on 2 cores a 192x192 checkpoint's first reconstruction fell from 0.54 s to 0.08 s for 0.17 s more of its
    passes (on more cores the overlap is nearly free). None where it is paid already. The caller joins it before
    it reconstructs; an error there is left to the caller's own reconstruction to raise, in the foreground."""
    if "pyoidn" in sys.modules:
        return None

    def run() -> None:
        with contextlib.suppress(Exception):
            for f in (tile, without_gradients(tile)):
                reconstruct(f)

    thread = threading.Thread(target=run, name="gradsep-reconstruction-warm-up", daemon=True)
    thread.start()
    return thread


# -------------------------------------------------------------------------------------------- checkpoint

#: Passes the rest of the frame is expected to take (renderer.budget.fill_to_deadline's passes shrink as the
#: deadline nears): each pays the candidate's fixed cost per pass.
FINAL_PASSES = 4


def pass_cost(warm: list[tuple[int, float]], fallback: float) -> tuple[float, float]:
    """(fixed seconds per pass, seconds per sample) of one kind of pass, for comparing plans: the least-squares
    line through its warm passes ``(spp, seconds)`` (renderer.budget.fitted_line) when they have two sizes or more
    (the fixed part clipped to [0, 0.95 x the smallest pass]); else no fixed part and ``fallback`` per sample.
    Unlike the deadline's conservative rate (renderer.budget.PassCosts.per_sample, the largest recent rate), this
    is the marginal cost: small passes are mostly fixed cost for G-PT (tracing the kernel), which must not be
    charged to every sample of the final frame's large passes."""
    line = fitted_line(warm)
    if line is None:
        return 0.0, fallback
    intercept, slope = line
    fixed = min(max(intercept, 0.0), 0.95 * min(y for _, y in warm))
    per = max((y - fixed) / x for x, y in warm) if slope <= 0 else slope  # a line gone flat or falling: noise
    return fixed, max(per, 1e-12)


@dataclass
class Assessment:
    """What the checkpoint measured of one plan."""

    name: str
    pilot_spp: int  # samples of each half at the checkpoint (the halves' mean)
    measured_relmse: float  # estimated RelMSE of a half's reconstruction (at pilot_spp; the halves' mean)
    per_sample: float  # seconds per sample of the whole frame (warm, marginal: pass_cost)
    method: str  # the reconstruction method that serves its frame
    standard_error: float = 0.0  # of measured_relmse (the estimate's noise)
    exponent: float = 0.5  # of the error-vs-spp law it is carried to the budget with
    budget_spp: float = 0.0
    predicted_relmse: float = math.inf
    predicted_se: float = 0.0  # of predicted_relmse (the estimate's noise carried to the budget)
    pass_seconds: float = 0.0  # fixed cost of one of its passes (pass_cost)
    reconstruct_rate: float = 0.0  # seconds per pixel of its reconstructions (the frame's check: renderer/check.py)

    def trace_entry(self) -> dict[str, float | str]:
        """This plan's entry in the checkpoint's figures (TRACE_KEY)."""
        return {"name": self.name, "spp": self.pilot_spp, "relmse": float(f"{self.measured_relmse:.4g}"),
                "se": float(f"{self.standard_error:.3g}"), "per_sample": float(f"{self.per_sample:.4g}"),
                "pass_seconds": float(f"{self.pass_seconds:.4g}"), "exponent": round(self.exponent, 3),
                "budget_spp": round(self.budget_spp)}


@dataclass
class Plan:
    """The planner's decision (a checkpoint's, or the fallback where none fitted)."""

    chosen: Candidate
    assessments: list[Assessment]
    pilot_seconds: float
    note: str = ""
    trace: dict[str, object] = field(default_factory=dict)  # the checkpoint's figures (TRACE_KEY)

    def assessment(self) -> Assessment | None:
        """The chosen plan's assessment (None: no checkpoint judged it)."""
        return next((a for a in self.assessments if a.name == self.chosen.name), None)

    def predicted(self) -> float:
        a = self.assessment()
        return a.predicted_relmse if a is not None else math.nan

    def metadata(self, layers: tuple[str, ...]) -> dict[str, str]:
        meta = {PLAN_KEY: self.chosen.name, PLAN_LAYERS_KEY: plan_layers_text(self.chosen, layers),
                PILOT_SECONDS_KEY: f"{self.pilot_seconds:.3f}"}
        if self.assessments:
            meta[PREDICTED_RELMSE_KEY] = f"{self.predicted():.6g}"
            meta[CANDIDATES_KEY] = ",".join(f"{a.name}={a.predicted_relmse:.6g}" for a in self.assessments)
            meta[PLAN_METHOD_KEY] = self.assessment().method  # type: ignore[union-attr]
        if self.trace:
            meta[TRACE_KEY] = json.dumps(self.trace, separators=(",", ":"))
        return meta

    def summary(self) -> str:
        if not self.assessments:
            return f"plan {self.chosen.name} ({self.note})"
        parts = ", ".join(f"{a.name} {a.predicted_relmse:.4g} at {a.budget_spp:.0f} spp (slope {a.exponent:.2f})"
                          for a in self.assessments)
        where = self.note if self.trace.get("cached") else f"checkpoint {self.pilot_seconds:.2f} s, {self.note}"
        return (f"plan {self.chosen.name}: predicted RelMSE {parts} ({where}, method "
                f"{self.metadata(()).get(PLAN_METHOD_KEY, '?')})")


#: Share of the budget (of the frame's samples with --spp) rendered with the fallback plan before the checkpoint
#: judges the candidates on the frame's halves. Those passes stay in the frame whatever the choice.
CHECKPOINT_SHARE = 0.15
#: Passes the frame is rendered in up to the checkpoint (each half needs two groups or more: renderer/check.py).
CHECKPOINT_PASSES = 8
#: The checkpoint's last passes: the rest of its share after the cost lines' passes, in this many passes.
#: A G-PT pass has a fixed cost (tracing, launch: ~0.06 s at 192x192 on 2 cores, a 2-spp pass's half), so
#: passes sized from a 1-spp pass's cost (fixed cost counted per sample) were ~20 small ones: 1.6 s of a 20 s
#: budget went to their fixed costs.
CHECKPOINT_LAST_PASSES = 4
#: The fewest samples of a --spp frame that get a checkpoint (its passes up to it: 4 of 1 spp, then 4 or more).
CHECKPOINT_MIN_SPP = 64
#: Side of the blocks whose means give the checkpoint's paired difference its standard error: a denoiser's errors
#: are correlated between neighbouring pixels, so single pixels would understate it.
CHECKPOINT_BLOCK = 8


def block_means(terms: np.ndarray, block: int = CHECKPOINT_BLOCK) -> np.ndarray:
    """The means of ``terms`` (rows, columns[, channels]) over ``block``-square blocks (the ragged edge left out;
    the whole array as one block when it is smaller than one)."""
    h, w = terms.shape[:2]
    if h < block or w < block:
        return np.asarray([float(np.mean(terms))])
    t = terms[:h - h % block, :w - w % block]
    t = t.reshape(h // block, block, w // block, block, -1)
    return t.mean(axis=(1, 3, 4)).ravel()


def run_checkpoint(passes: Passes, budget_spp: Callable[[Assessment], float], *, seconds: float | None = None,
                   spp: int | None = None, give_up_after: float = math.inf,
                   after_first: Callable[[], None] | None = None,
                   reconstruct: Callable[[Frame], tuple[np.ndarray, str]] = reconstruct_default) -> Plan:
    """Render the fallback plan (:func:`fallback`) for CHECKPOINT_SHARE of the budget (``seconds``) or of the
    frame's ``spp``, its passes dealt into the frame's halves (renderer/check.py), with primal passes of two sizes
    for primal's cost; then judge on the halves whether the rest is better spent on the fallback's passes
    or on primal ones (a plain frame, from the same passes' bases): each half reconstructed both ways, on up to
    TILE_COUNT tiles, and judged against the other half's groups, each candidate's estimate carried to the
    samples the rest of the budget buys it; primal replaces the fallback only when the paired difference of the
    carried estimates (same groups, same weights: the groups' noise cancels) is below zero by more than
    renderer.check.SWITCH_SE standard errors. Every pass stays in the frame. When the checkpoint's own cost (the
    primal kernel, the reconstructions) is predicted past ``give_up_after`` seconds, nothing is judged and the
    fallback is rendered. ``after_first`` runs after the first pass (the caller's start-up check)."""
    from gradsep.renderer.check import CHECK_MARGIN, SWITCH_SE

    clock = passes.clock
    start = clock()
    default = fallback(passes.layers)
    primal = candidate("primal")
    windows = tiles(passes.loaded.width, passes.loaded.height)
    pixels = sum((ys.stop - ys.start) * (xs.stop - xs.start) for ys, xs in windows)
    priors = passes.priors
    # the checkpoint's own cost: primal's kernel (no slower to load than the fallback's; nothing where it is known
    # warm) and four reconstructions (at the rate measured in this process where known, with the check's margin)
    measured = priors.reconstruct_rate if priors is not None else None
    rate = CHECK_MARGIN * measured if measured else CHECK_PRIOR_RATE
    work = reconstruct_startup() + 4 * pixels * rate
    too_small = "the budget is too small for a checkpoint"
    primal_warm = priors is not None and priors.warm(primal.name)
    if primal_warm and priors.warm(default.name) and work > give_up_after:  # type: ignore[union-attr]
        return Plan(default, [], clock() - start, too_small)  # known before any pass: the deadline sizes the first
    passes.run(default, 1)  # compiles (or loads) the fallback's kernel: the frame's first pass in any case
    if after_first is not None:
        after_first()
    kernel = 0.0 if primal_warm else passes.kind(default).costs.first_pass[1]  # type: ignore[index]
    if clock() - start + kernel + work > give_up_after:
        return Plan(default, [], clock() - start, too_small)
    passes.start_split()
    passes.run(primal, 1)  # primal's kernel (the filler's too)
    passes.run(default, 1)  # a warm pass of the fallback: its cost without the compile, to size the passes by
    if seconds is not None:
        left = start + CHECKPOINT_SHARE * seconds - clock()
        n = max(1, int(left / CHECKPOINT_PASSES / max(passes.kind(default).costs.per_sample, 1e-9)))
    else:
        n = max(1, int(CHECKPOINT_SHARE * (spp or 0)) // (CHECKPOINT_PASSES + 4))
    n = max(1, min(n, passes.max_spp // 2))
    # each plan at two sizes, n and 2n: its cost line (pass_cost) reads its fixed cost per pass (for G-PT, most of
    # a small pass) apart from its cost per sample, which decides how many samples the budget buys it
    for k in (n, 2 * n):
        passes.run(primal, k)
        passes.run(default, k)
    # each plan's cost line as these passes read it: what decides how many samples the rest buys each plan
    lines = {c.name: (list(passes.kind(c).costs.warm), passes.kind(c).costs.per_sample) for c in (default, primal)}
    # the reconstruction library's start-up, while the last passes render (not before: passes slowed by it would
    # read a plan's cost high, primal's ~1.5x)
    warming = None
    if reconstruct is reconstruct_default:
        side = (slice(0, min(WARM_TILE, passes.loaded.height)), slice(0, min(WARM_TILE, passes.loaded.width)))
        warming = warm_reconstruction(as_frame(passes.frame_result(default, side)))
    # then the rest of the checkpoint's share in CHECKPOINT_LAST_PASSES passes of the fallback (more, in pairs, where
    # a pass's lanes cannot hold them), each sized as it starts from the time left and the rate of the largest recent
    # pass, its fixed cost included: an upper bound on the cost per sample that a cost line fitted on passes slowed
    # by a busy moment cannot undercut (one did: a checkpoint of 8.8 s instead of 3). The passes are a smaller and a
    # larger in turn (about 2k/3 and 4k/3 for k per pass), so that the fallback's cost line stays readable.
    costs = passes.kind(default).costs

    def rate() -> float:
        largest, seconds_taken = max(costs.warm)
        return seconds_taken / largest

    if seconds is not None:
        total = (start + CHECKPOINT_SHARE * seconds - clock()) / rate()
    else:
        total = CHECKPOINT_SHARE * (spp or 0) - passes.spp
    count = CHECKPOINT_LAST_PASSES
    while total > count * 0.75 * passes.max_spp and count < 4 * CHECKPOINT_LAST_PASSES:
        count += 2
    for i in range(count):
        if seconds is not None:
            k = (start + CHECKPOINT_SHARE * seconds - clock()) / rate() / (count - i)
        else:
            k = (CHECKPOINT_SHARE * (spp or 0) - passes.spp) / (count - i)
        k *= 2 / 3 if i % 2 == 0 else 1.0  # the pair's first pass the smaller (the second gets what is left)
        passes.run(default, max(1, min(int(k), passes.max_spp)))
    checkpoint_spp = passes.spp
    halves = passes.halves(default)
    if halves is None:
        return Plan(default, [], clock() - start, "the checkpoint's halves were not ready")
    if warming is not None:
        warming.join()
    border = TILE_BORDER if len(windows) > 1 else 0
    # per plan and half: the block means of its reconstruction's error terms over the tiles (renderer/estimate.py)
    blocks: dict[str, list[np.ndarray]] = {default.name: [], primal.name: []}
    samples = [n for _, n, _ in halves]
    methods: dict[str, str] = {}
    seconds_in = {default.name: 0.0, primal.name: 0.0}  # the second half's reconstructions (the first pays start-up)
    judging = clock()
    for i, (frame, _, groups) in enumerate(halves):
        # primal's frame of the same passes is the fallback's without its gradients
        frames = {default.name: frame, primal.name: without_gradients(frame)}
        terms: dict[str, list[np.ndarray]] = {default.name: [], primal.name: []}
        for ys, xs in windows:
            images = {}
            for name, f in frames.items():
                began = time.perf_counter()
                images[name], methods[name] = reconstruct(crop(f, (ys, xs)))
                seconds_in[name] += (time.perf_counter() - began) * (i == 1)
            batches = [(b[ys, xs], k) for b, k in groups]
            # the same weights for both (their mean image): the groups' noise cancels in the difference
            weights = relative_weights(0.5 * (images[default.name] + images[primal.name]))
            for name, image in images.items():
                t = cross_terms(image, batches, weights)
                terms[name].append(block_means(t[border:-border or None, border:-border or None] if border else t))
        for name in blocks:
            blocks[name].append(np.concatenate(terms[name]))
    assessments: dict[str, Assessment] = {}
    for c in (default, primal):
        fixed, per = pass_cost(*lines[c.name])
        values, ses = zip(*(mean_and_se(b) for b in blocks[c.name]), strict=True)
        a = Assessment(c.name, round(float(np.mean(samples))), float(np.mean(values)), per, methods[c.name],
                       float(np.hypot(*ses)) / 2, pass_seconds=fixed, reconstruct_rate=seconds_in[c.name] / pixels,
                       exponent=EXPONENTS[c.name])
        a.budget_spp = budget_spp(a)
        # each half's estimate carried to the budget (one lost in the other half's noise counts as its noise)
        a.predicted_relmse = float(np.mean([at_budget(max(v, se), n, a.budget_spp, a.exponent)
                                            for v, se, n in zip(values, ses, samples, strict=True)]))
        a.predicted_se = at_budget(a.standard_error, a.pilot_spp, a.budget_spp, a.exponent)
        assessments[c.name] = a
    # the paired difference at the budget: primal's terms less the fallback's, each carried to its samples
    p, d = assessments[primal.name], assessments[default.name]
    difference, difference_se = mean_and_se(np.concatenate([
        at_budget(1.0, n, p.budget_spp, p.exponent) * tp - at_budget(1.0, n, d.budget_spp, d.exponent) * td
        for n, tp, td in zip(samples, blocks[primal.name], blocks[default.name], strict=True)]))
    chosen = primal if difference < -SWITCH_SE * difference_se else default
    trace: dict[str, object] = {"spp": checkpoint_spp, "seconds": round(clock() - judging, 3),
                                "plans": [a.trace_entry() for a in assessments.values()],
                                "difference": [float(f"{difference:.4g}"), float(f"{difference_se:.3g}")],
                                "chosen": chosen.name}
    return Plan(chosen, [assessments[default.name], assessments[primal.name]], clock() - start,
                f"checkpoint at {checkpoint_spp} spp", trace)


# ------------------------------------------------------------------------------------------- the frame


#: The write is predicted from WRITE_BANDS bands spread over the frame's height (content, and so the encoder's
#: cost, differs by region), each of WRITE_ROWS rows per thread of OpenEXR's pool (exr_write.configure_exr_threads:
#: ZIP compresses blocks of 16 rows, one per thread, so a band of one block would time one core), with a margin for
#: a shared machine's swings, plus the file's creation, fsync and rename (WRITE_FIXED), and a second measurement
#: near the end (WRITE_REMEASURE). Measured at 1280x720 on 2 cores, otherwise idle: the bands predicted 0.48-0.52 s
#: and the write took 0.50-0.67 s. Under load 3-6 (single-threaded encoding) it took 1.08-1.98x a prediction made
#: seconds before; the margin covers most of that, and at T = 5 s an overrun of the worst case is ~5 % of T, while
#: the earlier 1.75 left ~8 % of T idle on every frame.
WRITE_ROWS = 16
WRITE_BANDS = 3
WRITE_MARGIN = 1.35
WRITE_FIXED = 0.05
#: The write is measured again once the time left is below this many predicted writes (the frame's last passes).
WRITE_REMEASURE = 5.0


def write_seconds(band: Callable[[tuple[slice, slice]], Frame], width: int, height: int, rows: int | None = None,
                  bands: int = WRITE_BANDS, margin: float = WRITE_MARGIN) -> float:
    """Predicted seconds from the last pass's end to the frame on disk: assembling the frame from the passes' sums
    (``band(window)``: the frame of one window of rows), its channels, and their EXR encoding. Each of ``bands``
    bands of ``rows`` rows (default: WRITE_ROWS per thread of OpenEXR's pool) spread over the height is assembled
    and encoded after one untimed warm-up (the first encode in a process pays a one-time set-up: 2x a later one),
    and the time is scaled to the frame's height (the encoder and the assembly are linear in the rows)."""
    import OpenEXR

    from gradsep.model.exr_write import encode_exr

    if rows is None:
        rows = WRITE_ROWS * max(1, OpenEXR.global_thread_count())
    rows = max(1, min(rows, height))
    starts = sorted({round(f * (height - rows)) for f in np.linspace(0.0, 1.0, max(1, bands))})
    windows = [(slice(y, y + rows), slice(0, width)) for y in starts]
    encode_exr(band((slice(0, 1), slice(0, width))).to_channels())  # warm-up
    start = time.perf_counter()
    for window in windows:
        encode_exr(band(window).to_channels())
    seconds = time.perf_counter() - start
    return margin * seconds * height / (rows * len(windows)) + WRITE_FIXED


def as_frame(result: object) -> Frame:
    """A renderer.gpt.GptResult as a Frame (no metadata yet)."""
    layers = {name: Layer(base=v["base"], dx=v.get("dx"), dy=v.get("dy"), var=v.get("var"))
              for name, v in result.layers.items()}  # type: ignore[attr-defined]
    features = Features(result.albedo, result.normal, result.depth)  # type: ignore[attr-defined]
    return Frame(layers=layers, features=features, warnings=list(result.warnings))  # type: ignore[attr-defined]


def startup_error(seconds: float, needed: float) -> CommandError:
    return CommandError(f"--seconds {seconds:g} is below this machine's start-up cost: process start, scene load, "
                        f"kernel compile, one 1-spp pass and the write took {needed:.2f} s here; give more time")


@dataclass
class Planned:
    """A rendered frame and how it was planned."""

    frame: Frame
    candidate: Candidate
    plan: Plan | None  # None: a fixed plan (no checkpoint)
    spp: int
    gradient_spp: int  # samples that traced the chosen plan's gradients (0 for a plain frame)
    passes: int
    #: the frame's two halves for its own error estimate (renderer/check.py), with their samples; None: no check
    halves: list[Half] | None = None
    check_seconds: float | None = None  # what was held back for the check after the last pass


def render_planned(loaded: LoadedScene, layers: tuple[str, ...], *, seed: int, shift: str | None,
                   fixed: Candidate | None, deadline: Deadline | None = None, spp: int | None = None,
                   progress: Callable[[int, int], None] | None = None,
                   clock: Clock = time.monotonic,
                   check: Callable[[float, Candidate, float], float | None] | None = None,
                   priors: Priors | None = None) -> Planned:
    """Render ``loaded`` to a deadline (``deadline``) or to ``spp`` samples, with the ``fixed`` plan or (None) the
    plan its checkpoint chooses (:func:`run_checkpoint`). Raises CommandError (nothing rendered is kept) when the
    deadline cannot fit one pass and the write. The frame's metadata is the caller's
    (renderer.render.render_metadata) plus :meth:`Plan.metadata`.

    ``check`` says, given a reconstruction's seconds per pixel, the plan and the seconds it would cost beforehand,
    how many seconds the frame's own error estimate needs after the last pass (renderer/check.py: held back from
    the passes), or None for no estimate; with one, :attr:`Planned.halves` holds the halves it reconstructs. It is
    asked once the plan is chosen, with the checkpoint's reconstruction rate; for a fixed plan with a deadline,
    after the first pass, with the rate measured on a tile of it (:func:`reconstruct_rate`), where
    CHECK_PRIOR_RATE and the reconstruction's start-up say the check could fit.

    ``priors``: what earlier renders in this process measured on the scene (:class:`Priors`). With the chosen
    plan's cost line known and a caller's own tail (Deadline.tail: nothing to write, so no write to measure on a
    first pass), a deadline without a checkpoint sizes its first pass from that line instead of probing with a
    1-spp one: at sub-second budgets a pass's fixed cost is most of a small pass (at 320x240 a `direct-alternate`
    pass costs ~0.02 s whatever its samples, and a deadline that probed got 7-9 spp where one searched call of
    the same time had 27)."""
    if (deadline is None) == (spp is None):
        raise ValueError("give a deadline or a sample count, not both")
    passes = Passes(loaded, layers, seed, shift, clock, priors)
    held: float | None = None  # seconds held back for the frame's check (None: no check)
    write = 0.0  # predicted seconds to assemble, encode and write the frame, measured after its first pass
    measured_at = 0  # passes.index when it was measured (0: never)
    remeasured = False
    written: list[Candidate] = []  # the plan whose frame is written: the first pass's, then the chosen one

    def measure_write() -> float:
        nonlocal measured_at
        measured_at = passes.index
        return write_seconds(lambda window: as_frame(passes.frame_result(written[-1], window)), loaded.width,
                             loaded.height)

    def reserve() -> float:  # what must be left when the last pass ends: the write and the interpreter's exit
        nonlocal write, remeasured
        if deadline is not None and deadline.tail is not None:  # an in-process caller's own (Deadline.tail)
            return deadline.tail + (held or 0.0)
        if (deadline is not None and len(written) > 1 and not remeasured and passes.index > measured_at
                and deadline.left() < WRITE_REMEASURE * write):
            # the frame's last passes (the plan is chosen, a pass since the last measurement): measured again, at
            # the machine's load of now (a shared machine's single-thread speed swings 2x within seconds) and on the
            # plan's frame
            remeasured = True
            write = measure_write()
        return write + exit_seconds() + (held or 0.0)

    def after_first() -> None:  # the start-up check: one pass done, its frame must still be writable in time
        nonlocal write
        written.append(candidate(next(iter(passes.kinds))) if fixed is None else fixed)
        if deadline is None:  # a sample count: no deadline to keep
            return
        if deadline.tail is None:  # an in-process caller (Deadline.tail) writes nothing: no write to measure
            write = measure_write()
        if deadline.left() < reserve():
            raise startup_error(deadline.seconds, deadline.elapsed() + reserve())

    plan = None
    if fixed is None:
        def budget_spp(a: Assessment) -> float:
            if deadline is None:
                return float(spp)  # type: ignore[arg-type]
            usable = deadline.left() - reserve() - FINAL_PASSES * a.pass_seconds
            return passes.spp + max(0.0, usable) / a.per_sample

        if deadline is not None:
            plan = run_checkpoint(passes, budget_spp, seconds=deadline.seconds,
                                  give_up_after=PILOT_SHARE * deadline.seconds, after_first=after_first)
        elif spp >= CHECKPOINT_MIN_SPP:  # type: ignore[operator]
            plan = run_checkpoint(passes, budget_spp, spp=spp, after_first=after_first)
        else:
            plan = Plan(fallback(layers), [], 0.0, f"{spp} spp is too few for a checkpoint")
        chosen = plan.chosen
        assessed = plan.assessment()
        if check is not None and assessed is not None:
            held = check(assessed.reconstruct_rate, chosen, 0.0)
            if held is not None:
                passes.start_split()
    else:
        chosen = fixed
    written.append(chosen)
    if deadline is not None and deadline.tail is not None and priors is not None:
        deadline.tail = priors.reconstruct_seconds.get(chosen.name, deadline.tail)
    if deadline is None:
        target = int(spp)  # type: ignore[arg-type]
        # a split frame's rest in SPLIT_PASSES passes or more, so that each half gets groups of its own
        step = passes.max_spp if passes.split is None else max(1, -(-(target - passes.spp) // SPLIT_PASSES))
        while passes.spp < target:
            passes.run(chosen, min(passes.max_spp, step, target - passes.spp))
            if passes.index == 1:
                after_first()
            if progress is not None:
                progress(passes.spp, target)
    else:
        known = priors is not None and priors.warm(chosen.name) and deadline.tail is not None
        if passes.index == 0 and known:  # no checkpoint, the plan's cost known: the start-up check needs no pass
            costs = passes.kind(chosen).costs
            if deadline.left() < reserve() + LAST_PASS_MARGIN * costs.predict(1):
                raise startup_error(deadline.seconds, deadline.elapsed() + reserve() + costs.predict(1))
            rate = priors.reconstruct_rate  # type: ignore[union-attr]
            if check is not None and rate:
                held = check(rate, chosen, 0.0)
                if held is not None:
                    passes.start_split()
        elif passes.index == 0:  # no checkpoint: the first pass compiles the kernel and is the start-up check
            passes.run(chosen, 1)
            after_first()
            if check is not None and check(CHECK_PRIOR_RATE, chosen, reconstruct_startup()) is not None:
                held = check(reconstruct_rate(as_frame(passes.frame_result(chosen))), chosen, 0.0)
                if held is not None:
                    passes.start_split()
        # the chosen plan's passes, then primal passes in the gap too small for one more of them (FILLER)
        filler = candidate(FILLER)

        def run(n: int, c: Candidate = chosen) -> None:
            passes.run(c, n)
            if progress is not None:
                progress(passes.spp, 0)

        fill_with_filler(deadline, passes.kind(chosen).costs, run,
                         passes.kind(filler).costs if chosen.gradients != "none" else None,
                         lambda n: run(n, filler), reserve, passes.max_spp)
    result = passes.frame_result(chosen)
    k = passes.gradients.get(chosen.name, ({}, 0))[1]
    return Planned(as_frame(result), chosen, plan, passes.spp, k if chosen.gradients != "none" else 0, passes.index,
                   passes.halves(chosen) if held is not None else None, held)


#: The fewest passes the rest of a --spp frame is rendered in once it is split for its check.
SPLIT_PASSES = 8
#: Seconds per pixel a reconstruction is assumed to take before one is measured (a fixed plan's check): the
#: default method on a two-layer frame took ~1.1e-6 (`oidn-l1`) on the 2-core development machine
#: (benchmarks/bench_service.py at 1280x720), so 3e-6 leaves room for a slower machine.
CHECK_PRIOR_RATE = 3e-6
#: Side of the tile :func:`reconstruct_rate` times.
RATE_TILE = 64


def reconstruct_rate(frame: Frame, reconstruct: Callable[[Frame], tuple[np.ndarray, str]] = reconstruct_default,
                     side: int = RATE_TILE) -> float:
    """Seconds per pixel of the default reconstruction of ``frame``, timed on its centre tile (``side`` square, or
    the whole frame when smaller) after one untimed call on the same tile (the process's first reconstruction
    pays its start-up: RECONSTRUCT_STARTUP)."""
    h, w = frame.height, frame.width
    y0, x0 = max(0, (h - side) // 2), max(0, (w - side) // 2)
    tile = crop(frame, (slice(y0, min(h, y0 + side)), slice(x0, min(w, x0 + side))))
    reconstruct(tile)
    start = time.perf_counter()
    reconstruct(tile)
    return (time.perf_counter() - start) / (tile.width * tile.height)
