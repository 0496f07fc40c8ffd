"""Training of the ``fused`` method's blend models (model/fused.py, model/blend_net.py): unsupervised, Noise2Noise.

    python -m gradsep.training.fused cache  --data data/n2n16 -o runs/fused-cache     # candidates, once (cached)
    python -m gradsep.training.fused train  --cache runs/fused-cache --layer indirect --candidates oidn,refine-fast \
                                            --minutes 10 -o runs/fused-blend-indirect  # resumable
    python -m gradsep.training.fused export runs/fused-blend-indirect -o models/fused/indirect.onnx

The cache holds, per frame and layer, at the normalised exposure of model.fused.layer_candidates (computed by that
very function, as inference does): the layer's base, dx, dy; the candidates it was built for (cache.json); the 7
feature planes; and the base of the frame's independent second realization, multiplied by the *input's* scale s
(the target never decides s, so its noise stays independent of everything the network sees).

Loss (no reference anywhere): per-pixel relative squared error of the blend against the second realization's
base, ``(Σ w_k c_k − t)² / (sg(mean_rgb(c_oidn))² + REL_EPS)``. The prediction and the denominator are functions
of the first realization only, so the expected loss is the error against the true image plus the target's own
variance, a constant: its minimiser is the clean image (Noise2Noise). REL_EPS matches model.metrics' RelMSE ε at
the normalised exposure (mean 0.5).

Resumable: ``checkpoint.pt`` holds the weights, the optimiser and the step; the batches are a pure function of
(seed, step), so a resumed run continues the same sequence. ``--minutes`` is the total budget of the run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gradsep.model.fused import (
    BLEND_FORMAT,
    CANDIDATES,
    INPUT_NAMES,
    OIDN_SETTING,
    OUTPUT_NAME,
    data_channels,
)
from gradsep.model.infer import BLEND_PRIOR
from gradsep.model.preprocess import TRANSFER

CACHE_VERSION = 2


def cache_planes(k: int) -> int:
    """Planes per cached (frame, layer) with K candidates: base 3, dx 3, dy 3, candidates 3·K, features 7,
    target 3."""
    return 9 + 3 * k + 7 + 3
REL_EPS = 1e-2
LAYERS = ("direct", "indirect")


# ------------------------------------------------------------------------------------------------ cache


def frame_planes(layer: Any, features: Any, target_base: np.ndarray, aux: Any,
                 kinds: tuple[str, ...] = CANDIDATES, denoised: np.ndarray | None = None) -> np.ndarray:
    """(cache_planes(K), H, W) float32 for one layer of one frame; the candidates ``kinds`` from
    model.fused.layer_candidates, and the second realization's base ``target_base`` at the input's exposure.
    ``denoised``: the layer's OIDN image when the caller has it (layer_candidates then does not run OIDN)."""
    from gradsep.model.fused import layer_candidates
    from gradsep.model.preprocess import DepthRange, feature_planes, scaled_image

    scaled, cands, scale = layer_candidates(layer, aux, kinds, denoised=denoised)
    chw = [np.asarray(x, np.float32).transpose(2, 0, 1) for x in (scaled.base, scaled.dx, scaled.dy, *cands)]
    feats = feature_planes(features, DepthRange.of(features.depth))
    target = scaled_image(target_base, scale).transpose(2, 0, 1)
    planes = np.concatenate([*chw, feats, target]).astype(np.float32)
    return np.nan_to_num(planes, nan=0.0, posinf=0.0, neginf=0.0)


def build_cache(data: Path, out: Path, kinds: tuple[str, ...] = CANDIDATES,
                layers: tuple[str, ...] = LAYERS, extra: tuple[Path, ...] = ()) -> None:
    """Write out/{layer}/NNNNN.npy for every frame of the Noise2Noise dataset ``data`` and each of ``layers``
    (skips existing files). ``extra``: more datasets (other spp, other scenes) cached beside it as
    x{i}-NNNNN.npy; training samples all files alike."""
    from gradsep.model.exr_read import read_frame
    from gradsep.model.frame import feature_groups
    from gradsep.model.oidn import shared_denoiser
    from gradsep.model.policy import FEATURE_GROUPS
    from gradsep.training.dataset import load_manifest

    manifest = load_manifest(data)
    extras = [load_manifest(path) for path in extra]
    den = shared_denoiser(OIDN_SETTING)
    if not layers or any(layer not in LAYERS for layer in layers):
        raise SystemExit(f"--layers must be some of {LAYERS}, got {layers}")
    for layer in layers:
        (out / layer).mkdir(parents=True, exist_ok=True)
    meta = {"version": CACHE_VERSION, "candidates": list(kinds), "oidn_setting": OIDN_SETTING,
            "blend_format": BLEND_FORMAT, "dataset": manifest.sha256, "frames": len(manifest.frames)}
    if extras:
        meta["extra_datasets"] = [m.sha256 for m in extras]
    if (out / "cache.json").is_file() and json.loads((out / "cache.json").read_text()) != meta:
        raise SystemExit(f"{out} holds a cache of other candidates or code ({(out / 'cache.json').read_text()}); "
                         "use another folder or delete it")
    (out / "cache.json").write_text(json.dumps(meta))
    start = time.monotonic()
    entries = [("", entry, len(manifest.frames)) for entry in manifest.frames]
    entries += [(f"x{i}-", entry, len(m.frames)) for i, m in enumerate(extras) for entry in m.frames]
    for prefix, entry, count in entries:
        paths = {layer: out / layer / f"{prefix}{entry.index:05d}.npy" for layer in layers}
        if all(p.is_file() for p in paths.values()) or entry.target is None:
            continue
        frame = read_frame(entry.path, nonfinite="zero")
        other = read_frame(entry.target, nonfinite="zero")
        if len(feature_groups(frame.features)) < len(FEATURE_GROUPS):  # the blend is trained with every group
            continue
        aux = den.prefilter(frame.features)
        for layer, path in paths.items():
            if layer not in frame.layers or layer not in other.layers:
                continue
            planes = frame_planes(frame.layers[layer], frame.features, np.asarray(other.layers[layer].base, np.float32),
                                  aux, kinds)
            tmp = path.with_name(path.name + ".tmp.npy")
            np.save(tmp, planes)
            os.replace(tmp, path)
        print(f"cache {prefix}{entry.index + 1}/{count} ({time.monotonic() - start:.0f} s)", flush=True)


# ------------------------------------------------------------------------------------------------ batches


def split(files: list[Path], seed: int = 0) -> tuple[list[Path], list[Path]]:
    """Seeded 90/10 split by frame (validation frames never train)."""
    order = np.random.default_rng(seed).permutation(len(files))
    n_val = max(1, round(len(files) * 0.1))
    return [files[i] for i in sorted(order[n_val:])], [files[i] for i in sorted(order[:n_val])]


def tensors(planes: torch.Tensor, kinds: tuple[str, ...],
            cached: tuple[str, ...] = CANDIDATES) -> tuple[torch.Tensor, ...]:
    """(data, gradient, candidates (N, K, 3, h, w), target (N, 3, h, w)) of the candidates ``kinds`` from
    cached (N, cache_planes(len(cached)), h, w) planes holding the candidates ``cached``."""
    idx = [cached.index(k) for k in kinds]
    cands = torch.stack([planes[:, 9 + 3 * i: 12 + 3 * i] for i in idx], dim=1)
    f0 = 9 + 3 * len(cached)
    feats, target = planes[:, f0:f0 + 7], planes[:, f0 + 7:f0 + 10]
    data = torch.cat([TRANSFER.forward(planes[:, 0:3]), *(TRANSFER.forward(cands[:, k]) for k in range(len(idx))),
                      feats], dim=1)
    gradient = torch.cat([TRANSFER.forward_signed(planes[:, 3:6]), TRANSFER.forward_signed(planes[:, 6:9])], dim=1)
    return data, gradient, cands, target


def n2n_loss(weights: torch.Tensor, cands: torch.Tensor, target: torch.Tensor,
             denominator_source: torch.Tensor) -> torch.Tensor:
    """mean (Σ w_k c_k − t)² / (sg(mean_rgb(d))² + REL_EPS); ``d`` (OIDN's image, the first candidate) is a
    function of the input realization only."""
    pred = torch.sum(weights.unsqueeze(2) * cands, dim=1)
    d = denominator_source.detach()
    den = d.mean(dim=1, keepdim=True) ** 2 + REL_EPS
    return torch.mean((pred - target) ** 2 / den)


def sample(maps: list[np.ndarray], batch: int, patch: int, rng: np.random.Generator) -> torch.Tensor:
    out = np.empty((batch, maps[0].shape[0], patch, patch), np.float32)
    for b in range(batch):
        arr = maps[int(rng.integers(len(maps)))]
        h, w = arr.shape[1:]
        y, x = int(rng.integers(h - patch + 1)), int(rng.integers(w - patch + 1))
        crop = np.asarray(arr[:, y:y + patch, x:x + patch])
        if rng.integers(2):  # a horizontal flip is a different image with the same statistics; dx flips sign
            crop = crop[:, :, ::-1].copy()
            # flipped, dx(x) = J(x+1) - J(x) = -(the mirrored dx one column right); the last one is unknown
            crop[3:6] = -np.roll(crop[3:6], -1, axis=2)
            crop[3:6, :, -1] = 0.0
        out[b] = crop
    return torch.from_numpy(out)


# ------------------------------------------------------------------------------------------------ training


def _net(cfg: dict[str, Any]) -> torch.nn.Module:
    from gradsep.model.blend_net import BlendNet
    from gradsep.model.network import NetworkConfig

    return BlendNet(len(cfg["candidates"]), NetworkConfig.from_dict(cfg["network"]))


@torch.no_grad()
def validate(net: torch.nn.Module, maps: list[np.ndarray], kinds: tuple[str, ...],
             cached: tuple[str, ...] = CANDIDATES) -> dict[str, float]:
    """Noise2Noise loss on the validation frames (whole frames) for the blend and for each candidate alone:
    the blend earns its place where its value is below every candidate's (all share the target's variance)."""
    net.eval()
    sums: dict[str, float] = {}
    for arr in maps:
        planes = torch.from_numpy(np.array(arr))[None]  # a copy: the memory map is read-only
        data, gradient, cands, target = tensors(planes, kinds, cached)
        weights = net(data, gradient)
        bright = cands[:, 0]
        sums["blend"] = sums.get("blend", 0.0) + float(n2n_loss(weights, cands, target, bright))
        for k, kind in enumerate(kinds):
            one = torch.zeros_like(weights)
            one[:, k] = 1.0
            sums[kind] = sums.get(kind, 0.0) + float(n2n_loss(one, cands, target, bright))
    net.train()
    return {k: v / len(maps) for k, v in sums.items()}


def _checked_cache(cache: Path, kinds: tuple[str, ...]) -> tuple[dict[str, Any], tuple[str, ...]]:
    """The candidate cache's metadata and candidates, refused where it cannot serve a run on ``kinds``."""
    meta = json.loads((cache / "cache.json").read_text())
    cached = tuple(meta["candidates"])
    if meta.get("blend_format") != BLEND_FORMAT or any(k not in cached for k in kinds):
        raise SystemExit(f"{cache} holds candidates {cached} (format {meta.get('blend_format')}); this run needs "
                         f"{kinds} (format {BLEND_FORMAT}): rebuild the cache")
    if "target" in meta or "normalise" in meta:
        raise SystemExit(f"{cache} was made with another target or loss normalisation than this code trains on: "
                         "rebuild the cache")
    return meta, cached


def _run_config(args: argparse.Namespace, kinds: tuple[str, ...], meta: dict[str, Any]) -> dict[str, Any]:
    return {"layer": args.layer, "candidates": list(kinds), "patch": args.patch, "batch": args.batch, "lr": args.lr,
            "lr_schedule": "cosine",
            "seed": args.seed,
            "network": {"width": args.width, "depth": 3, "residual_blocks": args.blocks, "use_attention": True},
            "oidn_setting": OIDN_SETTING, "format": BLEND_FORMAT, "loss": f"n2n relmse eps {REL_EPS}",
            "dataset": meta["dataset"]}


def _resume(ckpt: Path, net: torch.nn.Module, opt: torch.optim.Optimizer) -> tuple[int, float]:
    """(step, seconds trained) of the run's checkpoint, loaded into ``net`` and ``opt``; (0, 0.0) for a new run."""
    if not ckpt.is_file():
        return 0, 0.0
    state = torch.load(ckpt, weights_only=True)
    net.load_state_dict(state["model"])
    opt.load_state_dict(state["opt"])
    return state["step"], state["elapsed"]


def _step(net: torch.nn.Module, opt: torch.optim.Optimizer, planes: torch.Tensor, kinds: tuple[str, ...],
          cached: tuple[str, ...]) -> float:
    """One optimiser step on a batch of cached planes; its loss."""
    data, gradient, cands, target = tensors(planes, kinds, cached)
    loss = n2n_loss(net(data, gradient), cands, target, cands[:, 0])
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss.detach())


def _append_log(run: Path, record: dict[str, Any]) -> None:
    with open(run / "log.jsonl", "a") as fh:
        fh.write(json.dumps(record) + "\n")


def train(args: argparse.Namespace) -> None:
    run = Path(args.output)
    cfg_path, ckpt = run / "config.json", run / "checkpoint.pt"
    kinds = tuple(k.strip() for k in args.candidates.split(","))
    if any(k not in CANDIDATES for k in kinds) or kinds[0] != "oidn":
        raise SystemExit(f"--candidates must start with oidn and be some of {CANDIDATES}, got {kinds}")
    cache = Path(args.cache)
    meta, cached = _checked_cache(cache, kinds)
    cfg = _run_config(args, kinds, meta)
    if cfg_path.is_file() and json.loads(cfg_path.read_text()) != cfg:
        raise SystemExit(f"{run} holds a different run; use another folder")
    run.mkdir(parents=True, exist_ok=True)  # only now: a refused start leaves no folder behind
    cfg_path.write_text(json.dumps(cfg, indent=2))
    torch.manual_seed(args.seed)
    net = _net(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    step, elapsed = _resume(ckpt, net, opt)
    train_files, val_files = split(sorted((cache / args.layer).glob("*.npy")), args.seed)
    maps = [np.load(f, mmap_mode="r") for f in train_files]
    budget = args.minutes * 60.0
    start, last_save = time.monotonic(), time.monotonic()
    print(f"{run}: {len(train_files)} train / {len(val_files)} val frames, candidates {kinds}, step {step}, "
          f"{elapsed / 60:.1f} min done", flush=True)

    def save() -> None:
        tmp = ckpt.with_name("checkpoint.tmp.pt")
        torch.save({"model": net.state_dict(), "opt": opt.state_dict(), "step": step,
                    "elapsed": elapsed + time.monotonic() - start, "config": cfg}, tmp)
        os.replace(tmp, ckpt)

    running = []
    while elapsed + time.monotonic() - start < budget:
        # the learning rate decays to 0 over the run's time budget (cosine; resumes continue it)
        done = min(1.0, (elapsed + time.monotonic() - start) / budget)
        for group in opt.param_groups:
            group["lr"] = args.lr * 0.5 * (1.0 + math.cos(math.pi * done))
        planes = sample(maps, args.batch, args.patch, np.random.default_rng([args.seed, step]))
        running.append(_step(net, opt, planes, kinds, cached))
        step += 1
        if step % 50 == 0:
            _append_log(run, {"kind": "step", "step": step, "loss": float(np.mean(running)),
                              "elapsed": round(elapsed + time.monotonic() - start, 1)})
            running = []
        if time.monotonic() - last_save > 120:
            save()
            last_save = time.monotonic()
    save()
    val = validate(net, [np.load(f, mmap_mode="r") for f in val_files], kinds, cached)
    record = {"kind": "validation", "step": step, "elapsed": round(elapsed + time.monotonic() - start, 1),
              "n2n_relmse": val}
    _append_log(run, record)
    print(json.dumps(record), flush=True)


# ------------------------------------------------------------------------------------------------ export


def export(run_dir: Path, output: Path) -> dict[str, Any]:
    """The run's network (inputs data, gradient; output weights) as one ONNX file with gradsep.* metadata,
    checked against PyTorch in ONNX Runtime before it is written."""
    import onnx
    import onnxruntime as ort

    from gradsep.training.export import OPSET, PARITY_TOLERANCE, save_onnx
    from gradsep.training.runlog import code_version

    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    cfg = state["config"]
    net = _net(cfg)
    net.load_state_dict(state["model"])
    net.eval()
    k, a = len(cfg["candidates"]), net.config.alignment
    g = torch.Generator().manual_seed(0)
    sample_in = (torch.rand(2, data_channels(k), 2 * a, 3 * a, generator=g),
                 torch.rand(2, 6, 2 * a, 3 * a, generator=g) - 0.5)
    n, h, w = torch.export.Dim("batch"), torch.export.Dim("height"), torch.export.Dim("width")
    shapes = {"data": {0: n, 2: h, 3: w}, "gradient": {0: n, 2: h, 3: w}}
    program = torch.onnx.export(net, sample_in, None, input_names=list(INPUT_NAMES), output_names=[OUTPUT_NAME],
                                opset_version=OPSET, dynamo=True, dynamic_shapes=shapes, verbose=False)
    proto = program.model_proto
    meta = {"gradsep.format": BLEND_FORMAT, "gradsep.prior": BLEND_PRIOR, "gradsep.layer": cfg["layer"],
            "gradsep.candidates": json.dumps(cfg["candidates"]), "gradsep.oidn_setting": cfg["oidn_setting"],
            "gradsep.exposure": "oidn-mean", "gradsep.alignment": str(a),
            "gradsep.network": json.dumps(net.config.to_dict()), "gradsep.attention": "true",
            "gradsep.training": json.dumps(cfg), "gradsep.trained_steps": str(state["step"]),
            "gradsep.trained_minutes": f"{state['elapsed'] / 60:.2f}", "gradsep.code_version": code_version()}
    onnx.helper.set_model_props(proto, meta)
    onnx.checker.check_model(proto)
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    worst = 0.0
    for hh, ww in ((2 * a, 3 * a), (5 * a, 2 * a)):
        data, grad = torch.rand(1, data_channels(k), hh, ww, generator=g), torch.rand(1, 6, hh, ww, generator=g)
        with torch.no_grad():
            ref = net(data, grad).numpy()
        got = session.run([OUTPUT_NAME], {"data": data.numpy(), "gradient": grad.numpy()})[0]
        worst = max(worst, float(np.abs(got - ref).max()))
    if not worst < PARITY_TOLERANCE:
        raise SystemExit(f"ONNX Runtime disagrees with PyTorch ({worst:.2e}); not writing {output}")
    path = save_onnx(proto, output)
    return {"path": str(path), "bytes": path.stat().st_size, "steps": state["step"], "parity": worst}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m gradsep.training.fused", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cache")
    c.add_argument("--data", required=True)
    c.add_argument("-o", "--output", required=True)
    c.add_argument("--candidates", default=",".join(CANDIDATES), help="the candidate kinds to cache")
    c.add_argument("--layers", default=",".join(LAYERS), help="the layers to cache")
    c.add_argument("--extra-data", action="append", default=[], metavar="DATASET",
                   help="another Noise2Noise dataset to cache beside --data (repeatable: other spp, other scenes)")
    t = sub.add_parser("train")
    t.add_argument("--cache", required=True)
    t.add_argument("--layer", choices=LAYERS, required=True)
    t.add_argument("--candidates", default=",".join(CANDIDATES), help="the candidate kinds the blend weighs")
    t.add_argument("--minutes", type=float, required=True, help="total budget of the run (resumed runs included)")
    t.add_argument("--patch", type=int, default=64)
    t.add_argument("--batch", type=int, default=8)
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--width", type=int, default=16, help="network width (model/network.py NetworkConfig)")
    t.add_argument("--blocks", type=int, default=4, help="residual blocks at the bottleneck")
    t.add_argument("-o", "--output", required=True)
    e = sub.add_parser("export")
    e.add_argument("run")
    e.add_argument("-o", "--output", required=True)
    args = p.parse_args(argv)
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    if args.cmd == "cache":
        build_cache(Path(args.data), Path(args.output), tuple(k.strip() for k in args.candidates.split(",")),
                    tuple(k.strip() for k in args.layers.split(",")), tuple(Path(p) for p in args.extra_data))
    elif args.cmd == "train":
        train(args)
    else:
        print(json.dumps(export(Path(args.run), Path(args.output))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
