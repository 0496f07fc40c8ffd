"""Training data: the renderer's dataset folder → cached per-frame planes → random patches.

``gradsep dataset`` writes ``DIR/manifest.json`` and ``DIR/frames/*.exr`` (frame contract). Decoding a
1280×720 EXR with every channel takes a noticeable fraction of a training step and holds every plane, so each
frame is decoded once into a small float32 cache file holding exactly what training needs for the chosen
layer — 12 linear layer planes + 7 normalised feature planes, preprocessed by model.preprocess (the same code
inference uses), + 9 target planes when the dataset has pairs — and patches are read from it through a
memory map. Memory stays bounded by the page cache, not by the dataset size.

Targets. A dataset made with ``gradsep dataset --pairs`` holds a second, independently rendered realization
of every frame; its base and gradients are the losses' targets (Noise2Noise: the target's noise is
independent of the input, so the losses are minimised by the clean image, not by a copy of the input's
noise). Without pairs the targets are the input's own measurements (the paper's self-supervised setting).

Patch positions are a pure function of (seed, epoch, index), so a resumed run sees the same patches, and
every DDP rank agrees without communication.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from gradsep.model.errors import FrameError
from gradsep.model.exr_read import read_frame
from gradsep.model.frame import Layer, feature_groups
from gradsep.model.policy import FEATURE_GROUPS, ILLUMINATION_LAYERS, SEPARATED_LAYERS
from gradsep.model.preprocess import (
    FEATURE_PLANES,
    LAYER_PLANES,
    MEASURED_PLANES,
    PREPROCESS_VERSION,
    PRIOR_ALPHA,
    DepthRange,
    feature_planes,
    layer_planes,
    measured_planes,
)

TRAINABLE_LAYERS = ILLUMINATION_LAYERS  # a network per layer; color = the unseparated baseline
CACHE_FORMAT = 2


class DatasetError(ValueError):
    """The dataset folder cannot be used for training; the message says why."""


@dataclass(frozen=True)
class FrameEntry:
    """One manifest frame: its EXR path, its target realization's (``--pairs``; None without) and the
    manifest record (seed, spp, layers, ...)."""

    index: int
    path: Path
    record: dict[str, Any]
    target: Path | None = None


@dataclass(frozen=True)
class Manifest:
    root: Path
    frames: tuple[FrameEntry, ...]
    sha256: str
    raw: dict[str, Any]


def load_manifest(data_dir: str | os.PathLike[str]) -> Manifest:
    """Read and check DIR/manifest.json; every problem is a DatasetError naming the file and field."""
    root = Path(data_dir)
    path = root / "manifest.json"
    if not path.is_file():
        raise DatasetError(f"{path}: no manifest.json (make the dataset with `gradsep dataset`)")
    blob = path.read_bytes()
    try:
        raw = json.loads(blob)
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(raw, dict) or raw.get("version") != 1:
        raise DatasetError(f"{path}: expected a version 1 manifest object")
    frames = raw.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: 'frames' must be a non-empty list")
    entries = []
    for i, rec in enumerate(frames):
        if not isinstance(rec, dict) or not isinstance(rec.get("file"), str):
            raise DatasetError(f"{path}: frames[{i}] has no 'file'")
        file = (root / rec["file"]).resolve()
        if not file.is_relative_to(root.resolve()):
            raise DatasetError(f"{path}: frames[{i}].file escapes the dataset folder: {rec['file']!r}")
        if not file.is_file():
            raise DatasetError(f"{path}: frames[{i}].file {rec['file']!r} does not exist")
        target = None
        if rec.get("target"):
            target = (root / str(rec["target"])).resolve()
            if not target.is_relative_to(root.resolve()):
                raise DatasetError(f"{path}: frames[{i}].target escapes the dataset folder: {rec['target']!r}")
            if not target.is_file():
                raise DatasetError(f"{path}: frames[{i}].target {rec['target']!r} does not exist")
        entries.append(FrameEntry(i, file, rec, target))
    return Manifest(root, tuple(entries), _identity(raw, blob), raw)


def _identity(raw: dict[str, Any], blob: bytes) -> str:
    """The dataset's identity: the renderer's content hash ("hash": settings + every frame's SHA-256), which
    survives re-merging manifest.json; the file's own SHA-256 for manifests without one."""
    value = raw.get("hash")
    if isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value):
        return value
    return hashlib.sha256(blob).hexdigest()


def split_frames(n: int, seed: int, val_fraction: float = 0.1) -> tuple[list[int], list[int]]:
    """Seeded 90/10 split by frame (never by patch: patches of one frame are correlated).

    At least one training frame; at least one validation frame once there are two frames or more.
    """
    order = np.random.default_rng(seed).permutation(n).tolist()
    n_val = 0 if n < 2 else min(n - 1, max(1, round(n * val_fraction)))
    return sorted(order[n_val:]), sorted(order[:n_val])


def select_layer(frame_layers: dict[str, Layer], layer: str) -> Layer | None:
    """The training layer of one frame; "color" is direct + indirect summed (or the frame's own color layer)."""
    if layer in frame_layers:
        return frame_layers[layer]
    if layer == "color":
        parts = [frame_layers[k] for k in SEPARATED_LAYERS if k in frame_layers]
        if parts:
            total = parts[0]
            for p in parts[1:]:
                total = total + p
            return total
    return None


# ---------------------------------------------------------------------------------------------------------------
# The per-frame cache
# ---------------------------------------------------------------------------------------------------------------


def _cache_key(entry: FrameEntry, layer: str, prior_alpha: float) -> dict[str, Any]:
    st = entry.path.stat()
    key = {"format": CACHE_FORMAT, "preprocess": PREPROCESS_VERSION, "layer": layer, "prior_alpha": prior_alpha,
           "source": str(entry.path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    if entry.target is not None:
        tt = entry.target.stat()
        key |= {"target": str(entry.target), "target_size": tt.st_size, "target_mtime_ns": tt.st_mtime_ns}
    return key


def build_cache(manifest: Manifest, layer: str, cache_dir: Path,
                progress: Callable[[int, int], None] | None = None,
                prior_alpha: float = PRIOR_ALPHA) -> tuple[list[Path | None], list[str]]:
    """Decode every frame once into ``cache_dir/NNNNN.npy`` (19 or 28, H, W) float32, its prior screened by
    ``prior_alpha``; reuse valid files.

    Returns one path per manifest frame (None when the frame cannot be used for ``layer``) and the warnings
    explaining each skipped frame.
    """
    cache_dir.mkdir(parents=True, exist_ok=True)
    paths: list[Path | None] = []
    warnings: list[str] = []
    for entry in manifest.frames:
        target = cache_dir / f"{entry.index:05d}.npy"
        meta_path = target.with_suffix(".json")
        key = _cache_key(entry, layer, prior_alpha)
        if target.is_file() and meta_path.is_file() and json.loads(meta_path.read_text()) == key:
            paths.append(target)
        else:
            reason = _write_cache_file(entry, layer, target, meta_path, key, prior_alpha)
            paths.append(None if reason else target)
            if reason:
                warnings.append(f"{entry.path.name}: skipped ({reason})")
        if progress:
            progress(entry.index + 1, len(manifest.frames))
    return paths, warnings


def _write_cache_file(entry: FrameEntry, layer: str, target: Path, meta_path: Path, key: dict[str, Any],
                      prior_alpha: float) -> str:
    """Write one cache file atomically; return why the frame is unusable, or "" on success."""
    try:
        frame = read_frame(entry.path, nonfinite="zero")
    except FrameError as exc:
        return f"unreadable: {exc}"
    chosen = select_layer(frame.layers, layer)
    if chosen is None:
        return f"no {layer} layer (has {', '.join(frame.layers)})"
    missing = [g for g in FEATURE_GROUPS if g not in feature_groups(frame.features)]
    if missing:  # the network is trained (and later served) with every group
        return "no feature channels" if frame.features is None else f"no {', '.join(missing)} feature channels"
    parts = [layer_planes(chosen, alpha=prior_alpha),
             feature_planes(frame.features, DepthRange.of(frame.features.depth))]
    if entry.target is not None:
        try:
            other = read_frame(entry.target, nonfinite="zero")
        except FrameError as exc:
            return f"target unreadable: {exc}"
        second = select_layer(other.layers, layer)
        if second is None or (other.height, other.width) != (frame.height, frame.width):
            return f"target {entry.target.name} has no matching {layer} layer of {frame.width}x{frame.height}"
        parts.append(measured_planes(second))
    planes = np.concatenate(parts)
    tmp = target.with_name(target.name + ".tmp.npy")
    np.save(tmp, planes.astype(np.float32, copy=False))
    os.replace(tmp, target)
    meta_path.write_text(json.dumps(key))
    return ""


# ---------------------------------------------------------------------------------------------------------------
# Patches
# ---------------------------------------------------------------------------------------------------------------


class PatchDataset(Dataset):
    """``patches_per_frame`` square crops per cached frame; item i → (planes (12,p,p), features (7,p,p),
    targets (9,p,p)) — the targets are the first nine planes again when the frame has no second realization.

    ``fixed=True`` (validation) draws the same crops every epoch; otherwise ``set_epoch`` redraws them.
    Frames smaller than the patch are left out by the caller (see ``usable``).
    """

    def __init__(self, files: Sequence[Path], patch: int, patches_per_frame: int, seed: int,
                 fixed: bool = False) -> None:
        if patch < 1 or patches_per_frame < 1:
            raise ValueError("patch and patches_per_frame must be >= 1")
        self.files = list(files)
        self.patch = patch
        self.per_frame = patches_per_frame
        self.seed = seed
        self.fixed = fixed
        self.epoch = 0
        self._maps: dict[int, np.ndarray] = {}
        self.shapes = [self._open(i).shape[1:] for i in range(len(self.files))]

    def _open(self, i: int) -> np.ndarray:
        if i not in self._maps:
            arr = np.load(self.files[i], mmap_mode="r")
            if arr.ndim != 3 or arr.shape[0] not in (LAYER_PLANES + FEATURE_PLANES,
                                                     LAYER_PLANES + FEATURE_PLANES + MEASURED_PLANES):
                raise DatasetError(f"{self.files[i]}: cache file has shape {arr.shape}; delete it to rebuild")
            self._maps[i] = arr
        return self._maps[i]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.files) * self.per_frame

    def origin(self, index: int) -> tuple[int, int, int]:
        """(frame, y0, x0) of item ``index``: a pure function of seed, epoch (unless fixed) and index."""
        frame = index // self.per_frame
        h, w = self.shapes[frame]
        rng = np.random.default_rng([self.seed, 0 if self.fixed else self.epoch + 1, index])
        return frame, int(rng.integers(0, h - self.patch + 1)), int(rng.integers(0, w - self.patch + 1))

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        frame, y0, x0 = self.origin(index)
        crop = np.array(self._open(frame)[:, y0:y0 + self.patch, x0:x0 + self.patch], dtype=np.float32)
        tensor = torch.from_numpy(crop)
        split = LAYER_PLANES + FEATURE_PLANES
        targets = tensor[split:] if tensor.shape[0] > split else tensor[:MEASURED_PLANES]
        return tensor[:LAYER_PLANES], tensor[LAYER_PLANES:split], targets

    @property
    def paired(self) -> bool:
        """True when every frame has an independent target realization."""
        return all(self._open(i).shape[0] > LAYER_PLANES + FEATURE_PLANES for i in range(len(self.files)))

    def __getstate__(self) -> dict[str, Any]:  # memory maps are reopened in worker processes
        state = self.__dict__.copy()
        state["_maps"] = {}
        return state


def usable(files: Sequence[Path | None], indices: Sequence[int], patch: int) -> tuple[list[Path], list[str]]:
    """Cache files of ``indices`` that exist and are at least ``patch`` pixels on each side."""
    keep, notes = [], []
    for i in indices:
        f = files[i]
        if f is None:
            continue
        arr = np.load(f, mmap_mode="r")
        if min(arr.shape[1:]) < patch:
            notes.append(f"frame {i}: {arr.shape[2]}x{arr.shape[1]} is smaller than the {patch}-pixel patch")
            continue
        keep.append(f)
    return keep, notes
