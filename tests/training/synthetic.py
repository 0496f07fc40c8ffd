"""A tiny synthetic dataset in the renderer's format, for the training tests (no Mitsuba needed).

Each frame is "albedo × smooth shading" split into a direct and an indirect part, with Monte-Carlo-like noise
on the base images (heavy-tailed, so there are fireflies) and much weaker noise on the gradients, which are
the exact forward differences of the clean images: the situation G-PT produces. Features are the clean
albedo (piecewise constant: the edges the first-order loss should find), normals and depth. Nothing here is
tuned to any scene.

It exercises the pipeline; it is not a stand-in for rendered data. Its images are much smoother and its base
images noisier than G-PT frames, so a flat image is a strong local minimum of the unsupervised loss here
(flat: L_data + L_grad ≈ 0.47 against 0.93 for the noisy input), whereas on rendered frames the gradients carry
real edges and a flat image costs about as much as the noisy input. Networks trained on it for minutes do not
become useful denoisers; judge training on renderer datasets.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from gradsep.model.exr_write import write_frame
from gradsep.model.frame import Features, Frame, Layer, forward_differences


def _smooth_field(rng: np.random.Generator, h: int, w: int, blobs: int) -> np.ndarray:
    """A positive smooth image: a sum of random Gaussian blobs, (H, W)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    out = np.full((h, w), 0.05, dtype=np.float32)
    for _ in range(blobs):
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        s = rng.uniform(0.15, 0.5) * max(h, w)
        out += rng.uniform(0.2, 1.0) * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s * s))
    return out


def _albedo(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Piecewise-constant colours: random rectangles over a background, (H, W, 3) in [0, 1]."""
    albedo = np.empty((h, w, 3), dtype=np.float32)
    albedo[:] = rng.uniform(0.3, 0.9, size=3)
    for _ in range(4):
        y0, x0 = rng.integers(0, h), rng.integers(0, w)
        y1, x1 = y0 + rng.integers(h // 6 + 1, h // 2 + 2), x0 + rng.integers(w // 6 + 1, w // 2 + 2)
        albedo[y0:y1, x0:x1] = rng.uniform(0.05, 0.95, size=3)
    return albedo


def _noisy(rng: np.random.Generator, clean: np.ndarray, spp: int, scale: float) -> np.ndarray:
    """Unbiased heavy-tailed noise: clean × (mean-one log-normal), its variance shrinking with spp."""
    sigma = scale / np.sqrt(spp)
    factor = rng.lognormal(-0.5 * sigma * sigma, sigma, size=clean.shape).astype(np.float32)
    return clean * factor


def synthetic_frame(seed: int, width: int = 64, height: int = 48, spp: int = 4,
                    realization: int = 0) -> tuple[Frame, dict[str, np.ndarray]]:
    """One frame (direct + indirect + features) and the clean radiance of each layer, (H, W, 3) each.

    ``seed`` fixes the scene, ``realization`` the noise: two realizations of one seed are independent noisy
    renders of the same clean images (the pairs of ``gradsep dataset --pairs``)."""
    rng = np.random.default_rng(seed)
    albedo = _albedo(rng, height, width)
    direct_shading = _smooth_field(rng, height, width, 3) * 2.0
    indirect_shading = _smooth_field(rng, height, width, 2) * 0.5
    depth = (2.0 + _smooth_field(rng, height, width, 1)).astype(np.float32)
    rng = np.random.default_rng([seed, realization])  # the noise, from here on
    layers: dict[str, Layer] = {}
    clean_layers: dict[str, np.ndarray] = {}
    for name, shading, noise in (("direct", direct_shading, 1.0), ("indirect", indirect_shading, 2.0)):
        clean = (albedo * shading[..., None]).astype(np.float32)
        clean_layers[name] = clean
        dx, dy = forward_differences(clean)
        grad_noise = 0.1 * noise / np.sqrt(spp)
        dx = dx + rng.normal(0, grad_noise, dx.shape).astype(np.float32) * np.abs(dx)
        dy = dy + rng.normal(0, grad_noise, dy.shape).astype(np.float32) * np.abs(dy)
        dx[:, -1] = 0.0
        dy[-1, :] = 0.0
        layers[name] = Layer(_noisy(rng, clean, spp, noise), dx.astype(np.float32), dy.astype(np.float32))
    normal = np.zeros((height, width, 3), dtype=np.float32)
    normal[..., 2] = 1.0
    features = Features(albedo=albedo, normal=normal, depth=depth)
    frame = Frame(layers=layers, features=features, metadata={"gradsep.spp": str(spp), "gradsep.synthetic": "1"})
    return frame, clean_layers


def make_synthetic_dataset(root: str | os.PathLike[str], frames: int = 6, width: int = 64, height: int = 48,
                           spp: int = 4, first_seed: int = 1000, pairs: bool = False) -> Path:
    """Write ``root/manifest.json`` + ``root/frames/*.exr`` the way `gradsep dataset` does (with ``pairs``, a
    second realization per frame as ``--pairs`` does); returns root."""
    root = Path(root)
    (root / "frames").mkdir(parents=True, exist_ok=True)
    records = []
    for seed in range(first_seed, first_seed + frames):
        frame, _ = synthetic_frame(seed, width, height, spp)
        rel = f"frames/proc_{seed:06d}.exr"
        write_frame(root / rel, frame)
        record = {"file": rel, "seed": seed, "spp": spp, "render_seconds": 0.0, "layers": list(frame.layers)}
        if pairs:
            record["target"] = f"frames/proc_{seed:06d}.b.exr"
            write_frame(root / record["target"], synthetic_frame(seed, width, height, spp, realization=1)[0])
        records.append(record)
    manifest = {"version": 1, "spp": spp, "size": [width, height], "frames": records, "synthetic": True,
                "pairs": pairs}
    (root / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return root
