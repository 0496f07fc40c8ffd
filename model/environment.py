"""Integer settings read from the environment by processes that have no pydantic Settings (the CLI, library
callers): one parser, so every such variable is refused the same way."""

from __future__ import annotations

import os


def env_int(variable: str, default: int, minimum: int, hint: str = "") -> int:
    """``$variable`` as an integer ≥ ``minimum``, or ``default`` when unset or blank; ValueError naming the
    variable otherwise (``hint``, e.g. what the smallest value means, is appended in parentheses)."""
    raw = os.environ.get(variable, "").strip()
    if not raw:
        return default
    note = f" ({hint})" if hint else ""
    try:
        value = int(raw)
    except ValueError:
        raise ValueError(f"${variable}={raw!r} is not an integer{note}") from None
    if value < minimum:
        raise ValueError(f"${variable}={value} must be at least {minimum}{note}")
    return value
