"""FastAPI dependencies shared by the routers."""

from __future__ import annotations

from fastapi import Request

from gradsep.service.engine import Engine
from gradsep.service.metrics import ServiceMetrics


def get_engine(request: Request) -> Engine:
    return request.app.state.engine


def get_metrics(request: Request) -> ServiceMetrics:
    return request.app.state.metrics

