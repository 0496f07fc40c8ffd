"""How far an outlier reaches, per reconstruction method, and what the outlier handling costs a clean frame.

    python benchmarks/bench_outliers.py                              # the locality table on the example frame
    python benchmarks/bench_outliers.py --frames examples/cbox-16spp.exr,tests/data/procedural-4242-16spp.exr
    python benchmarks/bench_outliers.py --methods l1,l2 --times 1e3,1e12
    python benchmarks/bench_outliers.py --clean examples/cbox-16spp.exr:examples/cbox-reference.exr

Locality: an outlier is put into *both* layers of the frame as a gradient-domain renderer writes one
(model.synthetic.with_outlier): its excess of K x the frame's mean in every channel of one pixel (``grad``), of a
horizontal pair (``pair``) or of a 3x3 block (``block``), the same jump in the layer's gradients, and the variance
of a single sample that large in ``L.var.Y``. For each method the output is compared with its output without the
outlier; printed per case: the share of the pixels farther than 16 px from it that moved by more than 1 %
(relative, with an epsilon of 1e-3 of the frame's mean), the farthest such pixel, and whether a warning counted it.
The denoising methods (oidn-l1, oidn, fused, network) are held to at most 0.1 % (tests/model/test_outliers.py).

Positions (``--positions grid``): the same at nine places (model.synthetic.places: a quarter, half and three
quarters of each side) instead of the centre alone, one line per method and case: at how many of them it held, and
the worst share. ``--hidden``: the same with the content the outlier hid given back (the detector's fills set to
what the frame without the outlier holds there, model.synthetic.hidden_given_back): what is left is the handling's
own reach.

Attribution (``--attribute``, ``network`` only): per case, the share moved and how bright the moved far pixels are
(their median in the output without the outlier, over the frame's mean), then the share again with the network's
Poisson prior taken, farther than R px from the outlier, from the frame without it (R = 16, 24, 32, 48): where
that share is 0 the network itself is local and the far change is its prior's (docs/decisions.md); and the share
moved when, with no outlier, the block's own content is replaced by a copy of the 3x3 patch 3 px to its right or
below (what any filling of an erased block changes). ``--prior-alpha A`` and ``--prior-budget PASSESxSTEPS`` solve
the network's prior with another alpha or IRLS budget, in every mode (the shipped models were trained on neither).

Clean-frame cost (``--clean FRAME:REFERENCE,...``): each method's RelMSE against the reference with the outlier
handling as shipped and with it switched off, and the handling's own time on the frame.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from gradsep.model.exr_read import read_frame
from gradsep.model.frame import Frame
from gradsep.model.methods import LoadedModels
from gradsep.model.metrics import relmse
from gradsep.model.reconstruct import load_fused, load_network, reconstruct
from gradsep.model.robust import FAR_KEPT, FAR_RADIUS, far_agreement
from gradsep.model.synthetic import CASES, hidden_given_back, places, with_outlier

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("oidn-l1", "oidn", "fused", "network", "l1", "l2")


def _models(method: str, loaded: dict[str, object]) -> LoadedModels | None:
    """The loaded models ``method`` needs, or None when this machine lacks them."""
    from gradsep.model import methods as table

    sets = {name: loaded.get(name, True) for name in table.get(method).models}
    if any(value is None or value is False for value in sets.values()):
        return None
    return LoadedModels(**sets)


def locality(frame: Frame, method: str, models: LoadedModels, times: list[float], radius: float) -> list[str]:
    """One line per (case, K): the share of far pixels moved, the reach, and the warnings' outlier count."""
    reference = reconstruct(frame, method, models=models).image
    where = (frame.height // 2, frame.width // 2)
    lines = []
    for case in CASES:
        cells = []
        for k in times:
            result = reconstruct(with_outlier(frame, case, where, k), method, models=models)
            kept, reach = far_agreement(result.image, reference, where, radius)
            warned = "w" if any(w.startswith("layer ") for w in result.warnings) else "-"
            cells.append(f"{100 * (1 - kept):6.2f}% {reach:5.1f}px {warned}")
        lines.append(f"{method:8s} {case:6s} " + " | ".join(cells))
    return lines


def positions(frame: Frame, method: str, models: LoadedModels, times: list[float], radius: float,
              hidden: bool) -> list[str]:
    """One line per case: at how many of model.synthetic.places' nine places every K held the contract (FAR_KEPT),
    and the worst share moved; ``hidden``: with the content the outlier hid given back
    (model.synthetic.hidden_given_back)."""
    from gradsep.model import outliers

    reference = reconstruct(frame, method, models=models).image
    own = outliers.split_frame

    def given_back(hit: Frame, sources: bool = False, threads: int = 1) -> tuple[Frame, object]:
        handled, split = own(hit, sources, threads)
        return hidden_given_back(frame, hit, handled), split

    if hidden:
        outliers.split_frame = given_back
    try:
        lines = []
        spots = places(frame)
        for case in CASES:
            kept = [min(far_agreement(reconstruct(with_outlier(frame, case, where, k), method, models=models).image,
                                      reference, where, radius)[0] for k in times) for where in spots]
            held = sum(share >= FAR_KEPT for share in kept)
            worst = 100 * (1 - min(kept))
            lines.append(f"{method:8s} {case:6s} held at {held}/{len(spots)} places, worst {worst:.2f}%")
    finally:
        outliers.split_frame = own
    return lines


def _network_image(frame: Frame, network: object, prior: object = None) -> np.ndarray:
    """The ``network`` method's image of ``frame`` after the detector, layer by layer; ``prior(name)`` (optional)
    gives the function the network's Poisson prior is computed with for that layer."""
    from gradsep.model import infer, outliers

    handled, split = outliers.split_frame(frame)
    own = infer.poisson_prior
    total = np.zeros((frame.height, frame.width, 3))
    try:
        for name, layer in handled.layers.items():
            infer.poisson_prior = own if prior is None else prior(name, handled.layers[name])
            total += split.restore(name, network.reconstruct_layer(name, layer, handled.features))
    finally:
        infer.poisson_prior = own
    return total


def attribute(frame: Frame, network: object, radii: tuple[int, ...] = (16, 24, 32, 48)) -> list[str]:
    """Per case: the far share moved, the moved pixels' median brightness, and the share with the prior beyond
    each radius taken from the frame without the outlier."""
    from gradsep.model import infer
    from gradsep.model.preprocess import poisson_prior, scaled_layer

    reference = _network_image(frame, network)
    where = (frame.height // 2, frame.width // 2)
    yy, xx = np.mgrid[0:frame.height, 0:frame.width]
    distance = np.hypot(yy - where[0], xx - where[1])
    lines = [f"network  refill {_refilled(frame, network, reference, where, offset):.2f}% moved with the block's "
             f"content copied from {offset} px away" for offset in ((0, 3), (3, 0))]
    for case in CASES:
        hit = with_outlier(frame, case, where, 1e3)
        image = _network_image(hit, network)
        moved = np.any(np.abs(image - reference) > 0.01 * (np.abs(reference) + 1e-3 * reference.mean()), axis=-1)
        moved &= distance > 16
        level = float(np.median(reference[moved].mean(axis=-1)) / reference.mean()) if moved.any() else 0.0
        shares = []
        for radius in radii:
            far = (distance > radius)[..., None]

            def prior(name: str, layer: object, far: np.ndarray = far) -> object:
                clean = poisson_prior(scaled_layer(frame.layers[name], 1.0 / infer.exposure_scale(layer)),
                                      alpha=network.models[name].prior_alpha)
                return lambda lay, **kw: np.where(far, clean, poisson_prior(lay, **kw))

            kept, _ = far_agreement(_network_image(hit, network, prior), reference, where, 16)
            shares.append(f"{100 * (1 - kept):.2f}")
        lines.append(f"network  {case:6s} {100 * moved.sum() / max((distance > 16).sum(), 1):.2f}% "
                     f"moved, median {level:.4f}x the mean; clean prior beyond {'/'.join(map(str, radii))} px: "
                     f"{'/'.join(shares)} %")
    return lines


def _refilled(frame: Frame, network: object, reference: np.ndarray, where: tuple[int, int],
              offset: tuple[int, int]) -> float:
    """The far share moved when the 3x3 block at ``where`` holds, in base and gradients, the patch ``offset`` away."""
    from dataclasses import replace

    from gradsep.model.frame import Layer

    (y, x), (dy, dx) = where, offset
    layers = {}
    for name, layer in frame.layers.items():
        planes = [np.array(a, copy=True) for a in (layer.base, layer.dx, layer.dy)]
        for plane in planes:
            plane[y:y + 3, x:x + 3] = plane[y + dy:y + dy + 3, x + dx:x + dx + 3]
        layers[name] = Layer(*planes, layer.var)
    kept, _ = far_agreement(_network_image(replace(frame, layers=layers), network), reference, where, 16)
    return 100 * (1 - kept)


def clean_cost(frame: Frame, reference: np.ndarray, method: str, models: LoadedModels) -> str:
    """RelMSE with the outlier handling and without it, and the handling's time on this frame."""
    from gradsep.model import outliers

    shipped = reconstruct(frame, method, models=models).image
    start = time.perf_counter()
    split = outliers.split_frame(frame)
    seconds = time.perf_counter() - start
    saved = outliers.split_frame
    outliers.split_frame = lambda frame, sources=False, threads=1: (frame, outliers.FrameSplit())
    try:
        without = reconstruct(frame, method, models=models).image
    finally:
        outliers.split_frame = saved
    found = sum(s.handled for s in split[1].layers.values())
    return (f"{method:8s} relmse {relmse(shipped, reference):.6f} without handling {relmse(without, reference):.6f} "
            f"outliers found {found} detector {1000 * seconds:.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", default=str(ROOT / "examples" / "cbox-16spp.exr"), help="comma-separated EXRs")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--times", default="1e3,1e6,1e12", help="outlier sizes, in units of the frame's mean")
    parser.add_argument("--models", default=str(ROOT / "models"))
    parser.add_argument("--radius", type=float, default=FAR_RADIUS)
    parser.add_argument("--attribute", action="store_true", help="network: is the far change its prior's?")
    parser.add_argument("--positions", choices=("centre", "grid"), default="centre",
                        help="where the outlier goes: the centre (each K on its own) or nine places (summarised)")
    parser.add_argument("--hidden", action="store_true",
                        help="with --positions grid: give back the content the outlier hid")
    parser.add_argument("--clean", default="", help="comma-separated FRAME:REFERENCE pairs for the clean-frame cost")
    parser.add_argument("--prior-alpha", type=float, default=None,
                        help="solve the network's prior with this alpha, not the models' own")
    parser.add_argument("--prior-budget", default=None, help="the network prior's IRLS budget, PASSESxSTEPS")
    args = parser.parse_args()
    from gradsep.model import infer, preprocess

    if args.prior_alpha is not None:  # LoadedModel.prior_alpha asks this function for every layer it solves
        infer.prior_alpha_of = lambda meta: args.prior_alpha
    if args.prior_budget:
        preprocess.PRIOR_IRLS_PASSES, preprocess.PRIOR_CG_STEPS = (int(v) for v in args.prior_budget.split("x"))

    loaded = {"network": load_network(args.models), "fused": load_fused(args.models)}
    methods = args.methods.split(",")
    times = [float(t) for t in args.times.split(",")]
    for pair in filter(None, args.clean.split(",")):
        path, ref_path = pair.split(":")
        frame, reference = read_frame(path), read_frame(ref_path)
        ref_image = sum(layer.base for layer in reference.layers.values())
        print(f"clean {path} against {ref_path}")
        for method in methods:
            models = _models(method, loaded)
            print(clean_cost(frame, ref_image, method, models) if models else f"{method:8s} skipped: no models",
                  flush=True)
    if args.clean:
        return
    if args.attribute and loaded["network"] is None:
        raise SystemExit("--attribute needs the network models")
    if args.attribute:
        for path in args.frames.split(","):
            print(f"{path}: network, far = > 16 px, K = 1e3")
            for line in attribute(read_frame(path), loaded["network"]):
                print(line, flush=True)
        return
    for path in args.frames.split(","):
        frame = read_frame(path)
        print(f"{path}: {frame.width}x{frame.height}; share of pixels > {args.radius:g} px away moved > 1 %, "
              f"reach, w = warned; K = {', '.join(f'{k:g}' for k in times)}")
        for method in methods:
            models = _models(method, loaded)
            if models is None:
                print(f"{method:8s} skipped: no models")
                continue
            lines = (positions(frame, method, models, times, args.radius, args.hidden)
                     if args.positions == "grid" else locality(frame, method, models, times, args.radius))
            for line in lines:
                print(line, flush=True)


if __name__ == "__main__":
    main()
