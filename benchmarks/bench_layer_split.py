"""Where one 720p layer of the ``network`` method goes: the truncated-L1 prior, the ONNX graph, and the rest.

    python benchmarks/bench_layer_split.py              # 1280x720, medians of 5, this checkout's code and models
    python benchmarks/bench_layer_split.py --repeats 9
    python benchmarks/bench_layer_split.py --models runs/l2c-models   # models trained on another prior kind

"layer" is NetworkReconstructor.reconstruct_layer per layer (the frame's two layers one after the other, as the
service runs them, divided by 2); "prior" is model.preprocess.poisson_prior on the direct layer (of the kind the
direct model was trained on); "graph" the
direct model's session alone on ready inputs; "rest" = layer - prior - graph (sanitising, planes, transfer,
padding, output, the prior's input copies). bench_service.py's synthetic frame. Run under the shared CPU lock.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_oidn import median_seconds  # noqa: E402
from bench_service import synthetic_frame  # noqa: E402

from gradsep.model import preprocess  # noqa: E402
from gradsep.model.frame import read_frame  # noqa: E402
from gradsep.model.reconstruct import load_network  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--models", type=Path, default=REPO / "models", help="models folder (default models/)")
    args = parser.parse_args()
    frame = read_frame(synthetic_frame(args.height, args.width))
    network = load_network(args.models)
    if network is None:
        raise SystemExit(f"no network models in {args.models}")
    layer, features, model = frame.layers["direct"], frame.features, network.models["direct"]
    planes = preprocess.layer_planes(layer)
    data, gradient = (np.ascontiguousarray(preprocess.pad_to_alignment(a, model.alignment))
                      for a in preprocess.network_inputs(planes, preprocess.feature_planes(features)))
    names = [n for n in ("direct", "indirect") if n in frame.layers]
    seconds = {
        "layer": median_seconds(lambda: [network.reconstruct_layer(n, frame.layers[n], features) for n in names],
                                args.repeats) / len(names),
        "prior": median_seconds(lambda: preprocess.poisson_prior(layer, kind=model.prior), args.repeats),
        "graph": median_seconds(lambda: model.run(data, gradient), args.repeats),
    }
    seconds["rest"] = seconds["layer"] - seconds["prior"] - seconds["graph"]
    print(f"{args.width}x{args.height}, medians of {args.repeats}, {model.choice.provider}/{model.choice.precision}, "
          f"prior {model.prior}, load {os.getloadavg()[0]:.2f}: "
          + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in seconds.items()))


if __name__ == "__main__":
    main()
