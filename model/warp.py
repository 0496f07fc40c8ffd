"""Where a neighbouring frame's pixels lie under frame t's: bilinear sampling at fractional positions, and the
chain of motion vectors from frame t to a frame several steps away (model/temporal.py's step 1)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gradsep.model import kernels
from gradsep.model.frame import Frame

#: A neighbour's gradient between two pixels is used where their positions in the neighbour are one pixel apart
#: within this many pixels (they move together; not across a silhouette).
STEADY_TOLERANCE = 0.25


def grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's (row, column), float32 (H, W) each."""
    rows = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    cols = np.broadcast_to(np.arange(w, dtype=np.float32)[None, :], (h, w))
    return rows, cols


class Sampler:
    """Bilinear sampling of (H, W[, C]) images at fractional (rows, cols); ``valid`` says where it is defined.

    Kept compact, as the top-left tap's flat index and the fractions, since a shot keeps a sampler per neighbour
    of every first stage still to be blended; the four taps and weights are derived per call, in one compiled
    pass (model.kernels.bilinear) or, without numba, in numpy with the same arithmetic."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray, valid: np.ndarray) -> None:
        h, w = rows.shape
        grid_r, grid_c = grid(h, w)
        if np.array_equal(rows, grid_r) and np.array_equal(cols, grid_c):  # no motion: nothing to resample
            self.valid, self.identity, self.integral = np.asarray(valid, bool), True, True
            return
        finite = np.isfinite(rows) & np.isfinite(cols)
        rows = np.where(finite, rows, -1.0)
        cols = np.where(finite, cols, -1.0)
        inside = (rows >= 0) & (rows <= h - 1) & (cols >= 0) & (cols <= w - 1)
        self.valid = np.asarray(valid, bool) & finite & inside
        r, c = np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)
        r0, c0 = np.floor(r), np.floor(c)
        self.fr, self.fc = (r - r0).astype(np.float32).ravel(), (c - c0).astype(np.float32).ravel()
        self.integral = not (self.fr.any() or self.fc.any())
        self.identity = False
        self._positions: tuple[np.ndarray, np.ndarray] | None = (rows, cols)  # for steady(), then dropped
        self._steady: tuple[np.ndarray, np.ndarray] | None = None
        index = r0.astype(np.intp) * w + c0.astype(np.intp)
        self.index = index.ravel().astype(np.int32 if h * w < 2**31 else np.intp)

    def steady(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Per axis (dx, dy), bool (H, W): where a pixel's position and the next pixel's along that axis are
        within STEADY_TOLERANCE of one pixel apart (the two move together); None for no motion."""
        if self.identity:
            return None
        if self._steady is None and self._positions is not None:
            rows, cols = self._positions
            out = []
            for along, across, axis in ((cols, rows, 1), (rows, cols, 0)):
                step = np.diff(along, axis=axis) - 1.0
                drift = np.diff(across, axis=axis)
                ok = (np.abs(step) <= STEADY_TOLERANCE) & (np.abs(drift) <= STEADY_TOLERANCE)
                pad = ((0, 0), (0, 1)) if axis == 1 else ((0, 1), (0, 0))
                out.append(np.pad(ok, pad, constant_values=True))
            self._steady, self._positions = (out[0], out[1]), None
        return self._steady

    def on_grid(self, tolerance: float) -> np.ndarray:
        """(H, W) bool: valid, at a pixel of the neighbour within ``tolerance`` on both axes."""
        if self.integral:
            return self.valid
        near = [(f <= tolerance) | (f >= 1 - tolerance) for f in (self.fr, self.fc)]
        return self.valid & (near[0] & near[1]).reshape(self.valid.shape)

    def nearest(self) -> Sampler:
        """These positions rounded to the nearest pixel, each of the neighbour's pixels taken once: where several of
        frame t's pixels round to one, the nearest of them keeps it and the others are invalid.

        A neighbour's noisy inputs are taken whole this way: a bilinear tap mixes four pixels' noise, which is then
        correlated between frame t's pixels (and a denoiser keeps correlated noise as detail); a pixel taken twice
        would be correlated with itself. No motion, or motion by whole pixels: this sampler itself."""
        if self.integral:
            return self
        h, w = self.valid.shape
        index = self.index.astype(np.intp)
        up, right = self.fr >= 0.5, self.fc >= 0.5
        rows = np.minimum(index // w + up, h - 1)
        cols = np.minimum(index % w + right, w - 1)
        flat = rows * w + cols
        distance = np.where(up, 1 - self.fr, self.fr) ** 2 + np.where(right, 1 - self.fc, self.fc) ** 2
        valid = self.valid.ravel()
        candidates = np.flatnonzero(valid)
        nearest = np.full(h * w, np.inf, np.float32)
        np.minimum.at(nearest, flat[candidates], distance[candidates])
        candidates = candidates[distance[candidates] <= nearest[flat[candidates]]]
        first = np.full(h * w, h * w, np.intp)  # a tie: the first of frame t's pixels in raster order keeps it
        np.minimum.at(first, flat[candidates], candidates)
        keep = np.zeros(h * w, bool)
        keep[candidates[first[flat[candidates]] == candidates]] = True
        out = object.__new__(Sampler)  # whole pixels, but never the identity: its valid pixels are still to be kept
        out.valid, out.identity, out.integral = keep.reshape(h, w), False, True
        out.index = flat.astype(self.index.dtype)
        out.fr = out.fc = np.zeros(h * w, np.float32)
        out._positions = (rows.reshape(h, w).astype(np.float32), cols.reshape(h, w).astype(np.float32))
        out._steady = None
        return out

    def __call__(self, image: np.ndarray, squared: bool = False) -> np.ndarray:
        """``image`` at the positions; ``squared`` weights by the squared bilinear weights (a variance's warp)."""
        if self.identity:
            return image
        shape = image.shape
        flat = np.ascontiguousarray(image).reshape(shape[0] * shape[1], -1)
        if self.integral:
            if kernels.AVAILABLE and flat.dtype == np.float32:
                return kernels.gather(flat, self.index, np.empty((self.index.shape[0], flat.shape[1]),
                                                                 np.float32)).reshape(shape)
            return np.take(flat, self.index, axis=0).reshape(shape)
        if kernels.AVAILABLE and flat.dtype == np.float32:
            out = np.empty(flat.shape, np.float32)
            kernels.bilinear(flat, self.index, self.fr, self.fc, shape[1], squared, out)
            return out.reshape(shape)
        out = np.zeros(flat.shape, np.float32)
        for taps, weight in self._taps(shape[0], shape[1]):
            tap = np.take(flat, taps, axis=0)
            tap *= weight * weight if squared else weight
            out += tap
        return out.reshape(shape).astype(image.dtype, copy=False)

    def _taps(self, h: int, w: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """The four taps' flat indices and (N, 1) weights (the numpy path)."""
        i00 = self.index.astype(np.intp)
        i01 = np.where(i00 % w + 1 < w, i00 + 1, i00)
        down = np.where(i00 // w + 1 < h, w, 0)
        fr, fc = self.fr[:, None], self.fc[:, None]
        return [(i00, (1 - fr) * (1 - fc)), (i01, (1 - fr) * fc), (i00 + down, fr * (1 - fc)),
                (i01 + down, fr * fc)]


def chain(frames: Sequence[Frame | None], centre: int, offset: int) -> Sampler | None:
    """Where frame ``centre + offset``'s pixels lie under frame ``centre``'s, by the chain of motion vectors
    between them; None when a frame of the chain is missing or has no vectors that way."""
    return chains(frames, centre, [offset])[offset]


def chains(frames: Sequence[Frame | None], centre: int, offsets: Sequence[int]) -> dict[int, Sampler | None]:
    """:func:`chain` for each of ``offsets``, each direction followed once: the chain to frame t ± 2 continues the
    chain to t ± 1 rather than starting again."""
    h, w = frames[centre].height, frames[centre].width  # type: ignore[union-attr]
    grid_r, grid_c = grid(h, w)
    out: dict[int, Sampler | None] = {o: None for o in offsets}
    for step in (-1, 1):
        want = {o for o in offsets if o * step > 0}
        direction = "backward" if step < 0 else "forward"
        rows, cols = grid_r, grid_c
        sampler = Sampler(rows, cols, np.ones((h, w), bool))  # where frame t's pixels lie in the frame reached
        index = centre
        for distance in range(1, max((abs(o) for o in want), default=0) + 1):
            frame = frames[index]
            motion = getattr(frame, "motion", None) if frame is not None else None
            if motion is None or getattr(motion, direction) is None or frames[index + step] is None:
                break  # this offset and every further one: None
            src_rows, src_cols, src_valid = motion.warp_source(direction)
            rows = rows + sampler(np.asarray(src_rows, np.float32) - grid_r)
            cols = cols + sampler(np.asarray(src_cols, np.float32) - grid_c)
            sampler = Sampler(rows, cols, sampler.valid & (np.rint(sampler(np.asarray(src_valid, np.float32))) > 0.5))
            index += step
            if distance * step in want:
                out[distance * step] = sampler
    return out
