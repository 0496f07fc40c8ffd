"""A planned frame's budget (renderer/frame_budget.py) against a fake clock and stand-in passes: the start-up check,
what is kept free after the last pass, the write measured again near the end, and the samples the rest buys; and
the write's prediction on bands of a frame."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from gradsep.model.errors import CommandError
from gradsep.model.frame import Frame, Layer
from gradsep.renderer import frame_budget
from gradsep.renderer.budget import Deadline
from gradsep.renderer.frame_budget import FINAL_PASSES, PILOT_SHARE, FrameBudget, exit_seconds, write_seconds
from gradsep.renderer.plans import plan_named


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def bound(budget: FrameBudget, monkeypatch: pytest.MonkeyPatch, write: float = 0.5) -> SimpleNamespace:
    """``budget`` bound to stand-in passes whose frame takes ``write`` seconds to write; the passes record how
    often the write was measured."""
    passes = SimpleNamespace(index=0, spp=0, loaded=SimpleNamespace(width=8, height=6), measured=0)

    def measured(band, width, height):  # noqa: ANN001, ANN202
        passes.measured += 1
        return write

    monkeypatch.setattr(frame_budget, "write_seconds", measured)
    budget.bind(passes)  # type: ignore[arg-type]
    return passes


def test_a_budget_is_a_deadline_or_a_sample_count():
    with pytest.raises(ValueError):
        FrameBudget()
    with pytest.raises(ValueError):
        FrameBudget(Deadline(1.0), spp=4)
    assert FrameBudget(spp=4).seconds is None and FrameBudget(Deadline(3.0)).seconds == 3.0
    assert FrameBudget(spp=4).checkpoint_allowance() == float("inf")
    assert FrameBudget(Deadline(3.0)).checkpoint_allowance() == pytest.approx(PILOT_SHARE * 3.0)


def test_a_sample_count_buys_itself_and_keeps_no_deadline(monkeypatch):
    budget = FrameBudget(spp=64)
    passes = bound(budget, monkeypatch)
    budget.after_first_pass(plan_named("primal"))
    assert passes.measured == 0 and budget.buys(SimpleNamespace(per_sample=1.0, pass_seconds=1.0)) == 64.0


def test_the_first_pass_measures_the_write_and_refuses_a_budget_it_cannot_keep(monkeypatch):
    clock = Clock()
    budget = FrameBudget(Deadline(2.0, clock=clock))
    passes = bound(budget, monkeypatch, write=0.5)
    clock.now = 1.0
    budget.after_first_pass(plan_named("primal"))  # 1 s left: the write and the exit fit
    assert passes.measured == 1 and budget.reserve() == pytest.approx(0.5 + exit_seconds())
    clock.now = 0.0
    budget = FrameBudget(Deadline(2.0, clock=clock))
    bound(budget, monkeypatch, write=0.5)
    clock.now = 1.6  # 0.4 s left: the write alone does not fit
    with pytest.raises(CommandError, match="below this machine's start-up cost"):
        budget.after_first_pass(plan_named("primal"))


def test_a_callers_tail_replaces_the_write_and_the_exit_and_the_check_is_held_back(monkeypatch):
    budget = FrameBudget(Deadline(2.0, clock=Clock(), tail=0.3))
    passes = bound(budget, monkeypatch)
    budget.after_first_pass(plan_named("primal"))
    assert passes.measured == 0 and budget.reserve() == pytest.approx(0.3)  # an in-process caller writes nothing
    budget.held = 0.2
    assert budget.reserve() == pytest.approx(0.5)


def test_the_write_is_measured_once_more_near_the_end_on_the_chosen_plans_frame(monkeypatch):
    clock = Clock()
    budget = FrameBudget(Deadline(10.0, clock=clock))
    passes = bound(budget, monkeypatch, write=0.5)
    budget.after_first_pass(plan_named("direct-alternate"))
    passes.index = 3
    clock.now = 8.0  # 2 s left, below five writes, but the plan is not chosen yet
    budget.reserve()
    assert passes.measured == 1
    budget.written.append(plan_named("primal"))  # the plan is chosen
    clock.now = 7.0  # 3 s left: not yet
    budget.reserve()
    assert passes.measured == 1
    clock.now = 8.0
    budget.reserve()
    budget.reserve()
    assert passes.measured == 2  # once only


def test_the_rest_of_a_deadline_buys_samples_at_a_plans_marginal_cost(monkeypatch):
    clock = Clock()
    budget = FrameBudget(Deadline(10.0, clock=clock, tail=1.0))
    passes = bound(budget, monkeypatch)
    passes.spp = 20
    clock.now = 4.0
    plan = SimpleNamespace(per_sample=0.01, pass_seconds=0.05)
    assert budget.buys(plan) == pytest.approx(20 + (6.0 - 1.0 - FINAL_PASSES * 0.05) / 0.01)
    clock.now = 9.5  # nothing left: the samples so far
    assert budget.buys(plan) == 20


def test_the_write_is_timed_on_bands_that_use_every_thread_of_openexrs_pool():
    """ZIP encodes blocks of 16 rows, one per thread: a band of one block would time one core of a parallel write."""
    import OpenEXR

    rng = np.random.default_rng(0)
    frame = Frame(layers={"color": Layer(base=rng.random((200, 40, 3), dtype=np.float32))})
    asked: list[int] = []

    def band(window: tuple[slice, slice]) -> Frame:
        rows = window[0]
        asked.append(rows.stop - rows.start)
        return Frame(layers={"color": Layer(base=frame.layers["color"].base[rows])})

    before = OpenEXR.global_thread_count()
    try:
        for threads, rows in ((0, 16), (1, 16), (2, 32), (4, 64)):
            OpenEXR.set_global_thread_count(threads)
            asked.clear()
            assert write_seconds(band, 40, 200) > 0
            assert asked[1:] == [rows] * 3  # after the one-row warm-up
    finally:
        OpenEXR.set_global_thread_count(before)
