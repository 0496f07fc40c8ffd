"""The C allocator of a reconstructing process: glibc's malloc limited to one arena.

A frame is reconstructed in short-lived worker threads (model/reconstruct.py runs a frame's layers concurrently),
and every solve allocates frame-sized numpy temporaries. glibc gives threads their own malloc *arenas*; a new
worker thread per frame lands in an arena whose freed memory was handed back to the kernel. Its temporaries are
then fresh pages every frame.
- Measured on a 1280x720 frame (2026-12-03): about 30,000 page faults and 0.3-0.6 s of kernel time in the
  direct layer's refinement alone (refinement thread CPU 0.8 s → 1.3-1.4 s).
- This happens once ONNX Runtime / OpenVINO sessions are loaded (the service always loads them), as the
  process's other threads already hold arenas.
- One arena keeps that memory in the process and reuses it.
- Same process, same frame, in-process service pipeline (`python benchmarks/bench_floor.py`): `oidn-l1` 2.15-2.49
  → 1.83-1.94 s, `network` 1.84-1.87 → 1.33-1.59 s, `fused` 2.97-3.33 → 2.66-3.07 s, and peak RSS 4.4 → 2.0 GiB.
  MALLOC_ARENA_MAX=2 was about the same, 4 was in between; raising the trim/mmap thresholds alone did not help.
- The service's allocations are few and large (numpy arrays; Python objects use their own allocator), so one
  arena costs no measurable lock contention.

``$GRADSEP_MALLOC_ARENAS`` sets the limit (default 1; 0 leaves glibc's own default of 8 per core). An operator's
``MALLOC_ARENA_MAX`` (glibc's own variable, read when the process starts) wins: then nothing is changed here. On a
C library without ``mallopt`` (musl, macOS) this is a no-op. Call :func:`configure_malloc` once, early, before the
worker threads exist: arenas already created stay as they are.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

log = logging.getLogger(__name__)

ARENAS_ENV = "GRADSEP_MALLOC_ARENAS"
DEFAULT_ARENAS = 1
#: glibc's mallopt parameter number for the arena limit (malloc.h M_ARENA_MAX).
M_ARENA_MAX = -8


def arenas_setting() -> int:
    """``$GRADSEP_MALLOC_ARENAS`` (≥ 0) or DEFAULT_ARENAS; ValueError naming the variable when it is not."""
    raw = os.environ.get(ARENAS_ENV, "").strip()
    if not raw:
        return DEFAULT_ARENAS
    try:
        value = int(raw)
    except ValueError:
        raise ValueError(f"${ARENAS_ENV}={raw!r} is not an integer (0 keeps glibc's default)") from None
    if value < 0:
        raise ValueError(f"${ARENAS_ENV}={value} must be at least 0 (0 keeps glibc's default)")
    return value


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") else None


def configure_malloc(arenas: int | None = None) -> int | None:
    """Limit malloc to ``arenas`` arenas (None: :func:`arenas_setting`); the limit now in force, or None when
    nothing was changed (0 asked, ``MALLOC_ARENA_MAX`` set by the operator, or no glibc ``mallopt``)."""
    arenas = arenas_setting() if arenas is None else arenas
    if arenas < 0:
        raise ValueError(f"malloc arenas must be at least 0, got {arenas}")
    if arenas == 0:
        return None
    if os.environ.get("MALLOC_ARENA_MAX", "").strip():
        log.info("MALLOC_ARENA_MAX=%s is set; malloc arenas left as it says", os.environ["MALLOC_ARENA_MAX"])
        return None
    libc = _libc()
    if libc is None:
        return None
    libc.mallopt.argtypes, libc.mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    if libc.mallopt(M_ARENA_MAX, arenas) != 1:
        log.warning("mallopt(M_ARENA_MAX, %d) failed; malloc arenas left at glibc's default", arenas)
        return None
    return arenas
