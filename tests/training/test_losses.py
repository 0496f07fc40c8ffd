"""training/losses.py: every term against values computed by hand on tiny tensors."""

from __future__ import annotations

import math

import pytest

torch = pytest.importorskip("torch")

from gradsep.model.preprocess import TRANSFER  # noqa: E402
from gradsep.training.losses import (  # noqa: E402
    BLACK_LEVEL,
    BetaSchedule,
    LossTerms,
    data_loss,
    first_order_loss,
    gbranch_loss,
    gradient_loss,
    loss_terms,
)


def C(x: float) -> float:  # noqa: N802 - the paper's name
    return math.log1p(16 * x) / math.log(17)


def t(rows: list[list[float]]) -> torch.Tensor:
    """(1, 1, H, W) tensor from nested lists."""
    return torch.tensor(rows, dtype=torch.float64)[None, None]


def test_data_loss_by_hand() -> None:
    # 4×4 block: prediction C(1) everywhere (linear 1, level 1), noisy base averaging 3
    # → (1 − 3)² / (1 + 0.01 + BLACK_LEVEL²)
    pred = torch.ones(1, 3, 4, 4, dtype=torch.float64)
    base = torch.zeros(1, 3, 4, 4, dtype=torch.float64)
    base[..., 0, 0] = 48.0
    assert float(data_loss(pred, base)) == pytest.approx(4.0 / (1.01 + BLACK_LEVEL ** 2), rel=1e-12)


def test_data_loss_tiny_images_pool_what_they_have() -> None:
    pred = torch.full((1, 3, 1, 2), C(2.0), dtype=torch.float64)       # linear 2 everywhere, level 2
    base = torch.tensor([1.0, 3.0], dtype=torch.float64).expand(1, 3, 1, 2)
    assert float(data_loss(pred, base)) == pytest.approx(1.0 / (4.0 + 0.04), rel=1e-6)   # 1×1 blocks
    one = torch.full((1, 3, 1, 1), C(2.0), dtype=torch.float64)
    assert float(data_loss(one, torch.full((1, 3, 1, 1), 2.0, dtype=torch.float64))) == pytest.approx(0.0, abs=1e-20)


def test_data_loss_is_scale_invariant_and_finite_on_black() -> None:
    """Above the black level the weight's floor follows the image's level, so a dark frame is anchored as firmly
    as a bright one; on a black patch a tiny prediction costs little and its gradient stays bounded."""
    gen = torch.Generator().manual_seed(0)
    linear = torch.rand(2, 3, 8, 8, generator=gen, dtype=torch.float64) + 0.1
    base = linear * (1 + 0.3 * torch.randn(2, 3, 8, 8, generator=gen, dtype=torch.float64)).clamp_min(0)
    losses = [float(data_loss(TRANSFER.forward(linear * s), base * s)) for s in (0.1, 1.0, 1e3)]
    assert losses[0] == pytest.approx(losses[1], rel=1e-3) and losses[2] == pytest.approx(losses[1], rel=1e-4)
    black = torch.zeros(1, 3, 8, 8, dtype=torch.float64)
    assert float(data_loss(black, black)) == 0.0 and torch.isfinite(data_loss(black, black + 1e-3))
    pred = TRANSFER.forward(torch.full((1, 3, 8, 8), 1e-4, dtype=torch.float64)).requires_grad_()
    loss = data_loss(pred, black)
    loss.backward()
    assert float(loss.detach()) < 0.02 and float(pred.grad.abs().max()) < 1.0


def test_data_loss_is_minimised_by_the_mean_not_the_median() -> None:
    """The reason for the relMSE data term: a right-skewed noisy target (one bright sample in sixteen, mean 1,
    median 0) must pull a constant prediction to its mean. GradNet's log-domain L1 would pick the median, 0."""
    base = torch.zeros(1, 3, 4, 4, dtype=torch.float64)
    base[..., 2, 1] = 16.0
    p = torch.full((1, 3, 1, 1), 0.3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([p], lr=0.02)
    for _ in range(1500):
        opt.zero_grad()
        data_loss(p.expand(1, 3, 4, 4), base, pool=1).backward()
        opt.step()
    assert float(TRANSFER.inverse(p.detach())[0, 0, 0, 0]) == pytest.approx(1.0, rel=1e-3)


def test_gradient_loss_zero_for_consistent_gradients() -> None:
    # linear image [[0, 1], [1, 18]] is C^-1 of pred [[0, 1], [1, 2]]
    pred = t([[0.0, 1.0], [1.0, 2.0]])
    dx = t([[1.0, 0.0], [17.0, 0.0]])           # last column is the contract's 0, excluded
    dy = t([[1.0, 17.0], [0.0, 0.0]])
    assert float(gradient_loss(pred, dx, dy)) == pytest.approx(0.0, abs=1e-12)


def test_gradient_loss_by_hand() -> None:
    pred = t([[0.0, 1.0], [1.0, 2.0]])          # linear differences: dx 1 and 17, dy 1 and 17
    dx = t([[18.0, 123.0], [1.0, -5.0]])        # last column ignored
    dy = t([[-1.0, 17.0], [99.0, 99.0]])        # last row ignored
    loss_x = (abs(C(1) - C(18)) + abs(C(17) - C(1))) / 2
    loss_y = (abs(C(1) + C(1)) + 0.0) / 2        # sign·C(|−1|) = −1
    assert float(gradient_loss(pred, dx, dy)) == pytest.approx(loss_x + loss_y, rel=1e-12)


def test_first_order_loss_by_hand() -> None:
    pred = t([[0.2, 0.7], [0.1, 0.1]])
    feats = t([[0.0, 1.0], [0.0, 0.0]])          # one feature channel
    coeffs = t([[0.3, 0.4], [0.5, 0.6]])        # one colour × one feature
    base = t([[0.5, 0.8], [0.5, 0.5]])
    w = math.exp(-9 * 0.3 ** 2)                  # edge-stopping weight where the base changes by 0.3
    # x: row 0 → |0.5−0.3|w and |0.5−0.4|w; row 1 → 0; means over 2 pairs
    # y: col 0 → |−0.1| twice (w = 1); col 1 → |−0.6+0.4|w and |−0.6+0.6|w
    expected = (0.2 * w) / 2 + (0.1 * w) / 2 + (0.1 + 0.2 * w) / 2 + (0.1 + 0.0) / 2
    assert float(first_order_loss(pred, coeffs, feats, base)) == pytest.approx(expected, rel=1e-12)


def test_first_order_loss_groups_coefficients_by_colour() -> None:
    g = torch.Generator().manual_seed(0)
    n, c, f, h, w = 2, 3, 7, 4, 5
    pred = torch.rand(n, c, h, w, generator=g, dtype=torch.float64)
    feats = torch.rand(n, f, h, w, generator=g, dtype=torch.float64)
    coeffs = torch.randn(n, c * f, h, w, generator=g, dtype=torch.float64)
    base = torch.rand(n, c, h, w, generator=g, dtype=torch.float64)
    # straightforward per-colour loop: colour k uses coefficient channels k*f … k*f+f−1
    total = torch.zeros((), dtype=torch.float64)
    for k in range(c):
        a = coeffs[:, k * f:(k + 1) * f]
        p, b = pred[:, k], base[:, k]
        fdx = feats[..., 1:] - feats[..., :-1]
        fdy = feats[..., 1:, :] - feats[..., :-1, :]
        pdx, pdy = p[..., 1:] - p[..., :-1], p[..., 1:, :] - p[..., :-1, :]
        wx = torch.exp(-9 * (b[..., 1:] - b[..., :-1]) ** 2)
        wy = torch.exp(-9 * (b[..., 1:, :] - b[..., :-1, :]) ** 2)
        total = total + ((pdx - (a[..., :-1] * fdx).sum(1)).abs() * wx).sum() / (n * c * h * (w - 1))
        total = total + ((pdx - (a[..., 1:] * fdx).sum(1)).abs() * wx).sum() / (n * c * h * (w - 1))
        total = total + ((pdy - (a[..., :-1, :] * fdy).sum(1)).abs() * wy).sum() / (n * c * (h - 1) * w)
        total = total + ((pdy - (a[..., 1:, :] * fdy).sum(1)).abs() * wy).sum() / (n * c * (h - 1) * w)
    assert float(first_order_loss(pred, coeffs, feats, base)) == pytest.approx(float(total), rel=1e-12)


def test_loss_terms_detach_the_gbranch_and_weight_the_total() -> None:
    g = torch.Generator().manual_seed(1)
    pred = torch.rand(1, 3, 4, 4, generator=g, requires_grad=True)
    coeffs = torch.randn(1, 21, 4, 4, generator=g, requires_grad=True)
    planes = torch.rand(1, 9, 4, 4, generator=g)
    feats = torch.rand(1, 7, 4, 4, generator=g)
    terms = loss_terms(pred, coeffs, planes, feats)
    with torch.no_grad():
        assert float(terms.data) == pytest.approx(float(data_loss(pred, planes[:, :3])))
        assert float(terms.grad) == pytest.approx(float(gradient_loss(pred, planes[:, 3:6], planes[:, 6:9])))
    terms.total(1.0, 2.0).backward()
    assert pred.grad is not None and coeffs.grad is None
    manual = LossTerms(torch.tensor(1.0), torch.tensor(2.0), torch.tensor(3.0))
    assert float(manual.total(0.5, 2.0)) == 0.5 + 2.0 + 6.0


def test_loss_terms_compare_with_independent_targets_when_given() -> None:
    g = torch.Generator().manual_seed(2)
    pred = torch.rand(1, 3, 8, 8, generator=g)
    coeffs = torch.randn(1, 21, 8, 8, generator=g)
    planes = torch.rand(1, 12, 8, 8, generator=g)
    targets = torch.rand(1, 9, 8, 8, generator=g)
    feats = torch.rand(1, 7, 8, 8, generator=g)
    paired = loss_terms(pred, coeffs, planes, feats, targets)
    assert float(paired.data) == pytest.approx(float(data_loss(pred, targets[:, :3])))
    assert float(paired.grad) == pytest.approx(float(gradient_loss(pred, targets[:, 3:6], targets[:, 6:9])))
    # the first-order term's edge weight reads the input's base, never the target's
    assert float(paired.first) == pytest.approx(float(first_order_loss(pred, coeffs, feats, planes[:, :3])))
    assert float(paired.data) != pytest.approx(float(loss_terms(pred, coeffs, planes, feats).data))


def test_noise2noise_data_term_is_minimised_by_the_clean_image_not_the_input() -> None:
    """With a target independent of the input, predicting the noisy input costs more than predicting the
    clean image: the loss no longer rewards copying the input's noise (it does without targets)."""
    g = torch.Generator().manual_seed(3)
    clean = torch.full((1, 3, 64, 64), 0.5)
    noisy = [clean * torch.empty_like(clean).exponential_(generator=g) for _ in range(2)]  # mean-one noise
    enc = TRANSFER.forward
    inp, tgt = noisy
    own = lambda x: float(data_loss(enc(x), inp, pool=1))  # noqa: E731 - the self-supervised data term
    n2n = lambda x: float(data_loss(enc(x), tgt, pool=1))  # noqa: E731
    assert own(inp) < own(clean)          # self-supervised: copying the input is optimal
    assert n2n(clean) < 0.5 * n2n(inp)    # Noise2Noise: the clean image wins clearly


def test_gbranch_loss_explains_the_noisy_input_and_trains_only_the_coefficients() -> None:
    g = torch.Generator().manual_seed(2)
    planes = torch.rand(1, 9, 4, 4, generator=g) * 3
    feats = torch.rand(1, 7, 4, 4, generator=g)
    coeffs = torch.randn(1, 21, 4, 4, generator=g, requires_grad=True)
    loss = gbranch_loss(coeffs, planes, feats)
    expected = first_order_loss(TRANSFER.forward(planes[:, :3]), coeffs, feats, planes[:, :3])
    assert float(loss.detach()) == pytest.approx(float(expected.detach()))
    loss.backward()
    assert coeffs.grad is not None and float(coeffs.grad.abs().sum()) > 0


def test_beta_schedule() -> None:
    beta = BetaSchedule()
    assert [beta(e) for e in (0, 1)] == [0.0, 0.0]
    assert beta(2) == pytest.approx(0.1) and beta(3) == pytest.approx(0.125)
    assert all(beta(e) <= beta(e + 1) for e in range(40))
    assert beta(16) == 2.0 and beta(10 ** 6) == 2.0
    gradnet = BetaSchedule(warmup_epochs=6, growth=1.1)
    assert gradnet(5) == 0.0 and gradnet(6) == pytest.approx(0.1) and gradnet(7) == pytest.approx(0.11)
