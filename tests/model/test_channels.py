"""Channel layouts (model/channels.py) and what an answer carries over (model.exr_write.encode_answer), through
``read_frame`` and ``gradsep reconstruct``: frames from other renderers, alpha, header metadata, warnings."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from gradsep.cli import main
from gradsep.model.channels import (
    LAYOUTS,
    ChannelMap,
    Layout,
    candidates,
    check_layout,
    layout_choices,
    layout_pattern,
    map_channels,
)
from gradsep.model.errors import ChannelError
from gradsep.model.exr_read import read_frame
from gradsep.model.exr_write import encode_answer, encode_exr, write_exr
from gradsep.model.frame import rgb_channels
from tests.service.frames import frame_channels

H, W = 12, 16
RNG = np.random.default_rng(7)


def _plane(low: float = 0.0, high: float = 1.0) -> np.ndarray:
    return RNG.uniform(low, high, (H, W)).astype(np.float32)


def _exr(channels: dict[str, np.ndarray], header: dict | None = None) -> bytes:
    buffer = io.BytesIO()
    base = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})}
    OpenEXR.File(base, {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}).write(buffer)
    return buffer.getvalue()


def _beauty(alpha: bool = True) -> dict[str, np.ndarray]:
    return {c: _plane(0.1, 2.0) for c in ("R", "G", "B", *(("A",) if alpha else ()))}


def test_layout_arguments_are_checked_against_the_table() -> None:
    """Every name of the table and ``auto`` is a valid argument, a row with a qualifier takes NAME:QUALIFIER as
    well, and anything else is refused naming every form."""
    for good in (*layout_choices(), "cycles:ViewLayer", "cycles:My.Layer"):
        assert check_layout(good) == good
    for bad in ("", "cycle", "cycles:", "mitsuba", "AUTO", "gradsep:x", "mitsuba-aov:x"):
        with pytest.raises(ValueError, match="unknown channel layout .*auto, gradsep, mitsuba-aov, cycles or "
                                             "cycles:VIEWLAYER"):
            check_layout(bad)


def _toy_layout() -> Layout:
    """A renderer whose beauty is ``toy.R toy.G toy.B``: one row, as a new layout would be added."""
    return Layout("toy-beauty", "a toy renderer's beauty", "a toy.R toy.G toy.B beauty",
                  lambda names: ["toy-beauty"] if "toy.R" in names else [],
                  lambda names, _qualifier: ChannelMap("toy-beauty", {f"color.{c}": f"toy.{c}" for c in "RGB"}))


def test_a_layout_added_as_one_row_is_read_detected_and_offered_everywhere(monkeypatch) -> None:
    """The table is the only place a layout is named: a new row is read (by name and by ``auto``), is named in the
    error for a file that matches nothing, and appears in ``gradsep reconstruct --channels``, ``gradsep client
    --channels`` and the service's ``channels`` parameter (its pattern and its description)."""
    from fastapi import FastAPI

    from gradsep.cli import build_parser
    from gradsep.service.routers.reconstruct import build_router

    monkeypatch.setitem(LAYOUTS, "toy-beauty", _toy_layout())
    toy = {f"toy.{c}": _plane() for c in "RGB"}
    for layout in ("toy-beauty", "auto"):
        frame = read_frame(_exr(toy), layout=layout)
        assert frame.layout == "toy-beauty" and list(frame.layers) == ["color"]
        np.testing.assert_array_equal(frame.layers["color"].base[..., 1], toy["toy.G"])
    with pytest.raises(ChannelError, match="a toy.R toy.G toy.B beauty"):
        read_frame(_exr({"other": _plane()}))
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for command in ("reconstruct", "client"):
        option = next(a for a in sub.choices[command]._actions if a.dest == "channels")
        assert "toy-beauty" in option.help, (command, option.help)
    app = FastAPI()
    app.include_router(build_router())
    params = app.openapi()["paths"]["/v1/reconstruct"]["post"]["parameters"]
    channels = next(p for p in params if p["name"] == "channels")
    assert channels["schema"]["pattern"] == layout_pattern() and "toy-beauty" in layout_pattern()
    assert "toy-beauty" in channels["description"]


def test_a_layout_row_needs_a_plain_name() -> None:
    for bad in ("auto", "Toy", "toy beauty", "", "toy:x"):
        with pytest.raises(ValueError, match="layout's name"):
            Layout(bad, "", "", lambda names: [], lambda names, _q: ChannelMap("toy", {}))


def test_a_beauty_rgba_exr_is_a_plain_color_frame_and_keeps_its_alpha() -> None:
    channels = _beauty()
    frame = read_frame(_exr(channels))
    assert list(frame.layers) == ["color"] and not frame.has_gradients and frame.features is None
    np.testing.assert_array_equal(frame.layers["color"].base, np.dstack([channels[c] for c in "RGB"]))
    np.testing.assert_array_equal(frame.alpha, channels["A"])
    assert frame.layout == "mitsuba-aov" and frame.warnings == []
    answer = OpenEXR.File(io.BytesIO(encode_answer(frame, rgb_channels("", frame.layers["color"].base))),
                          separate_channels=True)
    np.testing.assert_array_equal(answer.channels()["A"].pixels, channels["A"])
    assert answer.header()["gradsep.channels"] == "mitsuba-aov"


def test_a_beauty_without_alpha_has_none() -> None:
    frame = read_frame(_exr(_beauty(alpha=False)))
    assert frame.alpha is None and "A" not in frame.to_channels()


def test_mitsuba_aov_integrator_channels_are_read_as_features() -> None:
    """The names Mitsuba 3's aov integrator writes for aovs="albedo:albedo,nn:sh_normal,dd:depth" (checked
    against a real render: B G R albedo.B albedo.G albedo.R dd.T integrator.A ... nn.X nn.Y nn.Z)."""
    channels = _beauty(alpha=False)
    albedo = {f"albedo.{c}": _plane() for c in "RGB"}
    normal = {f"nn.{c}": _plane(-1, 1) for c in "XYZ"}
    depth = _plane(1, 5)
    extra = {f"integrator.{c}": _plane() for c in "RGBA"}
    frame = read_frame(_exr({**channels, **albedo, **normal, "dd.T": depth, **extra}))
    assert frame.layout == "mitsuba-aov" and frame.features is not None
    np.testing.assert_array_equal(frame.features.albedo, np.dstack([albedo[f"albedo.{c}"] for c in "RGB"]))
    np.testing.assert_array_equal(frame.features.normal, np.dstack([normal[f"nn.{c}"] for c in "XYZ"]))
    np.testing.assert_array_equal(frame.features.depth, depth)
    assert len(frame.warnings) == 1 and "integrator.A" in frame.warnings[0] and "4 channel" in frame.warnings[0]


def test_mitsuba_sh_normal_is_preferred_and_depth_letters_vary() -> None:
    names = ["R", "G", "B", *(f"albedo.{c}" for c in "RGB"), *(f"sh_normal.{c}" for c in "XYZ"),
             *(f"gn.{c}" for c in "XYZ"), "depth.Y"]
    cmap = map_channels(names)
    assert cmap.sources["normal.X"] == "sh_normal.X" and cmap.sources["depth.Z"] == "depth.Y"


def _cycles(view_layer: str = "ViewLayer", noisy: bool = False) -> dict[str, np.ndarray]:
    out = {f"{view_layer}.Combined.{c}": _plane(0.1, 2.0) for c in "RGBA"}
    if noisy:
        out.update({f"{view_layer}.Noisy Image.{c}": _plane(0.1, 2.0) for c in "RGBA"})
    out.update({f"{view_layer}.Denoising Albedo.{c}": _plane() for c in "RGB"})
    out.update({f"{view_layer}.Denoising Normal.{c}": _plane(-1, 1) for c in "XYZ"})
    out[f"{view_layer}.Denoising Depth.Z"] = _plane(1, 9)
    out[f"{view_layer}.Depth.Z"] = _plane(1, 9)
    return out


def test_a_cycles_multilayer_exr_is_read_through_its_passes() -> None:
    channels = _cycles()
    frame = read_frame(_exr(channels))
    assert frame.layout == "cycles:ViewLayer" and list(frame.layers) == ["color"]
    np.testing.assert_array_equal(frame.layers["color"].base,
                                  np.dstack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"]))
    np.testing.assert_array_equal(frame.alpha, channels["ViewLayer.Combined.A"])
    assert frame.features is not None
    np.testing.assert_array_equal(frame.features.albedo,
                                  np.dstack([channels[f"ViewLayer.Denoising Albedo.{c}"] for c in "RGB"]))
    np.testing.assert_array_equal(frame.features.normal,
                                  np.dstack([channels[f"ViewLayer.Denoising Normal.{c}"] for c in "XYZ"]))
    np.testing.assert_array_equal(frame.features.depth, channels["ViewLayer.Denoising Depth.Z"])
    assert len(frame.warnings) == 1 and "ViewLayer.Depth.Z" in frame.warnings[0]


def test_cycles_noisy_image_is_the_colour_when_blender_denoised_the_combined_pass() -> None:
    channels = _cycles(noisy=True)
    frame = read_frame(_exr(channels))
    np.testing.assert_array_equal(frame.layers["color"].base,
                                  np.dstack([channels[f"ViewLayer.Noisy Image.{c}"] for c in "RGB"]))
    np.testing.assert_array_equal(frame.alpha, channels["ViewLayer.Noisy Image.A"])


def test_two_view_layers_are_ambiguous_and_one_can_be_named() -> None:
    data = _exr({**_cycles("Front"), **_cycles("Back.Plate")})
    with pytest.raises(ChannelError) as info:
        read_frame(data)
    assert info.value.status == 422
    assert info.value.details["candidates"] == ["cycles:Back.Plate", "cycles:Front"]
    assert "cycles:Back.Plate" in info.value.message and "cycles:Front" in info.value.message
    with pytest.raises(ChannelError, match="several Cycles view layers"):
        read_frame(data, layout="cycles")
    assert read_frame(data, layout="cycles:Back.Plate").layout == "cycles:Back.Plate"


def test_a_beauty_beside_a_view_layer_is_ambiguous_and_either_can_be_chosen() -> None:
    channels = {**_beauty(), **_cycles()}
    data = _exr(channels)
    with pytest.raises(ChannelError) as info:
        read_frame(data)
    assert info.value.details["candidates"] == ["mitsuba-aov", "cycles:ViewLayer"]
    beauty = read_frame(data, layout="mitsuba-aov")
    np.testing.assert_array_equal(beauty.layers["color"].base[..., 0], channels["R"])
    cycles = read_frame(data, layout="cycles")
    np.testing.assert_array_equal(cycles.layers["color"].base[..., 0], channels["ViewLayer.Combined.R"])


def test_gradsep_layers_beside_a_top_level_preview_are_a_gradsep_frame() -> None:
    """The renderer's references carry R G B beside their layers: the contract's own layers are explicit."""
    channels = {**frame_channels(("direct", "indirect"), H, W), **_beauty(alpha=False)}
    assert candidates(list(channels)) == ["gradsep"]
    frame = read_frame(encode_exr(channels))
    assert list(frame.layers) == ["direct", "indirect"] and frame.layout == "gradsep"
    assert any("R" in w and "ignored" in w for w in frame.warnings)


@pytest.mark.parametrize(("layout", "message"), [("mitsuba-aov", "top-level R, G and B"),
                                                 ("cycles", "no Cycles view layer"),
                                                 ("cycles:Nope", "no Cycles view layer 'Nope'"),
                                                 ("bogus", "unknown channel layout")])
def test_a_layout_that_does_not_fit_is_a_422_naming_the_problem(layout: str, message: str) -> None:
    with pytest.raises(ChannelError, match=message) as info:
        read_frame(encode_exr(frame_channels(("direct",), H, W)), layout=layout)
    assert info.value.status == 422


def test_a_file_with_no_layout_still_says_what_is_expected() -> None:
    with pytest.raises(ChannelError, match="no illumination layer.*beauty.*Cycles"):
        read_frame(_exr({"Y": _plane()}))


# -- metadata through -------------------------------------------------------------------------------------------

WINDOW_HEADER = {"dataWindow": (np.array([10, 20], np.int32), np.array([73, 83], np.int32)),
                 "displayWindow": (np.array([0, 0], np.int32), np.array([99, 99], np.int32)),
                 "pixelAspectRatio": 2.0, "screenWindowWidth": 1.5,
                 "chromaticities": (0.64, 0.33, 0.3, 0.6, 0.15, 0.06, 0.3127, 0.329),
                 "gradsep.spp": "16", "gradsep.method": "from-the-input", "owner": "farm", "comments": "shot 12"}


def _windowed_frame(path: Path) -> dict[str, np.ndarray]:
    channels = frame_channels(("direct", "indirect"), 64, 64)
    path.write_bytes(_exr(channels, WINDOW_HEADER))
    return channels


def _assert_carried(header: dict) -> None:
    assert [list(v) for v in header["dataWindow"]] == [[10, 20], [73, 83]]
    assert [list(v) for v in header["displayWindow"]] == [[0, 0], [99, 99]]
    assert header["pixelAspectRatio"] == 2.0 and header["screenWindowWidth"] == 1.5
    np.testing.assert_allclose(header["chromaticities"], WINDOW_HEADER["chromaticities"], rtol=1e-6)
    assert header["gradsep.spp"] == "16" and header["owner"] == "farm" and header["comments"] == "shot 12"


def test_gradsep_reconstruct_keeps_windows_aspect_and_attributes(tmp_path: Path, capsys) -> None:
    _windowed_frame(tmp_path / "in.exr")
    code = main(["reconstruct", str(tmp_path / "in.exr"), "-o", str(tmp_path / "out.exr"), "--method", "l2"])
    assert code == 0, capsys.readouterr().err
    header = OpenEXR.File(str(tmp_path / "out.exr"), header_only=True).header()
    _assert_carried(header)
    assert header["gradsep.method"] == "l2"  # the answer's own keys win over the input's
    assert "gradsep.warnings" not in header


def test_write_exr_keeps_a_frames_image_attributes(tmp_path: Path) -> None:
    _windowed_frame(tmp_path / "in.exr")
    frame = read_frame(tmp_path / "in.exr")
    write_exr(tmp_path / "copy.exr", frame.to_channels(), metadata=frame.metadata,
              image_attributes=frame.image_attributes)
    _assert_carried(OpenEXR.File(str(tmp_path / "copy.exr"), header_only=True).header())


def test_malformed_image_attributes_are_dropped_not_written() -> None:
    """Values from an untrusted header are checked before they are copied: writing them back cannot fail."""
    from gradsep.model.exr_read import _image_attributes

    header = {"displayWindow": (np.array([50, 50], np.int32), np.array([0, 0], np.int32)),  # inverted
              "pixelAspectRatio": float("nan"), "screenWindowWidth": "wide", "chromaticities": (0.6, 0.3),
              "screenWindowCenter": np.array([0.5, 0.25], np.float32)}
    kept = _image_attributes(header)
    assert list(kept) == ["screenWindowCenter"]
    frame = read_frame(_exr(frame_channels(("color",), H, W)))
    frame.image_attributes = kept
    answer = OpenEXR.File(io.BytesIO(encode_answer(frame, rgb_channels("", frame.layers["color"].base))))
    np.testing.assert_array_equal(answer.header()["screenWindowCenter"], [0.5, 0.25])


# -- nothing silent -----------------------------------------------------------------------------------------------


def test_cli_warns_with_counts_for_half_saturation_negative_radiance_and_replaced_values(tmp_path: Path,
                                                                                         capsys) -> None:
    channels = frame_channels(("direct",), H, W)
    for c in "RGB":
        channels[f"direct.{c}"] = channels[f"direct.{c}"] * 1e6  # above half's 65504 everywhere
        channels[f"direct.dx.{c}"] *= 1e6
        channels[f"direct.dy.{c}"] *= 1e6
    channels["direct.R"][0, :3] = -5.0  # three negative radiance values
    channels["direct.G"][1, 1] = np.nan  # one value replaced by the nonfinite policy
    (tmp_path / "in.exr").write_bytes(_exr(channels))
    out = tmp_path / "out.exr"
    code = main(["reconstruct", str(tmp_path / "in.exr"), "-o", str(out), "--method", "l2", "--half",
                 "--nonfinite", "zero"])
    err = capsys.readouterr().err
    assert code == 0, err
    lines = [line for line in err.splitlines() if "warning" in line]
    assert any("3 negative radiance value(s) in direct.R (3)" in line for line in lines), err
    assert any("replaced non-finite values with 0 in direct.G (1)" in line for line in lines), err
    saturated = [line for line in lines if "saturated at 65504" in line]
    assert len(saturated) == 1 and int(saturated[0].split("warning: ")[1].split()[0]) > 0.9 * 3 * H * W
    header = OpenEXR.File(str(out), header_only=True).header()
    for needle in ("negative radiance", "non-finite", "saturated at 65504"):
        assert needle in header["gradsep.warnings"]


@pytest.mark.slow
@pytest.mark.render
def test_a_real_mitsuba_aov_render_is_read_as_color_with_features(tmp_path: Path) -> None:
    """Mitsuba 3's own output, not a synthetic copy of its names: hdrfilm through the aov integrator."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal,dd:depth",
                       "integrator": {"type": "path"}},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 6},
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0])},
        "sphere": {"type": "sphere"}, "light": {"type": "constant"}})
    mi.render(scene, spp=4)
    scene.sensors()[0].film().bitmap().write(str(tmp_path / "aov.exr"))
    frame = read_frame(tmp_path / "aov.exr")
    assert frame.layout == "mitsuba-aov" and list(frame.layers) == ["color"] and frame.features is not None
    assert (frame.height, frame.width) == (6, 8) and float(frame.layers["color"].base.mean()) > 0
    assert float(frame.features.depth.max()) > 0 and float(frame.features.albedo.max()) > 0


@pytest.mark.parametrize("method, kept", [("oidn-l1", True), ("l2", False)])
def test_a_planned_frames_predicted_error_is_carried_only_for_its_method(method: str, kept: bool) -> None:
    """A planned render's gradsep.predicted_relmse predicts the error of gradsep.plan_method's reconstruction: an
    answer made with that method carries it, an answer made with another method does not (it would be wrong)."""
    header = {"gradsep.predicted_relmse": "0.0123", "gradsep.plan_method": "oidn-l1", "gradsep.plan": "all",
              "gradsep.predicted_from": "frame", "gradsep.frame_check": '{"halves":[[8,0.01,0.002]]}'}
    frame = read_frame(_exr(_beauty(alpha=False), header))
    answer = OpenEXR.File(io.BytesIO(encode_answer(frame, rgb_channels("", frame.layers["color"].base),
                                                   metadata={"gradsep.method": method})), header_only=True)
    out = answer.header()
    assert ("gradsep.predicted_relmse" in out) is kept
    assert ("gradsep.predicted_from" in out) is kept and ("gradsep.frame_check" in out) is kept  # they describe it
    assert out["gradsep.plan"] == "all" and out["gradsep.plan_method"] == "oidn-l1"
