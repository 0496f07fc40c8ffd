"""The ``oidn`` method and plain (gradient-free) frames: OIDN per layer, features prefiltered once per frame,
exposure-invariant, energy kept on stiff inputs, and clear errors where a frame lacks what a method needs."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyoidn")

from gradsep.model.errors import ChannelError  # noqa: E402
from gradsep.model.exr_read import read_frame  # noqa: E402
from gradsep.model.exr_write import write_frame  # noqa: E402
from gradsep.model.frame import Features, Frame, Layer  # noqa: E402
from gradsep.model.oidn import MIN_SIDE, SETTINGS, Denoiser, exposure_scale, input_scale, shared_denoiser  # noqa: E402
from gradsep.model.oidn import method_setting as oidn_method_setting  # noqa: E402
from gradsep.model.reconstruct import available_methods, choose_method, reconstruct  # noqa: E402
from gradsep.model.robust import lit_level  # noqa: E402


def _image(h: int, w: int, seed: int = 0, noise: float = 0.3) -> np.ndarray:
    """A smooth image with multiplicative noise, like a few-spp render of a diffuse scene."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    clean = 0.6 + 0.4 * np.sin(x[..., None] / 7.0 + np.arange(3)) * np.cos(y[..., None] / 5.0)
    return (clean * rng.gamma(1 / noise**2, noise**2, (h, w, 3))).astype(np.float32), clean.astype(np.float32)


def _features(h: int, w: int) -> Features:
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1.0
    return Features(np.full((h, w, 3), 0.7, np.float32), normal, np.ones((h, w), np.float32))


def _plain(h: int = 40, w: int = 56, features: bool = True, scale: float = 1.0) -> Frame:
    noisy, _ = _image(h, w)
    layers = {"direct": Layer(noisy * scale), "indirect": Layer(0.3 * noisy[::-1] * scale)}
    return Frame(layers, _features(h, w) if features else None)


def test_oidn_denoises_towards_the_clean_image() -> None:
    noisy, clean = _image(64, 64, seed=1)
    out = shared_denoiser("prefiltered-high").denoise(noisy)
    err_in, err_out = np.mean((noisy - clean) ** 2), np.mean((out - clean) ** 2)
    assert err_out < 0.3 * err_in, (err_in, err_out)
    assert out.mean() == pytest.approx(noisy.mean(), rel=0.05)  # energy kept


@pytest.mark.parametrize("scale", [1e-8, 1e-4, 1e4, 1e6, 1e9])
def test_oidn_is_exposure_invariant_from_1e_minus_8_to_1e9(scale: float) -> None:
    """Relative accuracy per decade: the frame scaled by k denoises to k times the unit frame's result."""
    frame = _plain()
    unit = reconstruct(frame, "oidn")
    scaled = reconstruct(_plain(scale=scale), "oidn")
    rel = np.abs(scaled.image / scale - unit.image) / np.maximum(unit.image, 1e-6)
    assert rel.max() < 1e-3 and not scaled.warnings
    assert scaled.image.mean() / scale == pytest.approx(sum(lay.base.mean() for lay in frame.layers.values()),
                                                         rel=0.05)


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 1), (3, 4), (MIN_SIDE - 1, 33), (17, 9)])
def test_tiny_and_odd_sizes_keep_their_energy(shape: tuple[int, int]) -> None:
    """OIDN alone returns 23 % of a constant 1×1 image and moves a coloured one by 5-16 %: every channel's mean
    of a frame under MIN_SIDE is kept exactly, and larger odd sizes within 5 %."""
    h, w = shape
    rng = np.random.default_rng(h * 100 + w)
    for value in (1.0, 3.5e5):
        image = (value * rng.uniform(0.2, 1.0, (h, w, 3))).astype(np.float32)
        out = shared_denoiser("prefiltered-high").denoise(image)
        assert out.shape == (h, w, 3) and np.isfinite(out).all()
        rel = 1e-5 if min(h, w) < MIN_SIDE else 0.05
        for c in range(3):
            assert out[..., c].mean() == pytest.approx(image[..., c].mean(), rel=rel), (shape, value, c)


def test_black_and_nonfinite_inputs() -> None:
    d = shared_denoiser("prefiltered-high")
    assert not d.denoise(np.zeros((8, 9, 3), np.float32)).any()          # black in, black out (no filter run)
    bad = np.ones((24, 24, 3), np.float32)
    bad[3, 4] = np.nan
    bad[5, 6] = np.inf
    bad[7, 8] = -np.inf
    out = d.denoise(bad)
    assert np.isfinite(out).all() and (out >= 0).all()
    assert input_scale(np.zeros((2, 2, 3), np.float32)) == 1.0


def test_prefilter_runs_once_per_frame_and_is_shared(monkeypatch) -> None:
    calls = []
    real = Denoiser.prefilter
    monkeypatch.setattr(Denoiser, "prefilter", lambda self, f: calls.append(1) or real(self, f))
    result = reconstruct(_plain(), "oidn")
    assert len(calls) == 1 and "features" in result.timings
    assert set(result.layers) == {"direct", "indirect"}


def test_features_change_the_result_and_are_optional() -> None:
    with_aux = reconstruct(_plain(), "oidn").image
    without = reconstruct(_plain(features=False), "oidn")
    assert without.method == "oidn" and "features" not in without.timings
    assert not np.allclose(with_aux, without.image)


def test_zero_features_are_served() -> None:
    frame = _plain()
    frame.features = Features(np.zeros((40, 56, 3), np.float32), np.zeros((40, 56, 3), np.float32),
                              np.zeros((40, 56), np.float32))
    result = reconstruct(frame, "oidn")
    assert np.isfinite(result.image).all() and result.image.mean() > 0


def test_plain_frame_round_trips_and_defaults_to_oidn(tmp_path) -> None:
    frame = _plain()
    write_frame(tmp_path / "plain.exr", frame, half=True)
    back = read_frame(tmp_path / "plain.exr")
    assert not back.has_gradients and set(back.layers) == {"direct", "indirect"}
    assert back.layers["direct"].dx is None and back.features is not None
    assert choose_method(back) == "oidn" and available_methods(back) == ["oidn"]
    for method in ("l1", "l2", "network", "fused"):
        with pytest.raises(ChannelError, match="integrates gradients") as err:
            reconstruct(back, method)
        assert "direct.dx.R" in err.value.details["missing"]


def test_plain_color_frame_without_features() -> None:
    noisy, _ = _image(30, 20)
    frame = Frame({"color": Layer(noisy)})
    result = reconstruct(frame)
    assert result.method == "oidn" and set(result.layers) == {"color"}
    assert result.image.mean() == pytest.approx(noisy.mean(), rel=0.05)


def test_oidn_on_a_gradient_frame_ignores_the_gradients() -> None:
    noisy, _ = _image(32, 32)
    dx = np.full_like(noisy, 1e3)  # absurd gradients: oidn does not read them
    with_gradients = reconstruct(Frame({"direct": Layer(noisy, dx, dx)}), "oidn").image
    plain = reconstruct(Frame({"direct": Layer(noisy)}), "oidn").image
    np.testing.assert_array_equal(with_gradients, plain)


# ------------------------------------------------------------------------------------------- settings


def test_oidn_runs_its_setting(monkeypatch) -> None:
    """``oidn`` runs METHOD_SETTING (the default denoiser's), or $GRADSEP_OIDN_SETTING (docs/oidn.md)."""
    from gradsep.model import oidn

    assert oidn.METHOD_SETTING in oidn.SETTINGS and shared_denoiser().setting.name == oidn.METHOD_SETTING
    used = []
    real = Denoiser.denoise
    monkeypatch.setattr(Denoiser, "denoise", lambda self, *a: used.append(self.setting.name) or real(self, *a))
    reconstruct(_plain(), "oidn")
    assert set(used) == {oidn.METHOD_SETTING}
    used.clear()
    monkeypatch.setenv(oidn.SETTING_ENV, "prefiltered-high")
    reconstruct(_plain(), "oidn")
    assert set(used) == {"prefiltered-high"}
    monkeypatch.setenv(oidn.SETTING_ENV, "sharpest")
    with pytest.raises(ValueError, match="raw-fast"):  # an unknown setting names the valid ones
        reconstruct(_plain(), "oidn")


def test_a_frame_asks_for_its_setting_and_the_answer_records_the_one_that_ran(monkeypatch, tmp_path) -> None:
    """A render plan's ``gradsep.oidn_setting`` header selects the setting of every OIDN run at the ``oidn``
    method's setting (oidn, oidn-l1); $GRADSEP_OIDN_SETTING wins over it; a header naming no setting is a warning,
    not an error; a method without OIDN reports none; the CLI's answer records the setting that ran."""
    from gradsep.cli import main
    from gradsep.model import oidn
    from gradsep.model.exr_read import read_header
    from gradsep.model.header_keys import OIDN_SETTING_KEY

    monkeypatch.delenv(oidn.SETTING_ENV, raising=False)
    used: list[str] = []
    real = Denoiser.denoise
    monkeypatch.setattr(Denoiser, "denoise", lambda self, *a: used.append(self.setting.name) or real(self, *a))
    frame = _plain()
    frame.metadata[OIDN_SETTING_KEY] = "prefiltered-high"
    result = reconstruct(frame, "oidn")
    assert set(used) == {"prefiltered-high"} and result.oidn_setting == "prefiltered-high" and not result.warnings
    frame.metadata[OIDN_SETTING_KEY] = "sharpest"
    result = reconstruct(frame, "oidn")
    assert result.oidn_setting == oidn.METHOD_SETTING
    assert any("sharpest" in w and oidn.METHOD_SETTING in w for w in result.warnings)
    monkeypatch.setenv(oidn.SETTING_ENV, "raw-fast-level")
    frame.metadata[OIDN_SETTING_KEY] = "prefiltered-high"
    assert reconstruct(frame, "oidn").oidn_setting == "raw-fast-level"
    monkeypatch.delenv(oidn.SETTING_ENV)
    noisy, _ = _image(24, 24)
    gradients = Frame({"direct": Layer(noisy, np.zeros_like(noisy), np.zeros_like(noisy))},
                      metadata={OIDN_SETTING_KEY: "prefiltered-high"})
    assert reconstruct(gradients, "oidn-l1").oidn_setting == "prefiltered-high"
    assert reconstruct(gradients, "l2").oidn_setting is None
    frame.metadata[OIDN_SETTING_KEY] = "prefiltered-high"
    write_frame(tmp_path / "in.exr", frame)
    for method, recorded in (("oidn", "prefiltered-high"), (None, "prefiltered-high")):
        args = ["reconstruct", str(tmp_path / "in.exr"), "-o", str(tmp_path / "out.exr")]
        assert main(args + (["--method", method] if method else [])) == 0
        assert read_header(str(tmp_path / "out.exr")).attributes.get(OIDN_SETTING_KEY) == recorded


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_every_setting_is_exposure_exact_energy_keeping_and_black_safe(name: str) -> None:
    """The stability guarantees hold per setting: 1e-8 and 1e9 scale exactly, black stays black, 1x1 keeps its
    energy, and the auxiliary images follow the setting (denoised, or passed raw)."""
    denoiser = Denoiser(name)
    frame = _plain()
    aux = denoiser.prefilter(frame.features)
    assert aux.clean == name.startswith("prefiltered")
    assert aux.clean or np.array_equal(aux.albedo, frame.features.albedo)
    base = frame.layers["direct"].base
    unit = denoiser.denoise(base, aux)
    for scale in (1e-8, 1e9):
        scaled = denoiser.denoise(base * np.float32(scale), aux)
        rel = np.abs(scaled / scale - unit) / np.maximum(unit, 1e-6)
        assert np.isfinite(scaled).all() and rel.max() < 1e-3, (name, scale)
    assert not denoiser.denoise(np.zeros((8, 9, 3), np.float32), None).any()
    pixel = np.array([[[0.2, 3.0, 7.5]]], np.float32)
    np.testing.assert_allclose(denoiser.denoise(pixel, None), pixel, rtol=1e-5)
    with pytest.raises(ValueError, match="unknown OIDN setting"):
        Denoiser("fastest")


def test_the_lit_exposure_sets_the_lit_part_to_oidns_key_however_much_black_surrounds_it(monkeypatch) -> None:
    """``lit`` (the default) gives OIDN the layer scaled so its lit part's mean luminance is 0.18, OIDN's own
    autoexposure key, whatever the black around it; ``level`` (the fused models') scales the whole frame's robust
    level to 1."""
    rng = np.random.default_rng(5)
    patch = (0.5 + rng.random((32, 32, 3))).astype(np.float32)
    padded = np.zeros((160, 160, 3), np.float32)
    padded[64:96, 48:80] = patch
    for image in (patch, padded):
        assert exposure_scale(image) == pytest.approx(0.18 / lit_level(image))
        assert exposure_scale(image, "level") == input_scale(image)
    assert exposure_scale(padded) == pytest.approx(exposure_scale(patch), rel=1e-9)
    assert exposure_scale(padded, "level") > 20 * exposure_scale(patch, "level")  # the black dilutes its level
    seen: list[float] = []
    denoiser = Denoiser("raw-fast")
    real_run = denoiser._run
    monkeypatch.setattr(denoiser, "_run", lambda purpose, images, output, flags, scale=None: (
        seen.append(scale), real_run(purpose, images, output, flags, scale))[1])
    denoiser.denoise(padded, None)
    assert seen == [pytest.approx(exposure_scale(padded))]


def test_the_fused_candidates_denoise_at_the_exposure_they_were_trained_on(monkeypatch) -> None:
    """The blend models were trained on OIDN's image at the ``level`` exposure (the robust level over the whole
    frame at 1): their candidates' denoiser gives OIDN exactly that scale, where the ``oidn`` method's gives the
    lit part's."""
    from gradsep.model import fused

    rng = np.random.default_rng(6)
    padded = np.zeros((96, 96, 3), np.float32)
    padded[32:64, 40:72] = 0.5 + rng.random((32, 32, 3))
    for name, want in ((fused.OIDN_SETTING, input_scale(padded)), (oidn_method_setting(), exposure_scale(padded))):
        seen: list[float] = []
        denoiser = Denoiser(name)
        real_run = denoiser._run
        monkeypatch.setattr(denoiser, "_run", lambda purpose, images, output, flags, scale=None, d=real_run, s=seen: (
            s.append(scale), d(purpose, images, output, flags, scale))[1])
        denoiser.denoise(padded, None)
        assert seen == [pytest.approx(want)], name


def test_pyoidn_is_imported_without_torch_and_torch_stays_importable():
    """pyoidn imports torch for an optional tensor interface gradsep never uses; model.oidn.import_pyoidn keeps that
    1-2 s out of a render budget (fresh interpreter: nothing imported yet)."""
    import subprocess
    import sys

    code = ("import sys; from gradsep.model.oidn import import_pyoidn; p = import_pyoidn(); "
            "assert 'torch' not in sys.modules, 'torch was imported'; p.Device(); "
            "import importlib.util\nif importlib.util.find_spec('torch') is not None:\n"
            "    import torch; assert torch.zeros(1).sum().item() == 0\nprint('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
