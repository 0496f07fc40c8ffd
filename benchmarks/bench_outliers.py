"""How far a single-pixel outlier reaches, per reconstruction method.

    python benchmarks/bench_outliers.py                                   # the example frame, every method
    python benchmarks/bench_outliers.py --frame tests/data/procedural-4242-16spp.exr --layer indirect
    python benchmarks/bench_outliers.py --methods l1,l2 --times 1e2,1e6

A firefly of ``times`` × the layer's mean is added to every channel of one pixel of the layer's base (corner, edge,
centre); for each method the output is compared with the output without it. Printed per case: the share of the
pixels farther than 16 px from the firefly within 1 % (relative, ε = 1e-3 of the frame's mean), the farthest
pixel outside that bound, and the share of the whole frame outside it. The denoising methods (oidn-l1, oidn, fused,
network) must keep >= 99.9 % beyond 16 px (tests/model/test_outliers.py); the screened Poisson methods (l2 linear,
l1 close to it) are measured, not bounded: their reach is the screened Poisson kernel's, ~1/α pixels per e-fold,
and the firefly's size decides how many e-folds it takes to fall under 1 %.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from gradsep.model.exr_read import read_frame
from gradsep.model.frame import Frame, Layer
from gradsep.model.methods import LoadedModels
from gradsep.model.reconstruct import load_fused, load_network, reconstruct
from gradsep.model.robust import far_agreement

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("oidn-l1", "oidn", "fused", "network", "l1", "l2")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frame", default=str(ROOT / "examples" / "cbox-16spp.exr"))
    parser.add_argument("--layer", default="direct")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--times", default="1e2,1e4,1e8,1e30", help="firefly sizes, in units of the layer's mean")
    parser.add_argument("--models", default=str(ROOT / "models"))
    parser.add_argument("--radius", type=float, default=16.0)
    args = parser.parse_args()

    frame = read_frame(args.frame)
    models = {"network": load_network(args.models), "fused": load_fused(args.models)}
    layer = frame.layers[args.layer]
    mean = float(layer.base.mean(dtype=np.float64))
    positions = {"corner": (0, 0), "edge": (frame.height // 2, frame.width - 1),
                 "centre": (frame.height // 2, frame.width // 2)}
    print(f"{args.frame}: {frame.width}x{frame.height}, firefly in the {args.layer} layer (mean {mean:.4g})")
    print(f"{'method':8s} {'where':6s} {'times':>7s} {'kept beyond':>12s} {'reach px':>9s} {'changed':>8s}")
    for method in args.methods.split(","):
        kwargs = {"models": LoadedModels(**{method: models[method]})} if method in models else {}
        if method in models and models[method] is None:
            print(f"{method:8s} skipped: no models")
            continue
        reference = reconstruct(frame, method, **kwargs).image
        for name, where in positions.items():
            for times in (float(t) for t in args.times.split(",")):
                base = layer.base.copy()
                base[where] += np.float32(min(times * mean, 3e38))
                hit = Frame({**frame.layers, args.layer: Layer(base, layer.dx, layer.dy)}, frame.features)
                image = reconstruct(hit, method, **kwargs).image
                kept, reach = far_agreement(image, reference, where, args.radius)
                changed = 1.0 - far_agreement(image, reference, where, -1.0)[0]
                print(f"{method:8s} {name:6s} {times:7.0e} {100 * kept:11.3f}% {reach:9.1f} {100 * changed:7.2f}%",
                      flush=True)


if __name__ == "__main__":
    main()
