"""Numerical stability on stiff and extreme inputs: every output finite, IRLS convergent, policies explicit.

Each solve runs under ``np.errstate(divide/over/invalid="raise")``: a division by zero or an overflow anywhere in
the solvers is a failure even when the final image happens to come out finite.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from model.frame import Frame, Layer, NonFiniteError, forward_differences, layer_channels, read_frame
from model.poisson import energy_l1, solve_l1, solve_l2
from model.reconstruct import reconstruct

ALPHAS = [1e-4, 1e-2, 0.2, 10.0, 1e3]
SIZES = [(1, 1), (1, 12), (11, 1), (7, 9), (31, 17)]


def _solve(method: str, base, dx, dy, alpha: float = 0.2) -> np.ndarray:
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        if method == "l2":
            return solve_l2(base, dx, dy, alpha)
        image, stats = solve_l1(base, dx, dy, alpha)
        assert np.isfinite(stats.energies).all() and np.isfinite(stats.cg_residuals).all()
        return image


def _noisy(h: int, w: int, seed: int, scale: float = 1.0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    image = scale * rng.random((h, w, 3))
    dx, dy = forward_differences(image)
    base = image * (1 + rng.normal(0, 0.5, image.shape))
    dx = dx + scale * rng.normal(0, 0.1, dx.shape)
    dy = dy + scale * rng.normal(0, 0.1, dy.shape)
    return tuple(a.astype(np.float32) for a in (base, dx, dy))


@pytest.mark.parametrize("alpha", ALPHAS)
@pytest.mark.parametrize("method", ["l1", "l2"])
def test_alpha_sweep_exact_data_recovered(method: str, alpha: float) -> None:
    yy, xx = np.mgrid[0:24, 0:29] / 29
    image = np.stack([0.3 + np.sin(4 * xx + c) * yy for c in range(3)], -1).astype(np.float32)
    dx, dy = forward_differences(image)
    got = _solve(method, image, dx, dy, alpha)
    assert np.abs(got - image).max() <= 1e-6 * np.abs(image).max()


@pytest.mark.parametrize("alpha", ALPHAS)
@pytest.mark.parametrize("size", SIZES)
def test_alpha_sweep_noisy_data_finite_and_irls_converges(size: tuple[int, int], alpha: float) -> None:
    """Near-singular at α = 1e-4: the DCT solve stays exact (test_poisson) and IRLS must still lower its
    objective from the L2 start without producing anything non-finite."""
    base, dx, dy = _noisy(*size, seed=size[0] * 100 + size[1])
    l2 = _solve("l2", base, dx, dy, alpha)
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        l1, stats = solve_l1(base, dx, dy, alpha)
    assert np.isfinite(l2).all() and np.isfinite(l1).all()
    assert stats.energies[-1] <= stats.energies[0] * (1 + 1e-6)
    assert energy_l1(l1, base, dx, dy, alpha) <= energy_l1(l2, base, dx, dy, alpha) * (1 + 1e-5)


@pytest.mark.parametrize("method", ["l1", "l2"])
def test_radiance_spanning_1e_minus_8_to_1e6(method: str) -> None:
    rng = np.random.default_rng(0)
    image = (10.0 ** rng.uniform(-8, 6, size=(40, 33, 3))).astype(np.float32)
    dx, dy = forward_differences(image)
    exact = _solve(method, image, dx, dy)
    assert np.abs(exact - image).max() <= 1e-6 * np.abs(image).max()
    noisy = _solve(method, image * rng.uniform(0.5, 1.5, image.shape).astype(np.float32), dx, dy)
    assert np.isfinite(noisy).all()


@pytest.mark.parametrize("where", ["base", "dx", "dy"])
@pytest.mark.parametrize("method", ["l1", "l2"])
def test_single_pixel_firefly_of_1e6(method: str, where: str) -> None:
    yy, xx = np.mgrid[0:32, 0:32] / 32
    image = np.stack([0.5 + 0.2 * np.sin(5 * xx + c) for c in range(3)], -1).astype(np.float32)
    arrays = dict(zip(("base", "dx", "dy"), (image, *forward_differences(image)), strict=True))
    arrays = {k: v.copy() for k, v in arrays.items()}
    arrays[where][16, 15] += 1e6
    got = _solve(method, arrays["base"], arrays["dx"], arrays["dy"])
    assert np.isfinite(got).all()
    if method == "l1":  # an isolated outlier term gets a tiny IRLS weight: far less damage than under L2
        l2 = solve_l2(arrays["base"], arrays["dx"], arrays["dy"])
        assert np.abs(got - image).max() < 0.05 * np.abs(l2 - image).max()
        # ... and given CG steps enough to converge each pass, IRLS removes it entirely
        converged, _ = solve_l1(arrays["base"], arrays["dx"], arrays["dy"], cg_iterations=60)
        assert np.abs(converged - image).max() < 1e-6 * 1e6


@pytest.mark.parametrize("method", ["l1", "l2"])
@pytest.mark.parametrize("size", SIZES)
def test_all_black(method: str, size: tuple[int, int]) -> None:
    zeros = np.zeros((*size, 3), np.float32)
    got = _solve(method, zeros, zeros, zeros)
    assert got.shape == zeros.shape and not got.any()


@pytest.mark.parametrize("method", ["l1", "l2"])
def test_values_near_the_float32_limit_stay_finite(method: str) -> None:
    rng = np.random.default_rng(1)
    base = (rng.random((16, 16, 3)) * 3e38).astype(np.float32)
    dx = (rng.uniform(-1, 1, size=base.shape) * 3e38).astype(np.float32)
    dy = (rng.uniform(-1, 1, size=base.shape) * 3e38).astype(np.float32)
    if method == "l2":
        got = solve_l2(base, dx, dy, 1e-4)  # float64 inside; the result is clipped into float32 range
    else:
        got, _ = solve_l1(base, dx, dy)
    assert np.isfinite(got).all()


# ------------------------------------------------------------ non-finite inputs through the frame reader


def _write_half_frame(path: Path, layers: dict[str, Layer], poison: dict[str, list[float]]) -> None:
    """Write half channels with OpenEXR directly (our writer saturates, a renderer's may not): values that
    overflowed half (> 65504 -> Inf) and NaNs, poked into the named channels."""
    channels = {}
    for name, layer in layers.items():
        for prefix, image in ((name, layer.base), (f"{name}.dx", layer.dx), (f"{name}.dy", layer.dy)):
            for i, c in enumerate("RGB"):
                channels[f"{prefix}.{c}"] = image[..., i].astype(np.float16)
    for channel, values in poison.items():
        flat = channels[channel].reshape(-1)
        with np.errstate(over="ignore"):
            flat[: len(values)] = np.asarray(values, dtype=np.float32).astype(np.float16)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))


def _two_layers(h: int = 12, w: int = 15) -> dict[str, Layer]:
    yy, xx = np.mgrid[0:h, 0:w] / w
    out = {}
    for name, s in (("direct", 1.0), ("indirect", 0.25)):
        image = np.stack([s * (0.5 + 0.4 * np.sin(3 * xx + c) * yy) for c in range(3)], -1).astype(np.float32)
        out[name] = Layer(image, *forward_differences(image))
    return out


POISON = {"direct.R": [70000.0, -1e6], "indirect.dy.B": [np.nan, np.inf, np.nan]}


def test_half_overflow_and_nan_rejected_naming_channel_and_count(tmp_path: Path) -> None:
    _write_half_frame(tmp_path / "f.exr", _two_layers(), POISON)
    with pytest.raises(NonFiniteError) as info:
        read_frame(tmp_path / "f.exr")  # "reject" is the default policy
    assert info.value.details == {"direct.R": 2, "indirect.dy.B": 3}
    assert "direct.R (2)" in str(info.value) and "indirect.dy.B (3)" in str(info.value)


@pytest.mark.parametrize("method", ["l1", "l2"])
def test_half_overflow_and_nan_zeroed_with_warning_then_reconstructed(tmp_path: Path, method: str) -> None:
    _write_half_frame(tmp_path / "f.exr", _two_layers(), POISON)
    frame = read_frame(tmp_path / "f.exr", nonfinite="zero")
    assert len(frame.warnings) == 1 and "direct.R (2)" in frame.warnings[0]
    assert frame.layers["direct"].base[0, 0, 0] == 0 and frame.layers["indirect"].dy[0, 2, 2] == 0
    for layer in frame.layers.values():
        assert all(np.isfinite(a).all() for a in (layer.base, layer.dx, layer.dy))
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        result = reconstruct(frame, method)
    assert np.isfinite(result.image).all() and (result.image >= 0).all() and not result.warnings


def test_clean_half_frame_reconstructs_like_float(tmp_path: Path) -> None:
    layers = _two_layers()
    _write_half_frame(tmp_path / "f.exr", layers, {})
    frame = read_frame(tmp_path / "f.exr")
    assert not frame.warnings
    reference = reconstruct(Frame(layers), "l2").image
    np.testing.assert_allclose(reconstruct(frame, "l2").image, reference, atol=2e-3)
    assert set(layer_channels("direct")) <= set(frame.to_channels())


@pytest.mark.parametrize("method", ["l1", "l2"])
@pytest.mark.parametrize("size", SIZES)
def test_reconstruct_output_finite_for_degenerate_sizes(method: str, size: tuple[int, int]) -> None:
    layers = {}
    for i, name in enumerate(("direct", "indirect")):
        base, dx, dy = _noisy(*size, seed=i, scale=10.0 ** (3 * i - 2))
        layers[name] = Layer(base, dx, dy)
    result = reconstruct(Frame(layers), method)
    assert result.image.shape == (*size, 3)
    assert np.isfinite(result.image).all() and (result.image >= 0).all()
