"""What a frame costs in CPU time, per method, and the latency floor that sets on a machine of N cores.

    python benchmarks/bench_floor.py                          # bench_service.py's synthetic 1280x720 frame
    python benchmarks/bench_floor.py --frame render.exr       # your own frame (any size, any layers)
    python benchmarks/bench_floor.py --methods oidn-l1,network --repeats 5 --json

Each method runs ``service.pipeline.run_pipeline`` in this process: decode, reconstruct, encode, what one request
does in a service worker, without HTTP (add the upload's read, 0.07-0.12 s for a 66 MB frame on localhost, for
bench_service.py's p50). Per method, medians of ``--repeats`` after a warm-up: the wall time and the **process CPU
time** (every thread: OIDN's, OpenVINO's, OpenEXR's pool, the compiled kernels). The CPU time is the work a frame
needs whatever the schedule, so

* ``CPU / cores`` is the wall time a perfectly parallel run could reach on this machine (the *floor*), and
  ``wall / (CPU / cores)`` how far the measured run is from it (1.0: nothing left to overlap);
* ``3600 / CPU`` is frames per core-hour, what a farm can plan capacity on (a saturated service's throughput
  per core, whatever the latency);
* "cores for T" is ``ceil(CPU / T)``: a lower bound on the cores at this speed that a latency target T can need
  (the same work, perfectly split; more if part of it stays serial).

Targets (``--targets``, seconds): the p50 targets for the 1280x720 two-layer frame (network 0.8, l1 1.5,
fused 2.0, the default oidn-l1 2.0). The models are the service's (``$GRADSEP_MODELS`` or
models/), on the provider it would pick. Run under the shared CPU lock, nothing else running.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from pathlib import Path
from typing import Any

#: The checkout; its models/ folder is the default when $GRADSEP_MODELS is unset.
REPO = Path(__file__).resolve().parents[1]

DEFAULT_TARGETS = "network=0.8,l1=1.5,fused=2.0,oidn-l1=2.0"


def parse_targets(text: str) -> dict[str, float]:
    """``method=seconds,...`` → {method: seconds}."""
    out = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        method, _, seconds = item.partition("=")
        out[method.strip()] = float(seconds)
    return out


def measure(source: bytes, method: str, repeats: int, models: Any) -> dict[str, float]:
    """Median wall and process-CPU seconds of run_pipeline(method) over ``repeats`` runs after one warm-up."""
    from gradsep.model.exr_read import ReadLimits, read_header
    from gradsep.model.policy import DEFAULT_ALPHA
    from gradsep.service.pipeline import ReconstructParams, run_pipeline

    compression = read_header(source).compression
    params = ReconstructParams(method=method, alpha=DEFAULT_ALPHA, half=False, layers="sum", compression=compression)

    def once() -> tuple[float, float, dict[str, float]]:
        wall, cpu = time.perf_counter(), time.process_time()
        outcome = run_pipeline(source, params, ReadLimits(), "reject", models)
        return time.perf_counter() - wall, time.process_time() - cpu, outcome.timings

    once()
    runs = [once() for _ in range(repeats)]
    stages = {k: statistics.median(r[2].get(k, 0.0) for r in runs) for k in runs[0][2]}
    return {"wall": statistics.median(r[0] for r in runs), "cpu": statistics.median(r[1] for r in runs), **stages}


def report(rows: dict[str, dict[str, float]], cores: int, targets: dict[str, float]) -> None:
    print(f"| method | wall s | CPU s | floor on {cores} cores (CPU / {cores}) | wall / floor | frames per core-hour "
          "| target p50 | cores for the target (≥) | stages (wall medians) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for method, r in rows.items():
        floor = r["cpu"] / cores
        target = targets.get(method)
        need = "" if target is None else str(max(1, math.ceil(r["cpu"] / target)))
        stages = " ".join(f"{k}={v:.3f}" for k, v in r.items() if k not in ("wall", "cpu"))
        print(f"| {method} | {r['wall']:.3f} | {r['cpu']:.3f} | {floor:.3f} | {r['wall'] / floor:.2f} | "
              f"{3600 / r['cpu']:.0f} | {'' if target is None else f'{target:g} s'} | {need} | {stages} |",
              flush=True)


def main() -> None:
    from gradsep.model.exr_read import read_frame
    from gradsep.model.exr_write import configure_exr_threads
    from gradsep.model.reconstruct import available_methods
    from gradsep.model.synthetic import synthetic_frame
    from gradsep.service.engine import load_models

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frame", type=Path, help="an EXR frame (default: gradsep.model.synthetic's frame)")
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT of the synthetic frame")
    parser.add_argument("--methods", default="", help="comma-separated (default: every method the frame allows)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--targets", default=DEFAULT_TARGETS, help="method=seconds,... (p50 targets to size for)")
    parser.add_argument("--json", action="store_true", help="also print the rows as JSON")
    args = parser.parse_args()

    if args.frame is not None:
        source, label = args.frame.read_bytes(), str(args.frame)
    else:
        width, height = (int(v) for v in args.size.lower().split("x"))
        source, label = synthetic_frame(height, width), f"synthetic {width}x{height}"
    configure_exr_threads(-1)  # as the service's Engine does, and its malloc arenas (model/allocator.py)
    from gradsep.model.allocator import configure_malloc

    arenas = configure_malloc()
    models = Path(os.environ.get("GRADSEP_MODELS", REPO / "models"))
    loaded = load_models(models)
    frame = read_frame(source)
    offered = available_methods(frame, loaded)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()] or list(offered)
    missing = [m for m in methods if m not in offered]
    if missing:
        raise SystemExit(f"this frame cannot be served by {', '.join(missing)} (it allows {', '.join(offered)})")
    cores = os.cpu_count() or 1
    h, w = next(iter(frame.layers.values())).base.shape[:2]
    print(f"{label}: {w}x{h}, layers {', '.join(frame.layers)}, {len(source) / 1e6:.1f} MB; {cores} CPUs, "
          f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}; malloc arenas "
          f"{arenas if arenas is not None else 'as glibc or MALLOC_ARENA_MAX set them'}; medians of {args.repeats}\n")
    rows = {m: measure(source, m, args.repeats, loaded) for m in methods}
    report(rows, cores, parse_targets(args.targets))
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\npeak RSS {peak:.0f} MiB; load average at the end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    if args.json:
        print(json.dumps({"frame": label, "cores": cores, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
