"""What the service carries through and says: the input's header metadata and alpha on the answer, frames from
other renderers (channel layouts), and every value it clamps, saturates or replaces named with its count in
``X-Gradsep-Warnings`` and the EXR's ``gradsep.warnings``."""

from __future__ import annotations

import importlib.util
import io

import httpx
import numpy as np
import OpenEXR
import pytest

from tests.service.frames import expected_sum, frame_channels, rgb

HAS_OIDN = importlib.util.find_spec("pyoidn") is not None


def _exr(channels: dict[str, np.ndarray], header: dict | None = None) -> bytes:
    buffer = io.BytesIO()
    base = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})}
    OpenEXR.File(base, {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}).write(buffer)
    return buffer.getvalue()


def _post(client: httpx.Client, body: bytes, params: dict | None = None) -> httpx.Response:
    return client.post("/v1/reconstruct", content=body, params=params or {},
                       headers={"content-type": "image/x-exr"})


def _answer(response: httpx.Response) -> OpenEXR.File:
    return OpenEXR.File(io.BytesIO(response.content), separate_channels=True)


@pytest.mark.parametrize("transport", ["testclient", "uvicorn"])
def test_data_window_display_window_aspect_and_attributes_come_back(poisson_api, transport: str) -> None:
    header = {"dataWindow": (np.array([10, 20], np.int32), np.array([73, 83], np.int32)),
              "displayWindow": (np.array([0, 0], np.int32), np.array([99, 99], np.int32)),
              "pixelAspectRatio": 2.0, "gradsep.spp": "16", "gradsep.request_id": "stale", "owner": "farm"}
    response = _post(poisson_api[transport], _exr(frame_channels(("direct", "indirect"), 64, 64), header),
                     {"method": "l2", "layers": "all"})
    assert response.status_code == 200, response.text
    answer = _answer(response)
    got = answer.header()
    assert [list(v) for v in got["dataWindow"]] == [[10, 20], [73, 83]]
    assert [list(v) for v in got["displayWindow"]] == [[0, 0], [99, 99]]
    assert got["pixelAspectRatio"] == 2.0
    assert got["gradsep.spp"] == "16" and got["owner"] == "farm"
    assert got["gradsep.method"] == "l2" and got["gradsep.request_id"] != "stale"
    np.testing.assert_allclose(rgb({k: c.pixels for k, c in answer.channels().items()}),
                               expected_sum(("direct", "indirect"), 64, 64), rtol=1e-5, atol=1e-5)


def test_half_saturation_is_a_warning_with_its_count(poisson_api) -> None:
    channels = {k: v * 1e6 for k, v in frame_channels(("direct",), 8, 8).items()}  # every value above 65504
    response = _post(poisson_api["testclient"], _exr(channels), {"method": "l2", "format": "half"})
    assert response.status_code == 200, response.text
    want = "192 value(s) above the half-float range saturated at 65504"  # 8 x 8 x RGB
    assert want in response.headers["x-gradsep-warnings"]
    assert want in _answer(response).header()["gradsep.warnings"]
    float_answer = _post(poisson_api["testclient"], _exr(channels), {"method": "l2"})
    assert "x-gradsep-warnings" not in float_answer.headers


def test_negative_radiance_is_a_warning_with_its_count(poisson_api) -> None:
    channels = frame_channels(("color",), 8, 8)
    channels["color.B"][2:4, 2:4] = -1.0
    response = _post(poisson_api["testclient"], _exr(channels), {"method": "l2"})
    assert response.status_code == 200, response.text
    want = "4 negative radiance value(s) in color.B (4): radiance is non-negative, the output is clamped at 0"
    assert want in response.headers["x-gradsep-warnings"]
    assert want in _answer(response).header()["gradsep.warnings"]
    assert float(rgb({k: c.pixels for k, c in _answer(response).channels().items()}).min()) >= 0.0


def test_a_whole_negated_frame_says_so() -> None:
    """The audit's case: a negated frame came back black with no word; now the count is the whole frame."""
    from gradsep.model.exr_read import read_frame

    channels = {k: -v for k, v in frame_channels(("color",), 8, 8, gradients=False).items()}
    frame = read_frame(_exr(channels))
    assert any(w.startswith("192 negative radiance value(s)") for w in frame.warnings)


def test_values_replaced_by_the_nonfinite_policy_are_counted(tmp_path) -> None:
    from gradsep.service.main import create_app
    from tests.service.conftest import in_process, settings

    channels = frame_channels(("direct",), 8, 8)
    channels["direct.R"][0, 0] = np.inf
    channels["direct.dx.G"][1, :2] = np.nan
    with in_process(create_app(settings(nonfinite="zero"))) as client:
        response = _post(client, _exr(channels), {"method": "l2"})
    assert response.status_code == 200, response.text
    want = "replaced non-finite values with 0 in direct.R (1), direct.dx.G (2)"
    assert want in response.headers["x-gradsep-warnings"]
    assert want in _answer(response).header()["gradsep.warnings"]


@pytest.mark.skipif(not HAS_OIDN, reason="a plain frame is served by oidn (pyoidn, the serve extra)")
@pytest.mark.parametrize("transport", ["testclient", "uvicorn"])
def test_an_rgba_beauty_exr_is_served_and_keeps_its_alpha(poisson_api, transport: str) -> None:
    rng = np.random.default_rng(3)
    beauty = {c: rng.uniform(0.2, 1.0, (32, 32)).astype(np.float32) for c in "RGB"}
    beauty["A"] = np.tile(np.linspace(0, 1, 32, dtype=np.float32), (32, 1))
    response = _post(poisson_api[transport], _exr(beauty))
    assert response.status_code == 200, response.text
    assert response.headers["x-reconstruction-method"] == "oidn"
    answer = _answer(response)
    channels = {k: c.pixels for k, c in answer.channels().items()}
    assert set(channels) == {"R", "G", "B", "A"}
    np.testing.assert_array_equal(channels["A"], beauty["A"])
    assert answer.header()["gradsep.channels"] == "mitsuba-aov"
    assert abs(float(rgb(channels).mean()) / float(np.mean([beauty[c] for c in "RGB"])) - 1) < 0.05


@pytest.mark.skipif(not HAS_OIDN, reason="a plain frame is served by oidn (pyoidn, the serve extra)")
def test_the_oidn_setting_a_frame_asks_for_runs_and_the_answer_names_it(poisson_api, monkeypatch) -> None:
    """A render plan's ``gradsep.oidn_setting`` selects OIDN's setting; the answer's header names the one that ran;
    a header naming no setting is a warning and the default runs; a method without OIDN names none."""
    monkeypatch.delenv("GRADSEP_OIDN_SETTING", raising=False)
    channels = frame_channels(("direct", "indirect"), 32, 32)
    plain = frame_channels(("direct", "indirect"), 32, 32, gradients=False)  # served by oidn
    for asked, ran in (("prefiltered-high", "prefiltered-high"), ("sharpest", "raw-fast")):
        response = _post(poisson_api["testclient"], _exr(plain, {"gradsep.oidn_setting": asked}))
        assert response.status_code == 200, response.text
        assert _answer(response).header()["gradsep.oidn_setting"] == ran
        assert ("sharpest" in response.headers.get("x-gradsep-warnings", "")) == (asked == "sharpest")
    response = _post(poisson_api["testclient"], _exr(channels, {"gradsep.oidn_setting": "prefiltered-high"}),
                     {"method": "l2"})
    assert response.status_code == 200 and "gradsep.oidn_setting" not in _answer(response).header()


@pytest.mark.skipif(not HAS_OIDN, reason="a plain frame is served by oidn (pyoidn, the serve extra)")
def test_a_frames_variance_leaves_converged_pixels_alone_and_a_bad_one_is_named(poisson_api) -> None:
    """``L.var.Y`` of 0 (a converged frame) gives back the input under ``oidn``; a variance with a NaN is ignored
    with a warning naming the channel, and the frame is denoised as one without variance."""
    plain = frame_channels(("direct", "indirect"), 32, 32, gradients=False)
    converged = {**plain, "direct.var.Y": np.zeros((32, 32)), "indirect.var.Y": np.zeros((32, 32))}
    response = _post(poisson_api["testclient"], _exr(converged))
    assert response.status_code == 200, response.text
    got = rgb({k: c.pixels for k, c in _answer(response).channels().items()})
    np.testing.assert_allclose(got, rgb(plain, "direct") + rgb(plain, "indirect"), rtol=1e-5)
    bad = {**converged, "direct.var.Y": np.full((32, 32), np.nan)}
    response = _post(poisson_api["testclient"], _exr(bad))
    assert response.status_code == 200, response.text
    assert "direct.var.Y has 1024 NaN or negative value(s)" in response.headers["x-gradsep-warnings"]


def _cycles_exr(view_layers: tuple[str, ...] = ("ViewLayer",), beauty: bool = False) -> bytes:
    rng = np.random.default_rng(5)
    channels: dict[str, np.ndarray] = {}
    for v in view_layers:
        channels.update({f"{v}.Combined.{c}": rng.uniform(0.2, 1, (16, 16)) for c in "RGBA"})
        channels.update({f"{v}.Denoising Albedo.{c}": np.full((16, 16), 0.5) for c in "RGB"})
        channels.update({f"{v}.Denoising Normal.{c}": np.full((16, 16), float(c == "Z")) for c in "XYZ"})
        channels[f"{v}.Denoising Depth.Z"] = np.ones((16, 16))
    if beauty:
        channels.update({c: rng.uniform(0.2, 1, (16, 16)) for c in "RGB"})
    return _exr(channels)


def test_an_ambiguous_layout_is_a_422_naming_the_candidates(poisson_api) -> None:
    response = _post(poisson_api["testclient"], _cycles_exr(("Front", "Back")))
    assert response.status_code == 422
    error = response.json()["error"]
    assert error["code"] == "bad_channels" and error["details"]["candidates"] == ["cycles:Back", "cycles:Front"]
    assert "cycles:Back" in error["message"]


def test_an_unknown_layout_is_a_422_naming_the_parameter(poisson_api) -> None:
    response = _post(poisson_api["testclient"], _cycles_exr(), {"channels": "nuke"})
    assert response.status_code == 422
    assert response.json()["error"]["details"][0]["parameter"] == "channels"


@pytest.mark.skipif(not HAS_OIDN, reason="a plain frame is served by oidn (pyoidn, the serve extra)")
def test_a_cycles_exr_is_served_with_its_features_and_a_chosen_layout(poisson_api) -> None:
    client = poisson_api["testclient"]
    response = _post(client, _cycles_exr())
    assert response.status_code == 200, response.text
    assert "A" in _answer(response).channels()
    ambiguous = _cycles_exr(beauty=True)
    assert _post(client, ambiguous).status_code == 422
    chosen = _post(client, ambiguous, {"channels": "cycles:ViewLayer"})
    assert chosen.status_code == 200 and _answer(chosen).header()["gradsep.channels"] == "cycles:ViewLayer"
