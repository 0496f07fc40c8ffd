"""Compiled (numba) kernels for the IRLS inner loop of model.poisson.solve_l1.

Each kernel fuses what the numpy formulation does in several full-array passes with temporaries: the weighted
operator ``A p`` (one pass instead of ~10), the weighted right-hand side, the residuals together with their
per-pixel RGB norms, and the CG vector updates together with the new residual's inner products. The arithmetic
is the same float32 (or float64) arithmetic in a different order, so results agree with the numpy path to
rounding (tests/model/test_poisson.py compares both). Single-threaded (see _OPTS).

``AVAILABLE`` is False where numba cannot be imported (it is a core dependency, but a platform without its
wheels still works): model.poisson then runs its numpy path. ``GRADSEP_NUMBA=0`` forces the numpy path too.
Compiled code is cached on disk next to this file when that is writable (``cache=True``); otherwise each
process compiles on first use (~seconds; the service pays it during warm-up).
"""

from __future__ import annotations

import os

import numpy as np

try:  # pragma: no branch - which side runs depends on the host
    if os.environ.get("GRADSEP_NUMBA", "1") == "0":
        raise ImportError("disabled by GRADSEP_NUMBA=0")
    from numba import njit

    AVAILABLE = True
except ImportError:  # numpy fallback in model.poisson
    AVAILABLE = False

__all__ = ["AVAILABLE", "cg_update", "residuals_and_norms", "weighted_apply", "weighted_rhs"]


if AVAILABLE:
    # Serial: on the 2-core target, with the DCTs and a second request competing for the cores, threaded
    # kernels measured slower (20 ms vs 2-6 ms for one A·p on 3x720x1280 under load) than one thread.
    _OPTS = {"fastmath": False, "nogil": True}

    def _compiled(fn):
        """njit with an on-disk cache where numba finds a writable place for one (next to this file, or
        NUMBA_CACHE_DIR), else without: numba refuses ``cache=True`` when it has nowhere to write."""
        try:
            return njit(cache=True, **_OPTS)(fn)
        except RuntimeError:  # "cannot cache function ...: no locator available"
            return njit(cache=False, **_OPTS)(fn)

    @_compiled
    def weighted_apply(p, a2w0, wx, wy, out):  # pragma: no cover - compiled
        """out = (α² W0 + H_xᵀ Wx H_x + H_yᵀ Wy H_y) p for p (C, H, W)."""
        channels, height, width = p.shape
        for i in range(channels * height):
            c, y = i // height, i % height
            for x in range(width):
                pc = p[c, y, x]
                v = a2w0[y, x] * pc
                if x + 1 < width:
                    v -= wx[y, x] * (p[c, y, x + 1] - pc)
                if x > 0:
                    v += wx[y, x - 1] * (pc - p[c, y, x - 1])
                if y + 1 < height:
                    v -= wy[y, x] * (p[c, y + 1, x] - pc)
                if y > 0:
                    v += wy[y - 1, x] * (pc - p[c, y - 1, x])
                out[c, y, x] = v
        return out

    @_compiled
    def weighted_rhs(e0, ex, ey, aw0, wx, wy, out):  # pragma: no cover - compiled
        """out = α W0 e0 + H_xᵀ Wx ex + H_yᵀ Wy ey (the IRLS right-hand side Pᵀ W e)."""
        channels, height, width = e0.shape
        for i in range(channels * height):
            c, y = i // height, i % height
            for x in range(width):
                v = aw0[y, x] * e0[c, y, x]
                if x + 1 < width:
                    v -= wx[y, x] * ex[c, y, x]
                if x > 0:
                    v += wx[y, x - 1] * ex[c, y, x - 1]
                if y + 1 < height:
                    v -= wy[y, x] * ey[c, y, x]
                if y > 0:
                    v += wy[y - 1, x] * ey[c, y - 1, x]
                out[c, y, x] = v
        return out

    @_compiled
    def residuals_and_norms(x, base, dx, dy, alpha, e0, ex, ey, n0, nx, ny):  # pragma: no cover - compiled
        """e0 = α(base − x), ex = dx − H_x x, ey = dy − H_y x and their per-pixel norms over channels.

        Row by row, channel by channel (contiguous inner loops), summing squares into per-row accumulators."""
        channels, height, width = x.shape
        a = x.dtype.type(alpha)
        s0 = np.empty(width, np.float64)
        sx = np.empty(width, np.float64)
        sy = np.empty(width, np.float64)
        for y in range(height):
            s0[:] = 0.0
            sx[:] = 0.0
            sy[:] = 0.0
            below = y + 1 < height
            for c in range(channels):
                for col in range(width):
                    xc = x[c, y, col]
                    v = a * (base[c, y, col] - xc)
                    e0[c, y, col] = v
                    s0[col] += v * v
                for col in range(width - 1):
                    v = dx[c, y, col] - (x[c, y, col + 1] - x[c, y, col])
                    ex[c, y, col] = v
                    sx[col] += v * v
                if below:
                    for col in range(width):
                        v = dy[c, y, col] - (x[c, y + 1, col] - x[c, y, col])
                        ey[c, y, col] = v
                        sy[col] += v * v
            for col in range(width):
                n0[y, col] = np.sqrt(s0[col])
            for col in range(width - 1):
                nx[y, col] = np.sqrt(sx[col])
            if below:
                for col in range(width):
                    ny[y, col] = np.sqrt(sy[col])

    @_compiled
    def cg_update(d, r, p, ap, step, rr):  # pragma: no cover - compiled
        """d += step·p, r −= step·ap per channel; rr[c] = ‖r_c‖² after the update (float64 partial sums)."""
        channels, height, width = r.shape
        partial = np.zeros(channels * height)
        for i in range(channels * height):
            c, y = i // height, i % height
            s = step[c]
            acc = 0.0
            for x in range(width):
                d[c, y, x] += s * p[c, y, x]
                v = r[c, y, x] - s * ap[c, y, x]
                r[c, y, x] = v
                acc += v * v
            partial[i] = acc
        for c in range(channels):
            rr[c] = partial[c * height:(c + 1) * height].sum()


# ----------------------------------------------------------------------------------------------------------------
# Aggregation multigrid for the IRLS systems (model.poisson, preconditioner "mg")
#
# The weighted operator A = diag(a) + H_xᵀ Wx H_x + H_yᵀ Wy H_y is a graph Laplacian plus a diagonal. With the
# piecewise-constant prolongation P of 2×2 aggregates the Galerkin coarse operator PᵀAP has exactly the same form
# (coarse a = sum of the four fine a; a coarse x-edge weight = sum of the two fine x-edges crossing between the two
# aggregates; edges inside an aggregate drop out), so one 5-point stencil kernel serves every level and the
# hierarchy follows the IRLS weights exactly, down to a 1×1 level where the coarse problem (the image mean) is
# solved exactly. Smoother: red-black Gauss-Seidel, red then black before the coarse correction and black then
# red after it, so the V-cycle is a symmetric positive definite operator, as preconditioned CG needs.
# ----------------------------------------------------------------------------------------------------------------

__all__ += ["mg_coarsen", "mg_inverse_diagonal", "mg_jacobi_red", "mg_red_residual_restrict", "mg_prolong_red",
            "mg_sweep", "irls_weights"]

if AVAILABLE:

    @_compiled
    def irls_weights(n0, nx, ny, reg, alpha, w0, wx, wy, a2w0, aw0, diag):  # pragma: no cover - compiled
        """One IRLS pass's system from the residual norms, in place, in two passes over the weights instead of
        ~15 numpy passes: w = 1/(n + reg) normalised to mean 1 over all terms, a2w0 = α²·w0, aw0 = α·w0 and
        diag = diag(A) = α²w0 + the weights of the gradient terms touching each pixel."""
        height, width = n0.shape
        total = 0.0
        for n, w in ((n0, w0), (nx, wx), (ny, wy)):
            fn, fw = n.ravel(), w.ravel()
            for i in range(fn.size):
                v = 1.0 / (fn[i] + reg)
                fw[i] = v
                total += v
        scale = (n0.size + nx.size + ny.size) / total
        a2 = alpha * alpha
        for y in range(height):
            for x in range(width):
                v = w0[y, x] * scale
                w0[y, x] = v
                a2w0[y, x] = a2 * v
                aw0[y, x] = alpha * v
                d = a2 * v
                if x + 1 < width:
                    wx[y, x] *= scale
                    d += wx[y, x]
                if x > 0:
                    d += wx[y, x - 1]
                if y + 1 < height:  # scaled here, before the row below reads it
                    wy[y, x] *= scale
                    d += wy[y, x]
                if y > 0:
                    d += wy[y - 1, x]
                diag[y, x] = d

    @_compiled
    def mg_coarsen(a, wx, wy):  # pragma: no cover - compiled
        """The Galerkin coarse operator (a, wx, wy) of 2×2 aggregation; odd sizes leave 1-wide aggregates."""
        height, width = a.shape
        hc, wc = (height + 1) // 2, (width + 1) // 2
        ac = np.zeros((hc, wc), a.dtype)
        wxc = np.zeros((hc, max(wc - 1, 0)), a.dtype)
        wyc = np.zeros((max(hc - 1, 0), wc), a.dtype)
        for y in range(height):
            for x in range(width):
                ac[y // 2, x // 2] += a[y, x]
            for xc in range(wc - 1):
                wxc[y // 2, xc] += wx[y, 2 * xc + 1]
        for yc in range(hc - 1):
            for x in range(width):
                wyc[yc, x // 2] += wy[2 * yc + 1, x]
        return ac, wxc, wyc

    @_compiled
    def mg_inverse_diagonal(a, wx, wy):  # pragma: no cover - compiled
        """1 / diag(A) (a plus the weights of the edges touching each pixel)."""
        height, width = a.shape
        d = a.copy()
        for y in range(height):
            for x in range(width - 1):
                d[y, x] += wx[y, x]
                d[y, x + 1] += wx[y, x]
        for y in range(height - 1):
            for x in range(width):
                d[y, x] += wy[y, x]
                d[y + 1, x] += wy[y, x]
        for y in range(height):
            for x in range(width):
                d[y, x] = 1.0 / d[y, x] if d[y, x] > 0 else 0.0
        return d

    @_compiled
    def mg_sweep(z, r, wx, wy, idiag, color):  # pragma: no cover - compiled
        """One Gauss-Seidel half-sweep over the pixels with (x + y) % 2 == color (red 0, black 1). (Written out
        in full: with the point update in a helper function numba's code ran ~7x slower.)"""
        channels, height, width = z.shape
        for c in range(channels):
            for y in range(height):
                for x in range((y + color) % 2, width, 2):
                    s = r[c, y, x]
                    if x + 1 < width:
                        s += wx[y, x] * z[c, y, x + 1]
                    if x > 0:
                        s += wx[y, x - 1] * z[c, y, x - 1]
                    if y + 1 < height:
                        s += wy[y, x] * z[c, y + 1, x]
                    if y > 0:
                        s += wy[y - 1, x] * z[c, y - 1, x]
                    z[c, y, x] = s * idiag[y, x]

    @_compiled
    def mg_jacobi_red(z, r, idiag):  # pragma: no cover - compiled
        """The red half-sweep from z = 0: z = r/diag on red pixels, 0 on black ones (mg_sweep(…, 1) follows)."""
        channels, height, width = z.shape
        for c in range(channels):
            for y in range(height):
                for x in range(width):
                    z[c, y, x] = r[c, y, x] * idiag[y, x] if (x + y) % 2 == 0 else 0.0

    @_compiled
    def mg_red_residual_restrict(z, r, a, wx, wy, rc):  # pragma: no cover - compiled
        """rc = Pᵀ(r − A z) after a red-black presmoothing: the black residuals are zero (their equations were
        just solved), so only red pixels contribute."""
        channels, height, width = z.shape
        rc[:] = 0.0
        for c in range(channels):
            for y in range(height):
                for x in range(y % 2, width, 2):
                    zc = z[c, y, x]
                    v = a[y, x] * zc
                    if x + 1 < width:
                        v -= wx[y, x] * (z[c, y, x + 1] - zc)
                    if x > 0:
                        v += wx[y, x - 1] * (zc - z[c, y, x - 1])
                    if y + 1 < height:
                        v -= wy[y, x] * (z[c, y + 1, x] - zc)
                    if y > 0:
                        v += wy[y - 1, x] * (zc - z[c, y - 1, x])
                    rc[c, y // 2, x // 2] += r[c, y, x] - v

    @_compiled
    def mg_prolong_red(z, zc):  # pragma: no cover - compiled
        """z += P zc on the red pixels only: the black half-sweep that follows overwrites the black ones."""
        channels, height, width = z.shape
        for c in range(channels):
            for y in range(height):
                for x in range(y % 2, width, 2):
                    z[c, y, x] += zc[c, y // 2, x // 2]
