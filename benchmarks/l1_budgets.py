"""RelMSE and time of L1 solver configurations on rendered G-PT frames (not the synthetic benchmark frame).

    python benchmarks/l1_budgets.py --pairs /path/to/n2n16/frames --count 8 [--eval-cache DIR]

Two sources, each optional:

* ``--pairs DIR``: noise2noise pairs of a dataset folder (``proc_N.exr`` and its independent render ``proc_N.b.exr``):
  each layer of ``proc_N`` is reconstructed and compared with the *other* render's base. That reference is noisy,
  so absolute RelMSE values are inflated by a solver-independent term, but the differences between configurations
  are unbiased (the reference's noise is independent of the input).
* ``--study DIR``: benchmarks/study_refine.py's held-out cache (procedural seeds 81001-81008, G-PT 1/4/16/64 spp at
  320x240, two independent 1024-spp ``path`` references each): each layer against the truth with the references'
  noise removed (model.metrics.relmse_unbiased). Neither evaluation nor training scenes.
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

from gradsep.model.frame import read_frame  # noqa: E402
from gradsep.model.metrics import relmse, relmse_unbiased  # noqa: E402
from gradsep.model.poisson import solve_l1  # noqa: E402

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


def study_cases(cache: str) -> list[tuple[str, object, object]]:
    """(name, (reference 1, reference 2), layer) for every G-PT frame of study_refine.py's cache."""
    cases = []
    for folder in sorted(Path(cache).glob("procedural-*")):
        refs = sorted(folder.glob("ref-*.npz"))
        if len(refs) < 2:
            continue
        r1, r2 = (np.load(p) for p in refs[:2])
        for path in sorted(folder.glob("gpt-*.exr")):
            for name, layer in read_frame(path).layers.items():
                cases.append((f"{folder.name}/{path.stem}:{name}", (r1[name], r2[name]), layer))
    return cases


def _error(image: np.ndarray, ref) -> float:
    return relmse_unbiased(image, *ref) if isinstance(ref, tuple) else relmse(image, ref)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", help="a dataset frames folder with proc_N.exr / proc_N.b.exr pairs")
    p.add_argument("--count", type=int, default=8, help="pairs to use (default 8)")
    p.add_argument("--eval-cache", help="gradsep evaluate's cache folder (frames/, references/)")
    p.add_argument("--study", help="benchmarks/study_refine.py's cache folder (held-out procedural seeds)")
    p.add_argument("--per-case", action="store_true", help="also print every case's ratios")
    p.add_argument("--configs", nargs="*", default=list(DEFAULT_CONFIGS), help="solve_l1 keyword dict literals")
    args = p.parse_args(argv)
    cases = (pair_cases(args.pairs, args.count) if args.pairs else []) + (
        eval_cases(args.eval_cache) if args.eval_cache else []) + (
        study_cases(args.study) if args.study else [])
    if not cases:
        p.error("no frames: give --pairs, --eval-cache and/or --study")
    configs = [ast.literal_eval(c) for c in args.configs]
    rows = []
    for config in configs:
        errors, seconds = [], []
        for _, ref, layer in cases:
            start = time.perf_counter()
            image, _ = solve_l1(layer.base, layer.dx, layer.dy, **config)
            seconds.append(time.perf_counter() - start)
            errors.append(_error(image, ref))
        rows.append((config, errors, seconds))
    base_err = np.array(rows[0][1])
    print(f"{len(cases)} layers; ratios are per-layer RelMSE / the first configuration's, then summarised")
    print(f"{'configuration':<72}{'mean RelMSE':>12}{'ratio mean':>11}{'ratio geo':>10}{'ratio max':>10}"
          f"{'ratio min':>10}{'>1.1':>6}{'<0.9':>6}{'s/layer':>9}")
    for config, errors, seconds in rows:
        ratio = np.array(errors) / base_err
        geo = float(np.exp(np.mean(np.log(np.abs(ratio)))))
        print(f"{str(config):<72}{np.mean(errors):>12.5f}{ratio.mean():>11.4f}{geo:>10.4f}{ratio.max():>10.4f}"
              f"{ratio.min():>10.4f}{int((ratio > 1.1).sum()):>6}{int((ratio < 0.9).sum()):>6}"
              f"{statistics.mean(seconds):>9.3f}", flush=True)
    if args.per_case:
        print("case, RelMSE of the first configuration, then each other's ratio to it")
        for i, (name, _, _) in enumerate(cases):
            print(f"{name:<40}{base_err[i]:>10.5f}" + "".join(f"{r[1][i] / base_err[i]:>8.3f}" for r in rows[1:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
