"""Compiled (numba) kernels for the IRLS inner loop of model.poisson.solve_l1, the bilinear and whole-pixel warps
of model.temporal, and model.robust's box mean.

Each kernel fuses what the numpy formulation does in several full-array passes with temporaries: the weighted
operator ``A p`` (one pass instead of many), the weighted right-hand side, the residuals together with their
per-pixel RGB norms, one pass's weights with the system's diagonal, and the CG vector updates together with the
new residual's inner products. The arithmetic is the same float32 (or float64) arithmetic in a different order,
so results agree with the numpy path to rounding (tests/model/test_poisson.py compares both). Single-threaded
(see _OPTS). The multigrid preconditioner's kernels are in model/multigrid.py. :func:`bilinear` does the
temporal warp's float32 arithmetic in the numpy path's order, so the two agree bit for bit
(tests/model/test_temporal.py compares them). :func:`box_mean` sums in float64 where scipy's ``correlate1d`` sums
in double too, so the two agree to the last bit or two of float32 (tests/model/test_kernels.py); it runs over whole
rows, which the compiler vectorises, where ``correlate1d`` walks each line through a buffer.

``AVAILABLE`` is False where numba cannot be imported (it is a core dependency, but a platform without its
wheels still works): model.poisson, model.temporal and model.robust then run their numpy and scipy paths.
``GRADSEP_NUMBA=0`` forces those paths too. Compiled code is cached on disk next to this file when that is writable
(``cache=True``); otherwise each process compiles on first use (the service pays it during warm-up, the warp
included).
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

__all__ = ["AVAILABLE", "bilinear", "box_mean", "cg_update", "compiled", "gather", "irls_weights",
           "residuals_and_norms", "weighted_apply", "weighted_rhs"]


if AVAILABLE:
    # Serial: on the small-core-count target, with the DCTs and a second request competing for the cores, threaded
    # kernels measured slower than one thread (docs/decisions.md).
    _OPTS = {"fastmath": False, "nogil": True}

    def compiled(fn):
        """njit with an on-disk cache where numba finds a writable place for one (next to this file, or
        NUMBA_CACHE_DIR), else without: numba refuses ``cache=True`` when it has nowhere to write."""
        try:
            return njit(cache=True, **_OPTS)(fn)
        except RuntimeError:  # "cannot cache function ...: no locator available"
            return njit(cache=False, **_OPTS)(fn)

    @compiled
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

    @compiled
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

    @compiled
    def residuals_and_norms(x, base, dx, dy, alpha, residuals, norms):  # pragma: no cover - compiled
        """``residuals`` = (e0, ex, ey) ← (α(base − x), dx − H_x x, dy − H_y x) and ``norms`` = (n0, nx, ny) ← their
        per-pixel norms over channels.

        Row by row, channel by channel (contiguous inner loops), summing squares into per-row accumulators."""
        e0, ex, ey = residuals
        n0, nx, ny = norms
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

    @compiled
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

    @compiled
    def irls_weights(norms, reg, alpha, weights):  # pragma: no cover - compiled
        """One IRLS pass's system from the residual norms ``norms`` = (n0, nx, ny), in place into ``weights`` =
        (w0, wx, wy, a2w0, aw0, diag), in two passes over the weights instead of many numpy passes: w = 1/(n + reg)
        normalised to mean 1 over all terms, a2w0 = α²·w0, aw0 = α·w0 and diag = diag(A) = α²w0 + the weights of
        the gradient terms touching each pixel."""
        n0, nx, ny = norms
        w0, wx, wy, a2w0, aw0, diag = weights
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

    @compiled
    def bilinear(flat, index, fr, fc, width, squared, out):  # pragma: no cover - compiled
        """out[p] = the bilinear mix of the four pixels of ``flat`` (an (H·W, C) image, ``width`` wide) from
        ``index[p]`` (the top-left one's flat index; the right or lower one repeats it on the last column or row, the
        last row being where one row further leaves ``flat``) by the fractions
        (``fr[p]``, ``fc[p]``), each weight squared when ``squared`` (a variance's warp). One pass instead of
        model.temporal's numpy path's four gathers and products, with its float32 arithmetic in its order: the
        weights (1 - fr)(1 - fc), (1 - fr) fc, fr (1 - fc), fr fc, and 0 plus each tap times its weight in turn."""
        one, zero = np.float32(1.0), np.float32(0.0)
        size, channels = flat.shape
        for p in range(index.shape[0]):
            i00 = index[p]
            i01 = i00 + 1 if i00 % width + 1 < width else i00
            down = width if i00 + width < size else 0
            a, b = fr[p], fc[p]
            w00, w01, w10, w11 = (one - a) * (one - b), (one - a) * b, a * (one - b), a * b
            if squared:
                w00, w01, w10, w11 = w00 * w00, w01 * w01, w10 * w10, w11 * w11
            for c in range(channels):
                v = zero + flat[i00, c] * w00
                v += flat[i01, c] * w01
                v += flat[i00 + down, c] * w10
                v += flat[i01 + down, c] * w11
                out[p, c] = v

    @compiled
    def gather(flat, index, out):  # pragma: no cover - compiled
        """out[p] = flat[index[p]] for an (N, C) ``flat``: np.take along the first axis, without its generic path."""
        for p in range(index.shape[0]):
            i = index[p]
            for c in range(flat.shape[1]):
                out[p, c] = flat[i, c]
        return out

    @compiled
    def box_mean(image, size, out):  # pragma: no cover - compiled
        """out = the ``size`` × ``size`` mean (``size`` odd) of the (H, W) ``image``, edges repeated: a direct sum of
        ``size`` rows, then of ``size`` columns, each in float64 (a value reaches only the windows that hold it,
        as model.robust.box_mean requires), each divided by ``size``. Rows are summed whole, so both passes run
        over contiguous memory."""
        height, width = image.shape
        radius = size // 2
        inverse = 1.0 / size
        column = np.empty((height, width), np.float64)
        for y in range(height):
            row = column[y]
            row[:] = 0.0
            for k in range(-radius, radius + 1):
                source = image[min(max(y + k, 0), height - 1)]
                for x in range(width):
                    row[x] += source[x]
            for x in range(width):
                row[x] *= inverse
        padded = np.empty(width + 2 * radius, np.float64)
        total = np.empty(width, np.float64)
        for y in range(height):
            row = column[y]
            for x in range(radius):
                padded[x] = row[0]
                padded[width + radius + x] = row[width - 1]
            padded[radius:radius + width] = row
            total[:] = 0.0
            for k in range(size):
                for x in range(width):
                    total[x] += padded[k + x]
            for x in range(width):
                out[y, x] = total[x] * inverse
        return out
