"""Screened Poisson reconstruction of an image from a noisy base image and its noisy gradients.

Both solvers minimise, per illumination layer,

    E(I) = ‖α (I − I_b)‖ + ‖(H_x I − g_x, H_y I − g_y)‖

where ``H_x``/``H_y`` are the forward differences of the frame contract (``dx(x,y) = I(x+1,y) − I(x,y)``, no
term for the last column; ``dy`` likewise, no term for the last row) and α weights the base image. As in the
NVIDIA reference solver (Kettunen et al. 2015) α multiplies the *residual*, so the L2 data term carries α².

* :func:`solve_l2` -- the L2 minimiser in closed form. Its normal equations ``(α² + HᵀH) I = α² I_b + Hᵀg``
  involve ``HᵀH``, the 5-point Laplacian with Neumann boundaries, which the orthonormal DCT-II diagonalises
  (Bhat et al. 2008), so the exact solution costs two DCTs per channel: O(N log N).
* :func:`solve_l1` -- the L1 minimiser by iteratively reweighted least squares (IRLS) following the reference
  solver's "L1D" preset: a first unweighted pass (solved exactly, as :func:`solve_l2` does), then reweightings
  with per-term weights ``w = 1/(‖e‖_RGB + reg)`` normalised to mean 1 and ``reg = reg_init · reg_decay^(k−1)``.
  Each weighted system is solved by conjugate gradients warm-started from the previous iterate; unlike the
  reference we precondition CG with the DCT solve of the unweighted system, rescaled to the weights' diagonal,
  which needs far fewer steps per pass, so the default budget (:class:`L1Options`: L1_PASSES passes of
  L1_CG_STEPS steps) is a fraction of the reference's 20 passes of 50 plain steps at the same error on rendered
  frames (docs/poisson.md has the measurements). ``preconditioner="mg"`` is an aggregation-multigrid V-cycle
  instead (compiled kernels): it solves each pass far more exactly per step, which on rendered frames moved the
  image *further* from the reference (the truncated DCT-PCG regularises); model/refine.py runs it.

Precision: the L2 closed form is float64 throughout (at α = 1e-4 the constant mode is scaled by 1/α² = 1e8; its
coefficient is computed from exact sums rather than from the divergence, whose DC is zero analytically but
rounding noise numerically, so the mean stays exact). IRLS iterates in float32 on inputs scaled to
max |value| = 1 (no overflow, no subnormals), or in float64 when α < FLOAT32_MIN_ALPHA; CG inner products are
BLAS dots. IRLS is run to a fixed budget (as the reference), not to convergence, so a single huge outlier in a
gradient is reduced against L2 but not removed entirely. Results are returned as float32 (the frame format's
precision) unless ``L1Options(dtype=np.float64)`` (or ``solve_l2(..., dtype=np.float64)``) asks for float64.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import scipy.fft

from gradsep.model import kernels
from gradsep.model.frame import FLOAT32_MAX
from gradsep.model.multigrid import Multigrid
from gradsep.model.policy import DEFAULT_ALPHA

__all__ = ["L1_CG_STEPS", "L1_PASSES", "MIN_ALPHA", "L1Options", "L1Stats", "energy_l1", "energy_l2", "solve_l1",
           "solve_l2"]

#: Smallest accepted α. Below ~1e-154 α² underflows to 0 in float64 and the constant mode (eigenvalue α²) is
#: undetermined; well before that the data term stops meaning anything. Down to 1e-12 both solvers still
#: return the exact image from exact data (tested at MIN_ALPHA); 1e-8 keeps a margin of 1e4. Callers (CLI,
#: service) reject smaller values up front with a message naming the range.
MIN_ALPHA = 1e-8


@dataclass
class L1Stats:
    """What the IRLS solver did, for benchmarks, logs and tests.

    ``cg_iterations[k]`` and ``cg_residuals[k]`` describe reweighting pass ``k`` (pass 0 is the exact
    unweighted L2 solve: 0 CG iterations, residual 0). ``cg_residuals`` is the relative preconditioned-CG
    residual ``max_c ‖r_c‖/‖r0_c‖`` over channels when that pass stopped. ``energies[k]`` is the L1 energy
    (sum over terms of the RGB norm of the residual) after pass ``k``.
    """

    iterations: int = 0
    cg_iterations: list[int] = field(default_factory=list)
    cg_residuals: list[float] = field(default_factory=list)
    energies: list[float] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def total_cg_iterations(self) -> int:
        return int(sum(self.cg_iterations))


# --------------------------------------------------------------------------------------------- validation


def _prepare(base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float,
             dtype: type = np.float64) -> tuple[np.ndarray, ...]:
    """Validate inputs and return ``dtype`` (C, H, W) copies (the layout DCTs along the last axes like)."""
    arrays = {"base": np.asarray(base), "dx": np.asarray(dx), "dy": np.asarray(dy)}
    shape = arrays["base"].shape
    if len(shape) not in (2, 3):
        raise ValueError(f"base must be (H, W) or (H, W, C), got shape {shape}")
    if 0 in shape:
        raise ValueError(f"empty image: shape {shape}")
    for name, arr in arrays.items():
        if arr.shape != shape:
            raise ValueError(f"{name} has shape {arr.shape}, expected {shape} (the shape of base)")
        if not np.issubdtype(arr.dtype, np.floating) and not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            raise ValueError(f"{name} contains {bad} non-finite value(s); sanitise them before solving")
    if not (np.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha must be a finite number > 0 (got {alpha}); at 0 the mean is undetermined")
    if alpha < MIN_ALPHA:
        raise ValueError(f"alpha must be at least {MIN_ALPHA:g} (got {alpha:g}): below that the base image's "
                         "weight underflows and the image's mean is undetermined")
    out = []
    for arr in arrays.values():
        a = arr[None] if arr.ndim == 2 else np.moveaxis(arr, -1, 0)
        out.append(np.array(a, dtype=dtype, order="C", copy=True))  # always our own copy (scaled in place)
    return tuple(out)


def _prepare_with_image(image, base, dx, dy, alpha) -> tuple[np.ndarray, ...]:
    """:func:`_prepare` plus a candidate solution of the same shape, for the energy functions."""
    (x, _, _) = _prepare(image, dx, dy, alpha)
    return (x, *_prepare(base, dx, dy, alpha))


def _finish(image: np.ndarray, ndim: int, dtype: np.dtype) -> np.ndarray:
    """(C, H, W) float64 -> caller's layout and dtype; clipped so float32 output can never be ±Inf."""
    if np.dtype(dtype) == np.float32:
        image = np.clip(image, -FLOAT32_MAX, FLOAT32_MAX)
    image = image[0] if ndim == 2 else np.moveaxis(image, 0, -1)
    return np.ascontiguousarray(image, dtype=dtype)


# ------------------------------------------------------------------------------------------- operators


def _grad_x(img: np.ndarray) -> np.ndarray:
    """H_x: forward difference along x; shape (..., H, W-1) (the contract's last column has no term)."""
    return img[..., :, 1:] - img[..., :, :-1]


def _grad_y(img: np.ndarray) -> np.ndarray:
    """H_y: forward difference along y; shape (..., H-1, W)."""
    return img[..., 1:, :] - img[..., :-1, :]


def _div(gx: np.ndarray, gy: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """H_xᵀ gx + H_yᵀ gy (a negative divergence) for gx (..., H, W-1) and gy (..., H-1, W)."""
    out = np.zeros(shape, dtype=gx.dtype)
    out[..., :, :-1] -= gx
    out[..., :, 1:] += gx
    out[..., :-1, :] -= gy
    out[..., 1:, :] += gy
    return out


@lru_cache(maxsize=8)
def _laplacian_eigenvalues(height: int, width: int) -> np.ndarray:
    """Eigenvalues of the Neumann Laplacian HᵀH in the orthonormal DCT-II basis, shape (H, W).

    λ(k, l) = (2 − 2 cos(π l / W)) + (2 − 2 cos(π k / H)); λ(0, 0) = 0 is the constant mode. Cached because
    a frame's layers (and IRLS passes) share it; read-only so a caller cannot corrupt the cache.
    """
    ly = 2.0 - 2.0 * np.cos(np.pi * np.arange(height) / height)
    lx = 2.0 - 2.0 * np.cos(np.pi * np.arange(width) / width)
    lam = ly[:, None] + lx[None, :]
    lam.flags.writeable = False
    return lam


_local = threading.local()


@contextmanager
def fft_workers(workers: int) -> Iterator[None]:
    """Within the block, this thread's DCTs use ``workers`` threads (-1, the default: every core). A caller
    that runs several solves at once (model.reconstruct's concurrent layers) gives each one thread, so that the
    solves share the cores instead of oversubscribing them; the transforms' results do not depend on it."""
    previous = getattr(_local, "workers", -1)
    _local.workers = workers
    try:
        yield
    finally:
        _local.workers = previous


def _dct(a: np.ndarray, overwrite: bool = False) -> np.ndarray:
    return scipy.fft.dctn(a, type=2, axes=(-2, -1), norm="ortho", workers=getattr(_local, "workers", -1),
                          overwrite_x=overwrite)


def _idct(a: np.ndarray, overwrite: bool = False) -> np.ndarray:
    return scipy.fft.idctn(a, type=2, axes=(-2, -1), norm="ortho", workers=getattr(_local, "workers", -1),
                           overwrite_x=overwrite)


def _screened_solve(rhs: np.ndarray, alpha2: float, dc: np.ndarray | None = None) -> np.ndarray:
    """Solve (α² + HᵀH) x = rhs for each channel of rhs (C, H, W) by DCT diagonalisation.

    ``dc`` (C,) optionally overrides the constant-mode coefficient of the transformed right-hand side with an
    exactly computed value: it is divided by α² alone, so at small α any rounding in it is amplified 1/α².
    """
    height, width = rhs.shape[-2:]
    coeffs = _dct(rhs)
    if dc is not None:
        coeffs[:, 0, 0] = dc
    coeffs /= alpha2 + _laplacian_eigenvalues(height, width)
    return _idct(coeffs)


# ------------------------------------------------------------------------------------------------- L2


def _l2_core(base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float) -> np.ndarray:
    """The exact L2 minimiser for float64 (C, H, W) inputs."""
    alpha2 = alpha * alpha
    div = _div(dx[..., :, :-1], dy[..., :-1, :], base.shape)
    rhs = alpha2 * base + div
    # The divergence term sums to zero exactly (H·1 = 0), so the DC coefficient of the rhs is α²·Σ I_b / √N:
    # the solution's mean equals the base image's mean whatever α is.
    n = base.shape[-1] * base.shape[-2]
    dc = alpha2 * base.sum(axis=(-2, -1), dtype=np.float64) / np.sqrt(n)
    return _screened_solve(rhs, alpha2, dc)


def solve_l2(
    base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float = DEFAULT_ALPHA, *, dtype=np.float32
) -> np.ndarray:
    """Exact L2 screened Poisson reconstruction: argmin ‖α(I − base)‖² + ‖H_x I − dx‖² + ‖H_y I − dy‖².

    Arrays are (H, W) or (H, W, C) and channels are independent. The last column of ``dx`` and the last row
    of ``dy`` are ignored (the contract stores 0 there). Computed in float64; returned as ``dtype`` (float32
    by default, clipped to its range; ask for ``np.float64`` to keep full precision). Raises ValueError for
    mismatched shapes, non-finite input or α ≤ 0.
    """
    ndim = np.ndim(base)
    b, gx, gy = _prepare(base, dx, dy, alpha)
    return _finish(_l2_core(b, gx, gy, float(alpha)), ndim, dtype)


def energy_l2(image: np.ndarray, base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float) -> float:
    """‖α(I − base)‖² + ‖H I − g‖², the objective :func:`solve_l2` minimises (float64, for tests)."""
    x, b, gx, gy = _prepare_with_image(image, base, dx, dy, alpha)
    e0, ex, ey = _residuals(x, b, gx, gy, float(alpha))
    return float((e0**2).sum() + (ex**2).sum() + (ey**2).sum())


# ------------------------------------------------------------------------------------------------- L1


def _residuals(
    x: np.ndarray, base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """e = b − P x split into its data (C, H, W), x-gradient (C, H, W-1) and y-gradient (C, H-1, W) blocks."""
    e0 = base - x
    e0 *= alpha
    ex = dx[..., :, :-1] - _grad_x(x)
    ey = dy[..., :-1, :] - _grad_y(x)
    return e0, ex, ey


def _residuals_and_norms(x: np.ndarray, base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float,
                         out: list[np.ndarray] | None = None) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """:func:`_residuals` and their per-term RGB norms; one fused pass when the compiled kernels exist.

    ``out`` (an empty list the first time) keeps the six output buffers for the next call: IRLS consumes the
    previous residuals before asking for new ones, and reusing them saves a frame's worth of fresh pages per
    pass."""
    if not kernels.AVAILABLE:
        residuals = _residuals(x, base, dx, dy, alpha)
        return residuals, tuple(_norm_c(e) for e in residuals)
    c, h, w = x.shape
    if not out:
        out = [] if out is None else out
        out += [np.empty_like(x), np.empty((c, h, w - 1), x.dtype), np.empty((c, h - 1, w), x.dtype),
                np.empty((h, w), x.dtype), np.empty((h, w - 1), x.dtype), np.empty((h - 1, w), x.dtype)]
    kernels.residuals_and_norms(x, base, dx, dy, alpha, tuple(out[:3]), tuple(out[3:]))
    return tuple(out[:3]), tuple(out[3:])


def _mapped(terms: tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]], data_map: np.ndarray | None,
            ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """(residuals, norms) with the data term's residual and norm multiplied by the per-pixel α factor (in place:
    the buffers are recomputed every pass)."""
    if data_map is not None:
        (e0, _, _), (n0, _, _) = terms
        e0 *= data_map
        n0 *= data_map
    return terms


def _norm_c(e: np.ndarray) -> np.ndarray:
    """Per-term norm over channels (‖e‖_RGB): one weight per pixel and term, shared by the channels."""
    return np.sqrt(np.einsum("c...,c...->...", e, e))


def _l1_energy(norms: tuple[np.ndarray, ...]) -> float:
    return float(sum(n.sum(dtype=np.float64) for n in norms))


def energy_l1(image: np.ndarray, base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float) -> float:
    """Σ over terms of ‖residual‖_RGB: the objective :func:`solve_l1` minimises (float64)."""
    x, b, gx, gy = _prepare_with_image(image, base, dx, dy, alpha)
    return _l1_energy(tuple(_norm_c(e) for e in _residuals(x, b, gx, gy, float(alpha))))


def _dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-channel inner products of (C, H, W) arrays as (C, 1, 1) float64, via BLAS (fast and, unlike a
    naive float32 running sum, accurate on a megapixel)."""
    flat_a, flat_b = a.reshape(a.shape[0], -1), b.reshape(b.shape[0], -1)
    return np.array([float(np.dot(flat_a[c], flat_b[c])) for c in range(a.shape[0])])[:, None, None]


def _safe_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num/den, 0 where den is 0 (a channel whose CG has already converged exactly, e.g. all black)."""
    ok = den > 0
    return np.where(ok, num / np.where(ok, den, 1.0), 0.0)


class _WeightedSystem:
    """The normal equations A x = Pᵀ W² b of one IRLS pass, with work buffers reused across CG iterations.

    A = α² W0 + H_xᵀ Wx H_x + H_yᵀ Wy H_y, with one weight per pixel and term shared by the channels.
    """

    def __init__(self, shape: tuple[int, int, int], alpha: float, dtype: np.dtype, preconditioner: str):
        channels, height, width = shape
        self.alpha, self.alpha2, self.dtype = alpha, alpha * alpha, dtype
        self.preconditioner = preconditioner
        self._gx = np.empty((channels, height, width - 1), dtype)
        self._gy = np.empty((channels, height - 1, width), dtype)
        self._denominator = (self.alpha2 + _laplacian_eigenvalues(height, width)).astype(dtype)
        # diag(α² + HᵀH): 4 neighbours inside, fewer on the border; the "dct" preconditioner rescales by it.
        self._diag_l = np.full((height, width), self.alpha2)
        self._scatter_add(self._diag_l, np.ones((height, width - 1)), np.ones((height - 1, width)))

    @staticmethod
    def _scatter_add(out: np.ndarray, wx: np.ndarray, wy: np.ndarray) -> None:
        """out += diag(H_xᵀ Wx H_x + H_yᵀ Wy H_y): each term touches the two pixels it links."""
        out[..., :, :-1] += wx
        out[..., :, 1:] += wx
        out[..., :-1, :] += wy
        out[..., 1:, :] += wy

    def set_weights(self, norms: tuple[np.ndarray, ...], reg: float, data_map: np.ndarray | None = None) -> None:
        """IRLS weights w = 1/(‖e‖ + reg), normalised to mean 1 over all terms (as the reference solver), and
        what the preconditioner needs from them. ``data_map``: solve_l1's per-pixel factor on α (the data
        term's norm in ``norms`` already carries it)."""
        if kernels.AVAILABLE and self.dtype == np.float32:
            # fused kernel; the float64 (small-α) path keeps numpy's pairwise sums: its truncated CG amplifies
            # a 1-ulp change of the weights' normalisation far beyond rounding at small α
            diag_a = self._compiled_weights(norms, reg)
        else:
            w0, wx, wy = (1.0 / (n + reg) for n in norms)
            count = w0.size + wx.size + wy.size
            total = sum(w.sum(dtype=np.float64) for w in (w0, wx, wy))
            scale = self.dtype.type(count / total)
            self.w0, self.wx, self.wy = w0 * scale, wx * scale, wy * scale
            self._a2w0 = self.alpha2 * self.w0
            self._aw0 = self.alpha * self.w0
            diag_a = self._a2w0.astype(np.float64)
            self._scatter_add(diag_a, self.wx, self.wy)
        if data_map is not None:  # α → α·m per pixel: the data term's share of A, of the rhs and of diag(A)
            if getattr(self, "_map_sq", None) is None or self._map_source is not data_map:
                self._map_source, self._map_sq = data_map, data_map * data_map  # m² once per solve, not per pass
            diag_a += self._a2w0 * (self._map_sq - 1)  # in place: these arrays are rebuilt by the next pass
            self._a2w0 *= self._map_sq
            self._aw0 *= data_map
        if self.preconditioner == "dct":
            self._scale = np.sqrt(self._diag_l / diag_a).astype(self.dtype)
        elif self.preconditioner == "mg":
            self._multigrid = Multigrid(self._a2w0, self.wx, self.wy, self._gx.shape[0], diag_a)

    def _compiled_weights(self, norms: tuple[np.ndarray, ...], reg: float) -> np.ndarray:
        """set_weights in one fused kernel, into arrays kept across passes; returns diag(A)."""
        if getattr(self, "_weights", None) is None:
            self._weights = [np.empty_like(n) for n in norms] + [np.empty_like(norms[0]) for _ in range(3)]
            self._diag_l = self._diag_l.astype(self.dtype)
        self.w0, self.wx, self.wy, self._a2w0, self._aw0, diag_a = self._weights
        kernels.irls_weights(tuple(norms), reg, self.alpha, tuple(self._weights))
        return diag_a

    def buffer(self, name: str, like: np.ndarray) -> np.ndarray:
        """A work array shaped like ``like``, kept across IRLS passes (fresh pages cost as much as the pass's
        arithmetic). Callers must be done with the previous pass's content: d is added to x before the next
        pass, and ap/tmp/p are scratch."""
        buffers = self.__dict__.setdefault("_buffers", {})
        if name not in buffers:
            buffers[name] = np.empty_like(like)
        return buffers[name]

    def rhs(self, e0: np.ndarray, ex: np.ndarray, ey: np.ndarray) -> np.ndarray:
        """Pᵀ W² e: the normal-equation residual at the current iterate (CG then solves for the update)."""
        if kernels.AVAILABLE:
            if getattr(self, "_rhs", None) is None:
                self._rhs = np.empty_like(e0)  # reused: _pcg consumes it (its r) before the next pass asks
            return kernels.weighted_rhs(e0, ex, ey, self._aw0, self.wx, self.wy, self._rhs)
        out = self._aw0 * e0
        np.multiply(ex, self.wx, out=self._gx)
        np.multiply(ey, self.wy, out=self._gy)
        self._scatter_div(out)
        return out

    def _scatter_div(self, out: np.ndarray) -> None:
        """out += H_xᵀ gx + H_yᵀ gy for the gradients held in the work buffers."""
        out[..., :, :-1] -= self._gx
        out[..., :, 1:] += self._gx
        out[..., :-1, :] -= self._gy
        out[..., 1:, :] += self._gy

    def apply(self, p: np.ndarray, out: np.ndarray) -> np.ndarray:
        """out = A p, without temporaries beyond the two gradient buffers (one fused pass when compiled)."""
        if kernels.AVAILABLE:
            return kernels.weighted_apply(p, self._a2w0, self.wx, self.wy, out)
        np.subtract(p[..., :, 1:], p[..., :, :-1], out=self._gx)
        self._gx *= self.wx
        np.subtract(p[..., 1:, :], p[..., :-1, :], out=self._gy)
        self._gy *= self.wy
        np.multiply(p, self._a2w0, out=out)
        self._scatter_div(out)
        return out

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """z ≈ A⁻¹ r: the multigrid V-cycle, or the exact unweighted DCT solve rescaled symmetrically by
        √(diag L / diag A), so that it is exact when the weights are uniform and tracks their local magnitude when
        they are not."""
        if self.preconditioner == "mg":
            return self._multigrid.vcycle(r)
        scaled = np.multiply(r, self._scale, out=self.buffer("scaled", r))  # kept: no fresh pages per step
        coeffs = _dct(scaled, overwrite=True)
        coeffs /= self._denominator
        z = _idct(coeffs, overwrite=True)
        z *= self._scale
        return z


def _pcg(
    system: _WeightedSystem, r: np.ndarray, max_iter: int, tol: float
) -> tuple[np.ndarray, int, float]:
    """Preconditioned CG for A d = r from d = 0, one independent CG per channel, vectorised over channels.

    Stops when every channel's residual norm has dropped below ``tol`` relative to its start, or after
    ``max_iter`` iterations. Returns (d, iterations, worst relative residual). ``r`` is consumed.
    """
    d = system.buffer("d", r)
    d.fill(0)
    r0 = np.sqrt(_dots(r, r))
    if not np.any(r0 > 0):
        return d, 0, 0.0
    ap, tmp, p = system.buffer("ap", r), system.buffer("tmp", r), system.buffer("p", r)
    z = system.precondition(r)
    np.copyto(p, z)
    rz = _dots(r, z)
    rel, it = 1.0, 0
    while it < max_iter:
        system.apply(p, out=ap)
        step = _safe_div(rz, _dots(p, ap)).astype(r.dtype)
        if kernels.AVAILABLE:  # both updates and ‖r‖² in one pass
            rr = np.empty(r.shape[0])
            kernels.cg_update(d, r, p, ap, np.ascontiguousarray(step.ravel()), rr)
            rr = rr[:, None, None]
        else:
            d += np.multiply(p, step, out=tmp)
            r -= np.multiply(ap, step, out=tmp)
            rr = _dots(r, r)
        it += 1
        rel = float(np.max(_safe_div(np.sqrt(rr), r0)))
        if rel <= tol or it == max_iter:
            break
        z = system.precondition(r)
        rz_new = _dots(r, z)
        p *= _safe_div(rz_new, rz).astype(r.dtype)
        p += z
        rz = rz_new
    return d, it, rel


PRECONDITIONERS = ("dct", "mg")
#: IRLS passes of the ``l1`` method (pass 0, the exact L2 start, included) and DCT-PCG steps per pass. The
#: reference solver's preset runs 20 passes of 50 plain CG steps; this budget reached the same mean RelMSE on
#: held-out rendered layers at a fraction of the time. The truncated CG regularises: more steps or passes are not
#: uniformly better on rendered frames.
L1_PASSES = 8
L1_CG_STEPS = 2
# IRLS iterates in float32 (half the memory traffic, faster DCTs) unless α is small: the constant mode's eigenvalue
# is ~α², so float32 rounding lets the image mean drift by ~eps32/α²; below this threshold the iteration runs in
# float64.
FLOAT32_MIN_ALPHA = 1e-2


@dataclass(frozen=True)
class L1Options:
    """How :func:`solve_l1` runs IRLS; the defaults are the ``l1`` method's budget.

    ``iterations`` counts passes as the reference solver does: pass 0 is the unweighted (L2) problem, solved
    exactly; passes k = 1 … iterations−1 reweight each residual term by ``1/(‖e‖_RGB + reg_k)``,
    ``reg_k = reg_init·reg_decay^(k−1)`` (radiance units, as in the reference), and take up to ``cg_iterations``
    preconditioned CG steps from the previous iterate, stopping early once the residual fell by ``cg_tolerance``.
    ``preconditioner``: ``"dct"`` (diagonally rescaled DCT solve, the default) or ``"mg"`` (multigrid V-cycle).
    ``dtype``: the returned image's (float32 or float64).
    Raises ValueError for non-positive counts, a bad regularisation schedule or an unknown preconditioner.
    """

    iterations: int = L1_PASSES
    cg_iterations: int = L1_CG_STEPS
    cg_tolerance: float = 1e-3
    reg_init: float = 0.05
    reg_decay: float = 0.5
    preconditioner: str = "dct"
    dtype: type = np.float32

    def __post_init__(self) -> None:
        if self.iterations < 1 or self.cg_iterations < 1:
            raise ValueError(f"iterations and cg_iterations must be >= 1 (got {self.iterations}, "
                             f"{self.cg_iterations})")
        if not (self.reg_init > 0 and 0 < self.reg_decay <= 1):
            raise ValueError(f"need reg_init > 0 and 0 < reg_decay <= 1 (got {self.reg_init}, {self.reg_decay})")
        if self.preconditioner not in PRECONDITIONERS:
            raise ValueError(f"preconditioner must be one of {PRECONDITIONERS}, got {self.preconditioner!r}")


def solve_l1(base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float = DEFAULT_ALPHA,
             options: L1Options = L1Options(), *, alpha_map: np.ndarray | None = None,
             start_alpha: float | None = None) -> tuple[np.ndarray, L1Stats]:
    """L1 screened Poisson reconstruction by IRLS: argmin Σ‖α(I − base)‖ + Σ‖(H_x I − dx, H_y I − dy)‖.

    ``options`` (:class:`L1Options`) sets the passes, the CG budget, the reweighting and the output dtype. The
    channels of an (H, W, C) input share weights (the norm is over channels), so pass a layer's RGB together.
    Iterates in float32, or float64 when α < FLOAT32_MIN_ALPHA.
    ``alpha_map`` (H, W), finite and > 0: a per-pixel factor m(x) on the data term's α in the IRLS passes,
    Σ α·m(x)‖I − base‖ (model/refine.py's trust rule leans on the base more or less per pixel). Pass 0 (the L2
    start, a DCT solve) keeps the scalar α, or takes ``start_alpha`` (a DCT solve needs one α: model/refine.py
    starts a clean layer at its map's clean α); an all-ones map gives the solve without it.
    Returns the image and :class:`L1Stats`. Raises ValueError like :func:`solve_l2` and for a bad ``alpha_map``
    or ``start_alpha``.
    """
    start = time.perf_counter()
    ndim = np.ndim(base)
    _check_map(alpha_map, np.shape(base)[:2])
    alpha = float(alpha)
    if start_alpha is None:
        start_alpha = alpha  # (validated with the inputs below)
    elif not (np.isfinite(start_alpha) and start_alpha >= MIN_ALPHA):
        raise ValueError(f"start_alpha must be a finite number >= {MIN_ALPHA:g}, got {start_alpha}")
    work = np.dtype(np.float32 if min(alpha, start_alpha) >= FLOAT32_MIN_ALPHA else np.float64)
    b, gx, gy = _prepare(base, dx, dy, alpha, work.type)  # straight into the working precision: no float64 detour
    # IRLS is scale-covariant (inputs × s and reg × s give the solution × s), so iterate on inputs scaled to
    # max |value| = 1 with reg scaled alike: float32 can then neither overflow nor go subnormal. The L2 start is
    # linear, so it is solved on the scaled inputs too, in the working precision (its DCTs cost half in float32).
    scale = max(float(np.abs(a).max()) for a in (b, gx, gy)) or 1.0
    for a in (b, gx, gy):
        a /= work.type(scale)
    x = _l2_core(b, gx, gy, start_alpha)
    data_map = None if alpha_map is None else np.ascontiguousarray(alpha_map, work.type)
    stats = _irls(x, (b, gx, gy), alpha, options, data_map, scale)
    stats.seconds = time.perf_counter() - start
    return _finish_l1(x, scale, ndim, options.dtype), stats


def _check_map(alpha_map: np.ndarray | None, shape: tuple[int, ...]) -> None:
    """ValueError unless ``alpha_map`` is None or an (H, W) array, finite and > 0 everywhere."""
    if alpha_map is None:
        return
    alpha_map = np.asarray(alpha_map)
    if alpha_map.shape != shape:
        raise ValueError(f"alpha_map must be (H, W) = {shape}, got {alpha_map.shape}")
    if not (np.all(np.isfinite(alpha_map)) and np.all(alpha_map > 0)):
        raise ValueError("alpha_map must be finite and > 0 everywhere")


def _irls(x: np.ndarray, data: tuple[np.ndarray, np.ndarray, np.ndarray], alpha: float, options: L1Options,
          data_map: np.ndarray | None, scale: float) -> L1Stats:
    """The IRLS passes on the scaled problem ``data`` = (base, dx, dy), updating ``x`` (pass 0's image) in place."""
    b, gx, gy = data
    system = _WeightedSystem(x.shape, alpha, b.dtype, options.preconditioner)
    stats = L1Stats()
    buffers: list[np.ndarray] = []
    residuals, norms = _mapped(_residuals_and_norms(x, b, gx, gy, alpha, buffers), data_map)
    stats.cg_iterations.append(0)
    stats.cg_residuals.append(0.0)
    stats.energies.append(_l1_energy(norms) * scale)
    for k in range(1, options.iterations):
        reg = options.reg_init * options.reg_decay ** (k - 1) / scale
        system.set_weights(norms, reg=reg, data_map=data_map)
        delta, it, rel = _pcg(system, system.rhs(*residuals), options.cg_iterations, options.cg_tolerance)
        x += delta
        residuals, norms = _mapped(_residuals_and_norms(x, b, gx, gy, alpha, buffers), data_map)
        stats.cg_iterations.append(it)
        stats.cg_residuals.append(rel)
        stats.energies.append(_l1_energy(norms) * scale)
    stats.iterations = options.iterations
    return stats


def _finish_l1(x: np.ndarray, scale: float, ndim: int, dtype: type) -> np.ndarray:
    """The scaled iterate back at the input's scale, in the caller's layout and dtype."""
    if np.dtype(dtype) == np.float32 and x.dtype == np.float32 and float(np.abs(x).max()) * scale < FLOAT32_MAX / 2:
        x *= np.float32(scale)  # the common case: no float64 detour (a copy and two passes over the image)
        return _finish(x, ndim, dtype)
    return _finish(x.astype(np.float64) * scale, ndim, dtype)
