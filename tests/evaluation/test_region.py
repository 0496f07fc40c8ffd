"""Region passes (evaluation/region.py): where the rectangle goes, how its passes join the references, and that
the references stay unbiased and independent (the product estimator's premise)."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.evaluation.region import DESIGN_REDUCTION, Region, choose_region, pilot_floor_map
from gradsep.model.metrics import reference_floor, relmse, relmse_unbiased


def test_choose_region_covers_a_hot_spot_tile_aligned():
    floor = np.full((96, 128), 1e-4)
    floor[40:60, 70:100] = 1.0  # nearly all of the floor in one spot
    region = choose_region(floor, tile=16)
    assert region.x % 16 == 0 and region.y % 16 == 0
    rows, cols = region.slices
    assert floor[rows, cols].sum() > (1 - 1 / DESIGN_REDUCTION) * floor.sum()  # can deliver its design reduction
    assert region.fraction(128, 96) < 0.25  # and is not the whole frame
    big = choose_region(floor, tile=16, reduction=100.0)  # a larger reduction needs (nearly) all of the spot
    assert floor[big.slices].sum() > 0.99 * floor.sum() and big.fraction(128, 96) < 0.25


def test_choose_region_is_the_whole_frame_when_the_floor_is_even_or_absent():
    assert choose_region(np.full((40, 50), 0.3)) == Region(0, 0, 50, 40)
    assert choose_region(np.zeros((7, 9))) == Region(0, 0, 9, 7)
    assert choose_region(np.full((7, 9), np.nan)) == Region(0, 0, 9, 7)


def test_choose_region_on_odd_sizes_stays_inside_the_frame():
    rng = np.random.default_rng(3)
    for h, w in [(1, 1), (23, 37), (17, 16), (5, 300)]:
        floor = rng.random((h, w)) ** 8
        region = choose_region(floor, tile=16)
        assert region.width >= 1 and region.height >= 1
        assert region.x + region.width <= w and region.y + region.height <= h


def test_choose_region_minimises_the_extra_samples():
    """Against brute force over every tile-aligned rectangle: cost = area × D / (S - D)."""
    rng = np.random.default_rng(0)
    floor = rng.random((5 * 4, 6 * 4)) ** 6
    region = choose_region(floor, tile=4, reduction=2.0)
    total = floor.sum()
    need = total / 2

    def cost(y0, y1, x0, x1):
        share = floor[y0:y1, x0:x1].sum()
        return (y1 - y0) * (x1 - x0) * need / (share - need) if share > need else np.inf

    best = min(cost(4 * a, 4 * b, 4 * c, 4 * d) for a in range(5) for b in range(a + 1, 6)
               for c in range(6) for d in range(c + 1, 7))
    rows, cols = region.slices
    assert cost(rows.start, rows.stop, cols.start, cols.stop) == pytest.approx(best)


def test_choose_region_refuses_a_reduction_that_is_not_one():
    with pytest.raises(ValueError, match="reduction"):
        choose_region(np.ones((4, 4)), reduction=1.0)


def test_pilot_floor_map_is_the_floor_of_one_pass():
    """Two passes: the map's mean is model.metrics.reference_floor of the pair (one definition of the floor)."""
    rng = np.random.default_rng(1)
    a, b = rng.random((6, 5, 3)), rng.random((6, 5, 3))
    assert pilot_floor_map([a, b]).shape == (6, 5)
    mean = 0.5 * (a + b)
    expected = np.mean(((a - b) ** 2 / (mean * mean + 0.01)).mean(axis=-1)) / 2
    assert pilot_floor_map([a, b]).mean() == pytest.approx(expected)
    assert pilot_floor_map([a, b]).mean() == pytest.approx(reference_floor(a, b))
    with pytest.raises(ValueError, match="at least 2"):
        pilot_floor_map([a])


# ----------------------------------------------------------------------------------------------------------
# ReferenceSource with region passes, on toy renderers (no Mitsuba)
# ----------------------------------------------------------------------------------------------------------

H, W = 32, 48
HOT = (slice(8, 24), slice(16, 32))  # where the toy scene's variance lives


def _toy_source(tmp_path, truth, noise_in_hot=3.0, noise=0.05, log=None):
    """A ReferenceSource whose passes are ``truth`` + noise (heavy inside HOT), deterministic per seed."""
    from gradsep.evaluation.cache import EvalCache
    from gradsep.evaluation.references import ReferenceSource
    from gradsep.renderer.reference import Reference

    calls = {"pass": [], "region": []}
    scale = np.full((H, W, 1), noise)
    scale[HOT] = noise_in_hot

    def draw(seed, shape_slices=None):
        rng = np.random.default_rng(seed)
        sigma = scale if shape_slices is None else scale[shape_slices]
        base = truth if shape_slices is None else truth[shape_slices]
        # a positive, skewed estimator with mean `base` (like radiance: rare large samples)
        sample = base * rng.gamma(1.0 / sigma**2, sigma**2, size=base.shape)
        return sample.astype(np.float32)

    def render_pass(spp, seed):
        calls["pass"].append(seed)
        image = draw(seed)
        return Reference(image, (0.5 * image).astype(np.float32), None, {"gradsep.render_seconds": "1.0"})

    def render_region(region, spp, seed):
        calls["region"].append((region, seed))
        image = draw(seed, region.slices)
        return Reference(image, (0.5 * image).astype(np.float32), None, {"gradsep.render_seconds": "0.25"})

    key = {"scene": "toy", "size": [W, H], "seed": 0, "code": "test"}
    source = ReferenceSource(EvalCache(tmp_path), "toy", key, 4, render_pass, log or (lambda m: None),
                             render_region)
    return source, calls


def test_region_passes_join_the_references_pixel_by_pixel(tmp_path):
    truth = np.full((H, W, 3), 0.5)
    source, calls = _toy_source(tmp_path, truth)
    region = source.region()  # placed from the 8 pilot passes
    assert len(calls["pass"]) == 8
    rows, cols = region.slices
    assert rows.start <= 8 and rows.stop >= 24 and cols.start <= 16 and cols.stop >= 32  # covers the hot spot
    assert region.fraction(W, H) < 0.5

    plain = source.pair(8)
    more = source.pair(8, region_passes=3)
    assert len(calls["region"]) == 6 and all(r == region for r, _ in calls["region"])
    assert more.region == region and more.region_spp == 12 and plain.region is None
    assert more.tag != plain.tag and more.seconds == pytest.approx(plain.seconds + 6 * 0.25)
    # outside the rectangle nothing changed; inside, the mean of 2 full + 3 region passes per reference
    outside = np.ones((H, W), bool)
    outside[rows, cols] = False
    assert np.array_equal(more.first["total"][outside], plain.first["total"][outside])
    full = [source._pass(i)[0]["total"] for i in (0, 2)]
    extra = [source._pass(i, "region")[0]["total"] for i in (0, 2, 4)]
    samples = [f[rows, cols] for f in full] + extra
    expected = sum(x.astype(np.float64) for x in samples) / 5
    np.testing.assert_allclose(more.first["total"][rows, cols], expected, rtol=1e-6)
    # the layers follow the same samples: direct is half of total here, indirect the rest
    np.testing.assert_allclose(more.first["direct"], 0.5 * more.first["total"], rtol=1e-6)
    # and the floor splits exactly into outside + inside
    outside_part, inside_part = more.floor_split(region)
    assert outside_part + inside_part == pytest.approx(more.floor())
    assert inside_part < plain.floor_split(region)[1]


def test_pilot_and_region_passes_have_their_own_seeds_and_cache(tmp_path):
    truth = np.full((H, W, 3), 0.5)
    source, calls = _toy_source(tmp_path, truth)
    source.pair(8, region_passes=2)
    full_seeds = [s for s in calls["pass"]]
    region_seeds = [s for _, s in calls["region"]]
    assert len(set(full_seeds) | set(region_seeds)) == len(full_seeds) + len(region_seeds)  # all distinct
    again, calls2 = _toy_source(tmp_path, truth)  # a later run on the same cache
    assert again.pilot_passes_to_render() == 0  # the pilot is cached: placing the region costs nothing
    again.pair(8, region_passes=2)
    assert calls2 == {"pass": [], "region": []}  # ... every pilot, full and region pass came from the cache
    assert again.region_cached(3) == [True, True, True, True, False, False]
    with pytest.raises(ValueError, match="pilot"):
        again.ensure(0, "region")


def test_region_references_keep_the_product_estimator_unbiased(tmp_path):
    """Over independent toy runs (fresh seeds each), the mean of relmse_unbiased with region passes matches the
    method's true RelMSE against the truth, while one-reference RelMSE is biased upwards by the floor."""
    rng = np.random.default_rng(5)
    truth = 0.2 + rng.random((H, W, 3))
    method = truth * (1 + 0.05 * rng.standard_normal(truth.shape))
    true_error = relmse(method, truth)
    unbiased, naive = [], []
    for run in range(24):
        # moderate noise: the estimator normalises by the references' own mean, so it is exact only while
        # that mean is close to the truth (with 2 passes at 0.4 it reads 1.56x too high, region passes or not)
        source, _ = _toy_source(tmp_path / f"run{run}", truth, noise_in_hot=0.12)
        source.key["seed"] = run
        pair = source.pair(8, region_passes=4)
        unbiased.append(relmse_unbiased(method, pair.first["total"], pair.second["total"]))
        naive.append(relmse(method, pair.first["total"]))
    spread = np.std(unbiased) / np.sqrt(len(unbiased))
    assert abs(np.mean(unbiased) - true_error) < 4 * spread + 0.02 * true_error
    assert np.mean(naive) > true_error + 4 * spread  # the floor a one-reference figure would carry


@pytest.mark.render
def test_render_region_matches_the_full_frame_in_expectation():
    """A crop of Mitsuba's film renders the same pixel estimator as the full frame (box filter): same means
    within the noise, and the exact direct <= total split."""
    from gradsep.evaluation.region import render_region
    from gradsep.renderer.reference import DEFAULT_SAMPLER, render_loaded
    from gradsep.renderer.scene import load_scene

    loaded = load_scene("procedural:90001", width=24, height=16, max_depth=4)
    full = render_loaded(loaded, spp=256, seed=1, tile_spp=None, sampler=DEFAULT_SAMPLER).images()
    region = Region(8, 4, 10, 7)
    crop = render_region(loaded, region, spp=256, seed=2, sampler=DEFAULT_SAMPLER)
    assert crop.metadata["gradsep.kind"] == "reference-region" and crop.metadata["gradsep.region"] == "8,4,10,7"
    images = crop.images()
    assert images["total"].shape == (7, 10, 3)
    expected = full["total"][region.slices].astype(np.float64)
    assert np.all(images["direct"] <= images["total"] + 1e-5)
    ratio = images["total"].astype(np.float64).mean() / expected.mean()
    assert 0.9 < ratio < 1.1
    with pytest.raises(ValueError, match="not inside"):
        render_region(loaded, Region(20, 0, 10, 4), spp=4, seed=0, sampler=DEFAULT_SAMPLER)


# ----------------------------------------------------------------------------------------------------------
# The evaluation's use: region passes after the full passes stop (evaluation/convergence.py)
# ----------------------------------------------------------------------------------------------------------

def _converge(tmp_path, monkeypatch, smallest, cap=64, ref_seconds=None):
    """evaluation.convergence.converge_references on the toy source, the smallest ranked RelMSE fixed."""
    from types import SimpleNamespace

    import gradsep.evaluation.convergence as convergence
    from gradsep.evaluation.config import EvalConfig, resolve_scenes
    from gradsep.evaluation.results import SceneRun

    monkeypatch.setattr(convergence, "_smallest_ranked", lambda outputs, pair: smallest)
    config = EvalConfig(scenes=("procedural:1",), spp=(1,), width=W, height=H, ref_spp=4, output=tmp_path / "r",
                        cache_dir=tmp_path, models_dir=tmp_path / "m", methods=("gpt-primal",), seed=0,
                        max_depth=None, alpha=0.2, table_spp=None, quick=False, ref_spp_cap=cap,
                        ref_seconds=ref_seconds)
    messages: list[str] = []
    source, calls = _toy_source(tmp_path / "cache", np.full((H, W, 3), 0.5), noise_in_hot=0.5, log=messages.append)
    scene = SceneRun(resolve_scenes(["procedural:1"])[0][0], W, H, 8, ("direct", "indirect"),
                     np.zeros((H, W, 3), np.float32))
    pair = convergence.converge_references(SimpleNamespace(config=config, log=messages.append), scene, source, [])
    return scene, pair, calls, messages


def test_region_passes_are_added_once_the_full_passes_hit_the_cap(tmp_path, monkeypatch):
    # At the cap the floor is ~0.0027, over the 0.002 asked; 96 % of it is inside the region.
    scene, pair, calls, messages = _converge(tmp_path, monkeypatch, smallest=0.02)
    assert scene.reference_spp == 64 and len(calls["pass"]) == 2 * 16 + 8  # full passes to the cap, the pilot
    assert pair.region is not None and scene.reference_region == pair.region.as_list()
    count = scene.region_spp // 4
    assert 1 <= count <= 16 and len(calls["region"]) == 2 * count
    assert not scene.capped and scene.floor["total"] <= 0.1 * 0.02
    assert any("more each there" in m for m in messages)


def test_region_passes_stop_at_the_cap_and_say_why(tmp_path, monkeypatch):
    scene, pair, calls, _ = _converge(tmp_path, monkeypatch, smallest=1e-9)  # out of reach
    assert scene.capped and scene.region_spp == 64 and len(calls["region"]) == 2 * 16
    assert scene.cap_reason.startswith("the spp cap (64 spp each); region passes at their cap")


def test_region_passes_respect_the_time_budget(tmp_path, monkeypatch):
    # 1 s per full pass recorded; a budget too small for the pilot's 8 passes renders no region pass
    scene, pair, calls, _ = _converge(tmp_path, monkeypatch, smallest=1e-9, cap=64, ref_seconds=5.0)
    assert calls["region"] == [] and pair.region is None and scene.capped
    assert "pilot does not fit the time budget" in scene.cap_reason


def test_a_fixed_reference_spp_gets_no_region_passes(tmp_path, monkeypatch):
    scene, pair, calls, _ = _converge(tmp_path, monkeypatch, smallest=1e-9, cap=4)
    assert calls["region"] == [] and len(calls["pass"]) == 2 and scene.region_spp == 0 and scene.capped
