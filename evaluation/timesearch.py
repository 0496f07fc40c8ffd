"""How an equal-time row finds the spp its budget buys: a cost line per renderer, then a search on the measured
time curve.

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
(evaluation.scores.interpolated_scores; the report marks it). The time in the results is the time the kept try actually
took (the median of its timings), not the prediction.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Attempt", "Bracketed", "CostModel", "SearchRules", "TIME_SEARCH", "TimeSearch", "interpolate_at"]

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


@dataclass(frozen=True)
class SearchRules:
    """How a :class:`TimeSearch` tries: the accepted miss, the tries allowed, and which tries are re-timed."""

    tolerance: float = 0.05  # a try within this fraction of the target is kept
    max_tries: int = 8  # tries (distinct spp) before the one closest to the target is kept
    repeat_below: float = 2.0  # tries shorter than this many seconds are timed ``repeats`` times (median)
    repeats: int = 3


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
                 rules: SearchRules = SearchRules()) -> None:
        self.target, self.slope, self.max_spp = target, max(slope, 1e-12), max_spp
        self.overhead = max(0.0, overhead)
        self.tolerance, self.max_tries = rules.tolerance, rules.max_tries
        self.repeat_below, self.repeats = rules.repeat_below, rules.repeats
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
