"""A frame's layers one after the other against concurrently (``$GRADSEP_LAYER_THREADS``), in-process, per method.

    python benchmarks/bench_layers.py                           # 1280x720 two-layer frame, every method served here
    python benchmarks/bench_layers.py --methods l1,network --repeats 5
    python benchmarks/bench_layers.py --all-concurrent        # also the methods the table schedules sequentially

For each method the two settings alternate (1, 2, 1, 2, ...) so that both see the same machine load; the medians,
their ratio and the largest difference between the two outputs (expected: 0, the same computation) are printed
with the load average. The frame is gradsep.model.synthetic's 1280x720 direct + indirect frame with features.
Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time

import numpy as np

from gradsep.model import methods as table
from gradsep.model.exr_read import read_frame
from gradsep.model.reconstruct import LAYER_THREADS_ENV, available_methods, reconstruct
from gradsep.model.synthetic import synthetic_frame


def run(frame, method: str, threads: int, models) -> tuple[float, np.ndarray, dict[str, float]]:
    os.environ[LAYER_THREADS_ENV] = str(threads)
    start = time.perf_counter()
    result = reconstruct(frame, method, models=models)
    return time.perf_counter() - start, result.image, result.timings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--methods", default="", help="comma-separated (default: every method this host serves)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--threads", type=int, default=2, help="the concurrent setting compared with 1")
    parser.add_argument("--all-concurrent", action="store_true",
                        help="run every method's layers concurrently, not only the table's concurrent ones")
    args = parser.parse_args()
    if args.all_concurrent:  # the sequential methods of the table, measured as if they were concurrent
        for spec in table.methods():
            if spec.schedule == "sequential":
                table.register(dataclasses.replace(spec, schedule="concurrent"), replace=True)

    frame = read_frame(synthetic_frame(args.height, args.width))
    models = table.LoadedModels.load(None)
    methods = [m for m in args.methods.split(",") if m] or available_methods(frame, models)
    print(f"{args.width}x{args.height}, {list(frame.layers)}, load {os.getloadavg()[0]:.2f}")
    print("method   | 1 thread (s) | concurrent (s) | ratio | max |diff| | layer seconds (1 / concurrent)")
    for method in methods:
        run(frame, method, 1, models)  # warm-up: first-call costs (compilation, plans, sessions)
        times: dict[int, list[float]] = {1: [], args.threads: []}
        images, layer_times = {}, {}
        for _ in range(args.repeats):
            for threads in (1, args.threads):
                seconds, images[threads], layer_times[threads] = run(frame, method, threads, models)
                times[threads].append(seconds)
        seq, con = statistics.median(times[1]), statistics.median(times[args.threads])
        diff = float(np.max(np.abs(images[1] - images[args.threads])))
        layers = " / ".join(", ".join(f"{k} {v:.2f}" for k, v in layer_times[t].items()) for t in (1, args.threads))
        print(f"{method:8} | {seq:12.3f} | {con:14.3f} | {con / seq:5.2f} | {diff:10.3g} | {layers}", flush=True)
    print(f"load at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
