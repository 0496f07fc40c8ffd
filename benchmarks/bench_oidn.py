"""OIDN's cost per layer with prefiltered features (model/oidn.py, prefiltered-high), against a plain call.

    python benchmarks/bench_oidn.py                  # 1280x720, medians of 3 after one warm-up call each
    python benchmarks/bench_oidn.py --size 320x240

Reports, for a synthetic noisy HDR layer with random albedo/normal: ``pyoidn.denoise`` with the raw (noisy)
features (OIDN's default mode), the colour filter with prefiltered features (``cleanAux``, the
``prefiltered-high`` setting), and the two prefilter passes (albedo, normal) it runs once per frame. The ``oidn``
method's own setting (``raw-fast``: raw features, quality ``fast``; docs/oidn.md) is timed inside the service's
pipeline by bench_floor.py's ``oidn`` row; here it is timed on a two-layer frame beside ``prefiltered-high``, whose
extra time per pixel and layer is what a ``--seconds`` plan weighs before asking for it (renderer/render.py).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import numpy as np


def median_seconds(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up: device, filter and weights set up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> int:
    import pyoidn

    from gradsep.model.frame import Features
    from gradsep.model.oidn import Denoiser

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    rng = np.random.default_rng(0)
    image = rng.gamma(2.0, 0.5, (height, width, 3)).astype(np.float32)
    albedo = rng.uniform(0, 1, (height, width, 3)).astype(np.float32)
    normal = rng.uniform(-1, 1, (height, width, 3)).astype(np.float32)
    features = Features(albedo, normal, np.ones((height, width), np.float32))
    denoiser = Denoiser("prefiltered-high")
    aux = denoiser.prefilter(features)
    rows = [
        ("pyoidn.denoise, raw albedo/normal (one layer)",
         lambda: pyoidn.denoise(image, albedo, normal, hdr=True, quality="high")),
        ("colour filter, prefiltered features / cleanAux (one layer)", lambda: denoiser.denoise(image, aux)),
        ("prefilter of albedo + normal (once per frame)", lambda: denoiser.prefilter(features)),
    ]
    fast = Denoiser("raw-fast")

    def two_layers(den: Denoiser) -> Callable[[], object]:
        def run() -> None:
            frame_aux = den.prefilter(features)
            den.denoise(image, frame_aux)
            den.denoise(image, frame_aux)
        return run

    rows += [("raw-fast, a two-layer frame (the oidn method's default)", two_layers(fast)),
             ("prefiltered-high, a two-layer frame (its prefilter included)", two_layers(denoiser))]
    print(f"{width}x{height}, medians of {args.repeats}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    times = {}
    for label, fn in rows:
        times[label] = median_seconds(fn, args.repeats)
        print(f"{label:<62} {times[label]:7.3f} s")
    extra = (times[rows[-1][0]] - times[rows[-2][0]]) / (2 * width * height)
    print(f"{'prefiltered-high over raw-fast, per pixel and layer':<62} {extra * 1e6:7.3f} µs "
          "(renderer/render.py FARM_OIDN_EXTRA_SECONDS)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
