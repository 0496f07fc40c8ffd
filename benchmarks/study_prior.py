"""Prior-budget study of the ``network`` method (issue 15): how cheap may the truncated-L1 Poisson prior the shipped
models refine be before the *network's output* gets worse, and what each budget saves at 1280x720.

    python benchmarks/study_prior.py                 # error on the held-out frames + 720p prior time, medians
    python benchmarks/study_prior.py --skip-time     # the error table only
    python benchmarks/study_prior.py --repeats 7     # more timing repeats

Frames: benchmarks/study_refine.py's held-out cache (procedural seeds 81001-81008, 320x240 G-PT at 1, 4, 16, 64 spp,
two independent 1024-spp ``path`` references each; make it with ``python benchmarks/study_refine.py render --seeds
81001-81008 --spp 1,4,16,64``). Neither evaluation scenes (cbox, teapot, procedural 90001/90002) nor training seeds
(1000-1119). Error: RelMSE of the network's summed layers with the references' noise removed
(model.metrics.relmse_unbiased), as a ratio to today's prior budget on the same frame; geometric mean and worst frame.
Acceptance rule (issue 15): geometric mean within 1 % of today's and no frame more than 3 % worse.

Time: model.preprocess.poisson_prior on the direct layer of bench_service.py's synthetic 1280x720 frame, median.
Each variant overrides model.preprocess's PRIOR_* constants for the call. Run under the shared CPU lock.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_oidn import median_seconds  # noqa: E402

from gradsep.model import preprocess  # noqa: E402

DEFAULT_CACHE = Path(os.environ.get("GRADSEP_CACHE", Path.home() / ".cache" / "gradsep")) / "refine-study"
#: The budget the shipped models were trained with (the baseline every other variant is compared with).
TRAINED = {"PRIOR_IRLS_PASSES": 5, "PRIOR_CG_STEPS": 2, "PRIOR_PRECONDITIONER": "dct", "PRIOR_CG_TOLERANCE": 1e-3}
#: name -> the PRIOR_* constants it overrides.
VARIANTS: dict[str, dict[str, Any]] = {
    "trained: 5 passes x 2 dct CG": {},
    "4 x 2 dct": {"PRIOR_IRLS_PASSES": 4},
    "3 x 2 dct": {"PRIOR_IRLS_PASSES": 3},
    "2 x 2 dct": {"PRIOR_IRLS_PASSES": 2},
    "5 x 1 dct": {"PRIOR_CG_STEPS": 1},
    "3 x 1 dct": {"PRIOR_IRLS_PASSES": 3, "PRIOR_CG_STEPS": 1},
    "L2 start only (1 pass)": {"PRIOR_IRLS_PASSES": 1},
    "5 x 2 mg": {"PRIOR_PRECONDITIONER": "mg"},
    "3 x 2 mg": {"PRIOR_IRLS_PASSES": 3, "PRIOR_PRECONDITIONER": "mg"},
    "5 x 2 dct, tol 1e-1": {"PRIOR_CG_TOLERANCE": 1e-1},
}


@contextmanager
def prior_budget(overrides: dict[str, Any]) -> Iterator[None]:
    """gradsep.model.preprocess's prior constants set to TRAINED + ``overrides`` within the block."""
    values = {**TRAINED, **overrides}
    saved = {name: getattr(preprocess, name) for name in values}
    for name, value in values.items():
        setattr(preprocess, name, value)
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(preprocess, name, value)


def held_out_frames(cache: Path) -> Iterator[tuple[str, int, Path, np.ndarray, np.ndarray]]:
    """(scene folder name, spp, G-PT frame path, reference 1, reference 2) of every held-out frame of ``cache``
    whose scene has two references, scenes in name order and each scene's frames by spp."""
    for folder in sorted(p for p in cache.glob("procedural-*") if p.is_dir()):
        refs = sorted(folder.glob("ref-*.npz"))
        if len(refs) < 2:
            continue
        r1, r2 = (np.load(p)["total"] for p in refs[:2])
        for path in sorted(folder.glob("gpt-*.exr"), key=lambda p: int(p.stem.split("-")[1])):
            yield folder.name, int(path.stem.split("-")[1]), path, r1, r2


def error(cache: Path, variants: dict[str, dict[str, Any]]) -> None:
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.reconstruct import load_network

    network = load_network(REPO / "models")
    if network is None:
        raise SystemExit("no network models in models/")
    ratios: dict[str, list[float]] = {name: [] for name in variants}
    scores: dict[str, list[float]] = {name: [] for name in variants}
    frames = 0
    for _, _, path, r1, r2 in held_out_frames(cache):
        frame = read_frame(str(path))
        frames += 1
        baseline = None
        for name, overrides in variants.items():
            with prior_budget(overrides):
                total = sum(network.reconstruct_layer(n, layer, frame.features)
                            for n, layer in frame.layers.items() if n in network.layers)
            score = relmse_unbiased(total, r1, r2)
            baseline = score if baseline is None else baseline
            scores[name].append(score)
            ratios[name].append(score / baseline)
    if not frames:
        raise SystemExit(f"no held-out frames in {cache} (see the module docstring to render them)")
    print(f"\n{frames} held-out frames ({cache}); network RelMSE (unbiased) / the trained budget's, same frame\n")
    print("| prior budget | geo mean ratio | worst frame | mean RelMSE | accepted (<= 1.01, worst <= 1.03) |")
    print("|---|---:|---:|---:|---|")
    for name, r in ratios.items():
        geo = math.exp(sum(math.log(x) for x in r) / len(r))
        ok = geo <= 1.01 and max(r) <= 1.03
        print(f"| {name} | {geo:.4f} | {max(r):.4f} | {np.mean(scores[name]):.5f} | {'yes' if ok else 'no'} |")


def timing(variants: dict[str, dict[str, Any]], repeats: int) -> None:
    from bench_service import synthetic_frame

    from gradsep.model.frame import read_frame

    layer = read_frame(synthetic_frame(720, 1280)).layers["direct"]
    print(f"\nprior solve, 1280x720 direct layer, median of {repeats}, load {os.getloadavg()[0]:.2f}\n")
    print("| prior budget | ms |")
    print("|---|---:|")
    for name, overrides in variants.items():
        with prior_budget(overrides):
            seconds = median_seconds(lambda: preprocess.poisson_prior(layer), repeats)
        print(f"| {name} | {seconds * 1000:.0f} |", flush=True)
    print(f"load at the end {os.getloadavg()[0]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="study_refine.py's held-out frames")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-time", action="store_true")
    parser.add_argument("--skip-error", action="store_true")
    args = parser.parse_args()
    if not args.skip_error:
        error(args.cache, VARIANTS)
    if not args.skip_time:
        timing(VARIANTS, args.repeats)


if __name__ == "__main__":
    main()
