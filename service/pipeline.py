"""One request's work, in the calling worker thread: decode the frame, reconstruct each layer, encode the answer."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from gradsep.model import methods as table
from gradsep.model.errors import FrameError
from gradsep.model.exr_read import ReadLimits, Source, read_frame
from gradsep.model.exr_write import encode_answer
from gradsep.model.frame import rgb_channels
from gradsep.model.header_keys import OIDN_SETTING_KEY
from gradsep.service.errors import ServiceError
from gradsep.service.window import OFFSETS_KEY, Window, read_window

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
    neighbours: list[int] | None = None  # a window request's neighbours that contributed (offsets from frame t)


def reconstruct(frame: Any, method: str | None, alpha: float, models: table.LoadedModels | None = None) -> Any:
    """Indirection to ``model.reconstruct.reconstruct`` (imported on first use; tests may patch this name)."""
    from gradsep.model.reconstruct import reconstruct as model_reconstruct

    return model_reconstruct(frame, method, alpha, models)


def run_pipeline(source: Source, params: ReconstructParams, limits: ReadLimits, nonfinite: str,
                 models: table.LoadedModels | None = None) -> Outcome:
    """Decode, reconstruct and encode in the calling (worker) thread; frame problems raise FrameError."""
    timings: dict[str, float] = {}
    frame = _decode(source, params, limits, nonfinite, timings)
    result = reconstruct(frame, params.method, params.alpha, models)
    return _answer(frame, result, params, timings, [*frame.warnings])


def run_window_pipeline(window: Window, params: ReconstructParams, limits: ReadLimits, nonfinite: str,
                        models: table.LoadedModels | None = None) -> Outcome:
    """Frame t of a window request (service/window.py) reconstructed from its neighbours by
    :func:`model.temporal.reconstruct_window`; the answer names the neighbours used, and warns of the missing and
    the rejected ones. Errors of a neighbour name its part."""
    from gradsep.model.temporal import reconstruct_window

    timings: dict[str, float] = {}
    frame = _decode(window.frame.file, params, limits, nonfinite, timings)
    t0 = time.perf_counter()
    frames, centre = read_window(window, frame, limits, nonfinite, params.channels)
    timings["decode"] += time.perf_counter() - t0
    try:
        result = reconstruct_window(frames, centre, params.method, params.alpha, models)
    except ValueError as exc:
        if isinstance(exc, FrameError):
            raise
        raise ServiceError(422, "window_mismatch", f"the window's frames do not form one shot: {exc}") from None
    warnings = [*frame.warnings, *window_warnings(window, frame, result)]
    result.warnings = [w for w in result.warnings if not str(w).startswith("neighbour(s) ")]
    outcome = _answer(frame, result, params, timings, warnings, {OFFSETS_KEY: _offsets(result.neighbours)})
    outcome.neighbours = list(result.neighbours)
    return outcome


def window_warnings(window: Window, frame: Any, result: Any) -> list[str]:
    """What the answer says about the neighbours: missing (an empty part), or sent but never accepted."""
    warnings = []
    if window.missing:
        warnings.append(f"neighbour(s) {_offsets(window.missing)} missing: reconstructed from the frames it has")
    if getattr(frame, "motion", None) is None:
        warnings.append("the frame has no motion vectors: reconstructed on its own (the per-frame method)")
        return warnings
    rejected = [p.offset for p in window.parts if p.upload is not None and p.offset not in result.neighbours]
    if rejected:
        warnings.append(f"neighbour(s) {_offsets(rejected)} rejected: no pixel of theirs reached or agreed with "
                        "the frame")
    return warnings


def _offsets(offsets: list[int]) -> str:
    return ",".join(f"{o:+d}" for o in sorted(offsets))


def _decode(source: Source, params: ReconstructParams, limits: ReadLimits, nonfinite: str,
            timings: dict[str, float]) -> Any:
    t0 = time.perf_counter()
    if hasattr(source, "seek"):
        source.seek(0)  # the header check left the stream somewhere past the header
    frame = read_frame(source, limits=limits, nonfinite=nonfinite,  # type: ignore[arg-type]
                       layout=params.channels)
    timings["decode"] = time.perf_counter() - t0
    return frame


def _answer(frame: Any, result: Any, params: ReconstructParams, timings: dict[str, float], warnings: list[str],
            extra: dict[str, str] | None = None) -> Outcome:
    """Encode ``result`` (with the frame's header) as the answer; ``warnings`` gets the result's own."""
    for layer, seconds in dict(getattr(result, "timings", {}) or {}).items():
        timings[str(layer)] = float(seconds)
    warnings.extend(str(w) for w in getattr(result, "warnings", None) or ())
    image = _finite(np.asarray(result.image, dtype=np.float32), "sum", warnings)
    channels = dict(rgb_channels("", image))
    if params.layers == "all":
        for name, layer_image in dict(result.layers).items():
            channels.update(rgb_channels(name, _finite(np.asarray(layer_image, dtype=np.float32), name, warnings)))
    t1 = time.perf_counter()
    metadata = {"gradsep.method": str(result.method), "gradsep.alpha": f"{params.alpha:g}",
                "gradsep.request_id": params.request_id, "gradsep.layers": ",".join(frame.layers), **(extra or {})}
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

