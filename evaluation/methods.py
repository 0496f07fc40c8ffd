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
``oidn``                    OIDN on each layer of the G-PT frame, summed (``reconstruct(frame, "oidn")``)
``fused``                   the fused network of ``models/fused/<layer>.onnx`` (``reconstruct(frame, "fused",
                            fused=...)``); skipped, listing the missing files, without them
``path``                    Mitsuba's own ``path`` integrator at *equal time* (below)
``path-oidn``               ``path`` denoised by Intel Open Image Denoise (model/oidn.py) with albedo and normal
                            from a separate :data:`FEATURE_SPP`-spp feature pass (Mitsuba ``aov``) whose time
                            is counted; equal time
``path-sep-oidn``           the renderer's primal-only mode (``render_frame(..., gradients=False)``: G-PT's
                            direct/indirect routing and first-hit features, no offset paths), OIDN on each
                            layer (``reconstruct(frame, "oidn")``), summed; equal time. A method the code base
                            cannot run (no such reconstruct method, no primal-only mode, no pyoidn) is skipped
                            with that reason (:func:`unavailable`)
==========================  ===============================================================================

Equal time: the budget of a G-PT spp is the G-PT render time plus the reconstruction time of ``ours`` (of
``l1`` when ``ours`` is unavailable, which the report says). Each equal-time renderer's cost on the scene is
measured first as ``seconds = overhead + per_spp · spp``, a line fitted to warm renders (after an untimed 1-spp
render that pays the JIT compilation, which a user rendering a sequence pays once: 1, 4, 16, ... spp, each the
faster of two, until one takes a quarter second; every later render adds a point). A *try* is a render plus
its post-processing (the OIDN call(s)), timed together; ``path-oidn``'s feature pass is rendered once per row and
taken off the budget first. The spp is *bisected*: the first try at the line's prediction (for the budget less a
pre-measured post-processing time), and while a try's measured total misses the target by more than
:data:`PathRenderer.TOLERANCE` (5 %), the next interpolates between the closest too-fast and too-slow tries (their
midpoint when the interpolation leaves the bracket), at most :data:`PathRenderer.MAX_ATTEMPTS` tries. The row
keeps the try closest to the target and records the tries; the report flags every row whose measured total is
still outside ±5 % of its budget (spp granularity at tiny budgets, or a machine whose speed changed between
tries). The time in the results is the time the kept try actually took, not the prediction.

Timings exclude one-time costs on both sides: each network is run once untimed per frame size (ONNX
Runtime's allocation on a new shape), Mitsuba's kernels are compiled before the timed render. The G-PT
render time is the renderer's own (``gradsep.render_seconds``), which includes its per-frame tracing.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
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
    "EQUAL_TIME_KINDS",
    "Attempt",
    "FEATURE_SPP",
    "PathRenderer",
    "CostModel",
    "unavailable",
    "method_by_name",
    "run_method",
]

_F32_MAX = float(np.finfo(np.float32).max)
MAX_WAVEFRONT = (1 << 32) - 1  # Mitsuba's samples per launch
#: Samples per pixel of the feature pass that gives ``path-oidn`` its albedo and normal: a production renderer
#: writes them nearly for free; 4 spp antialiases edges well enough for OIDN, which prefilters them anyway.
FEATURE_SPP = 4
#: Source files whose changes alter a method's images or scores (part of every result's cache key).
METHOD_SOURCES: tuple[str, ...] = ("evaluation/methods.py", "model/poisson.py", "model/reconstruct.py",
                                   "model/infer.py", "model/preprocess.py", "model/metrics.py", "model/policy.py")


@dataclass(frozen=True)
class MethodSpec:
    """One compared method. ``models`` is the folder under the models directory that holds its ONNX files."""

    name: str
    label: str
    kind: str  # primal | poisson | network | recon | fused | path | oidn | sep-oidn
    poisson: str | None = None  # poisson: l1 | l2; recon: the model.reconstruct method name
    models: str | None = None
    separated: bool | None = None  # network: per-layer models (True) or the color model on the sum (False)
    attention: bool | None = None  # for the ablation table

    def model_names(self, layers: tuple[str, ...]) -> tuple[str, ...]:
        """The model files (``NAME.onnx``) this method needs for a frame with ``layers``."""
        if self.kind == "fused":
            return tuple(layers)
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
    MethodSpec("oidn", "G-PT + OIDN per layer", "recon", poisson="oidn"),
    MethodSpec("fused", "Fused network", "fused", models="fused"),
    MethodSpec("ours", "Ours (separated + attention)", "network", models="", separated=True, attention=True),
    MethodSpec("path", "Mitsuba path (equal time)", "path"),
    MethodSpec("path-oidn", "Mitsuba path + OIDN (equal time)", "oidn"),
    MethodSpec("path-sep-oidn", "Separated path + OIDN per layer (equal time)", "sep-oidn"),
)
#: Methods rendered to a time budget rather than reconstructing the G-PT frame.
EQUAL_TIME_KINDS: tuple[str, ...] = ("path", "oidn", "sep-oidn")


def unavailable(spec: MethodSpec) -> str | None:
    """Why ``spec`` cannot run with this code base (None: it can). Model files are checked separately."""
    if spec.kind in ("recon", "fused"):
        from model.reconstruct import METHODS as RECONSTRUCT_METHODS

        wanted = spec.poisson if spec.kind == "recon" else "fused"
        if wanted not in RECONSTRUCT_METHODS:
            return (f"model.reconstruct has no {wanted!r} method on this branch (expected "
                    f"reconstruct(frame, {wanted!r}{', fused=...' if spec.kind == 'fused' else ''}))")
    if spec.kind in ("oidn", "sep-oidn", "recon", "fused"):
        import importlib.util

        if importlib.util.find_spec("pyoidn") is None:
            return "pyoidn is not installed (pip install 'gradsep[evaluate]')"
    if spec.kind == "sep-oidn" and not primal_mode_available():
        return ("renderer.render.render_frame has no gradients= parameter: the primal-only render mode "
                "(issue 13 item 3) is not on this branch")
    return None


@cache
def primal_mode_available() -> bool:
    """Whether the renderer has the primal-only mode ``render_frame(..., gradients=False)`` (asked once: the
    code does not change while the process runs)."""
    import inspect

    from renderer.render import render_frame

    return "gradients" in inspect.signature(render_frame).parameters


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


@dataclass
class Attempt:
    """The try :meth:`PathRenderer.render_within` kept: its output (after ``post``), times, spp, tries made."""

    output: Any
    render_seconds: float
    post_seconds: float
    spp: int
    attempts: int
    miss: float  # |measured / target - 1|


class PathRenderer:
    """The equal-time renderers on one loaded scene, each with its cost model.

    Kinds: ``path`` (Mitsuba ``path``, raw colour), ``features`` (Mitsuba ``aov``: albedo and shading normal
    only, the cheap pass feeding OIDN) and ``primal`` (our renderer's primal-only mode, a gradient-free Frame).
    """

    #: Calibration renders grow ×4 from 1 spp until one takes this long: shorter ones are all noise and
    #: overhead on a busy machine.
    CALIBRATION_SECONDS = 0.25
    #: A prediction more than this many times the largest measured spp is probed at a quarter first.
    EXTRAPOLATION = 8
    #: A render is accepted when its measured time is within this fraction of its target.
    TOLERANCE = 0.05
    #: Renders tried per row before the one closest to the target is kept.
    MAX_ATTEMPTS = 5

    def __init__(self, loaded: Any) -> None:
        import mitsuba as mi

        self.loaded = loaded
        path = {"type": "path", "max_depth": int(loaded.max_depth), "rr_depth": int(loaded.rr_depth)}
        self.integrators = {
            "path": mi.load_dict(path),
            # albedo and shading normal only (no nested integrator): what a production renderer writes cheaply
            "features": mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal"}),
        }
        self.max_spp = max(1, MAX_WAVEFRONT // max(1, loaded.width * loaded.height))
        self._costs: dict[str, CostModel] = {}
        self._post_seconds: dict[str, float] = {}
        self._warm: set[str] = set()

    def render(self, kind: str, spp: int, seed: int) -> tuple[Any, float]:
        """The raw render (an (H, W, C) float32 array, or a Frame for ``primal``) and its wall seconds (recorded
        in the cost model once calibrated)."""
        start = time.perf_counter()
        if kind == "primal":
            from renderer.render import render_frame

            output: Any = render_frame(self.loaded, spp=int(spp), seed=int(seed) % (1 << 32), gradients=False)
        else:
            import mitsuba as mi

            image = mi.render(self.loaded.scene, sensor=self.loaded.sensor, integrator=self.integrators[kind],
                              spp=int(spp), seed=int(seed) % (1 << 32))
            output = np.array(image, dtype=np.float32)
        seconds = time.perf_counter() - start
        if kind in self._costs:
            self._costs[kind].add(spp, seconds)
        return output, seconds

    def warm(self, kind: str) -> None:
        """One untimed 1-spp render: Dr.Jit's kernel compilation, paid once per scene and kind."""
        if kind not in self._warm:
            self.render(kind, 1, 7)
            self._warm.add(kind)

    def cost(self, kind: str) -> CostModel:
        """The cost model of ``kind``, measured once per scene after an untimed compile render.

        Each calibration spp is rendered twice and the faster time kept: on a shared machine noise only ever
        adds time. At least two spp are measured, the last taking :data:`CALIBRATION_SECONDS` or more.
        """
        if kind not in self._costs:
            self.warm(kind)
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

    def render_within(self, kind: str, seconds: float, seed: int, post: Callable[[Any], Any] | None = None,
                      post_estimate: float = 0.0) -> Attempt:
        """Render ``kind`` (then run ``post`` on the render, e.g. the denoiser) at the spp whose measured time,
        render + ``post``, is within :data:`TOLERANCE` of ``seconds``. The first spp comes from the cost line
        (``post_estimate`` off the budget); then each try interpolates between the closest too-fast and
        too-slow tries (bisecting when that would not move inside the bracket), or scales the last try when only
        one side is known. The try closest to the target is kept."""
        spp = self.spp_for(kind, max(1e-6, seconds - post_estimate))
        tried: list[tuple[int, float]] = []
        best: Attempt | None = None
        while len(tried) < self.MAX_ATTEMPTS:
            output, took = self.render(kind, spp, seed)
            start = time.perf_counter()
            result = post(output) if post is not None else output
            post_took = time.perf_counter() - start if post is not None else 0.0
            total = took + post_took
            tried.append((spp, total))
            miss = total / seconds - 1.0 if seconds > 0 else math.inf
            if best is None or abs(miss) < best.miss:
                best = Attempt(result, took, post_took, spp, 0, abs(miss))
            if abs(miss) <= self.TOLERANCE:
                break
            following = self._next_spp(kind, seconds, tried, post_estimate)
            if following is None:
                break
            spp = following
        assert best is not None
        best.attempts = len(tried)
        return best

    def _next_spp(self, kind: str, seconds: float, tried: list[tuple[int, float]],
                  post_estimate: float = 0.0) -> int | None:
        """The next spp to try for ``seconds`` given the renders ``tried`` (None: no better integer spp)."""
        fast = [(s, t) for s, t in tried if t < seconds]
        slow = [(s, t) for s, t in tried if t >= seconds]
        if fast and slow:
            (s0, t0), (s1, t1) = max(fast), min(slow)
            if s1 - s0 <= 1:  # spp granularity: no integer between a too-fast and a too-slow render
                return None
            guess = round(s0 + (seconds - t0) * (s1 - s0) / (t1 - t0)) if t1 > t0 else (s0 + s1) // 2
            if not s0 < guess < s1 or any(guess == s for s, _ in tried):
                guess = (s0 + s1) // 2
            return guess
        spp, took = tried[-1]
        overhead = min(self.cost(kind).fit()[0] + post_estimate, 0.5 * took)  # fixed cost per try
        guess = max(1, min(self.max_spp, round(spp * (seconds - overhead) / max(took - overhead, 1e-9))))
        if (slow and spp == 1) or (fast and spp >= self.max_spp) or guess == spp:
            return None  # already at the smallest / largest possible spp
        return guess

    def post_seconds(self, name: str, run: Callable[[], object]) -> float:
        """The time of a row's fixed post-processing ``run`` (a denoiser call) on this scene's frame size,
        measured once per scene on a warm device (the first call initialises it): the faster of two, as noise
        on a shared machine only adds time."""
        if name not in self._post_seconds:
            run()
            timings = []
            for _ in range(2):
                start = time.perf_counter()
                run()
                timings.append(time.perf_counter() - start)
            self._post_seconds[name] = min(timings)
        return self._post_seconds[name]


def split_features(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """albedo, normal of an ``aov(albedo, sh_normal)`` render: the 6 AOV channels come last (Mitsuba puts
    any film channels, e.g. RGB(A) of a nested integrator, before them)."""
    if image.ndim != 3 or image.shape[-1] < 6:
        raise RuntimeError(f"aov render has shape {image.shape}; expected albedo + normal channels last")
    return np.ascontiguousarray(image[..., -6:-3]), np.ascontiguousarray(image[..., -3:])


def denoise(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Intel Open Image Denoise as model/oidn.py runs it for the ``oidn`` method (one definition): the RT filter
    on HDR input at quality "high", albedo and normal prefiltered first (they are noisy), exact exposure scaling."""
    from model.frame import Features
    from model.oidn import shared_denoiser

    denoiser = shared_denoiser()
    aux = denoiser.prefilter(Features(np.ascontiguousarray(albedo, np.float32),
                                      np.ascontiguousarray(normal, np.float32),
                                      np.zeros(color.shape[:2], np.float32)))
    return _sanitise(denoiser.denoise(np.ascontiguousarray(color, np.float32), aux))


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
    budget_seconds: float | None = None  # equal-time budget of the EQUAL_TIME_KINDS methods
    budget_method: str | None = None


def run_method(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """Run one method; ModelError for a model that exists but cannot be served."""
    runner = {"primal": _run_primal, "poisson": _run_poisson, "network": _run_network, "recon": _run_recon,
              "fused": _run_fused, "path": _run_path, "oidn": _run_oidn, "sep-oidn": _run_sep_oidn}[spec.kind]
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


def _run_recon(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """A model.reconstruct method that needs no network object (``oidn``: OIDN per layer of the G-PT frame)."""
    from model.reconstruct import reconstruct

    def run() -> Any:
        return reconstruct(ctx.frame, str(spec.poisson))

    ctx.networks.warm_up(ctx.models_dir, run, f"recon:{spec.poisson}", (ctx.frame.height, ctx.frame.width))
    start = time.perf_counter()
    result = run()
    seconds = time.perf_counter() - start
    return MethodOutput(result.image, result.layers, ctx.render_seconds, seconds, ctx.spp,
                        warnings=list(result.warnings))


def _run_fused(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """``reconstruct(frame, "fused", fused=<NetworkReconstructor of models/fused/>)``."""
    from model.reconstruct import reconstruct

    folder = ctx.models_dir / str(spec.models)
    fused = ctx.networks.get(folder)
    wrong = [m.path.name for m in fused.models.values() if getattr(m, "prior", "oidn") != "oidn"]
    if wrong:
        from model.infer import ModelError

        raise ModelError(f"{folder}: {', '.join(wrong)} refine another prior than OIDN's; not fused models")

    def run() -> Any:
        return reconstruct(ctx.frame, "fused", fused=fused)

    ctx.networks.warm_up(folder, run, "fused", (ctx.frame.height, ctx.frame.width))
    start = time.perf_counter()
    result = run()
    seconds = time.perf_counter() - start
    return MethodOutput(result.image, result.layers, ctx.render_seconds, seconds, ctx.spp,
                        warnings=list(result.warnings))


def _budget(ctx: MethodContext) -> float:
    if ctx.budget_seconds is None:
        raise RuntimeError("equal-time methods need a budget (the G-PT render + reconstruction time)")
    return ctx.budget_seconds


def _run_path(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    renderer = ctx.path()
    target = _budget(ctx)
    got = renderer.render_within("path", target, ctx.seed)
    return MethodOutput(_sanitise(got.output[..., :3]), {}, got.render_seconds, 0.0, got.spp,
                        extra=_equal_time_extra(ctx, target, got, renderer.max_spp))


def _run_oidn(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """``path`` + OIDN: a timed :data:`FEATURE_SPP`-spp feature pass, then ``path`` + the denoiser call tried
    at spp bisected until both together fit what is left of the budget."""
    renderer = ctx.path()
    target = _budget(ctx)
    renderer.warm("features")
    features, feature_seconds = renderer.render("features", FEATURE_SPP, ctx.seed ^ 0x5EED)
    albedo, normal = split_features(features)
    colour = np.ones(albedo.shape, np.float32)
    estimate = renderer.post_seconds("path-oidn", lambda: denoise(colour, albedo, normal))
    got = renderer.render_within("path", max(1e-6, target - feature_seconds), ctx.seed,
                                 post=lambda raw: denoise(raw[..., :3], albedo, normal), post_estimate=estimate)
    extra = _equal_time_extra(ctx, target, got, renderer.max_spp)
    extra["feature_spp"] = FEATURE_SPP
    return MethodOutput(got.output, {}, got.render_seconds + feature_seconds, got.post_seconds, got.spp, extra=extra)


def _run_sep_oidn(spec: MethodSpec, ctx: MethodContext) -> MethodOutput:
    """The primal-only G-PT render (separated layers, first-hit features, no gradients) reconstructed with the
    ``oidn`` method (OIDN on each layer, summed: model/oidn.py), render + reconstruction bisected to the budget."""
    from model.reconstruct import reconstruct

    renderer = ctx.path()
    target = _budget(ctx)
    renderer.warm("primal")
    sample, _ = renderer.render("primal", 1, 23)
    estimate = renderer.post_seconds("path-sep-oidn", lambda: reconstruct(sample, "oidn"))
    got = renderer.render_within("primal", target, ctx.seed, post=lambda frame: reconstruct(frame, "oidn"),
                                 post_estimate=estimate)
    result = got.output
    return MethodOutput(result.image, result.layers, got.render_seconds, got.post_seconds, got.spp,
                        extra=_equal_time_extra(ctx, target, got, renderer.max_spp), warnings=list(result.warnings))


def _equal_time_extra(ctx: MethodContext, target: float, got: Attempt, max_spp: int) -> dict[str, Any]:
    extra: dict[str, Any] = {"target_seconds": target, "budget_method": ctx.budget_method,
                             "attempts": got.attempts}
    if got.spp >= max_spp:
        extra["capped"] = f"spp capped at {max_spp} (Mitsuba's 2^32 samples per launch)"
    return extra
