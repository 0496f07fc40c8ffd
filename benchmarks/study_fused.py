"""Held-out study of the ``fused`` method's designs (model/fused.py, docs/network.md "The fused method").

    python benchmarks/study_fused.py prepare                 # baselines + candidates of the held-out frames (cached)
    python benchmarks/study_fused.py error RUNS...                # blend designs (training/fused.py run folders)
    python benchmarks/study_fused.py error --models models --per-frame   # the shipped models/fused via reconstruct()
    python benchmarks/study_fused.py time [--models models]        # 1280x720 two-layer frame, in-process medians

Frames: the refine study's held-out procedural seeds 81001-81008 (benchmarks/study_refine.py ``render``: 320x240 G-PT
at 1, 4, 16, 64 spp, two independent 1024-spp references each): neither evaluation scenes (cbox, teapot, 90001,
90002) nor training seeds. Error: RelMSE of the summed layers with the references' noise removed
(model.metrics.relmse_unbiased), as a ratio to ``oidn-l1`` (the default method) on the same frame; geometric mean
over the 32 frames, the worst ratio, and the frames where the method is below ``oidn-l1`` per spp.

A design ``RUNS`` entry is ``NAME=RUN_DIRECT,RUN_INDIRECT`` (two run folders of training/fused.py, evaluated from
their PyTorch checkpoints on the cached candidates, the very arrays inference computes).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from pathlib import Path

import numpy as np

REFINE_CACHE = Path(os.environ.get("GRADSEP_CACHE", Path.home() / ".cache" / "gradsep")) / "refine-study"
STUDY_CACHE = REFINE_CACHE.parent / "fused-study"
BASELINES = ("oidn", "oidn-l1", "l1", "network")


def _frames() -> list[tuple[str, int, Path]]:
    out = []
    for folder in sorted(p for p in REFINE_CACHE.glob("procedural-*") if p.is_dir()):
        for path in sorted(folder.glob("gpt-*.exr"), key=lambda p: int(p.stem.split("-")[1])):
            out.append((folder.name, int(path.stem.split("-")[1]), path))
    return out


def prepare() -> None:
    """Per frame: the baselines' images (through model.reconstruct) and each layer's candidates + network inputs."""
    from model.frame import read_frame
    from model.fused import CANDIDATES, OIDN_SETTING, blend_inputs, layer_candidates
    from model.oidn import shared_denoiser
    from model.reconstruct import load_network, reconstruct

    STUDY_CACHE.mkdir(parents=True, exist_ok=True)
    network = load_network("models")
    den = shared_denoiser(OIDN_SETTING)
    for scene, spp, path in _frames():
        out = STUDY_CACHE / f"{scene}-{spp}.npz"
        if out.is_file():
            continue
        frame = read_frame(str(path))
        arrays = {f"base_{m}": reconstruct(frame, m, network=network).image for m in BASELINES}
        aux = den.prefilter(frame.features)
        for name, layer in frame.layers.items():
            scaled, cands, scale = layer_candidates(layer, aux, CANDIDATES)
            data, gradient = blend_inputs(scaled, cands, frame.features)
            arrays |= {f"{name}_data": data, f"{name}_gradient": gradient, f"{name}_scale": np.float64(scale),
                       f"{name}_cands": np.stack(cands)}
        np.savez(out, **arrays)
        print(f"{scene} {spp} spp: prepared", flush=True)


def _design(spec: str):
    """NAME=RUN_DIRECT,RUN_INDIRECT → (name, {layer: (net, candidate indices)})."""
    import torch

    from model.fused import CANDIDATES
    from training.fused import _net

    name, _, runs = spec.partition("=")
    nets = {}
    for layer, run in zip(("direct", "indirect"), runs.split(","), strict=True):
        state = torch.load(Path(run) / "checkpoint.pt", weights_only=True)
        net = _net(state["config"])
        net.load_state_dict(state["model"])
        net.eval()
        nets[layer] = (net, [CANDIDATES.index(k) for k in state["config"]["candidates"]])
    return name, nets


def _blend_image(arrays, nets) -> np.ndarray:
    import torch

    from model.fused import blend

    total = 0.0
    for layer, (net, idx) in nets.items():
        data = arrays[f"{layer}_data"]
        k_all = arrays[f"{layer}_cands"].shape[0]
        keep = [0, 1, 2] + [c for i in idx for c in range(3 + 3 * i, 6 + 3 * i)] + list(range(3 + 3 * k_all,
                                                                                                10 + 3 * k_all))
        with torch.no_grad():
            w = net(torch.from_numpy(data[keep])[None], torch.from_numpy(arrays[f"{layer}_gradient"])[None])[0]
        cands = [arrays[f"{layer}_cands"][i] for i in idx]
        total = total + blend(w.numpy(), cands, float(arrays[f"{layer}_scale"]))
    return np.asarray(total, np.float32)


def _table(scores: dict[str, dict[tuple[str, int], float]], spps: list[int]) -> None:
    ref = scores["oidn-l1"]
    print("| method | RelMSE / oidn-l1 (geo. mean) | worst | " + " | ".join(f"below oidn-l1 @{s}" for s in spps)
          + " | geo. mean @16 | geo. mean @64 |")
    print("|---|---:|---:|" + "---:|" * (len(spps) + 2))
    for method, values in scores.items():
        ratios = {key: v / ref[key] for key, v in values.items()}
        geo = math.exp(statistics.fmean(math.log(max(r, 1e-12)) for r in ratios.values()))
        wins = []
        for s in spps:
            at = [r for (_, spp), r in ratios.items() if spp == s]
            wins.append(f"{sum(r < 1 for r in at)}/{len(at)}")
        per = [math.exp(statistics.fmean(math.log(max(r, 1e-12)) for (_, sp), r in ratios.items() if sp == s))
               for s in (16, 64)]
        print(f"| {method} | {geo:.3f} | {max(ratios.values()):.2f} | " + " | ".join(wins)
              + f" | {per[0]:.3f} | {per[1]:.3f} |")


def error(designs: list[str], models: str | None, per_frame: bool = False) -> None:
    from model.frame import read_frame
    from model.metrics import relmse_unbiased

    loaded = [_design(spec) for spec in designs]
    fused = None
    if models:
        from model.reconstruct import load_fused, reconstruct

        fused = load_fused(models)
    scores: dict[str, dict[tuple[str, int], float]] = {}
    for scene, spp, path in _frames():
        arrays = np.load(STUDY_CACHE / f"{scene}-{spp}.npz")
        refs = sorted((REFINE_CACHE / scene).glob("ref-*.npz"))
        r1, r2 = (np.load(p)["total"] for p in refs[:2])
        images = {m: arrays[f"base_{m}"] for m in BASELINES}
        for name, nets in loaded:
            images[name] = _blend_image(arrays, nets)
        if fused is not None:
            images["fused (shipped, reconstruct)"] = reconstruct(read_frame(str(path)), "fused", fused=fused).image
        for method, image in images.items():
            scores.setdefault(method, {})[(scene, spp)] = relmse_unbiased(image, r1, r2)
        if per_frame:
            row = {m: v[(scene, spp)] / scores["oidn-l1"][(scene, spp)] for m, v in scores.items()}
            print(f"{scene} {spp:>2} spp, RelMSE / oidn-l1: " + " ".join(f"{m}={r:.3f}" for m, r in row.items()))
    _table(scores, sorted({spp for _, spp in scores["oidn-l1"]}))


def timing(models: str, repeats: int) -> None:
    """The fused method on a 1280x720 two-layer frame in-process (model.reconstruct.reconstruct), with oidn-l1 as
    the same-run baseline; medians of ``repeats`` after one warm-up. A held-out frame tiled to 1280x720."""
    from model.frame import Features, Frame, Layer, read_frame
    from model.reconstruct import load_fused, reconstruct

    small = read_frame(str(_frames()[2][2]))  # procedural-81001, 16 spp

    def tile(x):
        return None if x is None else np.ascontiguousarray(np.tile(x, (3, 4) + (1,) * (x.ndim - 2))[:720, :1280])

    layers = {n: Layer(tile(lay.base), tile(lay.dx), tile(lay.dy)) for n, lay in small.layers.items()}
    f = small.features
    frame = Frame(layers, Features(tile(f.albedo), tile(f.normal), tile(f.depth)))
    fused = load_fused(models)
    for method in ("oidn-l1", "fused"):
        times, parts = [], []
        for i in range(repeats + 1):
            start = time.perf_counter()
            rec = reconstruct(frame, method, fused=fused)
            if i:
                times.append(time.perf_counter() - start)
                parts.append(rec.timings)
        split = {k: round(statistics.median(p[k] for p in parts), 3) for k in parts[0]}
        print(f"{method}: median {statistics.median(times):.2f} s per 1280x720 two-layer frame "
              f"(min {min(times):.2f}, {repeats} repeats; per part {split}); load {os.getloadavg()[0]:.2f}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("prepare")
    e = sub.add_parser("error")
    e.add_argument("designs", nargs="*", help="NAME=RUN_DIRECT,RUN_INDIRECT")
    e.add_argument("--models", default=None, help="also the shipped fused models of this models folder")
    e.add_argument("--per-frame", action="store_true", help="print every frame's ratios too")
    t = sub.add_parser("time")
    t.add_argument("--models", default="models")
    t.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    if args.cmd == "prepare":
        prepare()
    elif args.cmd == "error":
        error(args.designs, args.models, args.per_frame)
    else:
        timing(args.models, args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
