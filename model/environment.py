"""The process's environment: integer settings read from it by processes that have no pydantic Settings (the CLI,
library callers: one parser, so every such variable is refused the same way), the machine's CPU model, and a map
over worker threads."""

from __future__ import annotations

import os
import platform
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

_T = TypeVar("_T")
_R = TypeVar("_R")


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


def cpu_model() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo), else what ``platform`` knows of it."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def thread_map(fn: Callable[[_T], _R], items: Sequence[_T], threads: int, name: str = "gradsep") -> list[_R]:
    """``[fn(item) for item in items]`` on up to ``threads`` worker threads (named ``name``), in this thread for one
    item or one thread: the results in the items' order, and the first failure in that order raised, as the loop
    would. For numpy and scipy passes over whole images, which release the GIL."""
    workers = min(threads, len(items))
    if workers <= 1:
        return [fn(item) for item in items]
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name) as pool:
        return list(pool.map(fn, items))
