"""Health, readiness, the models and the metrics routes (service/routers/health.py, models.py, metrics.py)."""

from __future__ import annotations

import importlib.util
import re

from tests.service.conftest import TRANSPORT, post


@TRANSPORT
def test_health_readiness_models_and_metrics(poisson_api, transport):
    client = poisson_api[transport]
    assert client.get("/healthz").json() == {"status": "ok"}
    oidn = importlib.util.find_spec("pyoidn") is not None  # part of the serve extra; l1 is the fallback without
    methods, default = (["l1", "l2", "oidn", "oidn-l1"], "oidn-l1") if oidn else (["l1", "l2"], "l1")
    assert client.get("/readyz").json() == {"status": "ready", "methods": methods, "default_method": default,
                                            "default_method_plain": "oidn" if oidn else None}
    models = client.get("/v1/models").json()
    assert models["models"] == [] and models["default_method"] == default and models["state"] == "ready"
    assert models["limits"]["max_pixels"] == 8192 * 8192
    if oidn:  # which code runs the OIDN methods' denoiser, and at which setting
        assert models["oidn"] == {"setting": "raw-fast"}
    else:
        assert models["oidn"] is None
    post(client, b"definitely not an exr")
    metrics = client.get("/metrics")
    assert metrics.status_code == 200 and metrics.headers["content-type"].startswith("text/plain")
    text = metrics.text
    assert re.search(r'gradsep_http_requests_total\{method="GET",route="/healthz",status="200"\} [1-9]', text)
    assert re.search(r'gradsep_rejections_total\{reason="not_exr"\} [1-9]', text)
    assert "gradsep_http_request_duration_seconds_bucket" in text
    assert re.search(r"gradsep_http_requests_in_flight 1\.0", text)  # this very request
    assert re.search(r"gradsep_ready 1\.0", text)

