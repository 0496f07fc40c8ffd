"""OIDN's colour filter on other runtimes (docs/oidn.md, "Runtime"): error against time of the same weights run by
the OIDN library, by ONNX Runtime in fp32 (CPU provider, OpenVINO), in OpenVINO bf16, and as
``$GRADSEP_OIDN_RUNTIME=onnx`` serves it (``onnx``: bf16 with the full-resolution decoder level in fp32,
model/oidn_onnx.py).

    python benchmarks/study_oidn_runtime.py time                   # 1280x720 layer, medians of --repeats
    python benchmarks/study_oidn_runtime.py error                  # RelMSE on study_oidn.py's cached frames
    python benchmarks/study_oidn_runtime.py methods                # the OIDN methods on each runtime, same frames

Error: the held-out frames of benchmarks/study_oidn.py (its ``render`` step makes them: procedural seeds 70001-
70003 and training-range seeds 1001, 1500, G-PT 16 and 64 spp, 320x240, two 1024-spp references), each layer
denoised at ``--setting`` (default raw-fast) by each variant, summed, RelMSE with the references' noise removed;
per variant the geometric mean, best and worst of its ratio to the library on the same frame.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.study_oidn import DEFAULT_CACHE, SPPS  # noqa: E402

VARIANTS = ("library", "onnx-cpu-fp32", "openvino-fp32", "openvino-bf16", "onnx")


def denoiser(variant: str, setting: str):
    """A model.oidn.Denoiser running ``setting``'s colour filter as ``variant``: ``onnx`` is what
    ``$GRADSEP_OIDN_RUNTIME=onnx`` serves (OpenVINO bf16 with the full-resolution level in fp32 where the CPU
    has bf16); the others pin one provider and precision for the whole graph."""
    import onnxruntime as ort

    from gradsep.model.infer import ProviderChoice, SessionSettings
    from gradsep.model.oidn import SETTINGS, Denoiser
    from gradsep.model.oidn_onnx import unet_graph, weights_for

    if variant == "library":
        return Denoiser(setting, "library")
    den = Denoiser(setting, "onnx")
    if variant != "onnx":
        model = weights_for(SETTINGS[setting].aux, SETTINGS[setting].quality)
        unet = den._unets[model]
        provider, precision = {"onnx-cpu-fp32": ("cpu", "fp32"), "openvino-fp32": ("openvino", "fp32"),
                               "openvino-bf16": ("openvino", "bf16")}[variant]
        unet.session = ort.InferenceSession(unet_graph(unet.weights, model), SessionSettings().options(),
                                            providers=ProviderChoice(provider, precision, "").providers())
    return den


def timing(setting: str, width: int, height: int, repeats: int, variants: list[str]) -> None:
    from gradsep.model.frame import Features

    rng = np.random.default_rng(0)
    layer = rng.gamma(2.0, 0.5, (height, width, 3)).astype(np.float32)
    features = Features(rng.uniform(0, 1, (height, width, 3)).astype(np.float32),
                        rng.uniform(-1, 1, (height, width, 3)).astype(np.float32), np.ones((height, width), np.float32))
    print(f"{setting}, {width}x{height}, one layer, medians of {repeats} after a warm-up; load average "
          + " ".join(f"{v:.2f}" for v in os.getloadavg()))
    print("| runtime | colour filter s |\n|---|---:|")
    for variant in variants:
        den = denoiser(variant, setting)
        aux = den.prefilter(features)
        den.denoise(layer, aux)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            den.denoise(layer, aux)
            times.append(time.perf_counter() - start)
        print(f"| {variant} | {statistics.median(times):.3f} |", flush=True)
        den.close()


def error(setting: str, cache: Path, variants: list[str]) -> None:
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse_unbiased

    dens = {v: denoiser(v, setting) for v in variants}
    scores: dict[str, list[float]] = {v: [] for v in variants}
    for folder in sorted(p for p in cache.iterdir() if (p / "ref-2.npz").is_file()):
        r1, r2 = np.load(folder / "ref-1.npz")["total"], np.load(folder / "ref-2.npz")["total"]
        for spp in SPPS:
            frame = read_frame(folder / f"gpt-{spp}.exr")
            row = []
            for variant, den in dens.items():
                aux = den.prefilter(frame.features) if frame.features is not None else None
                image = sum(den.denoise(lay.base, aux).astype(np.float64) for lay in frame.layers.values())
                scores[variant].append(relmse_unbiased(image, r1, r2))
                row.append(f"{variant}={scores[variant][-1]:.4g}")
            print(f"{folder.name} {spp} spp " + " ".join(row), flush=True)
    base = scores["library"] if "library" in scores else None
    print(f"\n{setting}: RelMSE mean over {len(next(iter(scores.values())))} frames; ratio to the library per frame")
    print("| runtime | mean RelMSE | / library: geo. mean | best | worst |\n|---|---:|---:|---:|---:|")
    for variant, values in scores.items():
        if base is None:
            print(f"| {variant} | {statistics.fmean(values):.4g} | | | |")
            continue
        r = [v / b for v, b in zip(values, base, strict=True) if v > 0 and b > 0]
        geo = math.exp(statistics.fmean(math.log(x) for x in r))
        print(f"| {variant} | {statistics.fmean(values):.4g} | {geo:.4f} | {min(r):.4f} | {max(r):.4f} |")


def methods(cache: Path, names: list[str], runtimes: list[str]) -> None:
    """RelMSE of the OIDN methods (as model.reconstruct serves them) with each OIDN runtime on the cached frames,
    and the ratio of every runtime to the first, per method: what switching the runtime does to what is served
    (fused's blend model was trained on the library's output)."""
    from gradsep.model import oidn
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.reconstruct import load_fused, reconstruct

    fused = load_fused(Path("models"))
    scores: dict[tuple[str, str], list[float]] = {(m, r): [] for m in names for r in runtimes}
    for folder in sorted(p for p in cache.iterdir() if (p / "ref-2.npz").is_file()):
        r1, r2 = np.load(folder / "ref-1.npz")["total"], np.load(folder / "ref-2.npz")["total"]
        for spp in SPPS:
            frame = read_frame(folder / f"gpt-{spp}.exr")
            row = []
            for runtime in runtimes:
                os.environ[oidn.RUNTIME_ENV] = runtime
                for method in names:
                    image = reconstruct(frame, method, fused=fused).image
                    scores[(method, runtime)].append(relmse_unbiased(image, r1, r2))
                    row.append(f"{method}@{runtime}={scores[(method, runtime)][-1]:.4g}")
            print(f"{folder.name} {spp} spp " + " ".join(row), flush=True)
    print(f"\n| method | runtime | mean RelMSE | / {runtimes[0]}: geo. mean | best | worst |\n"
          "|---|---|---:|---:|---:|---:|")
    for method in names:
        base = scores[(method, runtimes[0])]
        for runtime in runtimes:
            values = scores[(method, runtime)]
            r = [v / b for v, b in zip(values, base, strict=True) if v > 0 and b > 0]
            geo = math.exp(statistics.fmean(math.log(x) for x in r))
            print(f"| {method} | {runtime} | {statistics.fmean(values):.4g} | {geo:.4f} | {min(r):.4f} | "
                  f"{max(r):.4f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("time", "error", "methods"))
    parser.add_argument("--methods", default="oidn,oidn-l1,fused", help="methods: which methods to score")
    parser.add_argument("--runtimes", default="library,onnx", help="methods: OIDN runtimes, the first the base")
    parser.add_argument("--setting", default="raw-fast", help="an OIDN setting the onnx runtime builds")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    if args.what == "methods":
        methods(args.cache, [m for m in args.methods.split(",") if m], [r for r in args.runtimes.split(",") if r])
        return 0
    variants = [v for v in args.variants.split(",") if v]
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        parser.error(f"unknown variants {unknown}; choose from {', '.join(VARIANTS)}")
    if args.what == "time":
        width, height = (int(v) for v in args.size.lower().split("x"))
        timing(args.setting, width, height, args.repeats, variants)
    else:
        error(args.setting, args.cache, variants)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
