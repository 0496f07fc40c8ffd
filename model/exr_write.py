"""Writing frames and answers: always whole files, never half-written.

:func:`encode_answer` is the one definition of what an answer carries (the reconstruction, the input's alpha and
header attributes, the answer's own ``gradsep.*`` keys: model/header_keys.py); :func:`write_bytes_atomic` writes
any file by a rename, so a killed run never leaves a half-written one. A half-float file saturates at ±65504
instead of overflowing to Inf; a layer's variance and the motion vectors stay float32 (model/frame.py
``is_float32_channel``).
"""

from __future__ import annotations

import io
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from gradsep.model.channels import ALPHA
from gradsep.model.exr_read import IMAGE_ATTRIBUTES
from gradsep.model.frame import Frame, is_float32_channel
from gradsep.model.header_keys import (
    ANSWER_KEYS,
    PLAN_METHOD_KEY,
    PREDICTED_RELMSE_KEY,
    PREDICTION_KEYS,
    WARNINGS_ATTRIBUTE,
    WARNINGS_LIMIT,
)

#: Compressions an answer may reuse from its request: the lossless ones. A lossy or unknown request compression
#: gets ZIP (a reconstruction must never lose precision on the way out; what each costs to read and encode:
#: `benchmarks/bench_service.py --io`).
LOSSLESS_COMPRESSIONS = tuple(c for c in ("NO_COMPRESSION", "RLE_COMPRESSION", "ZIPS_COMPRESSION",
                                          "ZIP_COMPRESSION", "PIZ_COMPRESSION", "ZSTD_COMPRESSION")
                              if hasattr(OpenEXR, c))
DEFAULT_COMPRESSION = "ZIP_COMPRESSION"


def output_compression(requested: str | None) -> str:
    """The compression to write: ``requested`` when it is lossless and known, else ZIP."""
    return requested if requested in LOSSLESS_COMPRESSIONS else DEFAULT_COMPRESSION


HALF_MAX = 65504.0  # the largest finite half float


def half_saturation(channels: Mapping[str, np.ndarray]) -> int:
    """How many values a half-float answer saturates at ±65504 (finite values beyond half's range)."""
    return sum(int(np.count_nonzero(np.abs(np.asarray(v, dtype=np.float32)) > HALF_MAX)) for v in channels.values())


def _exr_file(channels: Mapping[str, np.ndarray], half: bool, metadata: Mapping[str, str] | None,
              compression: str | None = None, image_attributes: Mapping[str, Any] | None = None) -> OpenEXR.File:
    dtype = np.float16 if half else np.float32
    shapes = {np.shape(v) for v in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"channels must be 2-D arrays of one shape, got {sorted(shapes)}")
    pixels = {}
    for name, value in channels.items():
        arr = np.asarray(value)
        if is_float32_channel(name):  # float32 even in a half file: variance and motion (model/frame.py)
            pixels[name] = np.ascontiguousarray(arr, dtype=np.float32)
            continue
        if half:  # float32 -> half overflows to Inf above 65504: saturate instead, outputs stay finite
            arr = np.clip(arr, -HALF_MAX, HALF_MAX)
        pixels[name] = np.ascontiguousarray(arr, dtype=dtype)
    header: dict[str, Any] = {"compression": getattr(OpenEXR, output_compression(compression)),
                              "type": OpenEXR.scanlineimage}
    height, width = next(iter(shapes))
    for key, value in (image_attributes or {}).items():
        if key == "dataWindow":  # the pixels decide the window's size; the input decides where it sits
            lo = np.asarray(value[0], dtype=np.int32)
            value = (lo, lo + np.array([width - 1, height - 1], dtype=np.int32))
        header[key] = value
    header.update({k: str(v) for k, v in (metadata or {}).items()})
    return OpenEXR.File(header, pixels)  # OpenEXR mutates both dicts: they are our own copies


def configure_exr_threads(count: int = -1) -> int:
    """Set OpenEXR's process-wide thread pool (-1: one thread per core, 0: single-threaded) and return its size.

    OpenEXR's Python binding defaults to no pool, so a ZIP-compressed frame would be encoded and decoded on one
    core; with a pool its line blocks are (de)compressed in parallel. The command line sets it once for every
    command (gradsep/cli.py), the service from its settings. Pixels are identical.
    """
    threads = (os.cpu_count() or 1) if count < 0 else count
    OpenEXR.set_global_thread_count(threads)
    return threads


def encode_exr(channels: Mapping[str, np.ndarray], *, half: bool = False,
               metadata: Mapping[str, str] | None = None, compression: str | None = None,
               image_attributes: Mapping[str, Any] | None = None) -> bytes:
    """Encode channels as the bytes of a single-part scanline EXR: ZIP compression, or ``compression`` (an
    OpenEXR name such as ``"NO_COMPRESSION"``, e.g. the request's) when it is lossless. ``image_attributes``:
    typed header attributes (IMAGE_ATTRIBUTES, e.g. a Frame's) written as well."""
    buffer = io.BytesIO()
    _exr_file(channels, half, metadata, compression, image_attributes).write(buffer)
    return buffer.getvalue()




def encode_answer(frame: Frame, channels: Mapping[str, np.ndarray], *, half: bool = False,
                  metadata: Mapping[str, str] | None = None, warnings: list[str] | None = None,
                  compression: str | None = None) -> bytes:
    """The EXR of a reconstruction of ``frame``: the one definition the CLI and the service write answers with.

    ``channels`` (R G B, maybe layers) plus the frame's alpha as ``A``; the header carries the frame's image
    attributes (data window, display window, pixel aspect...) and string attributes, then ``metadata`` (the
    answer's own ``gradsep.*``), then ``gradsep.warnings``. A half answer that saturates values above 65504 adds a
    warning naming the count to ``warnings`` (the caller's list, so its header, stderr or HTTP header says so too).
    """
    warnings = warnings if warnings is not None else []
    out = dict(channels)
    if frame.alpha is not None:
        out[ALPHA] = frame.alpha
    if half:
        saturated = half_saturation(out)
        if saturated:
            warnings.append(f"{saturated} value(s) above the half-float range saturated at {HALF_MAX:g} "
                            "(ask for format=float / drop --half to keep them)")
    carried = {k: v for k, v in frame.metadata.items() if k not in ANSWER_KEYS and k not in IMAGE_ATTRIBUTES}
    own = dict(metadata or {})
    if PREDICTED_RELMSE_KEY in carried and own.get("gradsep.method") != carried.get(PLAN_METHOD_KEY):
        carried = {k: v for k, v in carried.items() if k not in PREDICTION_KEYS}
    if frame.layout != "gradsep":
        own["gradsep.channels"] = frame.layout

    def encode(carried: Mapping[str, str], image_attributes: Mapping[str, Any]) -> bytes:
        header = {**carried, **own}
        if warnings:
            header[WARNINGS_ATTRIBUTE] = "; ".join(warnings)[:WARNINGS_LIMIT]
        return encode_exr(out, half=half, metadata=header, compression=compression,
                          image_attributes=image_attributes)

    try:
        return encode(carried, frame.image_attributes)
    except (RuntimeError, TypeError, ValueError) as exc:  # an input attribute OpenEXR reads but will not write
        warnings.append(f"the input's header attributes could not be written on the answer and were left out "
                        f"({type(exc).__name__}: {str(exc)[:200]})")
        return encode({}, {})


def _default_file_mode() -> int:
    """0666 minus the process umask: what ``open()`` would create (read from /proc without changing the umask)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o644


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path`` and rename it into place (atomic on POSIX).

    The file gets the permissions ``open()`` would give it (mkstemp's 0600 would hide frames from the other users
    of a shared render-farm folder).
    """
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent or ".")
    try:
        os.fchmod(fd, _default_file_mode())
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_exr(path: str | os.PathLike[str], channels: Mapping[str, np.ndarray], *, half: bool = False,
              metadata: Mapping[str, str] | None = None, image_attributes: Mapping[str, Any] | None = None) -> None:
    """Write channels to ``path`` atomically: a killed run never leaves a half-written file."""
    write_bytes_atomic(path, encode_exr(channels, half=half, metadata=metadata, image_attributes=image_attributes))


def write_frame(path: str | os.PathLike[str], frame: Frame, *, half: bool = False) -> None:
    """Write a frame per the contract (its alpha, attributes and image attributes too), atomically."""
    write_exr(path, frame.to_channels(), half=half, metadata=frame.metadata, image_attributes=frame.image_attributes)
