"""The methods `gradsep evaluate` compares, and how each one turns a scene + G-PT frame into an image and timings.

Every method produces (image, per-layer images where it has them, render seconds, reconstruction seconds):

==========================  ===============================================================================
``gpt-primal``              the G-PT frame's primal image, Σ layers' base: the input every reconstruction sees
``l2``, ``l1``              screened Poisson (model.poisson via model.reconstruct), per layer, summed
``gradnet``                 the ``color`` model (no separation, no attention: the GradNet-style baseline) run
                            on the frame's combined layer, ``Frame.combined()``
``ablation/<variant>``      the four ablation models of the paper's Fig. 7, ``models/ablation/<variant>/``:
                            ``combined-*`` run ``color.onnx`` on the combined layer, ``separated-*`` run
                            ``direct.onnx`` + ``indirect.onnx`` per layer; ``-attn`` / ``-noattn`` say whether
                            the network has CBAM attention
``ours``                    the shipped pair ``models/direct.onnx`` + ``models/indirect.onnx`` (separation +
                            attention), per layer, summed
``path``                    Mitsuba's own ``path`` integrator at *equal time* (below)
``path-oidn``               ``path`` with albedo/normal AOVs (Mitsuba's ``aov`` integrator wrapping ``path``,
                            same samples) denoised by Intel Open Image Denoise (``pyoidn``), equal time
==========================  ===============================================================================

Equal time: the budget of a G-PT spp is the G-PT render time plus the reconstruction time of ``ours`` (of
``l1`` when ``ours`` is unavailable, which the report says). Mitsuba's cost on the scene is measured first as
``seconds = overhead + per_spp · spp``, a line fitted to warm renders (after an untimed 1-spp render that pays
the JIT compilation, which a user rendering a sequence pays once: 1, 4, 16, ... spp, each the faster of two, until
one takes a quarter second; every later render adds a point, and a prediction far beyond the measured range is
first checked at a quarter of its spp). The spp is the largest that fits the budget (at least 1); for
``path-oidn`` the measured denoising time comes off the budget first. A render that misses its budget by more
than 25 % is redone once at the refitted spp. The time in
the results is the time that render actually took, not the prediction, so the plot places every point where
it really is.

Timings exclude one-time costs on both sides: each network is run once untimed per frame size (ONNX
Runtime's allocation on a new shape), Mitsuba's kernels are compiled before the timed render. The G-PT
render time is the renderer's own (``gradsep.render_seconds``), which includes its per-frame tracing.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from model.frame import Frame

__all__ = [
    "ABLATION_VARIANTS",
    "METHODS",
    "MethodContext",
    "MethodOutput",
    "MethodSpec",
    "NetworkPool",
    "PathRenderer",
    "CostModel",
    "method_by_name",
    "run_method",
]

_F32_MAX = float(np.finfo(np.float32).max)
MAX_WAVEFRONT = (1 << 32) - 1  # Mitsuba's samples per launch
#: Source files whose changes alter a method's images or scores (part of every result's cache key).
METHOD_SOURCES: tuple[str, ...] = ("model/evaluate_methods.py", "model/poisson.py", "model/reconstruct.py",
                                   "model/infer.py", "model/preprocess.py", "model/metrics.py")


@dataclass(frozen=True)
class MethodSpec:
    """One compared method. ``models`` is the folder under the models directory that holds its ONNX files."""

    name: str
    label: str
    kind: str  # primal | poisson | network | path | oidn
    poisson: str | None = None
    models: str | None = None
    separated: bool | None = None  # network: per-layer models (True) or the color model on the sum (False)
    attention: bool | None = None  # for the ablation table

    def model_names(self, layers: tuple[str, ...]) -> tuple[str, ...]:
        """The model files (``NAME.onnx``) this method needs for a frame with ``layers``."""
        if self.kind != "network":
            return ()
        return tuple(layers) if self.separated else ("color",)


ABLATION_VARIANTS: tuple[tuple[str, bool, bool], ...] = (
    # (variant, separated, attention) in the order of the paper's Fig. 7 (a)-(d)
    ("combined-noattn", False, False),
    ("separated-noattn", True, False),
    ("combined-attn", False, True),
    ("separated-attn", True, True),
)

METHODS: tuple[MethodSpec, ...] = (
    MethodSpec("gpt-primal", "Input (G-PT primal)", "primal"),
    MethodSpec("l2", "L2 Poisson", "poisson", poisson="l2"),
    MethodSpec("l1", "L1 Poisson", "poisson", poisson="l1"),
    MethodSpec("gradnet", "GradNet-style (color model)", "network", models="", separated=False, attention=False),
    *(MethodSpec(f"ablation/{v}", f"Ablation {v}", "network", models=f"ablation/{v}", separated=s, attention=a)
      for v, s, a in ABLATION_VARIANTS),
    MethodSpec("ours", "Ours (separated + attention)", "network", models="", separated=True, attention=True),
    MethodSpec("path", "Mitsuba path (equal time)", "path"),
    MethodSpec("path-oidn", "Mitsuba path + OIDN (equal time)", "oidn"),
)


def method_by_name(name: str) -> MethodSpec:
    for spec in METHODS:
        if spec.name == name:
            return spec
    raise KeyError(name)


@dataclass
class MethodOutput:
    """What one method produced for one (scene, spp)."""

    image: np.ndarray
    layers: dict[str, np.ndarray]
    render_seconds: float
    reconstruct_seconds: float
    method_spp: int
    extra: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


# ------------------------------------------------------------------------------------------------ networks


class NetworkPool:
    """Loaded ONNX reconstructors by folder, with the untimed warm-up runs per frame size.

    A model that exists but cannot be served (corrupt, exported for another layer) is an error the user has to
    fix, raised as ``ModelError`` -- not a method silently skipped.
    """

    def __init__(self) -> None:
        self._loaded: dict[Path, Any] = {}
        self._warm: set[tuple[Path, str, tuple[int, int]]] = set()

    def get(self, folder: Path) -> Any:
        folder = folder.resolve()
        if folder not in self._loaded:
            from model.infer import NetworkReconstructor

            self._loaded[folder] = NetworkReconstructor.load(folder)
        return self._loaded[folder]

    def warm_up(self, folder: Path, run: Callable[[], object], key: str, shape: tuple[int, int]) -> None:
        """Run ``run`` once untimed the first time ``key`` meets a frame of ``shape`` in ``folder``."""
        tag = (folder.resolve(), key, shape)
        if tag not in self._warm:
            run()
            self._warm.add(tag)


def _sanitise(image: np.ndarray) -> np.ndarray:
    """Finite and >= 0, as model.reconstruct does for its outputs (the combined-model path bypasses it)."""
    out = np.nan_to_num(np.asarray(image, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(out, 0.0, _F32_MAX)


# ------------------------------------------------------------------------------------------- Mitsuba path


class CostModel:
    """seconds ≈ overhead + per_spp · spp for one integrator on one scene and film, fitted to measured renders.

    Every timed render adds a sample, so predictions get better as the run goes on; a least-squares line
    through all samples (overhead clamped at 0, slope kept positive) is robust to one noisy measurement.
    """

    def __init__(self, max_spp: int) -> None:
        self.max_spp = max_spp
        self.samples: list[tuple[int, float]] = []

    def add(self, spp: int, seconds: float) -> None:
        if spp >= 1 and math.isfinite(seconds) and seconds >= 0:
            self.samples.append((int(spp), float(seconds)))

    @property
    def largest_sampled(self) -> int:
        return max((s for s, _ in self.samples), default=0)

    def fit(self) -> tuple[float, float]:
        """(overhead, per_spp); with a single distinct spp the overhead is taken as 0."""
        if not self.samples:
            raise RuntimeError("cost model has no measurements")
        x = np.array([s for s, _ in self.samples], dtype=np.float64)
        y = np.array([t for _, t in self.samples], dtype=np.float64)
        per_spp = 0.0
        if np.ptp(x) > 0:
            per_spp = float(np.polyfit(x, y, 1)[0])
        if not per_spp > 0:  # one spp only, or noise made the larger render faster: no overhead
            per_spp = max(float(np.sum(y) / np.sum(x)), 1e-9)
        overhead = max(0.0, float(np.mean(y - per_spp * x)))
        return overhead, per_spp

    def spp_for(self, seconds: float) -> int:
        """The largest spp whose predicted time fits ``seconds`` (at least 1, at most ``max_spp``)."""
        if not math.isfinite(seconds):
            return 1
        overhead, per_spp = self.fit()
        spp = math.floor((seconds - overhead) / per_spp + 1e-9)  # 1.5 s at 0.01 s/spp is 100, not 99.999…
        return int(min(self.max_spp, max(1, spp)))


class PathRenderer:
    """Mitsuba's ``path`` (raw) and ``aov`` + ``path`` (for OIDN) on one loaded scene, with their cost models."""

    #: Calibration renders grow ×4 from 1 spp until one takes this long: shorter ones are all noise and
    #: overhead on a busy machine.
    CALIBRATION_SECONDS = 0.25
    #: A prediction more than this many times the largest measured spp is probed at a quarter first.
    EXTRAPOLATION = 8
    #: A render whose measured time misses the budget by more than this fraction is redone once at the spp the
    #: refitted line gives (when that differs by more than the same fraction).
    TOLERANCE = 0.25

    def __init__(self, loaded: Any) -> None:
        import mitsuba as mi

        self.loaded = loaded
        path = {"type": "path", "max_depth": int(loaded.max_depth), "rr_depth": int(loaded.rr_depth)}
        self.integrators = {
            "path": mi.load_dict(path),
            # albedo and shading normal from the same camera samples as the colour: what a user feeds OIDN
            "oidn": mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal", "integrator": path}),
        }
        self.max_spp = max(1, MAX_WAVEFRONT // max(1, loaded.width * loaded.height))
        self._costs: dict[str, CostModel] = {}
        self._denoise_seconds: float | None = None

    def render(self, kind: str, spp: int, seed: int) -> tuple[np.ndarray, float]:
        """The raw render (H, W, C) as float32 and its wall seconds (recorded in the cost model once calibrated)."""
        import mitsuba as mi

        start = time.perf_counter()
        image = mi.render(self.loaded.scene, sensor=self.loaded.sensor, integrator=self.integrators[kind],
                          spp=int(spp), seed=int(seed) % (1 << 32))
        array = np.array(image, dtype=np.float32)
        seconds = time.perf_counter() - start
        if kind in self._costs:
            self._costs[kind].add(spp, seconds)
        return array, seconds

    def cost(self, kind: str) -> CostModel:
        """The cost model of ``kind``, measured once per scene after an untimed compile render.

        Each calibration spp is rendered twice and the faster time kept: on a shared machine noise only ever
        adds time. At least two spp are measured, the last taking :data:`CALIBRATION_SECONDS` or more.
        """
        if kind not in self._costs:
            self.render(kind, 1, 7)  # JIT compilation, not timed
            model = CostModel(self.max_spp)
            spp = 1
            while True:
                seconds = min(self.render(kind, spp, 11)[1], self.render(kind, spp, 13)[1])
                model.add(spp, seconds)
                if (seconds >= self.CALIBRATION_SECONDS and len(model.samples) >= 2) or spp >= self.max_spp:
                    break
                spp = min(self.max_spp, spp * 4)
            self._costs[kind] = model
        return self._costs[kind]

    def spp_for(self, kind: str, seconds: float) -> int:
        """The spp of ``kind`` that fits ``seconds``; far extrapolations are checked by a render at a quarter of
        the prediction first (its cost is a fraction of the final render's)."""
        model = self.cost(kind)
        spp = model.spp_for(seconds)
        while spp > self.EXTRAPOLATION * model.largest_sampled:
            self.render(kind, max(1, spp // 4), 19)
            spp = model.spp_for(seconds)
        return spp

    def render_within(self, kind: str, seconds: float, seed: int) -> tuple[np.ndarray, float, int]:
        """Render ``kind`` at the spp that fits ``seconds``: (image, measured seconds, spp).

        When the measured time misses the budget by more than :data:`TOLERANCE`, the line (now including this
        render) is refitted and the render redone once if the spp it gives differs by more than that too.
        """
        spp = self.spp_for(kind, seconds)
        image, took = self.render(kind, spp, seed)
        if abs(took - seconds) > self.TOLERANCE * seconds:
            again = self.cost(kind).spp_for(seconds)
            if abs(again - spp) > self.TOLERANCE * spp:
                spp = again
                image, took = self.render(kind, spp, seed)
        return image, took, spp

    def denoise_seconds(self) -> float:
        """OIDN's time on a frame of this size, measured on a warm device (its first call initialises it)."""
        if self._denoise_seconds is None:
            image, _ = self.render("oidn", 1, 17)
            color, albedo, normal = split_aov(image)
            denoise(color, albedo, normal)
            timings = []
            for _ in range(2):  # the faster of two: noise on a shared machine only adds time
                start = time.perf_counter()
                denoise(color, albedo, normal)
                timings.append(time.perf_counter() - start)
            self._denoise_seconds = min(timings)
        return self._denoise_seconds


def split_aov(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """colour, albedo, normal of an ``aov(albedo, sh_normal)`` render: RGB first, the 6 AOV channels last
    (a film with alpha puts A between them)."""
    if image.ndim != 3 or image.shape[-1] < 9:
        raise RuntimeError(f"aov render has shape {image.shape}; expected RGB(A) + albedo + normal channels")
    return (np.ascontiguousarray(image[..., :3]), np.ascontiguousarray(image[..., -6:-3]),
            np.ascontiguousarray(image[..., -3:]))


def denoise(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Intel Open Image Denoise, the RT filter on HDR input with (noisy, so prefiltered) albedo and normal.

    Inputs are made finite first (OIDN's contract): radiance ≥ 0, albedo in [0, 1], normals in [-1, 1].
    """
    import pyoidn

    c = np.clip(np.nan_to_num(color, nan=0.0, posinf=0.0, neginf=0.0), 0.0, _F32_MAX).astype(np.float32)
    a = np.clip(np.nan_to_num(albedo), 0.0, 1.0).astype(np.float32)
    n = np.clip(np.nan_to_num(normal), -1.0, 1.0).astype(np.float32)
    return _sanitise(pyoidn.denoise(c, a, n, hdr=True, clean_aux=False, quality="high"))


# ------------------------------------------------------------------------------------------------ running


@dataclass
class MethodContext:
    """Everything a method may need for one (scene, spp)."""

    frame: Frame
    render_seconds: float  # G-PT render time of ``frame``
    spp: int
    seed: int
    alpha: float
    models_dir: Path
    networks: NetworkPool
    path: Callable[[], PathRenderer]  # lazily built per scene (loads Mitsuba integrators)
    budget_seconds: float | None = None  # equal-time budget for path / path-oidn
    budget_method: str | None = None


def run_method(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """Run one method; ModelError for a model that exists but cannot be served."""
    runner = {"primal": _run_primal, "poisson": _run_poisson, "network": _run_network, "path": _run_path,
              "oidn": _run_oidn}[spec.kind]
    return runner(spec, ctx)


def _run_primal(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    layers = {name: _sanitise(layer.base) for name, layer in ctx.frame.layers.items()}
    image = _sanitise(sum(layers.values()))
    return MethodOutput(image, layers, ctx.render_seconds, 0.0, ctx.spp)


def _run_poisson(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    from model.reconstruct import reconstruct

    start = time.perf_counter()
    result = reconstruct(ctx.frame, str(spec.poisson), ctx.alpha)
    seconds = time.perf_counter() - start
    return MethodOutput(result.image, result.layers, ctx.render_seconds, seconds, ctx.spp,
                        extra={"alpha": ctx.alpha}, warnings=list(result.warnings))


def _run_network(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    from model.reconstruct import reconstruct

    folder = ctx.models_dir / (spec.models or "")
    network = ctx.networks.get(folder)
    frame = ctx.frame
    shape = (frame.height, frame.width)
    if spec.separated:
        def run() -> Any:
            return reconstruct(frame, "network", network=network)

        ctx.networks.warm_up(folder, run, "separated", shape)
        start = time.perf_counter()
        result = run()
        seconds = time.perf_counter() - start
        return MethodOutput(result.image, result.layers, ctx.render_seconds, seconds, ctx.spp,
                            warnings=list(result.warnings))

    def run_combined() -> np.ndarray:
        return _sanitise(network.reconstruct_layer("color", frame.combined(), frame.features))

    ctx.networks.warm_up(folder, run_combined, "color", shape)
    start = time.perf_counter()
    image = run_combined()
    seconds = time.perf_counter() - start
    return MethodOutput(image, {}, ctx.render_seconds, seconds, ctx.spp)


def _budget(ctx: MethodContext) -> float:
    if ctx.budget_seconds is None:
        raise RuntimeError("equal-time methods need a budget (the G-PT render + reconstruction time)")
    return ctx.budget_seconds


def _run_path(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    renderer = ctx.path()
    target = _budget(ctx)
    image, seconds, spp = renderer.render_within("path", target, ctx.seed)
    return MethodOutput(_sanitise(image[..., :3]), {}, seconds, 0.0, spp,
                        extra=_equal_time_extra(ctx, target, spp, renderer.max_spp))


def _run_oidn(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    renderer = ctx.path()
    target = _budget(ctx)
    raw, seconds, spp = renderer.render_within("oidn", target - renderer.denoise_seconds(), ctx.seed)
    color, albedo, normal = split_aov(raw)
    start = time.perf_counter()
    image = denoise(color, albedo, normal)
    denoise_seconds = time.perf_counter() - start
    return MethodOutput(image, {}, seconds, denoise_seconds, spp,
                        extra=_equal_time_extra(ctx, target, spp, renderer.max_spp))


def _equal_time_extra(ctx: MethodContext, target: float, spp: int, max_spp: int) -> dict[str, Any]:
    extra: dict[str, Any] = {"target_seconds": target, "budget_method": ctx.budget_method}
    if spp >= max_spp:
        extra["capped"] = f"spp capped at {max_spp} (Mitsuba's 2^32 samples per launch)"
    return extra
