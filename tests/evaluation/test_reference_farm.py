"""Issue 13's reference work in the evaluation: the sampler in the reference cache key, farm shards of the
reference passes that combine into exactly the cache one machine writes, and the report's software line."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from gradsep.evaluation.config import EvalConfig
from gradsep.evaluation.farm import render_reference_shard, shard_passes
from gradsep.model.errors import CommandError

SCENE = "procedural:3"


def _config(cache: Path, tmp: Path) -> EvalConfig:
    return EvalConfig(scenes=(SCENE,), spp=(1,), width=12, height=10, ref_spp=2, output=tmp / "report",
                      cache_dir=cache, models_dir=tmp / "models", methods=("gpt-primal",), seed=0, max_depth=None,
                      alpha=0.2, table_spp=None, quick=False, ref_spp_cap=8, ref_seconds=None)


def test_shard_passes_deal_the_passes_up_to_the_cap_round_robin() -> None:
    assert shard_passes(512, 4096, (1, 4)) == [0, 4, 8, 12]
    assert shard_passes(512, 4096, (4, 4)) == [3, 7, 11, 15]
    assert sorted(i for k in (1, 2, 3) for i in shard_passes(2, 8, (k, 3))) == list(range(8))
    with pytest.raises(CommandError, match="not a multiple"):
        shard_passes(512, 1000, (1, 2))


def _passes(cache: Path) -> dict[str, np.ndarray]:
    from gradsep.renderer.reference import load_reference

    return {p.name: load_reference(p).total for p in sorted((cache / "evaluate" / "references").rglob("*.exr"))}


@pytest.mark.render
def test_shards_combine_into_the_cache_one_machine_writes(tmp_path: Path) -> None:
    """Two shards' caches, copied together, hold the same pass files (names and pixels) as one unsharded run,
    and the evaluation's reference pair at the cap is then built without rendering anything."""
    from gradsep.evaluation.run import _Runner
    from gradsep.renderer.scene import load_scene

    for k in (1, 2):
        reports = render_reference_shard(_config(tmp_path / f"shard{k}", tmp_path), (k, 2), log=lambda m: None)
        # 4 full passes and 4 of the 8 pilot passes (which place region passes; evaluation/region.py)
        assert reports[0].passes == [k - 1, k + 1, k + 3, k + 5] and reports[0].pilots == [k - 1, k + 1, k + 3, k + 5]
        assert reports[0].rendered == 8
    whole = render_reference_shard(_config(tmp_path / "whole", tmp_path), (1, 1), log=lambda m: None)
    assert whole[0].rendered == 16 and whole[0].pilots == list(range(8))
    merged = tmp_path / "merged"
    for k in (1, 2):
        shutil.copytree(tmp_path / f"shard{k}", merged, dirs_exist_ok=True)
    a, b = _passes(merged), _passes(tmp_path / "whole")
    assert sorted(a) == sorted(b) and len(a) == 16 and sum("pilot" in name for name in a) == 8
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])

    config = _config(merged, tmp_path)
    runner = _Runner(config, False, lambda m: None)
    loaded = load_scene(SCENE, width=12, height=10)
    source = runner.references(_entry(), loaded)

    def refuse(spp: int, seed: int) -> None:
        raise AssertionError("a pass the shards rendered was rendered again")

    source.render_pass = refuse
    pair = source.pair(8)
    assert pair.spp == 8 and pair.floor() > 0 and runner.computed["references"] == 0
    assert source.pilot_passes_to_render() == 0 and source.region().width >= 1  # placed from the shards' pilot
    again = render_reference_shard(config, (1, 1), log=lambda m: None)
    assert again[0].rendered == 0  # everything cached


def _entry():
    from gradsep.evaluation.config import resolve_scenes

    return resolve_scenes([SCENE])[0][0]


@pytest.mark.render
def test_reference_cache_key_names_the_sampler(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Passes rendered with another sampler are never re-used: the sampler is part of every pass's key."""
    import gradsep.evaluation.run as run
    from gradsep.evaluation.run import _Runner
    from gradsep.renderer.scene import load_scene

    loaded = load_scene(SCENE, width=12, height=10)
    config = _config(tmp_path / "cache", tmp_path)
    source = _Runner(config, False, lambda m: None).references(_entry(), loaded)
    assert source.key["sampler"] == run.REFERENCE_SAMPLER == "multijitter"
    source.ensure(0)
    monkeypatch.setattr(run, "REFERENCE_SAMPLER", "independent")
    runner = _Runner(config, False, lambda m: None)
    other = runner.references(_entry(), loaded)
    other.ensure(0)
    assert runner.computed["references"] == 1  # re-rendered, not taken from the multijitter pass
    names = sorted(p.name for p in (tmp_path / "cache" / "evaluate" / "references").rglob("*.exr"))
    assert len(names) == 2


def test_command_shard_needs_references_only(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from gradsep.cli import main

    assert main(["evaluate", "--shard", "1/2", "-o", str(tmp_path / "r")]) == 2
    assert "--references-only" in capsys.readouterr().err
    assert main(["evaluate", "--references-only", "--shard", "3/2", "-o", str(tmp_path / "r")]) == 2
    assert "--shard" in capsys.readouterr().err


def test_software_names_the_distribution_that_provides_a_module(monkeypatch: pytest.MonkeyPatch) -> None:
    """onnxruntime-openvino installs the `onnxruntime` module: report its version, not "not installed"."""
    from importlib import metadata

    from gradsep.evaluation.report import software

    real = metadata.version

    def version(name: str) -> str:
        if name in ("onnxruntime", "pyoidn"):
            raise metadata.PackageNotFoundError(name)
        return "9.9.9" if name == "onnxruntime-openvino" else real(name)

    monkeypatch.setattr(metadata, "version", version)
    monkeypatch.setattr(metadata, "packages_distributions", lambda: {"onnxruntime": ["onnxruntime-openvino"]})
    sw = software()
    assert sw["onnxruntime"] == "9.9.9 (onnxruntime-openvino)"
    assert sw["pyoidn"] == "not installed"
