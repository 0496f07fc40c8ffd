"""`gradsep reference`: converged references with Mitsuba's own ``path`` integrator, split into direct/indirect.

A reference is what the evaluation compares reconstructions against, so it is rendered by an integrator that
shares no code with ours (Mitsuba's C++ ``path``, box pixel filter) and is written as ``R G B`` (the total) plus
``direct.{R,G,B}`` and, when the depth allows indirect light, ``indirect.{R,G,B}``.

How the split is made exactly: for one seed, Mitsuba's ``path`` at max depth D and at max depth 2 draw the same
random numbers up to and including the first camera-visible vertex (camera ray, light sample, BSDF sample), and a
depth-2 path stops right after the emitter its BSDF sample finds. Its contribution is therefore, sample by
sample, exactly the part of the depth-D sample that the frame contract calls ``direct`` (emission seen directly,
next-event estimation and the MIS-weighted BSDF hit at the first vertex), and ``indirect = total - direct`` holds
per sample: it carries no extra variance and is non-negative up to float rounding. Every pass checks this
(:func:`_check_split`) and fails loudly if a future Mitsuba breaks the assumption, rather than writing a
biased reference.

Samples are rendered in passes of ``tile_spp`` samples with distinct seeds (derived from ``--seed`` and the pass
index by a hash, so references rendered with neighbouring seeds share no pass) and averaged in float64, which
bounds the wavefront (Mitsuba addresses at most 2^32 samples per launch: 4096 spp at 1280x720 is 3.8e9) and
lets a progress bar advance.
"""

from __future__ import annotations

import io
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from model.progress import ProgressBar

if TYPE_CHECKING:  # scene.py needs Mitsuba at import time; load_reference must not
    from renderer.scene import LoadedScene

# Samples per pass when --tile-spp is not given: about 16 M samples keeps a pass to seconds on a CPU, so the
# progress bar moves, while a pass is still large enough to keep every core busy. Memory is not the limit on
# LLVM (a symbolic loop keeps path state in registers): 1280x720 at 16 spp per pass peaks at ~230 MB.
PASS_SAMPLE_BUDGET = 1 << 24
MAX_WAVEFRONT = (1 << 32) - 1  # Mitsuba's limit on samples per launch (32-bit sample index)


@dataclass
class Reference:
    """A rendered or loaded reference: float32 (H, W, 3) images and the EXR header's string metadata."""

    total: np.ndarray
    direct: np.ndarray
    indirect: np.ndarray | None
    metadata: dict[str, str] = field(default_factory=dict)

    def channels(self) -> dict[str, np.ndarray]:
        """Channel name -> (H, W) float32: ``R G B``, ``direct.*`` and, when present, ``indirect.*``."""
        from model.frame import rgb_channels

        out = dict(rgb_channels("", self.total))
        out.update(rgb_channels("direct", self.direct))
        if self.indirect is not None:
            out.update(rgb_channels("indirect", self.indirect))
        return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}

    def images(self) -> dict[str, np.ndarray]:
        """``total``, ``direct`` and, when present, ``indirect``: the reference's images by layer name."""
        out = {"total": self.total, "direct": self.direct}
        if self.indirect is not None:
            out["indirect"] = self.indirect
        return out

    def layer(self, name: str) -> np.ndarray:
        """``total``/``color`` (the unseparated image), ``direct`` or ``indirect``; a clear error if absent."""
        if name in ("total", "color"):
            return self.total
        if name == "direct":
            return self.direct
        if name == "indirect" and self.indirect is not None:
            return self.indirect
        raise KeyError(f"reference has no {name!r} layer (max depth {self.metadata.get('gradsep.max_depth', '?')})")


# ----------------------------------------------------------------------------------------------------------
# Passes and seeds
# ----------------------------------------------------------------------------------------------------------

def plan_passes(spp: int, tile_spp: int) -> list[int]:
    """Samples per pass: ``tile_spp`` each, the last one takes the remainder (weighted accordingly)."""
    if spp < 1 or tile_spp < 1:
        raise ValueError(f"spp and tile_spp must be positive, got {spp} and {tile_spp}")
    full, rest = divmod(spp, tile_spp)
    return [tile_spp] * full + ([rest] if rest else [])


def default_tile_spp(spp: int, width: int, height: int) -> int:
    """Samples per pass so one pass holds about :data:`PASS_SAMPLE_BUDGET` samples (at least 1, at most spp)."""
    return max(1, min(spp, PASS_SAMPLE_BUDGET // max(1, width * height)))


def pass_seed(seed: int, index: int) -> int:
    """The 32-bit sampler seed of pass ``index``: a hash of (seed, index), distinct across passes and seeds."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint32)[0])


# ----------------------------------------------------------------------------------------------------------
# Scene loading
# ----------------------------------------------------------------------------------------------------------

# ----------------------------------------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------------------------------------

def render_reference(spec: str, *, spp: int, width: int | None = None, height: int | None = None,
                     max_depth: int | None = None, seed: int = 0, tile_spp: int | None = None,
                     defines: Mapping[str, str] | None = None, progress: bool | None = False) -> Reference:
    """Render a reference of ``spec`` with Mitsuba's ``path`` integrator, split into direct and indirect.

    ``progress``: True shows a tqdm bar, None shows it only on a terminal, False hides it.
    """
    _check_positive("spp", spp)
    if tile_spp is not None:
        _check_positive("tile_spp", tile_spp)
    if seed < 0:
        raise ValueError(f"seed must be non-negative, got {seed}")
    from renderer.scene import load_scene  # box filter, film size, variant, unrenderable scenes refused

    loaded = load_scene(spec, width=width, height=height, max_depth=max_depth, defines=dict(defines or {}))
    return render_loaded(loaded, spp=spp, seed=seed, tile_spp=tile_spp, progress=progress)


def render_loaded(loaded: LoadedScene, *, spp: int, seed: int, tile_spp: int | None,
                  progress: bool | None = False) -> Reference:
    """The pass loop: per pass, ``path`` at the scene's depth and at depth 2 with one seed; float64 averages."""
    import mitsuba as mi

    depth = loaded.max_depth
    tile = tile_spp or default_tile_spp(spp, loaded.width, loaded.height)
    if loaded.width * loaded.height * tile > MAX_WAVEFRONT:
        raise ValueError(f"--tile-spp {tile} at {loaded.width}x{loaded.height} exceeds Mitsuba's 2^32 samples "
                         f"per pass; use at most {MAX_WAVEFRONT // (loaded.width * loaded.height)}")
    split = depth == -1 or depth > 2      # max depth <= 2: nothing but direct light exists
    total_it = mi.load_dict({"type": "path", "max_depth": depth})
    direct_it = mi.load_dict({"type": "path", "max_depth": 2}) if split else None

    def render(integrator: Any, k: int, s: int) -> np.ndarray:
        img = np.asarray(mi.render(loaded.scene, sensor=loaded.sensor, integrator=integrator, spp=k, seed=s),
                         dtype=np.float64)
        # An XML film may ask for RGBA (alpha dropped) or luminance (replicated): the file is always R G B.
        return img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, axis=-1)

    shape = (loaded.height, loaded.width, 3)
    total_sum, direct_sum = np.zeros(shape), np.zeros(shape)
    start = time.perf_counter()
    with ProgressBar(spp, enabled=progress, desc=f"reference {loaded.spec}".strip(), unit="spp") as bar:
        for i, k in enumerate(plan_passes(spp, tile)):
            s = pass_seed(seed, i)
            total = render(total_it, k, s)
            total_sum += k * total
            if direct_it is not None:
                direct = render(direct_it, k, s)
                _check_split(total, direct, i)
                direct_sum += k * direct
            bar.update(k)
    seconds = time.perf_counter() - start
    total_mean = total_sum / spp
    if direct_it is None:
        direct_mean, indirect_mean = total_mean, None
    else:
        direct_mean = direct_sum / spp
        # Per sample the difference is exact; what is left below zero is float rounding (checked per pass).
        indirect_mean = np.maximum(total_mean - direct_mean, 0.0)
    meta = loaded.scene_metadata()
    meta.update({"gradsep.kind": "reference", "gradsep.integrator": "path", "gradsep.spp": str(spp),
                 "gradsep.seed": str(seed), "gradsep.max_depth": str(depth), "gradsep.tile_spp": str(tile),
                 "gradsep.render_seconds": f"{seconds:.3f}", "gradsep.variant": str(mi.variant())})
    return Reference(_finite32(total_mean), _finite32(direct_mean),
                     None if indirect_mean is None else _finite32(indirect_mean), meta)


def _check_split(total: np.ndarray, direct: np.ndarray, index: int) -> None:
    """Fail if depth-2 ``path`` exceeds depth-D ``path`` beyond float rounding: the exact split no longer holds."""
    tolerance = 1e-4 * (np.abs(total) + np.abs(direct)) + 1e-6
    bad = (direct - total) > tolerance
    if bad.any():
        worst = float((direct - total).max())
        raise RuntimeError(
            f"pass {index}: direct exceeds total in {int(bad.sum())} values (worst {worst:.3g});"
            " Mitsuba's path integrator no longer draws the same random numbers at depth 2 and at full depth, so"
            " the exact direct/indirect split this reference relies on is broken")


def _finite32(image: np.ndarray) -> np.ndarray:
    """float32 with non-finite values (a NaN from a degenerate BSDF sample) replaced by 0: outputs stay finite."""
    return np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def _check_positive(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")


# ----------------------------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------------------------

def write_reference(path: str | Path, reference: Reference) -> None:
    """Write ``R G B`` + layers (float32) with the metadata, atomically (model.frame.write_exr)."""
    from model.frame import write_exr

    write_exr(path, reference.channels(), metadata=reference.metadata)


def load_reference(source: str | os.PathLike[str] | bytes) -> Reference:
    """Read a reference EXR safely (header checked first by the frame contract's reader).

    References are not frames (they carry no gradients), so ``read_frame`` does not apply; this reads the
    ``R G B`` / ``direct.*`` / ``indirect.*`` channels and raises the contract's typed errors when one is missing.
    """
    import OpenEXR

    from model.frame import RGB, ChannelError, NotExrError, read_header

    info = read_header(source)
    names = set(info.channels)
    for group in ("", "direct"):
        need = [f"{group}.{c}" if group else c for c in RGB]
        missing = [n for n in need if n not in names]
        if missing:
            raise ChannelError(f"not a reference: missing channels {', '.join(missing)}", missing)
    try:
        if isinstance(source, (bytes, bytearray, memoryview)):
            exr = OpenEXR.File(io.BytesIO(bytes(source)), separate_channels=True)
        else:
            exr = OpenEXR.File(os.fspath(source), separate_channels=True)
    except (RuntimeError, OSError, ValueError, TypeError) as exc:
        raise NotExrError(f"not a readable OpenEXR file: {exc}") from exc
    if len(exr.parts) != 1:  # OpenEXR returns no parts for a truncated file instead of raising
        raise NotExrError("truncated or corrupt OpenEXR file (pixel data could not be decoded)")
    decoded = exr.channels()

    def stack(prefix: str) -> np.ndarray:
        dot = f"{prefix}." if prefix else ""
        planes = [decoded[f"{dot}{c}"].pixels for c in RGB]
        if any(p is None or p.shape != (info.height, info.width) for p in planes):
            raise NotExrError(f"truncated or corrupt OpenEXR file (layer {prefix or 'RGB'} could not be decoded)")
        return _finite32(np.stack(planes, axis=-1).astype(np.float64))

    indirect = stack("indirect") if all(f"indirect.{c}" in names for c in RGB) else None
    return Reference(stack(""), stack("direct"), indirect, dict(info.attributes))
