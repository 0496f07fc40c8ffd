"""The FastAPI application: ``create_app(settings)`` builds one independent, stateless service instance."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio
from fastapi import FastAPI

from gradsep.model import __version__
from gradsep.service import errors, middleware, openapi
from gradsep.service.engine import Engine
from gradsep.service.metrics import ServiceMetrics
from gradsep.service.routers import health, metrics, models, reconstruct
from gradsep.service.settings import Settings


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    async with anyio.create_task_group() as task_group:  # closing it waits for in-flight inferences
        app.state.engine.start(task_group)  # loads models and warms up in the background
        yield


def create_app(settings: Settings | None = None) -> FastAPI:
    """An app with its own settings, metrics registry and inference gate (tests build many side by side)."""
    settings = settings or Settings()
    app = FastAPI(title="gradsep", version=__version__, lifespan=lifespan, docs_url=None, redoc_url=None,
                  openapi_url="/openapi.json" if settings.docs != "off" else None,
                  description="Gradient-domain rendering reconstruction with direct/indirect separation.")
    app.state.settings, app.state.metrics, app.state.engine = settings, ServiceMetrics(), Engine(settings)
    app.state.metrics.bind_engine(app.state.engine)
    errors.install_error_handlers(app)
    for router in (health.router, models.router, reconstruct.build_router(), metrics.router):
        app.include_router(router)
    if settings.docs != "off":
        openapi.install_docs(app)  # before the middleware reads the routes: /docs is then a known path for metrics
    middleware.install_middleware(app, settings, app.state.metrics, retry_after=app.state.engine.retry_after)
    openapi.install_openapi(app, secured=settings.token is not None)
    return app
