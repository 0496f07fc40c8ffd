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
#: The default per frame: the first method of this list that can serve it (model.reconstruct.choose_method):
#: ``fused`` for a gradient-domain frame with features when its models are installed, ``oidn`` for a plain frame.
#: The order is the evaluation's ranking (docs/evaluation-report/report.md).
DEFAULT_PREFERENCE: tuple[str, ...] = ("fused", "oidn", "network", "l1")
