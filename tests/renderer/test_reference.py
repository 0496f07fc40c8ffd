"""`gradsep reference`: the direct/indirect split of Mitsuba's path integrator, pass averaging, files, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gradsep.renderer.reference import (
    DEFAULT_SAMPLER,
    MAX_WAVEFRONT,
    SAMPLERS,
    Reference,
    ReferenceJob,
    _check_split,
    default_tile_spp,
    load_reference,
    merge_references,
    pass_seed,
    plan_passes,
    render_reference,
    sampler_count,
    write_reference,
)
from tests.renderer.scenes import resolve

# The shared Cornell box when present, else its built-in equivalent (tests/renderer/scenes.py).
CBOX = resolve("cbox").path

pytestmark = pytest.mark.render


def reference(spec: str, *, spp: int, seed: int = 0, tile_spp: int | None = None, sampler: str = DEFAULT_SAMPLER,
              shard: tuple[int, int] | None = None, **scene) -> Reference:
    """render_reference with the job's fields as keywords (the tests below vary them one at a time)."""
    return render_reference(spec, ReferenceJob(spp=spp, seed=seed, tile_spp=tile_spp, sampler=sampler, shard=shard),
                            **scene)


# -- pure planning ---------------------------------------------------------------------------------------------

def test_plan_passes_covers_spp_with_a_remainder_pass() -> None:
    assert plan_passes(8, 4) == [4, 4]
    assert plan_passes(5, 2) == [2, 2, 1]
    assert plan_passes(3, 16) == [3]
    with pytest.raises(ValueError):
        plan_passes(0, 4)


def test_default_tile_fits_mitsuba_wavefront_and_4096_spp_at_720p() -> None:
    tile = default_tile_spp(4096, 1280, 720)
    assert 1 <= tile <= 4096
    assert 1280 * 720 * tile <= MAX_WAVEFRONT
    assert sum(plan_passes(4096, tile)) == 4096
    assert default_tile_spp(4, 16, 16) == 4  # small jobs: one pass
    assert default_tile_spp(64, 8192, 8192) == 1


def test_pass_seeds_are_distinct_across_passes_and_neighbouring_seeds() -> None:
    seeds = {pass_seed(s, i) for s in range(4) for i in range(200)}
    assert len(seeds) == 800
    assert all(0 <= s < 2**32 for s in seeds)
    assert pass_seed(1, 0) == pass_seed(1, 0)


def test_split_check_fails_when_direct_exceeds_total() -> None:
    total = np.full((2, 2, 3), 1.0)
    _check_split(total, total.copy(), 0)  # equal: no indirect light, fine
    _check_split(total, total * 0.5, 0)
    direct = total.copy()
    direct[1, 1, 0] = 1.5
    with pytest.raises(RuntimeError, match="direct exceeds total in 1 values"):
        _check_split(total, direct, 3)


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_pass_plans_use_counts_the_sampler_renders_exactly(sampler: str) -> None:
    for spp, tile in [(512, 256), (128, 218), (4096, 256), (100, 64), (16, 16), (48, 16)]:
        plan = plan_passes(spp, tile, sampler)
        assert sum(plan) == spp and max(plan) <= tile
        assert all(sampler_count(sampler, k) == k for k in plan), (sampler, spp, plan)
    assert plan_passes(512, 256, "multijitter") == [256, 256]  # multijitter would render 528 for 512
    assert plan_passes(128, 218, "multijitter") == [120, 8]  # the fewest passes (not 121 + 6 + 1)
    assert plan_passes(16, 16, "orthogonal") == [4, 4, 4, 4]  # prime squares only (9 + 4 leaves 3)
    assert plan_passes(5, 2) == plan_passes(5, 2, "independent") == [2, 2, 1]


def test_pass_plan_refuses_what_a_sampler_cannot_render_and_unknown_samplers() -> None:
    with pytest.raises(ValueError, match="orthogonal sampler renders exactly"):
        plan_passes(6, 6, "orthogonal")  # 4 + 2: orthogonal renders 4 for 2
    with pytest.raises(ValueError, match="unknown sampler"):
        render_reference("procedural:1", ReferenceJob(spp=1, sampler="sobol"))


def test_default_tile_for_stratified_samplers_is_a_power_of_four() -> None:
    assert default_tile_spp(4096, 320, 240, "multijitter") == 256
    assert default_tile_spp(4096, 320, 240) == 218  # independent: the sample budget as before
    assert default_tile_spp(8, 16, 16, "multijitter") == 8
    tile = default_tile_spp(4096, 1280, 720, DEFAULT_SAMPLER)
    assert 1280 * 720 * tile <= MAX_WAVEFRONT and sum(plan_passes(4096, tile, DEFAULT_SAMPLER)) == 4096


# -- rendering -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("spec", ["procedural:5", str(CBOX)], ids=["procedural", "cbox"])
def test_rebuilt_camera_with_the_independent_sampler_renders_bit_identically(spec: str) -> None:
    """sampler_sensor copies the camera exactly: with the scenes' own (independent) sampler and one seed the
    rebuilt sensor renders the very same image (a wrong fov, transform or film would move every pixel)."""
    import mitsuba as mi

    from gradsep.renderer.reference import sampler_sensor
    from gradsep.renderer.scene import load_scene

    loaded = load_scene(spec, width=20, height=14)
    path = mi.load_dict({"type": "path", "max_depth": loaded.max_depth})
    own = np.array(mi.render(loaded.scene, sensor=loaded.sensor, integrator=path, spp=4, seed=3))[..., :3]
    rebuilt = np.array(mi.render(loaded.scene, sensor=sampler_sensor(loaded, "independent"), integrator=path,
                                 spp=4, seed=3))
    assert rebuilt.shape == own.shape and own.mean() > 0
    np.testing.assert_array_equal(rebuilt, own)


def test_rebuilt_thin_lens_camera_renders_bit_identically() -> None:
    import mitsuba as mi

    from gradsep.renderer.reference import sampler_sensor
    from gradsep.renderer.scene import LoadedScene, load_scene

    load_scene("procedural:1", width=4, height=4)  # selects the variant
    scene = mi.load_dict({
        "type": "scene", "light": {"type": "constant"}, "ball": {"type": "sphere", "radius": 0.5},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -1]).scale(3)},
        "camera": {"type": "thinlens", "aperture_radius": 0.2, "focus_distance": 2.5, "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -1, 4], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 18, "height": 12, "rfilter": {"type": "box"}}}})
    loaded = LoadedScene(scene=scene, spec="thinlens", width=18, height=12, max_depth=3, rr_depth=5)
    path = mi.load_dict({"type": "path", "max_depth": 3})
    own = np.array(mi.render(scene, sensor=loaded.sensor, integrator=path, spp=4, seed=2))[..., :3]
    rebuilt = np.array(mi.render(scene, sensor=sampler_sensor(loaded, "independent"), integrator=path, spp=4,
                                 seed=2))
    assert own.std() > 0
    np.testing.assert_array_equal(rebuilt, own)


def _image_means(spec: str, sampler: str, first_seed: int, count: int = 8) -> np.ndarray:
    refs = [reference(spec, spp=16, width=16, height=16, seed=first_seed + i, sampler=sampler)
            for i in range(count)]
    return np.array([[r.total.mean(), r.direct.mean()] for r in refs], dtype=np.float64)


@pytest.mark.parametrize("sampler", ["multijitter", "stratified"])
def test_stratified_references_are_unbiased_against_independent_path(sampler: str) -> None:
    """Every sampler estimates the same image: total and direct image means agree with independent sampling
    within noise (z < 4 over 8 independent 16-spp references each)."""
    base = _image_means(str(CBOX), "independent", 100)
    ours = _image_means(str(CBOX), sampler, 200)
    for col in (0, 1):
        a, b = ours[:, col], base[:, col]
        z = (a.mean() - b.mean()) / np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
        assert abs(z) < 4, (sampler, col, a.mean(), b.mean())


def test_multijitter_passes_with_different_seeds_are_independent() -> None:
    """Pass averaging and the product estimator need passes with different seeds to be uncorrelated. Per pixel,
    (a - t1)(b - t2) with t1, t2 two independent high-spp independent-sampler truths has expectation cov(a, b):
    over 8 pairs of 16-spp multijitter passes its mean must be zero within 4 standard errors, while the same
    pass twice (what a seed-blind stratification pattern would give) is many standard errors above zero."""
    spec, size = str(CBOX), dict(width=32, height=32)
    t1, t2 = (reference(spec, spp=1024, seed=s, sampler="independent", **size).total.astype(np.float64)
              for s in (1, 2))
    passes = [reference(spec, spp=16, seed=s, sampler="multijitter", **size).total.astype(np.float64)
              for s in range(10, 26)]

    def z(pairs: list[tuple[np.ndarray, np.ndarray]]) -> float:
        prod = np.concatenate([((a - t1) * (b - t2)).ravel() for a, b in pairs])
        return float(prod.mean() / (prod.std(ddof=1) / np.sqrt(prod.size)))

    different = z([(passes[i], passes[i + 1]) for i in range(0, 16, 2)])
    same = z([(passes[i], passes[i]) for i in range(0, 16, 2)])
    assert abs(different) < 4, different
    assert same > 8, same


def test_sharded_reference_merges_to_the_unsharded_one(tmp_path: Path) -> None:
    """Shards K/N render the job's passes with the job's seeds: merged, they are the unsharded reference."""
    job = dict(spp=20, width=12, height=10, tile_spp=4, seed=3, sampler="multijitter")
    whole = reference("procedural:6", **job)
    parts = [reference("procedural:6", shard=(k, 3), **job) for k in (3, 1, 2)]
    assert [p.metadata["gradsep.spp"] for p in parts] == ["4", "8", "8"]  # 5 passes dealt 2/2/1
    for i, part in enumerate(parts):  # through files, as a farm would
        write_reference(tmp_path / f"s{i}.exr", part)
    merged = merge_references([load_reference(tmp_path / f"s{i}.exr") for i in range(3)])
    for name in ("total", "direct", "indirect"):
        np.testing.assert_allclose(merged.layer(name), whole.layer(name), rtol=1e-5, atol=1e-7)
    assert merged.metadata["gradsep.spp"] == "20" and merged.metadata["gradsep.shards"] == "3"
    assert "gradsep.shard" not in merged.metadata


def test_merge_refuses_incomplete_or_mixed_shards() -> None:
    job = dict(spp=8, width=6, height=5, tile_spp=2, seed=3)
    a, b = (reference("procedural:6", shard=(k, 2), **job) for k in (1, 2))
    with pytest.raises(ValueError, match="shards 1..2"):
        merge_references([a])
    with pytest.raises(ValueError, match="shards 1..2"):
        merge_references([a, a])
    other = reference("procedural:6", shard=(2, 2), **{**job, "seed": 4})
    with pytest.raises(ValueError, match="gradsep.seed differs"):
        merge_references([a, other])
    with pytest.raises(ValueError, match="not a shard"):
        merge_references([a, reference("procedural:6", **job)])
    with pytest.raises(ValueError, match="has no passes"):
        reference("procedural:6", shard=(5, 5), **job)  # 4 passes only
    assert merge_references([b, a]).metadata["gradsep.spp"] == "8"


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["procedural:4", str(CBOX)], ids=["procedural", "cbox"])
def test_direct_layer_is_depth_two_light_and_indirect_the_rest(spec: str) -> None:
    """The split against independent renders (other seeds, no split): the direct layer must match a depth-2
    render of the scene and the indirect layer what a full-depth render adds to it, within noise. (That
    direct + indirect == total is true by construction and is not what this checks.)"""
    def means(seed: int, **kwargs) -> np.ndarray:  # image means of 6 independent 32-spp renders
        refs = [reference(spec, spp=32, width=24, height=20, tile_spp=32, seed=seed + i, **kwargs)
                for i in range(6)]
        return np.array([[r.total.mean(), r.direct.mean(), 0.0 if r.indirect is None else r.indirect.mean()]
                         for r in refs], dtype=np.float64)

    split, depth2, full = means(3), means(101, max_depth=2)[:, 0], means(202)[:, 0]

    def z(a: np.ndarray, b: np.ndarray) -> float:
        return float((a.mean() - b.mean()) / np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b)))

    # z < 4 within noise; a "direct" layer rendered at depth 3 is >10 sigma off in both scenes.
    assert abs(z(split[:, 1], depth2)) < 4, (split[:, 1].mean(), depth2.mean())
    assert abs(z(split[:, 2], full - depth2)) < 4, (split[:, 2].mean(), (full - depth2).mean())
    assert split[:, 2].mean() > 0.05 * split[:, 0].mean()  # both layers carry light in these scenes


def test_passes_are_the_sample_weighted_mean_of_seeded_renders() -> None:
    """5 spp in passes of 2 = (2*pass0 + 2*pass1 + 1*pass2) / 5, each pass Mitsuba's path with its pass seed."""
    import mitsuba as mi

    from gradsep.renderer.scene import load_scene

    ref = reference(str(CBOX), spp=5, width=16, height=16, tile_spp=2, seed=9, sampler="independent")
    loaded = load_scene(str(CBOX), width=16, height=16)  # its own sensor: cbox.xml's independent sampler
    path = mi.load_dict({"type": "path", "max_depth": loaded.max_depth})
    passes = [np.array(mi.render(loaded.scene, integrator=path, spp=k, seed=pass_seed(9, i)), dtype=np.float64)
              for i, k in enumerate([2, 2, 1])]
    expected = (2 * passes[0] + 2 * passes[1] + passes[2]) / 5
    np.testing.assert_allclose(ref.total, expected[..., :3], rtol=1e-5, atol=1e-6)


def test_two_passes_of_k_match_one_pass_of_2k_within_noise() -> None:
    a = reference(str(CBOX), spp=16, width=32, height=32, tile_spp=8, seed=1)
    b = reference(str(CBOX), spp=16, width=32, height=32, seed=1)
    assert b.metadata["gradsep.tile_spp"] == "16" and a.metadata["gradsep.tile_spp"] == "8"
    d = (a.total - b.total).astype(np.float64).mean(axis=-1).ravel()  # independent per pixel (box filter)
    assert np.abs(d).max() > 0, "different pass seeds must give different noise"
    t = d.mean() / (d.std(ddof=1) / np.sqrt(d.size))
    assert abs(t) < 4.5, f"tiled and untiled means differ by {t:.1f} standard errors"


def test_max_depth_two_writes_no_indirect_layer(tmp_path: Path) -> None:
    ref = reference("procedural:2", spp=2, width=12, height=10, max_depth=2)
    assert ref.indirect is None
    np.testing.assert_array_equal(ref.direct, ref.total)
    out = tmp_path / "direct.exr"
    write_reference(out, ref)
    back = load_reference(out)
    assert back.indirect is None
    with pytest.raises(KeyError, match="indirect"):
        back.layer("indirect")
    assert back.metadata["gradsep.max_depth"] == "2"


def test_file_round_trip_and_metadata(tmp_path: Path) -> None:
    ref = reference("procedural:6", spp=3, width=10, height=8, tile_spp=2, seed=5)
    out = tmp_path / "ref.exr"
    write_reference(out, ref)
    back = load_reference(out)
    assert load_reference(out.read_bytes()).metadata == back.metadata
    np.testing.assert_array_equal(back.total, ref.total)
    np.testing.assert_array_equal(back.indirect, ref.indirect)
    meta = back.metadata
    assert meta["gradsep.scene"] == "procedural:6" and meta["gradsep.spp"] == "3"
    assert meta["gradsep.seed"] == "5" and meta["gradsep.max_depth"] == "8"
    assert meta["gradsep.integrator"] == "path" and float(meta["gradsep.render_seconds"]) > 0
    assert not list(tmp_path.glob(".*.tmp")), "atomic write left a temporary file"


def test_load_reference_names_missing_channels(tmp_path: Path) -> None:
    from gradsep.model.errors import ChannelError, NotExrError
    from gradsep.model.exr_write import write_exr

    path = tmp_path / "not-a-ref.exr"
    write_exr(path, {"R": np.zeros((2, 2)), "G": np.zeros((2, 2)), "B": np.zeros((2, 2))})
    with pytest.raises(ChannelError, match="direct.R"):
        load_reference(path)
    with pytest.raises(NotExrError):
        load_reference(b"definitely not an exr file")


def test_reference_layer_accessor() -> None:
    img = np.ones((2, 2, 3), np.float32)
    ref = Reference(img * 3, img, img * 2, {})
    assert ref.layer("color") is ref.total and ref.layer("indirect") is ref.indirect
    assert set(ref.channels()) == {"R", "G", "B", "direct.R", "direct.G", "direct.B", "indirect.R",
                                   "indirect.G", "indirect.B"}


# -- command ---------------------------------------------------------------------------------------------------

def test_command_writes_reference(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    out = tmp_path / "cbox.exr"
    assert main(["reference", str(CBOX), "--spp", "4", "--width", "16", "--height", "12", "--tile-spp", "2",
                 "-D", "max_depth=3", "-o", str(out)]) == 0
    ref = load_reference(out)
    assert ref.total.shape == (12, 16, 3) and ref.indirect is not None
    assert ref.metadata["gradsep.max_depth"] == "3"  # the XML's <default> was overridden
    assert "wrote" in capsys.readouterr().out


def test_command_shards_and_merges(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    common = ["procedural:3", "--spp", "8", "--width", "8", "--height", "6", "--tile-spp", "2"]
    for k in (1, 2):
        assert main(["reference", *common, "--shard", f"{k}/2", "-o", str(tmp_path / f"p{k}.exr")]) == 0
    assert "shard 1/2" in capsys.readouterr().out
    # without --tile-spp a sharded job still deals passes to every shard (at most spp / N per pass)
    assert main(["reference", "procedural:3", "--spp", "8", "--width", "8", "--height", "6", "--shard", "2/2",
                 "-o", str(tmp_path / "q2.exr")]) == 0
    assert load_reference(tmp_path / "q2.exr").metadata["gradsep.spp"] == "4"
    assert main(["reference-merge", str(tmp_path / "p2.exr"), str(tmp_path / "p1.exr"),
                 "-o", str(tmp_path / "m.exr")]) == 0
    merged = load_reference(tmp_path / "m.exr")
    assert merged.metadata["gradsep.spp"] == "8" and merged.metadata["gradsep.sampler"] == DEFAULT_SAMPLER
    assert main(["reference-merge", str(tmp_path / "p1.exr"), "-o", str(tmp_path / "m2.exr")]) == 2
    assert "shards 1..2" in capsys.readouterr().err
    assert main(["reference-merge", str(tmp_path / "nope.exr"), "-o", str(tmp_path / "m3.exr")]) == 2
    assert "not found" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "message"), [
    (["--spp", "4", "--shard", "3/2"], "--shard"),
    (["--spp", "4", "--shard", "two"], "--shard"),
    (["--spp", "0"], "--spp"),
    (["--spp", "4", "--tile-spp", "0"], "--tile-spp"),
    (["--spp", "4", "--max-depth", "0"], "--max-depth"),
    (["--spp", "4", "--seed", "-1"], "--seed"),
    (["--spp", "4", "-D", "novalue"], "NAME=VALUE"),
])
def test_command_rejects_bad_options(argv: list[str], message: str, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    assert main(["reference", str(CBOX), *argv, "-o", str(tmp_path / "r.exr")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "r.exr").exists()


@pytest.mark.parametrize("sampler", ["sobol", "ldsampler"])
def test_command_offers_only_unbiased_samplers(sampler: str, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    with pytest.raises(SystemExit) as exit_info:  # argparse's own choice check
        main(["reference", str(CBOX), "--spp", "4", "--sampler", sampler, "-o", str(tmp_path / "r.exr")])
    assert exit_info.value.code == 2 and "--sampler" in capsys.readouterr().err


def test_command_rejects_bad_scene_and_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    assert main(["reference", str(tmp_path / "missing.xml"), "--spp", "1", "-o", str(tmp_path / "r.exr")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["reference", "procedural:1", "--spp", "1", "-o", str(tmp_path / "r.png")]) == 2
    assert ".exr" in capsys.readouterr().err
    assert main(["reference", "procedural:1", "--spp", "1", "-o", str(tmp_path / "no" / "r.exr")]) == 2
    assert "does not exist" in capsys.readouterr().err
