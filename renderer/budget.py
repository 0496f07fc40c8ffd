"""Wall-time budgets for `gradsep render --seconds T`: the deadline, the cost model of render passes, and how many
samples the next pass may take.

Standard library only (no Mitsuba, no numpy), and every clock is injectable, so the budget logic is unit-tested
against a fake clock (tests/renderer/test_budget.py); renderer/planner.py drives the real passes with it (the
frame's whole budget, with its write: renderer/frame_budget.py).

The budget is the whole command's: it counts from the process's start (interpreter, imports), not from when the
render begins, because that is the wall time a farm sees. A render pass cannot be interrupted (one compiled
kernel), so the deadline is kept by not starting a pass that is predicted to end after it: the next pass's
duration is predicted from the passes already measured in this process, and its size shrinks as the deadline
nears so that the frame ends close to it.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from gradsep.model.errors import CommandError

Clock = Callable[[], float]

#: The largest share of the time left that one pass may take while more than a few samples still fit: a pass that
#: runs a fifth slower than predicted (a shared machine's swing) then overruns by at most a tenth of the time left.
PASS_SHARE = 0.5
#: The most a pass may grow over the largest warm pass measured: the prediction is refreshed at each size.
PASS_GROWTH = 4
#: Safety factor on the predicted cost of the pass that would end the frame (its overrun is not recoverable).
LAST_PASS_MARGIN = 1.15
#: Once a pass's fixed cost (tracing the kernel, read-back: PassCosts.overhead) is over this share of the time
#: left, the rest is one pass: halving the time left pass after pass would pay that cost several times over (at
#: sub-second budgets a small frame's pass is mostly fixed cost: docs/decisions.md).
PASS_OVERHEAD_SHARE = 0.05


def check_seconds(value: object) -> float:
    """``--seconds``: a finite number > 0, else a one-line user error."""
    try:
        seconds = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise CommandError(f"--seconds must be a number of seconds, got {value!r}") from None
    if not math.isfinite(seconds) or seconds <= 0:
        raise CommandError(f"--seconds must be a finite number > 0, got {value}")
    return seconds


def process_age(clock: Clock = time.monotonic) -> float:
    """Seconds since this process started (Linux: /proc/self/stat against the boot clock); 0 where unknown.

    ``clock`` must be CLOCK_MONOTONIC-like: on Linux the process start time is in clock ticks since boot, read
    against CLOCK_BOOTTIME (which, unlike monotonic, counts suspend; the two agree on a machine that never slept)."""
    try:
        with open("/proc/self/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        start_ticks = int(fields[19])  # field 22 of proc(5), counted from the state field (3)
        started = start_ticks / os.sysconf("SC_CLK_TCK")
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - started
    except (OSError, ValueError, IndexError, AttributeError):
        return 0.0
    return max(0.0, age) if math.isfinite(age) else 0.0


@dataclass
class Deadline:
    """A wall-time budget of ``seconds`` that started ``spent`` seconds before it was made (process start-up; 0:
    it starts now, e.g. when an evaluation row starts).

    ``tail``: the seconds the caller needs after the last render pass, when it knows them -- an in-process caller
    (the evaluation's ``gpt-auto`` row) reconstructs the frame instead of writing it and exiting. None: the
    command's own tail, the frame's write and the interpreter's exit (renderer.frame_budget.FrameBudget)."""

    seconds: float
    spent: float = 0.0
    clock: Clock = time.monotonic
    tail: float | None = None
    start: float = field(init=False)

    def __post_init__(self) -> None:
        self.start = self.clock() - self.spent

    def elapsed(self) -> float:
        return self.clock() - self.start

    def left(self) -> float:
        return self.seconds - self.elapsed()


@dataclass
class PassCosts:
    """Measured wall time of the warm render passes of one kind, as ``overhead + per_sample * spp``.

    A kind's first pass compiles its kernel (or loads it from Dr.Jit's cache), so it is recorded apart
    (:meth:`first`, with the seconds Dr.Jit's back end spent compiling in it) and predicts later passes, less that
    compile, only until a warm pass has been measured (:func:`next_pass_spp` keeps the next pass small until then:
    a G-PT kernel's compile can be most of a short budget, and charging it to every sample would end the frame
    after one). ``overhead`` is the fixed
    cost of a pass (recording, launch, read-back); where it is not known (0) the whole pass time is charged per
    sample, which overestimates small passes: safe for a deadline. The per-sample cost is the largest of the
    recent rates, so a machine that slows down is followed at once.
    """

    overhead: float = 0.0  # fitted from warm passes of two sizes or more (fitted_overhead)
    warm: list[tuple[int, float]] = field(default_factory=list)  # (spp, seconds) of the last warm passes
    first_pass: tuple[int, float] | None = None  # (spp, seconds) of the compiling pass
    first_compile: float = 0.0  # seconds of that pass spent compiling kernels (Dr.Jit's back end; 0: not known)

    def first(self, spp: int, seconds: float, compile_seconds: float = 0.0) -> None:
        self.first_pass = (int(spp), float(seconds))
        self.first_compile = min(max(float(compile_seconds), 0.0), float(seconds))

    def record(self, spp: int, seconds: float) -> None:
        self.warm = [*self.warm[-3:], (int(spp), float(seconds))]
        self.overhead = fitted_overhead(self.warm, self.overhead)

    @property
    def per_sample(self) -> float:
        if self.warm:
            return max(max(seconds - self.overhead, 0.0) / spp for spp, seconds in self.warm)
        if self.first_pass is not None:
            spp, seconds = self.first_pass
            warm = seconds - self.first_compile
            return (warm if warm > 0 else seconds) / spp
        return math.inf

    def predict(self, spp: int) -> float:
        return self.overhead + self.per_sample * spp


def fitted_line(passes: list[tuple[int, float]]) -> tuple[float, float] | None:
    """The least-squares line ``seconds = intercept + slope * spp`` through passes ``(spp, seconds)``, as
    (intercept, slope); None while every pass has the same size."""
    if len({spp for spp, _ in passes}) < 2:
        return None
    n = len(passes)
    mean_x = sum(s for s, _ in passes) / n
    mean_y = sum(t for _, t in passes) / n
    sxx = sum((s - mean_x) ** 2 for s, _ in passes)
    slope = sum((s - mean_x) * (t - mean_y) for s, t in passes) / sxx
    return mean_y - slope * mean_x, slope


def fitted_overhead(passes: list[tuple[int, float]], default: float = 0.0) -> float:
    """The fixed cost per pass from warm passes of different sizes (:func:`fitted_line`'s intercept), clipped to
    [0, half the smallest pass's time] (timing noise on a shared machine can make the fitted line flat, which would
    call every pass overhead and make more samples look free); ``default`` while every pass has the same size."""
    line = fitted_line(passes)
    if line is None:
        return default
    return min(max(line[0], 0.0), 0.5 * min(t for _, t in passes))


def next_pass_spp(left: float, reserve: float, costs: PassCosts, max_spp: int) -> int:
    """Samples per pixel for the next pass, or 0 to stop: the pass must end, with ``reserve`` seconds (writing the
    frame) still left, before the deadline. While much time is left a pass takes at most PASS_SHARE of it, so the
    prediction is refreshed before the pass that ends the frame; that last pass is sized with LAST_PASS_MARGIN.
    A pass is at most PASS_GROWTH times the largest warm pass measured."""
    usable = left - reserve
    per = costs.per_sample
    if not (usable > 0 and per > 0 and math.isfinite(per)):
        return 0
    fits = math.floor((usable / LAST_PASS_MARGIN - costs.overhead) / per)
    if fits < 1:
        return 0
    share = math.floor((usable * PASS_SHARE - costs.overhead) / per)
    # a few samples left, or passes whose fixed cost is a large part of the time left: take them all in one pass
    last = share < max(2, fits // 4) or costs.overhead > PASS_OVERHEAD_SHARE * usable
    spp = fits if last else share
    if costs.warm:
        spp = min(spp, PASS_GROWTH * max(n for n, _ in costs.warm))
    elif costs.first_pass is not None and costs.first_compile > 0:  # a rate less the compile: not yet measured
        spp = min(spp, PASS_GROWTH * costs.first_pass[0])
    return max(1, min(spp, max_spp))


def fill_to_deadline(deadline: Deadline, costs: PassCosts, reserve: Callable[[], float], max_spp: int,
                     run: Callable[[int], None]) -> int:
    """Run passes (``run(spp)``, which records its own time in ``costs``) while :func:`next_pass_spp` finds one
    that fits before ``deadline`` with ``reserve()`` seconds left; returns the samples rendered."""
    done = 0
    while (spp := next_pass_spp(deadline.left(), reserve(), costs, max_spp)) > 0:
        run(spp)
        done += spp
    return done


# ------------------------------------------------------------------------------------------------- the filler

#: Passes of the frame's plan stop up to one pass short of the deadline, and at large frames one 1-spp G-PT pass is
#: a large share of a budget. That gap is filled with passes of a cheaper kind (renderer/plans.py FILLER: primal
#: passes, whose samples every plan's bases absorb). The filler's kernel costs a compile (or cache load) first, so
#: it is warmed up only where the plan's passes are coarse: a 1-spp pass of at least FILLER_MIN_PASS seconds and
#: FILLER_SHARE of the budget (small frames' passes are fine-grained already: nothing to gain).
FILLER_MIN_PASS = 0.5
FILLER_SHARE = 0.02
#: Before any warm pass, the plan's compiling 1-spp pass alone says its passes are coarse when it took this long:
#: the filler is then warmed up at once, while the time left surely holds it (waiting for a warm pass can leave no
#: room, and the frame ends a whole pass short). So does one of at least FILLER_MIN_PASS that took
#: FILLER_EARLY_SHARE of the budget: at short budgets a filler warmed up after the first warm pass no longer fits
#: (docs/decisions.md). Below both, the first warm pass decides (FILLER_MIN_PASS).
FILLER_EARLY_PASS = 2.0
FILLER_EARLY_SHARE = 0.1


def filler_pays(costs: PassCosts, seconds: float) -> bool:
    """Whether the plan's passes (``costs``) are coarse enough in a ``seconds`` budget to warm up a filler: its warm
    1-spp pass, or before one its compiling pass (FILLER_EARLY_PASS, FILLER_EARLY_SHARE)."""
    if costs.warm:
        return costs.predict(1) >= max(FILLER_MIN_PASS, FILLER_SHARE * seconds)
    if costs.first_pass is not None:
        first = costs.first_pass[1] / costs.first_pass[0]
        return first >= max(FILLER_SHARE * seconds,
                            min(FILLER_EARLY_PASS, max(FILLER_MIN_PASS, FILLER_EARLY_SHARE * seconds)))
    return False


def filler_warmup_fits(left: float, reserve: float, costs: PassCosts) -> bool:
    """Whether the filler's first (compiling) 1-spp pass surely ends before the deadline: it is bounded by the plan's
    own first pass (``costs.first_pass``), whose kernel is larger, whose sample costs more, and which also paid the
    process's one-time set-up (the JIT back end, the scene's upload)."""
    if costs.first_pass is None:
        return False
    return left - reserve >= LAST_PASS_MARGIN * costs.first_pass[1]


def fill_with_filler(deadline: Deadline, costs: PassCosts, run: Callable[[int], None], filler: PassCosts | None,
                     run_filler: Callable[[int], None], reserve: Callable[[], float], max_spp: int) -> int:
    """:func:`fill_to_deadline` with the plan's passes (``run``, costs ``costs``), then the gap too small for one more
    of them with the filler's cheaper passes (``run_filler``, costs ``filler``; None: no filler); returns the
    samples rendered. A cold filler's kernel is warmed up (a 1-spp pass, and a warm one where it fits) as soon as
    :func:`filler_pays` -- before the plan's passes, or after its first warm pass -- so that the gap's passes are
    sized from measured costs; else at the gap; always only where :func:`filler_warmup_fits`."""
    done = 0

    def warm_up() -> None:
        nonlocal done
        run_filler(1)
        done += 1

    def maybe_warm_up() -> None:
        if (filler is not None and filler.first_pass is None and filler_pays(costs, deadline.seconds)
                and filler_warmup_fits(deadline.left(), reserve(), costs)):
            warm_up()
            # and one warm pass, while there is time: the compiling pass overstates a pass (about twice a warm one),
            # which would leave the gap unfilled; its sample is the frame's
            if deadline.left() - reserve() >= LAST_PASS_MARGIN * filler.first_pass[1]:  # type: ignore[index]
                warm_up()

    def plan_pass(spp: int) -> None:
        run(spp)
        maybe_warm_up()

    maybe_warm_up()
    done += fill_to_deadline(deadline, costs, reserve, max_spp, plan_pass)
    if filler is None:
        return done
    if filler.first_pass is None and filler_warmup_fits(deadline.left(), reserve(), costs):
        warm_up()
    return done + fill_to_deadline(deadline, filler, reserve, max_spp, run_filler)
