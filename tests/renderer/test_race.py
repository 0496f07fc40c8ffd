"""The planner's race (renderer/plan.py run_pilot) with fakes: no Mitsuba, no render, no reconstruction library.

A fake Passes renders a known image plus Gaussian noise and charges a fake clock; a fake reconstruction returns
the truth off by a relative error whose law in spp is set per candidate, so the right choice is known."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from gradsep.model.frame import Frame, Layer
from gradsep.renderer import plan
from gradsep.renderer.budget import PassCosts
from gradsep.renderer.plan import Assessment, candidate, eliminate, run_pilot

SIDE = 48
TRUTH = 0.5 + np.random.default_rng(0).random((SIDE, SIDE, 3))
#: seconds per sample of each candidate (G-PT traces offset paths: dearer than primal)
PER_SAMPLE = {"primal": 1e-3, "direct-alternate": 2e-3, "direct": 3e-3}


class FakePasses:
    def __init__(self, seed: int = 1) -> None:
        self.now = 0.0
        self.clock = lambda: self.now
        self.layers = ("direct", "indirect")
        self.loaded = SimpleNamespace(width=SIDE, height=SIDE)
        self.max_spp = 64
        self.spp = 0
        self.rng = np.random.default_rng(seed)
        self.kinds: dict[str, SimpleNamespace] = {}
        self.runs: list[tuple[str, int]] = []

    def kind(self, c):
        return self.kinds.setdefault(c.name, SimpleNamespace(costs=PassCosts(), settings=c.name))

    def run(self, c, spp: int) -> dict[str, np.ndarray]:
        costs = self.kind(c).costs
        seconds = 0.01 + PER_SAMPLE[c.name] * spp
        (costs.first if costs.first_pass is None else costs.record)(spp, seconds)
        self.now += seconds
        self.spp += spp
        self.runs.append((c.name, spp))
        noise = self.rng.normal(0.0, 0.3 * math.sqrt(spp), TRUTH.shape)
        return {"direct.base": spp * TRUTH + noise}


def fake_reconstruction(monkeypatch, laws: dict[str, tuple[float, float]]):
    """Candidate ``c``'s reconstruction of ``n`` samples is ``TRUTH * (1 + e)`` with ``e^2 = a n^-p``
    (``laws[c] = (a, p)``): its RelMSE is about ``e^2``."""
    current: dict[str, object] = {}

    def sums_frame(sums, settings, spp):
        current.update(name=settings, spp=spp)
        return Frame(layers={"direct": Layer(sums["direct.base"] / spp)})

    def reconstruct(frame: Frame):
        a, p = laws[current["name"]]  # type: ignore[index]
        return TRUTH * (1 + math.sqrt(a * current["spp"] ** -p)), "fake"  # type: ignore[operator]

    monkeypatch.setattr(plan, "sums_frame", sums_frame)
    return reconstruct


def test_eliminate_keeps_the_best_and_those_within_the_combined_standard_errors():
    def a(name, value, se):
        x = Assessment(name, 8, value, 1e-3, "fake", se)
        x.predicted_relmse, x.predicted_se = value, se
        return x

    best, close, far = a("direct", 1.0, 0.3), a("direct-alternate", 1.4, 0.3), a("primal", 1.5, 0.3)
    assert [x.name for x in eliminate([far, best, close])] == ["direct", "direct-alternate"]  # 0.5 > hypot 0.42
    assert len(eliminate([a("direct", 1.0, 0.0), a("primal", 1.0, 0.0)])) == 2  # ties stay
    assert [x.name for x in eliminate([a("primal", 2.0, 0.0), a("direct", 1.0, 0.0)])] == ["direct"]


def test_the_race_follows_the_measured_law_and_drops_a_flattening_candidate(monkeypatch):
    """Primal is best at pilot samples but flattens (p = 0.1); ``direct`` falls as 1/n. The one-shot pilot's
    assumed law carried primal's lead ~10x; the race measures each slope between its rounds, drops primal, and
    stops once ``direct`` alone survives (no more pilot passes)."""
    reconstruct = fake_reconstruction(monkeypatch, {"primal": (0.01, 0.1), "direct-alternate": (0.02, 0.5),
                                                    "direct": (0.1, 1.0)})
    passes = FakePasses()
    result = run_pilot(passes, lambda a: 4096.0, pilot_spp=4, race_spp=0.35 * 4096, reconstruct=reconstruct)
    assert result.chosen.name == "direct"
    by_name = {a.name: a for a in result.assessments}
    assert by_name["direct"].exponent == pytest.approx(1.0, abs=0.05) and by_name["primal"].exponent < 0.2
    assert by_name["direct"].predicted_relmse < by_name["primal"].predicted_relmse
    assert result.note == "2 rounds"  # both others dropped after the first slope was read: the race ends
    assert passes.spp == 3 * (1 + 4 + 16) + 4 + 16  # warm-ups, two rounds (4, then 16 spp) of each and of B
    assert all(math.isfinite(a.predicted_relmse) for a in result.assessments)


def test_the_race_stops_at_its_share_when_no_candidate_can_be_told_apart(monkeypatch):
    """Equal laws: nobody is eliminated (their differences are within the estimates' noise), the rounds grow
    until the next would pass the race's share of the frame, and every pass stays in the frame."""
    reconstruct = fake_reconstruction(monkeypatch, {c: (0.01, 0.5) for c in PER_SAMPLE})
    passes = FakePasses()
    passes.max_spp = 16
    result = run_pilot(passes, lambda a: 2000.0, pilot_spp=4, race_spp=700, reconstruct=reconstruct)
    sizes = [n for name, n in passes.runs if name == "direct"]
    assert sizes == [1, 4, 16, 16, 16, 16, 16]  # warm-up, then rounds of 4, 16, 64 in passes of <= 16
    assert passes.spp == 3 + 4 * 84 and {a.pilot_spp for a in result.assessments} == {84}  # 4 x 256 more: > 700
    assert result.note == "3 rounds"


def test_the_race_keeps_to_its_share_of_the_time(monkeypatch):
    reconstruct = fake_reconstruction(monkeypatch, {c: (0.01, 0.5) for c in PER_SAMPLE})
    passes = FakePasses()
    run_pilot(passes, lambda a: 10_000.0, pilot_seconds=0.1, race_seconds=2.0, reconstruct=reconstruct)
    assert passes.now <= 2.0
    assert candidate("direct").name in {name for name, _ in passes.runs}


def test_choose_keeps_the_default_plan_unless_another_is_clearly_better():
    from gradsep.renderer.plan import FALLBACK, choose

    def a(name, value, se):
        x = Assessment(name, 8, value, 1e-3, "fake", se)
        x.predicted_relmse, x.predicted_se = value, se
        return x

    default = a(FALLBACK, 1.0, 0.2)
    assert choose([default, a("primal", 0.9, 0.2)]).name == FALLBACK  # 0.1 lower, within hypot 0.28: noise
    assert choose([default, a("primal", 0.5, 0.2)]).name == "primal"  # 0.5 lower: clearly better
    assert choose([a("primal", 0.9, 0.2), a("direct", 0.95, 0.01)]).name == "primal"  # no default left
    assert choose([a(FALLBACK, 0.5, 0.3), a("primal", 0.9, 0.0)]).name == FALLBACK
