"""The C allocator of a reconstructing process: glibc's malloc limited to one arena that keeps its memory.

A frame is reconstructed in short-lived worker threads (model/reconstruct.py runs a frame's layers concurrently),
and every solve allocates frame-sized numpy temporaries. glibc gives threads their own malloc *arenas*; a new
worker thread per frame lands in an arena whose freed memory was handed back to the kernel. Its temporaries are
then fresh pages every frame.
- That costs tens of thousands of page faults and a visible share of kernel time per frame, once ONNX Runtime /
  OpenVINO sessions are loaded (the service always loads them), as the process's other threads already hold
  arenas.
- One arena keeps that memory in the process and reuses it: every method's latency and the peak memory fall
  (docs/decisions.md, "One malloc arena", has the figures and commands: benchmarks/bench_floor.py,
  benchmarks/bench_service.py). The service's allocations are few and large (numpy arrays; Python objects use
  their own allocator), so one arena costs no measurable lock contention.
- One arena alone still leaves page faults per request: glibc returns the top of its heap to the kernel once
  twice its (adaptive) mmap threshold is free, and maps blocks over that threshold anew every time. So the
  threshold is fixed at its 64-bit maximum (MMAP_THRESHOLD, 32 MiB: a 2560x1440 RGB float32 image) and the trim
  threshold raised to TRIM_THRESHOLD. The cost is that the process keeps its high-water mark, still well below
  the peak of the many-arena default.

``$GRADSEP_MALLOC_ARENAS`` sets the arena limit (default 1; 0 leaves glibc's malloc entirely as it is, 8 arenas
per core and adaptive thresholds). An operator's own glibc variables (``MALLOC_ARENA_MAX``,
``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``, read when the process starts) win, each for its parameter,
and ``GLIBC_TUNABLES`` naming ``glibc.malloc`` for all three. On a C library without ``mallopt`` (musl, macOS) this
is a no-op. Call :func:`configure_malloc` once, early, before the worker threads exist: arenas already created
stay as they are.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

from gradsep.model.environment import env_int

log = logging.getLogger(__name__)

ARENAS_ENV = "GRADSEP_MALLOC_ARENAS"
DEFAULT_ARENAS = 1
#: glibc's mallopt parameter numbers (malloc.h).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8
#: Blocks up to this size come from the heap (glibc's largest allowed on 64-bit: HEAP_MAX_SIZE / 2).
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free memory at the top of the heap is returned to the kernel only beyond this.
TRIM_THRESHOLD = 1024 * 1024 * 1024


def arenas_setting() -> int:
    """``$GRADSEP_MALLOC_ARENAS`` (≥ 0) or DEFAULT_ARENAS; ValueError naming the variable when it is not."""
    return env_int(ARENAS_ENV, DEFAULT_ARENAS, 0, "0 keeps glibc's default")


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") else None


def _operator_set(variable: str) -> bool:
    """True when the operator configured this glibc malloc parameter themselves."""
    return bool(os.environ.get(variable, "").strip()) or "glibc.malloc" in os.environ.get("GLIBC_TUNABLES", "")


def configure_malloc(arenas: int | None = None) -> int | None:
    """Limit malloc to ``arenas`` arenas (None: :func:`arenas_setting`) with fixed mmap/trim thresholds; the arena
    limit now in force, or None when it was not changed (0 asked, the operator's own setting, or no glibc
    ``mallopt``)."""
    arenas = arenas_setting() if arenas is None else arenas
    if arenas < 0:
        raise ValueError(f"malloc arenas must be at least 0, got {arenas}")
    libc = _libc() if arenas else None
    if libc is None:
        return None
    libc.mallopt.argtypes, libc.mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    applied = None
    for variable, parameter, value in (("MALLOC_ARENA_MAX", M_ARENA_MAX, arenas),
                                       ("MALLOC_MMAP_THRESHOLD_", M_MMAP_THRESHOLD, MMAP_THRESHOLD),
                                       ("MALLOC_TRIM_THRESHOLD_", M_TRIM_THRESHOLD, TRIM_THRESHOLD)):
        if _operator_set(variable):
            log.info("%s is set by the operator; left as it says", variable)
        elif libc.mallopt(parameter, value) != 1:
            log.warning("mallopt(%d, %d) failed; that malloc parameter keeps glibc's default", parameter, value)
        elif parameter == M_ARENA_MAX:
            applied = arenas
    return applied
