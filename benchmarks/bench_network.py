"""Network inference latency (and peak memory) on this machine: ONNX Runtime variants and the PyTorch reference.

    python benchmarks/bench_network.py                       # 1280×720, untrained default network, table
    python benchmarks/bench_network.py --models models       # the exported models in models/
    python benchmarks/bench_network.py --json                # machine-readable
    python benchmarks/bench_network.py --memory              # also: peak RSS of a 4096×4096 layer (tiled)

The target (issue 5): a 1280×720 frame with both layers in ≤ 2 s on the 2-core machine, end to end (the
``frame: direct+indirect`` row: preprocessing, ORT, inverse transform, for both layers). Every row is the
median of ``--repeats`` timed runs after one warm-up run; timings on a shared machine are noisy, so re-run
on a quiet one before quoting them. Without ``--models`` the default network is exported untrained (weights
do not change the cost), which needs torch; with ``--models`` only numpy + onnxruntime are needed, except
for the PyTorch rows.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from gradsep.model.infer import NetworkReconstructor, TileSettings
from gradsep.model.onnx_session import SessionSettings
from gradsep.model.preprocess import DATA_INPUTS, GRADIENT_INPUTS


def median_time(fn: Callable[[], object], repeats: int) -> dict[str, float]:
    fn()  # warm-up: allocation, ORT's first-run graph work
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times)}


def synthetic_layer(h: int, w: int, seed: int = 0):  # noqa: ANN201 - (Layer, Features)
    from gradsep.model.frame import Features, Layer, forward_differences

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    clean = (1 + 0.5 * np.sin(xx / 40) * np.cos(yy / 30))[..., None] * np.array([0.9, 0.6, 0.4], np.float32)
    base = (clean * rng.lognormal(-0.02, 0.2, clean.shape)).astype(np.float32)
    dx, dy = forward_differences(clean)
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1
    return Layer(base, dx, dy), Features(np.clip(clean / 2, 0, 1), normal, 1 + yy / h)


def export_default_models(folder: Path, attention: bool = True) -> None:
    """Untrained default networks as direct/indirect.onnx (cost does not depend on the weights)."""
    import torch

    from gradsep.model.network import DualBranchNet, NetworkConfig
    from gradsep.training.export import model_metadata, save_onnx, to_onnx

    cfg = NetworkConfig(use_attention=attention)
    for i, layer in enumerate(("direct", "indirect")):
        torch.manual_seed(i)
        save_onnx(to_onnx(DualBranchNet(cfg), model_metadata(cfg, layer)), folder / f"{layer}.onnx")


def bench_ort(models: Path, h: int, w: int, repeats: int) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    layer, features = synthetic_layer(h, w)
    a = 8
    data = np.random.default_rng(1).random((1, len(DATA_INPUTS), -(-h // a) * a, -(-w // a) * a), np.float32)
    grad = np.random.default_rng(2).random((1, len(GRADIENT_INPUTS), data.shape[2], data.shape[3]), np.float32)

    def session_row(name: str, settings: SessionSettings) -> None:
        rec = NetworkReconstructor.load(models, settings)
        assert rec is not None
        sess = rec.models["direct"].session
        rows.append({"name": name, **median_time(lambda: sess.run(None, {"data": data, "gradient": grad}),
                                                 repeats)})

    for level in ("disable", "basic", "extended", "all"):
        session_row(f"ORT fp32 graph only, opt={level}, threads=auto", SessionSettings(optimization=level))
    for threads in (1, 2):
        session_row(f"ORT fp32 graph only, opt=all, threads={threads}", SessionSettings(intra_op_threads=threads))

    rec = NetworkReconstructor.load(models)
    assert rec is not None
    for name in sorted(rec.layers):
        rows.append({"name": f"layer {name}: preprocess + ORT + inverse",
                     **median_time(lambda n=name: rec.reconstruct_layer(n, layer, features), repeats)})
    both = [n for n in ("direct", "indirect") if n in rec.layers]
    rows.append({"name": f"frame: {'+'.join(both)} (sequential, the target)",
                 **median_time(lambda: [rec.reconstruct_layer(n, layer, features) for n in both], repeats)})
    # two sessions side by side, one ORT thread each, against the sequential default
    solo = NetworkReconstructor.load(models, SessionSettings(intra_op_threads=1))
    assert solo is not None
    with ThreadPoolExecutor(2) as pool:
        rows.append({"name": f"frame: {'+'.join(both)} (2 threads x 1 ORT thread)",
                     **median_time(lambda: list(pool.map(lambda n: solo.reconstruct_layer(n, layer, features),
                                                         both)), repeats)})
    return rows


def bench_torch(h: int, w: int, repeats: int, attention: bool) -> list[dict[str, object]]:
    try:
        import torch
    except ImportError:
        return []
    from gradsep.model.network import DualBranchNet, NetworkConfig

    net = DualBranchNet(NetworkConfig(use_attention=attention)).eval()
    a = net.config.alignment
    data = torch.rand(1, len(DATA_INPUTS), -(-h // a) * a, -(-w // a) * a)
    grad = torch.rand(1, len(GRADIENT_INPUTS), data.shape[2], data.shape[3])
    rows = []
    with torch.inference_mode():
        rows.append({"name": "PyTorch fp32 eager (reference)", **median_time(lambda: net(data, grad), repeats)})
        with torch.autocast("cpu", dtype=torch.bfloat16):
            rows.append({"name": "PyTorch bf16 autocast eager", **median_time(lambda: net(data, grad), repeats)})
    return rows


def bench_memory(models: Path, side: int) -> dict[str, object]:
    """Peak RSS of reconstructing one side×side layer (tiled), in a fresh process so nothing else counts: this
    script again, with the hidden ``--memory-child`` flag."""
    proc = subprocess.run([sys.executable, __file__, "--memory-child", str(side), "--models", str(models)],
                          capture_output=True, text=True, check=True)
    before_kb, peak_kb, seconds = proc.stdout.split()
    return {"name": f"memory: {side}x{side} layer, tiled {TileSettings().tile}+{TileSettings().overlap}",
            "peak_rss_gb": int(peak_kb) / 1e6, "inputs_rss_gb": int(before_kb) / 1e6, "seconds": float(seconds)}


def memory_child(models: Path, side: int) -> None:
    """The child of :func:`bench_memory`: prints RSS before, peak RSS (kB) and the layer's seconds."""
    layer, features = synthetic_layer(side, side)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rec = NetworkReconstructor.load(models)
    t = time.perf_counter()
    rec.reconstruct_layer("direct", layer, features)
    print(before, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, time.perf_counter() - t)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", type=Path, default=None, help="folder with direct.onnx/indirect.onnx "
                   "(default: export the untrained default network to a temporary folder)")
    p.add_argument("--size", default="1280x720", help="WxH")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-attention", action="store_true", help="benchmark the ablation network instead")
    p.add_argument("--no-torch", action="store_true", help="skip the PyTorch rows")
    p.add_argument("--memory", action="store_true", help="also measure peak RSS of a 4096x4096 layer")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--memory-child", type=int, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.memory_child is not None:
        memory_child(args.models, args.memory_child)
        return 0
    w, h = (int(v) for v in args.size.lower().split("x"))

    with tempfile.TemporaryDirectory() as tmp:
        models = args.models
        if models is None:
            models = Path(tmp)
            export_default_models(models, attention=not args.no_attention)
        rows = bench_ort(models, h, w, args.repeats)
        if not args.no_torch:
            rows += bench_torch(h, w, args.repeats, attention=not args.no_attention)
        if args.memory:
            rows.append(bench_memory(models, 4096))
    meta = {"size": [w, h], "repeats": args.repeats, "cpu_count": os.cpu_count(), "machine": platform.processor()
            or platform.machine(), "load_average": os.getloadavg(), "models": str(args.models or "untrained default"),
            "self_peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}
    if args.json:
        print(json.dumps({"meta": meta, "rows": rows}, indent=2))
        return 0
    print(f"{w}x{h}, median of {args.repeats} (load average {meta['load_average'][0]:.1f}: noisy if > 0)")
    print(f"{'variant':<58} {'median s':>9} {'min s':>8}")
    for r in rows:
        if "median_s" in r:
            print(f"{r['name']:<58} {r['median_s']:>9.3f} {r['min_s']:>8.3f}")
        else:
            print(f"{r['name']:<58} peak RSS {r['peak_rss_gb']:.2f} GB ({r['seconds']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
