"""The unsupervised losses (paper §4.3, GradNet's loss_functions): L = α·L_data + L_grad + β·L_1st.

No ground truth exists, so every term compares the prediction with the renderer's own noisy estimates:

* ``data_loss``: the prediction's *linear* radiance, box-averaged over DATA_POOL×DATA_POOL blocks, against
  the same average of the noisy base image, as a relative squared error (Noise2Noise's relMSE: the weight
  1/(sg(ŷ)² + ε·level²) does not depend on the target, so the minimiser is the target's *mean*). This is where we
  depart from GradNet, which uses L1 in the log domain: an L1 against a noisy target is minimised by its
  per-pixel *median*, and 16-spp Monte-Carlo radiance is strongly right-skewed (rare bright samples carry
  much of the energy), so that estimator is biased dark — our first models came out several times too dark. Pooling
  keeps the term unbiased while cutting the variance a single firefly adds to it (16 pixels × spp samples);
  the per-pixel detail comes from the gradient term, as in a screened Poisson reconstruction.
* ``gradient_loss``: the forward differences of the predicted *linear* image, compressed with sign·C, against
  the compressed rendered gradients (high frequencies, which G-PT estimates with little noise; differences
  are nearly symmetric around their mean, so the robust L1 of GradNet is kept here);
* ``first_order_loss``: the predicted log-domain differences should be explained by feature differences,
  Δŷ ≈ Σₖ aₖ·ΔFₖ, with per-pixel coefficients aₖ from the G-branch, weighted by exp(−9·ΔI_b²) so it acts
  only where the noisy image itself is flat (GradNet's edge-stopping weight). Each pixel pair is tested with
  the coefficients of both pixels (forward with the left/top pixel's, backward with the right/bottom's).

Shapes: predictions (N, 3, H, W) in the log domain of model.preprocess.TRANSFER; ``planes`` (N, 12, H, W)
linear base/dx/dy/prior from model.preprocess.layer_planes; ``features`` (N, 7, H, W); coefficients (N, 3·7, H, W).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gradsep.model.preprocess import TRANSFER, LogTransfer

#: GradNet's edge-stopping sharpness in exp(−k·ΔI²).
EDGE_SHARPNESS = 9.0
#: Block size of the data term's box average (4×4 pixels = 256 samples at 16 spp).
DATA_POOL = 4
#: ε of the data term's relative weight 1/(ŷ² + ε·level²) (Noise2Noise's 0.01, here relative to the image's
#: mean level): keeps the darkest pixels of an image from dominating its term.
REL_EPS = 1e-2
#: Radiance below which a block counts as black: an absolute floor of the weight, BLACK_LEVEL². Without it a
#: patch with no light at all (common in the direct layer: a shadowed corner) has level 0, and a prediction of
#: 1e-4 there scores a relative error of ~1 with a gradient ~1/ŷ that dominated whole batches (a few black
#: validation crops made the direct model's validation data term many times its prior's).
#: Dark frames are still anchored by the relative floor down to levels an order of magnitude above this.
BLACK_LEVEL = 1e-3


def _dx(x: torch.Tensor) -> torch.Tensor:
    """Forward difference along width, dropping the last column (where the contract's dx is 0)."""
    return x[..., :, 1:] - x[..., :, :-1]


def _dy(x: torch.Tensor) -> torch.Tensor:
    return x[..., 1:, :] - x[..., :-1, :]


def _pool(x: torch.Tensor, size: int) -> torch.Tensor:
    """Box average over size×size blocks (smaller for tiny images; a ragged border is left out)."""
    k = max(1, min(size, x.shape[-2], x.shape[-1]))
    return F.avg_pool2d(x, k) if k > 1 else x


def data_loss(pred: torch.Tensor, base: torch.Tensor, transfer: LogTransfer = TRANSFER,
              pool: int = DATA_POOL, eps: float = REL_EPS) -> torch.Tensor:
    """mean (P(ŷ) − P(I_b))² / (sg(P(ŷ))² + ε·sg(m)² + BLACK_LEVEL²), P = box average of linear radiance,
    m = the mean of P(ŷ) over each image of the batch; see the module docstring.

    The floor is relative to the image's own level (Noise2Noise uses an absolute 0.01, which suits radiance
    near 1): with an absolute floor a dark frame (radiance ~0.002) is barely anchored and a small log-domain
    offset doubles its brightness. It is computed from the prediction, not the noisy target, so the weight does
    not depend on the target and the minimiser stays its mean.
    """
    mean_pred = _pool(transfer.inverse(pred, clamp_negative=False), pool)
    mean_base = _pool(base, pool)
    level = mean_pred.detach().clamp_min(0.0).mean(dim=(-3, -2, -1), keepdim=True)
    weight = 1.0 / (mean_pred.detach() ** 2 + eps * level ** 2 + BLACK_LEVEL ** 2)
    return torch.mean((mean_pred - mean_base) ** 2 * weight)


def gradient_loss(pred: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor,
                  transfer: LogTransfer = TRANSFER) -> torch.Tensor:
    """mean |S(Δx C⁻¹(ŷ)) − S(dx)| + mean |S(Δy C⁻¹(ŷ)) − S(dy)| with S = sign·C.

    Differences are taken in linear radiance (that is what the renderer's gradients are) and compared after
    compression; the contract's zero last column/row of dx/dy is not a measurement and is excluded.
    """
    linear = transfer.inverse(pred, clamp_negative=False)
    loss_x = torch.mean(torch.abs(transfer.forward_signed(_dx(linear)) - transfer.forward_signed(dx[..., :, :-1])))
    loss_y = torch.mean(torch.abs(transfer.forward_signed(_dy(linear)) - transfer.forward_signed(dy[..., :-1, :])))
    return loss_x + loss_y


def first_order_loss(pred: torch.Tensor, coeffs: torch.Tensor, features: torch.Tensor,
                     base: torch.Tensor) -> torch.Tensor:
    """GradNet's first-order feature loss; see the module docstring. ``base`` is the linear noisy image."""
    n, c, h, w = pred.shape
    a = coeffs.reshape(n, c, features.shape[1], h, w)          # (N, 3, 7, H, W)
    f = features.unsqueeze(1)                                  # (N, 1, 7, H, W), shared by the colours
    fdx, fdy = _dx(f), _dy(f)
    est_x = torch.sum(a[..., :, :-1] * fdx, dim=2)             # predicted Δx from the left pixel's coefficients
    est_y = torch.sum(a[..., :-1, :] * fdy, dim=2)
    back_x = torch.sum(a[..., :, 1:] * -fdx, dim=2)            # predicted −Δx from the right pixel's
    back_y = torch.sum(a[..., 1:, :] * -fdy, dim=2)
    weight_x = torch.exp(-EDGE_SHARPNESS * _dx(base) ** 2)
    weight_y = torch.exp(-EDGE_SHARPNESS * _dy(base) ** 2)
    pdx, pdy = _dx(pred), _dy(pred)
    return (torch.mean(torch.abs(pdx - est_x) * weight_x) + torch.mean(torch.abs(pdx + back_x) * weight_x)
            + torch.mean(torch.abs(pdy - est_y) * weight_y) + torch.mean(torch.abs(pdy + back_y) * weight_y))


@dataclass
class LossTerms:
    """The three terms of one batch; ``total`` applies the weights."""

    data: torch.Tensor
    grad: torch.Tensor
    first: torch.Tensor

    def total(self, alpha: float, beta: float) -> torch.Tensor:
        return alpha * self.data + self.grad + beta * self.first

    def as_floats(self) -> dict[str, float]:
        return {"data": float(self.data.detach()), "grad": float(self.grad.detach()),
                "first": float(self.first.detach())}


def loss_terms(pred: torch.Tensor, coeffs: torch.Tensor, planes: torch.Tensor,
               features: torch.Tensor, targets: torch.Tensor | None = None) -> LossTerms:
    """All three terms for the main network; the G-branch coefficients are treated as constants.

    ``targets`` (N, 9, H, W): linear base/dx/dy of an independent realization of the same frames (Noise2Noise;
    ``gradsep dataset --pairs``); None compares with the input's own measurements, ``planes[:, 0:9]`` (the
    paper's setting). The first-order term's edge-stopping weight always reads the input's base.
    """
    measured = planes[:, 0:9] if targets is None else targets
    base, dx, dy = measured[:, 0:3], measured[:, 3:6], measured[:, 6:9]
    return LossTerms(
        data=data_loss(pred, base),
        grad=gradient_loss(pred, dx, dy),
        first=first_order_loss(pred, coeffs.detach(), features, planes[:, 0:3]),
    )


def gbranch_loss(coeffs: torch.Tensor, planes: torch.Tensor, features: torch.Tensor,
                 transfer: LogTransfer = TRANSFER) -> torch.Tensor:
    """The G-branch's own objective: explain the *noisy input's* log-domain differences (GradNet's active
    choice in its training loop), so the coefficients describe how radiance follows the features, not how
    the current network output does."""
    base = planes[:, 0:3]
    return first_order_loss(transfer.forward(base).detach(), coeffs, features, base)


@dataclass(frozen=True)
class BetaSchedule:
    """β per epoch: 0 during warm-up (the G-branch starts untrained, its coefficients mean nothing yet), then
    geometric growth from ``start`` by ``growth`` per epoch, capped at ``maximum`` (paper: "increases slowly
    with the epoch and stabilises at 2"). GradNet grows ×1.1 after 5 epochs of its 71; our CPU runs have
    tens of epochs, so the default grows ×1.25 after 2 and reaches 2 at epoch 16.
    """

    maximum: float = 2.0
    warmup_epochs: int = 2
    start: float = 0.1
    growth: float = 1.25

    def __call__(self, epoch: int) -> float:
        if epoch < self.warmup_epochs:
            return 0.0
        k = epoch - self.warmup_epochs
        # compare in log space so a long run cannot overflow growth**k
        if math.log(self.maximum / self.start) <= k * math.log(self.growth):
            return self.maximum
        return self.start * self.growth ** k
