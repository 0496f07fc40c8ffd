"""The network's input transform: the ONE definition shared by training and inference.

Training (training/dataset.py, training/losses.py) and inference (model/infer.py) both call these functions, so
the network sees exactly the same numbers in both. The math is written once against a tiny array namespace
(numpy or torch: both provide ``log1p``, ``expm1``, ``sign``, ``abs``, ``clip``, ``concatenate``), so
inference needs only numpy and the training loss differentiates the very same expressions in torch. This
module never imports torch.

What the network sees (channel order in DATA_INPUTS / GRADIENT_INPUTS below):

* base radiance, clamped to [0, RADIANCE_MAX], through C(I) = log(1 + μI) / log(1 + μ) with μ = 16 (GradNet's
  transfer function: compresses HDR fireflies while keeping dark regions resolved);
* the layer's robust screened Poisson reconstruction (``poisson_prior``) through the same C: the network
  predicts a correction to it;
* gradients through the signed version sign(g)·C(|g|), |g| clamped at RADIANCE_MAX;
* albedo as is (clipped to [0, 1], the contract's range), normal·0.5 + 0.5 (in [0, 1]), depth clamped to
  [0, DEPTH_MAX] and min-max normalised per frame to [0, 1];
* non-finite values anywhere → 0 (features always, as the paper does; radiance here too, so a caller that
  bypassed model.exr_read's policy still gets finite output).

The network predicts C(I) of the reconstruction; ``TRANSFER.inverse`` maps it back, clamped to
[0, RADIANCE_MAX] so the output is always finite and ≥ 0.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from gradsep.model.frame import FLOAT32_MAX
from gradsep.model.poisson import L1Options, solve_l1
from gradsep.model.policy import DEFAULT_ALPHA
from gradsep.model.robust import robust_level

if TYPE_CHECKING:  # only for hints; importing model.frame at run time is fine but not needed
    from gradsep.model.frame import Features, Layer

#: Transfer-function steepness (GradNet's μ).
MU = 16.0
#: Radiance (and |gradient|) clamp: the largest finite half float, so anything a half EXR can hold passes
#: unchanged while +Inf-like outliers stay bounded in the network's range (C(65504) ≈ 4.89).
RADIANCE_MAX = 65504.0
#: Depth clamp before per-frame normalisation (GradNet's 1e5): a far-away sky hit must not squash the rest.
DEPTH_MAX = 1.0e5
#: The Poisson prior the network refines: a truncated IRLS, which scored no worse than the converged solve on held-out
#: procedural frames (docs/decisions.md), screened by α. α is a property of each model (ONNX metadata
#: ``gradsep.prior_alpha``, TrainConfig.prior_alpha): PRIOR_ALPHA is what `gradsep train` uses, UNRECORDED_PRIOR_ALPHA
#: what a model without the key was trained with (the `l1`/`l2` methods' α).
PRIOR_ALPHA = DEFAULT_ALPHA
UNRECORDED_PRIOR_ALPHA = DEFAULT_ALPHA
PRIOR_IRLS_PASSES = 5
PRIOR_CG_STEPS = 2
#: Inference uses exactly this budget for ``l1`` models, as they were trained (every cheaper budget served a worse
#: image on held-out frames). The rest of the prior's solve is pinned to what the models were trained with.
PRIOR_REG_INIT = 0.05
PRIOR_REG_DECAY = 0.5
PRIOR_CG_TOLERANCE = 1e-3
PRIOR_PRECONDITIONER = "dct"
#: Frames taller than this are solved in horizontal bands (each extended by PRIOR_BAND_OVERLAP rows on both
#: sides, blended linearly where they overlap) so the solver's working memory, proportional to the pixels solved
#: at once, stays bounded on very large frames. The screening term confines a pixel's influence to ~1/α pixels,
#: but the truncated CG's step sizes and the IRLS weight normalisation are global, so bands differ slightly from
#: a whole-frame solve (tests/model/test_preprocess.py bounds it); frames up to PRIOR_BAND_ROWS + 2 ×
#: PRIOR_BAND_OVERLAP rows, every training frame included, are solved whole.
PRIOR_BAND_ROWS = 1024
PRIOR_BAND_OVERLAP = 64
#: Number of linear planes per layer (base, dx, dy, prior × RGB) and of normalised feature planes.
LAYER_PLANES = 12
FEATURE_PLANES = 7
#: The measured part of the layer planes (base, dx, dy × RGB): what the training losses compare with.
MEASURED_PLANES = 9
#: The network's input and output channels, in order: data, not code (exported as ONNX metadata and checked
#: by model/infer.py against each model it loads).
DATA_INPUTS: tuple[str, ...] = (
    "base.R", "base.G", "base.B",
    "prior.R", "prior.G", "prior.B",
    "albedo.R", "albedo.G", "albedo.B",
    "normal.X", "normal.Y", "normal.Z",
    "depth.Z",
)
GRADIENT_INPUTS: tuple[str, ...] = ("dx.R", "dx.G", "dx.B", "dy.R", "dy.G", "dy.B")
OUTPUTS: tuple[str, ...] = ("R", "G", "B")
#: The feature channels the first-order loss differentiates (the data input minus the radiance planes).
FEATURE_INPUTS: tuple[str, ...] = DATA_INPUTS[6:]
#: Where C(prior) sits in the data input: the network predicts a correction to it (model/network.py).
PRIOR_CHANNELS = slice(3, 6)
#: What C(prior) is, stored as ONNX metadata ``gradsep.prior`` (absent on the shipped models): the truncated robust
#: Poisson solve above (PRIOR_IRLS_PASSES x PRIOR_CG_STEPS, DCT-preconditioned), kind ``l1``. A model naming any
#: other kind is refused at load (model/infer.py): this code could not compute the prior it was trained on.
PRIOR_KINDS: tuple[str, ...] = ("l1",)
#: The kind a model without ``gradsep.prior`` metadata refines (every shipped network model).
DEFAULT_PRIOR = "l1"
#: The ``fused`` blend models see every layer at a normalised exposure: base, gradients and candidates multiplied by s
#: so that OIDN's image's robust level (model.robust.robust_level) is FUSED_MEAN (capped so its peak stays below
#: RADIANCE_MAX / FUSED_PEAK_MARGIN), and the blend divided by s (model/fused.py; ONNX metadata ``gradsep.exposure``
#: = ``oidn-mean``). The model is then the same for a frame at 1e-8 or 1e9 radiance, and HDR values are never
#: clipped by the transfer's range.
FUSED_MEAN = 0.5
FUSED_PEAK_MARGIN = 16.0
#: Bumped whenever the numbers the network sees change; stored in checkpoints, caches and ONNX metadata.
PREPROCESS_VERSION = 3

Window = tuple[int, int, int, int]  # (y0, y1, x0, x1), half-open, in frame pixels


def array_namespace(x: Any) -> ModuleType:
    """numpy for numpy arrays and scalars, torch for torch tensors (without importing torch ourselves)."""
    if type(x).__module__.startswith("torch"):
        return sys.modules["torch"]
    return np


class LogTransfer:
    """C(I) = log(1 + μI) / log(1 + μ) with its inverse and the signed variant for gradients.

    A class with forward/inverse (like OIDN's transfer functions) so the constants travel together and the
    ONNX metadata can state them.
    """

    def __init__(self, mu: float = MU, max_value: float = RADIANCE_MAX) -> None:
        if not (mu > 0 and max_value > 0):
            raise ValueError(f"LogTransfer needs mu > 0 and max_value > 0, got {mu}, {max_value}")
        self.mu = float(mu)
        self.max_value = float(max_value)
        self._norm = math.log1p(self.mu)
        self.max_encoded = math.log1p(self.mu * self.max_value) / self._norm

    def forward(self, x: Any) -> Any:
        """Radiance → network domain; negative radiance is clamped to 0 first."""
        xp = array_namespace(x)
        return xp.log1p(self.mu * xp.clip(x, 0.0, self.max_value)) / self._norm

    def inverse(self, y: Any, clamp_negative: bool = True) -> Any:
        """Network domain → radiance, clamped to [0, max_value] so the result is finite.

        ``clamp_negative=False`` (training losses only) keeps the smooth continuation below 0, which is bounded
        by −1/μ: a clamp there would zero the gradient of a pixel the network currently predicts as negative,
        and that pixel could never be pulled back up.
        """
        xp = array_namespace(y)
        lo = 0.0 if clamp_negative else None
        return xp.expm1(xp.clip(y, lo, self.max_encoded) * self._norm) / self.mu

    def forward_into(self, dst: np.ndarray, src: np.ndarray) -> np.ndarray:
        """:meth:`forward` of numpy float32 ``src`` written into ``dst`` (may be ``src``): the same float32
        operations in the same order, so bit-for-bit its numbers, without temporaries (inference)."""
        np.clip(src, 0.0, self.max_value, out=dst)
        dst *= self.mu
        np.log1p(dst, out=dst)
        dst /= self._norm
        return dst

    def inverse_into(self, dst: np.ndarray, src: np.ndarray) -> np.ndarray:
        """:meth:`inverse` (negatives clamped) of numpy float32 ``src`` written into ``dst`` (may be ``src``),
        bit-for-bit its numbers."""
        np.clip(src, 0.0, self.max_encoded, out=dst)
        dst *= self._norm
        np.expm1(dst, out=dst)
        dst /= self.mu
        return dst

    def forward_signed(self, g: Any) -> Any:
        """sign(g)·C(|g|): the gradient transform (odd, so a sign flip of the image flips the input)."""
        xp = array_namespace(g)
        return xp.sign(g) * self.forward(xp.abs(g))

    def inverse_signed(self, y: Any) -> Any:
        xp = array_namespace(y)
        return xp.sign(y) * self.inverse(xp.abs(y))

    def constants(self) -> dict[str, float]:
        return {"mu": self.mu, "max_value": self.max_value}


TRANSFER = LogTransfer()


# ---------------------------------------------------------------------------------------------------------------
# Frame → linear planes (numpy): sanitised, clamped, channel-first, optionally a window of the frame
# ---------------------------------------------------------------------------------------------------------------


def _crop(image: np.ndarray, window: Window | None) -> np.ndarray:
    if window is None:
        return image
    y0, y1, x0, x1 = window
    return image[y0:y1, x0:x1]


def _finite(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """float32 copy with NaN → 0, ±Inf → the nearest bound, everything clipped to [lo, hi]."""
    out = np.array(x, dtype=np.float32)  # always a copy: sanitised in place below
    return _sanitise_inplace(out, lo, hi)


def _sanitise_inplace(out: np.ndarray, lo: float, hi: float) -> np.ndarray:
    np.nan_to_num(out, copy=False, nan=0.0, posinf=hi, neginf=lo)
    return np.clip(out, lo, hi, out=out)


def _channels_first(dst: np.ndarray, src: np.ndarray, lo: float, hi: float) -> None:
    """Write an (h, w, c) image into a (c, h, w) slice of a preallocated array, sanitised: one strided copy
    and two in-place passes instead of several temporaries (this runs on every inference)."""
    np.copyto(dst, np.moveaxis(np.asarray(src), -1, 0), casting="unsafe")
    _sanitise_inplace(dst, lo, hi)


def poisson_prior(layer: Layer, band_rows: int = PRIOR_BAND_ROWS, band_overlap: int = PRIOR_BAND_OVERLAP,
                  planes: np.ndarray | None = None, alpha: float = PRIOR_ALPHA) -> np.ndarray:
    """(h, w, 3) float32: a robust screened Poisson reconstruction of the whole layer (model.poisson.solve_l1,
    screened by ``alpha``, the model's; PRIOR_IRLS_PASSES passes of PRIOR_CG_STEPS CG steps) from its sanitised
    planes, clipped to [0, RADIANCE_MAX].

    The network refines this instead of the raw base image: the solver integrates the gradients globally,
    which a CPU-trained U-Net with a small receptive field learns slowly, and its reweighting discards the
    outliers an L2 solve would smear. It is a whole-layer solve (in overlapping bands for tall frames, see
    PRIOR_BAND_ROWS), so it is computed once per layer and windows (tiles, patches) crop it.

    ``planes``: the whole layer's ``measured_planes`` when the caller has them (inference does): the same
    sanitised numbers, already channels-first, so the solver copies them contiguously instead of transposing
    three sanitised copies of its own (the result is bit-for-bit the same).
    """
    height, width = layer.base.shape[:2]
    if planes is not None:
        if planes.shape[0] < MEASURED_PLANES or planes.shape[1:] != (height, width):
            raise ValueError(f"planes {planes.shape} are not the measured planes of a {height}x{width} layer")
        base, dx, dy = (planes[i:i + 3].transpose(1, 2, 0) for i in (0, 3, 6))
    else:
        base = _finite(layer.base, 0.0, RADIANCE_MAX)
        dx = _finite(layer.dx, -RADIANCE_MAX, RADIANCE_MAX)
        dy = _finite(layer.dy, -RADIANCE_MAX, RADIANCE_MAX)
    if height <= band_rows + 2 * band_overlap:
        return _solve_prior(base, dx, dy, alpha)
    out = np.zeros((height, width, 3), np.float32)
    weight = np.zeros((height, 1, 1), np.float32)
    for core in range(0, height, band_rows):
        y0, y1 = max(0, core - band_overlap), min(height, core + band_rows + band_overlap)
        band_dy = dy[y0:y1].copy()
        band_dy[-1] = 0.0  # the band's last row has no neighbour below inside the band (as the contract's)
        w = _band_ramp(y0, y1, height, band_overlap)
        out[y0:y1] += _solve_prior(base[y0:y1], dx[y0:y1], band_dy, alpha) * w
        weight[y0:y1] += w
    return out / weight


def _band_ramp(y0: int, y1: int, height: int, overlap: int) -> np.ndarray:
    """(y1 − y0, 1, 1) blending weights: 1 inside, a linear ramp over the rows shared with a neighbour band."""
    rows = np.arange(y0, y1, dtype=np.float32)
    w = np.ones_like(rows)
    if y0 > 0:
        w = np.minimum(w, (rows - y0 + 1) / (2 * overlap + 1))
    if y1 < height:
        w = np.minimum(w, (y1 - rows) / (2 * overlap + 1))
    return w[:, None, None]


def prior_options() -> L1Options:
    """The prior's IRLS settings, every one named: the models were trained on exactly this solve, whatever the
    ``l1`` method's defaults (model.poisson.L1Options)."""
    return L1Options(iterations=PRIOR_IRLS_PASSES, cg_iterations=PRIOR_CG_STEPS, cg_tolerance=PRIOR_CG_TOLERANCE,
                     reg_init=PRIOR_REG_INIT, reg_decay=PRIOR_REG_DECAY, preconditioner=PRIOR_PRECONDITIONER)


def _solve_prior(base: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float) -> np.ndarray:
    prior, _ = solve_l1(base, dx, dy, alpha, prior_options())
    return _sanitise_inplace(prior, 0.0, RADIANCE_MAX)


def prior_exposure(prior: np.ndarray) -> float:
    """The ``fused`` models' exposure s (see FUSED_MEAN): robust_level(prior·s) = FUSED_MEAN (model.robust: a
    winsorised mean one pixel cannot move), 1.0 for a black prior.

    Float64 statistics: a 1e9-radiance frame's sum overflows nothing, a 1e-8 one underflows nothing.
    """
    if prior.size == 0:
        return 1.0
    level = robust_level(prior)  # one pixel cannot move it; the peak cap binds only on frames of extreme range
    peak = float(np.max(prior))
    if not (math.isfinite(level) and level > 0.0 and math.isfinite(peak)):
        return 1.0
    return min(FUSED_MEAN / level, RADIANCE_MAX / FUSED_PEAK_MARGIN / peak)




def scaled_image(image: np.ndarray, scale: float) -> np.ndarray:
    """float32 ``image × scale``, the product taken in float64 and rounded once (exact for a power of two) and
    clipped to float32's range, so a scale near either end of it never overflows to ±Inf."""
    return np.clip(np.asarray(image, np.float64) * scale, -FLOAT32_MAX, FLOAT32_MAX).astype(np.float32)


def scaled_layer(layer: Layer, scale: float) -> Layer:
    """The layer with base and gradients multiplied by ``scale`` (absent gradients stay absent), its variance by
    ``scale²``."""
    from gradsep.model.frame import Layer

    def mul(x: np.ndarray | None, by: float = scale) -> np.ndarray | None:
        return None if x is None else scaled_image(x, by)

    return Layer(mul(layer.base), mul(layer.dx), mul(layer.dy), mul(layer.var, scale * scale))  # type: ignore[arg-type]


def unlit_pixels(layer: Layer) -> np.ndarray:
    """(h, w) bool: pixels with no measured light in the layer — base 0 in every channel and every gradient
    term that touches the pixel (dx to its left and right neighbours, dy to those above and below) 0.

    Nothing was measured there, so nothing should be reconstructed there: inference sets the network's output
    to 0 on these pixels (a black background stays black instead of carrying the network's small offsets).
    """
    zero_base, zero_dx, zero_dy = (_all_channels_zero(np.asarray(a)) for a in (layer.base, layer.dx, layer.dy))
    unlit = zero_base & zero_dx & zero_dy
    unlit[:, 1:] &= zero_dx[:, :-1]     # the term linking the pixel to its left neighbour
    unlit[1:, :] &= zero_dy[:-1, :]     # the term linking it to the pixel above
    return unlit


def _all_channels_zero(image: np.ndarray) -> np.ndarray:
    """(h, w) bool: every channel of the pixel is 0. Same as ``np.all(image == 0, axis=-1)``, but one
    elementwise pass per channel instead of a reduction over a 3-long axis, which numpy runs far more slowly."""
    out = image[..., 0] == 0
    for c in range(1, image.shape[-1]):
        out &= image[..., c] == 0
    return out


def layer_planes(layer: Layer, window: Window | None = None, prior: np.ndarray | None = None,
                 alpha: float = PRIOR_ALPHA) -> np.ndarray:
    """(12, h, w) float32: base R G B, dx R G B, dy R G B, prior R G B, linear, finite, base and prior ≥ 0,
    all within ±RADIANCE_MAX. ``prior`` is the whole layer's ``poisson_prior`` (computed here, screened by
    ``alpha``, when None)."""
    if prior is None:
        prior = poisson_prior(layer, alpha=alpha)
    out = np.empty((LAYER_PLANES, *_crop(layer.base, window).shape[:2]), dtype=np.float32)
    _measured_into(out, layer, window)
    _channels_first(out[9:12], _crop(prior, window), 0.0, RADIANCE_MAX)
    return out


def measured_planes(layer: Layer, window: Window | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """(9, h, w) float32: the first nine planes of ``layer_planes`` (base, dx, dy), without the prior — what
    training compares a prediction with (training/losses.py). ``out``: a (9, h, w) float32 array to fill."""
    if out is None:
        out = np.empty((MEASURED_PLANES, *_crop(layer.base, window).shape[:2]), dtype=np.float32)
    _measured_into(out, layer, window)
    return out


def with_prior(planes: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Write the (h, w, 3) prior into planes 9-12 of (12, h, w) ``planes`` exactly as ``layer_planes`` does
    (channels first, clipped to [0, RADIANCE_MAX]); returns ``planes``."""
    _channels_first(planes[9:12], prior, 0.0, RADIANCE_MAX)
    return planes


def _measured_into(out: np.ndarray, layer: Layer, window: Window | None) -> None:
    _channels_first(out[0:3], _crop(layer.base, window), 0.0, RADIANCE_MAX)
    _channels_first(out[3:6], _crop(layer.dx, window), -RADIANCE_MAX, RADIANCE_MAX)
    _channels_first(out[6:9], _crop(layer.dy, window), -RADIANCE_MAX, RADIANCE_MAX)


@dataclass(frozen=True)
class DepthRange:
    """Per-frame depth normalisation: computed once over the whole frame so every tile or patch agrees."""

    lo: float
    hi: float

    @classmethod
    def of(cls, depth: np.ndarray) -> DepthRange:
        d = _finite(depth, 0.0, DEPTH_MAX)
        if d.size == 0:
            return cls(0.0, 0.0)
        return cls(float(d.min()), float(d.max()))

    def normalise(self, depth: np.ndarray) -> np.ndarray:
        d = _finite(depth, 0.0, DEPTH_MAX)
        span = self.hi - self.lo
        if span <= 0.0:  # a constant-depth frame (or all misses) carries no depth information
            return np.zeros_like(d)
        return np.clip((d - self.lo) / span, 0.0, 1.0)


def feature_planes(features: Features, depth_range: DepthRange | None = None,
                   window: Window | None = None) -> np.ndarray:
    """(7, h, w) float32: albedo in [0,1], normal·0.5+0.5 in [0,1], depth normalised per frame to [0,1]."""
    if depth_range is None:
        depth_range = DepthRange.of(features.depth)
    albedo = _crop(features.albedo, window)
    out = np.empty((FEATURE_PLANES, *albedo.shape[:2]), dtype=np.float32)
    _channels_first(out[0:3], albedo, 0.0, 1.0)
    _channels_first(out[3:6], _crop(features.normal, window), -1.0, 1.0)
    out[3:6] *= 0.5
    out[3:6] += 0.5
    out[6] = depth_range.normalise(_crop(features.depth, window))
    return out


# ---------------------------------------------------------------------------------------------------------------
# Linear planes → network inputs (numpy or torch, any leading batch dims; channels on axis -3)
# ---------------------------------------------------------------------------------------------------------------


def network_inputs(planes: Any, features: Any, transfer: LogTransfer = TRANSFER) -> tuple[Any, Any]:
    """(data, gradient) for DualBranchNet from (…, 12, h, w) layer planes and (…, 7, h, w) feature planes."""
    xp = array_namespace(planes)
    base, dx, dy = planes[..., 0:3, :, :], planes[..., 3:6, :, :], planes[..., 6:9, :, :]
    prior = planes[..., 9:12, :, :]
    data = xp.concatenate([transfer.forward(base), transfer.forward(prior), features], axis=-3)
    gradient = xp.concatenate([transfer.forward_signed(dx), transfer.forward_signed(dy)], axis=-3)
    return data, gradient


def network_inputs_numpy(planes: np.ndarray, features: np.ndarray, alignment: int = 1,
                         transfer: LogTransfer = TRANSFER) -> tuple[np.ndarray, np.ndarray]:
    """:func:`network_inputs` for one numpy window, written straight into the network's contiguous input arrays
    and reflect-padded to ``alignment`` (``pad_to_alignment``): the same float32 operations in the same order, so
    bit-for-bit the same numbers (tested), without the temporaries and the two concatenations (inference)."""
    height, width = planes.shape[-2:]
    data = np.empty((len(DATA_INPUTS), height, width), np.float32)
    gradient = np.empty((len(GRADIENT_INPUTS), height, width), np.float32)
    for src, dst in ((planes[0:3], data[0:3]), (planes[9:12], data[3:6])):
        transfer.forward_into(dst, src)
    data[6:] = features
    for src, dst in ((planes[3:6], gradient[0:3]), (planes[6:9], gradient[3:6])):
        np.abs(src, out=dst)
        transfer.forward_into(dst, dst)
        dst *= np.sign(src)
    return pad_to_alignment(data, alignment), pad_to_alignment(gradient, alignment)


def output_radiance(encoded: np.ndarray, fallback: np.ndarray | None = None,
                    transfer: LogTransfer = TRANSFER) -> np.ndarray:
    """Network output (3, h, w) in the transfer domain → (h, w, 3) float32 radiance, finite and ≥ 0.

    ``fallback`` is (h, w, 3) linear radiance (the clamped input base).

    Non-finite network outputs (which a sane model never produces) fall back to the clamped input base
    rather than to black, so a failure degrades to "no denoising" instead of holes.
    """
    y = np.asarray(encoded, dtype=np.float32)
    bad = ~np.isfinite(y)
    if not bad.any():  # the usual case: transfer.inverse's float32 operations, in one scratch array
        radiance = transfer.inverse_into(np.empty_like(y), y)
        return np.ascontiguousarray(radiance.transpose(1, 2, 0))
    radiance = transfer.inverse(np.where(bad, 0.0, y)).astype(np.float32)
    if fallback is not None:
        radiance = np.where(bad, np.asarray(fallback, np.float32).transpose(2, 0, 1), radiance)
    return np.ascontiguousarray(radiance.transpose(1, 2, 0))


# ---------------------------------------------------------------------------------------------------------------
# Alignment: reflection padding to the network's multiple and cropping back
# ---------------------------------------------------------------------------------------------------------------


def aligned_size(n: int, alignment: int) -> int:
    return -(-n // alignment) * alignment


def pad_to_alignment(x: np.ndarray, alignment: int) -> np.ndarray:
    """Reflect-pad the last two axes (bottom and right) up to multiples of ``alignment``.

    Reflection rather than zeros: a black border would read as a strong edge and leak dark values into the
    image through the convolutions. numpy reflects repeatedly when the pad exceeds the size and repeats the
    only pixel of a 1-pixel-wide axis.
    """
    if alignment < 1:
        raise ValueError(f"alignment must be >= 1, got {alignment}")
    h, w = x.shape[-2:]
    ph, pw = aligned_size(h, alignment) - h, aligned_size(w, alignment) - w
    if ph == 0 and pw == 0:
        return x
    pads = [(0, 0)] * (x.ndim - 2) + [(0, ph), (0, pw)]
    return np.pad(x, pads, mode="reflect")


def crop_to(x: np.ndarray, height: int, width: int) -> np.ndarray:
    """Undo ``pad_to_alignment`` on the last two axes."""
    return x[..., :height, :width]


def describe_prior(alpha: float = PRIOR_ALPHA) -> str:
    """The ``prior`` entry of ``describe_preprocessing`` (the text in the shipped models' metadata)."""
    return (f"L1 screened Poisson (IRLS, {PRIOR_IRLS_PASSES} passes x {PRIOR_CG_STEPS} CG steps) of the whole "
            f"layer, alpha={alpha}, clip [0, max_value], then C")


def describe_preprocessing(transfer: LogTransfer = TRANSFER, prior_alpha: float = PRIOR_ALPHA) -> dict[str, Any]:
    """The constants that define the input transform, for ONNX metadata and config.json."""
    return {
        "version": PREPROCESS_VERSION,
        "transfer": "log1p(mu*x)/log1p(mu); gradients sign(g)*C(|g|)",
        **transfer.constants(),
        "depth_max": DEPTH_MAX,
        "albedo": "clip [0,1]",
        "normal": "clip [-1,1] * 0.5 + 0.5",
        "depth": "clip [0, depth_max], per-frame min-max to [0,1]",
        "prior": describe_prior(prior_alpha),
        "nonfinite": "0",
        "padding": "reflect, bottom/right, to the network alignment",
    }
