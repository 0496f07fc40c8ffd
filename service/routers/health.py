"""Liveness and readiness: what orchestrators and load balancers poll. Never need the bearer token."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends
from pydantic import BaseModel, Field

from gradsep.service.dependencies import get_engine
from gradsep.service.engine import Engine
from gradsep.service.errors import ErrorResponse, ServiceError

router = APIRouter(tags=["health"])


class Health(BaseModel):
    status: str


class Ready(BaseModel):
    status: str
    methods: list[str]
    default_method: str = Field(description="the method for a gradient-domain frame with features")
    default_method_plain: str | None = Field(description="the method for a plain frame without gradients (oidn)")


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers (always cheap)")
async def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Ready, summary="Readiness: models loaded and a warm-up inference ran",
            responses={503: {"model": ErrorResponse, "description": "still loading, or model loading failed",
                             "headers": {"Retry-After": {"schema": {"type": "integer"}}}}})
async def readyz(engine: Annotated[Engine, Depends(get_engine)]) -> Ready:
    if engine.state == "failed":
        raise ServiceError(503, "models_failed", f"model loading or warm-up failed: {engine.failure}",
                           {"models_dir": str(engine.settings.models_dir)}, {"Retry-After": "60"})
    if engine.state != "ready":
        raise ServiceError(503, "not_ready", "loading models and warming up", None, {"Retry-After": "1"})
    return Ready(status="ready", methods=list(engine.methods), default_method=engine.default_method,
                 default_method_plain=engine.default_method_plain)
