"""A planned frame's render passes: each pass renders one plan's kernel (renderer.gpt.render_pass) with its own
random stream, and is added into the frame's sums.

Passes of different plans mix: every plan's base path is the same unbiased path tracer (the primal-only mode's
bases and features are G-PT's), so the frame's bases and features average the samples of every pass, and its
gradients those of the rendered plan's passes (the ``--gradient-spp`` rule of renderer.gpt.render_gpt). Once
:meth:`Passes.start_split` runs, every pass is also dealt into the groups of the frame's own error estimate
(renderer/check.py).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.model.errors import CommandError
from gradsep.model.frame import Features, Frame, Layer
from gradsep.renderer.budget import Clock, PassCosts
from gradsep.renderer.check import Half, Split
from gradsep.renderer.plans import RenderPlan
from gradsep.renderer.scene import LoadedScene


@dataclass
class CompileTime:
    """Seconds Dr.Jit's back end spent compiling kernels (cache misses) inside a :func:`compile_timer` block."""

    seconds: float = 0.0


@contextmanager
def compile_timer(active: bool = True) -> Iterator[CompileTime]:
    """Time the kernel compiles inside the block from Dr.Jit's kernel history (switched on for the block only;
    ``active`` False, or a Dr.Jit without it, measures nothing: 0). Only the back end's time of the kernels that
    missed the cache counts: the IR's generation recurs in every warm pass, so it is no compile."""
    timed = CompileTime()
    if not active:
        yield timed
        return
    try:
        import drjit as dr

        flag = dr.JitFlag.KernelHistory
        was = dr.flag(flag)
        dr.kernel_history()  # drop entries from before the block
        dr.set_flag(flag, True)
    except (ImportError, AttributeError):  # pragma: no cover - a Dr.Jit without kernel history
        yield timed
        return
    try:
        yield timed
    finally:
        dr.set_flag(flag, was)
        history = dr.kernel_history()
        timed.seconds = sum(float(k.get("backend_time", 0.0)) for k in history if not k.get("cache_hit")) / 1e3


@dataclass
class PassKind:
    """One plan's kernel settings on this frame and its passes' measured costs."""

    settings: Any  # renderer.gpt_settings.GptSettings
    shift: Any  # renderer.shift_protocol.Shift or None
    costs: PassCosts = field(default_factory=PassCosts)


@dataclass
class Priors:
    """What earlier renders in this process measured on the same scene and frame size, for a planner that starts
    warm (a worker that renders the scene again, the evaluation's planned row after its untimed calibration): no
    probing pass is spent on what is known.

    ``costs``: per plan name, its passes' measured cost (warm passes of two sizes or more: their kernel is
    compiled, so none of its passes is a compiling one); ``reconstruct_rate``: seconds per pixel of the default
    reconstruction, its start-up paid (what the checkpoint's and the frame check's reconstructions will take)."""

    costs: dict[str, PassCosts] = field(default_factory=dict)
    reconstruct_rate: float | None = None
    #: per plan name, the seconds its frame's reconstruction takes: an in-process caller's Deadline.tail becomes
    #: the chosen plan's once it is chosen (a plain frame's `oidn` is quicker than `oidn-l1`)
    reconstruct_seconds: dict[str, float] = field(default_factory=dict)

    def warm(self, name: str) -> bool:
        """Whether plan ``name``'s passes have a measured cost line (a pass can be sized without a probe)."""
        c = self.costs.get(name)
        return c is not None and len({spp for spp, _ in c.warm}) >= 2


class Passes:
    """Runs render passes of any plan on one scene and keeps their sums for the final frame."""

    def __init__(self, loaded: LoadedScene, layers: tuple[str, ...], seed: int, shift: str | None = None,
                 clock: Clock = time.monotonic, priors: Priors | None = None) -> None:
        from gradsep.renderer.gpt import MAX_LANES_PER_PASS

        self.loaded, self.layers, self.seed, self.shift_name, self.clock = loaded, layers, seed, shift, clock
        self.priors = priors
        self.max_spp = max(1, MAX_LANES_PER_PASS // (loaded.width * loaded.height))
        self.kinds: dict[str, PassKind] = {}
        self.index = 0  # passes so far: the next pass's seed stream
        self.bases: dict[str, np.ndarray] | None = None  # base and feature sums over every pass
        self.spp = 0
        self.gradients: dict[str, tuple[dict[str, np.ndarray], int]] = {}  # plan -> (gradient sums, spp)
        self._owned: list[np.ndarray] = []  # the sums arrays this object made (the others are a pass's own)
        #: once :meth:`start_split` ran: every pass also dealt into groups for the frame's own error estimate
        self.split: Split | None = None

    def kind(self, plan: RenderPlan) -> PassKind:
        if plan.name not in self.kinds:
            kind = PassKind(self._settings(plan), self._shift(plan))
            known = self.priors.costs.get(plan.name) if self.priors is not None else None
            if known is not None:  # a copy: this frame's passes refine it without touching the caller's
                kind.costs = PassCosts(known.overhead, list(known.warm), known.first_pass, known.first_compile)
            self.kinds[plan.name] = kind
        return self.kinds[plan.name]

    def _settings(self, plan: RenderPlan) -> Any:
        from gradsep.renderer.gpt_settings import GptSettings

        color = self.layers == ("color",)
        return GptSettings(max_depth=self.loaded.max_depth, rr_depth=self.loaded.rr_depth,
                           direct=color or "direct" in self.layers, indirect=color or "indirect" in self.layers,
                           separate=not color, gradients="direct" if plan.gradients == "direct" else "all",
                           offsets=plan.offsets if plan.traces_gradients else "all")

    def _shift(self, plan: RenderPlan) -> Any:
        """The plan's shift: none for a plain plan; for the direct layer's gradients the shift's
        ``for_direct_layer()`` where it has one (the parts that cannot change a direct-layer event left out)."""
        from gradsep.renderer.shift import make_shift

        if not plan.traces_gradients:
            return None
        try:
            shift = make_shift(self.shift_name)
        except ValueError as exc:
            raise CommandError(str(exc)) from None
        if plan.gradients == "direct":
            shift = getattr(shift, "for_direct_layer", lambda: shift)()
        return shift

    def run(self, plan: RenderPlan, spp: int) -> dict[str, np.ndarray]:
        """Render one pass of ``spp`` samples with ``plan``, add it to the frame, record its cost; returns its
        sums."""
        from gradsep.renderer.gpt import pass_seed, render_pass

        kind = self.kind(plan)
        first = kind.costs.first_pass is None and not kind.costs.warm  # a kernel known warm (Priors) compiles nothing
        start = self.clock()
        with compile_timer(first) as compiled:
            sums = render_pass(self.loaded.scene, kind.shift, kind.settings, self.loaded.width, self.loaded.height,
                               spp, pass_seed(self.seed, self.index))
        bases = {k: v for k, v in sums.items() if ".grad" not in k}
        grads = {k: v for k, v in sums.items() if ".grad" in k}
        self.bases = self._added(self.bases, bases)
        if grads:
            have, n = self.gradients.get(plan.name, (None, 0))
            self.gradients[plan.name] = (self._added(have, grads), n + spp)
        if self.split is not None:
            self.split.add(plan.name, bases, grads, spp)
        # the pass's cost includes adding it to the frame: what the deadline must budget for each pass
        seconds = self.clock() - start
        if first:
            kind.costs.first(spp, seconds, compiled.seconds)
        else:
            kind.costs.record(spp, seconds)
        self.index += 1
        self.spp += spp
        return sums

    def _added(self, total: dict[str, np.ndarray] | None, sums: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``total + sums``: the first pass's arrays as they are (a frame of one pass copies nothing), new arrays at
        the second (a pass's own sums are never written to: the caller may hold them), in place from then on (a
        large frame's float64 sums would cost a copy at every pass)."""
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

    def frame_result(self, plan: RenderPlan, window: tuple[slice, slice] | None = None) -> Any:
        """The frame so far as ``plan``'s frame (a renderer.gpt_settings.GptResult): every pass's bases and features,
        ``plan``'s passes' gradients; only its ``window`` (rows, columns) when given (what
        renderer.frame_budget.write_seconds times)."""
        from gradsep.renderer.gpt import finish

        assert self.bases is not None, "no pass rendered"
        grads, k = self.gradients.get(plan.name, ({}, 0))
        sums = {**self.bases, **grads}
        if window is not None:
            sums = {key: v[window] for key, v in sums.items()}
        return finish(sums, self.kind(plan).settings, self.spp, self.index, k or None)

    def gradient_spp(self, plan: RenderPlan) -> int:
        """The samples that traced ``plan``'s gradients (0 for a plain plan)."""
        return self.gradients.get(plan.name, ({}, 0))[1] if plan.traces_gradients else 0

    def start_split(self) -> None:
        """Deal every pass from now on into groups for the frame's own error estimate (renderer/check.py), the
        passes so far as one lump: splitting costs a copy of the frame's sums, so it starts only once the check is
        known to fit."""
        if self.split is None:
            self.split = Split()
            if self.bases is not None:
                self.split.add_lump(self.bases, self.gradients, self.spp, self.index)

    def halves(self, plan: RenderPlan) -> list[Half] | None:
        """The frame's two halves as ``plan``'s frames, with their samples and the other half's groups
        (renderer/check.py), or None when the passes were not split or a half lacks samples (or ``plan``'s
        gradients)."""
        from gradsep.renderer.gpt import finish

        grads, k = self.gradients.get(plan.name, ({}, 0))
        q = self.split
        if q is None or self.bases is None or not q.ready(plan.name, plan.traces_gradients, k):
            return None
        out = []
        for i, (sums, n, count, gradient_spp) in enumerate(q.halves(plan.name, self.bases, grads, self.spp, k)):
            frame = as_frame(finish(sums, self.kind(plan).settings, n, count, gradient_spp))
            frame.warnings = []
            out.append((frame, n, q.batches(i)))
        return out


def as_frame(result: Any) -> Frame:
    """A renderer.gpt_settings.GptResult as a Frame (no metadata yet)."""
    layers = {name: Layer(base=v["base"], dx=v.get("dx"), dy=v.get("dy"), var=v.get("var"))
              for name, v in result.layers.items()}
    features = Features(result.albedo, result.normal, result.depth)
    return Frame(layers=layers, features=features, warnings=list(result.warnings))


def without_gradients(frame: Frame) -> Frame:
    """``frame`` as a plain frame: its bases, variances and features, no gradients (what a primal plan's frame of
    the same passes is: every plan's bases are the same path tracer's)."""
    return Frame(layers={n: Layer(v.base, var=v.var) for n, v in frame.layers.items()}, features=frame.features)


def crop(frame: Frame, window: tuple[slice, slice]) -> Frame:
    """The ``window`` (rows, columns) of ``frame``'s layers and features, as contiguous arrays."""
    ys, xs = window

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else np.ascontiguousarray(a[ys, xs])

    f = frame.features
    features = None if f is None else Features(cut(f.albedo), cut(f.normal), cut(f.depth))
    return Frame(layers={n: Layer(cut(v.base), cut(v.dx), cut(v.dy), cut(v.var)) for n, v in frame.layers.items()},
                 features=features)
