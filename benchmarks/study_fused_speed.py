"""Speed/quality frontier of the ``fused`` method (issue 15: fused within 2.0 s; issue 14: its quality).

    python benchmarks/study_fused_speed.py error            # held-out RelMSE of every variant vs fused before
    python benchmarks/study_fused_speed.py error --per-frame
    python benchmarks/study_fused_speed.py time --repeats 3 # 1280x720: each stage's wall and CPU seconds

A *variant* changes what fused computes per layer beyond the one OIDN pass (raw-fast, model.fused.OIDN_SETTING)
that every variant shares: the direct layer's refinement budget (IRLS passes, the per-pass CG tolerance and its
step cap; model/refine.py's data weight is left as it is) and, on the indirect layer, the ``refine-fast``
candidate's solve and the resolution the blend network sees (``net/2``: its inputs 2x2-averaged, its weights
upsampled back bilinearly; the weights stay convex). VARIANTS lists them; ``before`` is fused as it was before
this study (the direct layer at the oidn-l1 method's full solve), ``shipped`` what model/fused.py serves now.

Frames: the held-out procedural seeds 81001-81008 of benchmarks/study_refine.py (320x240 G-PT at 1, 4, 16, 64 spp,
two independent 1024-spp references each, ~/.cache/gradsep/refine-study): never the evaluation's scenes (cbox,
teapot, procedural:90001/90002), never the training seeds. Error: RelMSE with the references' noise removed
(model.metrics.relmse_unbiased), as a ratio to ``before`` per frame: geometric mean, worst frame, and the same
for ``oidn-l1`` (the oidn-l1 method: its direct refinement + OIDN's indirect layer) as the bar fused must stay below.

Time: benchmarks/study_fused.py's 1280x720 frame (a held-out frame tiled), each stage timed alone (median wall
and process CPU seconds of ``--repeats`` after a warm-up). On the 2-core machine OIDN runs on both cores and the
rest mostly on one, so CPU seconds / 2 bounds a perfectly pipelined frame; the wall of the whole method through
model.reconstruct is printed too. Run both under the shared CPU lock.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


@dataclass(frozen=True)
class Variant:
    """What fused computes after OIDN. ``direct``: (IRLS passes, CG tolerance, CG step cap) of the direct layer's
    refinement, or None for OIDN's image alone; ``fast``: (passes, V-cycles per pass) of the indirect
    ``refine-fast`` candidate; ``net_scale``: 1, or 2 to run the blend network on a half-resolution layer."""

    direct: tuple[int, float, int] | None = (8, 0.1, 8)
    fast: tuple[int, int] = (3, 1)
    net_scale: int = 1
    blend: bool = True  # False: the indirect layer is OIDN's image (the oidn-l1 method)
    oidn_half: tuple[str, ...] = ()  # layers whose OIDN image is computed at half resolution and upsampled


def _shipped() -> Variant:
    """What model/fused.py serves: the direct refinement at its DIRECT_CG budget (passes: model/refine.py's)."""
    from gradsep.model.fused import DIRECT_CG
    from gradsep.model.refine import REFINE_ITERATIONS

    return Variant(direct=(REFINE_ITERATIONS, *DIRECT_CG))


VARIANTS: dict[str, Variant] = {
    "before": Variant(),  # fused before issue 15's budget study: the oidn-l1 method's full solve on direct
    "shipped": _shipped(),
    "oidn-l1": Variant(blend=False),
    "oidn-l1@DIRECT_CG": Variant(direct=(8, 0.1, 4), blend=False),  # the oidn-l1 method at fused's direct budget
    "d6": Variant(direct=(6, 0.1, 8)),
    "d5": Variant(direct=(5, 0.1, 8)),
    "d4": Variant(direct=(4, 0.1, 8)),
    "d3": Variant(direct=(3, 0.1, 8)),
    "d8t.2": Variant(direct=(8, 0.2, 8)),
    "d6t.2": Variant(direct=(6, 0.2, 8)),
    "d5t.2": Variant(direct=(5, 0.2, 8)),
    "d4t.2": Variant(direct=(4, 0.2, 8)),
    "d8t.3": Variant(direct=(8, 0.3, 8)),
    "d6t.3": Variant(direct=(6, 0.3, 8)),
    "d8s2": Variant(direct=(8, 0.1, 2)),
    "d6s2": Variant(direct=(6, 0.1, 2)),
    "d8s1": Variant(direct=(8, 0.1, 1)),
    "d5s1": Variant(direct=(5, 0.1, 1)),
    "d7": Variant(direct=(7, 0.1, 8)),
    "d7t.2": Variant(direct=(7, 0.2, 8)),
    "d8t.25": Variant(direct=(8, 0.25, 8)),
    "d8t.15": Variant(direct=(8, 0.15, 8)),
    "d8t.15c4": Variant(direct=(8, 0.15, 4)),
    "d8t.15c3": Variant(direct=(8, 0.15, 3)),
    "d8t.1c4": Variant(direct=(8, 0.1, 4)),
    "d8t.1c3": Variant(direct=(8, 0.1, 3)),
    "d8t.2c4": Variant(direct=(8, 0.2, 4)),
    "d8t.2c3": Variant(direct=(8, 0.2, 3)),  # shipped before the trust rule was merged
    "net/2": Variant(net_scale=2),
    "fast2x1": Variant(fast=(2, 1)),
    "fast1x1": Variant(fast=(1, 1)),
    "fast2x1+d8t.2": Variant(direct=(8, 0.2, 8), fast=(2, 1)),
    "fast2x1+d8t.2c4": Variant(direct=(8, 0.2, 4), fast=(2, 1)),
    "d5+net/2": Variant(direct=(5, 0.1, 8), net_scale=2),
    "d4t.2+net/2": Variant(direct=(4, 0.2, 8), net_scale=2),
    # OIDN at half resolution (2x2-averaged colour and features, bilinear back): a quarter of its cost
    "oidn/2-direct": Variant(direct=_shipped().direct, oidn_half=("direct",)),
    "oidn/2-both": Variant(direct=_shipped().direct, oidn_half=("direct", "indirect")),
    "oidn-l1+oidn/2-direct": Variant(direct=(8, 0.1, 4), blend=False, oidn_half=("direct",)),
}


def _hwc_pool2(x: np.ndarray) -> np.ndarray:
    """(H, W[, C]) → 2x2 means (edge-replicated to even sizes)."""
    y = x if x.ndim == 3 else x[..., None]
    out = _pool2(np.moveaxis(y, -1, 0).astype(np.float32))
    out = np.moveaxis(out, 0, -1)
    return out if x.ndim == 3 else out[..., 0]


def half_res_denoise(den, color: np.ndarray, features) -> np.ndarray:
    """OIDN on the 2x2-averaged colour with 2x2-averaged albedo and (renormalised) normal, upsampled bilinearly."""
    from gradsep.model.frame import Features

    normal = _hwc_pool2(features.normal)
    norm = np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.where(norm > 1e-6, normal / np.maximum(norm, 1e-6), 0.0).astype(np.float32)
    small = Features(np.ascontiguousarray(_hwc_pool2(features.albedo)), np.ascontiguousarray(normal),
                     np.ascontiguousarray(_hwc_pool2(features.depth)))
    out = den.denoise(np.ascontiguousarray(_hwc_pool2(color)), den.prefilter(small))
    h, w = color.shape[:2]
    return np.moveaxis(_upsample2(np.moveaxis(out, -1, 0), h, w), 0, -1)


def _pool2(x: np.ndarray) -> np.ndarray:
    """(C, H, W) → (C, ceil(H/2), ceil(W/2)) by 2x2 means (edge-replicated to even sizes)."""
    c, h, w = x.shape
    x = np.pad(x, [(0, 0), (0, h % 2), (0, w % 2)], mode="edge")
    return x.reshape(c, x.shape[1] // 2, 2, x.shape[2] // 2, 2).mean(axis=(2, 4), dtype=np.float32)


def _upsample2(w: np.ndarray, h: int, wd: int) -> np.ndarray:
    """(K, h2, w2) → (K, H, W): bilinear at pixel centres (a convex combination: weights stay convex)."""
    k, h2, w2 = w.shape
    ys = np.clip((np.arange(h) + 0.5) / 2 - 0.5, 0, h2 - 1)
    xs = np.clip((np.arange(wd) + 0.5) / 2 - 0.5, 0, w2 - 1)
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    y1, x1 = np.minimum(y0 + 1, h2 - 1), np.minimum(x0 + 1, w2 - 1)
    fy, fx = (ys - y0)[:, None], (xs - x0)[None, :]
    rows = w[:, y0] * (1 - fy) + w[:, y1] * fy
    return (rows[:, :, x0] * (1 - fx) + rows[:, :, x1] * fx).astype(np.float32)


def weights(model, data: np.ndarray, gradient: np.ndarray, net_scale: int) -> np.ndarray:
    """The blend model's (K, H, W) weights at full resolution, or computed at half resolution and upsampled."""
    if net_scale == 1:
        return model.weights(data, gradient)
    # gradients over 2 pixels of the pooled image: the sum of two neighbouring 1-pixel differences ≈ 2x the mean
    small = model.weights(_pool2(data), 2.0 * _pool2(gradient))
    return _upsample2(small, *data.shape[1:])


def direct_image(layer, denoised: np.ndarray, spec: tuple[int, float, int] | None) -> np.ndarray:
    """The direct layer: OIDN's image refined with ``spec``'s budget (at fused's exposure, then scaled back)."""
    from gradsep.model import refine as refine_mod
    from gradsep.model.preprocess import prior_exposure, scaled_image, scaled_layer

    if spec is None:
        return denoised
    passes, tol, cap = spec
    scale = prior_exposure(denoised)
    scaled, oidn = scaled_layer(layer, scale), scaled_image(denoised, scale)
    saved = refine_mod.REFINE_MAX_CG_STEPS
    refine_mod.REFINE_MAX_CG_STEPS = cap
    try:
        image = refine_mod.refine_layer("direct", oidn, scaled, passes=passes, cg_tolerance=tol)
    finally:
        refine_mod.REFINE_MAX_CG_STEPS = saved
    return np.clip(np.asarray(image, np.float64) / scale, 0, None).astype(np.float32)


def indirect_image(layer, denoised: np.ndarray, features, model, variant: Variant) -> np.ndarray:
    """The indirect layer: the blend of {OIDN, refine-fast at ``variant.fast``} with the shipped model."""
    from gradsep.model.fused import blend, blend_inputs
    from gradsep.model.preprocess import prior_exposure, scaled_image, scaled_layer
    from gradsep.model.refine import refine_layer

    if not variant.blend:
        return denoised
    scale = prior_exposure(denoised)
    scaled, oidn = scaled_layer(layer, scale), scaled_image(denoised, scale)
    passes, cycles = variant.fast
    fast = refine_layer("direct", oidn, scaled, 1.0, preconditioner="mg", cg_steps=cycles, passes=passes,
                        warm_start=False)
    cands = [oidn, np.clip(fast, 0, None).astype(np.float32)]
    data, gradient = blend_inputs(scaled, cands, features)
    return blend(weights(model, data, gradient, variant.net_scale), cands, scale)


def _geo(values: list[float]) -> float:
    return math.exp(statistics.fmean(math.log(max(v, 1e-12)) for v in values))


def error(names: list[str], per_frame: bool) -> None:
    from study_fused import REFINE_CACHE, _frames

    from gradsep.model.frame import read_frame
    from gradsep.model.fused import OIDN_SETTING
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.oidn import shared_denoiser
    from gradsep.model.reconstruct import load_fused, reconstruct

    fused = load_fused("models")
    model = fused.models["indirect"]
    den = shared_denoiser(OIDN_SETTING)
    ratios: dict[str, list[float]] = {n: [] for n in names}
    for scene, spp, path in _frames():
        frame = read_frame(str(path))
        r1, r2 = (np.load(p)["total"] for p in sorted((REFINE_CACHE / scene).glob("ref-*.npz"))[:2])
        aux = den.prefilter(frame.features)
        dn = {n: den.denoise(lay.base, aux) for n, lay in frame.layers.items()}
        half: dict[str, np.ndarray] = {}
        scores = {}
        for name in names:
            v = VARIANTS[name]
            for n in v.oidn_half:
                if n not in half:
                    half[n] = half_res_denoise(den, frame.layers[n].base, frame.features)
            d = {n: half[n] if n in v.oidn_half else dn[n] for n in dn}
            image = (direct_image(frame.layers["direct"], d["direct"], v.direct)
                     + indirect_image(frame.layers["indirect"], d["indirect"], frame.features, model, v))
            scores[name] = relmse_unbiased(image, r1, r2)
        if "shipped" in names and scene.endswith("81001") and spp == 16:  # this study's path == the served method
            served = relmse_unbiased(reconstruct(frame, "fused", fused=fused).image, r1, r2)
            assert abs(served / scores["shipped"] - 1) < 1e-3, (served, scores["shipped"])
        for name in names:
            ratios[name].append(scores[name] / scores["before"])
        if per_frame:
            print(f"{scene} {spp:>2} spp: before {scores['before']:.3g}; " + " ".join(
                f"{n}={scores[n] / scores['before']:.3f}" for n in names if n != "before"), flush=True)
    bar = ratios.get("oidn-l1")
    print("| variant | RelMSE / fused before (geo. mean) | worst frame | frames > 1.03 | / oidn-l1 (geo. mean) |")
    print("|---|---:|---:|---:|---:|")
    for name in names:
        r = ratios[name]
        vs = f"{_geo([a / b for a, b in zip(r, bar, strict=True)]):.3f}" if bar else "-"
        print(f"| {name} | {_geo(r):.4f} | {max(r):.3f} | {sum(x > 1.03 for x in r)}/{len(r)} | {vs} |")


def _time(fn, repeats: int) -> tuple[float, float]:
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus)


def _frame(kind: str):
    """The 1280x720 frame to time: ``tiled`` (a held-out render tiled), ``synthetic`` (bench_service.py's) or the
    path of an EXR frame (e.g. a held-out studio render at 1280x720, whose direct layer is clean as a whole: the
    tiled frame's seams make its direct layer disagree with its gradients, so it never runs the clean-layer
    average)."""
    if kind not in ("tiled", "synthetic"):
        from gradsep.model.frame import read_frame

        return read_frame(kind)
    if kind == "tiled":
        from study_fused import _tiled_frame

        return _tiled_frame()
    from bench_service import synthetic_frame

    from gradsep.model.frame import read_frame

    return read_frame(synthetic_frame(720, 1280))


def timing(names: list[str], repeats: int, frame_kind: str) -> None:
    from gradsep.model.fused import OIDN_SETTING
    from gradsep.model.oidn import shared_denoiser
    from gradsep.model.reconstruct import load_fused, reconstruct

    frame = _frame(frame_kind)
    fused = load_fused("models")
    model = fused.models["indirect"]
    den = shared_denoiser(OIDN_SETTING)
    aux = den.prefilter(frame.features)
    lay = frame.layers
    print(f"load {os.getloadavg()[0]:.2f}")
    import gradsep.model.fused as fused_mod
    from gradsep.model.refine import REFINE_CG_TOLERANCE, REFINE_MAX_CG_STEPS, clean_weight

    shipped_cg, shipped_average = fused_mod.DIRECT_CG, fused_mod.CLEAN_AVERAGE
    print(f"direct layer's clean weight w_f: {clean_weight(den.denoise(lay['direct'].base, aux), lay['direct']):.2f} "
          "(> 0: fused runs the clean-layer average's network on it)")
    for method in ("oidn", "oidn-l1", "fused", "fused (before)", "fused (no clean average)"):
        # "fused (before)": the direct layer at the oidn-l1 method's CG budget, as fused ran before this study;
        # "fused (no clean average)": without design 25's network on a clean direct layer (session 20)
        fused_mod.DIRECT_CG = (REFINE_CG_TOLERANCE, REFINE_MAX_CG_STEPS) if method == "fused (before)" else shipped_cg
        fused_mod.CLEAN_AVERAGE = None if method == "fused (no clean average)" else shipped_average
        name = method.split()[0]
        try:
            w, c = _time(lambda m=name: reconstruct(frame, m, fused=fused), repeats)
        finally:
            fused_mod.DIRECT_CG, fused_mod.CLEAN_AVERAGE = shipped_cg, shipped_average
        print(f"reconstruct {method}: wall {w:.3f} s, cpu {c:.3f} s", flush=True)
    dn = {n: den.denoise(lay[n].base, aux) for n in lay}
    w, c = _time(lambda: den.denoise(lay["indirect"].base, aux), repeats)
    print(f"OIDN one layer ({OIDN_SETTING}): wall {w:.3f} s, cpu {c:.3f} s", flush=True)
    w, c = _time(lambda: clean_weight(dn["direct"], lay["direct"]), repeats)
    print(f"clean weight of the direct layer (every fused frame with gradients): wall {w:.3f} s, cpu {c:.3f} s",
          flush=True)
    for name in names:
        v = VARIANTS[name]
        dw, dc = _time(lambda v=v: direct_image(lay["direct"], dn["direct"], v.direct), repeats)
        iw, ic = _time(lambda v=v: indirect_image(lay["indirect"], dn["indirect"], frame.features, model, v),
                       repeats)
        print(f"{name}: direct after OIDN wall {dw:.3f} cpu {dc:.3f}; indirect after OIDN wall {iw:.3f} "
              f"cpu {ic:.3f}; frame CPU incl. 2 OIDN {dc + ic + 2 * c:.2f} s", flush=True)
    print(f"load {os.getloadavg()[0]:.2f}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("error")
    e.add_argument("--variants", default=",".join(VARIANTS))
    e.add_argument("--per-frame", action="store_true")
    t = sub.add_parser("time")
    t.add_argument("--variants", default="before,shipped,oidn-l1,d8s2,fast2x1,net/2")
    t.add_argument("--repeats", type=int, default=3)
    t.add_argument("--frame", default="tiled",
                   help="tiled (a held-out render tiled to 1280x720), synthetic (bench_service.py's frame) or the "
                        "path of an EXR frame")
    args = p.parse_args()
    names = [n for n in args.variants.split(",") if n]
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variant(s) {unknown}; known: {', '.join(VARIANTS)}")
    if args.cmd == "error":
        error(["before", *[n for n in names if n != "before"]], args.per_frame)
    else:
        timing(names, args.repeats, args.frame)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
