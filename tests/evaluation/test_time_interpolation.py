"""Equal-time rows that no spp can bring within ±5 % of their budget (one sample costs more than 5 % of it):
the search keeps both tries around the budget, the run caches both outputs, and every metric of the row is
interpolated to the budget in log time (errors in log value); the report counts such a row as at its budget,
marks it and says between what it was interpolated."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gradsep.evaluation.config import EvalConfig, SceneEntry
from gradsep.evaluation.convergence import _smallest_ranked
from gradsep.evaluation.methods import BracketOutput, MethodOutput, evaluated_methods
from gradsep.evaluation.references import ReferencePair
from gradsep.evaluation.report_time import time_interpolations, time_misses
from gradsep.evaluation.results import SceneRun, row_seconds
from gradsep.evaluation.run import _Runner
from gradsep.evaluation.scores import image_scores, interpolated_scores
from gradsep.evaluation.timesearch import TimeSearch, interpolate_at


def _granular(spp: int) -> tuple[int, float, float]:
    """1 spp: 1.1 s, 2 spp: 2.1 s (render 80 %, post 20 %); the output is the spp."""
    seconds = 0.1 + 1.0 * spp
    return spp, 0.8 * seconds, 0.2 * seconds


def test_a_granular_search_keeps_both_tries_around_the_budget() -> None:
    got = TimeSearch(1.6, 1.0, 10_000).run(_granular, first_spp=1)
    assert got.miss > 0.05 and "granularity" in got.note
    assert got.bracket is not None
    low, high = got.bracket
    assert (low.spp, high.spp) == (1, 2) and (low.output, high.output) == (1, 2)
    assert low.seconds == pytest.approx(1.1) and high.seconds == pytest.approx(2.1)
    assert low.seconds < 1.6 < high.seconds


def test_a_search_within_the_tolerance_or_without_a_bracket_keeps_none() -> None:
    within = TimeSearch(5.0, 0.01, 10_000).run(lambda spp: (spp, 0.01 * spp, 0.0), first_spp=500)
    assert within.note == "" and within.bracket is None
    over = TimeSearch(1.0, 0.01, 10_000).run(lambda spp: (spp, 2.0 + 0.01 * spp, 0.0), first_spp=50)
    assert "1 spp alone" in over.note and over.bracket is None  # every try is too slow: nothing to interpolate


def test_interpolation_is_exact_for_an_error_falling_as_a_power_of_time() -> None:
    def error(t: float) -> float:
        return 0.3 * t ** -1.4

    for target in (1.2, 1.5, 1.99):
        got = interpolate_at(target, (1.0, error(1.0)), (2.0, error(2.0)), log_value=True)
        assert got == pytest.approx(error(target), rel=1e-12)
    # linear in log time for a metric that is not an error (SSIM, PSNR)
    assert interpolate_at(math.sqrt(2.0), (1.0, 0.5), (2.0, 0.7), log_value=False) == pytest.approx(0.6)
    # an unbiased error estimate may be <= 0 for a near-perfect image: no log of it, linear instead
    assert interpolate_at(1.5, (1.0, -1e-6), (2.0, 1e-6), log_value=True) == pytest.approx(
        -1e-6 + 2e-6 * math.log(1.5) / math.log(2.0))


def _pair(rng: np.random.Generator, truth: dict[str, np.ndarray]) -> ReferencePair:
    noisy = {k: {n: v + rng.normal(0, 0.01, v.shape).astype(np.float32) for n, v in truth.items()} for k in "ab"}
    return ReferencePair(1024, noisy["a"], noisy["b"], tag="t", seconds=1.0)


def _truth(rng: np.random.Generator) -> dict[str, np.ndarray]:
    direct = rng.uniform(0.2, 1.0, (12, 16, 3)).astype(np.float32)
    indirect = rng.uniform(0.1, 0.5, (12, 16, 3)).astype(np.float32)
    return {"total": direct + indirect, "direct": direct, "indirect": indirect}


def _noisy(truth: dict[str, np.ndarray], sigma: float, rng: np.random.Generator, spp: int, render: float,
           post: float) -> BracketOutput:
    layers = {n: truth[n] + rng.normal(0, sigma, truth[n].shape).astype(np.float32) for n in ("direct", "indirect")}
    return BracketOutput(spp, render, post, layers["direct"] + layers["indirect"], layers)


def test_interpolated_scores_lie_between_the_tries_and_say_so() -> None:
    rng = np.random.default_rng(0)
    truth = _truth(rng)
    pair = _pair(rng, truth)
    low, high = _noisy(truth, 0.2, rng, 3, 0.8, 0.1), _noisy(truth, 0.1, rng, 4, 1.1, 0.1)
    scores = interpolated_scores(1.0, [low, high], pair)
    sides = [image_scores(b.image, b.layers, pair) for b in (low, high)]
    for name in ("relmse", "relmse_direct", "relmse_indirect", "ssim", "psnr", "flip"):
        lo, hi = sorted((sides[0][name], sides[1][name]))
        assert lo <= scores[name] <= hi, name
    w = math.log(1.0 / 0.9) / math.log(1.2 / 0.9)  # the budget's place between the tries in log time
    assert scores["relmse"] == pytest.approx(sides[0]["relmse"] ** (1 - w) * sides[1]["relmse"] ** w)
    assert "3 spp (0.9 s" in scores["time_interpolated"] and "4 spp (1.2 s" in scores["time_interpolated"]


def _runner(tmp_path) -> _Runner:
    config = EvalConfig(scenes=("procedural:1",), spp=(1,), width=16, height=12, ref_spp=16,
                        output=tmp_path / "report", cache_dir=tmp_path / "cache", models_dir=tmp_path / "models",
                        methods=("path",), seed=3)
    return _Runner(config, False, lambda message: None)


def test_a_bracketed_row_is_cached_with_both_tries_and_scored_at_its_budget(tmp_path, monkeypatch) -> None:
    import gradsep.evaluation.run as run

    rng = np.random.default_rng(1)
    truth = _truth(rng)
    pair = _pair(rng, truth)
    low, high = _noisy(truth, 0.2, rng, 3, 0.8, 0.1), _noisy(truth, 0.1, rng, 4, 1.1, 0.1)
    calls = []

    def fake_run(spec, ctx) -> MethodOutput:
        calls.append(spec.name)
        return MethodOutput(high.image, dict(high.layers), 1.1, 0.1, 4,
                            extra={"target_seconds": 1.0, "time_note": "spp granularity: ..."}, bracket=[low, high])

    monkeypatch.setattr(run, "run_method", fake_run)
    runner = _runner(tmp_path)
    spec = next(m for m in evaluated_methods() if m.name == "path")
    scene = SceneRun(SceneEntry("procedural:1", "procedural-1", {}), 16, 12, 2, ("direct", "indirect"),
                     np.zeros((12, 16, 3), np.float32))
    first = runner.output(spec, scene, 1, None, {"k": 1})
    again = runner.output(spec, scene, 1, None, {"k": 1})
    assert calls == ["path"]  # the second came from the cache, with its bracket
    assert [b.spp for b in again.bracket] == [3, 4]
    for b, original in zip(again.bracket, (low, high), strict=True):
        assert np.array_equal(b.image, original.image) and b.total_seconds == pytest.approx(original.total_seconds)
        assert np.array_equal(b.layers["indirect"], original.layers["indirect"])
    assert again.row["time_bracket"] == [{"spp": 3, "total_seconds": pytest.approx(0.9)},
                                         {"spp": 4, "total_seconds": pytest.approx(1.2)}]
    scores = runner.score(again, scene, pair)
    expected = interpolated_scores(1.0, [low, high], pair)
    assert scores["relmse"] == pytest.approx(expected["relmse"])
    assert scores["time_interpolated"] == expected["time_interpolated"]
    assert scores["relmse"] != pytest.approx(image_scores(high.image, high.layers, pair)["relmse"])
    # the floor criterion ranks the same interpolated figure the report shows
    assert _smallest_ranked([first], pair) == pytest.approx(scores["relmse"])


def test_the_report_counts_an_interpolated_row_at_its_budget() -> None:
    rows = [{"scene": "s", "spp": 1, "method": "gpt-oidn-l1", "method_spp": 4, "total_seconds": 1.2,
             "target_seconds": 1.0, "attempts": 3, "time_note": "spp granularity: 3 spp takes 0.9 s, 4 spp 1.2 s",
             "time_interpolated": "3 spp (0.9 s, RelMSE 0.002) and 4 spp (1.2 s, RelMSE 0.0015)",
             "time_bracket": [{"spp": 3, "total_seconds": 0.9}, {"spp": 4, "total_seconds": 1.2}]},
            {"scene": "s", "spp": 1, "method": "path", "method_spp": 9, "total_seconds": 0.72, "target_seconds": 1.0,
             "attempts": 5, "time_note": "timing noise"}]
    assert len(time_misses(rows)) == 1 and "path" in time_misses(rows)[0]  # the other is not a miss
    (said,) = time_interpolations(rows)
    assert "gpt-oidn-l1" in said and "3 spp (0.9 s" in said and "granularity" in said
    assert row_seconds(rows[0]) == 1.0 and row_seconds(rows[1]) == 0.72
