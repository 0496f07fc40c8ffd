"""Held-out study of the ``fused`` method's designs (model/fused.py, docs/network.md "The fused method").

    python benchmarks/study_fused.py prepare                 # baselines + candidates of the held-out frames (cached)
    python benchmarks/study_fused.py error NAME=DIRECT,INDIRECT ...  # designs (run folders or candidate kinds)
    python benchmarks/study_fused.py error --models models --per-frame   # the shipped models/fused via reconstruct()
    python benchmarks/study_fused.py time [--models models]        # 1280x720 two-layer frame, in-process medians

Frames: the refine study's held-out procedural seeds 81001-81008 (benchmarks/study_refine.py ``render``: 320x240 G-PT
at 1, 4, 16, 64 spp, two independent 1024-spp references each): neither evaluation scenes (cbox, teapot, 90001,
90002) nor training seeds. Error: RelMSE of the summed layers with the references' noise removed
(model.metrics.relmse_unbiased), as a ratio to ``oidn-l1`` (the default method) on the same frame; geometric mean
over the 32 frames, the worst ratio, and the frames where the method is below ``oidn-l1`` per spp.

A design entry is ``NAME=DIRECT,INDIRECT``: each a run folder of training/fused.py (its network, evaluated from the
PyTorch checkpoint on the cached candidates, the very arrays inference computes, blends its candidates) or a
candidate kind of model.fused.CANDIDATES (the layer is that candidate alone, no network: ``refine,RUN`` is the
shipped design's shape). The candidates are cached per blend format (``*-cands2.npz``), the baselines once.
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


def _cands_path(scene: str, spp: int) -> Path:
    from gradsep.model.fused import BLEND_FORMAT

    return STUDY_CACHE / f"{scene}-{spp}-cands{BLEND_FORMAT}.npz"


def prepare() -> None:
    """Per frame: the baselines' images (through model.reconstruct) and each layer's candidates (every kind of
    model.fused.CANDIDATES) + network inputs, in a file per candidate format (model.fused.BLEND_FORMAT)."""
    from gradsep.model.frame import read_frame
    from gradsep.model.fused import CANDIDATES, OIDN_SETTING, blend_inputs, layer_candidates
    from gradsep.model.oidn import shared_denoiser
    from gradsep.model.reconstruct import load_network, reconstruct

    STUDY_CACHE.mkdir(parents=True, exist_ok=True)
    network = load_network("models")
    den = shared_denoiser(OIDN_SETTING)
    kinds = CANDIDATES
    for scene, spp, path in _frames():
        base_file, cand_file = STUDY_CACHE / f"{scene}-{spp}.npz", _cands_path(scene, spp)
        frame = read_frame(str(path))
        if not base_file.is_file():
            np.savez(base_file, **{f"base_{m}": reconstruct(frame, m, network=network).image for m in BASELINES})
        if cand_file.is_file():
            continue
        arrays = {"kinds": np.array(kinds)}
        aux = den.prefilter(frame.features)
        for name, layer in frame.layers.items():
            scaled, cands, scale = layer_candidates(layer, aux, kinds)
            data, gradient = blend_inputs(scaled, cands, frame.features)
            arrays |= {f"{name}_data": data, f"{name}_gradient": gradient, f"{name}_scale": np.float64(scale),
                       f"{name}_cands": np.stack(cands)}
        np.savez(cand_file, **arrays)
        print(f"{scene} {spp} spp: prepared", flush=True)


def _design(spec: str):
    """NAME=DIRECT,INDIRECT → (name, {layer: (net or None, candidate kinds)}). Each of DIRECT/INDIRECT is a run
    folder of training/fused.py (its network blends its candidates) or a candidate kind (the layer is that
    candidate alone, no network: e.g. ``refine``)."""
    import torch

    from gradsep.model.fused import CANDIDATES
    from gradsep.training.fused import _net

    name, _, runs = spec.partition("=")
    nets = {}
    for layer, run in zip(("direct", "indirect"), runs.split(","), strict=True):
        if run in CANDIDATES:
            nets[layer] = (None, [run])
            continue
        state = torch.load(Path(run) / "checkpoint.pt", weights_only=True)
        net = _net(state["config"])
        net.load_state_dict(state["model"])
        net.eval()
        nets[layer] = (net, list(state["config"]["candidates"]))
    return name, nets


def _blend_image(arrays, nets) -> np.ndarray:
    import torch

    from gradsep.model.fused import blend

    cached = [str(k) for k in arrays["kinds"]]
    total = 0.0
    for layer, (net, kinds) in nets.items():
        idx = [cached.index(k) for k in kinds]
        cands = [arrays[f"{layer}_cands"][i] for i in idx]
        scale = float(arrays[f"{layer}_scale"])
        if net is None:
            total = total + blend(np.ones((1, *cands[0].shape[:2]), np.float32), cands, scale)
            continue
        data = arrays[f"{layer}_data"]
        keep = [0, 1, 2] + [c for i in idx for c in range(3 + 3 * i, 6 + 3 * i)] + list(
            range(3 + 3 * len(cached), 10 + 3 * len(cached)))
        with torch.no_grad():
            w = net(torch.from_numpy(data[keep])[None], torch.from_numpy(arrays[f"{layer}_gradient"])[None])[0]
        total = total + blend(w.numpy(), cands, scale)
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
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse_unbiased

    loaded = [_design(spec) for spec in designs]
    fused = None
    if models:
        from gradsep.model.reconstruct import load_fused, reconstruct

        fused = load_fused(models)
    scores: dict[str, dict[tuple[str, int], float]] = {}
    for scene, spp, path in _frames():
        arrays = np.load(STUDY_CACHE / f"{scene}-{spp}.npz")
        cand_arrays = np.load(_cands_path(scene, spp)) if loaded else None
        refs = sorted((REFINE_CACHE / scene).glob("ref-*.npz"))
        r1, r2 = (np.load(p)["total"] for p in refs[:2])
        images = {m: arrays[f"base_{m}"] for m in BASELINES}
        for name, nets in loaded:
            images[name] = _blend_image(cand_arrays, nets)
        if fused is not None:
            images["fused (shipped, reconstruct)"] = reconstruct(read_frame(str(path)), "fused", fused=fused).image
        for method, image in images.items():
            scores.setdefault(method, {})[(scene, spp)] = relmse_unbiased(image, r1, r2)
        if per_frame:
            row = {m: v[(scene, spp)] / scores["oidn-l1"][(scene, spp)] for m, v in scores.items()}
            print(f"{scene} {spp:>2} spp, RelMSE / oidn-l1: " + " ".join(f"{m}={r:.3f}" for m, r in row.items()))
    _table(scores, sorted({spp for _, spp in scores["oidn-l1"]}))


def _tiled_frame():
    """A held-out frame (procedural-81001, 16 spp) tiled to 1280x720."""
    from gradsep.model.frame import Features, Frame, Layer, read_frame

    small = read_frame(str(_frames()[2][2]))

    def tile(x):
        return None if x is None else np.ascontiguousarray(np.tile(x, (3, 4) + (1,) * (x.ndim - 2))[:720, :1280])

    layers = {n: Layer(tile(lay.base), tile(lay.dx), tile(lay.dy)) for n, lay in small.layers.items()}
    f = small.features
    return Frame(layers, Features(tile(f.albedo), tile(f.normal), tile(f.depth)))


def _stages(fused, frame, repeats: int) -> None:
    """Where the fused method's time goes per layer: OIDN, each candidate, the network inputs, the network, the
    blend (the same functions reconstruct_layer calls, timed one by one)."""
    from bench_oidn import median_seconds  # this script's folder is on sys.path

    from gradsep.model.fused import OIDN_SETTING, refine
    from gradsep.model.oidn import shared_denoiser
    from gradsep.model.preprocess import prior_exposure, scaled_image, scaled_layer

    den = shared_denoiser(OIDN_SETTING)
    aux = den.prefilter(frame.features)
    for name, layer in frame.layers.items():
        row = {"oidn": median_seconds(lambda layer=layer: den.denoise(layer.base, aux), repeats)}
        denoised = den.denoise(layer.base, aux)
        scale = prior_exposure(denoised)
        scaled, oidn = scaled_layer(layer, scale), scaled_image(denoised, scale)
        kinds = fused.models[name].candidates if name in fused.models else (getattr(fused, "fixed", {})[name],)
        for kind in kinds:
            if kind != "oidn":
                row[kind] = median_seconds(lambda kind=kind, scaled=scaled, oidn=oidn: refine(kind, oidn, scaled),
                                           repeats)
        if name in fused.models:
            row |= _network_stages(fused.models[name], layer, aux, frame.features, repeats)
        print(f"  {name}: " + ", ".join(f"{k} {v:.3f} s" for k, v in row.items()), flush=True)


def _network_stages(model, layer, aux, features, repeats: int) -> dict[str, float]:
    from bench_oidn import median_seconds  # this script's folder is on sys.path

    from gradsep.model.fused import blend, blend_inputs, layer_candidates

    scaled, cands, scale = layer_candidates(layer, aux, model.candidates)
    row = {"inputs": median_seconds(lambda: blend_inputs(scaled, cands, features), repeats)}
    data, gradient = blend_inputs(scaled, cands, features)
    row[f"network ({model.choice.provider} {model.choice.precision})"] = median_seconds(
        lambda: model.weights(data, gradient), repeats)
    w = model.weights(data, gradient)
    row["blend"] = median_seconds(lambda: blend(w, cands, scale), repeats)
    return row


def timing(models: str, repeats: int) -> None:
    """The fused method on a 1280x720 two-layer frame in-process (model.reconstruct.reconstruct), with oidn and
    oidn-l1 as the same-run baselines; medians of ``repeats`` after one warm-up; then the per-stage split."""
    from gradsep.model.reconstruct import load_fused, reconstruct

    frame = _tiled_frame()
    fused = load_fused(models)
    for method in ("oidn", "oidn-l1", "fused"):
        times, parts = [], []
        for i in range(repeats + 1):
            start = time.perf_counter()
            rec = reconstruct(frame, method, fused=fused)
            if i:
                times.append(time.perf_counter() - start)
                parts.append(rec.timings)
        split = {k: round(statistics.median(p[k] for p in parts), 3) for k in parts[0]}
        print(f"{method}: median {statistics.median(times):.2f} s per 1280x720 two-layer frame "
              f"(min {min(times):.2f}, {repeats} repeats; per part {split}); load {os.getloadavg()[0]:.2f}",
              flush=True)
    print("fused per stage (medians):")
    _stages(fused, frame, repeats)


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
