"""model/network.py: shapes, alignment, where attention sits, CBAM's arithmetic, initialisation, MAC count."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
from torch import nn  # noqa: E402

from gradsep.model.network import (  # noqa: E402
    CBAM,
    ChannelAttention,
    DualBranchNet,
    GBranch,
    NetworkConfig,
    SpatialAttention,
    Up,
    macs_per_pixel,
)
from gradsep.model.preprocess import (  # noqa: E402
    DATA_INPUTS,
    FEATURE_INPUTS,
    GRADIENT_INPUTS,
    PRIOR_CHANNELS,
    crop_to,
    pad_to_alignment,
)

TINY = NetworkConfig(width=4, residual_blocks=1, gbranch_width=8)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Tiny networks run fastest on one thread; oversubscribed OpenMP threads on the shared 2 cores spin."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _inputs(n: int, h: int, w: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, len(DATA_INPUTS), h, w, generator=g), torch.rand(n, len(GRADIENT_INPUTS), h, w,
                                                                         generator=g) - 0.5


class TestShapes:
    @pytest.mark.parametrize(("n", "h", "w"), [(1, 8, 8), (2, 16, 40), (1, 24, 8)])
    def test_output_shape_and_range(self, n: int, h: int, w: int) -> None:
        torch.manual_seed(0)
        net = DualBranchNet(TINY).eval()
        with torch.no_grad():
            y = net(*_inputs(n, h, w))
        assert y.shape == (n, 3, h, w)
        assert torch.isfinite(y).all() and (y >= 0).all()

    def test_starts_as_the_identity_on_the_input_radiance(self) -> None:
        """The head starts at zero and the output is a correction to C(prior): an untrained network returns the
        Poisson prior's channels, not black; after a weight change it no longer does."""
        net = DualBranchNet(TINY).eval()
        data, grad = _inputs(1, 16, 16)
        with torch.no_grad():
            assert torch.equal(net(data, grad), data[:, PRIOR_CHANNELS])
            net.head.bias.fill_(-2.0)
            assert torch.equal(net(data, grad), torch.zeros(1, 3, 16, 16))         # clamped to C(I) ≥ 0
            assert (net.train()(data, grad) < 0).all()                                # unclamped in training

    @pytest.mark.parametrize(("h", "w"), [(1, 1), (5, 13), (17, 9), (3, 64)])
    def test_odd_sizes_through_padding(self, h: int, w: int) -> None:
        net = DualBranchNet(TINY).eval()
        data, grad = _inputs(1, h, w)
        a = net.config.alignment
        pd = torch.from_numpy(pad_to_alignment(data.numpy(), a))
        pg = torch.from_numpy(pad_to_alignment(grad.numpy(), a))
        with torch.no_grad():
            y = crop_to(net(pd, pg).numpy(), h, w)
        assert y.shape == (1, 3, h, w) and np.all(np.isfinite(y))

    def test_unaligned_input_is_refused_by_the_graph(self) -> None:
        net = DualBranchNet(TINY).eval()
        with pytest.raises(RuntimeError), torch.no_grad():
            net(*_inputs(1, 12, 8))

    @pytest.mark.parametrize("depth", [1, 2, 4])
    def test_depth_sets_alignment(self, depth: int) -> None:
        cfg = NetworkConfig(width=2, depth=depth, residual_blocks=0)
        assert cfg.alignment == 2 ** depth
        net = DualBranchNet(cfg).eval()
        with torch.no_grad():
            assert net(*_inputs(1, 2 ** depth, 2 * 2 ** depth)).shape == (1, 3, 2 ** depth, 2 * 2 ** depth)

    def test_gbranch_shape(self) -> None:
        out = GBranch(TINY)(*_inputs(2, 5, 7))
        assert out.shape == (2, 3 * len(FEATURE_INPUTS), 5, 7)


class TestAttentionPlacement:
    def test_cbam_after_each_upsampling_and_only_there(self) -> None:
        net = DualBranchNet(NetworkConfig(width=4, depth=3, residual_blocks=2))
        cbams = [name for name, m in net.named_modules() if isinstance(m, CBAM)]
        assert len(cbams) == 3
        assert all(name.startswith("decoder.") and name.endswith(".attention") for name in cbams)
        assert all(isinstance(up.attention, CBAM) for up in net.decoder)

    def test_no_attention_ablation(self) -> None:
        net = DualBranchNet(NetworkConfig(width=4, use_attention=False))
        assert not any(isinstance(m, CBAM | ChannelAttention | SpatialAttention) for m in net.modules())
        assert all(isinstance(up.attention, nn.Identity) for up in net.decoder)
        with torch.no_grad():
            assert net.eval()(*_inputs(1, 8, 8)).shape == (1, 3, 8, 8)


class TestCBAM:
    def test_channel_attention_by_hand(self) -> None:
        ca = ChannelAttention(channels=2, reduction=1)   # hidden = max(4, 2) = 4
        for p in ca.parameters():
            nn.init.zeros_(p)
        # MLP = second conv's bias only: sigmoid(b + b) per channel
        with torch.no_grad():
            ca.mlp[2].bias.copy_(torch.tensor([0.0, 1.0]))
        x = torch.tensor([[[[1.0, 3.0]], [[2.0, -2.0]]]])   # (1, 2, 1, 2)
        y = ca(x)
        assert torch.allclose(y[0, 0], x[0, 0] * 0.5)
        assert torch.allclose(y[0, 1], x[0, 1] * torch.sigmoid(torch.tensor(2.0)))

    def test_channel_attention_uses_avg_and_max(self) -> None:
        ca = ChannelAttention(channels=1, reduction=1)
        # MLP = identity-like: first conv weight 1 into hidden unit 0, second conv reads it back
        with torch.no_grad():
            for p in ca.parameters():
                p.zero_()
            ca.mlp[0].weight[0, 0] = 1.0
            ca.mlp[2].weight[0, 0] = 1.0
        x = torch.tensor([[[[1.0, 3.0]]]])                  # avg 2, max 3 → sigmoid(relu(2) + relu(3))
        assert torch.allclose(ca(x), x * torch.sigmoid(torch.tensor(5.0)))

    def test_spatial_attention_by_hand(self) -> None:
        sa = SpatialAttention()
        assert sa.conv.kernel_size == (7, 7) and sa.conv.in_channels == 2
        with torch.no_grad():
            sa.conv.weight.zero_()
            sa.conv.bias.zero_()
            sa.conv.weight[0, 0, 3, 3] = 1.0                # centre tap on the channel-mean map
            sa.conv.weight[0, 1, 3, 3] = 2.0                # and on the channel-max map
        x = torch.tensor([[[[1.0]], [[3.0]]]])               # mean 2, max 3 → sigmoid(2 + 6)
        assert torch.allclose(sa(x), x * torch.sigmoid(torch.tensor(8.0)))

    def test_up_applies_attention_after_the_deconvolution(self) -> None:
        up = Up(4, 2, attention=True, reduction=8)
        x = torch.rand(1, 4, 3, 5)
        y = up(x)
        assert y.shape == (1, 2, 6, 10)
        with torch.no_grad():
            expected = up.attention(torch.relu(up.deconv(x)))
        assert torch.allclose(y, expected)


class TestInitAndConfig:
    def test_he_initialisation(self) -> None:
        torch.manual_seed(0)
        net = DualBranchNet(NetworkConfig(width=32, residual_blocks=1))
        conv = net.bottleneck[0].conv1                      # 256 → 256, fan_in 256·9
        gain = math.sqrt(2.0 / (1 + 0.01 ** 2))
        expected = gain / math.sqrt(conv.in_channels * 9)
        assert float(conv.weight.detach().std()) == pytest.approx(expected, rel=0.02)
        assert float(conv.bias.detach().abs().max()) == 0.0

    def test_seeded_construction_is_reproducible(self) -> None:
        torch.manual_seed(3)
        a = DualBranchNet(TINY)
        torch.manual_seed(3)
        b = DualBranchNet(TINY)
        assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters(), strict=True))

    def test_config_validation_and_round_trip(self) -> None:
        with pytest.raises(ValueError, match="width"):
            NetworkConfig(width=0)
        with pytest.raises(ValueError, match="residual_blocks"):
            NetworkConfig(residual_blocks=-1)
        cfg = NetworkConfig(width=8, use_attention=False)
        assert NetworkConfig.from_dict({**cfg.to_dict(), "unknown_future_key": 1}) == cfg


def test_macs_per_pixel_matches_a_count_of_the_convolutions() -> None:
    """The MAC model in docs/network.md and the benchmark equals what the convolutions actually do."""
    cfg = NetworkConfig(width=4, residual_blocks=2)
    net = DualBranchNet(cfg).eval()
    total = 0

    def count(module: nn.Module, inputs: tuple[torch.Tensor, ...], output: torch.Tensor) -> None:
        nonlocal total
        k = module.kernel_size[0] * module.kernel_size[1]
        if isinstance(module, nn.ConvTranspose2d):        # each input pixel scatters k taps per output channel
            total += inputs[0].shape[2] * inputs[0].shape[3] * k * module.in_channels * module.out_channels
        elif module.in_channels > 2 and output.shape[2] > 1:   # skip CBAM's 1×1 MLP and 7×7 2-channel conv
            total += output.shape[2] * output.shape[3] * k * module.in_channels * module.out_channels

    for m in net.modules():
        if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
            m.register_forward_hook(count)
    h, w = 32, 48
    with torch.no_grad():
        net(*_inputs(1, h, w))
    assert total / (h * w) == pytest.approx(macs_per_pixel(cfg), rel=1e-9)
