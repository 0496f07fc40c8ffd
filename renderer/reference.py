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

The sampler (``--sampler``, :data:`DEFAULT_SAMPLER`): each pass draws its samples from one Mitsuba sampler
seeded with the pass seed. A stratified sampler (``multijitter``) spreads a pass's samples over each pixel's
first dimensions instead of drawing them independently, which lowers the variance of a pass at the same cost
(measured per CPU-second on held-out procedural scenes: docs/evaluation.md, "Reference sampler and reference
farms"); passes with different seeds are still independent (each permutation and jitter is hashed from its seed),
which is all the pass averaging, the two-reference product estimator and sharding rely on. Every sampler renders
an unbiased estimate of the same image, so the choice changes the noise, not the expectation. The sensor is rebuilt with
the chosen sampler (:func:`sampler_sensor`) so a scene file's own ``<sampler>`` no longer decides.

Sharding (``--shard K/N``): a job's passes are dealt round-robin to N shards, shard K renders passes
K-1, K-1+N, ... with the same pass seeds as the whole job, and :func:`merge_references` (``gradsep
reference-merge``) combines the N shard files, weighted by their samples, into the reference one machine
would have rendered (to float32 rounding): N machines buy N times the samples.
"""

from __future__ import annotations

import io
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gradsep.model.progress import ProgressBar

if TYPE_CHECKING:  # scene.py needs Mitsuba at import time; load_reference must not
    from gradsep.renderer.scene import LoadedScene

# Samples per pass when --tile-spp is not given: small enough that the progress bar moves, large enough to keep
# every core busy. Memory is not the limit on LLVM (a symbolic loop keeps path state in registers).
PASS_SAMPLE_BUDGET = 1 << 24
MAX_WAVEFRONT = (1 << 32) - 1  # Mitsuba's limit on samples per launch (32-bit sample index)

# Mitsuba samplers a reference may use. ``independent`` draws every sample independently; the others stratify a
# pass's samples per pixel. Chosen by measured floor per CPU-second on held-out procedural scenes
# (docs/decisions.md, "The references' sampler"; docs/evaluation.md, "Reference sampler and reference farms").
# Not ldsampler: its references of a scene sat above every other sampler's image mean (a bias or a correlation
# between seeds; either breaks the product estimator: docs/decisions.md, "The references' sampler").
SAMPLERS: tuple[str, ...] = ("independent", "multijitter", "stratified", "orthogonal")
DEFAULT_SAMPLER = "multijitter"


@dataclass
class Reference:
    """A rendered or loaded reference: float32 (H, W, 3) images and the EXR header's string metadata."""

    total: np.ndarray
    direct: np.ndarray
    indirect: np.ndarray | None
    metadata: dict[str, str] = field(default_factory=dict)

    def channels(self) -> dict[str, np.ndarray]:
        """Channel name -> (H, W) float32: ``R G B``, ``direct.*`` and, when present, ``indirect.*``."""
        from gradsep.model.frame import rgb_channels

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

def plan_passes(spp: int, tile_spp: int, sampler: str = "independent") -> list[int]:
    """Samples per pass: at most ``tile_spp`` each, every count one that ``sampler`` renders exactly.

    Independent sampling: ``tile_spp`` each, the last pass takes the remainder (weighted accordingly).
    A stratified sampler rounds a sample count it cannot stratify (multijitter renders 528 samples when asked
    for 512), which would silently change the spp; so each pass takes the largest count the sampler renders
    exactly, in as few passes as possible (512 in tiles of 256 -> 256 + 256). A ValueError when
    ``spp`` cannot be split so (orthogonal renders at least 4 samples per pixel).
    """
    if spp < 1 or tile_spp < 1:
        raise ValueError(f"spp and tile_spp must be positive, got {spp} and {tile_spp}")
    if sampler == "independent":
        full, rest = divmod(spp, tile_spp)
        return [tile_spp] * full + ([rest] if rest else [])
    exact = [k for k in range(min(tile_spp, spp), 0, -1) if sampler_count(sampler, k) == k]
    # Whole tiles first, then the fewest exact passes for the rest (a little dynamic programme over the last
    # tile plus the remainder, largest pass first among equals: one large stratified pass beats two small ones).
    full = max(0, spp // tile_spp - 1) if exact and exact[0] == tile_spp else 0
    rest = spp - full * tile_spp
    fewest, choice = [0] + [rest + 1] * rest, [0] * (rest + 1)
    for n in range(1, rest + 1):
        for k in exact:
            if k <= n and fewest[n - k] + 1 < fewest[n]:
                fewest[n], choice[n] = fewest[n - k] + 1, k
    if fewest[rest] > rest:
        raise ValueError(f"{spp} spp cannot be split into passes the {sampler} sampler renders exactly "
                         f"(its smallest sample count is {sampler_count(sampler, 1)}); choose another spp "
                         "or --sampler independent")
    out = [tile_spp] * full
    while rest:
        out.append(choice[rest])
        rest -= choice[rest]
    return out


@cache
def sampler_count(sampler: str, spp: int) -> int:
    """The samples per pixel Mitsuba's ``sampler`` actually renders when asked for ``spp``."""
    import mitsuba as mi

    from gradsep.renderer.variant import select_variant

    select_variant()
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; choose one of {', '.join(SAMPLERS)}")
    level = mi.log_level()
    mi.set_log_level(mi.LogLevel.Error)  # orthogonal warns when it rounds; the caller checks the count
    try:
        obj = mi.load_dict({"type": sampler, "sample_count": 4})
        obj.set_sample_count(int(spp))
        return int(obj.sample_count())
    finally:
        mi.set_log_level(level)


def default_tile_spp(spp: int, width: int, height: int, sampler: str = "independent") -> int:
    """Samples per pass so one pass holds about :data:`PASS_SAMPLE_BUDGET` samples (at least 1, at most spp).

    A stratified sampler gets the largest power of four within twice that budget (a count every stratified
    sampler but ``orthogonal`` renders exactly; 256 at 320x240): its variance falls faster than 1/spp within a
    pass, so larger passes pay, and 2^25 samples per launch stay well inside memory on LLVM.
    """
    budget = PASS_SAMPLE_BUDGET // max(1, width * height)
    if sampler == "independent":
        return max(1, min(spp, budget))
    tile = 1
    while tile * 4 <= 2 * budget:
        tile *= 4
    return max(1, min(spp, tile))


def pass_seed(seed: int, index: int) -> int:
    """The 32-bit sampler seed of pass ``index``: a hash of (seed, index), distinct across passes and seeds."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint32)[0])


# ----------------------------------------------------------------------------------------------------------
# Scene loading
# ----------------------------------------------------------------------------------------------------------

# ----------------------------------------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ReferenceJob:
    """What a reference renders: ``spp`` samples per pixel in passes of ``tile_spp`` (None: the default for the
    sampler and size), drawn by Mitsuba's ``sampler``, the passes seeded from ``seed``; ``shard`` = (K, N): only
    shard K (1-based) of N of the job's passes (see :func:`render_loaded`)."""

    spp: int
    seed: int = 0
    tile_spp: int | None = None
    sampler: str = DEFAULT_SAMPLER
    shard: tuple[int, int] | None = None

    def check(self) -> None:
        """A ValueError naming what is wrong with the job."""
        _check_positive("spp", self.spp)
        if self.tile_spp is not None:
            _check_positive("tile_spp", self.tile_spp)
        if self.seed < 0:
            raise ValueError(f"seed must be non-negative, got {self.seed}")
        check_sampler(self.sampler)
        if self.shard is not None:
            check_shard(self.shard)


def render_reference(spec: str, job: ReferenceJob, *, width: int | None = None, height: int | None = None,
                     max_depth: int | None = None, defines: Mapping[str, str] | None = None,
                     progress: bool | None = False) -> Reference:
    """Render a reference of ``spec`` with Mitsuba's ``path`` integrator, split into direct and indirect.

    ``progress``: True shows a tqdm bar, None shows it only on a terminal, False hides it.
    """
    job.check()
    from gradsep.renderer.scene import load_scene  # box filter, film size, variant, unrenderable scenes refused

    loaded = load_scene(spec, width=width, height=height, max_depth=max_depth, defines=dict(defines or {}))
    return render_loaded(loaded, spp=job.spp, seed=job.seed, tile_spp=job.tile_spp, progress=progress,
                         sampler=job.sampler, shard=job.shard)


def check_sampler(sampler: str) -> None:
    """A ValueError naming the choices when ``sampler`` is not one of :data:`SAMPLERS`."""
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; choose one of {', '.join(SAMPLERS)}")


def check_shard(shard: tuple[int, int]) -> None:
    """A ValueError unless ``shard`` = (K, N) with 1 <= K <= N."""
    k, n = shard
    if n < 1 or not 1 <= k <= n:
        raise ValueError(f"shard must be K/N with 1 <= K <= N, got {k}/{n}")


def parse_shard(text: str) -> tuple[int, int]:
    """``"2/8"`` -> (2, 8); a ValueError naming the expected form otherwise."""
    k, sep, n = text.partition("/")
    try:
        shard = (int(k), int(n))
    except ValueError:
        shard = (0, 0)
    if not sep or shard[1] < 1 or not 1 <= shard[0] <= shard[1]:
        raise ValueError(f"--shard must be K/N with 1 <= K <= N (e.g. 1/4), got {text!r}")
    return shard


def sampler_sensor(loaded: LoadedScene, sampler: str) -> Any:
    """The scene's camera rebuilt with Mitsuba's ``sampler``: same type, transform, field of view, clip planes,
    shutter, lens and film size, box filter. Mitsuba cannot swap a loaded sensor's sampler, and the scene's
    sensors are limited to perspective and thin-lens cameras (renderer.scene.SUPPORTED_SENSORS), whose every
    parameter ``mi.traverse`` exposes. With ``independent`` the rebuilt camera renders bit-identically to the
    scene's own independent one (tests/renderer/test_reference.py checks it)."""
    import mitsuba as mi

    check_sampler(sampler)
    sensor = loaded.sensor
    params = mi.traverse(sensor)

    def scalar(name: str) -> float:
        value = params[name]
        return float(value[0]) if hasattr(value, "__len__") else float(value)

    matrix = np.array(params["to_world"].matrix, dtype=np.float64).reshape(4, 4)
    film = sensor.film()
    size = [int(v) for v in film.size()]
    desc: dict[str, Any] = {
        "to_world": mi.ScalarTransform4f(np.ascontiguousarray(matrix, dtype=np.float32)),
        "fov": scalar("x_fov"), "fov_axis": "x",
        "near_clip": scalar("near_clip"), "far_clip": scalar("far_clip"),
        "shutter_open": scalar("shutter_open"), "shutter_close": scalar("shutter_open") + scalar("shutter_open_time"),
        "film": {"type": "hdrfilm", "width": size[0], "height": size[1], "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32", "sample_border": bool(film.sample_border())},
        "sampler": {"type": sampler, "sample_count": 4},
    }
    kind = sensor.class_name()
    if kind == "ThinLensCamera":
        desc.update(type="thinlens", aperture_radius=scalar("aperture_radius"),
                    focus_distance=scalar("focus_distance"))
    elif kind == "PerspectiveCamera":
        desc.update(type="perspective", principal_point_offset_x=scalar("principal_point_offset_x"),
                    principal_point_offset_y=scalar("principal_point_offset_y"))
    else:  # load_scene refuses other sensors; fail loudly should that change
        raise ValueError(f"cannot rebuild a {kind} with another sampler (perspective and thin-lens only)")
    return mi.load_dict(desc)


def render_loaded(loaded: LoadedScene, *, spp: int, seed: int, tile_spp: int | None,
                  progress: bool | None = False, sampler: str = DEFAULT_SAMPLER,
                  shard: tuple[int, int] | None = None) -> Reference:
    """The pass loop: per pass, ``path`` at the scene's depth and at depth 2 with one seed; float64 averages.

    ``shard`` = (K, N) renders only passes K-1, K-1+N, ... of the job's plan (same pass seeds), records them in
    the metadata, and returns their mean: :func:`merge_references` combines the N shards exactly. Without an
    explicit ``tile_spp`` a sharded job's passes hold at most spp / N samples, so every shard gets some.
    """
    import mitsuba as mi

    check_sampler(sampler)
    depth = loaded.max_depth
    tile, mine = _shard_passes(loaded, spp, tile_spp, sampler, shard)
    split = depth == -1 or depth > 2      # max depth <= 2: nothing but direct light exists
    total_it = mi.load_dict({"type": "path", "max_depth": depth})
    direct_it = mi.load_dict({"type": "path", "max_depth": 2}) if split else None
    sensor = sampler_sensor(loaded, sampler)

    def render(integrator: Any, k: int, s: int) -> np.ndarray:
        img = np.asarray(mi.render(loaded.scene, sensor=sensor, integrator=integrator, spp=k, seed=s),
                         dtype=np.float64)
        # The rebuilt film is RGB; kept general should a film ever come back RGBA (alpha dropped) or luminance.
        return img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, axis=-1)

    shape = (loaded.height, loaded.width, 3)
    total_sum, direct_sum = np.zeros(shape), np.zeros(shape)
    samples = sum(k for _, k in mine)
    start = time.perf_counter()
    with ProgressBar(samples, enabled=progress, desc=f"reference {loaded.spec}".strip(), unit="spp") as bar:
        for i, k in mine:
            s = pass_seed(seed, i)
            total = render(total_it, k, s)
            total_sum += k * total
            if direct_it is not None:
                direct = render(direct_it, k, s)
                _check_split(total, direct, i)
                direct_sum += k * direct
            bar.update(k)
    seconds = time.perf_counter() - start
    meta = loaded.scene_metadata()
    meta.update({"gradsep.kind": "reference", "gradsep.integrator": "path", "gradsep.spp": str(samples),
                 "gradsep.seed": str(seed), "gradsep.max_depth": str(depth), "gradsep.tile_spp": str(tile),
                 "gradsep.sampler": sampler, "gradsep.size": f"{loaded.width}x{loaded.height}",
                 "gradsep.render_seconds": f"{seconds:.3f}", "gradsep.variant": str(mi.variant())})
    if shard is not None:
        meta.update({"gradsep.shard": f"{shard[0]}/{shard[1]}", "gradsep.job_spp": str(spp),
                     "gradsep.passes": ",".join(str(i) for i, _ in mine)})
    return _mean_reference(total_sum / samples, None if direct_it is None else direct_sum / samples, meta)


def _shard_passes(loaded: LoadedScene, spp: int, tile_spp: int | None, sampler: str,
                  shard: tuple[int, int] | None) -> tuple[int, list[tuple[int, int]]]:
    """The job's samples per pass and the (index, samples) of the passes this shard renders (all without one)."""
    tile = tile_spp or default_tile_spp(spp, loaded.width, loaded.height, sampler)
    if shard is not None and tile_spp is None:
        # Every shard needs passes: at most spp / N samples per pass (a function of the job alone, so all shards
        # plan the same passes; the merge checks that their tiles agree).
        tile = max(1, min(tile, spp // shard[1]))
    if loaded.width * loaded.height * tile > MAX_WAVEFRONT:
        raise ValueError(f"--tile-spp {tile} at {loaded.width}x{loaded.height} exceeds Mitsuba's 2^32 samples "
                         f"per pass; use at most {MAX_WAVEFRONT // (loaded.width * loaded.height)}")
    plan = plan_passes(spp, tile, sampler)
    mine = list(enumerate(plan)) if shard is None else list(enumerate(plan))[shard[0] - 1::shard[1]]
    if not mine:
        raise ValueError(f"shard {shard[0]}/{shard[1]} has no passes: {spp} spp in passes of {tile} make "
                         f"{len(plan)}; use at most {len(plan)} shards or a smaller --tile-spp")
    return tile, mine


def _mean_reference(total_mean: np.ndarray, direct_mean: np.ndarray | None, meta: dict[str, str]) -> Reference:
    """The Reference of float64 means; ``direct_mean`` None: depth <= 2, everything is direct light."""
    if direct_mean is None:
        return Reference(_finite32(total_mean), _finite32(total_mean), None, meta)
    # Per sample the difference is exact; what is left below zero is float rounding (checked per pass).
    indirect_mean = np.maximum(total_mean - direct_mean, 0.0)
    return Reference(_finite32(total_mean), _finite32(direct_mean), _finite32(indirect_mean), meta)


# Metadata every shard of one job must share (the scene and everything that decides its passes and seeds).
SHARD_JOB_KEYS = ("gradsep.scene", "gradsep.defines", "gradsep.procedural_version", "gradsep.job_spp",
                  "gradsep.seed", "gradsep.max_depth", "gradsep.tile_spp", "gradsep.sampler", "gradsep.size",
                  "gradsep.variant", "gradsep.integrator")


def merge_references(parts: Sequence[Reference]) -> Reference:
    """Combine the N shards of one ``--shard K/N`` job into the job's reference, weighted by their samples.

    Exact up to float32 storage: the shards hold the job's passes with the job's seeds, so the merge is the
    same sample-weighted mean the unsharded render computes (indirect recomputed from the merged total and
    direct, as there). Refused, naming the problem, unless the parts are shards 1..N of one job, each once.
    """
    if not parts:
        raise ValueError("nothing to merge: give the N shard files of one job")
    metas = [p.metadata for p in parts]
    missing = [i for i, m in enumerate(metas) if "gradsep.shard" not in m]
    if missing:
        raise ValueError(f"part {missing[0] + 1} is not a shard (no gradsep.shard; render it with --shard K/N)")
    for key in SHARD_JOB_KEYS:
        values = {m.get(key) for m in metas}
        if len(values) > 1:
            raise ValueError(f"the parts come from different jobs: {key} differs ({', '.join(map(str, values))})")
    shards = [parse_shard(m["gradsep.shard"]) for m in metas]
    n = shards[0][1]
    got = sorted(k for k, _ in shards)
    if {s[1] for s in shards} != {n} or got != list(range(1, n + 1)):
        raise ValueError(f"need shards 1..{n} of {n} exactly once each, got {', '.join(f'{k}/{m}' for k, m in shards)}")
    weights = [int(m["gradsep.spp"]) for m in metas]
    samples = sum(weights)
    if str(samples) != metas[0]["gradsep.job_spp"]:
        raise ValueError(f"the shards hold {samples} spp, their job {metas[0]['gradsep.job_spp']}")
    total = sum(w * p.total.astype(np.float64) for w, p in zip(weights, parts, strict=True)) / samples
    direct = None
    if parts[0].indirect is not None:
        direct = sum(w * p.direct.astype(np.float64) for w, p in zip(weights, parts, strict=True)) / samples
    meta = {k: v for k, v in metas[0].items()
            if k not in ("gradsep.shard", "gradsep.passes", "gradsep.job_spp", "gradsep.eval_key")}
    meta.update({"gradsep.spp": str(samples), "gradsep.shards": str(n),
                 "gradsep.render_seconds": f"{sum(float(m.get('gradsep.render_seconds', 'nan')) for m in metas):.3f}"})
    return _mean_reference(total, direct, meta)


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
    """Write ``R G B`` + layers (float32) with the metadata, atomically (model.exr_write.write_exr)."""
    from gradsep.model.exr_write import write_exr

    write_exr(path, reference.channels(), metadata=reference.metadata)


def load_reference(source: str | os.PathLike[str] | bytes) -> Reference:
    """Read a reference EXR safely (header checked first by the frame contract's reader).

    References are not frames (they carry no gradients), so ``read_frame`` does not apply; this reads the
    ``R G B`` / ``direct.*`` / ``indirect.*`` channels and raises the contract's typed errors when one is missing.
    """
    import OpenEXR

    from gradsep.model.errors import ChannelError, NotExrError
    from gradsep.model.exr_read import read_header
    from gradsep.model.frame import RGB

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
