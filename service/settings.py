"""Service configuration: one pydantic-settings class, read from ``GRADSEP_*`` environment variables.

Every limit the service enforces lives here so that an operator can tune a deployment without code changes
(``GRADSEP_MAX_BODY_BYTES=1073741824 gradsep serve``) and so that tests can build apps with tiny limits.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import AliasChoices, Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from gradsep.model.allocator import DEFAULT_ARENAS
from gradsep.model.poisson import MIN_ALPHA
from gradsep.model.policy import DEFAULT_ALPHA, DEFAULT_MODELS_DIR, MODELS_ENV

MiB = 1024 * 1024


class Settings(BaseSettings):
    """Limits, concurrency and security of one service process (each uvicorn worker reads its own copy)."""

    model_config = SettingsConfigDict(env_prefix="GRADSEP_", extra="ignore", populate_by_name=True)

    max_body_bytes: int = Field(
        256 * MiB, ge=1024, description="largest request body accepted; bigger bodies get 413 while streaming")
    body_memory_bytes: int = Field(
        128 * MiB, ge=0,
        description="bytes of request bodies held in memory, across all open uploads; a body this pool cannot "
                    "hold goes on in a temporary file in spool_dir, so no upload buffers past it (0: every body "
                    "on disk)")
    max_uploads: int = Field(
        16, ge=1, le=4096,
        description="request bodies being received at once; beyond that 503 + Retry-After (each open upload "
                    "also holds up to two of uvicorn's per-connection read buffers)")
    spool_dir: Path | None = Field(
        None, description="folder for the request bodies spooled to disk (default: the system temporary folder); "
                          "on a disk, not tmpfs, or the spooled bytes are memory again")
    max_pixels: int = Field(
        8192 * 8192, ge=1, description="largest width*height decoded; decided from the EXR header (413)")
    max_values: int = Field(
        8192 * 8192 * 24, ge=1, description="largest width*height*channels decoded; from the header (413)")
    concurrency: int = Field(
        1, ge=1, le=64, description="inferences running at once (1-2 on a 2-core host; each uses its own thread)")
    queue_size: int = Field(
        8, ge=0, description="requests allowed to wait for an inference slot; beyond that 503 + Retry-After")
    inference_timeout: float = Field(
        300.0, gt=0, description="seconds a request waits for queueing + decode + reconstruction + encode (504)")
    body_timeout: float = Field(
        30.0, gt=0, le=3600,
        description="seconds a request body may stall (no bytes arriving) before the request gets 408 and its "
                    "connection is closed; a slow upload that keeps moving is not cut")
    token: SecretStr | None = Field(
        None, description="bearer token; when set every endpoint but /healthz, /readyz and (with docs=open) the "
                          "API docs requires it (401)")
    docs: Literal["open", "protected", "off"] = Field(
        "open", description="/docs, its assets and /openapi.json: open (no token needed: they hold no secret), "
                            "protected (behind the token like the API), or off (404)")
    models_dir: Path = Field(
        Path(DEFAULT_MODELS_DIR), validation_alias=AliasChoices(MODELS_ENV, "GRADSEP_MODELS_DIR"),
        description=f"folder of exported ONNX models (env {MODELS_ENV}); absent -> Poisson methods only")
    nonfinite: Literal["reject", "zero"] = Field(
        "reject", description="NaN/Inf in radiance or gradients: reject with 422, or replace with 0 and warn")
    default_alpha: float = Field(
        DEFAULT_ALPHA, ge=MIN_ALPHA, le=1000,
        description="screened Poisson data weight used when a request gives no alpha")
    layer_threads: int = Field(
        2, ge=1, le=64,
        description="a frame's layers reconstructed at once (1: one after the other); read by model.reconstruct "
                    "from the same variable, validated here so a bad value stops `gradsep serve` at startup")
    exr_threads: int = Field(
        -1, ge=-1, le=256,
        description="OpenEXR's process-wide worker threads for decoding requests and encoding answers "
                    "(line blocks are (de)compressed in parallel): -1 one per core, 0 single-threaded")
    malloc_arenas: int = Field(
        DEFAULT_ARENAS, ge=0, le=1024,
        description="glibc malloc arenas of the process, with fixed mmap/trim thresholds (model/allocator.py): 1 "
                    "keeps the frame-sized temporaries of the worker threads in one arena that keeps its memory "
                    "(no fresh pages per request); 0 leaves glibc's malloc as it is; the "
                    "operator's own MALLOC_* variables win")
    warm_up: bool = Field(True, description="run one small inference per method before reporting ready")
    log_level: Literal["critical", "error", "warning", "info", "debug"] = Field("info")

    @field_validator("token", mode="before")
    @classmethod
    def _empty_token_is_none(cls, value: object) -> object:
        """``GRADSEP_TOKEN=`` (set but empty) must not enable auth with an empty, guessable token."""
        if value is None or (isinstance(value, str) and not value.strip()):
            return None
        return value

    @field_validator("spool_dir")
    @classmethod
    def _spool_dir_exists(cls, value: Path | None) -> Path | None:
        if value is not None and not value.is_dir():
            raise ValueError(f"{value} is not a folder")
        return value

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower_level(cls, value: object) -> object:
        return value.lower() if isinstance(value, str) else value

    @property
    def token_value(self) -> str | None:
        return self.token.get_secret_value() if self.token is not None else None
