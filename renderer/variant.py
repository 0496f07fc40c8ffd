"""The Mitsuba variant the renderer runs on: chosen once per process, by one function; and the libLLVM the CPU
variant compiles its kernels with.

Scene loading (renderer/scene.py) and the procedural generator (renderer/procedural.py, which converts its plan
into Mitsuba objects) both need a variant set; both call :func:`select_variant`, which lives here so that neither
of them imports the other for it.

The CPU variant (``llvm_ad_rgb``) compiles with the libLLVM that Dr.Jit loads when it is imported: the one named
by ``DRJIT_LIBLLVM_PATH``, else the first its own search finds. Mitsuba 3.9's kernels need LLVM 19 or newer; an
older one aborts the process while compiling the first kernel (``LLVM ERROR: Cannot select: ... fmaximum``).
:func:`point_drjit_at_llvm` (run when the renderer package is imported, before anything imports Dr.Jit) finds a
suitable libLLVM in the ordinary library folders and names it in ``DRJIT_LIBLLVM_PATH`` (one the user set is
kept); :func:`select_variant` refuses the CPU variant in one line, naming the fix, when there is none.
"""

from __future__ import annotations

import glob
import os
import re
import sys
import threading
from collections.abc import MutableMapping, Sequence

from gradsep.renderer.errors import SceneError

__all__ = ["CPU_VARIANT", "GPU_VARIANT", "LLVM_ENV", "LLVM_SEARCH", "MIN_LLVM", "VARIANT_ENV", "find_llvm",
           "llvm_version", "point_drjit_at_llvm", "select_variant"]

VARIANT_ENV = "GRADSEP_MI_VARIANT"
CPU_VARIANT = "llvm_ad_rgb"
GPU_VARIANT = "cuda_ad_rgb"

_variant_lock = threading.Lock()

LLVM_ENV = "DRJIT_LIBLLVM_PATH"  # Dr.Jit reads it once, when it is imported
MIN_LLVM = 19  # the oldest LLVM major version Mitsuba's llvm_ad_rgb kernels compile with
# Where distributions install libLLVM (Debian/Ubuntu: /usr/lib/<triplet> and /usr/lib/llvm-N/lib).
LLVM_SEARCH: tuple[str, ...] = ("/usr/lib/*/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*",
                                "/usr/lib64/libLLVM*.so*", "/usr/lib64/llvm*/lib*/libLLVM*.so*",
                                "/usr/local/lib/libLLVM*.so*")
LLVM_FIX = "apt-get install libllvm19 (or make system-deps)"

# libLLVM-19.so, libLLVM-19.so.1, libLLVM.so.19.1, libLLVM-19.1.7.so; libLLVM.so itself says nothing (its folder may).
_LLVM_NAME = re.compile(r"^libLLVM(?:-(\d+)[\d.]*)?\.so(?:\.(\d+)[\d.]*)?$")
_LLVM_FOLDER = re.compile(r"/llvm-?(\d+)(?:\.[\d.]*)?/")

# What point_drjit_at_llvm found: the path it set or the user's, or None where no suitable libLLVM exists.
_llvm: dict[str, str | None] = {}


def llvm_version(path: str) -> int | None:
    """The LLVM major version of a libLLVM file: from its name's ``-N`` (libLLVM-19.so), else its folder's
    (/usr/lib/llvm-19/lib), else its name's ``.so.N`` (libLLVM.so.19.1); for a link, what its target says where
    the link itself says nothing. None where none of them says."""
    for candidate in (path, os.path.realpath(path)):
        match = _LLVM_NAME.match(os.path.basename(candidate))
        if match is None:
            continue
        folder = _LLVM_FOLDER.search(candidate)
        number = match.group(1) or (folder.group(1) if folder else None) or match.group(2)
        if number is not None:
            return int(number)
    return None


def find_llvm(patterns: Sequence[str] = LLVM_SEARCH) -> str | None:
    """The newest libLLVM of version MIN_LLVM or later in the folders ``patterns`` match, or None."""
    found = [(version, path) for pattern in patterns for path in sorted(glob.glob(pattern))
             if os.path.isfile(path) and (version := llvm_version(path)) is not None and version >= MIN_LLVM]
    return max(found)[1] if found else None


def point_drjit_at_llvm(environ: MutableMapping[str, str] | None = None,
                        patterns: Sequence[str] = LLVM_SEARCH) -> str | None:
    """Name a suitable libLLVM in ``DRJIT_LIBLLVM_PATH`` for Dr.Jit, unless the user already named one; returns the
    library in use, or None where none of version MIN_LLVM or later was found. Runs once per process (later calls
    return the first answer); it must run before Dr.Jit is imported to take effect."""
    env = os.environ if environ is None else environ
    if "path" not in _llvm:
        if env.get(LLVM_ENV):
            _llvm["path"] = env[LLVM_ENV]
        else:
            _llvm["path"] = find_llvm(patterns)
            if _llvm["path"] is not None:
                env[LLVM_ENV] = _llvm["path"]
    return _llvm["path"]


def _require_llvm() -> None:
    """Refuse the CPU variant where no suitable libLLVM was found (Linux only: elsewhere Dr.Jit's own search
    stands), before any kernel is compiled with an unsuitable one."""
    if sys.platform.startswith("linux") and "path" in _llvm and _llvm["path"] is None:
        raise SceneError(f"the CPU renderer ({CPU_VARIANT}) needs libLLVM {MIN_LLVM} or newer and none was found "
                         f"(LLVM 14/15 abort while compiling); install it: {LLVM_FIX}, or set {LLVM_ENV}")


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
            if wanted == CPU_VARIANT:
                _require_llvm()
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
        _require_llvm()
        mi.set_variant(CPU_VARIANT)
        return CPU_VARIANT


def _cuda_available() -> bool:
    """Whether Dr.Jit can reach a CUDA device (never raises)."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:
        return False
