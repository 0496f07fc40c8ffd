"""evaluation.timesearch.TimeSearch, the equal-time spp search, against fake timers: a fixed per-render overhead
the calibration slope does not know about, multiplicative noise and load spikes; and the cases where no spp can
meet the budget, which must be reported with the reason instead of passing as met."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.evaluation.timesearch import SearchRules, TimeSearch


class FakeTimer:
    """seconds(spp) = (overhead + per_spp · spp) x noise: lognormal jitter, and with probability ``spike`` a
    load spike (+60 %); ``measure`` returns (output, render seconds, post seconds) like PathRenderer's tries."""

    def __init__(self, overhead: float, per_spp: float, *, jitter: float = 0.0, spike: float = 0.0,
                 seed: int = 0) -> None:
        self.overhead, self.per_spp = overhead, per_spp
        self.jitter, self.spike = jitter, spike
        self.rng = np.random.default_rng(seed)
        self.calls: list[int] = []

    def true_seconds(self, spp: int) -> float:
        return self.overhead + self.per_spp * spp

    def measure(self, spp: int) -> tuple[int, float, float]:
        self.calls.append(spp)
        factor = float(np.exp(self.rng.normal(0.0, self.jitter))) if self.jitter else 1.0
        if self.rng.random() < self.spike:
            factor *= 1.6
        seconds = self.true_seconds(spp) * factor
        return spp, 0.8 * seconds, 0.2 * seconds  # the output is the spp, so the test sees what was kept


@pytest.mark.parametrize("seed", range(12))
def test_converges_within_5_percent_with_overhead_noise_and_spikes(seed: int) -> None:
    """Overhead 0.3-0.9 s that the calibration slope ignores, a slope mis-calibrated by 0.5-2x, 4 % jitter and a
    load spike in one timing of ten: the kept try is within 5 % measured, and its true time within 8 %."""
    rng = np.random.default_rng(1000 + seed)
    overhead, per_spp = rng.uniform(0.3, 0.9), rng.uniform(0.002, 0.02)
    budget = overhead + per_spp * rng.uniform(30, 400)
    timer = FakeTimer(overhead, per_spp, jitter=0.04, spike=0.1, seed=seed)
    calibrated = per_spp * rng.choice([0.5, 0.8, 1.25, 2.0])
    search = TimeSearch(budget, calibrated, max_spp=100_000)
    got = search.run(timer.measure, first_spp=max(1, round(budget / calibrated)))  # prediction without overhead
    assert got.miss <= 0.05 and got.note == "", (got, budget)
    assert got.output == got.spp and got.attempts <= 8
    assert abs(timer.true_seconds(got.spp) / budget - 1) <= 0.08, (got.spp, budget)
    assert abs((got.render_seconds + got.post_seconds) / budget - 1) == pytest.approx(got.miss, abs=1e-12)


def test_misses_are_rare_and_always_explained_under_heavy_spikes() -> None:
    """200 rows with one timing in ten spiked by +60 % (so some medians of three are spiked too): at least 95 %
    land within 5 %, and every row that does not carries a reason. (Measured: 197 of 200.)"""
    misses = 0
    for seed in range(200):
        rng = np.random.default_rng(1000 + seed)
        overhead, per_spp = rng.uniform(0.3, 0.9), rng.uniform(0.002, 0.02)
        budget = overhead + per_spp * rng.uniform(30, 400)
        calibrated = per_spp * rng.choice([0.5, 0.8, 1.25, 2.0])
        timer = FakeTimer(overhead, per_spp, jitter=0.04, spike=0.1, seed=seed)
        got = TimeSearch(budget, calibrated, max_spp=100_000).run(timer.measure, round(budget / calibrated))
        assert (got.miss <= 0.05) == (got.note == "") and got.attempts <= 8
        misses += got.miss > 0.05
    assert misses <= 10, misses


def test_one_spike_does_not_wall_off_the_right_spp() -> None:
    """The old bisection treated a spiked try below the right spp as a too-slow bound and never went above it;
    a short try is timed three times and the median used, so one spike changes nothing."""
    timer = FakeTimer(0.2, 0.01)
    spiked = {0}

    def measure(spp: int) -> tuple[int, float, float]:
        out = timer.measure(spp)
        if len(timer.calls) - 1 in spiked:  # the very first timing is 60 % slow
            return out[0], out[1] * 1.6, out[2] * 1.6
        return out

    got = TimeSearch(1.2, 0.01, 10_000).run(measure, first_spp=90)
    assert got.miss <= 0.05 and got.spp >= 95 and got.attempts <= 2


def test_long_tries_are_timed_once_unless_they_surprise() -> None:
    timer = FakeTimer(0.0, 0.01)
    got = TimeSearch(5.0, 0.01, 10_000, rules=SearchRules(repeat_below=2.0)).run(timer.measure, first_spp=500)
    assert timer.calls == [500] and got.attempts == 1 and got.miss == pytest.approx(0.0)
    slow = FakeTimer(2.0, 0.01)  # 2 s of overhead the calibration did not predict: re-timed before it is trusted
    got = TimeSearch(5.0, 0.01, 10_000, rules=SearchRules(repeat_below=2.0)).run(slow.measure, first_spp=500)
    assert slow.calls[:3] == [500] * 3 and got.miss <= 0.05


def test_gives_up_when_one_spp_is_already_over_budget() -> None:
    timer = FakeTimer(2.0, 0.01)  # a 2 s fixed cost against a 1 s budget: impossible
    got = TimeSearch(1.0, 0.01, 10_000).run(timer.measure, first_spp=50)
    assert got.spp == 1 and got.miss > 0.05 and "1 spp alone takes" in got.note
    assert got.attempts <= 3


def test_gives_up_on_integer_granularity() -> None:
    timer = FakeTimer(0.1, 1.0)  # 1 spp: 1.1 s, 2 spp: 2.1 s; a 1.6 s budget falls between
    got = TimeSearch(1.6, 1.0, 10_000).run(timer.measure, first_spp=1)
    assert got.miss > 0.05 and "granularity" in got.note and "1 spp" in got.note and "2 spp" in got.note


def test_gives_up_at_the_spp_cap() -> None:
    timer = FakeTimer(0.0, 0.001)
    got = TimeSearch(5.0, 0.001, max_spp=1000).run(timer.measure, first_spp=1000)
    assert got.spp == 1000 and "cap" in got.note


@pytest.mark.parametrize("seed", range(4))
def test_reports_noise_honestly_when_the_timer_is_useless(seed: int) -> None:
    """Timings off by 2x either way: the search stops after its tries, and a kept try outside 5 % says why."""
    timer = FakeTimer(0.1, 0.01, jitter=0.7, seed=seed)
    got = TimeSearch(1.0, 0.01, 10_000).run(timer.measure, first_spp=90)
    assert len(got.tries) <= got.attempts <= 8  # re-timings of a tried spp count as tries
    assert (got.miss <= 0.05) == (got.note == "")
    if got.note:
        assert "timing noise" in got.note
