"""The engine: the model sets this replica serves, readiness, warm-up, and the gate requests run through."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Literal

import anyio
import numpy as np
from anyio.abc import TaskGroup

from gradsep.model import methods as table
from gradsep.model.exr_read import ReadLimits
from gradsep.model.exr_write import configure_exr_threads
from gradsep.model.frame import Layer, forward_differences
from gradsep.service import pipeline
from gradsep.service.bodies import BytePool
from gradsep.service.gate import InferenceGate
from gradsep.service.settings import Settings

log = logging.getLogger("gradsep.service")


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
        self.body_pool = BytePool(settings.body_memory_bytes)  # request bodies in memory, across all uploads

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

    def retry_after(self) -> int:
        """Seconds a refused client should wait: the gate's estimate once it exists."""
        return self.gate.retry_after() if self.gate is not None else 1

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
            pipeline.reconstruct(frame, method, self.settings.default_alpha, self.models)
        if "l1" in self.methods:  # below FLOAT32_MIN_ALPHA IRLS runs in float64: compile those kernels now too
            pipeline.reconstruct(frame, "l1", 1e-3, self.models)
        # a window whose motion is on the pixel grid but not integral: the temporal warp's bilinear kernel compiles
        # now, not in the first window request (the warp does not depend on the method; the cheapest one runs)
        from gradsep.model.temporal import reconstruct_window

        reconstruct_window([warm_up_frame(moving=True) for _ in range(3)], 1, "l2", self.settings.default_alpha,
                           self.models)

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


def warm_up_frame(size: int = 16, moving: bool = False) -> Any:
    """A small smooth direct + indirect frame with exact gradients (and features, which the network reads);
    ``moving``: with motion vectors all valid, a pixel to the right per frame plus half the temporal grid tolerance
    (model.temporal.GRID_TOLERANCE): on the grid, so the neighbours are warped, but not integral, so bilinearly."""
    from gradsep.model.frame import Features, Frame, Motion
    from gradsep.model.temporal import GRID_TOLERANCE

    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    layers = {}
    for name, scale in (("direct", 1.0), ("indirect", 0.3)):
        base = np.stack([scale * (0.2 + x), scale * (0.3 + y), scale * (0.5 + 0.1 * x * y)], axis=-1)
        dx, dy = forward_differences(base)
        layers[name] = Layer(base.astype(np.float32), dx.astype(np.float32), dy.astype(np.float32))
    normal = np.zeros((size, size, 3), np.float32)
    normal[..., 2] = 1.0
    features = Features(np.full((size, size, 3), 0.5, np.float32), normal, np.ones((size, size), np.float32))
    out = Frame(layers, features)
    if moving:
        step = np.zeros((size, size, 2), np.float32)
        step[..., 0] = 1.0 + GRID_TOLERANCE / 2
        valid = np.ones((size, size), np.float32)
        out.motion = Motion(-step, step, valid, valid)
    return out

