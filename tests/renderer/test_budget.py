"""The time-budget logic of `gradsep render --seconds` (renderer/budget.py) against a fake clock: no Mitsuba."""

from __future__ import annotations

import math
import random

import pytest

from gradsep.model.errors import CommandError
from gradsep.renderer.budget import (
    FILLER_MIN_PASS,
    LAST_PASS_MARGIN,
    PASS_GROWTH,
    PASS_OVERHEAD_SHARE,
    Deadline,
    PassCosts,
    check_seconds,
    fill_to_deadline,
    fill_with_filler,
    filler_pays,
    filler_warmup_fits,
    fitted_overhead,
    next_pass_spp,
    process_age,
)


class FakeClock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "-inf", "abc", "", None, 0, -0.5, math.nan])
def test_bad_seconds_are_one_line_user_errors(value: object) -> None:
    with pytest.raises(CommandError) as err:
        check_seconds(value)
    assert "--seconds" in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize(("value", "expected"), [("5", 5.0), ("0.25", 0.25), (12, 12.0), ("1e2", 100.0)])
def test_good_seconds(value: object, expected: float) -> None:
    assert check_seconds(value) == expected


def test_deadline_counts_what_was_spent_before_it() -> None:
    clock = FakeClock()
    d = Deadline(10.0, spent=1.5, clock=clock)
    assert d.elapsed() == pytest.approx(1.5) and d.left() == pytest.approx(8.5)
    clock.now += 9.0
    assert d.left() == pytest.approx(-0.5)


def test_process_age_is_this_process() -> None:
    age = process_age()
    assert 0.0 <= age < 7 * 24 * 3600  # the test process started before this call, not before the machine


def test_fitted_overhead_recovers_a_line_and_is_clipped() -> None:
    assert fitted_overhead([(1, 0.3), (5, 1.1), (9, 1.9)]) == pytest.approx(0.1)
    assert fitted_overhead([(4, 1.0), (4, 1.2)], default=0.05) == 0.05  # one size: nothing to separate
    # a flat line (timing noise) would call everything overhead: at most half the smallest pass
    assert fitted_overhead([(1, 1.0), (8, 1.0)]) == pytest.approx(0.5)
    assert fitted_overhead([(1, 0.1), (8, 2.0)]) == 0.0  # a negative intercept is no overhead


def test_pass_costs_use_the_first_pass_only_until_a_warm_one() -> None:
    costs = PassCosts()
    assert costs.per_sample == math.inf
    costs.first(1, 3.0)  # compiling
    assert costs.per_sample == pytest.approx(3.0)
    costs.record(1, 0.3)
    costs.record(4, 0.9)
    assert costs.overhead == pytest.approx(0.1)
    assert costs.per_sample == pytest.approx(0.2)
    assert costs.predict(10) == pytest.approx(2.1)
    costs.record(4, 1.7)  # the machine slowed down: the slowest recent rate wins
    assert costs.per_sample > 0.3


def test_next_pass_spp_stops_when_nothing_fits() -> None:
    costs = PassCosts(warm=[(1, 0.5)])
    assert next_pass_spp(0.4, 0.0, costs, 100) == 0
    assert next_pass_spp(2.0, 1.8, costs, 100) == 0
    assert next_pass_spp(-1.0, 0.0, costs, 100) == 0
    assert next_pass_spp(10.0, 0.0, PassCosts(), 100) == 0  # no measured cost: never start blind


def test_a_compiling_pass_predicts_the_next_without_its_compile_and_keeps_it_small() -> None:
    """A G-PT kernel's compile can be half of a short budget (procedural:moving at 256², 10 s: a 5.3 s first
    pass): charged to its one sample it ended the frame at 1 spp with half the budget unused. Less the compile
    Dr.Jit measured, the rate lets the frame go on; the next pass stays within PASS_GROWTH of the first until a
    warm pass measures it."""
    charged = PassCosts(first_pass=(1, 5.3))
    assert next_pass_spp(4.7, 0.2, charged, 1000) == 0  # the whole compile charged to a sample: nothing fits
    costs = PassCosts()
    costs.first(1, 5.3, compile_seconds=5.0)
    assert costs.per_sample == pytest.approx(0.3)
    n = next_pass_spp(4.7, 0.2, costs, 1000)
    assert 1 <= n <= PASS_GROWTH
    costs.record(n, 0.3 * n)  # measured: growth from the warm pass, as before
    assert next_pass_spp(4.4, 0.2, costs, 1000) > n
    # a compile measured at or over the pass's own time (clock skew) leaves the whole pass as the rate
    skewed = PassCosts()
    skewed.first(1, 2.0, compile_seconds=3.0)
    assert skewed.per_sample == pytest.approx(2.0)


def test_next_pass_spp_shares_the_time_and_caps_growth_and_lanes() -> None:
    costs = PassCosts(warm=[(10, 1.0)])  # 0.1 s per sample
    n = next_pass_spp(100.0, 0.0, costs, 10_000)
    assert n == PASS_GROWTH * 10  # growth-limited, not the 500 that half the time would buy
    costs = PassCosts(warm=[(100, 10.0)])
    assert next_pass_spp(100.0, 0.0, costs, 10_000) == 400  # half of the time left at most: 500 > growth 400
    assert next_pass_spp(100.0, 0.0, costs, 64) == 64  # the lanes-per-pass cap
    # the last few samples are taken in one pass, with the safety margin
    costs = PassCosts(warm=[(1, 1.0)])
    assert next_pass_spp(3.0, 0.0, costs, 100) == math.floor(3.0 / LAST_PASS_MARGIN)


def test_passes_whose_fixed_cost_is_a_large_part_of_the_time_left_end_in_one_pass() -> None:
    """Halving the time left pass after pass pays the fixed cost each time: once it is over PASS_OVERHEAD_SHARE of
    the time left, the rest is one pass, sized with the margin."""
    costs = PassCosts()
    costs.record(8, 0.050)
    costs.record(16, 0.082)  # 0.018 s per pass + 0.004 s per sample (320x240 in process)
    assert costs.overhead == pytest.approx(0.018) and costs.per_sample == pytest.approx(0.004)
    # 0.3 s left: the fixed cost is 6 % of it -> all of it in one pass (without the rule: half of it, 33 spp)
    over, per = costs.overhead, costs.per_sample
    assert next_pass_spp(0.3, 0.0, costs, 10_000) == math.floor((0.3 / LAST_PASS_MARGIN - over) / per) == 60
    # 0.5 s left: 3.6 % -> half the time left, as before
    assert 0.018 < PASS_OVERHEAD_SHARE * 0.5
    assert next_pass_spp(0.5, 0.0, costs, 10_000) == math.floor((0.5 * 0.5 - over) / per) == 57


def _simulate(seconds: float, per: float, overhead: float, slow: float = 1.0, jitter: float = 0.0,
              seed: int = 0, first: float = 2.0) -> tuple[float, int]:
    """A budgeted render against a fake clock: one compiling pass, then fill_to_deadline, then a write."""
    rng = random.Random(seed)
    clock = FakeClock()
    deadline = Deadline(seconds, spent=0.5, clock=clock)  # 0.5 s of process start-up
    costs = PassCosts()
    write = 0.2

    def run(spp: int) -> None:
        took = (overhead + per * spp) * slow * (1.0 + rng.uniform(-jitter, jitter))
        clock.now += took
        costs.record(spp, took)

    clock.now += first
    costs.first(1, first)
    spp = 1 + fill_to_deadline(deadline, costs, lambda: write, 10_000, run)
    clock.now += write
    return deadline.elapsed(), spp


@pytest.mark.parametrize(("seconds", "per", "overhead"), [(5.0, 0.01, 0.02), (5.0, 0.3, 0.05), (30.0, 0.05, 0.1),
                                                          (60.0, 1.0, 0.2), (10.0, 0.9, 0.0)])
def test_a_steady_machine_ends_within_ten_percent_of_the_budget_never_after(seconds: float, per: float,
                                                                         overhead: float) -> None:
    elapsed, spp = _simulate(seconds, per, overhead)
    assert 0.9 * seconds <= elapsed <= seconds
    assert spp > 1


@pytest.mark.parametrize("seed", range(8))
def test_a_noisy_machine_ends_within_ten_percent(seed: int) -> None:
    """Every pass +-20 % off its prediction (a shared machine): the frame still ends within 10 % of T."""
    elapsed, _ = _simulate(20.0, 0.08, 0.05, jitter=0.2, seed=seed)
    assert 0.9 * 20.0 <= elapsed <= 1.1 * 20.0


def test_a_machine_that_slows_down_is_followed() -> None:
    """The warm passes run 1.5x slower than the compiling pass suggested: the next passes shrink."""
    elapsed, _ = _simulate(20.0, 0.08, 0.05, slow=1.5, first=0.2)
    assert 0.9 * 20.0 <= elapsed <= 1.1 * 20.0


def test_a_filler_is_warmed_up_only_for_coarse_passes_and_only_where_it_surely_fits() -> None:
    assert not filler_pays(PassCosts(), 20.0)  # no pass yet: nothing known
    assert not filler_pays(PassCosts(first_pass=(1, 1.5)), 20.0)  # a compiling pass at 320x240, under load
    assert filler_pays(PassCosts(first_pass=(1, 3.0)), 20.0)  # 1280x720: coarse already before a warm pass
    # a compiling pass of a tenth of a short budget is coarse too (1280x720 `direct-alternate` at T = 5 s) ...
    assert filler_pays(PassCosts(first_pass=(1, 0.55)), 5.0)
    assert not filler_pays(PassCosts(first_pass=(1, 0.55)), 10.0)  # ... not at 10 s: its first warm pass decides
    assert not filler_pays(PassCosts(first_pass=(1, 0.3)), 2.0)  # ... nor under FILLER_MIN_PASS (320x240)
    assert not filler_pays(PassCosts(warm=[(1, 0.25)]), 20.0)  # 320x240 G-PT: fine-grained already
    assert filler_pays(PassCosts(warm=[(1, 2.5)]), 20.0)  # 1280x720 G-PT: a pass is 12 % of the budget
    assert not filler_pays(PassCosts(warm=[(1, 2.5)]), 600.0)  # ... but 0.4 % of ten minutes
    assert filler_pays(PassCosts(warm=[(1, FILLER_MIN_PASS)]), 1.0)
    costs = PassCosts(warm=[(1, 2.5)])
    assert not filler_warmup_fits(100.0, 0.0, costs)  # no compiling pass measured: no bound
    costs.first(1, 4.0)
    assert filler_warmup_fits(10.0, 1.0, costs)
    assert not filler_warmup_fits(5.0, 1.0, costs)  # 4 s x the margin does not fit in 4 s


def _simulate_filled(seconds: float, per: float, filler_per: float, *, filler: bool, jitter: float = 0.0,
                     seed: int = 0) -> tuple[float, int, int]:
    """A budgeted render of a coarse plan (``per`` s per sample) against a fake clock, the way render_planned runs
    it: the plan's compiling pass, then its passes, a filler kind (``filler_per``) warmed up after the first warm
    pass where it pays, and the gap filled with it (``filler``), then the write. Returns (elapsed, plan's samples,
    filler's samples)."""
    rng = random.Random(seed)
    clock = FakeClock()
    deadline = Deadline(seconds, spent=0.5, clock=clock)
    plan, extra = PassCosts(), PassCosts()
    write, done = 0.8, {"plan": 0, "filler": 0}

    def take(costs: PassCosts, name: str, spp: int, rate: float, compile_s: float = 0.0) -> None:
        took = (0.1 + rate * spp) * (1.0 + rng.uniform(-jitter, jitter))
        clock.now += took + compile_s
        (costs.first if compile_s else costs.record)(spp, took + compile_s)
        done[name] += spp

    take(plan, "plan", 1, per, compile_s=1.5)
    fill_with_filler(deadline, plan, lambda n: take(plan, "plan", n, per), extra if filler else None,
                     lambda n: take(extra, "filler", n, filler_per, 0.0 if extra.first_pass else 0.3),
                     lambda: write, 10_000)
    clock.now += write
    return deadline.elapsed(), done["plan"], done["filler"]


@pytest.mark.parametrize("seconds", [12.0, 20.0, 25.0, 40.0, 60.0])
def test_a_cheaper_filler_closes_the_gap_a_coarse_plan_leaves(seconds: float) -> None:
    """At 1280x720 a G-PT pass is ~2.5 s per sample and a primal one ~0.6 s: the plan alone stops up to a pass
    short of T; with the filler the frame ends within 6 % of T, never after it, and the plan keeps its samples."""
    alone, plan_alone, _ = _simulate_filled(seconds, 2.5, 0.6, filler=False)
    filled, plan_filled, extra = _simulate_filled(seconds, 2.5, 0.6, filler=True)
    assert 0.94 * seconds <= filled <= seconds
    assert filled > alone and extra >= 1
    assert plan_filled >= plan_alone - 1  # the warm-up pass takes at most one plan pass's time


@pytest.mark.parametrize("seconds", [8.0, 10.0, 15.0])
def test_a_filler_too_costly_to_warm_up_safely_is_left_out(seconds: float) -> None:
    """Where the gap cannot surely hold the filler's compiling pass (bounded by the plan's own), nothing changes."""
    alone = _simulate_filled(seconds, 2.5, 0.6, filler=False)
    filled = _simulate_filled(seconds, 2.5, 0.6, filler=True)
    assert filled[0] <= seconds and filled[0] >= alone[0] and filled[1] >= alone[1] - 1


@pytest.mark.parametrize("seed", range(6))
def test_a_filled_frame_on_a_noisy_machine_never_ends_after_the_budget(seed: int) -> None:
    elapsed, _, _ = _simulate_filled(20.0, 2.5, 0.6, filler=True, jitter=0.1, seed=seed)
    assert 0.9 * 20.0 <= elapsed <= 20.0


def test_no_filler_for_fine_passes() -> None:
    _, _, extra = _simulate_filled(20.0, 0.05, 0.02, filler=True)
    assert extra == 0
