"""``GET /metrics``: Prometheus text exposition of this app's own registry."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends
from starlette.responses import Response

from gradsep.service.dependencies import get_metrics
from gradsep.service.errors import ErrorResponse
from gradsep.service.metrics import ServiceMetrics

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=Response, summary="Prometheus metrics",
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                             "description": "Prometheus text format 0.0.4"},
                       401: {"model": ErrorResponse, "description": "bearer token missing or invalid"}})
async def metrics(registry: Annotated[ServiceMetrics, Depends(get_metrics)]) -> Response:
    return Response(registry.render(), media_type=registry.content_type)
