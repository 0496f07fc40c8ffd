"""`gradsep reference`: the direct/indirect split of Mitsuba's path integrator, pass averaging, files, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from renderer.reference import (
    MAX_WAVEFRONT,
    Reference,
    _check_split,
    default_tile_spp,
    load_reference,
    pass_seed,
    plan_passes,
    render_reference,
    write_reference,
)
from tests.renderer.scenes import resolve

# The shared Cornell box when present, else its built-in equivalent (tests/renderer/scenes.py).
CBOX = resolve("cbox").path

pytestmark = pytest.mark.render


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


# -- rendering -------------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("spec", ["procedural:4", str(CBOX)], ids=["procedural", "cbox"])
def test_direct_layer_is_depth_two_light_and_indirect_the_rest(spec: str) -> None:
    """The split against independent renders (other seeds, no split): the direct layer must match a depth-2
    render of the scene and the indirect layer what a full-depth render adds to it, within noise. (That
    direct + indirect == total is true by construction and is not what this checks.)"""
    def means(seed: int, **kwargs) -> np.ndarray:  # image means of 6 independent 32-spp renders
        refs = [render_reference(spec, spp=32, width=24, height=20, tile_spp=32, seed=seed + i, **kwargs)
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

    from renderer.scene import load_scene

    ref = render_reference(str(CBOX), spp=5, width=16, height=16, tile_spp=2, seed=9)
    loaded = load_scene(str(CBOX), width=16, height=16)
    path = mi.load_dict({"type": "path", "max_depth": loaded.max_depth})
    passes = [np.array(mi.render(loaded.scene, integrator=path, spp=k, seed=pass_seed(9, i)), dtype=np.float64)
              for i, k in enumerate([2, 2, 1])]
    expected = (2 * passes[0] + 2 * passes[1] + passes[2]) / 5
    np.testing.assert_allclose(ref.total, expected[..., :3], rtol=1e-5, atol=1e-6)


def test_two_passes_of_k_match_one_pass_of_2k_within_noise() -> None:
    a = render_reference(str(CBOX), spp=16, width=32, height=32, tile_spp=8, seed=1)
    b = render_reference(str(CBOX), spp=16, width=32, height=32, seed=1)
    assert b.metadata["gradsep.tile_spp"] == "16" and a.metadata["gradsep.tile_spp"] == "8"
    d = (a.total - b.total).astype(np.float64).mean(axis=-1).ravel()  # independent per pixel (box filter)
    assert np.abs(d).max() > 0, "different pass seeds must give different noise"
    t = d.mean() / (d.std(ddof=1) / np.sqrt(d.size))
    assert abs(t) < 4.5, f"tiled and untiled means differ by {t:.1f} standard errors"


def test_max_depth_two_writes_no_indirect_layer(tmp_path: Path) -> None:
    ref = render_reference("procedural:2", spp=2, width=12, height=10, max_depth=2)
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
    ref = render_reference("procedural:6", spp=3, width=10, height=8, tile_spp=2, seed=5)
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
    from model.frame import ChannelError, NotExrError, write_exr

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


@pytest.mark.parametrize(("argv", "message"), [
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


def test_command_rejects_bad_scene_and_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    assert main(["reference", str(tmp_path / "missing.xml"), "--spp", "1", "-o", str(tmp_path / "r.exr")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["reference", "procedural:1", "--spp", "1", "-o", str(tmp_path / "r.png")]) == 2
    assert ".exr" in capsys.readouterr().err
    assert main(["reference", "procedural:1", "--spp", "1", "-o", str(tmp_path / "no" / "r.exr")]) == 2
    assert "does not exist" in capsys.readouterr().err
