"""One request's work, in the calling worker thread: decode the frame, reconstruct each layer, encode the answer."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from gradsep.model import methods as table
from gradsep.model.exr_read import ReadLimits, Source, read_frame
from gradsep.model.exr_write import encode_answer
from gradsep.model.frame import rgb_channels
from gradsep.model.header_keys import OIDN_SETTING_KEY

log = logging.getLogger("gradsep.service")


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
    return Outcome(body, str(result.method), timings, warnings)


def _finite(image: np.ndarray, name: str, warnings: list[str]) -> np.ndarray:
    """Outputs are always finite: a solver that produced NaN/Inf is logged and the values are zeroed."""
    bad = int(np.count_nonzero(~np.isfinite(image)))
    if bad:
        log.error("reconstruction of %s produced %d non-finite values; replaced with 0", name, bad)
        warnings.append(f"reconstruction of {name} produced {bad} non-finite values, replaced with 0")
        image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
    return image


def server_timing(timings: Mapping[str, float]) -> str:
    """``Server-Timing`` header value: ``decode;dur=1.2, direct;dur=30.5, ...`` in milliseconds."""
    parts = []
    for name, seconds in timings.items():
        token = "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "step"
        parts.append(f"{token};dur={seconds * 1000:.1f}")
    return ", ".join(parts)

