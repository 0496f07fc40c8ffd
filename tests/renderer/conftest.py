"""Fixtures the renderer's test modules share."""

from __future__ import annotations

import pytest

from tests.renderer.scenes import resolve


@pytest.fixture(scope="module")
def small():
    """The Cornell box at 16x12, max depth 5: the planner tests' frame (loading it needs Mitsuba)."""
    pytest.importorskip("mitsuba")
    from gradsep.renderer.scene import load_scene

    return load_scene(str(resolve("cbox")), width=16, height=12, max_depth=5)
