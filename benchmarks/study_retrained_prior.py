"""Issue 15: ``network`` models *retrained* on a cheaper prior against today's shipped models, on held-out frames.

    python benchmarks/study_retrained_prior.py --candidate runs/l2-models       # per-frame table + decision
    python benchmarks/study_retrained_prior.py --candidate runs/l2-models --time   # + 720p prior time per kind

``--candidate``: a folder with direct.onnx and indirect.onnx exported from ``gradsep train --prior KIND`` runs; each
model is served with the prior its metadata names (model.preprocess.POISSON_PRIORS). ``--baseline`` (default
models/): today's models.

Frames: benchmarks/study_refine.py's held-out cache, as benchmarks/study_prior.py (procedural seeds 81001-81008,
320x240 G-PT at 1, 4, 16, 64 spp, two independent 1024-spp ``path`` references each). Neither evaluation scenes
(cbox, teapot, procedural 90001/90002) nor training seeds (1000-1119). Error: RelMSE of the summed layers with the
references' noise removed (model.metrics.relmse_unbiased), per frame, for the candidate, the baseline and the
``l1`` method.

Acceptance rule, fixed before any result was looked at: the candidate is accepted when the geometric mean over
frames of RelMSE(candidate) / RelMSE(baseline) is <= 1.03, no frame's ratio exceeds 1.25, and the candidate beats
``l1`` (lower RelMSE) on at least as many frames as the baseline does.

Time (``--time``): model.preprocess.poisson_prior of each kind on the direct layer of bench_service.py's synthetic
1280x720 frame, median. Run under the shared CPU lock.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_oidn import median_seconds  # noqa: E402
from study_prior import held_out_frames  # noqa: E402

from gradsep.model import preprocess  # noqa: E402

DEFAULT_CACHE = Path(os.environ.get("GRADSEP_CACHE", Path.home() / ".cache" / "gradsep")) / "refine-study"
GEO_MEAN_MAX = 1.03
WORST_MAX = 1.25


def _network_total(network: Any, frame: Any) -> np.ndarray:
    return sum(network.reconstruct_layer(n, layer, frame.features)
               for n, layer in frame.layers.items() if n in network.layers)


def held_out_scores(cache: Path, baseline: Any, candidate: Any) -> list[dict[str, Any]]:
    """One row per held-out frame: its name and the RelMSE (unbiased) of baseline, candidate and l1."""
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.reconstruct import reconstruct

    rows = []
    for scene, spp, path, r1, r2 in held_out_frames(cache):
        frame = read_frame(str(path))
        rows.append({
            "frame": f"{scene.split('-')[1]} {spp} spp",
            "baseline": relmse_unbiased(_network_total(baseline, frame), r1, r2),
            "candidate": relmse_unbiased(_network_total(candidate, frame), r1, r2),
            "l1": relmse_unbiased(reconstruct(frame, "l1").image, r1, r2),
        })
        print(f"  {rows[-1]['frame']}: baseline {rows[-1]['baseline']:.5f} candidate "
              f"{rows[-1]['candidate']:.5f} l1 {rows[-1]['l1']:.5f}", file=sys.stderr, flush=True)
    return rows


def decide(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The acceptance rule of the module docstring."""
    ratios = [r["candidate"] / r["baseline"] for r in rows]
    geo = math.exp(sum(math.log(x) for x in ratios) / len(ratios))
    wins = {k: sum(r[k] < r["l1"] for r in rows) for k in ("baseline", "candidate")}
    accepted = geo <= GEO_MEAN_MAX and max(ratios) <= WORST_MAX and wins["candidate"] >= wins["baseline"]
    return {"geo_mean": geo, "worst": max(ratios), "worst_frame": rows[ratios.index(max(ratios))]["frame"],
            "best": min(ratios), "wins_vs_l1": wins, "accepted": accepted}


def report(rows: list[dict[str, Any]], candidate: Any) -> None:
    priors = sorted({m.prior for m in candidate.models.values()})
    print(f"\n{len(rows)} held-out frames; candidate prior(s): {', '.join(priors)}\n")
    print("| frame | today's network | candidate | ratio | l1 |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['frame']} | {r['baseline']:.5f} | {r['candidate']:.5f} | {r['candidate'] / r['baseline']:.3f} "
              f"| {r['l1']:.5f} |")
    d = decide(rows)
    print(f"\ngeometric-mean ratio {d['geo_mean']:.4f} (<= {GEO_MEAN_MAX}), worst frame {d['worst']:.4f} "
          f"({d['worst_frame']}; <= {WORST_MAX}), best {d['best']:.4f}; frames better than l1: today's "
          f"{d['wins_vs_l1']['baseline']}, candidate {d['wins_vs_l1']['candidate']} of {len(rows)}")
    for key in ("baseline", "candidate", "l1"):
        geo = math.exp(sum(math.log(r[key]) for r in rows) / len(rows))
        print(f"  {key}: mean RelMSE {np.mean([r[key] for r in rows]):.5f}, geometric mean {geo:.5f}")
    print(f"decision: {'ACCEPTED' if d['accepted'] else 'REJECTED'}")


def timing(repeats: int) -> None:
    from bench_service import synthetic_frame

    from gradsep.model.frame import read_frame

    layer = read_frame(synthetic_frame(720, 1280)).layers["direct"]
    print(f"\nprior solve, 1280x720 direct layer, median of {repeats}, load {os.getloadavg()[0]:.2f}\n")
    print("| prior kind | ms |")
    print("|---|---:|")
    for kind in preprocess.POISSON_PRIORS:
        seconds = median_seconds(lambda kind=kind: preprocess.poisson_prior(layer, kind=kind), repeats)
        print(f"| {kind} | {seconds * 1000:.0f} |", flush=True)
    print(f"load at the end {os.getloadavg()[0]:.2f}")


def main() -> None:
    from gradsep.model.reconstruct import load_network

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--candidate", type=Path, required=True, help="folder with the retrained direct/indirect.onnx")
    parser.add_argument("--baseline", type=Path, default=REPO / "models", help="today's models (default models/)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="study_refine.py's held-out frames")
    parser.add_argument("--time", action="store_true", help="also time each prior kind at 720p")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    baseline, candidate = load_network(args.baseline), load_network(args.candidate)
    if baseline is None or candidate is None:
        raise SystemExit(f"no network models in {args.baseline if baseline is None else args.candidate}")
    rows = held_out_scores(args.cache, baseline, candidate)
    if not rows:
        raise SystemExit(f"no held-out frames in {args.cache} (see benchmarks/study_prior.py to render them)")
    report(rows, candidate)
    if args.time:
        timing(args.repeats)


if __name__ == "__main__":
    main()
