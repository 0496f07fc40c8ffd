"""The API docs and the OpenAPI schema (service/openapi.py)."""

from __future__ import annotations

import re

from tests.service.conftest import TRANSPORT


@TRANSPORT
def test_docs_page_and_its_assets_are_served_locally(poisson_api, transport):
    """/docs must work on an offline farm network: every script and stylesheet it loads comes from us."""
    client = poisson_api[transport]
    page = client.get("/docs")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assets = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    assert assets and all(a.startswith("/docs/static/") for a in assets), assets
    for asset in assets:
        response = client.get(asset)
        assert response.status_code == 200 and len(response.content) > 100, asset
    assert "SwaggerUIBundle" in client.get("/docs/static/swagger-ui-bundle.js").text
    assert client.get("/openapi.json").status_code == 200

