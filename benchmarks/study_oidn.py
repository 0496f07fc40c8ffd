"""Error against time of OIDN's settings for the ``oidn`` method (docs/oidn.md): which auxiliary images the
colour filter gets (prefiltered + cleanAux, raw, none) x quality preset (high, balanced, fast).

    python benchmarks/study_oidn.py render --scene procedural:70001   # one scene's frames + references (cached)
    python benchmarks/study_oidn.py error                              # RelMSE table over every cached scene
    python benchmarks/study_oidn.py time                               # 1280x720 cost per setting, medians

Error: G-PT frames (16 and 64 spp, 320x240) of scenes that are not evaluation scenes (held-out procedural seeds
7xxxx and training-range seeds), each layer denoised by OIDN at a setting, summed, scored by RelMSE with the
references' noise removed (model.metrics.relmse_unbiased over two independent Mitsuba ``path`` references).
Time: one 1280x720 two-layer frame = the setting's auxiliary pass (prefilter, once per frame) + 2 colour filter
calls, on synthetic noisy HDR data (OIDN's cost does not depend on content), medians of ``--repeats``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from pathlib import Path

import numpy as np

SIZE = (320, 240)
SPPS = (16, 64)
REF_SPP = 1024
DEFAULT_CACHE = Path(os.environ.get("GRADSEP_CACHE", Path.home() / ".cache" / "gradsep")) / "oidn-study"


def _stem(scene: str) -> str:
    return scene.replace(":", "-").replace("/", "_")


def render(scene: str, cache: Path) -> None:
    """The scene's G-PT frames at SPPS and two independent references (seeds 1 and 2), unless cached."""
    from gradsep.model.frame import write_frame
    from gradsep.renderer.reference import render_loaded
    from gradsep.renderer.render import render_frame
    from gradsep.renderer.scene import load_scene

    folder = cache / _stem(scene)
    folder.mkdir(parents=True, exist_ok=True)
    loaded = load_scene(scene, width=SIZE[0], height=SIZE[1])
    for spp in SPPS:
        path = folder / f"gpt-{spp}.exr"
        if not path.is_file():
            write_frame(path, render_frame(loaded, spp=spp, seed=100 + spp))
            print(f"{scene}: G-PT {spp} spp rendered", flush=True)
    for seed in (1, 2):
        path = folder / f"ref-{seed}.npz"
        if not path.is_file():
            start = time.perf_counter()
            ref = render_loaded(loaded, spp=REF_SPP, seed=seed, tile_spp=None, progress=False)
            np.savez(path, **{k: np.asarray(v, np.float32) for k, v in ref.images().items()})
            print(f"{scene}: reference {seed} ({REF_SPP} spp) in {time.perf_counter() - start:.0f} s", flush=True)


def _denoise_frame(frame, setting: str, runtime: str = "library") -> np.ndarray:
    from gradsep.model.oidn import shared_denoiser

    denoiser = shared_denoiser(setting, runtime)
    aux = denoiser.prefilter(frame.features) if frame.features is not None else None
    return sum(denoiser.denoise(layer.base, aux).astype(np.float64) for layer in frame.layers.values())


def _variants(settings: list[str], runtimes: list[str]) -> list[tuple[str, str, str]]:
    """(column name, setting, runtime): every setting on the library, and on the onnx runtime where it builds
    that setting's model (model/oidn_onnx.py), named ``<setting>@onnx``."""
    from gradsep.model.oidn import SETTINGS
    from gradsep.model.oidn_onnx import weights_for

    out = []
    for name in settings:
        for runtime in runtimes:
            if runtime == "library":
                out.append((name, name, runtime))
            elif weights_for(SETTINGS[name].aux, SETTINGS[name].quality) is not None:
                out.append((f"{name}@{runtime}", name, runtime))
    return out


def error(cache: Path, fused_dir: Path | None, fused_prior: str | None = None, settings: list[str] | None = None,
          runtimes: list[str] | None = None) -> None:
    """RelMSE (reference noise removed) of every setting on every cached (scene, spp), and its ratio to
    prefiltered-high (the setting before this study). ``fused_prior``: also score the fused models fed that
    setting's OIDN output instead of the prior they were trained on (what switching their prior without
    retraining would do). ``runtimes``: also run each setting on the onnx runtime (``<setting>@onnx``)."""
    from gradsep.model.frame import read_frame
    from gradsep.model.metrics import reference_floor, relmse_unbiased
    from gradsep.model.oidn import SETTINGS

    chosen = list(dict.fromkeys(["prefiltered-high", *(settings or SETTINGS)]))
    variants = _variants(chosen, runtimes or ["library"])
    names = [v[0] for v in variants]
    results: dict[str, list[float]] = {n: [] for n in names}
    extra: dict[str, list[float]] = {}
    rows = []
    fused = None
    if fused_dir is not None and fused_dir.is_dir():
        from gradsep.model.infer import NetworkReconstructor

        fused = NetworkReconstructor.load(fused_dir)
    for folder in sorted(p for p in cache.iterdir() if (p / "ref-2.npz").is_file()):
        r1, r2 = np.load(folder / "ref-1.npz"), np.load(folder / "ref-2.npz")
        floor = reference_floor(r1["total"], r2["total"])
        for spp in SPPS:
            frame = read_frame(folder / f"gpt-{spp}.exr")
            row = {"frame": f"{folder.name} {spp} spp", "floor": floor}
            for name, setting, runtime in variants:
                value = relmse_unbiased(_denoise_frame(frame, setting, runtime), r1["total"], r2["total"])
                results[name].append(value)
                row[name] = value
            if fused is not None:
                from gradsep.model.reconstruct import reconstruct

                value = relmse_unbiased(reconstruct(frame, "fused", fused=fused).image, r1["total"], r2["total"])
                extra.setdefault("fused", []).append(value)
                row["fused"] = value
                if fused_prior:
                    value = _fused_with_prior(frame, fused, fused_prior, r1["total"], r2["total"])
                    extra.setdefault(f"fused, prior {fused_prior}", []).append(value)
                    row[f"fused/{fused_prior}"] = value
            rows.append(row)
            print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else str(v) for k, v in row.items()), flush=True)
    base = results["prefiltered-high"]

    def ratios(values: list[float], to: list[float]) -> tuple[float, float, float]:
        r = [v / b for v, b in zip(values, to, strict=True) if b > 0 and v > 0]
        geo = math.exp(statistics.fmean(math.log(x) for x in r)) if r else math.nan
        return geo, min(r, default=math.nan), max(r, default=math.nan)

    print(f"\n{len(base)} frames; RelMSE mean, geometric mean of the ratio to prefiltered-high, worst ratio; for "
          "an @onnx column also the ratio to the same setting on the library (geo. mean, best, worst frame)")
    print("| setting | mean RelMSE | geo. mean ratio | worst ratio | / library: geo. | best | worst |\n"
          "|---|---:|---:|---:|---:|---:|---:|")
    for name, values in [*results.items(), *extra.items()]:
        geo, _, worst = ratios(values, base)
        same = name.split("@")[0]
        lib = (" | " + " | ".join(f"{x:.4f}" for x in ratios(values, results[same]))
               if "@" in name and same in results else " | | |")
        print(f"| {name} | {statistics.fmean(values):.4g} | {geo:.3f} | {worst:.3f}{lib} |")


def _fused_with_prior(frame, fused, setting: str, r1: np.ndarray, r2: np.ndarray) -> float:
    """The fused method's RelMSE with its prior denoiser swapped for ``setting``'s (restored afterwards)."""
    from gradsep.model import oidn
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.reconstruct import reconstruct

    key = (oidn.PRIOR_SETTING, oidn.runtime_setting())
    trained = oidn.shared_denoiser(*key)
    with oidn._shared_lock:
        oidn._shared[key] = oidn.Denoiser(setting, key[1])
    try:
        return relmse_unbiased(reconstruct(frame, "fused", fused=fused).image, r1, r2)
    finally:
        with oidn._shared_lock:
            oidn._shared[key] = trained


def timing(width: int, height: int, repeats: int, names: list[str], runtimes: list[str] | None = None) -> None:
    """Seconds of one two-layer frame per setting at width x height: auxiliary pass + 2 colour filter calls."""
    from gradsep.model.frame import Features
    from gradsep.model.oidn import SETTINGS, shared_denoiser

    rng = np.random.default_rng(0)
    layers = [rng.gamma(2.0, 0.5, (height, width, 3)).astype(np.float32) for _ in range(2)]
    features = Features(rng.uniform(0, 1, (height, width, 3)).astype(np.float32),
                        rng.uniform(-1, 1, (height, width, 3)).astype(np.float32), np.ones((height, width), np.float32))
    print(f"{width}x{height}, medians of {repeats} after a warm-up; load average "
          + " ".join(f"{v:.2f}" for v in os.getloadavg()))
    print("| setting | aux pass s | colour filter s (per layer) | two-layer frame s |\n|---|---:|---:|---:|")
    for name, setting, runtime in _variants(names or list(SETTINGS), runtimes or ["library"]):
        denoiser = shared_denoiser(setting, runtime)
        aux = denoiser.prefilter(features)
        denoiser.denoise(layers[0], aux)  # warm-up: filter and weights set up
        aux_t, colour_t = [], []
        for _ in range(repeats):
            start = time.perf_counter()
            aux = denoiser.prefilter(features)
            aux_t.append(time.perf_counter() - start)
            for layer in layers:
                start = time.perf_counter()
                denoiser.denoise(layer, aux)
                colour_t.append(time.perf_counter() - start)
        a, c = statistics.median(aux_t), statistics.median(colour_t)
        print(f"| {name} | {a:.3f} | {c:.3f} | {a + 2 * c:.3f} |", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("render", "error", "time"))
    parser.add_argument("--scene", action="append", default=[], help="render: scene spec (repeatable)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    parser.add_argument("--fused", type=Path, default=Path("models/fused"), help="error: fused models (if present)")
    parser.add_argument("--fused-prior", help="error: also score fused fed this setting's OIDN output (no retraining)")
    parser.add_argument("--size", default="1280x720", help="time: WIDTHxHEIGHT")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--settings", default="", help="error/time: comma-separated subset of settings (default: all)")
    parser.add_argument("--runtimes", default="library",
                        help="error/time: comma-separated OIDN runtimes to compare (library, onnx; model/oidn.py)")
    args = parser.parse_args()
    if args.what == "render":
        for scene in args.scene:
            render(scene, args.cache)
    elif args.what == "error":
        error(args.cache, args.fused, args.fused_prior, [n for n in args.settings.split(",") if n],
              [r for r in args.runtimes.split(",") if r])
    else:
        width, height = (int(v) for v in args.size.lower().split("x"))
        timing(width, height, args.repeats, [n for n in args.settings.split(",") if n],
               [r for r in args.runtimes.split(",") if r])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
