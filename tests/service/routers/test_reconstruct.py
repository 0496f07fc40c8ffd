"""``POST /v1/reconstruct`` (service/routers/reconstruct.py): its HTTP contract, status code by status code, through
TestClient and a real uvicorn."""

from __future__ import annotations

import importlib.util
import re

import numpy as np
import pytest

from gradsep.service.main import create_app
from gradsep.service.routers.reconstruct import MULTIPART_FIELD_BYTES
from tests.service.conftest import TRANSPORT, assert_error, post, settings
from tests.service.frames import (
    channels_bytes,
    decode,
    expected_sum,
    frame_bytes,
    frame_channels,
    huge_header,
    rgb,
    subsampled,
)

# --------------------------------------------------------------------------------------------------------------
# 200
# --------------------------------------------------------------------------------------------------------------


@TRANSPORT
@pytest.mark.parametrize("half_input", [False, True], ids=["float", "half"])
@pytest.mark.parametrize("layers", [("direct",), ("indirect",), ("color",), ("direct", "indirect")],
                         ids=["direct-only", "indirect-only", "color", "direct+indirect"])
def test_every_layer_set_reconstructs_to_the_sum_of_its_layers(poisson_api, transport, layers, half_input):
    seed = len(layers) + 10 * half_input
    response = post(poisson_api[transport], frame_bytes(layers, seed=seed, half=half_input), {"method": "l2"})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/x-exr"
    channels, attributes = decode(response.content)
    assert set(channels) == {"R", "G", "B"}
    assert all(c.dtype == np.float32 for c in channels.values())
    expected = expected_sum(layers, seed=seed)
    tolerance = 2e-3 if half_input else 1e-4  # half input carries ~1e-3 relative rounding
    np.testing.assert_allclose(rgb(channels), expected, rtol=tolerance, atol=tolerance)
    assert attributes["gradsep.method"] == "l2"
    assert attributes["gradsep.layers"] == ",".join(layers)


@TRANSPORT
@pytest.mark.parametrize("encoding", ["multipart", "image/x-exr", "application/octet-stream", "no-content-type"])
def test_multipart_and_raw_bodies_are_both_accepted(poisson_api, transport, encoding):
    data = frame_bytes(seed=3)
    client = poisson_api[transport]
    if encoding == "multipart":
        response = client.post("/v1/reconstruct?method=l1", files={"frame": ("f.exr", data, "image/x-exr")})
    else:
        response = post(client, data, {"method": "l1"},
                        content_type=None if encoding == "no-content-type" else encoding)
    assert response.status_code == 200, response.text
    assert response.headers["x-reconstruction-method"] == "l1"
    np.testing.assert_allclose(rgb(decode(response.content)[0]), expected_sum(seed=3), rtol=1e-3, atol=1e-3)


@TRANSPORT
def test_half_output_and_all_layers(poisson_api, transport):
    response = post(poisson_api[transport], frame_bytes(seed=5),
                    {"method": "l1", "alpha": 0.5, "format": "half", "layers": "all"})
    assert response.status_code == 200, response.text
    channels, attributes = decode(response.content)
    assert set(channels) == {"R", "G", "B", "direct.R", "direct.G", "direct.B",
                             "indirect.R", "indirect.G", "indirect.B"}
    assert all(c.dtype == np.float16 for c in channels.values())
    for layer in ("direct", "indirect"):
        np.testing.assert_allclose(rgb(channels, layer), expected_sum((layer,), seed=5), rtol=5e-3, atol=5e-3)
    assert attributes["gradsep.alpha"] == "0.5"


@TRANSPORT
def test_request_id_and_server_timing(poisson_api, transport):
    client = poisson_api[transport]
    response = post(client, frame_bytes(seed=7), headers={"X-Request-ID": "farm-job-42.frame-0007"})
    assert response.status_code == 200
    assert response.headers["x-request-id"] == "farm-job-42.frame-0007"
    timing = response.headers["server-timing"]
    for step in ("decode", "direct", "indirect", "encode"):
        assert re.search(rf"\b{step};dur=\d+(\.\d+)?", timing), timing
    assert decode(response.content)[1]["gradsep.request_id"] == "farm-job-42.frame-0007"

    generated = client.get("/healthz").headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", generated)
    hostile = client.get("/healthz", headers={"X-Request-ID": "x" * 500}).headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", hostile)  # not echoed: too long for logs


# --------------------------------------------------------------------------------------------------------------
# 400
# --------------------------------------------------------------------------------------------------------------


@TRANSPORT
@pytest.mark.parametrize("case", ["garbage", "empty", "truncated-header", "truncated-pixels"])
def test_not_an_exr_or_truncated_is_400(poisson_api, transport, case):
    data = frame_bytes(seed=1)
    body = {"garbage": b"P6\n32 24\n255\n" + bytes(100), "empty": b"", "truncated-header": data[:60],
            "truncated-pixels": data[: len(data) - 200]}[case]
    error = assert_error(post(poisson_api[transport], body), 400, "not_exr")
    assert "exr" in error["message"].lower()


@TRANSPORT
def test_mismatched_channel_sizes_are_400_naming_the_channel(poisson_api, transport):
    """Within one EXR a channel can only differ in size by subsampling; the contract refuses it."""
    error = assert_error(post(poisson_api[transport], subsampled(frame_bytes(("color",)), "color.G")),
                         400, "unsupported_exr")
    assert error["details"] == ["color.G"]


@TRANSPORT
def test_multipart_without_frame_field_is_400(poisson_api, transport):
    response = poisson_api[transport].post("/v1/reconstruct", files={"image": ("f.exr", frame_bytes())})
    error = assert_error(response, 400, "missing_frame")
    assert error["details"] == {"fields": ["image"]}


@TRANSPORT
def test_a_multipart_field_over_64_kib_is_400_and_one_under_is_ignored(poisson_api, transport):
    """Non-file fields are held in memory while the body is parsed: each is capped (docs/service.md, memory)."""
    frame = {"frame": ("f.exr", frame_bytes(seed=2), "image/x-exr")}
    big = poisson_api[transport].post("/v1/reconstruct", params={"method": "l2"}, files=frame,
                                      data={"note": "x" * (MULTIPART_FIELD_BYTES + 1)})
    assert_error(big, 400, "bad_request")
    small = poisson_api[transport].post("/v1/reconstruct", params={"method": "l2"}, files=frame,
                                        data={"note": "x" * MULTIPART_FIELD_BYTES})
    assert small.status_code == 200, small.text


# --------------------------------------------------------------------------------------------------------------
# 413
# --------------------------------------------------------------------------------------------------------------


@TRANSPORT
def test_huge_declared_image_is_413_from_the_header_without_decoding(poisson_api, transport, monkeypatch):
    decoded = []
    monkeypatch.setattr("gradsep.service.pipeline.read_frame", lambda *a, **k: decoded.append(a) or 1 / 0)
    data = huge_header(frame_bytes(("color",), height=4, width=4))
    assert len(data) < 10_000  # a tiny body: the size can only come from the header
    error = assert_error(post(poisson_api[transport], data), 413, "too_large")
    assert error["details"]["width"] == 200_000 and error["details"]["height"] == 200_000
    assert decoded == []


def test_value_budget_from_settings_is_413(serve):
    data = frame_bytes(height=32, width=32)  # 18 channels x 1024 pixels
    with serve(create_app(settings(max_values=18 * 1024 - 1))) as client:
        error = assert_error(post(client, data), 413, "too_large")
        assert error["details"]["max_values"] == 18 * 1024 - 1
        assert post(client, frame_bytes(("color",), height=32, width=32)).status_code == 200


def test_body_over_the_byte_limit_is_413_declared_or_streamed(serve):
    data = frame_bytes(height=64, width=64)
    assert len(data) > 20_000
    with serve(create_app(settings(max_body_bytes=20_000))) as client:
        declared = assert_error(post(client, data), 413, "body_too_large")
        assert declared["details"]["max_body_bytes"] == 20_000

        def chunks():  # no Content-Length: chunked transfer, the limit is counted while streaming
            for i in range(0, len(data), 4096):
                yield data[i:i + 4096]

        assert_error(client.post("/v1/reconstruct", content=chunks(), headers={"Content-Type": "image/x-exr"}),
                     413, "body_too_large")
        assert client.get("/healthz").status_code == 200
        assert post(client, frame_bytes(height=16, width=16)).status_code == 200


# --------------------------------------------------------------------------------------------------------------
# 415, 404, 405
# --------------------------------------------------------------------------------------------------------------


@TRANSPORT
@pytest.mark.parametrize("content_type", ["text/plain", "application/json", "application/x-www-form-urlencoded"])
def test_wrong_content_type_is_415(poisson_api, transport, content_type):
    error = assert_error(post(poisson_api[transport], frame_bytes(), content_type=content_type),
                         415, "unsupported_media_type")
    assert "image/x-exr" in error["details"]["accepted"]


# --------------------------------------------------------------------------------------------------------------
# 422
# --------------------------------------------------------------------------------------------------------------


@TRANSPORT
def test_missing_and_unknown_channels_are_422_and_listed(poisson_api, transport):
    channels = frame_channels(("direct",))
    del channels["direct.dx.G"], channels["direct.dy.B"]
    channels["direct.dz.R"] = channels["direct.R"]
    error = assert_error(post(poisson_api[transport], channels_bytes(channels)), 422, "bad_channels")
    assert error["details"]["missing"] == ["direct.dx.G", "direct.dy.B"]
    assert error["details"]["unknown"] == ["direct.dz.R"]


@TRANSPORT
def test_no_illumination_layer_and_mixed_layers_are_422(poisson_api, transport):
    features_only = {k: v for k, v in frame_channels(("color",), features=True).items()
                     if not k.startswith("color")}
    error = assert_error(post(poisson_api[transport], channels_bytes(features_only)), 422, "bad_channels")
    assert "no illumination layer" in error["message"]
    mixed = frame_channels(("color", "direct"))
    error = assert_error(post(poisson_api[transport], channels_bytes(mixed)), 422, "bad_channels")
    assert error["details"]["conflicting_layers"] == ["direct", "color"]


@TRANSPORT
@pytest.mark.parametrize("half", [False, True], ids=["float", "half"])
def test_nan_and_inf_are_422_naming_channel_and_count(poisson_api, transport, half):
    channels = frame_channels(("direct", "indirect"))
    channels["direct.dx.G"][0, :3] = np.nan
    channels["indirect.R"][5, 5] = np.inf
    error = assert_error(post(poisson_api[transport], channels_bytes(channels, half=half)), 422, "non_finite")
    assert error["details"] == {"direct.dx.G": 3, "indirect.R": 1}


def test_zero_policy_answers_200_finite_with_a_warning(serve):
    channels = frame_channels(("color",))
    channels["color.dy.B"][2, 2] = -np.inf
    with serve(create_app(settings(nonfinite="zero"))) as client:
        response = post(client, channels_bytes(channels))
        assert response.status_code == 200, response.text
        assert "color.dy.B (1)" in response.headers["x-gradsep-warnings"]
        out, attributes = decode(response.content)
        assert np.isfinite(rgb(out)).all()
        assert "color.dy.B" in attributes["gradsep.warnings"]


@TRANSPORT
@pytest.mark.parametrize("params, parameter", [
    ({"method": "bilateral"}, "method"), ({"alpha": "0"}, "alpha"), ({"alpha": "nan"}, "alpha"),
    ({"alpha": "inf"}, "alpha"), ({"alpha": "abc"}, "alpha"), ({"alpha": "1e-200"}, "alpha"),
    ({"alpha": "1e-9"}, "alpha"), ({"format": "png"}, "format"),
    ({"layers": "some"}, "layers")])
def test_invalid_parameters_are_422_naming_the_parameter(poisson_api, transport, params, parameter):
    error = assert_error(post(poisson_api[transport], frame_bytes(), params), 422, "invalid_parameter")
    assert [d["parameter"] for d in error["details"]] == [parameter]


@TRANSPORT
@pytest.mark.parametrize("method", ["l1", "l2"])
def test_smallest_documented_alpha_returns_the_frames_energy(poisson_api, transport, method):
    """alpha = 1e-8 (the bottom of the documented range) is served exactly, not as an all-black image."""
    response = post(poisson_api[transport], frame_bytes(), {"method": method, "alpha": "1e-8"})
    assert response.status_code == 200, response.text
    assert "x-gradsep-warnings" not in response.headers
    image = rgb(decode(response.content)[0])
    assert np.isfinite(image).all()
    np.testing.assert_allclose(image, expected_sum(), rtol=1e-4, atol=1e-4)  # exact gradients: exact answer


@TRANSPORT
def test_a_frame_with_the_direct_layers_gradients_only(poisson_api, transport):
    """`gradsep render --gradients direct`: direct.* with its gradients, a plain indirect layer. The default
    (oidn-l1, which refines the direct layer alone) and oidn serve it; l1/l2 answer 422 naming the indirect
    layer's gradient channels."""
    client = poisson_api[transport]
    channels = {k: v for k, v in frame_channels(("direct", "indirect"), features=True, seed=4).items()
                if not k.startswith(("indirect.dx.", "indirect.dy."))}
    for method in ("l1", "l2"):
        error = assert_error(post(client, channels_bytes(channels), {"method": method}), 422, "bad_channels")
        assert error["details"]["missing"] == [f"indirect.{g}.{c}" for g in ("dx", "dy") for c in "RGB"]
        assert "indirect.dx.R" in error["message"]
    response = post(client, channels_bytes(channels))
    if importlib.util.find_spec("pyoidn") is None:  # nothing serves it on a host without OIDN
        assert_error(response, 422, "bad_channels")
        return
    assert response.status_code == 200, response.text
    assert response.headers["x-reconstruction-method"] == "oidn-l1"
    assert np.isfinite(rgb(decode(response.content)[0])).all()
    explicit = post(client, channels_bytes(channels), {"method": "oidn"})
    assert explicit.status_code == 200 and explicit.headers["x-reconstruction-method"] == "oidn"


@TRANSPORT
def test_network_without_models_is_422_listing_available_methods(poisson_api, transport):
    error = assert_error(post(poisson_api[transport], frame_bytes(), {"method": "network"}),
                         422, "method_unavailable")
    oidn = importlib.util.find_spec("pyoidn") is not None
    assert error["details"] == {"available": ["l1", "l2", "oidn", "oidn-l1"] if oidn else ["l1", "l2"]}
    assert "it needs the per-layer networks, models/{direct,indirect,color}.onnx" in error["message"]
    fused = assert_error(post(poisson_api[transport], frame_bytes(), {"method": "fused"}), 422, "method_unavailable")
    assert "fused" not in fused["details"]["available"]


# --------------------------------------------------------------------------------------------------------------
# 401
# --------------------------------------------------------------------------------------------------------------


@TRANSPORT
def test_hostile_foreign_channel_names_cannot_inject_headers(poisson_api, transport):
    channels = frame_channels(("color",))
    channels["evil\r\nSet-Cookie: x=1\u00e9"] = channels["color.R"]
    response = post(poisson_api[transport], channels_bytes(channels))
    assert response.status_code == 200, response.text
    assert "set-cookie" not in response.headers
    warning = response.headers["x-gradsep-warnings"]
    assert "ignored channels" in warning and "evil??Set-Cookie: x=1?" in warning


# --------------------------------------------------------------------------------------------------------------
# Malformed HTTP (uvicorn's parser) and the offline API docs
# --------------------------------------------------------------------------------------------------------------


@TRANSPORT
@pytest.mark.parametrize(("sent", "answered"), [
    ("NO_COMPRESSION", "NO_COMPRESSION"), ("ZIP_COMPRESSION", "ZIP_COMPRESSION"),
    ("PIZ_COMPRESSION", "PIZ_COMPRESSION"), ("PXR24_COMPRESSION", "ZIP_COMPRESSION")])
def test_answer_compression_follows_the_request_when_lossless(poisson_api, transport, sent, answered):
    from gradsep.model.exr_read import read_header
    from gradsep.model.exr_write import encode_exr

    body = encode_exr(frame_channels(), compression=sent) if sent != "PXR24_COMPRESSION" else _lossy(sent)
    response = post(poisson_api[transport], body, {"method": "l2"})
    assert response.status_code == 200, response.text
    assert read_header(response.content).compression == answered
    np.testing.assert_allclose(rgb(decode(response.content)[0]), expected_sum(), rtol=1e-4, atol=1e-4)


def _lossy(compression: str) -> bytes:
    """A frame written with a lossy codec (float channels through PXR24 lose mantissa bits)."""
    import io

    import OpenEXR

    pixels = {k: np.ascontiguousarray(v, np.float32) for k, v in frame_channels().items()}
    buffer = io.BytesIO()
    OpenEXR.File({"compression": getattr(OpenEXR, compression), "type": OpenEXR.scanlineimage}, pixels).write(buffer)
    return buffer.getvalue()




# --------------------------------------------------------------------------------------------------------------
# Integer (UINT) channels: docs/service.md's error table
# --------------------------------------------------------------------------------------------------------------


def _with_uint(channels: dict[str, np.ndarray], uint: set[str]) -> bytes:
    """These channels as EXR, the named ones stored as UINT (what an object-id or crypto-matte AOV is)."""
    import io

    import OpenEXR

    pixels = {name: np.ascontiguousarray(value, np.uint32 if name in uint else np.float32)
              for name, value in channels.items()}
    buffer = io.BytesIO()
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, pixels).write(buffer)
    return buffer.getvalue()


@TRANSPORT
@pytest.mark.parametrize("channels", ["auto", "gradsep"])
def test_an_integer_channel_the_frame_does_not_read_is_ignored_with_a_warning(poisson_api, transport, channels):
    frame = {**frame_channels(seed=7), "objectId": np.arange(24 * 32).reshape(24, 32)}
    response = post(poisson_api[transport], _with_uint(frame, {"objectId"}), {"method": "l2", "channels": channels})
    assert response.status_code == 200, response.text
    assert "ignored channels outside the frame contract: objectId" in response.headers["x-gradsep-warnings"]
    np.testing.assert_allclose(rgb(decode(response.content)[0]), expected_sum(seed=7), rtol=1e-4, atol=1e-4)


@TRANSPORT
@pytest.mark.parametrize("channel", ["direct.R", "indirect.dx.G", "albedo.R", "direct.var.Y", "A"])
def test_an_integer_channel_the_frame_reads_is_400_naming_it(poisson_api, transport, channel):
    frame = {**frame_channels(features=True), "direct.var.Y": np.ones((24, 32)), "A": np.ones((24, 32))}
    error = assert_error(post(poisson_api[transport], _with_uint(frame, {channel}), {"method": "l2"}),
                         400, "unsupported_exr")
    assert error["details"] == [channel] and "integer pixels" in error["message"]


def test_the_query_parameters_are_one_dependency_with_the_documented_names(poisson_api):
    """The endpoint reads its query through ReconstructQuery; the schema keeps the five parameters, in order, with
    ``format`` by its alias."""
    schema = poisson_api["testclient"].get("/openapi.json").json()
    parameters = schema["paths"]["/v1/reconstruct"]["post"]["parameters"]
    assert [(p["name"], p["in"], p.get("required", False)) for p in parameters] == [
        ("method", "query", False), ("alpha", "query", False), ("format", "query", False),
        ("layers", "query", False), ("channels", "query", False)]
    response = post(poisson_api["testclient"], frame_bytes(seed=8),
                    {"method": "l2", "alpha": 0.5, "format": "half", "layers": "all", "channels": "gradsep"})
    assert response.status_code == 200, response.text
    channels, attributes = decode(response.content)
    assert channels["R"].dtype == np.float16 and "direct.R" in channels
    assert attributes["gradsep.alpha"] == "0.5" and attributes["gradsep.method"] == "l2"
