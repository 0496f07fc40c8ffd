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


def fake_pass(rng: np.random.Generator, spp: int, gradients: bool) -> dict[str, np.ndarray]:
    sums = {"direct.base": rng.random((4, 5, 3)) * spp, "direct.sq": rng.random((4, 5, 1)) * spp,
            "albedo": rng.random((4, 5, 3)) * spp}
    if gradients:
        sums["direct.grad0"] = rng.standard_normal((4, 5, 3)) * spp
    return sums


def deal(split: Split, plan: str, sums: dict[str, np.ndarray], spp: int) -> None:
    """One pass's sums to ``split``, its gradient sums apart (as renderer.passes.Passes.run deals them)."""
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
