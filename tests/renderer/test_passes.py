"""A planned frame's render passes (renderer/passes.py): passes of one plan are render_gpt's bit for bit, passes of
several plans share the bases and keep their own gradients, and a split frame's halves make the frame."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model.frame import Frame, Layer
from gradsep.renderer.passes import Passes, crop, without_gradients
from gradsep.renderer.plans import plan_named
from tests.renderer.scenes import resolve

CBOX = str(resolve("cbox"))


def test_a_crop_and_a_plain_frame_keep_what_they_should():
    rng = np.random.default_rng(1)
    image = rng.random((6, 8, 3), dtype=np.float32)
    frame = Frame(layers={"direct": Layer(image, image + 1, image + 2, image[..., 0])})
    cut = crop(frame, (slice(1, 4), slice(2, 7)))
    layer = cut.layers["direct"]
    assert layer.base.shape == (3, 5, 3) and layer.base.flags.c_contiguous
    np.testing.assert_array_equal(layer.dy, image[1:4, 2:7] + 2)
    plain = without_gradients(frame).layers["direct"]
    assert not plain.has_gradients and plain.var is frame.layers["direct"].var and plain.base is image


mi = pytest.importorskip("mitsuba")


@pytest.mark.render
def test_passes_of_one_plan_are_render_gpt_bit_for_bit(small):
    from gradsep.renderer.gpt import render_gpt
    from gradsep.renderer.gpt_settings import Film, GptSettings
    from gradsep.renderer.shift import make_shift

    passes = Passes(small, ("direct", "indirect"), seed=5)
    passes.run(plan_named("all"), 3)
    mine = passes.frame_result(plan_named("all"))
    ref = render_gpt(small.scene, make_shift("hybrid"), GptSettings(max_depth=5), Film(16, 12, 3, 5))
    for layer in ("direct", "indirect"):
        for key in ("base", "dx", "dy"):
            np.testing.assert_array_equal(mine.layers[layer][key], ref.layers[layer][key])
    np.testing.assert_array_equal(mine.albedo, ref.albedo)


@pytest.mark.render
def test_passes_of_several_plans_share_bases_and_keep_their_own_gradients(small):
    passes = Passes(small, ("direct", "indirect"), seed=1)
    primal = passes.run(plan_named("primal"), 2)
    kept = {k: v.copy() for k, v in primal.items()}
    direct = passes.run(plan_named("direct-alternate"), 1)
    full = passes.run(plan_named("all"), 3)
    assert passes.spp == 6 and passes.index == 3
    for k, v in kept.items():  # the frame's sums are added in place, never into a pass's own
        np.testing.assert_array_equal(primal[k], v)
    r = passes.frame_result(plan_named("all"))
    expected = (primal["direct.base"] + direct["direct.base"] + full["direct.base"]) / 6
    np.testing.assert_allclose(r.layers["direct"]["base"], expected.astype(np.float32), rtol=1e-6)
    assert passes.gradients["all"][1] == 3 and passes.gradients["direct-alternate"][1] == 1
    assert "dx" in r.layers["indirect"]  # from the all passes alone
    d = passes.frame_result(plan_named("direct-alternate"))
    assert "dx" in d.layers["direct"] and "dx" not in d.layers["indirect"]
    p = passes.frame_result(plan_named("primal"))
    assert all("dx" not in v for v in p.layers.values())



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
    from gradsep.renderer.scene import load_scene

    scene = load_scene(str(resolve("cbox")), width=16, height=12)
    passes = Passes(scene, ("direct", "indirect"), seed=5)
    passes.start_split()  # from the first pass: no lump
    for c, n in (("direct-alternate", 1), ("primal", 1), ("direct-alternate", 4), ("direct-alternate", 4),
                 ("primal", 3), ("direct-alternate", 2), ("direct-alternate", 2), ("primal", 1),
                 ("direct-alternate", 3), ("direct-alternate", 1)):
        passes.run(plan_named(c), n)
    chosen = plan_named("direct-alternate")
    halves = halves_of_the_frame(passes, chosen)
    assert passes.spp == 22
    assert all(h.layers["direct"].has_gradients and not h.layers["indirect"].has_gradients for h, _, _ in halves)
    assert Passes(scene, ("direct", "indirect"), seed=5).halves(chosen) is None  # not split: no halves
    # a split started after some passes (a pilot's): those passes are one lump in half A
    late = Passes(scene, ("direct", "indirect"), seed=6)
    for c, n in (("primal", 1), ("direct-alternate", 1), ("direct-alternate", 4), ("direct", 4)):
        late.run(plan_named(c), n)
    late.start_split()
    assert late.split is not None and late.split.spp[0] == 10 and late.split.passes[0] == 4
    for n in (4, 4, 3, 3, 2, 2, 2, 1):
        late.run(chosen, n)
    halves_of_the_frame(late, chosen)
    assert late.spp == 31




@pytest.mark.render
def test_the_compile_timer_counts_a_kernel_that_misses_the_cache_and_nothing_warm():
    """renderer.passes.compile_timer reads Dr.Jit's kernel history: a kernel seen for the first time (a literal no
    kernel had before) costs back-end seconds; the same kernel again is a cache hit, 0; inactive measures 0; and the
    history flag is left as it was."""
    import random

    import drjit as dr

    from gradsep.renderer.passes import compile_timer

    mi.set_variant("llvm_ad_rgb")
    literal = random.random() + 2.0  # part of the kernel's IR: a new kernel for this process and the disk cache

    def kernel() -> None:
        x = dr.arange(mi.Float, 4096)
        dr.eval(dr.sin(x * literal) + dr.cos(x / literal))

    was = dr.flag(dr.JitFlag.KernelHistory)
    with compile_timer() as cold:
        kernel()
    with compile_timer() as warm:
        kernel()
    with compile_timer(False) as off:
        kernel()
    assert cold.seconds > 0.0
    assert warm.seconds == 0.0 and off.seconds == 0.0
    assert dr.flag(dr.JitFlag.KernelHistory) == was


@pytest.mark.render
def test_a_first_pass_records_its_compile_apart(small):
    passes = Passes(small, ("direct", "indirect"), seed=7)
    plan = plan_named("all")
    passes.run(plan, 1)
    costs = passes.kind(plan).costs
    assert costs.first_pass is not None and 0.0 <= costs.first_compile <= costs.first_pass[1]
    passes.run(plan, 1)
    assert costs.warm and costs.first_compile == passes.kind(plan).costs.first_compile
