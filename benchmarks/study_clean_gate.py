"""Design 27 (issue 14, session 21): a learned per-pixel gate over three estimates of a clean direct layer.

Design 25 (model/fused.py ``CLEAN_AVERAGE``) averages a clean direct layer's refinement R with the ``network``
method's image N at a fixed weight ½ where the two agree. This study asks whether a *learned* gate does better: per
pixel, softmax weights over R, N and P (the network's own truncated-L1 prior, which the network computes anyway), as
a linear function of fixed features; fused's clean-layer output would be R + w_f·(Σ_k π_k c_k − R), convex like
design 25's. docs/network.md, "Design 27", has the protocol and the results.

    collect OUT SOURCE...   per clean direct layer (w_f > 0) of each source: R, N, P, the base, and the scoring
                            target, into OUT/*.npz. A source is a study cache (study_direct_trust.py render: two
                            references per scene), a ``gradsep dataset --pairs`` folder (the twin realization's
                            base: the unsupervised target) or FRAME.exr@REF1.exr,REF2.exr (one frame, two
                            `gradsep reference` files).
    fit GLOB -o THETA.pt    fit the gate's weights to the frames GLOB names: on twins (``--pairs`` datasets) the
                            Noise2Noise loss against the second realization (unsupervised: what a shipped gate
                            would train on); on frames with references their RelMSE (supervised: an upper bound
                            for this gate family, never shippable). Each frame's loss is divided by R's.
    score GLOB --theta THETA.pt
                            the gate's direct-layer RelMSE (reference noise removed) as a ratio to design 25 per
                            frame, and N's, by source (geometric mean, worst, frames).

Only pixels where some candidate differs from R can move the loss, so the fit keeps those (over 1e-8 of the frame's
largest difference) and carries the rest as a constant.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CANDIDATES = ("R", "N", "P")  # the refinement, the network's image, the network's truncated-L1 prior
KEEP = 1e-8  # pixels whose candidates differ by more than this fraction of the frame's largest difference


# ---------------------------------------------------------------------------------------------------- collect

def _sources(source: str):
    """(key, frame path, targets) for every frame of one source (see the module docstring)."""
    from study_direct_trust import _frames

    from gradsep.model.frame import read_frame
    from gradsep.renderer.reference import load_reference

    if "@" in source:
        frame, refs = source.split("@")
        r1, r2 = (load_reference(p).images()["direct"] for p in refs.split(","))
        yield Path(frame).stem.replace("-", "_", 1), Path(frame), {"r1": r1, "r2": r2}  # grouped by scene
        return
    folder = Path(source).expanduser()
    if (folder / "manifest.json").is_file():
        for path in sorted((folder / "frames").glob("proc_*[0-9].exr")):
            twin = read_frame(str(path.with_suffix(".b.exr"))).layers["direct"].base
            yield f"{folder.name}_{path.stem}", path, {"twin": twin}
        return
    for label, path, r1, r2 in _frames(folder):
        yield f"{folder.name}_{label.replace(' ', '_')}", path, {"r1": r1["direct"], "r2": r2["direct"]}


def collect(out: Path, sources: list[str]) -> None:
    import study_direct_trust as trust

    from gradsep.model.frame import read_frame
    from gradsep.model.oidn import METHOD_SETTING, Denoiser, input_scale
    from gradsep.model.preprocess import poisson_prior

    den = Denoiser(METHOD_SETTING)
    out.mkdir(parents=True, exist_ok=True)
    for source in sources:
        for key, path, targets in _sources(source):
            dst = out / f"{key}.npz"
            if dst.is_file():
                continue
            frame = read_frame(str(path))
            trust._CONTEXT["features"] = frame.features
            aux = den.prefilter(frame.features) if frame.features is not None else None
            layer = frame.layers["direct"]
            denoised = den.denoise(layer.base, aux)
            refined, clean, network = trust._refined_clean_second(denoised, layer, None)
            if network is None:  # a noisy layer: design 25 and the gate leave it alone
                np.savez(dst, clean=False, wf=clean)
                continue
            np.savez_compressed(dst, clean=True, wf=clean, R=refined, N=network, P=poisson_prior(layer),
                                base=layer.base, s=input_scale(denoised), **targets)
            print(f"{key}: w_f {clean:.2f}", flush=True)
    den.close()


# ---------------------------------------------------------------------------------------------------- the gate

def _log_rho(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """log10 of design 25's per-pixel disagreement ρ (model.fused.disagreement) of two images already at the
    mean-1 exposure, + 1e-6."""
    from gradsep.model.fused import disagreement

    return np.log10(disagreement(a, b, 1.0) + 1e-6)


def features(z) -> np.ndarray:
    """(pixels, 13) at the refinement's mean-1 exposure: 1; log ρ of (R, N), (R, P), (N, P), (base, R); log
    luminance; 3² and 7² box means of log ρ(R, N) and log ρ(base, R); the base's local relative variance (5²); a
    black-pixel flag; the frame's log relative base-to-R difference (a noise level)."""
    from scipy.ndimage import uniform_filter

    s = float(z["s"])
    refined, network, prior, base = (z[k] * s for k in ("R", "N", "P", "base"))
    lum = np.mean(refined, -1)
    rn, br = _log_rho(refined, network), _log_rho(base, refined)
    out = [np.ones_like(lum), rn, _log_rho(refined, prior), _log_rho(network, prior), br, np.log10(lum + 1e-3)]
    for size in (3, 7):
        out += [uniform_filter(rn, size), uniform_filter(br, size)]
    b = np.mean(base, -1)
    var = np.maximum(uniform_filter(b * b, 5) - uniform_filter(b, 5) ** 2, 0)
    out.append(np.log10(var / (uniform_filter(lum, 5) ** 2 + 0.01) + 1e-6))
    out.append((lum <= 1e-6).astype(np.float64))
    noise = float(np.mean((base - refined) ** 2)) / (float(np.mean(refined ** 2)) + 1e-12)
    out.append(np.full_like(lum, math.log10(max(noise, 1e-8))))
    return np.stack(out, -1).reshape(-1, len(out))


def load(pattern: str) -> list[dict]:
    """The clean frames of ``pattern``: features, candidates and target of the pixels that can move the loss."""
    import glob

    import torch

    frames = []
    for path in sorted(glob.glob(str(Path(pattern).expanduser()))):
        z = np.load(path)
        if not z["clean"]:
            continue
        s = float(z["s"])
        cands = np.stack([z[k] for k in CANDIDATES]).reshape(3, -1, 3).astype(np.float64)
        diff = ((cands[1:] - cands[:1]) ** 2).sum((0, 2))
        keep = diff > KEEP * float(diff.max() + 1e-30)
        f = {"name": Path(path).stem, "wf": float(z["wf"]), "pixels": diff.size, "kept": int(keep.sum())}
        cols = {"F": features(z)[keep], "E": cands[:, keep]}
        if "r1" in z:
            r1, r2 = (z[k].reshape(-1, 3).astype(np.float64) for k in ("r1", "r2"))
            n = (0.5 * (r1 + r2)) ** 2 + 0.01
            cols.update(r1=r1[keep], r2=r2[keep], n=n[keep])
            full = (cands[0] - r1) * (cands[0] - r2) / n
        else:  # Noise2Noise: the twin at the same exposure; the weight from the first realization only
            t = z["twin"].reshape(-1, 3).astype(np.float64) * s
            n = np.repeat((np.mean(z["R"].astype(np.float64) * s, -1) ** 2 + 0.01).reshape(-1, 1), 3, 1)
            cols.update(t=t[keep], n=n[keep], s=np.full((int(keep.sum()), 1), s))
            full = (cands[0] * s - t) ** 2 / n
        f["const"] = float(full[~keep].sum()) / (diff.size * 3)  # the untouched pixels' share of the mean
        f.update({k: torch.tensor(v, dtype=torch.float64) for k, v in cols.items()})
        frames.append(f)
    return frames


def _batch(frames: list[dict]) -> dict:
    import torch

    out = {k: torch.cat([f[k] for f in frames], -2 if k == "E" else 0)
           for k in ("F", "E", "r1", "r2", "n", "t", "s") if k in frames[0]}
    out["wf"] = torch.cat([torch.full((f["kept"], 1), f["wf"], dtype=torch.float64) for f in frames])
    out["frame"] = torch.cat([torch.full((f["kept"],), i) for i, f in enumerate(frames)])
    out["pixels"] = torch.tensor([f["pixels"] * 3.0 for f in frames], dtype=torch.float64)
    out["const"] = torch.tensor([f["const"] for f in frames], dtype=torch.float64)
    return out


def per_frame_error(b: dict, out, count: int):
    """Each frame's mean loss of ``out`` (the kept pixels' (P, 3) images): RelMSE against the references, or the
    Noise2Noise loss against the twin."""
    import torch

    if "r1" in b:
        e = (out - b["r1"]) * (out - b["r2"]) / b["n"]
    else:
        e = (out * b["s"] - b["t"]) ** 2 / b["n"]
    return torch.zeros(count, dtype=torch.float64).index_add(0, b["frame"], e.sum(-1)) / b["pixels"] + b["const"]


def gated(b: dict, theta, mu, sd):
    """The gate's image on the kept pixels: R + w_f·(Σ_k π_k c_k − R), π = softmax(standardised features · θ)."""
    import torch

    weights = torch.softmax(((b["F"] - mu) / sd) @ theta, -1)
    mixed = (weights.T[..., None] * b["E"]).sum(0)
    return b["E"][0] + b["wf"] * (mixed - b["E"][0])


def design25(b: dict):
    """Design 25 on the kept pixels (model.fused.CLEAN_AVERAGE's gate, from feature 1, log ρ(R, N))."""
    import torch

    from gradsep.model.fused import CLEAN_AVERAGE, CLEAN_AVERAGE_WEIGHT

    low, high = CLEAN_AVERAGE
    g = torch.clamp((math.log10(high) - b["F"][:, 1]) / math.log10(high / low), 0.0, 1.0)[:, None]
    return b["E"][0] + CLEAN_AVERAGE_WEIGHT * b["wf"] * g * (b["E"][1] - b["E"][0])


def fit(pattern: str, iterations: int, output: Path) -> None:
    import torch

    torch.manual_seed(0)
    frames = [f for f in load(pattern) if f["kept"] > 0]
    b = _batch(frames)
    mu, sd = b["F"].mean(0), b["F"].std(0) + 1e-9
    mu[0], sd[0] = 0.0, 1.0
    base = per_frame_error(b, b["E"][0], len(frames))  # R's loss: each frame's weight
    keep = base > 0
    theta = torch.zeros(b["F"].shape[1], len(CANDIDATES), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([theta], lr=0.05)
    for it in range(iterations):
        opt.zero_grad()
        loss = (per_frame_error(b, gated(b, theta, mu, sd), len(frames))[keep] / base[keep]).mean()
        loss.backward()
        opt.step()
        if it % 100 == 0 or it == iterations - 1:
            print(f"iteration {it}: mean loss / R's {loss.item():.5f}", flush=True)
    torch.save({"theta": theta.detach(), "mu": mu, "sd": sd, "frames": len(frames), "pattern": pattern}, output)
    print(f"{len(frames)} frames; wrote {output}")


def _geo(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values))


def score(pattern: str, theta_path: Path) -> None:
    import torch

    saved = torch.load(theta_path)
    frames = [f for f in load(pattern) if f["kept"] > 0 and "r1" in f]
    b = _batch(frames)
    count = len(frames)
    d25 = per_frame_error(b, design25(b), count)
    gate = per_frame_error(b, gated(b, saved["theta"], saved["mu"], saved["sd"]), count) / d25
    net = per_frame_error(b, b["E"][1], count) / d25
    groups: dict[str, tuple[list[float], list[float]]] = {}
    for i, f in enumerate(frames):
        if not d25[i] > 0:
            continue
        group = f["name"].split("_")[0]
        groups.setdefault(group, ([], []))
        groups[group][0].append(float(gate[i]))
        groups[group][1].append(float(net[i]))
    print(f"\nRelMSE of the direct layer / design 25's (gate fitted on {saved['pattern']}, {saved['frames']} frames)\n")
    print("| source | frames | gate: geo | worst | better | network: geo | worst |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for group, (g, n) in groups.items():
        print(f"| {group} | {len(g)} | {_geo(g):.3f} | {max(g):.2f} | {sum(v < 1 for v in g)}/{len(g)} | "
              f"{_geo(n):.3f} | {max(n):.2f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("collect")
    p.add_argument("out", type=Path)
    p.add_argument("sources", nargs="+")
    p = sub.add_parser("fit")
    p.add_argument("pattern")
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("-o", "--output", type=Path, required=True)
    p = sub.add_parser("score")
    p.add_argument("pattern")
    p.add_argument("--theta", type=Path, required=True)
    args = parser.parse_args()
    import torch

    torch.set_num_threads(2)
    if args.command == "collect":
        collect(args.out, args.sources)
    elif args.command == "fit":
        fit(args.pattern, args.iterations, args.output)
    else:
        score(args.pattern, args.theta)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
