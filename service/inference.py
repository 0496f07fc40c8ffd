"""Inference off the event loop: model loading and warm-up, a bounded queue, and the per-request pipeline.

Why a gate of our own rather than ``anyio.to_thread.run_sync(limiter=...)`` alone: a thread cannot be killed, so
when a request passes its timeout (504) its reconstruction keeps running in the background. anyio would release
the limiter's slot as soon as the waiting request gave up, letting a new inference start beside the abandoned
one and oversubscribing the CPU. Here every job runs in a task of the app's own task group that holds its slot
until the thread really ends; the request only waits for the job's completion event, with a deadline. A job
whose request gave up while it was still queued never starts. Shutdown (the lifespan's task group closing)
waits for running jobs, so in-flight work finishes.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, Literal, TypeVar

import anyio
import numpy as np
from anyio.abc import TaskGroup

from gradsep.model import methods as table
from gradsep.model.exr_read import ReadLimits, Source, read_frame
from gradsep.model.exr_write import configure_exr_threads, encode_answer
from gradsep.model.frame import Layer, forward_differences, rgb_channels
from gradsep.model.header_keys import OIDN_SETTING_KEY
from gradsep.service.errors import ServiceError
from gradsep.service.settings import Settings

log = logging.getLogger("gradsep.service")

T = TypeVar("T")


# ---------------------------------------------------------------------------------------------------------------
# The gate: a capacity limiter plus a bounded waiting room
# ---------------------------------------------------------------------------------------------------------------


@dataclass(eq=False)
class _Job(Generic[T]):
    fn: Callable[[], T]
    done: anyio.Event = field(default_factory=anyio.Event)
    result: T | None = None
    error: BaseException | None = None
    abandoned: bool = False
    queued_at: float = field(default_factory=time.perf_counter)
    started_at: float | None = None


class InferenceGate:
    """At most ``concurrency`` jobs run (each in a worker thread); at most ``queue_size`` more wait.

    ``waiting`` and ``running`` are only touched on the event loop, so plain ints are safe. ``running`` counts
    threads until they return, including those whose request already timed out.
    """

    def __init__(self, concurrency: int, queue_size: int, task_group: TaskGroup) -> None:
        self.concurrency, self.queue_size = concurrency, queue_size
        self._slots = anyio.CapacityLimiter(concurrency)
        self._threads = anyio.CapacityLimiter(concurrency)  # our own, so Starlette's thread pool can't starve us
        self._tg = task_group
        self.waiting = 0
        self.running = 0
        self._mean_seconds = 1.0  # exponentially weighted mean job duration, for Retry-After

    @property
    def full(self) -> bool:
        return self.waiting + self.running >= self.concurrency + self.queue_size

    def retry_after(self) -> int:
        """Seconds a rejected client should wait: the estimated time to drain what is admitted now."""
        backlog = (self.waiting + self.running) / self.concurrency
        return int(min(60, max(1, math.ceil(backlog * self._mean_seconds))))

    def queue_full_error(self) -> ServiceError:
        retry = self.retry_after()
        return ServiceError(
            503, "queue_full",
            f"inference queue is full ({self.running} running, {self.waiting} waiting); retry in {retry} s",
            {"running": self.running, "waiting": self.waiting, "queue_size": self.queue_size},
            headers={"Retry-After": str(retry)})

    async def run(self, fn: Callable[[], T], timeout: float) -> tuple[T, float]:
        """Run ``fn`` in a worker thread; return (result, seconds spent queued). 503 if full, 504 on timeout."""
        if self.full:
            raise self.queue_full_error()
        job: _Job[T] = _Job(fn)
        self.waiting += 1
        self._tg.start_soon(self._execute, job)
        try:
            with anyio.fail_after(timeout):
                await job.done.wait()
        except TimeoutError:
            job.abandoned = True
            state = "still running in the background" if job.started_at is not None else "never started"
            raise ServiceError(
                504, "timeout", f"inference did not finish within {timeout:g} s (the job {state})",
                {"timeout_seconds": timeout, "started": job.started_at is not None}) from None
        finally:
            job.abandoned = job.abandoned or not job.done.is_set()  # the request was cancelled (disconnect)
        if job.error is not None:
            raise job.error
        assert job.started_at is not None
        return job.result, job.started_at - job.queued_at  # type: ignore[return-value]

    async def _execute(self, job: _Job[Any]) -> None:
        queued = True
        try:
            async with self._slots:
                self.waiting -= 1
                queued = False
                if job.abandoned:
                    return
                job.started_at = time.perf_counter()
                self.running += 1
                try:
                    job.result = await anyio.to_thread.run_sync(job.fn, limiter=self._threads)
                except Exception as exc:  # handed to the waiting request, which re-raises it
                    job.error = exc
                finally:
                    self.running -= 1
                    elapsed = time.perf_counter() - job.started_at
                    self._mean_seconds = 0.8 * self._mean_seconds + 0.2 * elapsed
        finally:
            if queued:
                self.waiting -= 1
            job.done.set()


# ---------------------------------------------------------------------------------------------------------------
# One request's work: decode, reconstruct each layer, encode
# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReconstructParams:
    method: str | None  # None: model.reconstruct.choose_method decides per frame
    alpha: float
    half: bool
    layers: Literal["sum", "all"]
    request_id: str = "-"
    compression: str | None = None  # the request's EXR compression; the answer reuses it when lossless
    channels: str = "auto"  # the input's channel layout (model/channels.py)


@dataclass
class Outcome:
    body: bytes
    method: str
    timings: dict[str, float]  # Server-Timing names -> seconds, in order
    warnings: list[str]
    source_layers: list[str]


def reconstruct(frame: Any, method: str | None, alpha: float, models: table.LoadedModels | None = None) -> Any:
    """Indirection to ``model.reconstruct.reconstruct`` (imported on first use; tests may patch this name)."""
    from gradsep.model.reconstruct import reconstruct as model_reconstruct

    return model_reconstruct(frame, method, alpha, models)


def run_pipeline(source: Source, params: ReconstructParams, limits: ReadLimits, nonfinite: str,
                 models: table.LoadedModels | None = None) -> Outcome:
    """Decode, reconstruct and encode in the calling (worker) thread; frame problems raise FrameError."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if hasattr(source, "seek"):
        source.seek(0)  # the header check left the stream somewhere past the header
    frame = read_frame(source, limits=limits, nonfinite=nonfinite,  # type: ignore[arg-type]
                       layout=params.channels)
    timings["decode"] = time.perf_counter() - t0
    result = reconstruct(frame, params.method, params.alpha, models)
    for layer, seconds in dict(getattr(result, "timings", {}) or {}).items():
        timings[str(layer)] = float(seconds)
    warnings = [*frame.warnings, *(str(w) for w in getattr(result, "warnings", None) or ())]
    image = _finite(np.asarray(result.image, dtype=np.float32), "sum", warnings)
    channels = dict(rgb_channels("", image))
    if params.layers == "all":
        for name, layer_image in dict(result.layers).items():
            channels.update(rgb_channels(name, _finite(np.asarray(layer_image, dtype=np.float32), name, warnings)))
    t1 = time.perf_counter()
    metadata = {"gradsep.method": str(result.method), "gradsep.alpha": f"{params.alpha:g}",
                "gradsep.request_id": params.request_id, "gradsep.layers": ",".join(frame.layers)}
    if getattr(result, "oidn_setting", None):
        metadata[OIDN_SETTING_KEY] = str(result.oidn_setting)
    body = encode_answer(frame, channels, half=params.half, metadata=metadata, warnings=warnings,
                         compression=params.compression)
    timings["encode"] = time.perf_counter() - t1
    return Outcome(body, str(result.method), timings, warnings, list(frame.layers))


def _finite(image: np.ndarray, name: str, warnings: list[str]) -> np.ndarray:
    """Outputs are always finite: a solver that produced NaN/Inf is logged and the values are zeroed."""
    bad = int(np.count_nonzero(~np.isfinite(image)))
    if bad:
        log.error("reconstruction of %s produced %d non-finite values; replaced with 0", name, bad)
        warnings.append(f"reconstruction of {name} produced {bad} non-finite values, replaced with 0")
        image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
    return image


# ---------------------------------------------------------------------------------------------------------------
# The engine: models, readiness, warm-up
# ---------------------------------------------------------------------------------------------------------------


class Engine:
    """What the routers need: which methods exist, whether we are ready, and the gate to run work through."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        configure_exr_threads(settings.exr_threads)
        from gradsep.model.allocator import configure_malloc

        arenas = configure_malloc(settings.malloc_arenas)  # before the worker threads exist: model/allocator.py
        log.info("malloc arenas: %s", arenas if arenas is not None else "left as glibc / MALLOC_ARENA_MAX set them")
        self.limits = ReadLimits(max_pixels=settings.max_pixels, max_values=settings.max_values)
        self.models = table.LoadedModels(**{name: None for name in table.MODEL_SETS})  # nothing until loaded
        self.state: Literal["loading", "ready", "failed"] = "loading"
        self.failure: str | None = None
        self.gate: InferenceGate | None = None

    @property
    def network(self) -> Any:
        """The ``network`` method's loaded models (None: not loaded)."""
        return self.models.get("network")

    @property
    def fused(self) -> Any:
        """The ``fused`` method's loaded models (None: not loaded)."""
        return self.models.get("fused")

    @property
    def oidn(self) -> bool:
        return self.models.has("oidn")

    @property
    def methods(self) -> tuple[str, ...]:
        """What this replica serves: the methods of the table (model/methods.py) whose model sets are loaded, in
        the table's order."""
        return self.models.serves()

    @property
    def default_method(self) -> str:
        """The default for a gradient-domain frame with features (the first served of the default preference)."""
        return table.default_method(self.methods, gradients=True) or "l1"

    @property
    def default_method_plain(self) -> str | None:
        """The default for a plain frame (no gradients): the first served method that needs none, or None."""
        return table.default_method(self.methods, gradients=False)

    def describe_methods(self) -> list[dict[str, Any]]:
        """The table of methods as /v1/models shows it: each method's needs and whether this replica serves it."""
        served = set(self.methods)
        return [{**m.summary(), "served": m.name in served} for m in table.methods()]

    def start(self, task_group: TaskGroup) -> None:
        """Create the gate and load + warm up in the background, so /healthz answers during a long load."""
        s = self.settings
        self.gate = InferenceGate(s.concurrency, s.queue_size, task_group)
        task_group.start_soon(self._load_and_warm_up)

    async def _load_and_warm_up(self) -> None:
        try:
            self.models = await anyio.to_thread.run_sync(load_models, self.settings.models_dir)
            if self.settings.warm_up:
                started = time.perf_counter()
                await anyio.to_thread.run_sync(self._warm_up)
                log.info("warm-up of %s done in %.2f s", ", ".join(self.methods), time.perf_counter() - started)
            self.state = "ready"
            log.info("ready; methods %s (default %s)%s", ", ".join(self.methods), self.default_method,
                     self._provider_note())
        except Exception as exc:  # a broken model folder: stay alive (liveness) but never report ready
            self.state, self.failure = "failed", f"{type(exc).__name__}: {exc}"
            log.exception("model loading or warm-up failed; /readyz will answer 503")

    def _warm_up(self) -> None:
        """One tiny reconstruction per method: first-call costs (imports, FFT plans, ORT sessions) paid now."""
        if self.network is not None and hasattr(self.network, "warm_up"):
            self.network.warm_up()
        frame = warm_up_frame()
        for method in self.methods:
            reconstruct(frame, method, self.settings.default_alpha, self.models)
        if "l1" in self.methods:  # below FLOAT32_MIN_ALPHA IRLS runs in float64: compile those kernels now too
            reconstruct(frame, "l1", 1e-3, self.models)

    def _provider_note(self) -> str:
        """`` inference on openvino/bf16`` (one entry per distinct provider/precision of the loaded models)."""
        kinds = sorted({f"{m.get('provider', '?')}/{m.get('precision', '?')}" for m in self.describe_models()})
        return f"; network inference on {', '.join(kinds)}" if kinds else ""

    def describe_oidn(self) -> dict[str, Any] | None:
        """The ``oidn`` method's denoiser: its setting (None where pyoidn is not installed)."""
        if not self.oidn:
            return None
        from gradsep.model.oidn import method_setting, shared_denoiser

        return shared_denoiser(method_setting()).describe()

    def describe_models(self) -> list[dict[str, Any]]:
        """Every loaded model, as its model set describes it (provider and precision as the session runs it),
        with ``method``: the model set it belongs to."""
        out = []
        for name, models in self.models.loaded().items():
            describe = getattr(models, "describe", None)
            if callable(describe):
                out += [{**dict(m), "method": name} for m in describe()]
        return out


def load_models(models_dir: Path) -> table.LoadedModels:
    """Every model set of the table (model.methods.MODEL_SETS) from ``models_dir``, by its own loader: a set that
    is absent (no folder, no package) is None and its methods are not served; models that fail to load raise,
    because serving silently without the models an operator shipped would be worse than not becoming ready."""
    models = table.LoadedModels.load(models_dir)
    for name, model_set in table.MODEL_SETS.items():
        if not models.has(name):
            served = [m.name for m in table.methods() if name in m.models]
            log.info("%s not available (%s); not served: %s", model_set.description,
                     models_dir / model_set.folder if model_set.folder else "not installed", ", ".join(served))
    return models


def warm_up_frame(size: int = 16) -> Any:
    """A small smooth direct + indirect frame with exact gradients (and features, which the network reads)."""
    from gradsep.model.frame import Features, Frame

    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    layers = {}
    for name, scale in (("direct", 1.0), ("indirect", 0.3)):
        base = np.stack([scale * (0.2 + x), scale * (0.3 + y), scale * (0.5 + 0.1 * x * y)], axis=-1)
        dx, dy = forward_differences(base)
        layers[name] = Layer(base.astype(np.float32), dx.astype(np.float32), dy.astype(np.float32))
    normal = np.zeros((size, size, 3), np.float32)
    normal[..., 2] = 1.0
    features = Features(np.full((size, size, 3), 0.5, np.float32), normal, np.ones((size, size), np.float32))
    return Frame(layers, features)


def server_timing(timings: Mapping[str, float]) -> str:
    """``Server-Timing`` header value: ``decode;dur=1.2, direct;dur=30.5, ...`` in milliseconds."""
    parts = []
    for name, seconds in timings.items():
        token = "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "step"
        parts.append(f"{token};dur={seconds * 1000:.1f}")
    return ", ".join(parts)

