"""Time the screened Poisson solvers on a synthetic 1280×720 frame and print medians.

    python benchmarks/bench_poisson.py                 # L2 and L1 (defaults), 3 layers, 5 repeats
    python benchmarks/bench_poisson.py --candidates    # + multigrid budgets and the network's prior
    python benchmarks/bench_poisson.py --json          # one JSON document on stdout instead of the table

The frame has three illumination layers' worth of channels (direct, indirect, color: base + dx + dy each, RGB)
so the figures read directly as "a 1280×720 three-layer frame"; per-layer medians are printed as well, so the
cost of a separated frame (two layers) or of one primal+gradients set (the unit of the NVIDIA solver's "~1 s
for 1280×720 on a GTX 980") can be read off the same run. The data is synthetic and seeded: smooth shading with
edges, multiplicative Monte-Carlo-like noise with heavy-tailed fireflies in the base, lighter noise with rarer
outliers in the gradients; the indirect layer noisier than the direct one. It is not fitted to any scene.

Each configuration runs once untimed (imports, FFT plans, caches), then ``--repeats`` times; the median of the
per-repeat totals is reported, with CG iterations, the final L1 energy and RelMSE against the noise-free image.
Timings on a shared machine are noisy: the load average is printed with them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass

import numpy as np
import scipy

from gradsep.model.frame import forward_differences
from gradsep.model.metrics import relmse
from gradsep.model.poisson import L1_CG_STEPS, L1_PASSES, L1Options, energy_l1, solve_l1, solve_l2
from gradsep.model.policy import DEFAULT_ALPHA

LAYERS = {"direct": 0.3, "indirect": 0.8, "color": 0.5}  # layer -> relative noise level


@dataclass
class SyntheticLayer:
    truth: np.ndarray
    base: np.ndarray
    dx: np.ndarray
    dy: np.ndarray


def synthetic_layer(height: int, width: int, noise: float, seed: int) -> SyntheticLayer:
    """A noisy primal + gradients set with a known noise-free image."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    yy /= height
    xx /= width
    shading = np.stack([0.4 + 0.3 * np.sin(7 * xx + c) * np.cos(5 * yy - c) for c in range(3)], -1)
    edges = (xx > 0.35) * 0.5 + ((xx - 0.7) ** 2 + (yy - 0.4) ** 2 < 0.03) * 2.0 + (yy > 0.8) * 0.3
    truth = shading + edges[..., None] * np.array([1.0, 0.8, 0.6])
    dx, dy = forward_differences(truth)

    def heavy_tailed(shape: tuple[int, ...], rate: float, scale: float) -> np.ndarray:
        spikes = rng.random(shape[:2]) < rate
        out = np.zeros(shape)
        out[spikes] = rng.exponential(scale, size=(int(spikes.sum()), shape[2]))
        return out

    base = truth * (1 + noise * rng.standard_normal(truth.shape)) + heavy_tailed(truth.shape, 0.002, 30.0)
    dx = dx + 0.3 * noise * rng.standard_normal(dx.shape) + heavy_tailed(dx.shape, 0.0005, 5.0)
    dy = dy + 0.3 * noise * rng.standard_normal(dy.shape) + heavy_tailed(dy.shape, 0.0005, 5.0)
    dx[:, -1] = 0
    dy[-1] = 0
    return SyntheticLayer(*(a.astype(np.float32) for a in (truth, base, dx, dy)))


def configurations(args: argparse.Namespace) -> dict[str, dict]:
    configs = {
        "l2": {"solver": "l2"},
        "l1": {"solver": "l1", "iterations": args.passes, "cg_iterations": args.cg_iterations,
               "preconditioner": "dct"},
    }
    if args.candidates:
        configs["l1-mg-20x1"] = {"solver": "l1", "iterations": 20, "cg_iterations": 1, "preconditioner": "mg"}
        configs["l1-mg-10x1"] = {"solver": "l1", "iterations": 10, "cg_iterations": 1, "preconditioner": "mg"}
        configs["prior-dct-5x2"] = {"solver": "l1", "iterations": 5, "cg_iterations": 2, "preconditioner": "dct"}
    return configs


def run_once(config: dict, layer: SyntheticLayer, alpha: float) -> tuple[np.ndarray, float, int]:
    start = time.perf_counter()
    if config["solver"] == "l2":
        image, cg = solve_l2(layer.base, layer.dx, layer.dy, alpha), 0
    else:
        options = L1Options(**{k: v for k, v in config.items() if k != "solver"})
        image, stats = solve_l1(layer.base, layer.dx, layer.dy, alpha, options)
        cg = stats.total_cg_iterations
    return image, time.perf_counter() - start, cg


def bench(args: argparse.Namespace) -> dict:
    width, height = args.size
    names = list(LAYERS)[: args.layers]
    layers = {name: synthetic_layer(height, width, LAYERS[name], seed=i) for i, name in enumerate(names)}
    results = {}
    for label, config in configurations(args).items():
        repeats = args.repeats
        run_once(config, layers[names[0]], args.alpha)  # warm-up: imports, FFT plans, caches
        totals, per_layer, cg, quality = [], {n: [] for n in names}, {}, {}
        for _ in range(repeats):
            total = 0.0
            for name, layer in layers.items():
                image, seconds, iterations = run_once(config, layer, args.alpha)
                per_layer[name].append(seconds)
                total += seconds
                cg[name] = iterations
                quality[name] = {"relmse": relmse(image, layer.truth),
                                 "l1_energy": energy_l1(image, layer.base, layer.dx, layer.dy, args.alpha)}
            totals.append(total)
        results[label] = {
            "config": config,
            "repeats": repeats,
            "median_total_s": statistics.median(totals),
            "min_total_s": min(totals),
            "median_per_layer_s": {n: statistics.median(v) for n, v in per_layer.items()},
            "cg_iterations_per_layer": cg,
            "quality_per_layer": quality,
        }
    return {
        "frame": {"width": width, "height": height, "layers": names, "alpha": args.alpha},
        "machine": {
            "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
            "python": platform.python_version(),
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "processor": platform.processor() or platform.machine(),
        },
        "results": results,
    }


def print_table(report: dict) -> None:
    frame, machine = report["frame"], report["machine"]
    load = ", ".join(f"{x:.2f}" for x in machine["load_average"] or [])
    print(f"{frame['width']}x{frame['height']} frame, layers {', '.join(frame['layers'])}, alpha {frame['alpha']}; "
          f"{machine['cpus']} CPUs, load average {load}; numpy {machine['numpy']}, scipy {machine['scipy']}")
    header = (f"{'method':<20}{'total s (median)':>17}{'per layer s':>13}{'CG its/layer':>14}{'RelMSE':>10}"
              f"{'L1 energy':>13}")
    print(header)
    print("-" * len(header))
    for label, r in report["results"].items():
        per_layer = statistics.mean(r["median_per_layer_s"].values())
        cg = statistics.mean(r["cg_iterations_per_layer"].values())
        err = statistics.mean(q["relmse"] for q in r["quality_per_layer"].values())
        energy = sum(q["l1_energy"] for q in r["quality_per_layer"].values())
        print(f"{label:<20}{r['median_total_s']:>17.3f}{per_layer:>13.3f}{cg:>14.0f}{err:>10.4f}{energy:>13.6g}")
    print("(medians over repeats; RelMSE against the noise-free image, mean over layers; L1 energy summed)")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    def size(text: str) -> tuple[int, int]:
        w, _, h = text.lower().partition("x")
        return int(w), int(h)

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=size, default=(1280, 720), help="WIDTHxHEIGHT (default 1280x720)")
    p.add_argument("--layers", type=int, choices=(1, 2, 3), default=3,
                   help="illumination layers: 1 = direct, 2 = + indirect, 3 = + color (default 3)")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats per configuration (default 5)")
    p.add_argument("--alpha", type=float, default=DEFAULT_ALPHA)
    p.add_argument("--passes", type=int, default=L1_PASSES,
                   help=f"IRLS passes for 'l1' (default {L1_PASSES}, model.poisson.L1_PASSES)")
    p.add_argument("--cg-iterations", type=int, default=L1_CG_STEPS,
                   help=f"CG steps per IRLS pass for 'l1' (default {L1_CG_STEPS}, model.poisson.L1_CG_STEPS)")
    p.add_argument("--candidates", action="store_true",
                   help="+ multigrid-preconditioned budgets and the network's prior")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    report = bench(args)
    if args.json:
        json.dump(report, sys.stdout, indent=2)
        print()
    else:
        print_table(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
