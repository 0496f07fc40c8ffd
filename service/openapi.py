"""OpenAPI schema tweaks: declare bearer security exactly when the service enforces it.

Declaring it unconditionally would make the schema lie when no token is configured (schema-driven tests such as
schemathesis check that a declared scheme is enforced), so the scheme is added only for secured deployments,
with health and readiness marked as open.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.middleware import OPEN_PATHS


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
