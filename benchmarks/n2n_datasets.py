"""Noise2Noise training sets for `gradsep train`: merge `gradsep dataset --pairs` folders into one, and find the
frames whose second realization dominates the unsupervised data term (docs/network.md, designs 29-30).

    python benchmarks/n2n_datasets.py merge data/n2n-mixed data/n2n16-rooms data/n2n16-studio data/gate-room-4 ...
    python benchmarks/n2n_datasets.py tail data/n2n-mixed --drop-above 1 -o data/n2n-mixed-robust

``merge`` hard-links every frame (and its target) into ``OUT/frames/<source folder>_<file>`` and writes one
version-1 manifest whose frames are the sources' in the order given; nothing is copied or re-rendered.

``tail`` scores the training data term (training.losses.data_loss) of the layer's truncated-L1 prior — the
network's own input, before any training — against each frame's independent second realization, on every
``--patch``² crop at stride ``--stride``, and prints each frame's worst crop. It reads only the training pairs,
never a reference. A crop whose prior already scores far above the median is one where the prediction is near
black and the target holds light (a mostly black frame meets a firefly): the relative weight 1/(P(ŷ)² + ε·m² +
black²) is then at its largest, and a handful of such crops carried 99.9 % of design 29's loss. ``--drop-above T``
writes a merged copy without the frames whose worst crop is above T.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from pathlib import Path

import numpy as np


def _link(src: Path, dst: Path) -> None:
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:  # another filesystem: a copy keeps the merge usable
        import shutil

        shutil.copy2(src, dst)


def merge(out: Path, sources: list[Path], keep: set[str] | None = None) -> int:
    """Merge dataset folders (or a subset: ``keep`` = the output file names to keep) into ``out``; returns the
    number of frames written."""
    from gradsep.training.dataset import load_manifest

    frames_dir = out / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    records: list[dict] = []
    spps: set[int] = set()
    sizes: set[tuple[int, ...]] = set()
    tags = [src.resolve().name for src in sources]
    if len(set(tags)) != len(tags):
        raise SystemExit(f"two sources share a folder name ({', '.join(tags)}): their frames' names would collide")
    for src in sources:
        manifest = load_manifest(src)
        spps.add(int(manifest.raw.get("spp", 0)))
        sizes.add(tuple(manifest.raw.get("size", ())))
        tag = src.resolve().name
        for entry in manifest.frames:
            rec = dict(entry.record)
            name = f"{tag}_{entry.path.name}"
            if keep is not None and name not in keep:
                continue
            _link(entry.path, frames_dir / name)
            rec["file"] = f"frames/{name}"
            rec["source"] = f"{tag}/{entry.record['file']}"
            if entry.target is not None:
                tname = f"{tag}_{entry.target.name}"
                _link(entry.target, frames_dir / tname)
                rec["target"] = f"frames/{tname}"
            records.append(rec)
    if not records:
        raise SystemExit(f"{out}: no frames to write")
    identity = hashlib.sha256(json.dumps([(r["file"], r.get("sha256"), r.get("target_sha256"))
                                         for r in records]).encode()).hexdigest()
    manifest = {"version": 1, "spp": next(iter(spps)) if len(spps) == 1 else 0, "spp_mixed": sorted(spps),
                "size": list(next(iter(sizes))) if len(sizes) == 1 else None, "count": len(records),
                "pairs": all("target" in r for r in records), "complete": True, "missing": 0, "hash": identity,
                "merged_from": [str(s) for s in sources], "frames": records}
    tmp = out / "manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, out / "manifest.json")
    return len(records)


def worst_crops(data: Path, layer: str, cache: Path, patch: int, stride: int) -> list[tuple[float, str]]:
    """(worst crop's data term, frame file name) of every usable frame, highest first."""
    import torch

    from gradsep.model.preprocess import FEATURE_PLANES, LAYER_PLANES, MEASURED_PLANES, TRANSFER
    from gradsep.training.dataset import build_cache, load_manifest
    from gradsep.training.losses import data_loss

    manifest = load_manifest(data)
    files, warnings = build_cache(manifest, layer, cache, prior="l1")
    for w in warnings:
        print(f"  {w}", file=sys.stderr)
    out: list[tuple[float, str]] = []
    for entry, path in zip(manifest.frames, files, strict=True):
        if path is None:
            continue
        planes = np.load(path, mmap_mode="r")
        if planes.shape[0] <= LAYER_PLANES + FEATURE_PLANES:
            raise SystemExit(f"{entry.path}: no second realization (render the set with --pairs)")
        twin = LAYER_PLANES + FEATURE_PLANES  # the second realization's measured planes start here (its base first)
        prior = torch.from_numpy(np.array(planes[MEASURED_PLANES:LAYER_PLANES]))  # model.preprocess.layer_planes
        target = torch.from_numpy(np.array(planes[twin:twin + 3]))
        h, w = prior.shape[-2:]
        p = min(patch, h, w)
        worst = 0.0
        for y in range(0, h - p + 1, stride):
            for x in range(0, w - p + 1, stride):
                pred = TRANSFER.forward(prior[None, :, y:y + p, x:x + p].clamp_min(0.0))
                worst = max(worst, float(data_loss(pred, target[None, :, y:y + p, x:x + p])))
        out.append((worst, Path(entry.record["file"]).name))
    return sorted(out, reverse=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("merge", help="merge dataset folders (hard links) into OUT")
    m.add_argument("out", type=Path)
    m.add_argument("sources", type=Path, nargs="+")
    t = sub.add_parser("tail", help="each frame's worst crop: the truncated-L1 prior's data term against its twin")
    t.add_argument("data", type=Path)
    t.add_argument("--layer", default="direct")
    t.add_argument("--cache", type=Path, default=None, help="decoded planes (default: runs/n2n-tail/<data name>)")
    t.add_argument("--patch", type=int, default=128)
    t.add_argument("--stride", type=int, default=64)
    t.add_argument("--show", type=int, default=12, help="frames to list (highest first)")
    t.add_argument("--drop-above", type=float, default=None)
    t.add_argument("-o", "--output", type=Path, default=None, help="with --drop-above: the merged copy to write")
    args = parser.parse_args()
    if args.cmd == "merge":
        print(f"{args.out}: {merge(args.out, args.sources)} frames")
        return 0
    cache = args.cache or Path("runs") / "n2n-tail" / f"{args.data.resolve().name}-{args.layer}"
    scores = worst_crops(args.data, args.layer, cache, args.patch, args.stride)
    values = np.array([s for s, _ in scores])
    print(f"{len(scores)} frames; worst-crop data term: median {np.median(values):.4g}, "
          f"90th pct {np.percentile(values, 90):.4g}, max {values.max():.4g}")
    for s, name in scores[:args.show]:
        print(f"  {s:12.4g}  {name}")
    if args.drop_above is not None:
        dropped = {n for s, n in scores if s > args.drop_above}
        print(f"above {args.drop_above:g}: {len(dropped)} frames: {', '.join(sorted(dropped)) or 'none'}")
        if args.output is not None:
            from gradsep.training.dataset import load_manifest

            manifest = load_manifest(args.data)
            keep = {Path(e.record["file"]).name for e in manifest.frames} - dropped
            n = merge(args.output, [args.data], keep={f"{args.data.resolve().name}_{k}" for k in keep})
            print(f"{args.output}: {n} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
