"""The ``fused`` method's network (PyTorch, training and export only): the paper's dual-branch CBAM U-Net of
model/network.py — the same Encoder, residual bottleneck, Up + CBAM decoder and He initialisation — with two
changes at its ends (model/fused.py explains the method):

* the data branch reads C(base), the K candidates' C(candidate) side by side, and the 7 feature planes;
* the head predicts K logits per pixel, and the output is their softmax: per-pixel convex weights over the
  candidates (zero-initialised head: an untrained model averages them).
"""

from __future__ import annotations

import torch
from torch import nn

from model.fused import data_channels
from model.network import Encoder, NetworkConfig, ResidualBlock, Up, init_weights


class BlendNet(nn.Module):
    """``forward(data, gradient)`` → (N, K, H, W) softmax weights over the K candidates."""

    def __init__(self, candidates: int, config: NetworkConfig | None = None) -> None:
        super().__init__()
        if candidates < 1:
            raise ValueError(f"a blend needs at least one candidate, got {candidates}")
        self.config = config = config or NetworkConfig()
        self.candidates = candidates
        widths = config.stage_widths()
        self.data_encoder = Encoder(data_channels(candidates), widths)
        self.grad_encoder = Encoder(6, widths)
        bottleneck = 2 * widths[-1]
        self.bottleneck = nn.Sequential(*(ResidualBlock(bottleneck) for _ in range(config.residual_blocks)))
        ups = []
        cin = bottleneck + 2 * widths[-1]
        for i in reversed(range(config.depth)):
            ups.append(Up(cin, widths[i], config.use_attention, config.attention_reduction))
            cin = widths[i] + (2 * widths[i - 1] if i > 0 else 0)
        self.decoder = nn.ModuleList(ups)
        self.head = nn.Conv2d(widths[0], candidates, 3, padding=1)
        init_weights(self)
        nn.init.zeros_(self.head.weight)  # uniform weights at the start: the plain average of the candidates

    def logits(self, data: torch.Tensor, gradient: torch.Tensor) -> torch.Tensor:
        d_skips = self.data_encoder(data)
        g_skips = self.grad_encoder(gradient)
        x = self.bottleneck(torch.cat([d_skips[-1], g_skips[-1]], dim=1))
        for level, up in zip(reversed(range(self.config.depth)), self.decoder, strict=True):
            x = up(torch.cat([x, d_skips[level], g_skips[level]], dim=1))
        return self.head(x)

    def forward(self, data: torch.Tensor, gradient: torch.Tensor) -> torch.Tensor:
        return torch.softmax(self.logits(data, gradient), dim=1)
