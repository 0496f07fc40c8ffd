"""A small random frame for the frame-contract tests (tests/model/test_frame.py, test_exr_read.py)."""

from __future__ import annotations

import numpy as np

from gradsep.model.frame import Features, Frame, Layer, forward_differences


def make_frame(h: int = 6, w: int = 9, layers: tuple[str, ...] = ("direct", "indirect"), features: bool = True,
               seed: int = 0) -> Frame:
    rng = np.random.default_rng(seed)
    out = {}
    for name in layers:
        base = rng.random((h, w, 3), dtype=np.float32) * 4
        out[name] = Layer(base, *forward_differences(base))
    feats = None
    if features:
        normal = rng.normal(size=(h, w, 3)).astype(np.float32)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        feats = Features(rng.random((h, w, 3), dtype=np.float32), normal, rng.random((h, w), dtype=np.float32) * 10)
    return Frame(out, feats, {"gradsep.spp": "16"})
