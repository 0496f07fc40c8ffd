"""The frame's own error estimate (renderer/check.py): passes dealt into groups, the two halves of a frame, and
the estimate itself on images whose error is known. The estimate's accuracy on rendered frames against
references is benchmarks/bench_planner.py's ``predict``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gradsep.model.metrics import RELMSE_EPSILON
from gradsep.renderer.check import CHECK_MARGIN, GROUPS, Split, check_frame, check_seconds
from gradsep.renderer.estimate import at_budget
from tests.renderer.scenes import resolve


def fake_pass(rng: np.random.Generator, spp: int, gradients: bool) -> dict[str, np.ndarray]:
    sums = {"direct.base": rng.random((4, 5, 3)) * spp, "direct.sq": rng.random((4, 5, 1)) * spp,
            "albedo": rng.random((4, 5, 3)) * spp}
    if gradients:
        sums["direct.grad0"] = rng.standard_normal((4, 5, 3)) * spp
    return sums


def deal(split: Split, plan: str, sums: dict[str, np.ndarray], spp: int) -> None:
    """One pass's sums to ``split``, its gradient sums apart (as renderer.plan.Passes.run deals them)."""
    split.add(plan, {k: v for k, v in sums.items() if ".grad" not in k},
              {k: v for k, v in sums.items() if ".grad" in k}, spp)


def test_passes_go_to_the_smaller_half_and_its_emptiest_group_and_the_halves_add_up_to_the_frame():
    rng = np.random.default_rng(1)
    q = Split()
    sizes = [1, 1, 8, 8, 8, 8, 32, 32, 7, 3, 16, 16, 2]
    # primal passes (False) fill the bases only
    kinds = [False, True, True, False, True, True, True, True, True, False, True, True, False]
    total: dict[str, np.ndarray] = {}
    grads: dict[str, np.ndarray] = {}
    gradient_spp = 0
    for spp, g in zip(sizes, kinds, strict=True):
        before = list(q.spp)
        sums = fake_pass(rng, spp, g)
        kept = {k: v.copy() for k, v in sums.items()}
        deal(q, "direct", sums, spp)
        assert all(np.array_equal(sums[k], kept[k]) for k in sums)  # the pass's own arrays are never written
        h = GROUPS // 2
        first = 0 if sum(before[:h]) <= sum(before[h:]) else h
        target = first + int(np.argmin(before[first:first + h]))
        assert q.spp[target] == before[target] + spp
        assert abs(sum(q.spp[:h]) - sum(q.spp[h:])) <= max(sizes)  # the halves within one pass of each other
        for k, v in sums.items():
            (grads if ".grad" in k else total)[k] = (grads if ".grad" in k else total).get(k, 0.0) + v
        gradient_spp += spp if g else 0
    assert sum(q.spp) == sum(sizes) and sum(q.passes) == len(sizes)
    big = Split()  # a frame that ends in two large passes: one to each half
    for spp in (1, 1, 1, 1, 2, 2, 2, 2, 100, 100):
        deal(big, "primal", fake_pass(rng, spp, False), spp)
    assert sum(big.spp[:h]) == sum(big.spp[h:]) == 106
    assert q.ready("direct", True, gradient_spp)
    (a, na, pa, ga), (b, nb, pb, gb) = q.halves("direct", total, grads, sum(sizes), gradient_spp)
    assert na + nb == sum(sizes) and pa + pb == len(sizes) and ga + gb == gradient_spp and ga > 0 and gb > 0
    for k in total:
        np.testing.assert_allclose(a[k] + b[k], total[k], rtol=1e-12)
    np.testing.assert_allclose(a["direct.grad0"] + b["direct.grad0"], grads["direct.grad0"], rtol=1e-12)
    h = GROUPS // 2
    for half, others in ((0, range(h, GROUPS)), (1, range(h))):  # judged against the other half's groups only
        assert [n for _, n in q.batches(half)] == [q.spp[i] for i in others]


def test_a_half_without_samples_or_gradients_is_not_ready():
    rng = np.random.default_rng(2)
    q = Split()
    for _ in range(3):  # equal passes alternate between the halves: A, B, A
        deal(q, "direct", fake_pass(rng, 4, True), 4)
    assert not q.ready("direct", True, 12)  # half B has one group with samples
    deal(q, "primal", fake_pass(rng, 4, False), 4)
    assert q.ready("primal", False, 0)
    assert q.ready("direct", True, 12)
    q2 = Split()
    for i in range(GROUPS):  # only half B's passes (every second one) traced gradients
        deal(q2, "direct", fake_pass(rng, 4, i % 2 == 1), 4)
    assert sum(q2.spp[:GROUPS // 2]) == sum(q2.spp[GROUPS // 2:])
    assert not q2.ready("direct", True, 4 * GROUPS // 2)


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e5])
def test_the_estimate_finds_a_known_error_at_any_scale(scale):
    """Quarters of truth + noise; a 'reconstruction' 10 % too bright: the estimate is the reconstruction's
    RelMSE-weighted error (w = 1 / (R^2 + eps)), carried from each half's samples."""
    rng = np.random.default_rng(3)
    truth = (0.5 + rng.random((96, 96, 3))) * scale
    q = Split()
    for _ in range(GROUPS):
        noisy = truth + rng.standard_normal(truth.shape) * 0.05 * truth
        deal(q, "primal", {"direct.base": noisy * 16, "direct.sq": np.zeros((96, 96, 1))}, 16)
    halves = [(object(), 64, q.batches(0)), (object(), 64, q.batches(1))]
    result = check_frame(halves, 128, 0.5, lambda frame: 1.1 * truth)
    expected = float(np.mean((0.1 * truth) ** 2 / ((1.1 * truth) ** 2 + RELMSE_EPSILON)))
    for n, value, se in result.options[""].halves:
        assert n == 64 and value == pytest.approx(expected, rel=0.1) and se < 0.1 * expected
    assert result.relmse == pytest.approx(np.mean([at_budget(v, 64, 128, 0.5) for _, v, _ in
                                                   result.options[""].halves]))
    assert result.relmse == pytest.approx(expected * 0.5 ** 0.5, rel=0.1)
    meta = json.loads(result.metadata()["gradsep.frame_check"])
    assert [h[0] for h in meta["halves"]] == [64, 64] and meta["exponent"] == 0.5


def test_an_exact_reconstruction_counts_as_the_estimates_noise_never_below_zero():
    rng = np.random.default_rng(4)
    truth = 0.5 + rng.random((64, 64, 3))
    q = Split()
    for _ in range(GROUPS):
        deal(q, "primal", {"direct.base": (truth + 0.1 * rng.standard_normal(truth.shape)) * 4,
                         "direct.sq": np.zeros((64, 64, 1))}, 4)
    n = 2 * GROUPS
    result = check_frame([(None, n, q.batches(0)), (None, n, q.batches(1))], 2 * n, 0.5, lambda frame: truth)
    assert result.relmse > 0 and all(result.relmse <= 3 * se for _, _, se in result.options[""].halves)


def noisy_halves(rng: np.random.Generator, truth: np.ndarray, noise: float, spp: int = 4) -> list:
    q = Split()
    for _ in range(GROUPS):
        sample = truth * (1 + noise * rng.standard_normal(truth.shape))
        deal(q, "primal", {"direct.base": sample * spp, "direct.sq": np.zeros(truth.shape[:2] + (1,))}, spp)
    n = spp * GROUPS // 2
    return [(None, n, q.batches(0)), (None, n, q.batches(1))]


def test_the_better_reconstruction_is_chosen_by_a_paired_difference_free_of_the_groups_noise():
    """Two reconstructions 10 % and 3 % too bright, judged against groups whose noise (50 % per sample) is far
    above either error: their paired difference is far less noisy than either estimate, and the better one is
    chosen whichever is listed first; two equal ones keep the first."""
    rng = np.random.default_rng(5)
    truth = 0.5 + rng.random((64, 64, 3))
    halves = noisy_halves(rng, truth, 0.5)
    worse, better = (lambda frame: 1.10 * truth), (lambda frame: 1.03 * truth)
    result = check_frame(halves, 32, 0.5, {"raw-fast": worse, "prefiltered-high": better})
    assert result.chosen == "prefiltered-high"
    difference, se = result.differences["prefiltered-high"]
    expected = float(np.mean(((0.03 * truth) ** 2 - (0.10 * truth) ** 2) / ((1.065 * truth) ** 2 + RELMSE_EPSILON)))
    assert difference == pytest.approx(expected, rel=0.1) and difference < -10 * se
    assert result.relmse == result.options["prefiltered-high"].relmse
    alone = min(s for _, _, s in result.options["raw-fast"].halves)
    assert se < 0.25 * alone  # the groups' noise products cancel in the difference
    assert check_frame(halves, 32, 0.5, {"a": better, "b": worse}).chosen == "a"
    assert check_frame(halves, 32, 0.5, {"a": better, "b": better}).chosen == "a"
    meta = json.loads(result.metadata()["gradsep.frame_check"])
    assert meta["chosen"] == "prefiltered-high" and set(meta["options"]) == {"raw-fast", "prefiltered-high"}
    assert meta["halves"] == meta["options"]["prefiltered-high"]  # the served setting's figures


def test_the_check_time_is_two_reconstructions_with_a_margin():
    assert check_seconds(1e-6, 1000) == pytest.approx(2 * CHECK_MARGIN * 1e-3)
    assert check_seconds(1e-6, 1000, 1e-6) == pytest.approx(2 * 2 * CHECK_MARGIN * 1e-3)
    assert check_seconds(-1.0, 1000) == 0.0


def halves_of_the_frame(passes, chosen) -> list:  # noqa: ANN001
    """``passes``' halves, checked to make its frame: their samples add up to its samples, and their bases,
    weighted by samples, are its bases."""
    halves = passes.halves(chosen)
    assert halves is not None and sum(n for _, n, _ in halves) == passes.spp
    frame = passes.frame_result(chosen)
    for layer in ("direct", "indirect"):
        mixed = sum(n * h.layers[layer].base.astype(np.float64) for h, n, _ in halves) / passes.spp
        np.testing.assert_allclose(mixed, frame.layers[layer]["base"], rtol=1e-4, atol=1e-6)
    return halves


@pytest.mark.render
def test_rendered_halves_are_the_frame_split_in_two():
    """A split render's two halves: their samples make the frame's, and their bases, weighted by samples, are the
    frame's bases; each half's gradients average only that half's gradient passes."""
    from gradsep.renderer.plan import Passes, candidate
    from gradsep.renderer.scene import load_scene

    scene = load_scene(str(resolve("cbox")), width=16, height=12)
    passes = Passes(scene, ("direct", "indirect"), seed=5)
    passes.start_split()  # from the first pass: no lump
    for c, n in (("direct-alternate", 1), ("primal", 1), ("direct-alternate", 4), ("direct-alternate", 4),
                 ("primal", 3), ("direct-alternate", 2), ("direct-alternate", 2), ("primal", 1),
                 ("direct-alternate", 3), ("direct-alternate", 1)):
        passes.run(candidate(c), n)
    chosen = candidate("direct-alternate")
    halves = halves_of_the_frame(passes, chosen)
    assert passes.spp == 22
    assert all(h.layers["direct"].has_gradients and not h.layers["indirect"].has_gradients for h, _, _ in halves)
    assert Passes(scene, ("direct", "indirect"), seed=5).halves(chosen) is None  # not split: no halves
    # a split started after some passes (a pilot's): those passes are one lump in half A
    late = Passes(scene, ("direct", "indirect"), seed=6)
    for c, n in (("primal", 1), ("direct-alternate", 1), ("direct-alternate", 4), ("direct", 4)):
        late.run(candidate(c), n)
    late.start_split()
    assert late.split is not None and late.split.spp[0] == 10 and late.split.passes[0] == 4
    for n in (4, 4, 3, 3, 2, 2, 2, 1):
        late.run(chosen, n)
    halves_of_the_frame(late, chosen)
    assert late.spp == 31


@pytest.mark.render
@pytest.mark.slow
@pytest.mark.parametrize(("gradients", "operator_setting"),
                         [("none", None), ("none", "prefiltered-high"), ("auto", None)])
def test_a_budgeted_plain_frame_compares_the_oidn_settings_on_its_halves(monkeypatch, gradients, operator_setting):
    """A plain --seconds frame whose budget affords prefiltered-high has its halves reconstructed with both it and
    the default; the header's setting is the one the comparison chose, and the prediction is that setting's. An
    operator's $GRADSEP_OIDN_SETTING (which wins over the header when serving) leaves nothing to compare, and a
    frame with gradients keeps the rule's setting."""
    from gradsep.model.header_keys import OIDN_SETTING_KEY, PREDICTED_RELMSE_KEY
    from gradsep.model.oidn import METHOD_SETTING, SETTING_ENV
    from gradsep.renderer import plan
    from gradsep.renderer.budget import Deadline
    from gradsep.renderer.render import render_planned_frame
    from gradsep.renderer.scene import load_scene

    monkeypatch.setattr(plan, "reconstruct_startup", lambda: 0.0)  # as if paid: the check fits 8 s
    if operator_setting:
        monkeypatch.setenv(SETTING_ENV, operator_setting)
    else:
        monkeypatch.delenv(SETTING_ENV, raising=False)
    scene = load_scene(str(resolve("cbox")), width=16, height=12, max_depth=5)
    frame, summary = render_planned_frame(scene, deadline=Deadline(8.0), spp=None, seed=4, gradients=gradients)
    meta = frame.metadata
    assert meta["gradsep.predicted_from"] == "frame" and "the frame's halves" in summary
    check = json.loads(meta["gradsep.frame_check"])
    if operator_setting or meta["gradsep.plan"] != "primal":
        assert "options" not in check
        return
    assert set(check["options"]) == {METHOD_SETTING, "prefiltered-high"} and check["chosen"] in check["options"]
    assert (meta.get(OIDN_SETTING_KEY) or METHOD_SETTING) == check["chosen"]
    assert all(len(h) == 2 for h in check["options"].values()) and len(check["differences"]) == 1
    assert float(meta[PREDICTED_RELMSE_KEY]) >= 0 and meta["gradsep.plan_method"] == "oidn"


def test_the_reconstruction_rate_is_timed_on_the_centre_tile_after_a_warm_up():
    from gradsep.model.frame import Frame, Layer
    from gradsep.renderer.plan import reconstruct_rate

    frame = Frame(layers={"direct": Layer(np.ones((100, 130, 3), np.float32))})
    seen = []

    def fake(tile: Frame) -> tuple[np.ndarray, str]:
        seen.append(tile.layers["direct"].base.shape)
        return tile.layers["direct"].base, "oidn"

    rate = reconstruct_rate(frame, fake, side=64)
    assert seen == [(64, 64, 3), (64, 64, 3)] and 0 < rate < 1
    small = Frame(layers={"direct": Layer(np.ones((5, 7, 3), np.float32))})
    seen.clear()
    reconstruct_rate(small, fake, side=64)
    assert seen == [(5, 7, 3), (5, 7, 3)]  # a frame under the tile: the whole frame


def test_without_halves_the_pilots_prediction_is_carried_to_the_samples_the_frame_got():
    """A pilot slowed by a load spike predicts that the budget buys 49 spp and carries its estimate there; the
    frame then renders 543. Its header states the error at 543 spp (error ~ spp^-exponent), not at 49."""
    from gradsep.model.header_keys import PREDICTED_RELMSE_KEY
    from gradsep.renderer.plan import Assessment, Plan, Planned, candidate
    from gradsep.renderer.render import frame_check

    chosen = Assessment("direct-alternate", 1, 0.08, 0.3, "oidn-l1", exponent=0.5, budget_spp=49.0,
                        predicted_relmse=0.012)
    other = Assessment("primal", 1, 0.07, 0.1, "oidn", exponent=0.5, budget_spp=131.0, predicted_relmse=0.007)
    plan = Plan(candidate("direct-alternate"), [chosen, other], pilot_seconds=3.0)
    meta = plan.metadata(("direct", "indirect"))
    planned = Planned(frame=None, candidate=candidate("direct-alternate"), plan=plan,  # type: ignore[arg-type]
                      spp=543, gradient_spp=538, passes=19)
    summary = frame_check(planned, meta)
    assert meta["gradsep.predicted_from"] == "pilot" and "the pilot's" in summary
    assert float(meta[PREDICTED_RELMSE_KEY]) == pytest.approx(at_budget(0.012, 49, 543, 0.5), rel=1e-5)
    assert float(meta[PREDICTED_RELMSE_KEY]) < 0.004
