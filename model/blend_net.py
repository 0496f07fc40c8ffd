"""The ``fused`` method's network (PyTorch, training and export only): the paper's dual-branch CBAM U-Net of
model/network.py — the same Encoder, residual bottleneck, Up + CBAM decoder and He initialisation — with two
changes at its ends (model/fused.py explains the method):

* the data branch reads C(base), the K candidates' C(candidate) side by side, and the 7 feature planes;
* the head predicts K logits per pixel, and the output is their softmax: per-pixel convex weights over the
  candidates (zero-initialised head: an untrained model averages them).
"""

from __future__ import annotations

import torch

from gradsep.model.fused import data_channels
from gradsep.model.network import DualBranchTrunk, NetworkConfig


class BlendNet(DualBranchTrunk):
    """``forward(data, gradient)`` → (N, K, H, W) softmax weights over the K candidates. The zero-initialised
    head starts at uniform weights: the plain average of the candidates."""

    def __init__(self, candidates: int, config: NetworkConfig | None = None) -> None:
        if candidates < 1:
            raise ValueError(f"a blend needs at least one candidate, got {candidates}")
        super().__init__(data_channels(candidates), 6, candidates, config)
        self.candidates = candidates

    def logits(self, data: torch.Tensor, gradient: torch.Tensor) -> torch.Tensor:
        return self.head_output(data, gradient)

    def forward(self, data: torch.Tensor, gradient: torch.Tensor) -> torch.Tensor:
        return torch.softmax(self.logits(data, gradient), dim=1)
