"""Correctness of the G-PT renderer against Mitsuba's own `path` integrator on the Cornell box, the teapot (the
shared third-party files, or their built-in stand-ins: tests/renderer/scenes.py) and scenes built in the tests.

Tolerances come from the sample counts: every comparison estimates the standard error of both sides from
independent seeds (G-PT) or independent reference chunks (Mitsuba) and allows a few standard errors. Small
images and few samples keep the whole module to well under a minute on two cores; one loaded scene and one set
of renders per scene is shared through module-scoped fixtures, so only a handful of kernels are compiled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from gradsep.cli import main  # noqa: E402
from gradsep.model.errors import CommandError  # noqa: E402
from gradsep.model.exr_read import read_frame  # noqa: E402
from gradsep.model.exr_write import write_frame  # noqa: E402
from gradsep.renderer.gpt import MAX_LANES_PER_PASS, pass_plan, render_gpt  # noqa: E402
from gradsep.renderer.gpt_settings import Film, GptSettings  # noqa: E402
from gradsep.renderer.hybrid import HybridShift  # noqa: E402
from gradsep.renderer.render import FrameOptions, parse_layers, plan_layers, render_frame  # noqa: E402
from gradsep.renderer.scene import load_scene  # noqa: E402
from gradsep.renderer.shift import ReplayShift, make_shift  # noqa: E402
from gradsep.renderer.variant import select_variant  # noqa: E402
from tests.renderer.scenes import CBOX_GEOMETRY, resolve  # noqa: E402

pytestmark = pytest.mark.render


# The shared third-party scenes when present, else built-in equivalents (tests/renderer/scenes.py): every test
# here runs on whichever is available.
CBOX = str(resolve("cbox"))
TEAPOT = str(resolve("teapot"))
SIZE = 24
SEEDS = 16  # independent G-PT renders per scene
SPP = 8  # per G-PT render
REF_CHUNKS = 8  # independent Mitsuba `path` renders making the high-spp reference
REF_SPP = 512  # per chunk (4096 in all: 32x the G-PT total per render)
Z_MAX = 5.0  # per-pixel |z| above this counts as an outlier


def fd_x(img: np.ndarray) -> np.ndarray:
    """Forward differences along x per the frame contract (works on stacks: (..., H, W, C))."""
    d = np.zeros_like(img)
    d[..., :, :-1, :] = img[..., :, 1:, :] - img[..., :, :-1, :]
    return d


def fd_y(img: np.ndarray) -> np.ndarray:
    d = np.zeros_like(img)
    d[..., :-1, :, :] = img[..., 1:, :, :] - img[..., :-1, :, :]
    return d


@dataclass
class Renders:
    """G-PT renders of one scene over SEEDS seeds, plus Mitsuba `path` references."""

    base: dict[str, np.ndarray]  # layer -> (SEEDS, H, W, 3)
    dx: dict[str, np.ndarray]
    dy: dict[str, np.ndarray]
    features: list  # GptResult per seed
    ref: dict[int, np.ndarray]  # max_depth -> (REF_CHUNKS, H, W, 3) chunks of the reference
    low: dict[int, np.ndarray]  # max_depth -> (SEEDS, H, W, 3) `path` at the G-PT sample count

    def total(self, key: str) -> np.ndarray:
        return sum(getattr(self, key).values())


def path_render(scene, spp: int, seed: int, max_depth: int) -> np.ndarray:
    integrator = mi.load_dict({"type": "path", "max_depth": max_depth})
    return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed), dtype=np.float64)


SHIFTS = ("replay", "hybrid")
SCENE_DEPTHS = {"cbox": 6, "teapot": 4, "sky": 4}
_scenes: dict[str, object] = {}
_references: dict[str, tuple[dict, dict]] = {}
_renders: dict[tuple[str, str, str], Renders] = {}


def load_test_scene(name: str):
    """The three test scenes, loaded once per worker. The teapot file asks for direct light only; depth 4 adds
    the teapot's light on itself (a faint indirect layer) and keeps silhouettes against the black background."""
    if name not in _scenes:
        if name == "sky":
            select_variant()
            _scenes[name] = mi.load_dict(open_scene_dict())
        else:
            spec = CBOX if name == "cbox" else TEAPOT
            _scenes[name] = load_scene(spec, width=SIZE, height=SIZE, max_depth=SCENE_DEPTHS[name]).scene
    return _scenes[name]


def make_renders(name: str, shift: str, offsets: str = "all", gradients: str = "all") -> Renders:
    """G-PT over SEEDS seeds with ``shift`` (tracing ``offsets``: GptSettings.offsets; gradients of ``gradients``
    layers: GptSettings.gradients), plus the scene's `path` references (shared between shifts)."""
    key = (name, shift, offsets) if gradients == "all" else (name, shift, offsets, gradients)
    if key in _renders:
        return _renders[key]
    scene, depth = load_test_scene(name), SCENE_DEPTHS[name]
    settings = GptSettings(max_depth=depth, offsets=offsets, gradients=gradients)
    results = [render_gpt(scene, make_shift(shift), settings, Film(SIZE, SIZE, SPP, seed)) for seed in range(SEEDS)]
    layers = list(results[0].layers)
    stack = {k: {layer: np.stack([r.layers[layer][k] for r in results]).astype(np.float64) for layer in layers
                 if k in results[0].layers[layer]}  # a layer without gradients has "base" alone
             for k in ("base", "dx", "dy")}
    if name not in _references:
        ref = {d: np.stack([path_render(scene, REF_SPP, 10_000 + i, d) for i in range(REF_CHUNKS)])
               for d in (depth, 2)}
        low = {d: np.stack([path_render(scene, SPP, 20_000 + i, d) for i in range(SEEDS)]) for d in (depth, 2)}
        _references[name] = (ref, low)
    ref, low = _references[name]
    _renders[key] = Renders(base=stack["base"], dx=stack["dx"], dy=stack["dy"], features=results, ref=ref, low=low)
    return _renders[key]


@pytest.fixture(scope="module")
def cbox() -> Renders:
    return make_renders("cbox", "replay")


@pytest.fixture(scope="module")
def teapot() -> Renders:
    return make_renders("teapot", "replay")


@pytest.fixture(scope="module")
def sky() -> Renders:
    return make_renders("sky", "replay")


def open_scene_dict() -> dict:
    """A diffuse sphere on a finite floor under a sky (constant environment) and a small area light.

    Unlike the closed Cornell box, offset paths here regularly leave the scene while their base path goes on
    (silhouettes against the sky), which is where the shift's MIS weights for one-sided events matter.
    """
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1.5, 5], target=[0, 0.3, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "rfilter": {"type": "box"}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.4, 0.5, 0.7]}},
        "sphere": {"type": "sphere", "center": [0, 0.5, 0], "radius": 0.5,
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.3, 0.2]}}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(1.5),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}},
        "lamp": {"type": "rectangle",
                 "to_world": mi.ScalarTransform4f().translate([1.0, 2.0, 0.5]).rotate([1, 0, 0], 90).scale(0.3),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [20, 18, 15]}}},
    }


def two_sample_z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z of mean(a) - mean(b) over axis 0, standard errors from the spread of the independent repeats."""
    se2 = a.var(0, ddof=1) / a.shape[0] + b.var(0, ddof=1) / b.shape[0]
    return (a.mean(0) - b.mean(0)) / np.sqrt(se2 + 1e-30)


def z_against_reference(est: np.ndarray, ref_chunks: np.ndarray, floor: float) -> np.ndarray:
    """Per-pixel z of the mean of ``est`` (seeds) against the reference chunks' mean.

    ``floor`` is an absolute standard-error floor: a pixel whose rare contributions (a silhouette hit by a few
    samples in a thousand) never showed up in the G-PT seeds has a sample variance of 0, not a true one of 0.
    """
    se2 = est.var(0, ddof=1) / est.shape[0] + ref_chunks.var(0, ddof=1) / ref_chunks.shape[0]
    return (est.mean(0) - ref_chunks.mean(0)) / np.sqrt(se2 + floor**2)


def assert_matches_reference(est: np.ndarray, ref_chunks: np.ndarray, floor: float, what: str,
                             max_z2: float = 2.0) -> None:
    """Seeds of an estimate against reference chunks: per-pixel z statistics plus an aggregate scale check.

    The per-pixel checks catch localized bias (a wrong weight at silhouettes); the scale check catches a bias
    spread thinly over the whole image (a missing factor on one kind of contribution), which per-pixel noise
    would hide: over the pixels whose reference value is clearly nonzero, sum(est * sign(ref)) / sum(|ref|)
    must be 1 within a few standard errors.
    """
    z = z_against_reference(est, ref_chunks, floor)
    assert np.mean(z**2) < max_z2, f"{what}: mean z^2 {np.mean(z**2):.2f}"
    assert np.mean(np.abs(z) > Z_MAX) < 0.01, f"{what}: {np.mean(np.abs(z) > Z_MAX):.2%} pixels beyond {Z_MAX} sigma"
    ref = ref_chunks.mean(0)
    ref_se = np.sqrt(ref_chunks.var(0, ddof=1) / ref_chunks.shape[0])
    signed = np.abs(ref) > 6 * ref_se + floor
    # Small references (a 4x4 room has 12 gradient pixels) used to skip this check silently. It is valid at any
    # pixel count once the reference's own noise is in the standard error (the chunks give it the same way the
    # seeds give the estimate's), so it always runs; only a reference with no clearly nonzero pixel is refused.
    assert signed.any(), f"{what}: no reference pixel is clearly nonzero; the scale check cannot run"
    sign = np.sign(ref[signed])
    norm = np.abs(ref[signed]).sum()
    per_seed = (est[:, signed] * sign).sum(axis=1) / norm
    per_chunk = (ref_chunks[:, signed] * sign).sum(axis=1) / norm
    scale = per_seed.mean() / per_chunk.mean()
    se = np.sqrt(per_seed.var(ddof=1) / len(per_seed) + per_chunk.var(ddof=1) / len(per_chunk))
    assert abs(scale - 1) < 4 * se + 0.03, f"{what}: scaled by {scale:.3f} +- {se:.3f} against the reference"


# ---------------------------------------------------------------------------------------------------------------
# Primal: direct + indirect = Mitsuba's path
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["cbox", "teapot", "sky"])
def test_total_mean_matches_path(scene, request):
    r: Renders = request.getfixturevalue(scene)
    depth = max(r.ref)
    ours = r.total("base").mean(axis=(1, 2))  # per-seed image means (SEEDS, 3)
    theirs = r.low[depth].mean(axis=(1, 2))
    z = two_sample_z(ours, theirs)
    assert np.all(np.abs(z) < 4.5), f"image mean differs from path: z={z}, ours={ours.mean(0)}, path={theirs.mean(0)}"


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["cbox", "teapot", "sky"])
def test_direct_layer_matches_path_depth_2(scene, request):
    r: Renders = request.getfixturevalue(scene)
    z = two_sample_z(r.base["direct"].mean(axis=(1, 2)), r.low[2].mean(axis=(1, 2)))
    assert np.all(np.abs(z) < 4.5), f"direct layer mean differs from path max_depth=2: z={z}"
    # and pixel by pixel against the high-spp reference
    zp = z_against_reference(r.base["direct"], r.ref[2], floor=1e-3)
    assert np.mean(np.abs(zp) > Z_MAX) < 0.01


@pytest.mark.slow
def test_indirect_layer_is_the_rest(cbox):
    """indirect = path(max_depth 6) - path(max_depth 2) in expectation, and clearly nonzero in the cbox."""
    ind = cbox.base["indirect"].mean(axis=(1, 2))
    rest = (cbox.low[6] - cbox.low[2]).mean(axis=(1, 2))
    assert np.all(np.abs(two_sample_z(ind, rest)) < 4.5)
    assert ind.mean() > 0.02


@pytest.mark.slow
def test_pixels_match_high_spp_reference_teapot(teapot):
    """Per pixel (teapot: no caustics, so per-pixel errors are close to Gaussian at this sample count)."""
    z = z_against_reference(teapot.total("base"), teapot.ref[4], floor=1e-3)
    assert np.mean(z**2) < 2.0
    assert np.mean(np.abs(z) > Z_MAX) < 0.01


# ---------------------------------------------------------------------------------------------------------------
# Gradients: unbiased (converge to finite differences of the reference) and better than finite differences
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("shift", SHIFTS)
@pytest.mark.parametrize("scene", ["cbox", "teapot", "sky"])
@pytest.mark.parametrize("axis", ["dx", "dy"])
def test_gradients_converge_to_reference_differences(scene, axis, shift):
    r = make_renders(scene, shift)
    depth = max(r.ref)
    fd = fd_x if axis == "dx" else fd_y
    assert_matches_reference(r.total(axis), fd(r.ref[depth]), 2e-3, f"{scene} {axis}")


@pytest.mark.slow
@pytest.mark.parametrize("offsets", ["pair", "single", "alternate"])
@pytest.mark.parametrize("scene", ["cbox", "teapot", "sky"])
@pytest.mark.parametrize("axis", ["dx", "dy"])
def test_fewer_offsets_per_sample_converge_to_reference_differences(scene, axis, offsets):
    """Tracing one axis's two offsets (or one offset) per sample, chosen per sample and counted with its inverse
    probability (GptSettings.offsets), is unbiased too, with the hybrid shift; each layer against its own
    reference on the cbox."""
    r = make_renders(scene, "hybrid", offsets)
    depth = max(r.ref)
    fd = fd_x if axis == "dx" else fd_y
    assert_matches_reference(r.total(axis), fd(r.ref[depth]), 2e-3, f"{scene} {axis} {offsets}")
    if scene == "cbox":
        est = r.dx if axis == "dx" else r.dy
        assert_matches_reference(est["direct"], fd(r.ref[2]), 2e-3, f"direct {axis} {offsets}")
        assert_matches_reference(est["indirect"], fd(r.ref[6] - r.ref[2]), 2e-3, f"indirect {axis} {offsets}")


@pytest.mark.slow
@pytest.mark.parametrize("offsets", ["pair", "single", "alternate"])
def test_fewer_offsets_keep_the_primal_and_count_gradients_at_any_spp(offsets):
    """The primal is the base paths alone, bit for bit the same whichever offsets are traced; at an odd sample
    count (stratified and unstratified samples, groups of unequal size within a pixel) the gradients of the
    coarse mixed room still match the reference, for replay and the hybrid shift."""
    sky = make_renders("sky", "hybrid", offsets)
    full = make_renders("sky", "hybrid")
    for layer in sky.base:
        np.testing.assert_array_equal(sky.base[layer], full.base[layer])
    scene = coarse_room(8, "mixed")
    ref = np.stack([path_render(scene, 4096, 30_000 + i, 4) for i in range(REF_CHUNKS)])
    for shift in SHIFTS:
        results = [render_gpt(scene, make_shift(shift), GptSettings(max_depth=4, offsets=offsets), Film(8, 8, 67, seed))
                   for seed in range(SEEDS)]
        for key, fd in (("dx", fd_x), ("dy", fd_y)):
            est = np.stack([sum(r.layers[layer][key] for layer in r.layers) for r in results]).astype(np.float64)
            assert_matches_reference(est, fd(ref), 2e-3, f"coarse mixed {shift} {offsets} {key}")


@pytest.mark.slow
@pytest.mark.parametrize(("scene_name", "shift", "offsets"), [
    ("cbox", "hybrid", "all"), ("cbox", "replay", "all"), ("sky", "hybrid", "all"), ("cbox", "hybrid", "pair"),
    ("cbox", "hybrid", "alternate"), ("teapot", "hybrid", "all")])
def test_direct_gradients_mode_is_the_full_renders_direct_layer(scene_name, shift, offsets):
    """GptSettings(gradients="direct") traces the offsets only to the direct layer's vertices: its direct layer
    (base and gradients) is the ``all`` render's with the same seed, bit for bit up to rounding; its indirect
    layer carries no gradients and is the primal-only render's; the features are unchanged. (The teapot, lit by
    point lights at depth 4, is the case where the offsets stop after the first vertex.)"""
    scene, depth = load_test_scene(scene_name), SCENE_DEPTHS[scene_name]
    for seed in (0, 7):
        film = Film(SIZE, SIZE, 5, seed)
        full = render_gpt(scene, make_shift(shift), GptSettings(max_depth=depth, offsets=offsets), film)
        direct = render_gpt(scene, make_shift(shift), GptSettings(max_depth=depth, offsets=offsets,
                                                                   gradients="direct"), film)
        primal = render_gpt(scene, None, GptSettings(max_depth=depth), film)
        assert set(direct.layers["direct"]) == {"base", "var", "dx", "dy"}
        assert set(direct.layers["indirect"]) == {"base", "var"}
        assert np.abs(full.layers["direct"]["dx"]).max() > 0
        for key in ("base", "var", "dx", "dy"):
            np.testing.assert_allclose(direct.layers["direct"][key], full.layers["direct"][key], rtol=1e-6,
                                       atol=1e-7, err_msg=f"direct {key}")
        np.testing.assert_allclose(direct.layers["indirect"]["base"], primal.layers["indirect"]["base"], rtol=1e-6,
                                   atol=1e-7)
        np.testing.assert_allclose(direct.layers["indirect"]["base"], full.layers["indirect"]["base"], rtol=1e-6,
                                   atol=1e-7)
        for key in ("albedo", "normal", "depth"):
            np.testing.assert_array_equal(getattr(direct, key), getattr(full, key), err_msg=key)


@pytest.mark.slow
@pytest.mark.parametrize("offsets", ["all", "alternate"])
def test_direct_gradients_mode_leaves_out_the_manifold_solve(monkeypatch, offsets):
    """``--gradients direct`` runs the hybrid shift without its manifold solve (HybridShift.for_direct_layer): a
    mirror at x_1 would be solved at x_2, past the mode's vertices. The frame is bit for bit the one of the full
    shift (the cbox's mirror ball is seen directly and reflects the lamp), and the solve is not even traced
    (power: with the full shift it is)."""
    import gradsep.renderer.manifold as manifold

    scene = load_test_scene("cbox")
    settings = GptSettings(max_depth=SCENE_DEPTHS["cbox"], gradients="direct", offsets=offsets)
    solves = []
    solve = manifold.solve_mirror
    monkeypatch.setattr(manifold, "solve_mirror", lambda *a: solves.append(1) or solve(*a))

    def render(leave_out: bool):
        if not leave_out:  # the full shift: render_gpt hands the mode the shift itself
            monkeypatch.setattr(HybridShift, "for_direct_layer", lambda self: self)
        solves.clear()
        result = render_gpt(scene, make_shift("hybrid"), settings, Film(SIZE, SIZE, 5, 3))
        return result, len(solves)

    (lean, lean_solves), (full, full_solves) = render(True), render(False)
    assert lean_solves == 0 and full_solves > 0
    for layer, images in lean.layers.items():
        for key, image in images.items():
            np.testing.assert_array_equal(image, full.layers[layer][key], err_msg=f"{layer} {key}")
    for key in ("albedo", "normal", "depth"):
        np.testing.assert_array_equal(getattr(lean, key), getattr(full, key), err_msg=key)
    assert np.abs(lean.layers["direct"]["dx"]).max() > 0


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["cbox", "sky"])
@pytest.mark.parametrize("axis", ["dx", "dy"])
def test_direct_gradients_mode_is_unbiased(scene, axis):
    """The direct layer's gradients against finite differences of the depth-2 reference; both layers' energy
    against `path` (the total at the scene's depth, the direct layer at depth 2, indirect = the rest)."""
    r = make_renders(scene, "hybrid", gradients="direct")
    depth = max(r.ref)
    fd = fd_x if axis == "dx" else fd_y
    assert set(getattr(r, axis)) == {"direct"}
    assert_matches_reference(getattr(r, axis)["direct"], fd(r.ref[2]), 2e-3, f"{scene} direct {axis}")
    z = two_sample_z(r.total("base").mean(axis=(1, 2)), r.low[depth].mean(axis=(1, 2)))
    assert np.all(np.abs(z) < 4.5), f"{scene}: image mean differs from path: z={z}"
    z = two_sample_z(r.base["direct"].mean(axis=(1, 2)), r.low[2].mean(axis=(1, 2)))
    assert np.all(np.abs(z) < 4.5), f"{scene}: direct layer mean differs from path at depth 2: z={z}"
    rest = (r.low[depth] - r.low[2]).mean(axis=(1, 2))
    assert np.all(np.abs(two_sample_z(r.base["indirect"].mean(axis=(1, 2)), rest)) < 4.5)


def test_gradients_mode_is_validated():
    with pytest.raises(ValueError, match="unknown gradients mode"):
        GptSettings(gradients="indirect").validate()
    with pytest.raises(ValueError, match="direct layer"):
        GptSettings(gradients="direct", separate=False).validate()
    with pytest.raises(ValueError, match="direct layer"):
        GptSettings(gradients="direct", direct=False).validate()
    assert GptSettings(gradients="direct").gradient_layer_names() == ("direct",)
    assert GptSettings().gradient_layer_names() == ("direct", "indirect")
    with pytest.raises(CommandError, match="--gradients must be one of"):
        render_frame(CBOX, spp=1, gradients="sometimes", options=FrameOptions(width=4, height=4))


def test_alternate_offsets_trace_two_offsets_and_keep_the_primal():
    """Each lane traces one offset per axis (both axes get gradients), and the primal is bit for bit the `all`
    render's: the offsets never touch the base path or its random numbers."""
    scene = load_scene(CBOX, width=12, height=10).scene
    full = render_gpt(scene, make_shift("hybrid"), GptSettings(max_depth=4), Film(12, 10, 4, 5))
    alt = render_gpt(scene, make_shift("hybrid"), GptSettings(max_depth=4, offsets="alternate"), Film(12, 10, 4, 5))
    for layer, images in alt.layers.items():
        np.testing.assert_array_equal(images["base"], full.layers[layer]["base"])
        for key in ("dx", "dy"):
            assert np.all(np.isfinite(images[key])) and np.abs(images[key][:, :-1] if key == "dx"
                                                                 else images[key][:-1]).max() > 0, (layer, key)
        assert np.all(images["dx"][:, -1] == 0) and np.all(images["dy"][-1] == 0)


def test_offsets_mode_is_validated():
    with pytest.raises(ValueError, match="offsets mode"):
        GptSettings(offsets="three").validate()


@pytest.mark.slow
@pytest.mark.parametrize("shift", SHIFTS)
@pytest.mark.parametrize("axis", ["dx", "dy"])
def test_layer_gradients_converge_to_layer_references(axis, shift):
    """Each layer's gradients against the differences of its own reference: path(2) and path(6) - path(2)."""
    cbox = make_renders("cbox", shift)
    fd = fd_x if axis == "dx" else fd_y
    est = cbox.dx if axis == "dx" else cbox.dy
    assert_matches_reference(est["direct"], fd(cbox.ref[2]), 2e-3, f"direct {axis}")
    assert_matches_reference(est["indirect"], fd(cbox.ref[6] - cbox.ref[2]), 2e-3, f"indirect {axis}")


@pytest.mark.slow
@pytest.mark.parametrize("shift", SHIFTS)
def test_russian_roulette_keeps_everything_unbiased(cbox, shift):
    """Russian roulette from the second vertex on (decided on the base path, applied to the whole lane)."""
    scene = load_test_scene("cbox")
    results = [render_gpt(scene, make_shift(shift), GptSettings(max_depth=6, rr_depth=1), Film(SIZE, SIZE, SPP, seed))
               for seed in range(100, 100 + SEEDS)]
    indirect = cbox.ref[6] - cbox.ref[2]
    # The cbox's caustics (light reaching walls via the mirror and glass spheres, found by BSDF sampling alone)
    # make per-pixel primal errors heavy-tailed at this sample count, so the per-pixel z^2 of the primal is
    # held to what Mitsuba's own `path` reaches against the same reference with the same sample count.
    baseline = np.mean(z_against_reference(cbox.low[6] - cbox.low[2], indirect, 1e-3) ** 2)
    for key, fd, floor in (("base", lambda a: a, 1e-3), ("dx", fd_x, 2e-3), ("dy", fd_y, 2e-3)):
        est = np.stack([r.layers["indirect"][key] for r in results]).astype(np.float64)
        assert_matches_reference(est, fd(indirect), floor, f"indirect {key} with roulette",
                                 max_z2=max(2.0, 1.5 * baseline) if key == "base" else 2.0)


@pytest.mark.slow
@pytest.mark.parametrize("offsets", ["all", "pair", "alternate"])
@pytest.mark.parametrize("scene_name", ["cbox", "specular"])
@pytest.mark.parametrize("shift", SHIFTS)
def test_offsets_on_the_base_pixel_give_zero_gradients(monkeypatch, shift, scene_name, offsets):
    """With all four pixel shifts set to (0, 0), every offset path *is* its base path, so every gradient sample
    must vanish -- at every depth, through mirrors and glass, with Russian roulette from the second vertex on.
    Any asymmetry between how the lane treats base and offsets (random numbers, roulette weights, termination,
    event routing, a Jacobian or MIS ratio that is not 1 for coinciding paths) shows up as a nonzero gradient.
    Replay is exact; the hybrid shift recomputes reconnection directions and may differ by rounding, and its
    manifold reconnection through a mirror solves for the mirror point to ~1e-6 of the path length, which near
    focusing configurations (tiny footprints) leaves Jacobians off by up to ~1e-3 (gradients ~1e-4)."""
    import gradsep.renderer.gpt_loop as gpt_loop
    import gradsep.renderer.lanes as lanes

    for module in (gpt_loop, lanes):  # where the pixel shifts are read: every lane's, and a group's
        monkeypatch.setattr(module, "SHIFT_OFFSETS", ((0, 0),) * 4)
    scene = load_scene(CBOX, width=16, height=16).scene if scene_name == "cbox" else coarse_room(16, "specular")
    settings = GptSettings(max_depth=-1, rr_depth=1, offsets=offsets)
    res = render_gpt(scene, make_shift(shift), settings, Film(16, 16, 4, 7))
    tolerance = 0.0 if shift == "replay" else 2e-4
    for layer in ("direct", "indirect"):
        base = res.layers[layer]["base"]
        assert base.mean() > 0
        for key in ("dx", "dy"):
            assert np.all(np.abs(res.layers[layer][key]) <= tolerance * (1.0 + base)), (layer, key)


@pytest.mark.slow
def test_primal_does_not_depend_on_the_shift():
    replay, hybrid = make_renders("sky", "replay"), make_renders("sky", "hybrid")
    for layer in replay.base:
        np.testing.assert_allclose(hybrid.base[layer], replay.base[layer], rtol=1e-6, atol=1e-7)


def diffuse_room_dict() -> dict:
    """A closed diffuse room (open towards the camera) with a ceiling lamp and a ball."""
    tf = mi.ScalarTransform4f

    def wall(to_world, rgb: list[float]) -> dict:
        return {"type": "rectangle", "to_world": to_world,
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}}

    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": tf().look_at(origin=[0, 0, 3.2], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "rfilter": {"type": "box"}}},
        "floor": wall(tf().translate([0, -1, 0]).rotate([1, 0, 0], -90), [0.7, 0.7, 0.7]),
        "ceiling": wall(tf().translate([0, 1, 0]).rotate([1, 0, 0], 90), [0.7, 0.7, 0.7]),
        "back": wall(tf().translate([0, 0, -1]), [0.7, 0.7, 0.7]),
        "left": wall(tf().translate([-1, 0, 0]).rotate([0, 1, 0], 90), [0.7, 0.2, 0.2]),
        "right": wall(tf().translate([1, 0, 0]).rotate([0, 1, 0], -90), [0.2, 0.7, 0.2]),
        "ball": {"type": "sphere", "center": [0.3, -0.6, 0.1], "radius": 0.4, "bsdf": {"type": "diffuse"}},
        "lamp": {"type": "rectangle", "to_world": tf().translate([0, 0.99, 0]).rotate([1, 0, 0], 90).scale(0.25),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [15, 15, 15]}}},
    }


MATERIAL_SETS = ("diffuse", "mixed", "glossy", "specular")

# Shift variants: the two shifts, and the hybrid shift as the --gradients direct mode runs it (no manifold
# reconnection: offsets follow at curved mirrors instead), which must be unbiased at every depth too.
VARIANTS = {
    "replay": ReplayShift,
    "hybrid": HybridShift,
    "hybrid-no-manifold": lambda: HybridShift(manifold=False),
}


def coarse_room(size: int, materials: str = "mixed"):
    """The diffuse room at a handful of pixels: neighbouring pixels see distant points, so reconnection Jacobians
    are far from 1 and shifts often fail or switch strategy -- the place where a wrong Jacobian, density ratio
    or invertibility check shows up as bias.

    ``mixed`` adds a mirror ball, a diffuse base under a smooth coating (a delta and a non-delta lobe at one
    vertex) on the floor and ball, and a glossy metal; ``glossy`` has narrow and medium glossy lobes in
    reflection and refraction next to the mirror (a rough plastic floor, a rough glass ball, a narrow rough
    metal), which is where the half-vector copy works; ``specular`` has delta-only vertices of every kind the
    shift tells apart: a mirror ball and a glass ball (curved: offsets move onto their vertices, or replay where
    the segment is short), a flat mirror panel (replay), and a thin-dielectric tube (a null lobe: replay)."""
    select_variant()
    scene = diffuse_room_dict()
    scene["sensor"]["film"]["width"] = scene["sensor"]["film"]["height"] = size
    if materials != "diffuse":
        scene["mirror"] = {"type": "sphere", "center": [-0.45, -0.65, -0.3], "radius": 0.35,
                           "bsdf": {"type": "conductor"}}
    if materials == "mixed":
        scene["ball"]["bsdf"] = {"type": "plastic"}
        scene["floor"]["bsdf"] = {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}
        scene["metal"] = {"type": "sphere", "center": [-0.4, 0.4, -0.5], "radius": 0.25,
                          "bsdf": {"type": "roughconductor", "alpha": 0.15}}
    elif materials == "specular":
        scene["ball"]["bsdf"] = {"type": "dielectric", "int_ior": 1.5}
        scene["mirror"]["bsdf"] = {"type": "conductor", "material": "Au"}  # reflectance varies with the angle
        tf = mi.ScalarTransform4f
        scene["panel"] = {"type": "rectangle", "bsdf": {"type": "conductor"},
                          "to_world": tf().translate([0.55, 0.3, -0.6]).rotate([0, 1, 0], -35).scale(0.3)}
        scene["tube"] = {"type": "cylinder", "p0": [-0.2, 0.2, -0.2], "p1": [0.3, 0.6, -0.4], "radius": 0.15,
                         "bsdf": {"type": "thindielectric", "int_ior": 1.5}}
    elif materials == "glossy":
        scene["ball"]["bsdf"] = {"type": "roughdielectric", "alpha": 0.12, "int_ior": 1.5}
        scene["floor"]["bsdf"] = {"type": "roughplastic", "alpha": 0.06,
                                  "diffuse_reflectance": {"type": "rgb", "value": [0.4, 0.4, 0.4]}}
        scene["metal"] = {"type": "sphere", "center": [-0.4, 0.4, -0.5], "radius": 0.25,
                          "bsdf": {"type": "roughconductor", "alpha": 0.04}}
    return mi.load_dict(scene)


@pytest.mark.slow
@pytest.mark.parametrize(("materials", "variant"), [
    ("mixed", "replay"), ("mixed", "hybrid"), ("glossy", "replay"), ("glossy", "hybrid"),
    ("specular", "replay"), ("specular", "hybrid"), ("specular", "hybrid-no-manifold"),
])
def test_gradients_unbiased_at_coarse_resolution(materials, variant):
    scene = coarse_room(8, materials)
    ref = np.stack([path_render(scene, 4096, 30_000 + i, 4) for i in range(REF_CHUNKS)])
    results = [render_gpt(scene, VARIANTS[variant](), GptSettings(max_depth=4), Film(8, 8, 64, seed))
               for seed in range(SEEDS)]
    for key, fd in (("dx", fd_x), ("dy", fd_y)):
        est = np.stack([sum(r.layers[layer][key] for layer in r.layers) for r in results]).astype(np.float64)
        assert_matches_reference(est, fd(ref), 2e-3, f"coarse {materials} {variant} {key}")


_converged: dict[tuple[str, str], dict[str, np.ndarray]] = {}


def converged_gradients(materials: str, shift: str) -> dict[str, np.ndarray]:
    """dx, dy of the 4x4 coarse room at 16k spp over 8 seeds (cached per worker: replay serves several tests)."""
    if (materials, shift) not in _converged:
        scene = coarse_room(4, materials)
        runs = [render_gpt(scene, VARIANTS[shift](), GptSettings(max_depth=3), Film(4, 4, 16384, seed))
                for seed in range(8)]
        _converged[materials, shift] = {key: np.stack([sum(r.layers[layer][key] for layer in r.layers) for r in runs])
                                        .astype(np.float64) for key in ("dx", "dy")}
    return _converged[materials, shift]


@pytest.mark.slow
@pytest.mark.parametrize(("materials", "variant"), [
    ("diffuse", "hybrid"), ("mixed", "hybrid"), ("glossy", "hybrid"), ("specular", "hybrid"),
    ("specular", "hybrid-no-manifold"),
])
def test_both_shifts_estimate_the_same_gradients(materials, variant):
    """Two unbiased estimators of the same pixel differences must agree: 4x4 pixels at 16k samples each, so
    even a bias of a few percent of one pixel pair's difference stands out. The all-diffuse room has the least
    noise; the mixed one adds a mirror, a coated (delta + diffuse) floor and ball, and a glossy metal; the
    glossy one narrow glossy reflection and rough glass beside the mirror (half-vector copies)."""
    estimates = {shift: converged_gradients(materials, shift) for shift in ("replay", variant)}
    for key in ("dx", "dy"):
        # A NaN/Inf estimate is a failure of its own (it used to be hidden by replacing non-finite z with 0)
        for shift, estimate in estimates.items():
            assert np.isfinite(estimate[key]).all(), f"{shift} {key}: non-finite gradient estimate"
        z = two_sample_z(estimates[variant][key], estimates["replay"][key])
        assert np.abs(z).max() < 5.0, f"{key}: shifts disagree, z =\n{np.round(z, 1)}"


# ---------------------------------------------------------------------------------------------------------------
# Float32 robustness: grazing angles and tiny triangles
# ---------------------------------------------------------------------------------------------------------------


def _mesh(name: str, vertices: np.ndarray, faces: np.ndarray, bsdf: dict):
    """A triangle mesh from numpy arrays (Mitsuba's documented way of building one in memory)."""
    props = mi.Properties()
    props["mesh_bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(name, len(vertices), len(faces), props=props)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    return mesh


def uv_sphere(center, radius: float, rings: int, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """A latitude/longitude sphere: its triangles shrink to slivers of ~1e-5 area at the poles."""
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3) * radius + center
    i, j = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return v, faces


def tiny_triangle_room(size: int):
    """The diffuse room with a ball of 100k triangles (slivers at the poles) and a cloud of 20k disconnected
    triangles 1e-4 to 3e-3 units across, a hundred of them degenerate (collinear): reconnections land on
    triangles far smaller than a pixel and than Mitsuba's ray epsilon."""
    select_variant()
    scene = diffuse_room_dict()
    scene["sensor"]["film"]["width"] = scene["sensor"]["film"]["height"] = size
    del scene["ball"]
    v, f = uv_sphere(np.array([0.3, -0.6, 0.1]), 0.4, 200, 250)
    scene["ball"] = _mesh("ball", v, f, {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.5, 0.3]}})
    rng = np.random.default_rng(0)
    n = 20_000
    centres = rng.uniform([-0.9, -0.95, -0.9], [0.9, 0.6, 0.6], (n, 3))
    tris = centres[:, None, :] + 10 ** rng.uniform(-4, -2.5, (n, 1, 1)) * rng.normal(size=(n, 3, 3))
    tris[:100, 2] = 0.5 * (tris[:100, 0] + tris[:100, 1])
    scene["dust"] = _mesh("dust", tris.reshape(-1, 3), np.arange(3 * n).reshape(n, 3), {"type": "diffuse"})
    return mi.load_dict(scene)


def grazing_scene(size: int):
    """A camera 2 cm above a large floor looking along it, a tall lamp standing on the floor and a ball: the
    floor is seen, reconnected to and lit at grazing angles (cosines down to ~1e-3)."""
    select_variant()
    tf = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": tf().look_at(origin=[0, 0.02, 6], target=[0, 0.0, -1], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.05, 0.06, 0.08]}},
        "floor": {"type": "rectangle", "to_world": tf().rotate([1, 0, 0], -90).scale(30),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}},
        "ball": {"type": "sphere", "center": [-0.6, 0.3, 0], "radius": 0.3, "bsdf": {"type": "diffuse"}},
        "lamp": {"type": "rectangle", "to_world": tf().translate([0.8, 0.5, -1.0]).scale([0.4, 0.5, 1]),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [12, 10, 8]}}},
    })


ROBUSTNESS_SCENES = {"grazing": grazing_scene, "tiny": tiny_triangle_room}


@pytest.mark.slow
@pytest.mark.parametrize("name", ["grazing", "tiny"])
def test_gradients_unbiased_on_grazing_and_tiny_geometry(name):
    scene = ROBUSTNESS_SCENES[name](8)
    ref = np.stack([path_render(scene, 4096, 40_000 + i, 4) for i in range(REF_CHUNKS)])
    for shift in ("replay", "hybrid"):
        results = [render_gpt(scene, VARIANTS[shift](), GptSettings(max_depth=4), Film(8, 8, 64, seed))
                   for seed in range(SEEDS)]
        assert all(r.invalid_samples == 0 for r in results)
        for key, fd in (("dx", fd_x), ("dy", fd_y)):
            est = np.stack([sum(r.layers[layer][key] for layer in r.layers) for r in results]).astype(np.float64)
            assert_matches_reference(est, fd(ref), 2e-3, f"{name} {shift} {key}")


@pytest.mark.slow
@pytest.mark.parametrize("shift", SHIFTS)
@pytest.mark.parametrize("axis", ["dx", "dy"])
def test_gradients_beat_finite_differences_of_primal(axis, shift):
    """At equal spp (one render each), G-PT's gradient error is well below that of differencing its primal."""
    cbox = make_renders("cbox", shift)
    fd = fd_x if axis == "dx" else fd_y
    ref = fd(cbox.ref[6]).mean(0)
    err_gpt = np.abs(cbox.total(axis) - ref)
    err_fd = np.abs(fd(cbox.total("base")) - ref)
    ratio = np.median(err_fd) / np.median(err_gpt)
    assert ratio > 1.5, f"median error ratio FD/G-PT {ratio:.2f}"
    assert err_gpt.mean() < err_fd.mean()


@pytest.mark.slow
def test_contract_borders_are_zero(cbox):
    assert np.all(cbox.total("dx")[:, :, -1, :] == 0)
    assert np.all(cbox.total("dy")[:, -1, :, :] == 0)


# ---------------------------------------------------------------------------------------------------------------
# Features
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["cbox", "teapot"])
def test_features_are_valid(scene, request):
    for res in request.getfixturevalue(scene).features[:2]:
        for arr in (res.albedo, res.normal, res.depth):
            assert np.all(np.isfinite(arr))
        assert res.albedo.min() >= 0 and res.albedo.max() <= 1
        np.testing.assert_allclose(np.linalg.norm(res.normal, axis=-1), 1.0, atol=1e-4)
        assert res.depth.min() >= 0


@pytest.mark.slow
def test_features_follow_the_cbox_geometry(cbox):
    """Features against the Cornell box fixture's geometry (tests/renderer/scenes.py owns the numbers)."""
    g = CBOX_GEOMETRY
    res = cbox.features[0]
    c = SIZE // 2
    # The centre pixel looks at the back wall head on.
    assert abs(res.depth[c, c] - (g.camera_z - g.back_wall_z)) < 0.05
    np.testing.assert_allclose(res.normal[c, c], [0, 0, 1], atol=1e-3)
    np.testing.assert_allclose(res.albedo[c, c], g.white, atol=1e-3)
    # The mirror sphere faces the open front of the box: the chain through it leaves the scene, so its central
    # pixels have no feature vertex (depth 0), not the sphere's depth. The glass sphere: the chain passes through
    # to what lies behind it.
    focal = (SIZE / 2) / np.tan(np.radians(g.fov_degrees / 2))

    def pixel(x: float, y: float, z: float) -> tuple[int, int]:
        dist = g.camera_z - z
        return int(SIZE / 2 + focal * x / dist), int(SIZE / 2 - focal * y / dist)

    mx, my = pixel(*g.mirror_sphere[0])
    assert res.depth[my, mx] == 0.0
    (gx, gy), (centre, radius) = pixel(*g.glass_sphere[0]), g.glass_sphere
    assert res.depth[gy, gx] > g.camera_z - centre[2] + radius


@pytest.mark.slow
def test_teapot_background_has_no_depth(teapot):
    res = teapot.features[0]
    assert res.depth[0, 0] == 0 and np.all(res.albedo[0, 0] == 0)
    hit = res.depth > 0
    assert 0.05 < hit.mean() < 0.9
    assert np.all((res.depth[hit] > 9) & (res.depth[hit] < 16))  # camera ~13 units from the teapot


# ---------------------------------------------------------------------------------------------------------------
# Layers, depth limits, frames, command
# ---------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cbox_small():
    return load_scene(CBOX, width=16, height=12)


@pytest.mark.slow
def test_direct_only_render_equals_full_direct_layer(cbox_small):
    """--layers direct traces only to the first vertex and gives exactly the full render's direct layer."""
    full = render_frame(cbox_small, spp=4, seed=3)
    direct = render_frame(cbox_small, spp=4, seed=3, layers="direct")
    assert list(direct.layers) == ["direct"]
    assert list(full.layers) == ["direct", "indirect"]
    for key in ("base", "dx", "dy"):
        np.testing.assert_allclose(getattr(direct.layers["direct"], key), getattr(full.layers["direct"], key),
                                   rtol=1e-5, atol=1e-6)


def test_max_depth_2_has_no_indirect_layer(cbox_small):
    frame = render_frame(cbox_small, spp=2, options=FrameOptions(max_depth=2))
    assert list(frame.layers) == ["direct"]
    assert any("indirect" in w for w in frame.warnings)
    with pytest.raises(CommandError):
        render_frame(cbox_small, spp=2, layers="indirect", options=FrameOptions(max_depth=2))


def test_max_depth_1_is_emitters_seen_directly(cbox_small):
    frame = render_frame(cbox_small, spp=2, options=FrameOptions(max_depth=1))
    base = frame.layers["direct"].base
    lit = base.max(axis=-1) > 0
    assert 0 < lit.mean() < 0.2  # only the light
    # each pixel is the light's radiance times the fraction of its 2 samples that hit it: 0, 1/2 or 1
    fraction = base[lit] / np.array([18.387, 13.9873, 6.75357], dtype=np.float32)
    np.testing.assert_allclose(fraction, np.round(fraction * 2) / 2, atol=1e-4)


@pytest.mark.slow
def test_seeds_are_reproducible_and_distinct(cbox_small):
    a = render_frame(cbox_small, spp=2, seed=5, layers="direct")
    b = render_frame(cbox_small, spp=2, seed=5, layers="direct")
    c = render_frame(cbox_small, spp=2, seed=6, layers="direct")
    np.testing.assert_array_equal(a.layers["direct"].base, b.layers["direct"].base)
    assert not np.array_equal(a.layers["direct"].base, c.layers["direct"].base)


@pytest.mark.slow
def test_passes_give_the_same_estimator(cbox_small):
    """Splitting samples into passes (3 + 3 + 2 here) changes the random streams, not the expectation."""
    settings = GptSettings(indirect=False)
    one, many = [], []
    for seed in range(8):
        a = render_gpt(cbox_small.scene, ReplayShift(), settings, Film(16, 12, 8, seed))
        b = render_gpt(cbox_small.scene, ReplayShift(), settings, Film(16, 12, 8, seed), max_lanes=16 * 12 * 3)
        assert a.passes == 1 and b.passes == 3
        one.append(a.layers["direct"]["base"].mean(axis=(0, 1)))
        many.append(b.layers["direct"]["base"].mean(axis=(0, 1)))
    assert np.all(np.abs(two_sample_z(np.array(one), np.array(many))) < 4.5)
    assert pass_plan(10, 10, 7, max_lanes=300) == [3, 3, 1]
    assert pass_plan(10, 10, 7, max_lanes=10) == [1] * 7


def test_default_pass_plan_renders_production_frames_in_few_passes():
    """Each pass re-records and re-reads the kernel (~0.5 s at 1280x720, docs/renderer.md "Lanes per pass"), while
    a lane's state costs no memory: a 1280x720 frame is one pass up to 72 spp, larger frames split evenly, and no
    pass reaches the UInt32 lane index's 2^32."""
    assert pass_plan(1280, 720, 16) == [16] and pass_plan(1280, 720, 72) == [72]
    assert pass_plan(1280, 720, 73) == [72, 1]
    assert pass_plan(1920, 1080, 64) == [32, 32]
    assert pass_plan(320, 240, 64) == [64]
    for w, h, spp in ((1280, 720, 4096), (7680, 4320, 3), (1, 1, 1 << 30)):
        plan = pass_plan(w, h, spp)
        assert sum(plan) == spp and max(plan) * w * h <= MAX_LANES_PER_PASS < 1 << 32


def test_frame_round_trips_through_the_contract(cbox_small, tmp_path):
    frame = render_frame(cbox_small, spp=2, seed=1)
    path = tmp_path / "f.exr"
    write_frame(path, frame)
    back = read_frame(path)
    assert list(back.layers) == ["direct", "indirect"]
    for name, layer in frame.layers.items():
        for key in ("base", "dx", "dy"):
            np.testing.assert_array_equal(getattr(back.layers[name], key), getattr(layer, key))
    np.testing.assert_array_equal(back.features.normal, frame.features.normal)
    np.testing.assert_array_equal(back.features.depth, frame.features.depth)
    for key in ("gradsep.spp", "gradsep.seed", "gradsep.scene", "gradsep.max_depth", "gradsep.shift",
                "gradsep.version", "gradsep.render_seconds"):
        assert key in back.metadata
    assert back.metadata["gradsep.spp"] == "2" and back.metadata["gradsep.shift"] == "hybrid"
    assert float(back.metadata["gradsep.render_seconds"]) > 0


@pytest.mark.slow
def test_procedural_frames_record_the_generator_version():
    pytest.importorskip("gradsep.renderer.procedural")
    from gradsep.renderer.procedural_builder import GENERATOR_VERSION

    frame = render_frame("procedural:5", spp=1, layers="direct", options=FrameOptions(width=8, height=6))
    assert frame.metadata["gradsep.procedural_version"] == str(GENERATOR_VERSION)
    assert frame.metadata["gradsep.scene"] == "procedural:5"


def test_layer_and_shift_arguments():
    assert parse_layers("indirect, direct") == ("direct", "indirect")
    with pytest.raises(CommandError, match="unknown layer"):
        parse_layers("direct,glossy")
    with pytest.raises(CommandError):
        parse_layers(" , ")
    assert plan_layers(("direct", "indirect"), -1) == (("direct", "indirect"), [])
    assert plan_layers(("direct", "indirect"), 2)[0] == ("direct",)
    assert make_shift(None).name == "hybrid"
    assert isinstance(make_shift("hybrid"), HybridShift) and isinstance(make_shift("replay"), ReplayShift)
    with pytest.raises(ValueError, match="unknown shift"):
        make_shift("manifold")


@pytest.mark.slow
@pytest.mark.parametrize("shift", [None, "replay"])
def test_render_command_end_to_end(tmp_path, capsys, shift):
    out = tmp_path / "t.exr"
    rc = main(["render", TEAPOT, "--spp", "2", "--width", "16", "--height", "12", "--seed", "4", "-o", str(out),
               *(["--shift", shift] if shift else [])])
    assert rc == 0
    frame = read_frame(out)
    assert (frame.width, frame.height) == (16, 12)
    assert list(frame.layers) == ["direct"]  # the teapot's own integrator is `direct`
    assert frame.metadata["gradsep.seed"] == "4"
    assert frame.metadata["gradsep.max_depth"] == "2"
    assert frame.metadata["gradsep.shift"] == (shift or "hybrid")


@pytest.mark.slow
def test_render_command_gradients_direct(tmp_path, capsys):
    """`--gradients direct`: a frame with the direct layer's gradients and a plain indirect layer, which the
    frame contract reads back; the metadata says which layers carry gradients."""
    out = tmp_path / "d.exr"
    rc = main(["render", CBOX, "--spp", "2", "--width", "16", "--height", "12", "--seed", "4",
               "--gradients", "direct", "-o", str(out)])
    assert rc == 0
    frame = read_frame(out)
    assert list(frame.layers) == ["direct", "indirect"] and frame.gradient_layers == ("direct",)
    assert frame.metadata["gradsep.gradients"] == "direct" and frame.metadata["gradsep.integrator"] == "gpt"
    full = render_frame(load_scene(CBOX, width=16, height=12), spp=2, seed=4)
    assert full.metadata["gradsep.gradients"] == "all"
    np.testing.assert_allclose(frame.layers["direct"].dx, full.layers["direct"].dx, rtol=1e-6, atol=1e-7)


def test_render_command_offsets(tmp_path):
    """`--offsets alternate`: the same channels as a full render (both layers' gradients), the same primal, and
    the mode in the metadata (absent for the default `all`); the command's choices are the renderer's modes."""
    from gradsep.renderer.lanes import OFFSET_MODES
    from gradsep.renderer.render import OFFSET_CHOICES

    assert OFFSET_CHOICES == OFFSET_MODES
    with pytest.raises(CommandError, match="--offsets must be one of"):
        render_frame(CBOX, spp=1, options=FrameOptions(offsets="three", width=4, height=4))
    out = tmp_path / "a.exr"
    rc = main(["render", CBOX, "--spp", "2", "--width", "10", "--height", "8", "--seed", "4", "--max-depth", "4",
               "--offsets", "alternate", "-o", str(out)])
    assert rc == 0
    frame = read_frame(out)
    assert frame.gradient_layers == ("direct", "indirect") and frame.metadata["gradsep.offsets"] == "alternate"
    full = render_frame(load_scene(CBOX, width=10, height=8, max_depth=4), spp=2, seed=4)
    assert "gradsep.offsets" not in full.metadata
    for layer in ("direct", "indirect"):
        np.testing.assert_array_equal(frame.layers[layer].base, full.layers[layer].base)
        assert np.abs(frame.layers[layer].dx).max() > 0


@pytest.mark.parametrize("argv, message", [
    (["--gradients", "direct", "--layers", "color"], "--gradients direct"),
    (["--gradients", "direct", "--layers", "indirect"], "--gradients direct"),
    (["--no-gradients", "--gradients", "all"], "--no-gradients"),
    (["--gradients", "none", "--shift", "replay"], "--shift"),
    (["--no-gradients", "--offsets", "alternate"], "--offsets"),
    (["--spp", "0"], "spp"),
    (["--layers", "glossy"], "unknown layer"),
    (["--max-depth", "0"], "max-depth"),
    (["-D", "nosuch=1"], "nosuch"),
])
def test_render_command_errors(tmp_path, capsys, argv, message):
    rc = main(["render", CBOX, "--width", "8", "--height", "8", "-o", str(tmp_path / "x.exr"),
               *(["--spp", "1"] if "--spp" not in argv else []), *argv])
    assert rc == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "x.exr").exists()


def test_render_command_refuses_bad_output(tmp_path, capsys):
    assert main(["render", CBOX, "--spp", "1", "-o", str(tmp_path / "x.png")]) == 2
    assert main(["render", CBOX, "--spp", "1", "-o", str(tmp_path / "missing" / "x.exr")]) == 2
