"""RelMSE and time of L1 solver configurations on rendered G-PT frames (not the synthetic benchmark frame).

    python benchmarks/l1_budgets.py --pairs /path/to/n2n16/frames --count 8 [--eval-cache DIR]

Two sources, each optional:

* ``--pairs DIR``: noise2noise pairs of a dataset folder (``proc_N.exr`` and its independent render ``proc_N.b.exr``):
  each layer of ``proc_N`` is reconstructed and compared with the *other* render's base. That reference is noisy,
  so absolute RelMSE values are inflated by a solver-independent term, but the differences between configurations
  are unbiased (the reference's noise is independent of the input).
* ``--eval-cache DIR``: ``gradsep evaluate``'s cache (frames/SCENE/*.exr and references/SCENE/spp*-pass*.exr): each
  procedural scene's frames against the mean of its reference passes. cbox and teapot are skipped (the shared
  scenes nothing is tuned on).

Configurations are keyword sets of model.poisson.solve_l1 (``--configs`` takes Python dict literals); the first one
is the baseline the others are compared with (ratio of mean RelMSE, mean seconds per layer).
"""

from __future__ import annotations

import argparse
import ast
import glob
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.frame import read_frame  # noqa: E402
from model.metrics import relmse  # noqa: E402
from model.poisson import solve_l1  # noqa: E402

DEFAULT_CONFIGS = (
    "{'preconditioner': 'dct', 'iterations': 20, 'cg_iterations': 4}",
    "{'preconditioner': 'mg', 'iterations': 20, 'cg_iterations': 1}",
    "{'preconditioner': 'mg', 'iterations': 20, 'cg_iterations': 2}",
    "{'preconditioner': 'mg', 'iterations': 10, 'cg_iterations': 1}",
    "{'preconditioner': 'mg', 'iterations': 10, 'cg_iterations': 2}",
)


def pair_cases(folder: str, count: int) -> list[tuple[str, np.ndarray, object]]:
    cases = []
    for path in sorted(glob.glob(str(Path(folder) / "*.b.exr")))[:count]:
        a, b = read_frame(path.replace(".b.exr", ".exr")), read_frame(path)
        for name, layer in a.layers.items():
            cases.append((f"{Path(path).name}:{name}", b.layers[name].base, layer))
    return cases


def eval_cases(cache: str) -> list[tuple[str, np.ndarray, object]]:
    cases = []
    for scene_dir in sorted(Path(cache, "frames").iterdir()):
        if scene_dir.name in ("cbox", "teapot"):
            continue
        refs = [read_frame(p) for p in sorted(glob.glob(str(Path(cache, "references", scene_dir.name, "*.exr"))))]
        if not refs:
            continue
        for path in sorted(scene_dir.glob("*.exr")):
            frame = read_frame(path)
            for name, layer in frame.layers.items():
                ref = np.mean([r.layers[name].base for r in refs], axis=0)
                cases.append((f"{scene_dir.name}/{path.name}:{name}", ref, layer))
    return cases


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", help="a dataset frames folder with proc_N.exr / proc_N.b.exr pairs")
    p.add_argument("--count", type=int, default=8, help="pairs to use (default 8)")
    p.add_argument("--eval-cache", help="gradsep evaluate's cache folder (frames/, references/)")
    p.add_argument("--configs", nargs="*", default=list(DEFAULT_CONFIGS), help="solve_l1 keyword dict literals")
    args = p.parse_args(argv)
    cases = (pair_cases(args.pairs, args.count) if args.pairs else []) + (
        eval_cases(args.eval_cache) if args.eval_cache else [])
    if not cases:
        p.error("no frames: give --pairs and/or --eval-cache")
    configs = [ast.literal_eval(c) for c in args.configs]
    rows = []
    for config in configs:
        errors, seconds = [], []
        for _, ref, layer in cases:
            start = time.perf_counter()
            image, _ = solve_l1(layer.base, layer.dx, layer.dy, **config)
            seconds.append(time.perf_counter() - start)
            errors.append(relmse(image, ref))
        rows.append((config, errors, seconds))
    base_err = np.array(rows[0][1])
    print(f"{len(cases)} layers; ratios are per-layer RelMSE / the first configuration's, then summarised")
    print(f"{'configuration':<72}{'mean RelMSE':>12}{'ratio mean':>11}{'ratio max':>10}{'s/layer':>9}")
    for config, errors, seconds in rows:
        ratio = np.array(errors) / base_err
        print(f"{str(config):<72}{np.mean(errors):>12.5f}{ratio.mean():>11.4f}{ratio.max():>10.4f}"
              f"{statistics.mean(seconds):>9.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
