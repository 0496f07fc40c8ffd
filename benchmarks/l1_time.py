"""Time of solve_l1 budgets on one 1280x720 layer as the service runs it (each layer's DCTs on one thread, since
the two layers are solved concurrently), interleaved in one run so they see the same load, with the synthetic
benchmark frame's RelMSE (bench_poisson.synthetic_layer, direct and indirect). The first configuration is the
baseline of the ratios.

    python benchmarks/l1_time.py "{'iterations': 10, 'cg_iterations': 4}" "{}" "{'preconditioner': 'mg'}"

Arguments are model.poisson.solve_l1 keyword dict literals (``{}``: the defaults). Medians of ``--repeats``
after one untimed round. Run under the shared CPU lock.
"""

from __future__ import annotations

import argparse
import ast
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_poisson import LAYERS, synthetic_layer  # noqa: E402

from gradsep.model.metrics import relmse  # noqa: E402
from gradsep.model.poisson import fft_workers, solve_l1  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("configs", nargs="+", help="solve_l1 keyword dict literals")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    configs = [ast.literal_eval(c) for c in args.configs]
    layers = {n: synthetic_layer(720, 1280, LAYERS[n], seed) for seed, n in enumerate(("direct", "indirect"))}
    times: dict[int, list[float]] = {i: [] for i in range(len(configs))}
    errors = {}
    with fft_workers(1):
        for repeat in range(args.repeats + 1):
            for i, config in enumerate(configs):
                total = 0.0
                for name, layer in layers.items():
                    start = time.perf_counter()
                    image, _ = solve_l1(layer.base, layer.dx, layer.dy, **config)
                    total += time.perf_counter() - start
                    errors[(i, name)] = relmse(image, layer.truth)
                if repeat:  # the first round warms up (numba, FFT plans)
                    times[i].append(total / len(layers))
    base = statistics.median(times[0])
    print(f"1280x720, s per layer (median of {args.repeats}), load {os.getloadavg()[0]:.2f}")
    for i, config in enumerate(configs):
        med = statistics.median(times[i])
        rel = " / ".join(f"{errors[(i, n)]:.5f}" for n in layers)
        print(f"{str(config):<60} {med:7.3f} s  x{med / base:5.2f}  RelMSE {rel}", flush=True)


if __name__ == "__main__":
    main()
