"""The demo `make demo` runs: reconstruct the shipped example frame with every available method and print its error.

The example is the shared Cornell box (mirror and glass spheres) at 96×96, made by

    gradsep render ../shared/scenes/cbox/cbox.xml --spp 16 --width 96 --height 96 --seed 7 -o examples/cbox-16spp.exr
    gradsep reference ../shared/scenes/cbox/cbox.xml --spp 4096 --width 96 --height 96 --seed 1 \\
        -o examples/cbox-reference.exr

Needs only the serving dependencies (numpy, scipy, OpenEXR, onnxruntime): no renderer, no torch.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from gradsep.model.exr_read import read_frame
from gradsep.model.methods import LoadedModels
from gradsep.model.methods import names as method_names
from gradsep.model.metrics import psnr, relmse
from gradsep.model.reconstruct import available_methods, reconstruct, unavailable_reason
from gradsep.renderer.reference import load_reference

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def main() -> int:
    frame = read_frame(HERE / "cbox-16spp.exr")
    reference = load_reference(HERE / "cbox-reference.exr").total
    models = LoadedModels.load(ROOT / "models")
    print(f"example: {frame.width}x{frame.height} frame, layers {', '.join(frame.layers)}, "
          f"{frame.metadata.get('gradsep.spp', '?')} spp; reference {reference.shape[1]}x{reference.shape[0]}")
    print(f"{'method':<10} {'RelMSE':>9} {'PSNR dB':>8} {'seconds':>8}")
    primal = frame.combined().base
    print(f"{'input':<10} {relmse(primal, reference):9.4f} {psnr(primal, reference):8.2f} {'-':>8}")
    methods = available_methods(frame, models)  # the methods table's default preference, best first
    for method in methods:
        start = time.perf_counter()
        result = reconstruct(frame, method, models=models)
        seconds = time.perf_counter() - start
        image = result.image
        assert np.isfinite(image).all()
        print(f"{method:<10} {relmse(image, reference):9.4f} {psnr(image, reference):8.2f} {seconds:8.2f}")
    for name in (n for n in method_names() if n not in methods):
        print(f"({name} did not run: {unavailable_reason(name, frame, models)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
