"""OpenAPI schema tweaks and the offline API docs.

Bearer security is declared exactly when the service enforces it.

Declaring it unconditionally would make the schema lie when no token is configured (schema-driven tests such as
schemathesis check that a declared scheme is enforced), so the scheme is added only for secured deployments,
with health and readiness marked as open.

``/docs`` is Swagger UI served from the ``swagger-ui-bundle`` package's files (``/docs/static/...``), not from a
CDN: render-farm networks are often offline, where FastAPI's default page stays blank. FastAPI's ``/redoc``
(CDN only) is switched off in service.main.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.openapi.utils import get_openapi
from starlette.responses import HTMLResponse
from starlette.staticfiles import StaticFiles

from gradsep.service.middleware import OPEN_PATHS


def install_openapi(app: FastAPI, *, secured: bool) -> None:
    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description,
                                 routes=app.routes)
            if secured:
                schema.setdefault("components", {})["securitySchemes"] = {
                    "bearer": {"type": "http", "scheme": "bearer", "description": "GRADSEP_TOKEN"}}
                schema["security"] = [{"bearer": []}]
                for path in OPEN_PATHS:
                    for operation in schema.get("paths", {}).get(path, {}).values():
                        operation["security"] = []
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


DOCS_STATIC = "/docs/static"


def install_docs(app: FastAPI) -> None:
    """``GET /docs``: Swagger UI whose script, stylesheet and icon are served by this app (works offline)."""
    from swagger_ui_bundle import swagger_ui_path  # the serve extra's package of Swagger UI's built files

    app.mount(DOCS_STATIC, StaticFiles(directory=str(swagger_ui_path)), name="swagger-ui")

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json", title=f"{app.title} API",
            swagger_js_url=f"{DOCS_STATIC}/swagger-ui-bundle.js", swagger_css_url=f"{DOCS_STATIC}/swagger-ui.css",
            swagger_favicon_url=f"{DOCS_STATIC}/favicon-32x32.png")
