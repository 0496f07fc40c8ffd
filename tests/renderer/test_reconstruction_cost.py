"""What reconstructing costs the planner (renderer/reconstruction_cost.py): its start-up paid in the background,
and its rate timed on a tile."""

from __future__ import annotations

import sys

import numpy as np

from gradsep.model.frame import Frame, Layer
from gradsep.renderer.reconstruction_cost import (
    RECONSTRUCT_STARTUP,
    reconstruct_rate,
    reconstruct_startup,
    warm_reconstruction,
)


def test_the_reconstruction_start_up_is_paid_in_the_background_both_ways_and_only_once(monkeypatch):
    """The checkpoint's first reconstruction pays the library's start-up: a thread pays it on a small tile, with
    gradients and as a plain frame, while passes render. An error there is left for the foreground to raise."""
    rng = np.random.default_rng(0)
    grad = rng.random((16, 16, 3), dtype=np.float32)
    tile = Frame(layers={"direct": Layer(base=grad, dx=grad, dy=grad)})
    seen: list[bool] = []

    def fake(frame: Frame):
        seen.append(frame.layers["direct"].has_gradients)
        raise RuntimeError("the library failed")  # swallowed in the thread

    monkeypatch.delitem(sys.modules, "pyoidn", raising=False)
    assert reconstruct_startup() == RECONSTRUCT_STARTUP  # not paid yet: the planner budgets for it
    thread = warm_reconstruction(tile, fake)
    assert thread is not None
    thread.join(timeout=10)
    assert seen == [True]  # the first call raised: the thread stopped there, quietly
    seen.clear()
    thread = warm_reconstruction(tile, lambda f: (seen.append(f.layers["direct"].has_gradients), ("", ""))[1])
    thread.join(timeout=10)
    assert seen == [True, False]
    monkeypatch.setitem(sys.modules, "pyoidn", object())
    assert warm_reconstruction(tile, fake) is None and reconstruct_startup() == 0.0  # paid already


def test_the_reconstruction_rate_is_timed_on_the_centre_tile_after_a_warm_up():
    frame = Frame(layers={"direct": Layer(np.ones((100, 130, 3), np.float32))})
    seen = []

    def fake(tile: Frame) -> tuple[np.ndarray, str]:
        seen.append(tile.layers["direct"].base.shape)
        return tile.layers["direct"].base, "oidn"

    rate = reconstruct_rate(frame, fake, side=64)
    assert seen == [(64, 64, 3), (64, 64, 3)] and 0 < rate < 1
    small = Frame(layers={"direct": Layer(np.ones((5, 7, 3), np.float32))})
    seen.clear()
    reconstruct_rate(small, fake, side=64)
    assert seen == [(5, 7, 3), (5, 7, 3)]  # a frame under the tile: the whole frame
