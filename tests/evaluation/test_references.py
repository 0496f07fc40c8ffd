"""The reference-noise removal: the product estimator against a known truth, the floor, the spp schedule."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.evaluation.references import next_reference_spp
from gradsep.model.metrics import RELMSE_EPSILON, reference_floor, relmse, relmse_unbiased

NOISE, ERROR = 0.03, 0.02  # relative: a floor of ~9e-4 against an error of ~4e-4


def _truth(seed: int = 0):
    """A known truth t and an image x = t + a known relative error."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0.2, 2.0, (160, 160, 3))
    return truth, truth * (1 + ERROR * rng.standard_normal(truth.shape))


def _references(truth: np.ndarray, seed: int):
    """Two independent noisy references of ``truth`` (relative Gaussian noise)."""
    rng = np.random.default_rng(1000 + seed)
    return (truth * (1 + NOISE * rng.standard_normal(truth.shape)),
            truth * (1 + NOISE * rng.standard_normal(truth.shape)))


def _known(image: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean((image - truth) ** 2 / (truth**2 + RELMSE_EPSILON)))


def test_product_estimator_recovers_the_error_against_the_truth():
    """Reference noise larger than the image's error: one reference overstates RelMSE about 3×; the product
    estimator over two independent references matches the squared error against the known truth."""
    truth, image = _truth()
    r1, r2 = _references(truth, 0)
    known = _known(image, truth)
    assert relmse(image, r1) > 2.5 * known  # the bias the estimator removes
    assert relmse_unbiased(image, r1, r2) == pytest.approx(known, rel=0.05)
    # a perfect image scores ~0 instead of the floor
    assert abs(relmse_unbiased(truth, r1, r2)) < 0.05 * relmse(truth, r1)


def test_product_estimator_is_unbiased_over_many_reference_draws():
    """Averaged over independent reference pairs the estimate converges to the known error (within 2 %; the
    normaliser r̄² leaves a relative bias of about 1.5 × floor × (1 + floor / error), ~0.4 % here), while the
    one-reference RelMSE converges to error + floor; the floor estimate matches the references' known noise."""
    truth, image = _truth()
    known = _known(image, truth)
    true_floor = float(np.mean(NOISE**2 * truth**2 / (truth**2 + RELMSE_EPSILON)))
    estimates, naive, floors = [], [], []
    for seed in range(10):
        r1, r2 = _references(truth, seed)
        estimates.append(relmse_unbiased(image, r1, r2))
        naive.append(relmse(image, r1))
        floors.append(reference_floor(r1, r2))
    assert np.mean(estimates) == pytest.approx(known, rel=0.02)
    assert np.mean(naive) == pytest.approx(known + true_floor, rel=0.05)
    assert np.mean(floors) == pytest.approx(true_floor, rel=0.05)


def test_correlated_references_do_not_remove_the_noise():
    """The estimator needs independent references: with r2 = r1 it is the plain one-reference RelMSE (up to
    its normaliser), which the test above shows to be biased -- so the independence is what does the work."""
    truth, image = _truth()
    r1, _ = _references(truth, 3)
    assert relmse_unbiased(image, r1, r1) == pytest.approx(relmse(image, r1), rel=1e-9)
    assert reference_floor(r1, r1) == 0.0


def test_estimators_reject_mismatched_or_nonfinite_input():
    truth, image = _truth()
    r1, r2 = _references(truth, 4)
    with pytest.raises(ValueError, match="shape"):
        relmse_unbiased(image, r1[:10], r2)
    r2[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        relmse_unbiased(image, r1, r2)


def test_reference_spp_schedule():
    assert next_reference_spp(512, floor=1e-5, smallest=1e-3, fraction=0.1, cap=4096) is None  # 1 % : enough
    assert next_reference_spp(512, floor=2e-4, smallest=1e-3, fraction=0.1, cap=4096) == 1024  # 20 % -> ×2
    assert next_reference_spp(512, floor=5e-4, smallest=1e-3, fraction=0.1, cap=4096) == 4096  # 50 % -> ×8
    assert next_reference_spp(512, floor=5e-3, smallest=1e-3, fraction=0.1, cap=4096) == 4096  # capped
    assert next_reference_spp(4096, floor=5e-3, smallest=1e-3, fraction=0.1, cap=4096) is None  # at the cap
    assert next_reference_spp(512, floor=1e-5, smallest=-1e-6, fraction=0.1, cap=2048) == 2048  # unresolved


def test_reference_spp_schedule_in_whole_passes():
    """With the pass spp as step: the smallest whole number of passes covering 1.25x the 1/spp prediction."""
    # 2048 spp at a floor 10.7x the target (cbox-like): 21.9k predicted, 27.4k with the margin -> 54 passes of 512
    assert next_reference_spp(2048, floor=8.0e-4, smallest=7.5e-4, fraction=0.1, cap=65536, step=512) == 27648
    assert next_reference_spp(512, floor=1.1e-4, smallest=1e-3, fraction=0.1, cap=4096, step=512) == 1024  # +1 pass
    assert next_reference_spp(512, floor=5e-3, smallest=1e-3, fraction=0.1, cap=4096, step=512) == 4096  # capped
    assert next_reference_spp(512, floor=1e-5, smallest=1e-3, fraction=0.1, cap=4096, step=512) is None
    assert next_reference_spp(512, floor=1e-5, smallest=0.0, fraction=0.1, cap=2048, step=512) == 2048


def test_reference_time_budget_limits_the_raise():
    from gradsep.evaluation.references import within_time

    # 512 spp took 20 s for both references: 4096 would add 140 s of new rendering
    assert within_time(512, 4096, seconds=20.0, budget=240.0) == 4096
    assert within_time(512, 4096, seconds=20.0, budget=100.0) == 2048  # 60 s more fits, 140 s does not
    assert within_time(512, 4096, seconds=200.0, budget=100.0) is None  # not even a doubling fits
    assert within_time(512, 1024, seconds=float("nan"), budget=1.0) == 1024  # no timing: the cap decides
    # in whole passes (10 s each, two per step): 100 s buy 10 new passes, so 3072 spp
    assert within_time(512, 4096, seconds=20.0, budget=100.0, step=512) == 3072
    assert within_time(512, 4096, seconds=20.0, budget=15.0, step=512) is None  # 1024 would add 20 s


def test_reference_time_budget_counts_only_passes_not_yet_cached():
    from gradsep.evaluation.references import within_time

    cached = 6  # passes 0..5 are in the cache (a farm's shards or an earlier run): 1536 spp each is free
    to_render = lambda spp: max(0, 2 * spp // 512 - cached)  # noqa: E731
    assert within_time(512, 4096, seconds=20.0, budget=0.5, step=512, to_render=to_render) == 1536
    assert within_time(512, 4096, seconds=20.0, budget=20.0, step=512, to_render=to_render) == 2048
    assert within_time(512, 1024, seconds=20.0, budget=0.5, step=512, to_render=lambda spp: 0) == 1024
    assert within_time(512, 4096, seconds=20.0, budget=0.5, step=512, to_render=lambda spp: 2) is None




def test_reference_source_counts_the_passes_still_to_render(tmp_path):
    """The budget's input: a pass in the cache (written by this or an earlier run, or a farm shard) is not new."""
    from gradsep.evaluation.cache import EvalCache
    from gradsep.evaluation.references import ReferenceSource
    from gradsep.renderer.reference import Reference

    rendered: list[int] = []

    def render_pass(spp: int, seed: int) -> Reference:
        rendered.append(seed)
        image = np.full((2, 3, 3), 0.5, np.float32)
        return Reference(image, image.copy(), None, {"gradsep.render_seconds": "1.0"})

    key = {"scene": "toy", "size": [3, 2], "seed": 0}

    def source() -> ReferenceSource:
        return ReferenceSource(EvalCache(tmp_path), "toy", key, 4, render_pass, lambda message: None)

    first = source()
    assert first.passes_to_render(8) == 4 and not first.cached(0)
    first.pair(4)  # passes 0 and 1
    assert len(rendered) == 2 and first.passes_to_render(4) == 0 and first.passes_to_render(8) == 2
    again = source()  # a later run on the same cache: the files count as cached
    assert again.cached(1) and not again.cached(2) and again.passes_to_render(12) == 4
    again.pair(4)
    assert len(rendered) == 2  # nothing re-rendered
