"""The reconstruction policy's constants, in one place: the method names, which need what, and the default.

Import-light on purpose (no numpy): the command line's argument parsers, the service's query validation and the
library all read these names, so a new method or a change of default is made here once.
"""

from __future__ import annotations

#: Every reconstruction method (model/reconstruct.py documents each).
METHODS: tuple[str, ...] = ("network", "l1", "l2", "oidn", "oidn-l1", "fused")
#: Methods that integrate gradients: a plain (gradient-free) frame cannot use them.
GRADIENT_METHODS: frozenset[str] = frozenset({"network", "l1", "l2", "oidn-l1", "fused"})
#: Methods that run Open Image Denoise (they need pyoidn).
OIDN_METHODS: frozenset[str] = frozenset({"oidn", "oidn-l1"})
#: Methods that need a loaded model set (and the frame's feature channels).
MODEL_METHODS: frozenset[str] = frozenset({"network", "fused"})
#: The default per frame: the first method of this list that can serve it (model.reconstruct.choose_method).
#: ``oidn-l1`` first for a G-PT frame: chosen on held-out procedural seeds, never on the evaluation's scenes
#: (model/refine.py; docs/network.md "The oidn-l1 method"): it lowered RelMSE against ``oidn`` in every (seed, spp)
#: case at 16 and 64 spp and in 10 of 12 at 1-4 spp. ``oidn`` for a plain frame (oidn-l1 needs gradients) and
#: wherever it comes next; ``fused`` was not better than ``oidn`` (the evaluation report of 2026-12-01: worse in 13
#: of 16 cases); ``network`` on a host without pyoidn; ``l1`` when nothing else applies.
DEFAULT_PREFERENCE: tuple[str, ...] = ("oidn-l1", "oidn", "fused", "network", "l1")
