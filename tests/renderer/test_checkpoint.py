"""The ``auto`` checkpoint (renderer/checkpoint.py) with fakes: no Mitsuba, no render, no reconstruction library;
and once on a real render.

A fake Passes renders a known image plus Gaussian noise, deals its passes into a real renderer.check.Split and
charges a fake clock; a fake reconstruction returns the truth off by a known relative error per candidate (a frame
with gradients is the fallback's, a plain one primal's), so the right choice at the budget is known."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from gradsep.model.frame import Frame, Layer
from gradsep.model.header_keys import PREDICTED_RELMSE_KEY
from gradsep.renderer import plans, reconstruction_cost
from gradsep.renderer.budget import PassCosts
from gradsep.renderer.check import CHECK_MARGIN, Split
from gradsep.renderer.checkpoint import (
    CHECKPOINT_LAST_PASSES,
    CHECKPOINT_SHARE,
    TOO_SMALL,
    block_means,
    run_checkpoint,
    tiles,
)
from gradsep.renderer.passes import Priors
from gradsep.renderer.plans import FALLBACK
from tests.renderer.scenes import resolve

SIDE = 48
TRUTH = 0.5 + np.random.default_rng(0).random((SIDE, SIDE, 3))
#: seconds per sample of each plan (G-PT traces offset paths: dearer than primal) and per pass
PER_SAMPLE = {"primal": 1e-3, "direct-alternate": 2e-3}
PER_PASS = 0.01


class FakePasses:
    def __init__(self, seed: int = 1) -> None:
        self.now = 0.0
        self.clock = lambda: self.now
        self.layers = ("direct", "indirect")
        self.loaded = SimpleNamespace(width=SIDE, height=SIDE)
        self.max_spp = 64
        self.spp = self.index = 0
        self.rng = np.random.default_rng(seed)
        self.kinds: dict[str, SimpleNamespace] = {}
        self.runs: list[tuple[str, int]] = []
        self.slow: dict[int, float] = {}  # pass index -> how much slower than its cost it runs (a busy moment)
        self.priors = None  # renderer.passes.Priors: none, like a fresh process
        self.split: Split | None = None
        self.bases: dict[str, np.ndarray] = {}
        self.gradients: dict[str, tuple[dict[str, np.ndarray], int]] = {}

    def kind(self, c):
        return self.kinds.setdefault(c.name, SimpleNamespace(costs=PassCosts(), settings=c.name))

    def run(self, c, spp: int) -> dict[str, np.ndarray]:
        costs = self.kind(c).costs
        seconds = (PER_PASS + PER_SAMPLE[c.name] * spp) * self.slow.get(self.index, 1.0)
        (costs.first if costs.first_pass is None else costs.record)(spp, seconds)
        self.now += seconds
        bases = {"direct.base": spp * TRUTH + self.rng.normal(0.0, 0.3 * math.sqrt(spp), TRUTH.shape)}
        grads = {"direct.dx.grad": np.zeros_like(TRUTH)} if c.gradients != "none" else {}
        self.bases = {k: v + self.bases.get(k, 0.0) for k, v in bases.items()}
        if grads:
            have, n = self.gradients.get(c.name, ({}, 0))
            self.gradients[c.name] = ({k: v + have.get(k, 0.0) for k, v in grads.items()}, n + spp)
        if self.split is not None:
            self.split.add(c.name, bases, grads, spp)
        self.spp += spp
        self.index += 1
        self.runs.append((c.name, spp))
        return {**bases, **grads}

    def start_split(self) -> None:
        if self.split is None:
            self.split = Split()
            self.split.add_lump(self.bases, self.gradients, self.spp, self.index)

    def halves(self, c):
        grads, k = self.gradients.get(c.name, ({}, 0))
        q = self.split
        if q is None or not q.ready(c.name, c.gradients != "none", k):
            return None
        out = []
        for i, (sums, n, _, _) in enumerate(q.halves(c.name, self.bases, grads, self.spp, k)):
            base = sums["direct.base"] / n
            layer = Layer(base, np.zeros_like(base), np.zeros_like(base)) if grads else Layer(base)
            out.append((Frame(layers={"direct": layer}), n, q.batches(i)))
        return out


def fake_reconstruction(errors: dict[str, float]):
    """The fallback's frame (with gradients) comes back as ``TRUTH * (1 + errors[FALLBACK])``, a plain one with
    ``errors["primal"]``: RelMSE about ``e^2`` at any samples (the checkpoint carries it with the prior law)."""
    def reconstruct(frame: Frame):
        e = errors[FALLBACK if frame.layers["direct"].has_gradients else "primal"]
        return TRUTH[: frame.height, : frame.width] * (1 + e), "fake"
    return reconstruct


class FakeBudget:
    """The frame's budget as the checkpoint sees it (renderer.frame_budget.FrameBudget's interface): ``seconds``
    or ``spp``, the allowance for the checkpoint's own cost, and the samples the rest buys a plan (here, the whole
    ``seconds`` at its measured per-sample cost)."""

    def __init__(self, seconds: float | None = None, spp: int | None = None, allowance: float = math.inf) -> None:
        self.seconds, self.spp, self.allowance = seconds, spp, allowance
        self.first: list[str] = []

    def checkpoint_allowance(self) -> float:
        return self.allowance

    def after_first_pass(self, plan) -> None:
        self.first.append(plan.name)

    def buys(self, a) -> float:
        return float(self.spp) if self.seconds is None else self.seconds / a.per_sample


def budget(seconds: float, allowance: float = math.inf) -> FakeBudget:
    return FakeBudget(seconds, allowance=allowance)


@pytest.mark.parametrize(("errors", "chosen"), [
    ({FALLBACK: 0.1, "primal": 0.3}, FALLBACK),  # primal's 2x samples cannot make up 9x the error
    ({FALLBACK: 0.2, "primal": 0.1}, "primal"),  # lower error and cheaper
    ({FALLBACK: 0.1, "primal": 0.1}, "primal"),  # equal error at equal samples: primal buys twice as many
    ({FALLBACK: 0.1, "primal": 0.1 * 2 ** 0.25}, FALLBACK),  # primal's samples exactly make up its error: a tie
])
def test_the_checkpoint_chooses_by_the_error_each_plan_reaches_at_the_budget(errors, chosen):
    passes = FakePasses()
    result = run_checkpoint(passes, budget(10.0), reconstruct=fake_reconstruction(errors))
    assert result.chosen.name == chosen
    by_name = {a.name: a for a in result.assessments}
    assert set(by_name) == {FALLBACK, "primal"}
    mean = 1 + sum(errors.values()) / 2  # the weights come from the two reconstructions' mean image
    for name, a in by_name.items():
        relmse = (errors[name] / mean) ** 2
        assert a.measured_relmse == pytest.approx(relmse, rel=0.02)
        assert a.per_sample == pytest.approx(PER_SAMPLE[name], rel=1e-6)  # the cost line reads the fixed cost apart
        assert a.pass_seconds == pytest.approx(PER_PASS, rel=1e-6)
        assert a.predicted_relmse == pytest.approx(relmse * (a.pilot_spp / a.budget_spp) ** 0.5, rel=0.02)
    assert "checkpoint at" in result.note and result.trace["chosen"] == chosen
    assert {e["name"] for e in result.trace["plans"]} == {FALLBACK, "primal"} and len(result.trace["difference"]) == 2


def test_the_checkpoint_keeps_to_its_share_and_every_pass_stays_in_the_frame():
    passes = FakePasses()
    passes.max_spp = 4096
    result = run_checkpoint(passes, budget(20.0), reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.1}))
    assert passes.now <= CHECKPOINT_SHARE * 20.0
    assert passes.spp == sum(n for _, n in passes.runs) and result.pilot_seconds == pytest.approx(passes.now)
    assert [name for name, _ in passes.runs[:7]] == [FALLBACK, "primal", FALLBACK, "primal", FALLBACK, "primal",
                                                     FALLBACK]
    n = passes.runs[3][1]
    assert n > 1 and [k for _, k in passes.runs[3:7]] == [n, n, 2 * n, 2 * n]  # two sizes of each: the cost lines
    # then the rest of the share in CHECKPOINT_LAST_PASSES passes of the fallback, a smaller and a larger in turn
    # (its cost line stays readable): the share is used, not spent on many small passes' fixed costs
    last = passes.runs[7:]
    assert len(last) == CHECKPOINT_LAST_PASSES and {name for name, _ in last} == {FALLBACK}
    sizes = [k for _, k in last]
    assert all(a < b for a, b in zip(sizes[::2], sizes[1::2], strict=True))  # a smaller and a larger in turn
    assert passes.now >= 0.95 * CHECKPOINT_SHARE * 20.0
    # where a pass's lanes cannot hold them (max_spp), more passes, in pairs
    passes = FakePasses()
    run_checkpoint(passes, budget(20.0), reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.1}))
    last = passes.runs[7:]
    assert len(last) > CHECKPOINT_LAST_PASSES and len(last) % 2 == 0 and max(k for _, k in last) <= passes.max_spp


def test_a_busy_moment_during_the_small_passes_does_not_stretch_the_checkpoint():
    """The passes that give the cost lines run 3x slow (the machine busy, e.g. with the reconstruction's start-up):
    a line through them is nearly flat, and passes sized from its slope would overrun the share many times."""
    passes = FakePasses()
    passes.max_spp = 4096
    passes.slow = {i: 3.0 for i in range(2, 6)}  # the warm 1-spp pass, n and 2n of primal, n of the fallback
    run_checkpoint(passes, budget(20.0), reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.1}))
    assert passes.now <= 1.05 * CHECKPOINT_SHARE * 20.0


def test_with_spp_the_checkpoint_takes_its_share_of_the_samples():
    passes = FakePasses()
    run_checkpoint(passes, FakeBudget(spp=1000), reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.2}))
    assert passes.spp <= CHECKPOINT_SHARE * 1000


def test_a_budget_too_small_for_the_checkpoint_renders_one_pass_and_judges_nothing():
    passes = FakePasses()
    small = budget(0.05, allowance=0.005)
    result = run_checkpoint(passes, small, reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.1}))
    assert result.chosen.name == FALLBACK and result.assessments == []
    assert passes.runs == [(FALLBACK, 1)] and passes.split is None
    assert result.note == TOO_SMALL and small.first == [FALLBACK]  # the start-up check ran after its one pass


def known_costs(name: str) -> PassCosts:
    """A warm cost line of ``name``'s passes, as an earlier render in the process measured it (Priors)."""
    costs = PassCosts(first_pass=(1, 0.5))
    for spp in (8, 16):
        costs.record(spp, PER_PASS + PER_SAMPLE[name] * spp)
    return costs


def test_with_both_plans_known_warm_a_budget_too_small_spends_no_probing_pass(monkeypatch):
    """Priors (both kernels warm, the reconstruction's rate measured): whether the checkpoint fits is known before
    any pass, so the deadline's first pass is sized from the cost line instead of being a 1-spp probe."""
    monkeypatch.setattr(reconstruction_cost, "reconstruct_startup", lambda: 0.0)  # paid already: a warm process
    passes = FakePasses()
    passes.priors = Priors({name: known_costs(name) for name in PER_SAMPLE}, reconstruct_rate=1e-6)
    pixels = SIDE * SIDE
    work = 4 * pixels * 1e-6 * CHECK_MARGIN  # four reconstructions at the measured rate, with the margin
    result = run_checkpoint(passes, budget(1.0, allowance=0.9 * work),
                            reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.1}))
    assert result.note == TOO_SMALL and passes.runs == []
    # where that work fits, the measured rate (not the prior CHECK_PRIOR_RATE) and no primal compile are charged
    assert 4 * pixels * reconstruction_cost.CHECK_PRIOR_RATE > 1.2 * work
    passes = FakePasses()
    passes.priors = Priors({name: known_costs(name) for name in PER_SAMPLE}, reconstruct_rate=1e-6)
    result = run_checkpoint(passes, budget(20.0, allowance=1.1 * work + PER_PASS + 2e-3),
                            reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.1}))
    assert result.assessments and passes.runs[0] == (FALLBACK, 1)
    # without priors the same share gives up: the prior rate is dearer
    passes = FakePasses()
    result = run_checkpoint(passes, budget(20.0, allowance=1.1 * work + PER_PASS + 2e-3),
                            reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.1}))
    assert not result.assessments and passes.runs == [(FALLBACK, 1)]


def test_an_unseparated_frame_checks_all_against_primal():
    passes = FakePasses()
    passes.layers = ("color",)
    PER_SAMPLE["all"] = 3e-3
    try:
        def reconstruct(frame: Frame):
            e = 0.1 if frame.layers["direct"].has_gradients else 0.3
            return TRUTH * (1 + e), "fake"
        result = run_checkpoint(passes, budget(10.0), reconstruct=reconstruct)
    finally:
        del PER_SAMPLE["all"]
    assert result.chosen.name == "all" and {a.name for a in result.assessments} == {"all", "primal"}


def test_block_means_average_squares_and_keep_small_arrays_whole():
    t = np.arange(16 * 24 * 3, dtype=np.float64).reshape(16, 24, 3)
    b = block_means(t, 8)
    assert b.shape == (6,) and b.mean() == pytest.approx(t.mean())
    assert block_means(np.ones((5, 5, 3)), 8).tolist() == [1.0]
    assert block_means(np.ones((17, 9)), 8).shape == (2,)  # the ragged edge left out


def test_metadata_of_a_checkpoint_plan_names_the_candidates_and_the_prediction():
    passes = FakePasses()
    result = run_checkpoint(passes, budget(10.0), reconstruct=fake_reconstruction({FALLBACK: 0.1, "primal": 0.3}))
    meta = result.metadata(("direct", "indirect"))
    assert meta[plans.PLAN_KEY] == FALLBACK and meta[plans.PLAN_LAYERS_KEY] == "direct=alternate,indirect=none"
    assert set(dict(p.split("=") for p in meta[plans.CANDIDATES_KEY].split(","))) == {FALLBACK, "primal"}
    assert float(meta[PREDICTED_RELMSE_KEY]) == pytest.approx(result.assessment().predicted_relmse, rel=1e-5)


def test_tiles_cover_small_frames_whole_and_spread_over_large_ones():
    assert tiles(64, 48) == [(slice(0, 48), slice(0, 64))]
    windows = tiles(1280, 720)
    assert len(windows) == 4
    for ys, xs in windows:
        assert ys.stop - ys.start == 128 and xs.stop - xs.start == 128
        assert 0 <= ys.start and ys.stop <= 720 and 0 <= xs.start and xs.stop <= 1280
    assert len({(w[0].start, w[1].start) for w in windows}) == 4


@pytest.mark.render
def test_the_checkpoint_judges_the_plans_on_the_frames_own_halves():
    """A stand-in reconstruction: a frame with gradients comes back as the truth (a 512-spp render), a plain one
    20 % too dark. At equal samples (--spp) the checkpoint must keep the plan with gradients, and the difference of
    its two reference-free estimates must be the true difference: the halves' groups are common to both
    reconstructions, so their noise cancels (each estimate alone carries it, see its standard error)."""
    pytest.importorskip("mitsuba")
    from gradsep.model.metrics import relmse
    from gradsep.renderer.frame_budget import FrameBudget
    from gradsep.renderer.passes import Passes
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    scene = load_scene(str(resolve("cbox")), width=48, height=36, max_depth=5)
    truth = render_frame(scene, spp=512, seed=99, gradients="none").combined().base

    def fake(frame: Frame) -> tuple[np.ndarray, str]:
        return (truth if frame.layers["direct"].has_gradients else 0.8 * truth), "fake"

    passes = Passes(scene, ("direct", "indirect"), seed=3)
    frame_budget = FrameBudget(spp=1024)
    frame_budget.bind(passes)
    judgement = run_checkpoint(passes, frame_budget, reconstruct=fake)
    assert judgement.chosen.name == FALLBACK
    by_name = {a.name: a for a in judgement.assessments}
    assert set(by_name) == {"primal", FALLBACK} and by_name[FALLBACK].budget_spp == 1024
    mean = 0.9  # the estimate's weights come from the two reconstructions' mean image
    true_difference = relmse(0.8 * truth / mean, truth / mean)
    difference = by_name["primal"].measured_relmse - by_name[FALLBACK].measured_relmse
    assert difference == pytest.approx(true_difference, rel=0.3)  # the groups' noise cancels in the difference
    assert all(math.isfinite(a.predicted_relmse) and a.predicted_relmse >= 0 for a in judgement.assessments)
    assert passes.spp <= CHECKPOINT_SHARE * 1024 and passes.split is not None
    meta = judgement.metadata(("direct", "indirect"))
    assert meta[plans.PLAN_KEY] == FALLBACK and float(meta[PREDICTED_RELMSE_KEY]) == pytest.approx(
        by_name[FALLBACK].predicted_relmse, rel=1e-5)
