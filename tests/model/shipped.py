"""The shipped models (models/) for a method's tests: each model set the method's table entry names, loaded once
per test worker, or a skip naming what this machine lacks (no models, no pyoidn)."""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

import pytest

from gradsep.model import methods as table

MODELS = Path(__file__).resolve().parents[2] / "models"


@cache
def _loaded(name: str) -> Any:
    return table.resolve(table.MODEL_SETS[name].loader)(MODELS)


def models_for(method: str) -> table.LoadedModels:
    """What ``reconstruct`` needs to run ``method`` with the shipped models; skips when a set is unavailable."""
    sets = {}
    for name in table.get(method).models:
        value = _loaded(name)
        if value is None or value is False:
            pytest.skip(f"{method} needs {table.MODEL_SETS[name].description}, which this machine lacks")
        sets[name] = value
    return table.LoadedModels(**sets)
