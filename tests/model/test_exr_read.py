"""Reading a frame (model/exr_read.py): what is written reads back, every problem in the channels is named, untrusted
bytes get typed errors, the non-finite policy, and the variance channel."""

from __future__ import annotations

import struct

import numpy as np
import OpenEXR
import pytest

from gradsep.model.errors import ChannelError, FrameTooLargeError, NonFiniteError, NotExrError, UnsupportedExrError
from gradsep.model.exr_read import ReadLimits, read_frame, read_header
from gradsep.model.exr_write import encode_exr, write_frame
from gradsep.model.frame import (
    FEATURE_CHANNELS,
    VARIANCE_MAX,
    Frame,
    Layer,
)
from tests.model.frames import make_frame


def patch_data_window(data: bytes, width: int, height: int) -> bytes:
    """Rewrite the dataWindow attribute of an EXR header in place (a crafted header, as an attacker would)."""
    key = b"dataWindow\x00box2i\x00"
    at = data.index(key) + len(key)
    assert struct.unpack("<i", data[at:at + 4])[0] == 16
    box = struct.pack("<4i", 0, 0, width - 1, height - 1)
    return data[:at + 4] + box + data[at + 20:]


# -- round trip --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("half", [False, True])
@pytest.mark.parametrize("layers", [("direct", "indirect"), ("direct",), ("indirect",), ("color",)])
def test_round_trip(tmp_path, half: bool, layers: tuple[str, ...]) -> None:
    frame = make_frame(layers=layers)
    path = tmp_path / "f.exr"
    write_frame(path, frame, half=half)
    back = read_frame(path)
    assert list(back.layers) == list(layers)
    tol = 2e-3 if half else 0
    for name in layers:
        np.testing.assert_allclose(back.layers[name].base, frame.layers[name].base, rtol=tol, atol=tol)
        np.testing.assert_allclose(back.layers[name].dy, frame.layers[name].dy, rtol=tol, atol=tol)
        assert back.layers[name].base.dtype == np.float32
    np.testing.assert_allclose(back.features.depth, frame.features.depth, rtol=tol)
    assert back.metadata["gradsep.spp"] == "16"
    assert (back.width, back.height) == (9, 6)
    assert read_frame(path.read_bytes()).layers.keys() == back.layers.keys()  # bytes source
    with open(path, "rb") as fh:  # stream source
        assert read_frame(fh).width == 9


@pytest.mark.parametrize("compression", ["NO_COMPRESSION", "RLE_COMPRESSION", "PIZ_COMPRESSION", "ZSTD_COMPRESSION",
                                         "DWAA_COMPRESSION", "PXR24_COMPRESSION"])
def test_any_compression_openexr_reads(tmp_path, compression: str) -> None:
    frame = make_frame(layers=("direct",), features=False)
    header = {"compression": getattr(OpenEXR, compression), "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, dict(frame.to_channels())).write(str(tmp_path / "c.exr"))
    back = read_frame(tmp_path / "c.exr")
    lossy = compression in ("DWAA_COMPRESSION", "PXR24_COMPRESSION")
    np.testing.assert_allclose(back.layers["direct"].base, frame.layers["direct"].base, rtol=5e-2 if lossy else 0)


def test_features_are_optional_as_a_whole() -> None:
    frame = read_frame(encode_exr(make_frame(features=False).to_channels()))
    assert frame.features is None


def test_foreign_channels_are_ignored_with_a_warning() -> None:
    channels = make_frame().to_channels()
    channels["custom.aov"] = np.ones_like(channels["depth.Z"])
    frame = read_frame(encode_exr(channels))
    assert any("custom.aov" in w for w in frame.warnings)


def test_alpha_is_read_and_written_back() -> None:
    channels = make_frame().to_channels()
    channels["A"] = np.linspace(0, 1, channels["depth.Z"].size, dtype=np.float32).reshape(channels["depth.Z"].shape)
    frame = read_frame(encode_exr(channels))
    assert frame.warnings == [] and frame.layout == "gradsep"
    np.testing.assert_array_equal(frame.alpha, channels["A"])
    np.testing.assert_array_equal(frame.to_channels()["A"], channels["A"])


@pytest.mark.parametrize("nonfinite", ["reject", "zero"])
def test_nonfinite_alpha_becomes_0_and_the_warning_counts_it(nonfinite: str) -> None:
    """Alpha is not radiance, so no policy rejects it, but every value replaced is reported: three bad values
    (NaN, +Inf, -Inf) become 0, one warning names the channel and the count, and the other values are kept."""
    channels = make_frame().to_channels()
    alpha = np.full_like(channels["depth.Z"], 0.5)
    alpha[0, 0], alpha[1, 2], alpha[-1, -1] = np.nan, np.inf, -np.inf
    channels["A"] = alpha
    frame = read_frame(encode_exr(channels), nonfinite=nonfinite)
    assert frame.alpha[0, 0] == frame.alpha[1, 2] == frame.alpha[-1, -1] == 0
    assert np.count_nonzero(frame.alpha == 0.5) == alpha.size - 3
    assert [w for w in frame.warnings if "alpha" in w] == ["replaced non-finite alpha values with 0 in A (3)"]


def test_a_finite_alpha_reads_without_a_warning() -> None:
    channels = make_frame().to_channels()
    channels["A"] = np.zeros_like(channels["depth.Z"])
    assert read_frame(encode_exr(channels)).warnings == []


# -- channel validation names every problem --------------------------------------------------------------------


def test_missing_and_unknown_channels_are_all_named() -> None:
    channels = make_frame().to_channels()
    del channels["indirect.dy.B"], channels["normal.Y"]
    channels["direct.dz.R"] = channels["depth.Z"]
    with pytest.raises(ChannelError) as err:
        read_frame(encode_exr(channels))
    assert err.value.status == 422
    assert err.value.details["missing"] == ["indirect.dy.B", "normal.Y"]
    assert err.value.details["unknown"] == ["direct.dz.R"]
    assert "indirect.dy.B" in str(err.value) and "direct.dz.R" in str(err.value)


def test_plain_frames_carry_bases_only_and_gradients_are_per_layer() -> None:
    channels = make_frame().to_channels()
    plain = {k: v for k, v in channels.items() if ".dx." not in k and ".dy." not in k}
    frame = read_frame(encode_exr(plain))
    assert not frame.has_gradients and frame.layers["indirect"].dy is None and frame.gradient_layers == ()
    assert frame.to_channels().keys() == plain.keys()  # writes back exactly what it read
    # a layer with some but not all of its gradient channels: the missing ones (of that layer only) are named
    partial = dict(channels)
    del partial["indirect.dx.G"], partial["indirect.dy.R"], partial["direct.dy.B"]
    with pytest.raises(ChannelError) as err:
        read_frame(encode_exr(partial))
    assert err.value.details["missing"] == ["direct.dy.B", "indirect.dx.G", "indirect.dy.R"]
    with pytest.raises(ValueError, match="both gradients"):
        Layer(np.zeros((2, 2, 3), np.float32), np.zeros((2, 2, 3), np.float32))


@pytest.mark.parametrize("plain_layer", ["indirect", "direct"])
def test_a_frame_may_carry_gradients_on_some_layers_only(tmp_path, plain_layer: str) -> None:
    """`gradsep render --gradients direct`: the direct layer's nine channels and a plain indirect layer (and, as
    the contract is per layer, the other way round too). Read back exactly; has_gradients means every layer."""
    channels = {k: v for k, v in make_frame().to_channels().items()
                if not k.startswith((f"{plain_layer}.dx.", f"{plain_layer}.dy."))}
    frame = read_frame(encode_exr(channels))
    with_gradients = "direct" if plain_layer == "indirect" else "indirect"
    assert frame.gradient_layers == (with_gradients,) and not frame.has_gradients
    assert frame.layers[plain_layer].dx is None and frame.layers[with_gradients].dy is not None
    assert frame.to_channels().keys() == channels.keys()
    for name, value in frame.to_channels().items():
        np.testing.assert_array_equal(value, channels[name], err_msg=name)
    write_frame(tmp_path / "mixed.exr", frame)
    assert read_frame(tmp_path / "mixed.exr").gradient_layers == (with_gradients,)
    # the non-finite policy covers the gradients that are there, and only those
    channels[f"{with_gradients}.dx.R"][0, 0] = np.nan
    with pytest.raises(NonFiniteError) as err:
        read_frame(encode_exr(channels))
    assert err.value.details == {f"{with_gradients}.dx.R": 1}


def test_no_illumination_layer() -> None:
    channels = {c: np.zeros((2, 2), np.float32) for c in FEATURE_CHANNELS}
    with pytest.raises(ChannelError, match="no illumination layer"):
        read_frame(encode_exr(channels))


def test_color_and_separated_layers_do_not_mix() -> None:
    channels = make_frame(layers=("direct", "color")).to_channels()
    with pytest.raises(ChannelError, match="not both"):
        read_frame(encode_exr(channels))


# -- untrusted bytes ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("data", [b"", b"\x00", b"GIF89a" + b"\x00" * 100, b"v/1\x01", bytes(range(256)) * 4])
def test_garbage_is_not_exr(data: bytes) -> None:
    with pytest.raises(NotExrError):
        read_frame(data)


def test_every_truncation_is_a_typed_error() -> None:
    data = encode_exr(make_frame(h=20, w=17).to_channels())
    for cut in range(0, len(data), max(1, len(data) // 97)):
        with pytest.raises((NotExrError, ChannelError)):
            read_frame(data[:cut])


def test_huge_declared_size_is_rejected_from_the_header() -> None:
    data = patch_data_window(encode_exr(make_frame(h=4, w=4).to_channels()), 200_000, 200_000)
    with pytest.raises(FrameTooLargeError) as err:
        read_header(data)
    assert err.value.status == 413 and err.value.details["width"] == 200_000
    with pytest.raises(FrameTooLargeError):
        read_frame(data)


def test_value_budget_counts_channels() -> None:
    data = encode_exr(make_frame(h=10, w=10).to_channels())
    limits = ReadLimits(max_pixels=100, max_values=100 * 20)  # 25 channels > 20
    with pytest.raises(FrameTooLargeError, match="channels"):
        read_frame(data, limits=limits)
    assert read_frame(data, limits=ReadLimits(max_pixels=100, max_values=100 * 25)).width == 10


def test_tiled_and_multipart_are_rejected(tmp_path) -> None:
    tile = OpenEXR.TileDescription()
    tile.xSize, tile.ySize, tile.mode = 16, 16, OpenEXR.ONE_LEVEL
    channels = make_frame(layers=("direct",), features=False).to_channels()
    OpenEXR.File({"type": OpenEXR.tiledimage, "tiles": tile}, dict(channels)).write(str(tmp_path / "t.exr"))
    with pytest.raises(UnsupportedExrError, match="tiled"):
        read_frame(tmp_path / "t.exr")
    parts = [OpenEXR.Part({}, dict(channels), "a"), OpenEXR.Part({}, dict(channels), "b")]
    OpenEXR.File(parts).write(str(tmp_path / "m.exr"))
    with pytest.raises(UnsupportedExrError, match="multi-part"):
        read_frame(tmp_path / "m.exr")


def test_missing_file_is_a_typed_error(tmp_path) -> None:
    with pytest.raises(NotExrError, match="cannot read"):
        read_frame(tmp_path / "absent.exr")


# -- non-finite policy -------------------------------------------------------------------------------------------


def nonfinite_frame(half: bool) -> bytes:
    channels = make_frame().to_channels()
    channels["direct.R"][0, 0] = 1e6 if half else np.inf  # 1e6 overflows half to +Inf
    channels["indirect.dx.G"][1, :3] = np.nan
    channels["normal.X"][2, 2] = np.nan
    channels["depth.Z"][0, 1] = np.inf
    return encode_exr(channels, half=False) if not half else _encode_raw_half(channels)


def _encode_raw_half(channels: dict[str, np.ndarray]) -> bytes:
    """Half without saturation: what a renderer that overflowed would write."""
    import io

    buf = io.BytesIO()
    with np.errstate(over="ignore"):
        pixels = {k: v.astype(np.float16) for k, v in channels.items()}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, pixels).write(buf)
    return buf.getvalue()


@pytest.mark.parametrize("half", [False, True])
def test_nonfinite_radiance_is_rejected_naming_channel_and_count(half: bool) -> None:
    with pytest.raises(NonFiniteError) as err:
        read_frame(nonfinite_frame(half))
    assert err.value.details == {"direct.R": 1, "indirect.dx.G": 3}
    assert "direct.R (1)" in str(err.value)


@pytest.mark.parametrize("half", [False, True])
def test_nonfinite_zero_policy_sanitises_and_warns(half: bool) -> None:
    frame = read_frame(nonfinite_frame(half), nonfinite="zero")
    assert frame.layers["direct"].base[0, 0, 0] == 0
    assert frame.features.normal[2, 2, 0] == 0 and frame.features.depth[0, 1] == 0
    for arr in frame.to_channels().values():
        assert np.isfinite(arr).all()
    assert any("indirect.dx.G (3)" in w for w in frame.warnings)


def test_features_are_always_zeroed_even_under_reject() -> None:
    channels = make_frame().to_channels()
    channels["albedo.G"][0, 0] = np.nan
    frame = read_frame(encode_exr(channels))
    assert frame.features.albedo[0, 0, 1] == 0


# -- the variance channel ----------------------------------------------------------------------------------------


def _with_variance(frame: Frame, seed: int = 1) -> Frame:
    rng = np.random.default_rng(seed)
    for layer in frame.layers.values():
        layer.var = (rng.random(layer.base.shape[:2]) * 1e-9).astype(np.float32)  # below half's smallest value
    return frame


@pytest.mark.parametrize("half", [False, True])
def test_variance_round_trips_in_float32_even_in_a_half_file(tmp_path, half: bool) -> None:
    frame = _with_variance(make_frame())
    path = tmp_path / "v.exr"
    write_frame(path, frame, half=half)
    with OpenEXR.File(str(path)) as exr:
        kinds = {name: ch.pixels.dtype for name, ch in exr.channels().items()}
    assert kinds["direct.var.Y"] == np.float32 and kinds["indirect.var.Y"] == np.float32
    assert kinds.get("direct.R", kinds.get("direct")) == (np.float16 if half else np.float32)  # RGB may be grouped
    back = read_frame(path)
    for name, layer in frame.layers.items():
        np.testing.assert_array_equal(back.layers[name].var, layer.var)
    assert back.warnings == []


def test_a_frame_without_variance_reads_as_none() -> None:
    back = read_frame(encode_exr(make_frame().to_channels()))
    assert all(layer.var is None for layer in back.layers.values())


def test_a_variance_channel_that_is_not_a_variance_is_dropped_with_a_warning() -> None:
    frame = _with_variance(make_frame())
    frame.layers["direct"].var[0, 0] = np.nan
    frame.layers["indirect"].var[1, 1] = -1.0
    back = read_frame(encode_exr(frame.to_channels()))
    assert back.layers["direct"].var is None and back.layers["indirect"].var is None
    text = " ".join(back.warnings)
    assert "direct.var.Y has 1 NaN or negative" in text and "indirect.var.Y has 1 NaN or negative" in text


def test_an_infinite_variance_reads_as_the_cap() -> None:
    frame = _with_variance(make_frame())
    frame.layers["direct"].var[2, 3] = np.inf
    back = read_frame(encode_exr(frame.to_channels()))
    assert back.layers["direct"].var[2, 3] == np.float32(VARIANCE_MAX) and back.warnings == []


def test_a_variance_without_its_layer_or_of_another_kind_is_named() -> None:
    channels = make_frame(layers=("direct",)).to_channels()
    channels["indirect.var.Y"] = np.zeros((6, 9), np.float32)
    with pytest.raises(ChannelError, match="missing channels indirect.R"):
        read_frame(encode_exr(channels))
    channels = make_frame(layers=("direct",)).to_channels()
    channels["direct.var.R"] = np.zeros((6, 9), np.float32)
    with pytest.raises(ChannelError, match="unknown channels direct.var.R"):
        read_frame(encode_exr(channels))
