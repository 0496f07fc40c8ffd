"""The cells of report.md's tables: rows by method, numbers as the report prints them, the best in bold, an
equal-time row's spp and a multi-seed row's standard error."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

__all__ = ["bold_best", "by_method", "fmt", "spp_cell", "stderr_cell"]


def by_method(rows: Iterable[Mapping[str, Any]], spp: int) -> dict[str, Mapping[str, Any]]:
    return {str(r["method"]): r for r in rows if int(r["spp"]) == spp}


def fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "–"
    value = float(value)
    if math.isinf(value):
        return "∞"
    return f"{value:.{digits}g}"


def bold_best(values: dict[str, float | None], higher: bool) -> dict[str, str]:
    present = {k: v for k, v in values.items() if v is not None and not math.isnan(v)}
    best = (max if higher else min)(present.values()) if present else None
    return {k: ("–" if v is None else (f"**{fmt(v)}**" if v == best else fmt(v))) for k, v in values.items()}


def spp_cell(row: Mapping[str, Any]) -> str:
    if int(row.get("seeds") or 1) > 1:  # the seeds' median spp; * when a seed was interpolated to the budget
        return f"{row['method_spp']}{'*' if row.get('time_interpolated') else ''}"
    bracket = row.get("time_bracket")
    if row.get("time_interpolated") and isinstance(bracket, list) and len(bracket) == 2:
        return f"{bracket[0]['spp']}–{bracket[1]['spp']}*"
    return str(row["method_spp"])


def stderr_cell(row: Mapping[str, Any]) -> str:
    """`` ±SE`` after a multi-seed row's mean RelMSE (``--time-seeds``, ``--frame-seeds``), else nothing."""
    if int(row.get("seeds") or 1) > 1 and row.get("relmse_stderr") is not None:
        return f" ±{fmt(row['relmse_stderr'], 2)}"
    return ""
