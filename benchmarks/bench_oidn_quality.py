"""OIDN settings (model/oidn.py, docs/oidn.md) compared by RelMSE on rendered frames: exposure, features, quality.

    python benchmarks/bench_oidn_quality.py --scenes procedural:93301,procedural:studio:93301 --size 192 \\
        --spp 16,64,256 --ref-spp 1024 --settings raw-fast-level,raw-fast,prefiltered-high \\
        --cache ~/.cache/gradsep/oidn-quality
    python benchmarks/bench_oidn_quality.py --scenes procedural:93301,... --settings raw-fast --without-variance

For every scene and sample count, renders a plain frame (``--no-gradients``) and a direct-gradient frame
(``--gradients direct --offsets alternate``), reconstructs the first with ``oidn`` and the second with ``oidn-l1``
under each setting (``$GRADSEP_OIDN_SETTING``; with ``--sum`` also ``oidn`` on the sum of the plain frame's
layers; with ``--without-variance`` also on the frames with their variance channels dropped), and scores
them against two independent ``gradsep reference`` renders (model.metrics.relmse_unbiased: the references' noise
removed in expectation). Prints one row per frame and, per family (rooms, studios), sample count, method and
setting, the geometric mean and the worst of its RelMSE over the first setting's, then the same split by whether the
frame's direct layer holds a light in view. Frames and references are cached in ``--cache`` under names that say
what made them, so a second run only reconstructs.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

NO_VARIANCE = " without variance"
PIPELINES = {"oidn": ("--no-gradients",), "oidn-l1": ("--gradients", "direct", "--offsets", "alternate")}


def gradsep(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "gradsep", *args], check=True, stdout=subprocess.DEVNULL)


def cached_render(cache: Path, scene: str, size: int, spp: int, seed: int, method: str) -> Path:
    path = cache / f"frame-{scene.replace(':', '_')}-{size}-{spp}-{seed}-{method}.exr"
    if not path.exists():
        gradsep("render", scene, "--spp", str(spp), "--width", str(size), "--height", str(size), "--seed", str(seed),
                *PIPELINES[method], "-o", str(path))
    return path


def cached_reference(cache: Path, scene: str, size: int, spp: int, seed: int) -> Path:
    path = cache / f"ref-{scene.replace(':', '_')}-{size}-{spp}-{seed}.exr"
    if not path.exists():
        gradsep("reference", scene, "--width", str(size), "--height", str(size), "--spp", str(spp), "--seed",
                str(seed), "-o", str(path))
    return path


def relmse(frame: object, method: str, setting: str, refs: tuple[object, object], summed: bool = False) -> float:
    """RelMSE of ``frame`` (a read model.frame.Frame, left unchanged) reconstructed with ``method`` at OIDN
    ``setting``; ``summed``: its layers added into one unseparated ``color`` layer first (OIDN on the sum instead of
    per layer). A setting named ``S without
    variance`` is ``S`` on the frame with its variance channels dropped (no back-off: model/backoff.py)."""
    from dataclasses import replace

    from gradsep.model.frame import Frame
    from gradsep.model.metrics import relmse_unbiased
    from gradsep.model.oidn import SETTING_ENV
    from gradsep.model.reconstruct import reconstruct

    os.environ[SETTING_ENV] = setting.removesuffix(NO_VARIANCE)
    loaded = frame
    if setting.endswith(NO_VARIANCE):
        loaded = replace(frame, layers={name: replace(layer, var=None) for name, layer in frame.layers.items()})
    if summed:
        loaded = Frame({"color": loaded.combined()}, loaded.features, metadata=loaded.metadata)
    return relmse_unbiased(reconstruct(loaded, method).image, *refs)


def main() -> int:
    from gradsep.model.exr_read import read_frame
    from gradsep.renderer.planned_frame import has_light_in_view
    from gradsep.renderer.reference import load_reference

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", required=True, help="comma-separated scene specs (procedural:SEED, ...)")
    parser.add_argument("--size", type=int, default=192)
    parser.add_argument("--spp", default="16,64,256")
    parser.add_argument("--seed", type=int, default=11, help="the frames' render seed")
    parser.add_argument("--ref-spp", type=int, default=1024)
    parser.add_argument("--settings", default="raw-fast-level,raw-fast",
                        help="OIDN settings (model.oidn.SETTINGS); each is compared with the first")
    parser.add_argument("--sum", action="store_true",
                        help="also run oidn on the sum of the plain frame's layers (one column per setting)")
    parser.add_argument("--without-variance", action="store_true",
                        help="also score every setting on the frames with their variance channels dropped")
    parser.add_argument("--cache", default="~/.cache/gradsep/oidn-quality")
    args = parser.parse_args()
    cache = Path(args.cache).expanduser()
    cache.mkdir(parents=True, exist_ok=True)
    settings = args.settings.split(",")
    if args.without_variance:
        settings += [name + NO_VARIANCE for name in settings]
    base, others = settings[0], settings[1:]
    summed = [f"{name} on the sum" for name in settings] if args.sum else []
    others = others + summed
    ratios: dict[tuple[str, int, str, str], list[float]] = defaultdict(list)
    by_light: dict[tuple[str, str, bool], list[float]] = defaultdict(list)  # (method, setting, a light in view)
    print(f"| scene | spp | method | {base} RelMSE | " + " | ".join(f"{s} / {base}" for s in others) + " |")
    print("|---|---:|---|---:|" + "---:|" * len(others))
    for scene in args.scenes.split(","):
        refs = tuple(load_reference(str(cached_reference(cache, scene, args.size, args.ref_spp, s))).total
                     for s in (1, 2))
        family = "studios" if ":studio:" in scene else "rooms"
        for spp in (int(s) for s in args.spp.split(",")):
            for method in PIPELINES:
                frame = read_frame(cached_render(cache, scene, args.size, spp, args.seed, method))  # read once
                light = has_light_in_view(frame)
                err = {name: relmse(frame, method, name, refs) for name in settings}
                if method == "oidn":
                    err |= {name: relmse(frame, method, name.removesuffix(" on the sum"), refs, summed=True)
                            for name in summed}
                row = []
                for name in others:
                    if name not in err:
                        row.append("–")
                        continue
                    ratio = err[name] / err[base] if err[base] > 0 else float("nan")
                    ratios[(family, spp, method, name)].append(ratio)
                    by_light[(method, name, light)].append(ratio)
                    row.append(f"{ratio:.3f}")
                print(f"| {scene} | {spp} | {method} | {err[base]:.4g} | " + " | ".join(row) + " |", flush=True)
    print(f"\n| family | spp | method | setting | frames | / {base}, geometric mean | worst | lower |")
    print("|---|---:|---|---|---:|---:|---:|---:|")
    for (family, spp, method, name), values in sorted(ratios.items()):
        good = [v for v in values if v > 0 and math.isfinite(v)]
        geo = math.exp(sum(map(math.log, good)) / len(good)) if good else float("nan")
        print(f"| {family} | {spp} | {method} | {name} | {len(values)} | {geo:.3f} | {max(values):.3f} | "
              f"{sum(v < 1 for v in values)} |")
    print(f"\nBy whether the direct layer holds a light in view (renderer.planned_frame.has_light_in_view):\n\n"
          f"| method | setting | light in view | frames | / {base}, geometric mean | worst |")
    print("|---|---|---|---:|---:|---:|")
    for (method, name, light), values in sorted(by_light.items()):
        geo = math.exp(sum(math.log(v) for v in values) / len(values))
        print(f"| {method} | {name} | {'yes' if light else 'no'} | {len(values)} | {geo:.3f} | {max(values):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
