"""The aggregation-multigrid preconditioner of the IRLS systems (model.poisson, preconditioner ``"mg"``).

The weighted operator A = diag(a) + H_xᵀ Wx H_x + H_yᵀ Wy H_y is a graph Laplacian plus a diagonal. With the
piecewise-constant prolongation P of 2×2 aggregates the Galerkin coarse operator PᵀAP has exactly the same form
(coarse a = sum of the four fine a; a coarse x-edge weight = sum of the two fine x-edges crossing between the two
aggregates; edges inside an aggregate drop out), so one 5-point stencil kernel serves every level and the
hierarchy follows the IRLS weights exactly, down to a 1×1 level where the coarse problem (the image mean) is
solved exactly. Smoother: red-black Gauss-Seidel, red then black before the coarse correction and black then
red after it, so the V-cycle is a symmetric positive definite operator, as preconditioned CG needs.

The kernels are compiled with numba (model/kernels.py): without it there is no ``"mg"`` preconditioner.
"""

from __future__ import annotations

import numpy as np

from gradsep.model.kernels import AVAILABLE

__all__ = ["Multigrid"]

if AVAILABLE:
    from gradsep.model.kernels import compiled

    @compiled
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

    @compiled
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

    @compiled
    def mg_sweep(z, r, wx, wy, idiag, color):  # pragma: no cover - compiled
        """One Gauss-Seidel half-sweep over the pixels with (x + y) % 2 == color (red 0, black 1), the point
        update written inline (numba compiles it better than a helper call)."""
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

    @compiled
    def mg_jacobi_red(z, r, idiag):  # pragma: no cover - compiled
        """The red half-sweep from z = 0: z = r/diag on red pixels, 0 on black ones (mg_sweep(…, 1) follows)."""
        channels, height, width = z.shape
        for c in range(channels):
            for y in range(height):
                for x in range(width):
                    z[c, y, x] = r[c, y, x] * idiag[y, x] if (x + y) % 2 == 0 else 0.0

    @compiled
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

    @compiled
    def mg_prolong_red(z, zc):  # pragma: no cover - compiled
        """z += P zc on the red pixels only: the black half-sweep that follows overwrites the black ones."""
        channels, height, width = z.shape
        for c in range(channels):
            for y in range(height):
                for x in range(y % 2, width, 2):
                    z[c, y, x] += zc[c, y // 2, x // 2]


class Multigrid:
    """Aggregation-multigrid V-cycle for one IRLS system (the module's docstring has the why).

    Levels halve each side (2×2 aggregates, Galerkin coarse operators of the same 5-point form) down to 1×1, where
    the coarse problem, the weighted mean, is solved exactly: the constant mode, whose eigenvalue ~α² makes it the
    stiff one at small α, is therefore handled exactly. One red-black Gauss-Seidel half-sweep pair before and after
    each coarse correction."""

    def __init__(self, a: np.ndarray, wx: np.ndarray, wy: np.ndarray, channels: int, diag: np.ndarray) -> None:
        if not AVAILABLE:
            raise RuntimeError("the mg preconditioner needs numba's compiled kernels (unavailable or GRADSEP_NUMBA=0)")
        self.levels: list[tuple[np.ndarray, ...]] = []
        idiag = (1.0 / diag).astype(a.dtype)  # the fine level's diagonal is known already
        while True:
            height, width = a.shape
            z = np.empty((channels, height, width), a.dtype)
            r = np.empty((channels, height, width), a.dtype)
            self.levels.append((a, wx, wy, idiag, z, r))
            if height == 1 and width == 1:
                break
            a, wx, wy = mg_coarsen(a, wx, wy)
            idiag = mg_inverse_diagonal(a, wx, wy)

    def vcycle(self, r: np.ndarray) -> np.ndarray:
        z = np.empty_like(r)
        self._cycle(0, r, z)
        return z

    def _cycle(self, level: int, r: np.ndarray, z: np.ndarray) -> None:
        a, wx, wy, idiag, _, _ = self.levels[level]
        if level == len(self.levels) - 1:  # 1×1: exact
            np.multiply(r, idiag, out=z)
            return
        _, _, _, _, zc, rc = self.levels[level + 1]
        mg_jacobi_red(z, r, idiag)
        mg_sweep(z, r, wx, wy, idiag, 1)
        mg_red_residual_restrict(z, r, a, wx, wy, rc)
        self._cycle(level + 1, rc, zc)
        mg_prolong_red(z, zc)
        mg_sweep(z, r, wx, wy, idiag, 1)
        mg_sweep(z, r, wx, wy, idiag, 0)
