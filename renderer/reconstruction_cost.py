"""What reconstructing a frame costs the planner, which must budget for it before it happens: the reconstruction
library's one-time start-up (paid early, in the background), and its seconds per pixel (timed on a tile).

The checkpoint (renderer/checkpoint.py) and the frame's own error estimate (renderer/check.py) reconstruct the
frame's halves; the deadline holds their time back from the passes.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from gradsep.model.frame import Frame
from gradsep.renderer.passes import crop, without_gradients

#: A reconstruction: a frame in, its image and the method that made it out.
Reconstruct = Callable[[Frame], tuple[np.ndarray, str]]

#: What the first reconstruction in a process costs before its work (importing pyoidn -- without torch:
#: model.oidn.import_pyoidn -- and the reconstruction modules, creating the OIDN device and its filters, loading
#: the compiled kernels), rounded up. Counted against the checkpoint's share before it is paid, so that a budget
#: too small for it falls back instead of overrunning.
RECONSTRUCT_STARTUP = 1.0
#: Seconds per pixel a reconstruction is assumed to take before one is measured (a fixed plan's check): the
#: default method's measured rate with room for a slower machine (docs/decisions.md).
CHECK_PRIOR_RATE = 3e-6
#: Side of the tile :func:`reconstruct_rate` times.
RATE_TILE = 64
#: Side of the tile the reconstruction library's start-up is paid on, in the background (warm_reconstruction).
WARM_TILE = 16


def reconstruct_startup() -> float:
    """RECONSTRUCT_STARTUP while this process has not reconstructed yet, else 0."""
    return 0.0 if "pyoidn" in sys.modules else RECONSTRUCT_STARTUP


def reconstruct_default(frame: Frame) -> tuple[np.ndarray, str]:
    """The one call into the reconstruction library: the default method that would serve this frame."""
    from gradsep.model.reconstruct import reconstruct

    result = reconstruct(frame)
    return result.image, result.method


def reconstruct_rate(frame: Frame, reconstruct: Reconstruct = reconstruct_default, side: int = RATE_TILE) -> float:
    """Seconds per pixel of the default reconstruction of ``frame``, timed on its centre tile (``side`` square, or
    the whole frame when smaller) after one untimed call on the same tile (the process's first reconstruction
    pays its start-up: RECONSTRUCT_STARTUP)."""
    h, w = frame.height, frame.width
    y0, x0 = max(0, (h - side) // 2), max(0, (w - side) // 2)
    tile = crop(frame, (slice(y0, min(h, y0 + side)), slice(x0, min(w, x0 + side))))
    reconstruct(tile)
    start = time.perf_counter()
    reconstruct(tile)
    return (time.perf_counter() - start) / (tile.width * tile.height)


def warm_reconstruction(tile: Frame, reconstruct: Reconstruct = reconstruct_default) -> threading.Thread | None:
    """Pay the reconstruction library's one-time start-up (RECONSTRUCT_STARTUP: its import, OIDN's device and
    filters) in a background thread, on a small ``tile`` of the frame both ways (with its gradients and as a
    plain frame), while the checkpoint's passes render: Dr.Jit's kernels and OIDN's set-up run outside the GIL, so
    the overlap costs the passes little. None where it is paid already. The caller joins it before it
    reconstructs; an error there is left to the caller's own reconstruction to raise, in the foreground."""
    if "pyoidn" in sys.modules:
        return None

    def run() -> None:
        with contextlib.suppress(Exception):
            for f in (tile, without_gradients(tile)):
                reconstruct(f)

    thread = threading.Thread(target=run, name="gradsep-reconstruction-warm-up", daemon=True)
    thread.start()
    return thread
