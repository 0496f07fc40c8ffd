"""Split samples (``FrameOptions(gradient_spp=K)``, `gradsep render --gradient-spp K`): K of the ``spp``
samples trace offsets (G-PT), the other ``spp - K`` are primal-only; the bases and features average all ``spp``
samples, the gradients come from the K G-PT samples.

The primal-only mode's bases and features are G-PT's primal estimator (tests/renderer/test_primal.py), so the
merged base is an unbiased estimate of the same layers; these tests check the merge itself (against the two
kinds of passes rendered separately), the argument errors, that K == spp is today's render bit for bit, the
metadata, and (one Mitsuba-heavy test) the split render's energies and direct gradients against `path`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from gradsep.cli import main  # noqa: E402
from gradsep.model.errors import CommandError  # noqa: E402
from gradsep.model.exr_read import read_frame  # noqa: E402
from gradsep.renderer.gpt import mean_variance, pass_seed, render_gpt, render_pass  # noqa: E402
from gradsep.renderer.gpt_settings import Film, GptSettings  # noqa: E402
from gradsep.renderer.render import FrameOptions, render_frame  # noqa: E402
from gradsep.renderer.scene import load_scene  # noqa: E402
from gradsep.renderer.shift import make_shift  # noqa: E402
from tests.renderer.scenes import resolve  # noqa: E402
from tests.renderer.test_gpt import (  # noqa: E402  the G-PT tests' scenes and statistics
    SCENE_DEPTHS,
    SIZE,
    assert_matches_reference,
    fd_x,
    fd_y,
    path_render,
    two_sample_z,
)
from tests.renderer.test_gpt import load_test_scene as scene_of  # noqa: E402

pytestmark = pytest.mark.render

CBOX = str(resolve("cbox"))


@pytest.fixture(scope="module")
def small():
    return load_scene(CBOX, width=12, height=10, max_depth=5)


def test_gradient_spp_argument_errors(small):
    for bad in (0, -1, 5):
        with pytest.raises(CommandError, match="--gradient-spp must be between 1 and --spp"):
            render_frame(small, spp=4, gradients="direct", options=FrameOptions(gradient_spp=bad))
    with pytest.raises(CommandError, match="--gradient-spp must be an integer"):
        render_frame(small, spp=4, options=FrameOptions(gradient_spp=2.5))
    with pytest.raises(CommandError, match="--gradient-spp has no effect without gradients"):
        render_frame(small, spp=4, gradients=False, options=FrameOptions(gradient_spp=2))
    settings = GptSettings(max_depth=5)
    with pytest.raises(ValueError, match="gradient_spp must be in"):
        render_gpt(small.scene, make_shift("hybrid"), settings, Film(12, 10, 4, gradient_spp=0))
    with pytest.raises(ValueError, match="needs gradients"):
        render_gpt(small.scene, None, settings, Film(12, 10, 4, gradient_spp=2))


@pytest.mark.parametrize("gradients,offsets", [("all", "all"), ("direct", "alternate")])
def test_gradient_spp_equal_to_spp_is_the_plain_render(small, gradients, offsets):
    plain = render_frame(small, spp=5, seed=3, gradients=gradients, options=FrameOptions(offsets=offsets))
    same = render_frame(small, spp=5, seed=3, gradients=gradients,
                        options=FrameOptions(offsets=offsets, gradient_spp=5))
    for name, layer in plain.layers.items():
        for key in ("base", "dx", "dy"):
            np.testing.assert_array_equal(getattr(same.layers[name], key), getattr(layer, key), err_msg=key)
    for key in ("albedo", "normal", "depth"):
        np.testing.assert_array_equal(getattr(same.features, key), getattr(plain.features, key), err_msg=key)
    assert "gradsep.gradient_spp" not in same.metadata
    drop = {"gradsep.render_seconds"}
    assert {k: v for k, v in same.metadata.items() if k not in drop} == \
        {k: v for k, v in plain.metadata.items() if k not in drop}


def test_split_frame_is_the_spp_weighted_mean(small):
    """The split render's bases and features are the per-pixel sums of its G-PT passes and its primal-only passes
    over all N samples (features over their combined hit counts), its gradients the K G-PT samples' alone; the
    primal-only passes have their own seeds (pass index after the G-PT passes)."""
    n, k, seed = 7, 3, 11
    settings = GptSettings(max_depth=5, gradients="direct", offsets="alternate")
    shift = make_shift("hybrid")
    split = render_gpt(small.scene, shift, settings, Film(12, 10, n, seed, gradient_spp=k))
    gpt_only = render_gpt(small.scene, shift, settings, Film(12, 10, k, seed))
    g = render_pass(small.scene, shift, settings, 12, 10, k, pass_seed(seed, 0))
    primal_settings = dataclasses.replace(settings, gradients="all", offsets="all")
    p = render_pass(small.scene, None, primal_settings, 12, 10, n - k, pass_seed(seed, 1))
    assert split.passes == 2 and split.spp == n
    for layer in ("direct", "indirect"):
        expected = (g[f"{layer}.base"] + p[f"{layer}.base"]) / n
        np.testing.assert_allclose(split.layers[layer]["base"], expected, rtol=1e-6, atol=1e-7, err_msg=layer)
        # the bases are not the G-PT part's alone: the primal samples count
        assert not np.allclose(split.layers[layer]["base"], gpt_only.layers[layer]["base"])
    np.testing.assert_array_equal(split.layers["direct"]["dx"], gpt_only.layers["direct"]["dx"])
    np.testing.assert_array_equal(split.layers["direct"]["dy"], gpt_only.layers["direct"]["dy"])
    assert set(split.layers["indirect"]) == {"base", "var"}
    for layer in ("direct", "indirect"):  # the variance is over all N samples too
        expected = mean_variance(g[f"{layer}.base"] + p[f"{layer}.base"], g[f"{layer}.sq"] + p[f"{layer}.sq"], n)
        np.testing.assert_allclose(split.layers[layer]["var"], expected, rtol=1e-5, atol=1e-9, err_msg=layer)
    hits = (g["hit"] + p["hit"])[..., 0]
    assert hits.max() > k  # the primal samples' first hits count in the features
    albedo = np.clip((g["albedo"] + p["albedo"]) / np.maximum(hits, 1.0)[..., None], 0.0, 1.0)
    np.testing.assert_allclose(split.albedo, albedo, rtol=1e-6, atol=1e-7)
    depth = np.where(hits > 0, (g["depth"] + p["depth"])[..., 0] / np.maximum(hits, 1.0), 0.0)
    np.testing.assert_allclose(split.depth, depth, rtol=1e-6, atol=1e-6)
    normal = g["normal"] + p["normal"]
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    np.testing.assert_allclose(split.normal, normal, rtol=1e-5, atol=1e-6)
    # the primal passes are not a replay of the G-PT pass's random numbers
    assert not np.allclose(p["direct.base"] / (n - k), g["direct.base"] / k)


def test_split_metadata_and_command(small, tmp_path, capsys):
    frame = render_frame(small, spp=6, seed=2, gradients="direct",
                         options=FrameOptions(offsets="alternate", gradient_spp=2))
    assert frame.metadata["gradsep.spp"] == "6" and frame.metadata["gradsep.gradient_spp"] == "2"
    assert frame.metadata["gradsep.gradients"] == "direct" and frame.metadata["gradsep.integrator"] == "gpt"
    assert frame.metadata["gradsep.passes"] == "2"
    out = tmp_path / "s.exr"
    args = ["render", CBOX, "--spp", "4", "--width", "12", "--height", "10", "--gradients", "direct"]
    assert main([*args, "--gradient-spp", "1", "-o", str(out)]) == 0
    assert "4 spp (1 with gradients)" in capsys.readouterr().out
    back = read_frame(out)
    assert back.metadata["gradsep.gradient_spp"] == "1" and back.metadata["gradsep.spp"] == "4"
    assert back.layers["direct"].has_gradients and not back.layers["indirect"].has_gradients
    for extra, message in ((["--gradient-spp", "5"], "between 1 and --spp (4)"),
                           (["--gradient-spp", "0"], "between 1 and --spp (4)")):
        assert main([*args, *extra, "-o", str(tmp_path / "x.exr")]) == 2
        assert message in capsys.readouterr().err
    assert main(["render", CBOX, "--spp", "4", "--no-gradients", "--gradient-spp", "2",
                 "-o", str(tmp_path / "x.exr")]) == 2
    assert "--gradient-spp has no effect with --no-gradients" in capsys.readouterr().err
    assert not (tmp_path / "x.exr").exists()


SEEDS = 16
N, K = 8, 3
REF_CHUNKS, REF_SPP = 8, 512


def test_split_render_is_unbiased():
    """cbox, hybrid, ``--gradients direct --offsets alternate`` with 3 of 8 samples tracing offsets: the direct
    layer's gradients against finite differences of the depth-2 `path` reference (per pixel and in scale), the
    total, direct and indirect energies against `path` (test_direct_gradients_mode_is_unbiased's checks)."""
    scene, depth = scene_of("cbox"), SCENE_DEPTHS["cbox"]
    settings = GptSettings(max_depth=depth, gradients="direct", offsets="alternate")
    runs = [render_gpt(scene, make_shift("hybrid"), settings, Film(SIZE, SIZE, N, seed, gradient_spp=K))
            for seed in range(SEEDS)]
    base = {layer: np.stack([r.layers[layer]["base"] for r in runs]).astype(np.float64) for layer in runs[0].layers}
    ref = {d: np.stack([path_render(scene, REF_SPP, 10_000 + i, d) for i in range(REF_CHUNKS)]) for d in (depth, 2)}
    low = {d: np.stack([path_render(scene, N, 20_000 + i, d) for i in range(SEEDS)]) for d in (depth, 2)}
    for axis, fd in (("dx", fd_x), ("dy", fd_y)):
        est = np.stack([r.layers["direct"][axis] for r in runs]).astype(np.float64)
        assert_matches_reference(est, fd(ref[2]), 2e-3, f"split cbox direct {axis}")
    z = two_sample_z((base["direct"] + base["indirect"]).mean(axis=(1, 2)), low[depth].mean(axis=(1, 2)))
    assert np.all(np.abs(z) < 4.5), f"image mean differs from path: z={z}"
    z = two_sample_z(base["direct"].mean(axis=(1, 2)), low[2].mean(axis=(1, 2)))
    assert np.all(np.abs(z) < 4.5), f"direct layer mean differs from path at depth 2: z={z}"
    rest = (low[depth] - low[2]).mean(axis=(1, 2))
    assert np.all(np.abs(two_sample_z(base["indirect"].mean(axis=(1, 2)), rest)) < 4.5)
