"""The dual-branch CBAM reconstruction network (PyTorch): GradNet's layout plus the paper's attention.

Reads like the diagram in docs/network.md::

    data  (base, prior, albedo, normal, depth: 13 ch) ─► Down ─► Down ─► Down ─┐
    grad  (dx RGB + dy RGB, 6 ch)                     ─► Down ─► Down ─► Down ─┤ concat
                                                                               ▼
                                                                 residual blocks (bottleneck)
    decoder:  Up(bottleneck ⊕ data₃ ⊕ grad₃) ─► CBAM ─► Up(· ⊕ data₂ ⊕ grad₂) ─► CBAM
              ─► Up(· ⊕ data₁ ⊕ grad₁) ─► CBAM ─► 3×3 conv ─► + C(prior) ─► ReLU ─► log-domain radiance

Each Down halves the resolution, so inputs must be a multiple of ``2**depth`` (``NetworkConfig.alignment``);
model/preprocess.py pads to it. The G-branch (``GBranch``) predicts per-pixel feature coefficients used only
by the first-order loss during training; it is not part of the exported inference graph.

This module imports torch: training and export use it, inference (model/infer.py) never does.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

# Channel names are data, defined with the transform that produces them (numpy-only, so inference shares them).
from gradsep.model.preprocess import DATA_INPUTS, FEATURE_INPUTS, GRADIENT_INPUTS, OUTPUTS, PRIOR_CHANNELS

__all__ = ["DualBranchNet", "GBranch", "NetworkConfig"]


@dataclass(frozen=True)
class NetworkConfig:
    """Width and depth of the network; serialised into config.json and the ONNX metadata.

    Defaults: GradNet's layout (3 stages, 4 residual blocks) at half its width: GradNet's own widths cost four
    times the multiply-adds (:func:`describe` counts them), which leaves no room for two layers in the service's
    latency target on the target machine (benchmarks/bench_network.py, docs/network.md), and a smaller network
    also takes more training steps in a CPU-hour.
    """

    width: int = 16                 # channels after the first Down; doubled per stage
    depth: int = 3                  # number of stride-2 stages; alignment = 2**depth
    residual_blocks: int = 4        # at the bottleneck, 2·width·2**(depth-1) channels (as GradNet)
    use_attention: bool = True      # CBAM after each upsampling stage (False: the GradNet ablation)
    attention_reduction: int = 8    # CBAM channel-MLP reduction ratio (hidden = channels // ratio, ≥ 4)
    gbranch_width: int = 32         # G-branch hidden channels (GradNet: 64)

    def __post_init__(self) -> None:
        for name in ("width", "depth", "attention_reduction", "gbranch_width"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"NetworkConfig.{name} must be >= 1, got {getattr(self, name)!r}")
        if self.residual_blocks < 0:
            raise ValueError(f"NetworkConfig.residual_blocks must be >= 0, got {self.residual_blocks!r}")

    @property
    def alignment(self) -> int:
        """Input height and width must be multiples of this (one factor 2 per Down stage)."""
        return 2 ** self.depth

    def stage_widths(self) -> list[int]:
        """Channels of each encoder stage, shallowest first."""
        return [self.width * 2 ** i for i in range(self.depth)]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> NetworkConfig:
        """Build from a dict, ignoring unknown keys so older/newer configs still load."""
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in known})


class Down(nn.Module):
    """3×3 stride-2 convolution + leaky ReLU: one encoder stage (GradNet's ConvBlock)."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(self.conv(x))


class ResidualBlock(nn.Module):
    """conv–leaky ReLU–conv plus identity (paper Fig. 5a): deepens the bottleneck without losing the input."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.leaky_relu(self.conv1(x)))


class ChannelAttention(nn.Module):
    """CBAM channel attention: a shared MLP scores the average- and max-pooled channel vectors.

    Max pooling keeps the strongest response of each channel (edges) and average pooling its overall
    energy; their sum through one MLP, squashed by a sigmoid, reweights the channels.
    """

    def __init__(self, channels: int, reduction: int) -> None:
        super().__init__()
        hidden = max(4, channels // reduction)
        # 1×1 convolutions on the (N, C, 1, 1) pooled vectors are the MLP, shared by both poolings.
        self.mlp = nn.Sequential(nn.Conv2d(channels, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, channels, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        avg = x.mean(dim=(2, 3), keepdim=True)
        peak = x.amax(dim=(2, 3), keepdim=True)
        return x * torch.sigmoid(self.mlp(avg) + self.mlp(peak))


class SpatialAttention(nn.Module):
    """CBAM spatial attention: a 7×7 convolution over the per-pixel channel mean and max maps."""

    def __init__(self, kernel_size: int = 7) -> None:
        super().__init__()
        self.conv = nn.Conv2d(2, 1, kernel_size, padding=kernel_size // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        maps = torch.cat([x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)], dim=1)
        return x * torch.sigmoid(self.conv(maps))


class CBAM(nn.Module):
    """Channel then spatial attention (Woo et al. 2018), the order CBAM found best."""

    def __init__(self, channels: int, reduction: int) -> None:
        super().__init__()
        self.channel = ChannelAttention(channels, reduction)
        self.spatial = SpatialAttention()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.spatial(self.channel(x))


class Up(nn.Module):
    """4×4 stride-2 transposed convolution + ReLU (GradNet's DeConvBlock), then CBAM when enabled.

    The paper puts attention here and only here: attention in the encoder or skips made the network keep
    noise as features (§4.2).
    """

    def __init__(self, cin: int, cout: int, attention: bool, reduction: int) -> None:
        super().__init__()
        self.deconv = nn.ConvTranspose2d(cin, cout, 4, stride=2, padding=1)
        self.attention: nn.Module = CBAM(cout, reduction) if attention else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.attention(F.relu(self.deconv(x)))


class Encoder(nn.Module):
    """A stack of Down stages returning every stage's output (the skips the decoder concatenates)."""

    def __init__(self, cin: int, widths: list[int]) -> None:
        super().__init__()
        chans = [cin, *widths]
        self.stages = nn.ModuleList(Down(a, b) for a, b in zip(chans[:-1], chans[1:], strict=True))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        skips = []
        for stage in self.stages:
            x = stage(x)
            skips.append(x)
        return skips


class DualBranchTrunk(nn.Module):
    """The paper's dual-branch U-Net up to its output head: a data encoder and a gradient encoder that meet at
    the bottleneck (concatenated, then residual blocks) and at every decoder stage, where both branches' skips
    are concatenated with the upsampled stream; a 3×3 head with ``outputs`` channels, zero-initialised. The
    `network` model (DualBranchNet) and the fused blend model (model.blend_net.BlendNet) read its head."""

    def __init__(self, data_inputs: int, gradient_inputs: int, outputs: int,
                 config: NetworkConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or NetworkConfig()
        widths = config.stage_widths()
        self.data_encoder = Encoder(data_inputs, widths)
        self.grad_encoder = Encoder(gradient_inputs, widths)
        bottleneck = 2 * widths[-1]
        self.bottleneck = nn.Sequential(*(ResidualBlock(bottleneck) for _ in range(config.residual_blocks)))
        ups = []
        cin = bottleneck + 2 * widths[-1]
        for i in reversed(range(config.depth)):
            ups.append(Up(cin, widths[i], config.use_attention, config.attention_reduction))
            # next stage input: this output + the data and gradient skips one level shallower
            cin = widths[i] + (2 * widths[i - 1] if i > 0 else 0)
        self.decoder = nn.ModuleList(ups)
        self.head = nn.Conv2d(widths[0], outputs, 3, padding=1)
        init_weights(self)
        nn.init.zeros_(self.head.weight)  # the subclass's output starts at its neutral value; see its forward

    def head_output(self, data: torch.Tensor, gradient: torch.Tensor) -> torch.Tensor:
        """The head's (N, outputs, H, W) response to the two branches' inputs."""
        d_skips = self.data_encoder(data)
        g_skips = self.grad_encoder(gradient)
        x = self.bottleneck(torch.cat([d_skips[-1], g_skips[-1]], dim=1))
        # deepest first: each Up sees the stream plus both branches' skips at the stream's resolution
        for level, up in zip(reversed(range(self.config.depth)), self.decoder, strict=True):
            x = up(torch.cat([x, d_skips[level], g_skips[level]], dim=1))
        return self.head(x)


class DualBranchNet(DualBranchTrunk):
    """Data branch + gradient branch U-Net; ``forward(data, gradient)`` returns log-domain radiance (≥ 0 in eval mode).

    Data branch: low frequencies from the noisy base and the features. Gradient branch: high frequencies
    from dx/dy only (DualBranchTrunk). The zero-initialised head starts the model as the identity on C(prior).
    """

    def __init__(self, config: NetworkConfig | None = None) -> None:
        super().__init__(len(DATA_INPUTS), len(GRADIENT_INPUTS), len(OUTPUTS), config)

    def forward(self, data: torch.Tensor, gradient: torch.Tensor) -> torch.Tensor:
        # Global residual: predict a correction to C(prior) (model.preprocess.poisson_prior), with the head
        # initialised to zero, so training starts from the robust screened Poisson solution instead of from
        # black, and a short CPU budget is spent on what the prior gets wrong (outliers it smears, edges the
        # features explain) rather than on learning to integrate gradients across the image.
        y = data[:, PRIOR_CHANNELS] + self.head_output(data, gradient)
        # C(I) ≥ 0. Clamped only in inference: in training a ReLU would stop the gradient of every pixel it
        # clamps (black input pixels start exactly at 0), and the losses read ŷ < 0 smoothly instead.
        return y if self.training else F.relu(y)


class GBranch(nn.Module):
    """Predicts, per pixel and output colour, one coefficient per feature channel (paper Fig. 5b).

    The first-order loss asks that the image's finite differences look like Σₖ coeffₖ · (feature
    difference)ₖ. The branch sees the same inputs as the main network. Output: (N, 3·7, H, W), grouped by
    colour channel (R's 7 coefficients first).
    """

    def __init__(self, config: NetworkConfig | None = None) -> None:
        super().__init__()
        config = config or NetworkConfig()
        cin = len(DATA_INPUTS) + len(GRADIENT_INPUTS)
        hidden = config.gbranch_width
        self.net = nn.Sequential(
            nn.Conv2d(cin, hidden, 3, padding=1), nn.LeakyReLU(),
            nn.Conv2d(hidden, hidden, 3, padding=1), nn.LeakyReLU(),
            nn.Conv2d(hidden, len(OUTPUTS) * len(FEATURE_INPUTS), 3, padding=1),
        )
        init_weights(self)

    def forward(self, data: torch.Tensor, gradient: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([data, gradient], dim=1))


def init_weights(module: nn.Module) -> None:
    """He (Kaiming) initialisation for every convolution (paper §4.5), zero biases."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
            nn.init.kaiming_normal_(m.weight, a=0.01, nonlinearity="leaky_relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)


def macs_per_pixel(config: NetworkConfig) -> float:
    """Multiply-accumulates per full-resolution pixel of the inference graph (for docs and benchmarks)."""
    widths = config.stage_widths()
    total = 0.0
    cins = [len(DATA_INPUTS), *widths[:-1]]
    gins = [len(GRADIENT_INPUTS), *widths[:-1]]
    for i, w in enumerate(widths):
        scale = 4.0 ** -(i + 1)
        total += scale * 9 * w * (cins[i] + gins[i])
    bottleneck = 2 * widths[-1]
    total += 4.0 ** -config.depth * 2 * config.residual_blocks * 9 * bottleneck * bottleneck
    cin = bottleneck + 2 * widths[-1]
    for i in reversed(range(config.depth)):
        # a 4×4 stride-2 transposed conv touches 2×2 taps per output pixel
        total += 4.0 ** -i * 4 * cin * widths[i]
        cin = widths[i] + (2 * widths[i - 1] if i > 0 else 0)
    total += 9 * widths[0] * len(OUTPUTS)
    return total


def describe(config: NetworkConfig) -> str:
    """One line for logs: widths, blocks, attention, MACs for a 1280×720 frame."""
    gmac = macs_per_pixel(config) * 1280 * 720 / 1e9
    return (f"DualBranchNet widths={config.stage_widths()} residual_blocks={config.residual_blocks} "
            f"attention={config.use_attention} ~{gmac:.1f} GMAC per 1280x720 layer "
            f"(alignment {config.alignment}, {math.log2(config.alignment):.0f} stages)")
