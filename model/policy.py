"""The reconstruction policy's constants, in one place: the method names, which need what, and the default.

Import-light on purpose (no numpy): the command line's argument parsers, the service's query validation and the
library all read these names, so a new method or a change of default is made here once.
"""

from __future__ import annotations

#: Every reconstruction method (model/reconstruct.py documents each).
METHODS: tuple[str, ...] = ("network", "l1", "l2", "oidn", "fused")
#: Methods that integrate gradients: a plain (gradient-free) frame cannot use them.
GRADIENT_METHODS: frozenset[str] = frozenset({"network", "l1", "l2", "fused"})
#: Methods that need a loaded model set (and the frame's feature channels).
MODEL_METHODS: frozenset[str] = frozenset({"network", "fused"})
#: The default per frame: the first method of this list that can serve it (model.reconstruct.choose_method).
#: The order is the evaluation's ranking (docs/evaluation-report/report.md, 2026-12-01, reference noise removed):
#: ``oidn`` had the lowest RelMSE of the G-PT methods in 12 of 16 (scene, spp) cases and ``fused`` was not
#: better than it (worse in 13 of 16, by 0.2-38 %, better in 3 by at most 1 %) at a higher cost, so ``oidn``
#: comes first for every frame it can serve; ``network`` on a host without pyoidn; ``l1`` when nothing else applies.
#: (Where OIDN is weak -- the teapot at 4-64 spp, 3-8x above ``network`` -- no method in this list is chosen
#: per scene yet: docs/network.md, "The oidn and fused methods".)
#: That ranking was measured with ``oidn`` at OIDN's prefiltered-high setting. Since docs/oidn.md ``oidn`` runs
#: raw-fast (1.69x the RelMSE, 6-8x faster: the 2 s latency target); ``fused`` keeps its trained prior and is now
#: ahead of ``oidn`` in error on the study's frames (1.02x vs 1.69x the old setting) at about 5x the latency. The
#: order is kept for latency; the next evaluation report measures the new trade-off.
DEFAULT_PREFERENCE: tuple[str, ...] = ("oidn", "fused", "network", "l1")
