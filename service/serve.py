"""`gradsep serve`: run the service under uvicorn with settings validated up front."""

from __future__ import annotations

import copy
from typing import Any

from gradsep.model.errors import CommandError
from gradsep.service.settings import Settings


def _settings_or_error() -> Settings:
    """Read GRADSEP_* once here so a typo fails the command with one line instead of crashing each worker."""
    from pydantic import ValidationError

    try:
        return Settings()
    except ValidationError as exc:
        problems = "; ".join(f"{_variable(e['loc'])}: {e['msg']}" for e in exc.errors())
        raise CommandError(f"invalid service settings: {problems}") from None


def _variable(loc: tuple[object, ...]) -> str:
    name = ".".join(str(p) for p in loc).upper()
    return name if name.startswith("GRADSEP_") else f"GRADSEP_{name}"


def log_config(level: str) -> dict[str, Any]:
    """uvicorn's logging config plus our ``gradsep`` logger (access lines carry the request id)."""
    from uvicorn.config import LOGGING_CONFIG

    config = copy.deepcopy(LOGGING_CONFIG)
    config["loggers"]["gradsep"] = {"handlers": ["default"], "level": level.upper(), "propagate": False}
    return config


def serve(host: str, port: int, workers: int) -> None:
    """Start uvicorn with the app factory; each worker process builds its own app (stateless replicas)."""
    import uvicorn

    if not 0 <= port <= 65535:
        raise CommandError(f"--port must be between 0 and 65535, got {port}")
    if workers < 1:
        raise CommandError(f"--workers must be at least 1, got {workers}")
    from gradsep.service.protocol import http_protocol

    settings = _settings_or_error()
    uvicorn.run(
        "gradsep.service.main:create_app", factory=True, host=host, port=port, workers=workers,
        log_level=settings.log_level, log_config=log_config(settings.log_level),
        access_log=False,  # our own access line (service.middleware) has the request id
        server_header=False,
        http=http_protocol(),  # malformed requests (Content-Length: abc) get our JSON error, not plain text
        # On SIGTERM uvicorn stops accepting, lets in-flight requests finish, then runs the lifespan shutdown
        # (which waits for inference threads). Bound the wait by the longest a request may legitimately take.
        timeout_graceful_shutdown=int(settings.inference_timeout) + 30,
    )
