"""``/v1/models`` reports each loaded model's provider and precision as its ONNX Runtime session really runs it:
the network's models and the fused blend models (and their clean-layer average).

ONNX Runtime may build a session without the accelerated provider it was given (model/onnx_session.py
``served_by``). Here every session is a stand-in that runs on the CPU and reports the providers a test chooses,
while the host is made to look like an OpenVINO bf16 machine, so the provider asked for is always OpenVINO: a
report that repeats the request instead of reading the session fails.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
import onnxruntime as ort  # noqa: E402

from gradsep.model.exr_write import encode_exr  # noqa: E402
from gradsep.model.frame import rgb_channels  # noqa: E402
from gradsep.model.onnx_session import CPU_EP, OPENVINO_EP  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
REAL_SESSION = ort.InferenceSession


def _sessions_reporting(providers: list[str]) -> type:
    class Session:
        """Runs on ORT's CPU provider whatever it is given; ``get_providers`` answers ``providers``."""

        def __init__(self, source: Any, options: Any = None, **kwargs: Any) -> None:  # providers= is ignored
            self._session = REAL_SESSION(source, options, providers=[CPU_EP])

        def get_providers(self) -> list[str]:
            return list(providers)

        def __getattr__(self, name: str) -> Any:
            return getattr(self._session, name)

    return Session


@pytest.fixture
def openvino_host(monkeypatch) -> Any:
    """A host where the provider choice is OpenVINO in bf16; returns a setter for what sessions report."""
    monkeypatch.setattr(ort, "get_available_providers", lambda: [OPENVINO_EP, CPU_EP])
    monkeypatch.setattr("gradsep.model.onnx_session.cpu_flags", lambda *a: frozenset({"avx512_bf16"}))
    monkeypatch.setenv("GRADSEP_ONNX_PROVIDER", "auto")

    def report(providers: list[str]) -> None:
        monkeypatch.setattr(ort, "InferenceSession", _sessions_reporting(providers))

    return report


@pytest.mark.slow
@pytest.mark.parametrize(("session", "want"), [([CPU_EP], ("cpu", "fp32")),
                                                ([OPENVINO_EP, CPU_EP], ("openvino", "bf16"))],
                         ids=["openvino-not-enabled", "openvino-enabled"])
def test_v1_models_reports_what_each_session_runs_on(openvino_host, session: list[str],
                                                     want: tuple[str, str]) -> None:
    pytest.importorskip("pyoidn")
    if not (REPO / "models" / "fused" / "indirect.onnx").is_file():
        pytest.skip("the shipped fused models are not in models/")
    from fastapi.testclient import TestClient

    from gradsep.service.main import create_app
    from gradsep.service.settings import Settings

    openvino_host(session)
    app = create_app(Settings(models_dir=REPO / "models", token=None, warm_up=False))
    with TestClient(app) as client:
        deadline = time.monotonic() + 60
        while client.get("/readyz").status_code != 200:
            assert time.monotonic() < deadline, client.get("/readyz").text
            time.sleep(0.05)
        plain = encode_exr(rgb_channels("color", np.full((16, 16, 3), 0.3, np.float32)))
        answer = client.post("/v1/reconstruct", content=plain, headers={"Content-Type": "image/x-exr"})
        assert answer.status_code == 200 and answer.headers["x-reconstruction-method"] == "oidn"
        info = client.get("/v1/models").json()
    kinds = {m["method"] for m in info["models"]}
    assert kinds == {"network", "fused"}, kinds
    for model in info["models"]:
        assert (model["provider"], model["precision"]) == want, model
