"""training/dataset.py: the manifest, the per-frame plane cache, the frame split and the random patches."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gradsep.model.exr_write import write_frame  # noqa: E402
from gradsep.model.frame import Features, Frame, Layer  # noqa: E402
from gradsep.model.preprocess import FEATURE_PLANES, LAYER_PLANES  # noqa: E402
from gradsep.training.dataset import (  # noqa: E402
    DatasetError,
    PatchDataset,
    build_cache,
    load_manifest,
    select_layer,
    split_frames,
)


def test_split_is_seeded_90_10_and_by_frame() -> None:
    train_idx, val_idx = split_frames(20, seed=0)
    assert len(val_idx) == 2 and sorted(train_idx + val_idx) == list(range(20))
    assert split_frames(20, seed=0) == (train_idx, val_idx) and split_frames(20, seed=1) != (train_idx, val_idx)
    assert split_frames(1, seed=0) == ([0], [])
    assert len(split_frames(2, seed=0)[1]) == 1


def test_select_layer_sums_for_color() -> None:
    one = np.ones((2, 2, 3), np.float32)
    layers = {"direct": Layer(one, one * 2, one * 3), "indirect": Layer(one * 10, one * 20, one * 30)}
    color = select_layer(layers, "color")
    assert color is not None and np.all(color.base == 11) and np.all(color.dx == 22) and np.all(color.dy == 33)
    assert select_layer({"direct": layers["direct"]}, "indirect") is None


def test_patches_are_deterministic_and_change_with_the_epoch(tiny_dataset: Path, tmp_path: Path) -> None:
    files, warnings = build_cache(load_manifest(tiny_dataset), "direct", tmp_path / "cache")
    assert not warnings and all(f is not None for f in files)
    ds = PatchDataset([f for f in files if f], patch=16, patches_per_frame=3, seed=5)
    planes, feats, targets = ds[4]
    assert planes.shape == (LAYER_PLANES, 16, 16) and feats.shape == (FEATURE_PLANES, 16, 16)
    assert not ds.paired and torch.equal(targets, planes[:9]), "unpaired: the input's own measurements"
    again = PatchDataset([f for f in files if f], patch=16, patches_per_frame=3, seed=5)
    assert torch.equal(again[4][0], planes)
    origins = [ds.origin(i) for i in range(len(ds))]
    ds.set_epoch(1)
    assert [ds.origin(i) for i in range(len(ds))] != origins
    # cached planes equal the preprocessing of the frame itself
    cached = np.load(files[0])
    assert cached.shape == (LAYER_PLANES + FEATURE_PLANES, 48, 64)
    assert cached[LAYER_PLANES:].min() >= 0 and cached[LAYER_PLANES:].max() <= 1


def test_paired_frames_give_independent_targets(tmp_path: Path) -> None:
    from gradsep.model.exr_read import read_frame
    from gradsep.model.preprocess import measured_planes
    from tests.training.synthetic import make_synthetic_dataset

    root = make_synthetic_dataset(tmp_path / "ds", frames=2, width=24, height=20, pairs=True)
    manifest = load_manifest(root)
    assert all(e.target is not None for e in manifest.frames)
    files, warnings = build_cache(manifest, "indirect", tmp_path / "cache")
    assert not warnings
    cached = np.load(files[0])
    assert cached.shape == (LAYER_PLANES + FEATURE_PLANES + 9, 20, 24)
    other = read_frame(manifest.frames[0].target)
    np.testing.assert_array_equal(cached[LAYER_PLANES + FEATURE_PLANES:], measured_planes(other.layers["indirect"]))
    ds = PatchDataset([f for f in files if f], patch=8, patches_per_frame=2, seed=1)
    planes, _, targets = ds[0]
    assert ds.paired and targets.shape == (9, 8, 8) and not torch.equal(targets, planes[:9])
    # a missing target is named before training starts
    manifest.frames[1].target.unlink()
    with pytest.raises(DatasetError, match=r"frames\[1\]\.target .*does not exist"):
        load_manifest(root)


def test_cache_is_reused_and_frames_without_the_layer_are_skipped(tmp_path: Path) -> None:
    from tests.training.synthetic import make_synthetic_dataset

    root = make_synthetic_dataset(tmp_path / "ds", frames=2, width=16, height=16)
    one = np.ones((16, 16, 3), np.float32)
    write_frame(root / "frames" / "proc_001001.exr",
                Frame({"direct": Layer(one, 0 * one, 0 * one)},
                      Features(one * 0.5, one, np.ones((16, 16), np.float32))))
    files, warnings = build_cache(load_manifest(root), "indirect", tmp_path / "cache")
    assert files[0] is not None and files[1] is None
    assert len(warnings) == 1 and "no indirect layer" in warnings[0]
    stamp = files[0].stat().st_mtime_ns
    build_cache(load_manifest(root), "indirect", tmp_path / "cache")
    assert files[0].stat().st_mtime_ns == stamp
    # another prior α is another cache: the prior planes are solved again
    before = np.load(files[0])
    again, _ = build_cache(load_manifest(root), "indirect", tmp_path / "cache", prior_alpha=50.0)
    assert again[0] == files[0] and files[0].stat().st_mtime_ns != stamp
    after = np.load(files[0])
    assert np.array_equal(before[:9], after[:9]) and not np.array_equal(before[9:12], after[9:12])


@pytest.mark.parametrize(("manifest", "message"), [
    (None, "no manifest.json"),
    ("{not json", "not valid JSON"),
    ('{"version": 2, "frames": []}', "version 1"),
    ('{"version": 1, "frames": []}', "non-empty"),
    ('{"version": 1, "frames": [{"file": "../outside.exr"}]}', "escapes"),
    ('{"version": 1, "frames": [{"file": "frames/missing.exr"}]}', "does not exist"),
])
def test_manifest_errors(tmp_path: Path, manifest: str | None, message: str) -> None:
    if manifest is not None:
        (tmp_path / "manifest.json").write_text(manifest)
    (tmp_path.parent / "outside.exr").write_bytes(b"x")
    with pytest.raises(DatasetError, match=message):
        load_manifest(tmp_path)


def test_manifest_identity_prefers_the_renderers_content_hash(tiny_dataset: Path, tmp_path: Path) -> None:
    import hashlib
    import shutil

    blob = (tiny_dataset / "manifest.json").read_bytes()
    assert load_manifest(tiny_dataset).sha256 == hashlib.sha256(blob).hexdigest()
    copy = tmp_path / "ds"
    shutil.copytree(tiny_dataset, copy)
    raw = json.loads(blob)
    raw["hash"] = "ab" * 32
    (copy / "manifest.json").write_text(json.dumps(raw, indent=4))
    assert load_manifest(copy).sha256 == "ab" * 32
