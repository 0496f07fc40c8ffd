"""fused's direct layer (model/fused.py FIXED_LAYERS): the oidn-l1 refinement at fused's own CG budget DIRECT_CG."""

from __future__ import annotations

import numpy as np
import pytest

from gradsep.model import fused
from gradsep.model.frame import Layer, forward_differences

pytest.importorskip("pyoidn")


def _layer(h: int = 24, w: int = 28, seed: int = 3) -> Layer:
    rng = np.random.default_rng(seed)
    truth = np.repeat(np.repeat(rng.uniform(0.1, 2.0, (h // 6 + 1, w // 6 + 1, 3)), 6, 0), 6, 1)[:h, :w]
    truth = truth.astype(np.float32)
    dx, dy = forward_differences(truth)
    noisy = truth * rng.gamma(4.0, 0.25, truth.shape).astype(np.float32)
    return Layer(noisy, dx + rng.normal(0, 0.05, dx.shape).astype(np.float32),
                 dy + rng.normal(0, 0.05, dy.shape).astype(np.float32))


def test_direct_layer_is_the_refinement_at_the_pinned_cg_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    """The served direct kind solves with DIRECT_CG (relative residual, step cap) per IRLS pass and the oidn-l1
    method's passes, and nothing else: every pass stops within the cap."""
    import gradsep.model.refine as refine

    assert fused.FIXED_LAYERS["direct"] == "refine-direct" and "refine-direct" in fused.FIXED_KINDS
    calls: list[dict] = []
    stats: list = []
    real = refine.solve_l1

    def spy(*args, **kwargs):
        options = args[4]
        calls.append({"passes": options.iterations, "cg_iterations": options.cg_iterations,
                      "cg_tolerance": options.cg_tolerance, **kwargs})
        out = real(*args, **kwargs)
        stats.append(out[1])
        return out

    monkeypatch.setattr(refine, "solve_l1", spy)
    tolerance, steps = fused.DIRECT_CG
    _, (image,), scale = fused.layer_candidates(_layer(), None, ("refine-direct",))
    assert len(calls) == 1
    assert calls[0]["cg_iterations"] == steps and calls[0]["cg_tolerance"] == tolerance
    assert calls[0]["passes"] == refine.REFINE_ITERATIONS
    assert max(stats[0].cg_iterations) <= steps
    assert image.dtype == np.float32 and np.isfinite(image).all() and image.min() >= 0 and scale > 0


def test_direct_budget_is_cheaper_than_and_close_to_the_oidn_l1_solve() -> None:
    """refine-direct is oidn-l1's refinement at fused's own CG budget: a nearby image (the same one while both
    budgets are equal, as since the oidn-l1 cap became 4 steps), from the same OIDN pass."""
    from gradsep.model.refine import refine_layer

    layer = _layer(40, 48, seed=7)
    scaled, (oidn, cheap), _ = fused.layer_candidates(layer, None, ("oidn", "refine-direct"))
    full = refine_layer("direct", oidn, scaled)  # the oidn-l1 method's own solve of the same layer
    assert not np.array_equal(cheap, oidn)
    rel = np.abs(cheap - full).mean() / full.mean()
    assert rel < 0.05, rel
    for unknown in ("refine-directly", "oidn-l1", "refine", "l1"):  # not candidates (any more)
        with pytest.raises(fused.BlendModelError, match="unknown candidate kind"):
            fused.layer_candidates(layer, None, (unknown,))
