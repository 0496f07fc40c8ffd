"""Outliers stay local: a firefly as renderers make them (one pixel with its gradients, a horizontal pair or a 3x3
block, each with its gradients and a single sample's variance, in both layers) of 1e3, 1e6 or 1e12 times the
frame's mean, and a firefly in a layer's base alone (1e2 to 1e30 times the frame's mean, at a corner, an edge or
the centre), change no more than 0.1 % of the pixels farther than 16 px from it by more than 1 % (relative, with
an epsilon of 1e-3 of the frame's mean), for every denoising method, and every one is counted in the warnings;
the detector (model/outliers.py) leaves ordinary frames and lights in view alone; and the robust statistics.

Frames: the committed example (examples/cbox-16spp.exr) and a procedural scene (tests/data/procedural-4242-16spp.exr,
``gradsep render procedural:4242 --spp 16 --width 96 --height 72 --seed 7``), both 16 spp, direct and indirect layers.
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import gradsep.model.methods as table
import gradsep.model.outliers as outliers
import gradsep.model.reconstruct as reconstruct_module
from gradsep.model.exr_read import read_frame
from gradsep.model.frame import Frame, Layer
from gradsep.model.outliers import SOURCE_LEVEL, find_clusters, split_frame, split_layer
from gradsep.model.robust import (
    FAR_KEPT,
    FAR_RADIUS,
    OUTLIER_SPREAD_RADIUS,
    far_agreement,
    lit_level,
    luminance,
    robust_level,
    winsorised_sum,
)
from gradsep.model.synthetic import CASES, frame_mean, hidden_given_back, places, with_outlier
from tests.model.shipped import models_for

REPO = Path(__file__).resolve().parents[2]
FRAMES = {"cbox": REPO / "examples" / "cbox-16spp.exr",
          "procedural": REPO / "tests" / "data" / "procedural-4242-16spp.exr"}
DENOISERS = ("oidn-l1", "oidn", "fused", "network")
#: The contract (model.robust): beyond NEAR pixels, at least KEPT of the pixels within 1 % of the output without it.
NEAR, KEPT = FAR_RADIUS, FAR_KEPT

_cache: dict[str, Any] = {}


def _frame(name: str) -> Frame:
    if name not in _cache:
        _cache[name] = read_frame(FRAMES[name])
    return _cache[name]


def _reconstruct(frame: Frame, method: str) -> Any:
    return reconstruct_module.reconstruct(frame, method, models=models_for(method))


def _with_firefly(frame: Frame, layer: str, where: tuple[int, int], times: float) -> Frame:
    """``frame`` with ``times`` × the frame's mean added to every channel of one pixel of a layer's base."""
    old = frame.layers[layer]
    base = old.base.copy()
    base[where] += np.float32(min(times * frame_mean(frame), 3e38))
    return Frame({**frame.layers, layer: Layer(base, old.dx, old.dy)}, frame.features)


def _position(frame: Frame, name: str) -> tuple[int, int]:
    return {"corner": (0, 0), "edge": (frame.height // 2, frame.width - 1),
            "centre": (frame.height // 2, frame.width // 2)}[name]


def _check(frame_name: str, method: str, cases: list[tuple[str, str, float]]) -> None:
    frame = _frame(frame_name)
    reference = _reconstruct(frame, method)
    assert not reference.warnings  # an ordinary frame has no outlier: it is denoised as it always was
    for layer, position, times in cases:
        where = _position(frame, position)
        result = _reconstruct(_with_firefly(frame, layer, where, times), method)
        assert np.isfinite(result.image).all()
        kept, reach = far_agreement(result.image, reference.image, where, NEAR)
        assert kept >= KEPT, (f"{method} on {frame_name}: a {times:g}x firefly in the {layer} layer's {position} "
                              f"changed {100 * (1 - kept):.2f} % of the far pixels by > 1 %, up to {reach:.0f} px away")
        assert any("outlier" in w for w in result.warnings)  # handled, and reported


@pytest.mark.parametrize("frame_name", list(FRAMES))
@pytest.mark.parametrize("method", DENOISERS)
def test_a_firefly_changes_nothing_far_from_it(method: str, frame_name: str) -> None:
    _check(frame_name, method, [("direct", "centre", 1e2), ("direct", "edge", 1e6), ("indirect", "corner", 1e30)])


#: Cases (method, frame, case) the detector does not yet hold to the contract: `network` on the example's 3x3 block.
#: Not the network (test_the_network_alone_is_local_its_prior_is_not below) but the Poisson prior it refines: its
#: ten DCT-preconditioned CG steps each spread a change by about 1/alpha px, so the prior of the frame without the
#: outlier depends, on dark pixels up to 60 px away, on the block's clean content, which the outlier erased
#: (docs/decisions.md). Strict: once a prior fixes it, the case fails here until it is taken off this list.
KNOWN_NON_LOCAL = {("network", "cbox", "block")}


def _check_case(frame_name: str, method: str, case: str, times: tuple[float, ...]) -> None:
    frame = _frame(frame_name)
    reference = _reconstruct(frame, method)
    where = (frame.height // 2, frame.width // 2)
    for k in times:
        result = _reconstruct(with_outlier(frame, case, where, k), method)
        assert np.isfinite(result.image).all()
        kept, reach = far_agreement(result.image, reference.image, where, NEAR)
        assert kept >= KEPT, (f"{method} on {frame_name}: a {case} outlier of {k:g}x the mean in both layers "
                              f"changed {100 * (1 - kept):.2f} % of the far pixels by > 1 %, up to {reach:.0f} px away")
        counted = [w for w in result.warnings if w.startswith("layer ")]
        assert {w.split(":")[0] for w in counted} == {"layer direct", "layer indirect"}  # both, counted


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("frame_name", list(FRAMES))
@pytest.mark.parametrize("method", DENOISERS)
def test_an_outlier_as_renderers_make_it_changes_nothing_far_from_it(method: str, frame_name: str,
                                                                     case: str, request) -> None:
    if (method, frame_name, case) in KNOWN_NON_LOCAL:
        request.node.add_marker(pytest.mark.xfail(reason="network's far-reaching prior (KNOWN_NON_LOCAL)",
                                                  strict=True, raises=AssertionError))
    _check_case(frame_name, method, case, (1e3, 1e6, 1e12))


@pytest.mark.parametrize("frame_name", list(FRAMES))
@pytest.mark.parametrize("method", DENOISERS)
def test_the_handling_itself_is_local_wherever_the_outlier_lands(method: str, frame_name: str, monkeypatch) -> None:
    """At each of nine places, every case, with the content the outlier hid given back
    (model.synthetic.hidden_given_back): nothing beyond NEAR px moves. The detection, the fills and the energy's
    footprint are local everywhere; what a method does with the content the outlier hid is its own (off the
    centre, OIDN's and the prior's reach: docs/methods.md#how-far-an-outlier-reaches)."""
    frame = _frame(frame_name)
    reference = _reconstruct(frame, method).image
    own = outliers.split_frame
    for where in places(frame):
        for case in CASES:
            hit = with_outlier(frame, case, where, 1e6)

            def given_back(f: Frame, sources: bool = False, threads: int = 1, hit: Frame = hit) -> Any:
                handled, split = own(f, sources, threads)
                assert f is hit and split.layers  # found, in every layer
                return hidden_given_back(frame, hit, handled), split

            monkeypatch.setattr(outliers, "split_frame", given_back)
            kept, reach = far_agreement(_reconstruct(hit, method).image, reference, where, NEAR)
            assert kept >= KEPT, (f"{method} on {frame_name}: a {case} at {where}, the hidden content given back, "
                                  f"changed {100 * (1 - kept):.2f} % of the far pixels by > 1 %, up to {reach:.0f} px")


def test_the_network_alone_is_local_its_prior_is_not(monkeypatch) -> None:
    """KNOWN_NON_LOCAL's case with the prior farther than NEAR px taken from the frame without the outlier (at the
    exposure the handled layer runs at): then nothing far moves, so the network's own receptive field and exposure
    are local, and the far change is its prior's."""
    import gradsep.model.infer as infer
    from gradsep.model.preprocess import scaled_layer

    frame = _frame("cbox")
    network = models_for("network").get("network")
    where = (frame.height // 2, frame.width // 2)
    handled, split = split_frame(with_outlier(frame, "block", where, 1e3))
    yy, xx = np.mgrid[0:frame.height, 0:frame.width]
    far = (np.hypot(yy - where[0], xx - where[1]) > NEAR)[..., None]
    own_prior = infer.poisson_prior
    reference = sum(network.reconstruct_layer(name, clean, frame.features) for name, clean in frame.layers.items())
    result = np.zeros((frame.height, frame.width, 3))
    for name, clean in frame.layers.items():
        clean_prior = own_prior(scaled_layer(clean, 1.0 / infer.exposure_scale(handled.layers[name])))
        monkeypatch.setattr(infer, "poisson_prior",
                            lambda layer, c=clean_prior, **kw: np.where(far, c, own_prior(layer, **kw)))
        result += split.restore(name, network.reconstruct_layer(name, handled.layers[name], frame.features))
    assert far_agreement(result, reference, where, NEAR)[0] >= KEPT


@pytest.mark.slow
@pytest.mark.parametrize("frame_name", list(FRAMES))
@pytest.mark.parametrize("method", DENOISERS)
def test_a_firefly_changes_nothing_far_from_it_every_position_and_size(method: str, frame_name: str) -> None:
    _check(frame_name, method, [(layer, position, times) for layer in ("direct", "indirect")
                                for position in ("corner", "edge", "centre") for times in (1e2, 1e4, 1e8, 1e30)])


# ------------------------------------------------------------------------------------------- the statistics


def test_the_level_is_the_mean_of_an_ordinary_frame_and_scales_with_it() -> None:
    for layer in _frame("procedural").layers.values():
        level = robust_level(layer.base)
        assert level == pytest.approx(float(layer.base.mean(dtype=np.float64)), rel=0.05)
        for k in (1e-30, 1e-8, 1e9, 1e30):
            assert robust_level(layer.base * np.float32(k)) == pytest.approx(k * level, rel=1e-5)


def test_one_value_moves_the_level_and_a_sum_by_one_capped_value_at_most() -> None:
    rng = np.random.default_rng(0)
    image = rng.random((64, 64, 3)).astype(np.float32)
    flat = image.mean(axis=-1, dtype=np.float64)
    cap = float(np.quantile(flat, 0.999))
    for value in (1e3, 1e30, np.inf, np.nan):
        hit = image.copy()
        hit[5, 7] = value
        assert abs(robust_level(hit) - robust_level(image)) <= 2 * cap / flat.size
        values = flat.copy()
        values[5, 7] = value if np.isfinite(value) else 1e300
        assert abs(winsorised_sum(values) - winsorised_sum(flat)) <= 2 * cap
    assert robust_level(np.zeros((4, 4, 3))) == 0.0 and robust_level(np.zeros((0, 3))) == 0.0
    sparse = np.zeros((100, 100, 3), np.float32)
    sparse[3, 4] = 2.0  # lit in fewer pixels than the quantile leaves: the plain mean of the light
    assert robust_level(sparse) == pytest.approx(2.0 / 1e4)


def test_the_lit_level_is_the_level_of_the_lit_part_and_scales_with_the_image() -> None:
    """A small object on black has the level of the object (OIDN's exposure bins that are black do not count),
    the level scales exactly with the image, and black, empty and non-finite input read as no light."""
    rng = np.random.default_rng(3)
    patch = (0.5 + rng.random((32, 48, 3))).astype(np.float32)
    frame = np.zeros((192, 160, 3), np.float32)
    frame[64:96, 32:80] = patch  # aligned with the 16-pixel bins
    assert lit_level(frame) == pytest.approx(lit_level(patch), rel=1e-12)
    assert robust_level(frame) < 0.06 * lit_level(frame)  # the whole-frame level counts the black
    for k in (1e-30, 1e-8, 1e9, 1e30):
        assert lit_level(frame * np.float32(k)) == pytest.approx(k * lit_level(frame), rel=1e-5)
    odd = rng.random((17, 23, 3)).astype(np.float32)  # bins of unequal size, as OIDN splits an odd frame
    assert lit_level(odd) == pytest.approx(float(luminance(odd).mean()), rel=0.01)
    assert lit_level(np.zeros((4, 4, 3))) == 0.0 and lit_level(np.zeros((0, 0, 3))) == 0.0
    bad = frame.copy()
    bad[0, 0], bad[0, 1] = np.nan, -np.inf
    assert lit_level(bad) == lit_level(frame)
    assert lit_level(np.ones((1, 1, 3))) == pytest.approx(1.0)


def test_one_pixel_moves_the_lit_level_by_little() -> None:
    """A firefly inside the lit part counts as the 99.9th percentile at most; one in the black adds its bin to
    the lit part (diluting the level by that bin's share) and no more."""
    rng = np.random.default_rng(4)
    frame = np.zeros((192, 192, 3), np.float32)
    frame[:96, :96] = rng.random((96, 96, 3))
    level = lit_level(frame)
    for value in (1e3, 1e30, np.inf):
        inside, outside = frame.copy(), frame.copy()
        inside[40, 50] = value
        outside[150, 150] = value
        assert abs(lit_level(inside) - level) < 1e-3 * level
        assert abs(lit_level(outside) - level) < 0.03 * level  # one more 16x16 bin among 36


def _textured(height: int = 21, width: int = 32, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (0.5 + rng.random((height, width, 3))).astype(np.float32)


@pytest.mark.parametrize("times", [1e2, 1e8, 1e30, 3e38])
@pytest.mark.parametrize("where", [(0, 0), (0, 20), (17, 31), (20, 20)])
def test_the_split_replaces_an_outlier_by_its_neighbours_and_keeps_its_energy(where: tuple[int, int],
                                                                             times: float) -> None:
    base = _textured()
    hit = base.copy()
    hit[where] = np.float32(min(times, 3e38))
    split = split_layer(Layer(hit))
    assert split is not None and (split.outliers, split.lights, split.gradients) == (1, 0, 0)
    inlier = split.layer.base
    assert np.array_equal(np.delete(inlier.reshape(-1, 3), where[0] * 32 + where[1], 0),
                          np.delete(base.reshape(-1, 3), where[0] * 32 + where[1], 0))
    assert inlier[where].max() <= base.max() and np.isfinite(inlier).all()
    back = split.restore(inlier)  # the excess spread back, its sum kept, nothing beyond its footprint
    assert back.astype(np.float64).sum() == pytest.approx(hit.astype(np.float64).sum(), rel=1e-5)
    yy, xx = np.mgrid[0:21, 0:32]
    outside = np.maximum(np.abs(yy - where[0]), np.abs(xx - where[1])) > OUTLIER_SPREAD_RADIUS
    assert np.array_equal(back[outside], inlier[outside])


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("variance", ["noise", "agree", "none"])
def test_a_cluster_and_its_gradients_are_replaced_and_its_energy_goes_where_the_variance_says(case: str,
                                                                                           variance: str) -> None:
    """A pixel, a pair or a 3x3 block with its gradients: the base and the gradients around it are replaced, none
    elsewhere; its energy comes back exactly, spread from its centre where its variance is a single sample's
    (noise), in place and pinned where its samples agree (a light), and, without a variance, spread for a lone
    pixel and in place for a group."""
    from gradsep.model.frame import forward_differences

    base = _textured(40, 48, 2)
    clean = Layer(base, *forward_differences(base), np.full((40, 48), 1e-4, np.float32))
    frame = with_outlier(Frame({"direct": clean}), case, (20, 24), 1e6)
    layer = frame.layers["direct"]
    var = {"noise": layer.var, "agree": clean.var, "none": None}[variance]
    split = split_layer(Layer(layer.base, layer.dx, layer.dy, var))
    assert split is not None
    mask = np.any(layer.base != base, axis=-1)
    assert split.outliers + split.lights == np.count_nonzero(mask)
    moved = np.any(split.layer.dx != layer.dx, axis=-1) | np.any(split.layer.dy != layer.dy, axis=-1)
    near = np.zeros_like(mask)
    near[19:24, 23:28] = True
    assert moved.any() and not (moved & ~near).any() and split.gradients > 0
    assert np.abs(split.layer.base - base).max() < 1.0 and np.abs(split.layer.dx).max() < 1.0
    restored = split.restore(split.layer.base)
    assert restored.astype(np.float64).sum() == pytest.approx(layer.base.astype(np.float64).sum(), rel=1e-6)
    spread = variance == "noise" or (variance == "none" and case == "grad")
    assert (split.spread is not None, split.in_place is not None, split.pinned is not None) == (spread, not spread,
                                                                                                 not spread)
    if not spread:
        np.testing.assert_allclose(restored[mask], layer.base[mask], rtol=1e-6)
        assert split.pinned[mask].all() and split.lights == np.count_nonzero(mask)


def test_a_lone_gradient_spike_is_replaced_and_a_base_only_firefly_leaves_the_gradients_alone() -> None:
    from gradsep.model.frame import forward_differences

    base = _textured(30, 30, 4)
    dx, dy = forward_differences(base)
    spiked = dx.copy()
    spiked[12, 9] = 1e12
    split = split_layer(Layer(base, spiked, dy))
    assert split is not None and (split.outliers, split.gradients) == (0, 1)
    assert abs(float(split.layer.dx[12, 9].max())) < 1.0 and split.spread is None and split.in_place is None
    np.testing.assert_array_equal(split.restore(base), base)  # a gradient carries no energy of its own
    hit = base.copy()
    hit[12, 9] = 1e6
    split = split_layer(Layer(hit, dx, dy))
    assert split is not None and (split.outliers, split.gradients) == (1, 0)
    assert split.layer.dx is dx and split.layer.dy is dy


def test_ordinary_frames_and_lights_larger_or_softer_than_a_cluster_are_left_alone() -> None:
    for name in FRAMES:
        frame = _frame(name)
        same, split = split_frame(frame)
        assert same is frame and not split.layers
        same, split = split_frame(frame, sources=True)
        assert same is frame and not split.layers
    smooth = np.full((12, 12, 3), 0.5, np.float32)
    assert split_layer(Layer(smooth)) is None
    big = smooth.copy()
    big[2:6, 2:6] = 1e4  # 4x4: larger than a cluster
    assert split_layer(Layer(big)) is None
    soft = smooth.copy()
    soft[4:7, 4:7] = 2e3  # a light whose rim the emitter covers in part
    soft[3, 4:7] = soft[7, 4:7] = soft[4:7, 3] = soft[4:7, 7] = 5e2
    assert split_layer(Layer(soft)) is None
    ones = np.ones((1, 1))

    def window(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        return ones[rows[:, :, None], cols[:, None, :]]

    assert find_clusters(np.zeros((4, 4), bool), window) is None
    assert find_clusters(ones > 0.5, window) is None  # a lone pixel with no ring is no cluster


def test_a_light_in_view_is_capped_and_put_back_in_place_for_oidn_a_lone_firefly_is_not_one() -> None:
    """With ``sources`` (``oidn``), a group of pixels over SOURCE_LEVEL x the lit level too large for a cluster is
    capped at that luminance (colour kept) and comes back in place exactly, pinned with its rim; a lone pixel is an
    outlier; ordinary frames have none, and scaling the frame scales both parts."""
    rng = np.random.default_rng(6)
    base = (0.5 + rng.random((96, 120, 3))).astype(np.float32)
    hit = base.copy()
    hit[10:14, 14:18] = np.array([3e4, 2e4, 1e4], np.float32)  # a warm light in view, 4x4 pixels
    split = split_layer(Layer(hit), sources=True)
    assert split is not None and (split.sources, split.outliers, split.lights) == (16, 0, 0)
    capped = split.layer.base
    cap = SOURCE_LEVEL * lit_level(hit)
    assert luminance(capped[10:14, 14:18]) == pytest.approx(np.full((4, 4), cap), rel=1e-5)
    np.testing.assert_allclose(capped[10, 14] / capped[10, 14, 0], [1.0, 2 / 3, 1 / 3], rtol=1e-5)
    mask = np.zeros((96, 120), bool)
    mask[10:14, 14:18] = True
    assert np.array_equal(capped[~mask], hit[~mask])
    np.testing.assert_allclose(split.restore(capped), hit, rtol=1e-6)
    assert split.pinned[9:15, 14:18].all() and split.pinned.sum() == 16 + 16
    scaled = split_layer(Layer(hit * np.float32(1e9)), sources=True)
    np.testing.assert_allclose(scaled.layer.base, capped * np.float32(1e9), rtol=1e-5)
    assert split_layer(Layer(hit)) is None  # without ``sources`` a light is left as rendered
    lone = base.copy()
    lone[5, 5] = 1e6
    assert split_layer(Layer(lone), sources=True).sources == 0


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 7, 3), (5, 1, 3), (3, 3, 3), (17, 23, 3)])
@pytest.mark.parametrize("value", [1e4, 1e30, 3.4e38])
def test_tiny_frames_and_float32s_top_keep_every_value_finite_and_exact(shape, value) -> None:
    """Tiny and odd frames, black frames and outliers or lights up to float32's largest value: what the method sees
    and the excess are finite and non-negative and add back to the input (float64 sum, clipped at float32's top)."""
    from gradsep.model.frame import forward_differences

    rng = np.random.default_rng(sum(shape))
    base = rng.random(shape).astype(np.float32)
    base[: min(2, shape[0]), : min(2, shape[1])] = np.float32(value)
    dx, dy = forward_differences(base)
    split = split_layer(Layer(base, dx, dy, np.ones(shape[:2], np.float32)), sources=True)
    if split is not None:
        seen = split.layer
        assert np.isfinite(seen.base).all() and seen.base.min() >= 0
        assert np.isfinite(seen.dx).all() and np.isfinite(seen.dy).all() and np.isfinite(seen.var).all()
        restored = split.restore(seen.base)
        assert np.isfinite(restored).all()
        assert restored.astype(np.float64).sum() == pytest.approx(base.astype(np.float64).sum(), rel=1e-5)
    assert split_layer(Layer(np.zeros(shape, np.float32))) is None
    assert lit_level(np.zeros(shape, np.float32)) == 0.0 and math.isfinite(lit_level(base))


@pytest.mark.skipif(importlib.util.find_spec("pyoidn") is None, reason="oidn needs pyoidn")
@pytest.mark.parametrize("size", [2, 4])
def test_oidn_keeps_a_light_in_view_where_it_is_and_its_reach_does_not_grow_with_it(size: int, monkeypatch) -> None:
    """A light of 1e4 or 1e6 x the level on a plain frame, 2x2 (a cluster: kept out of OIDN) or 4x4 (a bright
    source: capped for OIDN): ``oidn`` returns its pixels as rendered; the cluster's reach (the pixels it changes
    by more than 1 % beside the output without it) ends within 25 px and does not grow with its brightness.
    Without the detector, the 1e6 light reaches across the 96x72 frame. The answer says why."""
    frame = _frame("procedural")
    plain = Frame({n: Layer(layer.base) for n, layer in frame.layers.items()}, frame.features)
    level = float(plain.layers["direct"].base.mean(dtype=np.float64))
    without = _reconstruct(plain, "oidn")
    light = (slice(10, 10 + size), slice(20, 20 + size))

    def with_light(times: float) -> tuple[Any, np.ndarray]:
        base = plain.layers["direct"].base.copy()
        base[light] = np.float32(times * level)
        return _reconstruct(Frame({**plain.layers, "direct": Layer(base)}, plain.features), "oidn"), base

    reach = {}
    for times in (1e4, 1e6):
        result, base = with_light(times)
        energy = result.layers["direct"][light].astype(np.float64).sum()
        assert energy == pytest.approx(base[light].astype(np.float64).sum(), rel=0.01)
        reach[times] = far_agreement(result.image, without.image, (10, 20), 25.0)
        assert any("light in view" in w for w in result.warnings)
        np.testing.assert_array_equal(result.layers["direct"][light], base[light])  # as rendered
    if size <= outliers.CLUSTER_SIZE:  # kept out of OIDN whole: nothing changes beyond 25 px at any brightness
        assert reach[1e4] == reach[1e6] and reach[1e6][0] == 1.0
    assert table.get("oidn").split_sources and not table.get("oidn-l1").split_sources
    monkeypatch.setattr(outliers, "split_frame", lambda frame, sources=False, threads=1: (frame, outliers.FrameSplit()))
    assert far_agreement(with_light(1e6)[0].image, without.image, (10, 20), 25.0)[1] > 60


@pytest.mark.parametrize("shape, count", [((1, 1, 3), 1), ((5, 7, 3), 4), ((40, 56, 3), 60)])
def test_spreading_by_patches_equals_filtering_the_whole_frame(shape, count, monkeypatch) -> None:
    """spread() adds one separable patch per outlier while they are few and filters the whole frame when they are
    many: the two give the same image to rounding, footprints cut by the border included, and keep the excess."""
    from gradsep.model import robust

    rng = np.random.default_rng(count)
    excess = np.zeros(shape, np.float32)
    excess[rng.integers(0, shape[0], count), rng.integers(0, shape[1], count)] = rng.uniform(1, 1e6, (count, 3))
    patches = robust.spread(excess)
    monkeypatch.setattr(robust, "SPREAD_PATCH_LIMIT", -1)
    whole = robust.spread(excess)
    np.testing.assert_allclose(patches, whole, rtol=1e-12, atol=1e-9 * float(whole.max()))
    np.testing.assert_allclose(patches.sum(axis=(0, 1)), excess.astype(np.float64).sum(axis=(0, 1)), rtol=1e-12)


@pytest.mark.parametrize("shape, count", [((1, 1, 3), 1), ((5, 7, 3), 4), ((40, 56, 3), 60)])
def test_adding_points_patch_by_patch_equals_adding_their_excess_image(shape, count, monkeypatch) -> None:
    """add_points (what the detector's spread outliers come back with) gives add_excess's image of the same points
    to float32 rounding, whether it adds patches or, past SPREAD_PATCH_LIMIT, filters the frame."""
    from gradsep.model import robust

    rng = np.random.default_rng(count)
    image = rng.random(shape).astype(np.float32)
    ys, xs = rng.integers(0, shape[0], count), rng.integers(0, shape[1], count)
    values = rng.uniform(1, 1e3, (count, 3))
    dense = np.zeros(shape, np.float64)
    np.add.at(dense, (ys, xs), values)
    want = robust.add_excess(image, dense)
    np.testing.assert_allclose(robust.add_points(image, ys, xs, values), want, rtol=1e-6)
    monkeypatch.setattr(robust, "SPREAD_PATCH_LIMIT", -1)
    np.testing.assert_allclose(robust.add_points(image, ys, xs, values), want, rtol=1e-6)


# ------------------------------------------------------------------------------------------------ the fast paths
# The detector and the lit level run on every layer of every request; their cheaper forms must give the same
# numbers as the plain ones they replace (issue 54, what the protection costs).


def _odd_values(shape: tuple[int, ...], seed: int) -> np.ndarray:
    """float32 values over many magnitudes, with negatives, zeros, NaN and ±∞ sprinkled in."""
    rng = np.random.default_rng(seed)
    values = (rng.standard_normal(shape) * 10.0 ** rng.integers(-30, 30, shape)).astype(np.float32)
    flat = values.reshape(-1)
    picks = rng.choice(flat.size, size=min(flat.size, 12), replace=False)
    flat[picks] = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 3.4e38] * 2, np.float32)[:picks.size]
    return values


@pytest.mark.parametrize("seed", range(4))
def test_the_magnitude_is_the_channel_mean_of_absolute_values_non_finite_read_as_the_largest(seed: int) -> None:
    image = _odd_values((23, 17, 3), seed)
    with np.errstate(over="ignore", invalid="ignore"):
        expected = (np.abs(image[..., 0]) + np.abs(image[..., 1]) + np.abs(image[..., 2])) / np.float32(3)
    expected[~np.isfinite(expected)] = np.finfo(np.float32).max
    assert np.array_equal(outliers._magnitude(image), expected)
    assert np.array_equal(outliers._magnitude(image[..., :1]), np.fmin(np.abs(image[..., 0]), 3.4028235e38))


@pytest.mark.parametrize("seed", range(4))
def test_neighbour_counts_at_a_few_pixels_are_the_full_frame_convolution(seed: int) -> None:
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    mask = rng.random((19, 26)) < 0.2
    mask[0, 0] = mask[-1, -1] = mask[0, -1] = True  # corners and edges included
    ys, xs = np.nonzero(mask)
    full = ndimage.convolve(mask.astype(np.int8), np.ones((3, 3), np.int8), mode="constant")
    assert np.array_equal(outliers._neighbour_counts(mask, ys, xs), full[ys, xs])


def test_a_gradient_far_below_the_threshold_is_passed_on_and_one_near_it_is_looked_at() -> None:
    frame = _frame("procedural")
    layer = frame.layers["direct"]
    threshold = 2.0 * float(np.nanmax(np.abs(layer.dx))) + 1.0
    assert outliers._clean_gradient(layer.dx, layer.base, 1, threshold) == (layer.dx, 0)
    spiked = layer.dx.copy()
    spiked[10, 10] = 4.0 * threshold  # a lone spike: the screen must not hide it
    fixed, replaced = outliers._clean_gradient(spiked, layer.base, 1, threshold)
    assert replaced == 1 and abs(float(fixed[10, 10, 0])) < threshold
    nan = layer.dx.copy()
    nan[3, 3] = np.nan  # not "within" anything: the per-pixel pass runs
    assert not outliers._all_within(nan, threshold)


def _lit_level_by_definition(lum: np.ndarray) -> float:
    """model.robust.lit_level_of_luminance as its docstring defines it, with no shortcut."""
    from gradsep.model.robust import LIT_BIN, LIT_FRACTION, WINSOR_QUANTILE

    height, width = lum.shape
    rows = np.array([i * height // -(-height // LIT_BIN) for i in range(-(-height // LIT_BIN))])
    cols = np.array([j * width // -(-width // LIT_BIN) for j in range(-(-width // LIT_BIN))])
    sums = np.add.reduceat(np.add.reduceat(lum, rows, axis=0), cols, axis=1)
    row_sizes, col_sizes = np.diff(np.append(rows, height)), np.diff(np.append(cols, width))
    frame_level = robust_level(lum)
    if not (math.isfinite(frame_level) and frame_level > 0.0):
        return 0.0
    lit_bins = sums / np.outer(row_sizes, col_sizes) > LIT_FRACTION * frame_level
    lit = lum[np.repeat(np.repeat(lit_bins, row_sizes, axis=0), col_sizes, axis=1)]
    k = int(WINSOR_QUANTILE * (lit.size - 1))
    cap = float(np.partition(lit, k)[k])
    level = float(np.minimum(lit, cap).mean())
    return level if level > 0.0 else float(lit.mean())


@pytest.mark.parametrize("frame_name", list(FRAMES))
def test_the_lit_level_and_the_luminance_are_their_definitions(frame_name: str) -> None:
    from gradsep.model.policy import LUMINANCE
    from gradsep.model.robust import lit_level_of_luminance

    for layer in _frame(frame_name).layers.values():
        base = layer.base.copy()
        with np.errstate(invalid="ignore"):
            expected = (base[..., 0] * np.float64(LUMINANCE[0]) + base[..., 1] * np.float64(LUMINANCE[1])
                        + base[..., 2] * np.float64(LUMINANCE[2]))
        assert np.array_equal(luminance(base), np.maximum(expected, 0.0))
        lum = luminance(base)
        assert lit_level_of_luminance(lum) == _lit_level_by_definition(lum)  # every bin lit
        dark = lum.copy()
        dark[: dark.shape[0] // 2] = 0.0
        assert lit_level_of_luminance(dark) == _lit_level_by_definition(dark)  # half of the bins black
        base[2, 3] = np.inf
        base[4, 5, 1] = np.nan
        assert luminance(base)[2, 3] == 0.0 and luminance(base)[4, 5] == 0.0


def test_the_lit_level_the_detector_hands_on_is_the_one_oidn_would_measure() -> None:
    from gradsep.model.oidn import _finite

    frame = _frame("cbox")
    seen, split = split_frame(frame, sources=True)
    assert set(split.lit_levels) == set(frame.layers)
    for name, level in split.lit_levels.items():
        assert level == lit_level(_finite(seen.layers[name].base, 0.0, 3.4028235e38))
    assert not split_frame(frame, sources=False)[1].lit_levels  # only the sources pass measures it
    negative = frame.layers["direct"].base.copy()
    negative[5, 5, 0] = -1.0  # OIDN clamps it: its level is not the detector's
    moved = replace(frame, layers={**frame.layers, "direct": Layer(negative, frame.layers["direct"].dx,
                                                                   frame.layers["direct"].dy)})
    assert set(split_frame(moved, sources=True)[1].lit_levels) == set(frame.layers) - {"direct"}
    light = frame.layers["direct"].base.copy()
    light[20, 30:34] = 1e6 * float(light.mean())  # a light in view: capped for oidn, so measured before that
    capped = replace(frame, layers={**frame.layers, "direct": Layer(light, frame.layers["direct"].dx,
                                                                    frame.layers["direct"].dy)})
    seen, split = split_frame(capped, sources=True)
    assert split.layers["direct"].sources > 0 and "direct" not in split.lit_levels
