"""``GET /v1/models``: what this replica can do, so clients and operators can check a deployment."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends
from pydantic import BaseModel, Field

from gradsep.service.dependencies import get_engine
from gradsep.service.engine import Engine
from gradsep.service.errors import ErrorResponse

router = APIRouter(tags=["models"])


class Limits(BaseModel):
    max_body_bytes: int
    max_pixels: int
    max_values: int


class ModelsInfo(BaseModel):
    state: str = Field(description="loading, ready or failed")
    default_method: str = Field(description="the method used when a request names none, for a gradient-domain "
                                            "frame with features (the first served of the methods table's default "
                                            "preference; a frame it cannot serve gets the next that can)")
    default_method_plain: str | None = Field(description="the method for a plain frame without gradients")
    methods: list[str] = Field(description="methods this replica serves: those of the methods table whose models "
                                           "are loaded (see method_table)")
    method_table: list[dict[str, Any]] = Field(
        default_factory=list,
        description="every method of the table: what it needs of a frame (gradients: none, direct or all; feature "
                    "groups used and required), the model sets it needs, and whether this replica serves it")
    models: list[dict[str, Any]] = Field(
        description="loaded networks: name, layers, input channels, checksums and export metadata")
    oidn: dict[str, Any] | None = Field(
        None, description="the OIDN methods' denoiser: its setting (model/oidn.py); null without pyoidn")
    limits: Limits


@router.get("/v1/models", response_model=ModelsInfo, summary="Loaded models, available methods and limits",
            responses={401: {"model": ErrorResponse, "description": "bearer token missing or invalid"}})
async def list_models(engine: Annotated[Engine, Depends(get_engine)]) -> ModelsInfo:
    s = engine.settings
    return ModelsInfo(state=engine.state, default_method=engine.default_method,
                      default_method_plain=engine.default_method_plain, methods=list(engine.methods),
                      method_table=engine.describe_methods(),
                      models=engine.describe_models(), oidn=engine.describe_oidn() if engine.state == "ready" else None,
                      limits=Limits(max_body_bytes=s.max_body_bytes, max_pixels=s.max_pixels,
                                    max_values=s.max_values))
