"""``POST /v1/reconstruct``: an EXR frame in, the reconstructed EXR out.

The body is read by hand (not through FastAPI body parameters) because one operation accepts two encodings --
multipart with a ``frame`` file field, or the raw EXR -- and because every step must fail with the service's
own status codes in a fixed order, cheapest first:

  auth (middleware) -> query parameters 422 -> not ready 503 -> unknown method 422 -> content type 415
  -> queue already full 503 (body drained, not buffered) -> body over the byte limit 413 (streaming count)
  -> header: not an EXR 400, too large 413 (before any pixel is decoded); a window's neighbours' headers: the
  same, and another size, layout or shot 422 -> queue 503 / timeout 504 -> decode 400/422 -> reconstruction
  (of a window: model.temporal.reconstruct_window, service/window.py) -> encode.
"""

# No ``from __future__ import annotations``: build_router's endpoint is annotated with a type made when the app is
# created (the methods enum), which FastAPI must see as an object, not as a string naming a local.
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Annotated, Any, Literal

import anyio
from fastapi import APIRouter, Depends, Query, Request
from starlette.datastructures import FormData, UploadFile
from starlette.exceptions import HTTPException
from starlette.formparsers import MultiPartException, MultiPartParser
from starlette.responses import Response

from gradsep.model import methods as table
from gradsep.model.channels import DEFAULT_LAYOUT, choices_text, layout_pattern
from gradsep.model.errors import NotExrError
from gradsep.model.exr_read import HeaderInfo, read_header
from gradsep.model.poisson import MIN_ALPHA
from gradsep.service.bodies import Upload, read_body
from gradsep.service.dependencies import get_engine, get_metrics
from gradsep.service.engine import Engine
from gradsep.service.errors import ErrorResponse, ServiceError
from gradsep.service.metrics import ServiceMetrics
from gradsep.service.middleware import request_id_of
from gradsep.service.pipeline import Outcome, ReconstructParams, run_pipeline, run_window_pipeline, server_timing
from gradsep.service.window import MAX_NEIGHBOURS, SIDES, Window, check_neighbours, window_parts

RAW_TYPES = ("image/x-exr", "application/octet-stream")
#: Largest non-file field of a multipart body held in memory (the frame itself is a file part, which Starlette
#: spools to disk past its small in-memory head); a bigger field is a 400.
MULTIPART_FIELD_BYTES = 64 << 10
#: Bytes of a multipart file part held in memory before it moves to a temporary file: the first (the frame) as
#: Starlette's default; each further one (a window's neighbours) less, so a window request holds little more
#: memory than a single frame's.
FRAME_HEAD_BYTES, NEIGHBOUR_HEAD_BYTES = MultiPartParser.spool_max_size, 64 << 10
EXR_MEDIA_TYPE = "image/x-exr"
_BINARY = {"type": "string", "format": "binary"}

REQUEST_BODY = {
    "required": True,
    "description": "an OpenEXR frame per docs/frame-format.md: multipart field `frame`, or the raw file; a "
                   "temporal window adds its neighbours as repeatable `previous` / `next` parts, nearest first",
    "content": {
        "multipart/form-data": {"schema": {"type": "object", "required": ["frame"], "properties": {
            "frame": {**_BINARY, "description": "the .exr (frame t)"},
            **{side: {"type": "array", "maxItems": MAX_NEIGHBOURS, "items": _BINARY,
                      "description": f"frames t{sign:+d}, t{2 * sign:+d}, ... (an empty part: that frame is "
                                     "missing)"} for side, sign in SIDES.items()}}}},
        "image/x-exr": {"schema": _BINARY},
        "application/octet-stream": {"schema": _BINARY},
    },
}


def _err(description: str, headers: dict[str, Any] | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"model": ErrorResponse, "description": description}
    if headers:
        out["headers"] = headers
    return out


RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"description": "the reconstruction as OpenEXR: R G B (plus A when the frame has alpha, plus direct.R ... "
                         "with layers=all), with the frame's data window, display window, pixel aspect ratio and "
                         "string attributes",
          "content": {EXR_MEDIA_TYPE: {"schema": _BINARY}},
          "headers": {"X-Request-ID": {"schema": {"type": "string"}, "description": "echoed or generated"},
                      "Server-Timing": {"schema": {"type": "string"},
                                        "description": "queue, decode, per-layer and encode durations (ms)"},
                      "X-Reconstruction-Method": {"schema": {"type": "string"}},
                      "X-Gradsep-Neighbours": {"schema": {"type": "string"},
                                               "description": "a window request's neighbours used, as offsets from "
                                                              "frame t (-1,+1), or none"},
                      "X-Gradsep-Warnings": {"schema": {"type": "string"},
                                             "description": "what was replaced, clamped or saturated, with counts "
                                                            "(also in the EXR's gradsep.warnings)"}}},
    400: _err("not an OpenEXR file, corrupt or truncated; unsupported EXR kind; malformed multipart"),
    401: _err("bearer token missing or invalid (only when the service has a token)"),
    413: _err("body over the byte limit (a multipart body: details.frames_fit), or image over the pixel/value "
              "limit (decided from the header)"),
    408: _err("the request body stalled longer than the service's body timeout"),
    415: _err("content type is not multipart/form-data, image/x-exr or application/octet-stream"),
    422: _err("invalid parameter; missing or inconsistent channels; no illumination layer; ambiguous channel "
              "layout (details.candidates); NaN/Inf values; a neighbour of another size, layout or shot"),
    503: _err("not ready yet, or the inference queue is full; retry after Retry-After seconds",
              {"Retry-After": {"schema": {"type": "integer"}}}),
    504: _err("the inference did not finish within the service's timeout"),
}


@dataclass(frozen=True)
class ReconstructQuery:
    """The query parameters of ``POST /v1/reconstruct``, read by the endpoint's one query dependency."""

    method: str | None  # None: model.reconstruct picks the best method that serves the frame (model.policy)
    alpha: float | None
    output_format: Literal["half", "float"]
    layers: Literal["sum", "all"]
    channels: str


def query_dependency() -> Callable[..., ReconstructQuery]:
    """The dependency that reads the query parameters; its ``method`` enum (in the OpenAPI schema and its
    validation) is the table of methods as it stands when the router is built (model/methods.py)."""
    method_names = Literal[table.names()]  # type: ignore[valid-type]
    alpha_methods = "/".join(m.name for m in table.methods() if m.alpha)

    def read_query(
        method: Annotated[method_names | None, Query(  # type: ignore[valid-type]
            description="reconstruction method; default: the first of " + " > ".join(table.default_preference())
                        + " that this replica serves for the frame (a plain frame without gradients gets the "
                        "first that needs none). " + "; ".join(f"{m.name}: {m.description}"
                                                              for m in table.methods()))] = None,
        alpha: Annotated[float | None, Query(
            ge=MIN_ALPHA, le=1000, allow_inf_nan=False,
            description=f"screened Poisson data weight (methods {alpha_methods}), in [{MIN_ALPHA:g}, 1000]")] = None,
        output_format: Annotated[Literal["half", "float"], Query(
            alias="format", description="pixel type of the returned EXR")] = "float",
        layers: Annotated[Literal["sum", "all"], Query(
            description="sum: R G B only; all: also each reconstructed layer (direct.R, ...)")] = "sum",
        channels: Annotated[str, Query(
            pattern=layout_pattern(), description=f"channel layout of the frame: {choices_text()} (auto: the one "
            "layout the file matches; ambiguous files get 422 naming the candidates)")] = DEFAULT_LAYOUT,
    ) -> ReconstructQuery:
        return ReconstructQuery(method, alpha, output_format, layers, channels)

    return read_query


def build_router() -> APIRouter:
    """The router of ``POST /v1/reconstruct``, built when an app is created (its query dependency with it)."""
    router = APIRouter(tags=["reconstruction"])
    read_query = query_dependency()

    @router.post("/v1/reconstruct", response_class=Response, responses=RESPONSES,
                 openapi_extra={"requestBody": REQUEST_BODY},
                 summary="Reconstruct a frame's illumination layers and return their sum")
    async def reconstruct_frame(
        request: Request,
        engine: Annotated[Engine, Depends(get_engine)],
        metrics: Annotated[ServiceMetrics, Depends(get_metrics)],
        query: Annotated[ReconstructQuery, Depends(read_query)],
    ) -> Response:
        return await _reconstruct(request, engine, metrics, query)

    return router


async def _reconstruct(request: Request, engine: Engine, metrics: ServiceMetrics,
                       query: ReconstructQuery) -> Response:
    t_start = time.perf_counter()
    gate = _ready_gate(engine)
    _check_method(engine, query.method)
    media = _media_type(request)
    if gate.full:  # shed load before buffering anything; drain so the client reads our answer cleanly
        async for _ in request.stream():
            pass
        raise gate.queue_full_error()
    upload = await _read_body(request, media, engine)
    read_seconds = time.perf_counter() - t_start
    outcome, queued = await _run(upload, engine, query, request_id_of(request.scope))
    metrics.inference.labels(method=outcome.method).observe(sum(outcome.timings.values()))
    timings = {"read": read_seconds, "queue": queued, **outcome.timings, "total": time.perf_counter() - t_start}
    headers = {"Server-Timing": server_timing(timings), "X-Reconstruction-Method": outcome.method,
               "Content-Disposition": 'attachment; filename="reconstruction.exr"'}
    if outcome.neighbours is not None:
        headers["X-Gradsep-Neighbours"] = ",".join(f"{o:+d}" for o in outcome.neighbours) or "none"
    if outcome.warnings:
        headers["X-Gradsep-Warnings"] = _header_safe("; ".join(outcome.warnings))
    return Response(outcome.body, media_type=EXR_MEDIA_TYPE, headers=headers)


async def _run(upload: Window, engine: Engine, query: ReconstructQuery, request_id: str) -> tuple[Outcome, float]:
    """Header check, then the pipeline through the gate. The body is closed when the work is done: by the job in
    its thread once it has started (so a job that outlives its request, timed out or disconnected, reads its body
    to the end and frees it when it ends), or here when no job started."""
    started = threading.Event()
    try:
        header = await anyio.to_thread.run_sync(_check_header, upload.frame, engine)
        if upload.parts:
            await anyio.to_thread.run_sync(check_neighbours, upload, header, engine.limits)
        alpha = query.alpha if query.alpha is not None else engine.settings.default_alpha
        params = ReconstructParams(query.method, alpha, query.output_format == "half", query.layers, request_id,
                                   header.compression, query.channels)
        job = partial(_job, upload, params, engine, started)
        return await engine.gate.run(job, engine.settings.inference_timeout)  # type: ignore[union-attr]
    finally:
        if not started.is_set():
            upload.close()


def _job(upload: Window, params: ReconstructParams, engine: Engine, started: threading.Event) -> Outcome:
    """One request's pipeline in a worker thread; its body closed when it ends."""
    started.set()
    try:
        if upload.parts:
            return run_window_pipeline(upload, params, engine.limits, engine.settings.nonfinite, engine.models)
        return run_pipeline(upload.frame.file, params, engine.limits, engine.settings.nonfinite, engine.models)
    finally:
        upload.close()


def _check_method(engine: Engine, method: str | None) -> None:
    if method is not None and method not in engine.methods:
        needs = ", ".join(table.MODEL_SETS[n].description for n in engine.models.missing(table.get(method)))
        raise ServiceError(422, "method_unavailable", f"method {method!r} is not available on this replica (it "
                           f"needs {needs or 'models this replica has not loaded'}); available: "
                           f"{', '.join(engine.methods)}", {"available": list(engine.methods)})


def _header_safe(text: str, limit: int = 1000) -> str:
    """Printable ASCII only: warnings quote channel names from the (untrusted) file, e.g. with CR/LF in them."""
    return "".join(c if " " <= c <= "~" else "?" for c in text[:limit])


def _ready_gate(engine: Engine) -> Any:
    if engine.state != "ready" or engine.gate is None:
        code = "models_failed" if engine.state == "failed" else "not_ready"
        raise ServiceError(503, code, f"service is not ready ({engine.state}); see /readyz", None,
                           {"Retry-After": "1" if engine.state == "loading" else "60"})
    return engine.gate


def _media_type(request: Request) -> str:
    """The request's media type; 415 unless multipart or raw EXR. No Content-Type means raw bytes (RFC 9110)."""
    header = request.headers.get("content-type")
    media = (header or "application/octet-stream").split(";", 1)[0].strip().lower()
    if media != "multipart/form-data" and media not in RAW_TYPES:
        raise ServiceError(
            415, "unsupported_media_type",
            f"unsupported content type {media[:100]!r}: send multipart/form-data with a file field 'frame' "
            "(curl -F frame=@f.exr) or the raw file as image/x-exr or application/octet-stream "
            "(curl -H 'Content-Type: image/x-exr' --data-binary @f.exr)",
            {"accepted": ["multipart/form-data", *RAW_TYPES]})
    return media


async def _read_body(request: Request, media: str, engine: Engine) -> Window:
    """The EXR: a raw body spooled within the service's body memory pool (service/bodies.py), or the file field
    of a multipart body (Starlette spools it to disk past its small in-memory part) with the neighbours of a
    window request (service/window.py)."""
    if media != "multipart/form-data":
        declared = request.headers.get("content-length")
        body = await read_body(request.stream(), engine.body_pool, engine.settings.spool_dir,
                               int(declared) if declared is not None else None)
        return Window(Upload(body.file, body.size, body.close))
    form = await _parse_form(request)
    try:
        frames = form.getlist("frame")
        if len(frames) != 1 or not isinstance(frames[0], UploadFile):
            raise ServiceError(400, "missing_frame", "multipart body has more than one field 'frame'" if frames[1:]
                               else "multipart body has no file field 'frame' (curl -F frame=@f.exr)",
                               {"fields": list(form.keys())[:16]})
        parts = window_parts({side: form.getlist(side) for side in SIDES}, _file_upload)
    except ServiceError:
        await form.close()
        raise
    return Window(_file_upload(frames[0]), parts)  # type: ignore[arg-type]


class _WindowParser(MultiPartParser):
    """Starlette's multipart parser, its file parts after the first kept in memory up to NEIGHBOUR_HEAD_BYTES."""

    @property  # type: ignore[override]
    def spool_max_size(self) -> int:  # read as a file part begins, its count (_current_files) just raised
        return FRAME_HEAD_BYTES if getattr(self, "_current_files", 0) <= 1 else NEIGHBOUR_HEAD_BYTES


async def _parse_form(request: Request) -> FormData:
    """The multipart body's fields (as ``request.form`` parses them, with the window's smaller heads); 400 for a
    malformed body."""
    parser = _WindowParser(request.headers, request.stream(), max_files=1 + 2 * MAX_NEIGHBOURS, max_fields=16,
                           max_part_size=MULTIPART_FIELD_BYTES)
    try:
        return await parser.parse()
    except MultiPartException as exc:
        raise HTTPException(status_code=400, detail=exc.message) from None


def _file_upload(value: Any) -> Upload | None:
    """A multipart file part as an Upload; None for a text field."""
    if not isinstance(value, UploadFile):
        return None
    return Upload(value.file, value.size or 0, value.file.close)


def _check_header(upload: Upload, engine: Engine) -> HeaderInfo:
    """Header only: 400 for non-EXR, 413 for a declared size over the budget, before any pixel is decoded."""
    if upload.size == 0:
        raise NotExrError("empty request body; expected an OpenEXR file")
    upload.file.seek(0)
    return read_header(upload.file, engine.limits)
