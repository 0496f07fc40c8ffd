"""The Mitsuba variant the renderer runs on: chosen once per process, by one function.

Scene loading (renderer/scene.py) and the procedural generator (renderer/procedural.py, which converts its plan
into Mitsuba objects) both need a variant set; both call :func:`select_variant`, which lives here so that neither
of them imports the other for it.
"""

from __future__ import annotations

import os
import threading

from gradsep.renderer.errors import SceneError

__all__ = ["CPU_VARIANT", "GPU_VARIANT", "VARIANT_ENV", "select_variant"]

VARIANT_ENV = "GRADSEP_MI_VARIANT"
CPU_VARIANT = "llvm_ad_rgb"
GPU_VARIANT = "cuda_ad_rgb"

_variant_lock = threading.Lock()


def select_variant() -> str:
    """Set (once) and return the Mitsuba variant: $GRADSEP_MI_VARIANT, else CUDA when usable, else LLVM.

    Only ``*_ad_rgb`` variants make sense here (the integrator is written for RGB with Dr.Jit JIT arrays); an
    explicit request for anything else is refused rather than silently replaced.
    """
    import mitsuba as mi

    with _variant_lock:
        current = mi.variant()
        if current is not None and current in (GPU_VARIANT, CPU_VARIANT) and VARIANT_ENV not in os.environ:
            return current
        wanted = os.environ.get(VARIANT_ENV)
        if wanted:
            if wanted not in (CPU_VARIANT, GPU_VARIANT):
                raise SceneError(f"{VARIANT_ENV}={wanted!r}: the G-PT renderer needs {CPU_VARIANT} or {GPU_VARIANT}")
            if wanted not in mi.variants():
                raise SceneError(f"{VARIANT_ENV}={wanted!r}: this Mitsuba build has no such variant")
            if current != wanted:
                try:
                    mi.set_variant(wanted)
                except Exception as exc:  # e.g. no CUDA driver
                    raise SceneError(f"{VARIANT_ENV}={wanted!r} cannot be used here: {exc}") from exc
            return wanted
        if current in (GPU_VARIANT, CPU_VARIANT):
            return current
        if GPU_VARIANT in mi.variants() and _cuda_available():
            try:
                mi.set_variant(GPU_VARIANT)
                return GPU_VARIANT
            except Exception:  # driver present but unusable: fall back to the CPU
                pass
        mi.set_variant(CPU_VARIANT)
        return CPU_VARIANT


def _cuda_available() -> bool:
    """Whether Dr.Jit can reach a CUDA device (never raises)."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:
        return False
