"""Temporal reconstruction (model/temporal.py), the flicker metric (model/metrics.py) and ``gradsep reconstruct
--frames`` (model/commands.py), on synthetic shots whose truth is known: a static shot, a light switched off, and
a whole-frame shift (integer and subpixel) with the pixels that enter the frame disoccluded."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gradsep.model.exr_read import read_frame, read_header
from gradsep.model.exr_write import encode_exr
from gradsep.model.frame import Features, Frame, Layer
from gradsep.model.metrics import flicker, relmse
from gradsep.model.reconstruct import reconstruct
from gradsep.model.temporal import Motion, ShotReconstructor, reconstruct_window
from gradsep.model.warp import chain

pytest.importorskip("pyoidn", reason="the per-frame method of a plain frame is oidn")

SIZE = 64
NOISE = 0.25  # relative noise of one frame's base


def _truth(shift: float = 0.0, lamp: float = 1.0) -> np.ndarray:
    """A smooth (H, W, 3) scene with an edge and a bright patch (the lamp's pool, scaled by ``lamp``), moved right
    by ``shift`` pixels."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    xx = xx - shift
    shade = 0.4 + 0.2 * np.sin(xx / 7.0) * np.cos(yy / 9.0) + 0.3 * (xx > SIZE / 2)
    pool = np.exp(-((xx - 20) ** 2 + (yy - 20) ** 2) / 60.0)
    grey = shade + 0.1 * lamp + 1.5 * lamp * pool
    return np.repeat(grey[..., None], 3, axis=-1).astype(np.float32)


def _frame(truth: np.ndarray, seed: int, motion: Motion | None = None) -> Frame:
    """A noisy plain frame of ``truth``: the noise shared by the channels, so the luminance's variance is the
    noise's; albedo and normal constant."""
    rng = np.random.default_rng(seed)
    sigma = NOISE * truth[..., 0]
    base = np.maximum(truth + (sigma * rng.standard_normal(sigma.shape))[..., None], 0).astype(np.float32)
    features = Features(albedo=np.full(truth.shape, 0.5, np.float32),
                        normal=np.dstack([np.zeros((SIZE, SIZE, 2)), np.ones((SIZE, SIZE))]).astype(np.float32))
    frame = Frame({"color": Layer(base, var=(sigma * sigma).astype(np.float32))}, features)
    frame.motion = motion
    return frame


def _motion(shift: float) -> Motion:
    """Every pixel moves right by ``shift`` per frame: backward.u = -shift, forward.u = +shift (v = 0); the
    columns whose source is off screen are invalid."""
    cols = np.arange(SIZE, dtype=np.float32)[None, :].repeat(SIZE, 0)
    backward = np.zeros((SIZE, SIZE, 2), np.float32)
    forward = np.zeros((SIZE, SIZE, 2), np.float32)
    backward[..., 0], forward[..., 0] = -shift, shift
    return Motion(backward, forward, ((cols - shift) >= 0).astype(np.float32),
                  ((cols + shift) <= SIZE - 1).astype(np.float32))


def _shot(truths: list[np.ndarray], motion: Motion | None, seed: int = 0) -> list[Frame]:
    return [_frame(t, seed * 100 + i, motion) for i, t in enumerate(truths)]


def _temporal(frames: list[Frame], window: int = 5) -> list[np.ndarray]:
    shot = ShotReconstructor(lambda n: frames[n] if 0 <= n < len(frames) else None, window)
    return [shot.reconstruct(n).image for n in range(len(frames))]


def _per_frame(frames: list[Frame]) -> list[np.ndarray]:
    return [reconstruct(f).image for f in frames]


def _geomean(values: list[float]) -> float:
    return math.exp(float(np.mean(np.log(values))))


# ------------------------------------------------------------------------------------------------ the metric


def test_flicker_is_zero_for_a_steady_error_and_measures_a_change() -> None:
    ref = [np.ones((4, 4, 3))] * 3
    steady = [np.full((4, 4, 3), 1.2)] * 3  # wrong, but the same error every frame: no flicker
    assert flicker(steady, ref) == 0.0
    jumping = [np.ones((4, 4, 3)), np.full((4, 4, 3), 1.1), np.ones((4, 4, 3))]
    assert flicker(jumping, ref) == pytest.approx(0.01 / 1.01)
    masks = [None, np.zeros((4, 4), bool), np.eye(4, dtype=bool)]
    assert flicker(jumping, ref, masks=masks) == pytest.approx(0.01 / 1.01)  # only the last pair counts
    with pytest.raises(ValueError, match="at least two"):
        flicker(steady[:1], ref[:1])


def test_flicker_of_a_light_switched_off_equals_that_of_it_switched_on() -> None:
    """The same pair of frames played forwards and backwards changes by as much: normalised by frame t's reference
    alone, the error of the lit frame divided by the dark one's reference counted 20x more one way."""
    rng = np.random.default_rng(3)
    lit, dark = np.full((16, 16, 3), 1.0), np.full((16, 16, 3), 0.05)
    images = [lit + 0.05 * rng.standard_normal(lit.shape), dark + 0.005 * rng.standard_normal(lit.shape)]
    off = flicker(images, [lit, dark])
    on = flicker(images[::-1], [dark, lit])
    assert off == pytest.approx(on)
    assert off == pytest.approx(float(np.mean((images[0] - lit - images[1] + dark) ** 2 / (0.525 ** 2 + 1e-2))))


def test_flicker_with_two_references_removes_their_noise() -> None:
    rng = np.random.default_rng(1)
    truth = np.ones((64, 64, 3))
    images = [truth + 0.1 * rng.standard_normal(truth.shape) for _ in range(6)]
    r1 = [truth + 0.1 * rng.standard_normal(truth.shape) for _ in range(6)]
    r2 = [truth + 0.1 * rng.standard_normal(truth.shape) for _ in range(6)]
    expected = 2 * 0.01 / 1.01  # the images' own change: two independent errors of variance 0.01
    assert flicker(images, r1, r2) == pytest.approx(expected, rel=0.1)
    assert flicker(images, r1) > 1.5 * expected  # one noisy reference adds its own change


# ------------------------------------------------------------------------------------------------ per-frame identity


def test_one_frame_or_no_motion_is_the_per_frame_method_bit_for_bit() -> None:
    frames = _shot([_truth()] * 5, None)
    per = reconstruct(frames[2])
    for window, centre in ((frames[2:3], 0), (frames, 2)):
        out = reconstruct_window(window, centre)
        assert out.method == per.method and out.neighbours == []
        np.testing.assert_array_equal(out.image, per.image)
    assert np.array_equal(_temporal(frames)[2], per.image)
    moving = _shot([_truth()], _motion(0.0))
    np.testing.assert_array_equal(reconstruct_window(moving, 0).image, reconstruct(moving[0]).image)


def test_window_and_shot_reconstructor_agree() -> None:
    frames = _shot([_truth()] * 5, _motion(0.0), seed=3)
    out = reconstruct_window(frames, 2)
    np.testing.assert_array_equal(out.image, _temporal(frames)[2])
    assert out.neighbours == [-2, -1, 1, 2]


def test_a_shot_in_order_keeps_only_its_window_and_gives_each_window() -> None:
    """ShotReconstructor forgets a frame and a first stage before the next first stage runs, as soon as no later
    window needs them; each frame is what reconstruct_window gives it, also a frame asked for again, out of order.
    A moving shot never computes the still neighbours' box means. Window 7: first stages over frames n - 2 .. n + 2,
    the second stage over the first stages of n - 1 .. n + 1, the moved stage over those of the neighbours between
    pixels (at 0.5 px a frame, n - 1 and n + 1; frames two away are on the grid), and n - 2's is still kept."""
    truths = [_truth(0.5 * i) for i in range(9)]
    frames = _shot(truths, _motion(0.5), seed=13)
    shot = ShotReconstructor(lambda n: frames[n] if 0 <= n < len(frames) else None, 7)
    images = []
    for n in range(len(frames)):
        images.append(shot.reconstruct(n).image)
        assert sorted(shot._firsts) == list(range(max(n - 2, -1), n + 2))
        assert sorted(shot._frames) == list(range(n - 3, n + 4))  # the frames of the first stages still to run
    for n in (3, 4, 5):
        np.testing.assert_array_equal(images[n], reconstruct_window(frames[n - 3:n + 4], 3).image)
    np.testing.assert_array_equal(shot.reconstruct(4).image, images[4])
    assert all(not f._temporal_stats.boxes for f in frames)


@pytest.mark.parametrize(("window", "radii"), [(1, (0, 0)), (3, (1, 0)), (5, (2, 0)), (7, (2, 1)), (9, (2, 2))])
def test_the_first_stage_reaches_two_frames_and_the_second_the_rest(window: int, radii: tuple[int, int]) -> None:
    from gradsep.model import temporal

    assert temporal._radii(window) == radii


# ------------------------------------------------------------------------------------------------ quality


def test_static_shot_beats_per_frame_and_does_not_flicker() -> None:
    truth = _truth()
    frames = _shot([truth] * 8, _motion(0.0), seed=5)
    per, tem = _per_frame(frames), _temporal(frames)
    refs = [truth] * 8
    ratio = _geomean([relmse(x, truth) for x in tem]) / _geomean([relmse(x, truth) for x in per])
    assert ratio <= 0.67
    assert flicker(tem, refs) <= 0.4 * flicker(per, refs)


def test_light_switched_off_is_not_ghosted() -> None:
    on, off = _truth(lamp=1.0), _truth(lamp=0.0)
    truths = [on] * 4 + [off] * 4
    frames = _shot(truths, _motion(0.0), seed=7)
    per, tem = _per_frame(frames), _temporal(frames)
    for t in (4, 5):  # the frames after the switch, whose windows hold lit frames
        assert relmse(tem[t], off) <= 1.1 * relmse(per[t], off), t
    pool = np.zeros((SIZE, SIZE), bool)
    pool[12:29, 12:29] = True  # where the lamp's light was
    assert relmse(tem[4][pool], off[pool]) <= 1.1 * relmse(per[4][pool], off[pool])


@pytest.mark.parametrize("shift", [2.0, 1.25])
def test_moving_shot_is_warped_and_disocclusions_are_not_ghosted(shift: float) -> None:
    """Whole-pixel motion gains through the first stage; motion between pixels (1.25 px a frame: 2.5 px two frames
    away, between pixels too) through the moved stage, the neighbours' results; the pixels that entered the frame
    are not ghosted either way."""
    truths = [_truth(shift * i) for i in range(7)]
    frames = _shot(truths, _motion(shift), seed=11)
    per, tem = _per_frame(frames), _temporal(frames)
    inner = slice(2, 5)
    ratio = (_geomean([relmse(tem[t], truths[t]) for t in range(7)[inner]])
             / _geomean([relmse(per[t], truths[t]) for t in range(7)[inner]]))
    assert ratio <= 0.8
    edge = slice(0, math.ceil(shift))  # the columns that entered the frame: frame t - 1 has no pixel there
    for t in range(2, 5):
        assert relmse(tem[t][:, edge], truths[t][:, edge]) <= 1.1 * relmse(per[t][:, edge], truths[t][:, edge])


def test_a_neighbour_wholly_off_the_grid_is_taken_whole_by_its_nearest_pixels(monkeypatch) -> None:
    """A camera move between pixels (0.5 px a frame): the first stage takes each neighbour's nearest pixel whole,
    so the accumulated input's noise falls with the frames and stays uncorrelated between pixels (a bilinear tap
    would mix neighbouring pixels' noise), and the agreeing pixels are marked for the moved stage too. Without
    features, which tell a tap across an edge, the neighbours are neither warped nor tested: frame t's inputs as
    they were."""
    from gradsep.model import temporal

    truths = [_truth(0.5 * i) for i in range(3)]
    frames = _shot(truths, _motion(0.5), seed=3)
    bare = [Frame(f.layers, None) for f in frames]
    for frame, source in zip(bare, frames, strict=True):
        frame.motion = source.motion
    counted = []
    stats = temporal.frame_stats
    monkeypatch.setattr(temporal, "frame_stats", lambda frame: counted.append(frame) or stats(frame))
    for shot, tested in ((frames, 3), (bare, 1)):
        counted.clear()
        chained = {o: chain(shot, 1, o) for o in (-1, 1)}
        out, agreement = temporal._accumulate(shot, 1, chained, [])
        assert len(counted) == tested
        assert all(not mask.any() for per in agreement.accept.values() for mask in per.values())  # none on the grid
        assert set(agreement.accept[next(iter(shot[1].layers))]) == {-1, 1}
        assert agreement.moved_offsets() == ([-1, 1] if shot is frames else [])
        if shot is bare:
            for name, layer in shot[1].layers.items():
                np.testing.assert_array_equal(out.layers[name].base, layer.base)
            continue
        both = agreement.taken["color"][-1] & agreement.taken["color"][1]
        assert both.mean() > 0.8
        inner = both[1:-1, 1:-2] & both[1:-1, 2:-1]  # horizontal pairs, both accumulated from three frames
        noise = {k: (image.layers["color"].base - truths[1])[..., 0] / truths[1][..., 0]
                 for k, image in (("in", shot[1]), ("out", out))}
        assert np.var(noise["out"][1:-1, 1:-1][both[1:-1, 1:-1]]) <= 0.45 * np.var(noise["in"])
        left, right = noise["out"][1:-1, 1:-2][inner], noise["out"][1:-1, 2:-1][inner]
        assert abs(np.corrcoef(left, right)[0, 1]) < 0.1  # bilinear taps: 0.28


@pytest.mark.parametrize("level", [1e-8, 1e6, 3e38])
def test_taken_taps_are_demodulated_and_finite_at_any_level(level: float) -> None:
    """A camera move over texture, at radiance from 1e-8 to near float32's largest: the nearest pixels taken over
    another texel are multiplied by frame t's albedo over theirs, within TEXTURE_RATIO (a stripe of 0.3 next to 0.4:
    taken; next to 0.9: another material, left out), and the accumulated input stays finite and on frame t's
    texture (near float32's largest the rejection test keeps frame t's own)."""
    from gradsep.model import temporal

    shift = 0.5
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)

    def albedo(i: int) -> np.ndarray:
        column = np.floor(xx - shift * i) % 6
        stripes = np.where(column < 2, 0.3, np.where(column < 4, 0.4, 0.9))
        return np.repeat(stripes[..., None], 3, axis=-1).astype(np.float32)

    truths = [np.full((SIZE, SIZE, 3), level, np.float32) * albedo(i) for i in range(3)]
    with np.errstate(over="ignore"):
        frames = _shot(truths, _motion(shift), seed=19)
    for i, frame in enumerate(frames):
        frame.features = Features(albedo=albedo(i), normal=frame.features.normal)
        for image in (frame.layers["color"].base, frame.layers["color"].var):  # a renderer's float32 output
            np.minimum(image, np.finfo(np.float32).max, out=image)
    out, agreement = temporal._accumulate(frames, 1, {o: chain(frames, 1, o) for o in (-1, 1)}, [])
    base = out.layers["color"].base
    assert np.isfinite(base).all() and np.isfinite(out.layers["color"].var).all()
    taken = agreement.taken["color"][-1] | agreement.taken["color"][1]
    mine = albedo(1)[..., 0]
    if level > 1e30:  # the rejection test's squares overflow there: it rejects, and frame t keeps its own
        return
    assert taken.mean() > 0.5
    for o in (-1, 1):
        theirs = chain(frames, 1, o).nearest()(albedo(1 + o))[..., 0]
        mixed = (theirs == 0.9) != (mine == 0.9)
        assert mixed.any() and not (agreement.taken["color"][o] & mixed).any()
        assert (agreement.taken["color"][o] & (theirs != mine)).any()  # 0.3 next to 0.4: taken, demodulated
    noise = np.abs(base[..., 0] / (level * mine) - 1.0)[taken]  # on frame t's texture, within the noise
    assert np.median(noise) < 0.2


def test_a_camera_move_between_pixels_keeps_texture_and_does_not_ghost_a_switched_light() -> None:
    """The moved stage under a camera turning 1.25 px a frame: a sharp albedo edge (texture) is neither blurred nor
    doubled (the taps across it fail the albedo test; elsewhere the results are demodulated), and a lamp switched
    off mid-shot leaves no light in the frames after the switch (the neighbours' inputs fail the rejection test)."""
    shift = 1.25
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)

    def albedo(i: int) -> np.ndarray:
        stripes = 0.2 + 0.6 * ((((xx - shift * i) // 3) % 2) == 0)  # 3-pixel stripes: an edge every 3 columns
        return np.repeat(stripes[..., None], 3, axis=-1).astype(np.float32)

    lamps = [1.0] * 4 + [0.0] * 4
    truths = [_truth(shift * i, lamp) * albedo(i) for i, lamp in enumerate(lamps)]
    frames = _shot(truths, _motion(shift), seed=17)
    for i, frame in enumerate(frames):
        frame.features = Features(albedo=albedo(i), normal=frame.features.normal)
    per, tem = _per_frame(frames), _temporal(frames)
    steady = [t for t in range(2, 6) if t not in (4, 5)]
    assert _geomean([relmse(tem[t], truths[t]) for t in steady]) <= 0.9 * _geomean(
        [relmse(per[t], truths[t]) for t in steady])
    for t in (4, 5):  # after the switch
        assert relmse(tem[t], truths[t]) <= 1.1 * relmse(per[t], truths[t]), t


@pytest.mark.parametrize("level", [1e-8, 1.0, 1e6, 1e38])
def test_the_moved_stage_blends_illumination_and_puts_frame_ts_texture_back(level: float) -> None:
    """A neighbour half a pixel away whose result is smooth light times a 1-pixel stripe texture: blended
    demodulated, the output is frame t's texture times the mean light (no stripe blurred into its neighbours), at any
    radiance and finite at float32's largest; pixels the agreement leaves out keep frame t's own."""
    from gradsep.model.temporal import TemporalReconstruction, _Agreement, moved_stage
    from gradsep.model.warp import Sampler, grid

    size = 16
    rows, cols = grid(size, size)
    stripes = np.repeat((0.2 + 0.6 * (np.arange(size) % 2))[None, :, None], size, 0).repeat(3, -1)
    mine_albedo, their_albedo = stripes.astype(np.float32), stripes[:, ::-1].astype(np.float32)  # shifted a pixel
    light = np.float32(level) * np.ones((size, size, 3), np.float32)
    own_layer = light * (mine_albedo + 0.02)
    their_layer = light * (their_albedo + 0.02)
    sampler = Sampler(rows, cols + 0.5, np.ones((size, size), bool))
    moved = np.ones((size, size), bool)
    moved[:, :4] = False
    agreement = _Agreement({1: sampler}, moved={"color": {1: moved}}, albedo=mine_albedo)

    def result(layer: np.ndarray, agree: _Agreement) -> TemporalReconstruction:
        out = TemporalReconstruction(layer, {"color": layer}, {}, "oidn")
        out.agreement = agree
        return out

    own = result(own_layer, agreement)
    other = result(their_layer, _Agreement(albedo=their_albedo))
    out = moved_stage(own, own, {1: other})
    assert out.neighbours == [1] and np.isfinite(out.image).all()
    inside = np.s_[:, 4:-1]  # the last column's taps are clamped at the edge
    np.testing.assert_allclose(out.image[inside], own_layer[inside], rtol=1e-5)
    np.testing.assert_array_equal(out.image[:, :4], own_layer[:, :4])
    black = np.zeros((size, size, 3), np.float32)  # a light seen directly: radiance over a black albedo
    hot = result(np.full((size, size, 3), 3e38, np.float32), _Agreement(albedo=black))
    out = moved_stage(own, result(own_layer, _Agreement({1: sampler}, moved={"color": {1: moved}}, albedo=black)),
                      {1: hot})
    assert np.isfinite(out.image).all() and (out.image >= 0).all()


def test_a_neighbours_gradient_counts_only_where_both_its_pixels_correspond() -> None:
    """A gradient joins a pixel and the next one: across a motion edge (the left half moved, the right half did not)
    or beside a disoccluded pixel, the neighbour's difference is between other pixels, so frame t keeps its own."""
    from gradsep.model import temporal

    size = 16

    def frame(gradient: float, motion: Motion | None) -> Frame:
        base = np.ones((size, size, 3), np.float32)
        dx = np.full((size, size, 3), gradient, np.float32)
        dx[:, -1] = 0.0
        layer = Layer(base, dx, np.zeros_like(base), np.full((size, size), 1e-4, np.float32))
        out = Frame({"color": layer}, None)
        out.motion = motion
        return out

    backward = np.zeros((size, size, 2), np.float32)
    backward[:, :8, 0] = -2.0  # the left half moved 2 pixels right since frame t - 1; its first 2 columns are new
    valid = np.ones((size, size), np.float32)
    valid[:, :2] = 0.0
    own = frame(0.0, Motion(backward, None, valid, None))
    frames = [frame(4.0, None), own]
    out, agreement = temporal._accumulate(frames, 1, {-1: chain(frames, 1, -1)}, [])
    assert agreement.accept["color"][-1][:, 2:].all() and not agreement.accept["color"][-1][:, :2].any()
    dx = out.layers["color"].dx[..., 0]
    np.testing.assert_allclose(dx[:, 3:7], 2.0)  # both pixels seen in t - 1, next to each other there: averaged
    np.testing.assert_allclose(dx[:, 8:15], 2.0)
    np.testing.assert_array_equal(dx[:, 7], 0.0)  # pixel 7 is at column 5 of t - 1, pixel 8 at column 8
    np.testing.assert_array_equal(dx[:, :2], 0.0)  # columns 0-1 are not in t - 1
    np.testing.assert_allclose(out.layers["color"].base, 1.0)


# ------------------------------------------------------------------------------------------------ bad input


def test_a_neighbour_without_variance_is_of_the_same_shot_and_warned() -> None:
    """A frame rendered to a deadline that got one sample has no L.var.Y: it is a frame of the same shot (the
    window does not refuse it), its noise is estimated spatially, and the warning names it."""
    frames = _shot([_truth(float(i)) for i in range(3)], _motion(1.0), seed=4)
    bare = Frame({"color": Layer(frames[0].layers["color"].base)}, frames[0].features)
    bare.motion = frames[0].motion
    full = reconstruct_window(frames, 1)
    out = reconstruct_window([bare, frames[1], frames[2]], 1)
    assert out.neighbours == full.neighbours == [-1, 1]
    assert any("no variance channel" in w and "frame(s) -1:" in w for w in out.warnings), out.warnings
    assert not any("no variance channel" in w for w in full.warnings)
    assert np.isfinite(out.image).all()
    truth = _truth(1.0)
    assert relmse(out.image, truth) < relmse(reconstruct(frames[1]).image, truth)


def test_the_shot_layout_leaves_out_motion_and_variance() -> None:
    from gradsep.model.frame import shot_layout

    plain = ["direct.R", "direct.G", "direct.B", "albedo.R"]
    assert shot_layout([*plain, "direct.var.Y", "backward.u", "forward.v"]) == shot_layout(plain)
    assert shot_layout([*plain, "indirect.R"]) != shot_layout(plain)


def test_frames_of_another_size_or_layout_are_named() -> None:
    frames = _shot([_truth()] * 3, _motion(0.0))
    small = Frame({"color": Layer(frames[0].layers["color"].base[:32, :32])})
    with pytest.raises(ValueError, match=r"frame \+1 is 32x32"):
        reconstruct_window([frames[0], frames[1], small], 1)
    featureless = Frame({"color": frames[0].layers["color"]})
    with pytest.raises(ValueError, match=r"frame -1 carries other channels than frame t"):
        reconstruct_window([featureless, frames[1], frames[2]], 1)
    with pytest.raises(ValueError, match="centre"):
        reconstruct_window([None, frames[1]], 0)
    with pytest.raises(ValueError, match="odd"):
        ShotReconstructor(lambda n: None, 4)


def test_a_missing_neighbour_is_a_warning_and_the_frame_uses_what_it_has() -> None:
    frames = _shot([_truth()] * 5, _motion(0.0))
    out = reconstruct_window([frames[0], None, frames[2], frames[3], frames[4]], 2)
    assert any("missing" in w for w in out.warnings)
    assert -1 not in out.neighbours and -2 not in out.neighbours and 1 in out.neighbours


def _write_shot(folder: Path, sizes: list[int], motion: bool = False) -> None:
    rng = np.random.default_rng(0)
    for i, size in enumerate(sizes, start=1):
        base = (0.5 + 0.1 * rng.standard_normal((size, size))).astype(np.float32)
        channels = {f"color.{c}": base for c in "RGB"}
        channels["color.var.Y"] = np.full((size, size), 0.01, np.float32)
        if motion:  # still: zero vectors, all valid, as the renderer writes them for a still shot
            for direction in ("backward", "forward"):
                channels[f"{direction}.u"] = channels[f"{direction}.v"] = np.zeros((size, size), np.float32)
                channels[f"{direction}.valid"] = np.ones((size, size), np.float32)
        (folder / f"shot.{i:04d}.exr").write_bytes(encode_exr(channels))


def _gradsep(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gradsep", *args], capture_output=True, text=True, timeout=300)


def test_command_writes_each_frame_with_its_neighbours_header(tmp_path: Path) -> None:
    _write_shot(tmp_path, [16, 16, 16])
    out = _gradsep("reconstruct", str(tmp_path / "shot.%04d.exr"), "--frames", "1-2", "-o",
                   str(tmp_path / "out.####.exr"))
    assert out.returncode == 0, out.stderr
    for n in (1, 2):
        header = read_header(tmp_path / f"out.{n:04d}.exr")
        assert header.attributes[temporal_key()] == ""  # no motion vectors: no neighbour reached it
        assert read_frame(tmp_path / f"out.{n:04d}.exr", layout="auto").width == 16
    assert "no motion vectors" in out.stderr
    assert not (tmp_path / "out.0003.exr").exists()


def test_command_with_motion_vectors_names_the_frames_used(tmp_path: Path) -> None:
    _write_shot(tmp_path, [16, 16, 16, 16], motion=True)
    out = _gradsep("reconstruct", str(tmp_path / "shot.%04d.exr"), "--frames", "2-3", "-o",
                   str(tmp_path / "out.%04d.exr"))
    assert out.returncode == 0, out.stderr
    assert read_header(tmp_path / "out.0002.exr").attributes[temporal_key()] == "1,3,4"
    assert read_header(tmp_path / "out.0003.exr").attributes[temporal_key()] == "1,2,4"
    assert "neighbour frame(s) 5 missing" in out.stderr  # frame 3's window reaches 5, which does not exist


def temporal_key() -> str:
    from gradsep.model.commands import NEIGHBOURS_KEY

    return NEIGHBOURS_KEY


@pytest.mark.parametrize(("sizes", "frames", "output", "message"), [
    ([16, 16, 12], "1-3", "out.%04d.exr", "shot.0003.exr is 12x12"),
    ([16, 16], "1-3", "out.%04d.exr", "shot.0003.exr of the shot is missing"),
    ([16, 16], "2-1", "out.%04d.exr", "reversed"),
    ([16, 16], "1-2", "out.exr", "no frame-number field"),
])
def test_command_bad_input_is_one_line_exit_2_and_no_file(tmp_path: Path, sizes: list[int], frames: str,
                                                          output: str, message: str) -> None:
    _write_shot(tmp_path, sizes)
    out = _gradsep("reconstruct", str(tmp_path / "shot.%04d.exr"), "--frames", frames, "-o",
                   str(tmp_path / output))
    assert out.returncode == 2
    assert message in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert not list(tmp_path.glob("out*"))
