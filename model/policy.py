"""The contract's constants, in one place: layer names, method names, which need what, the default method for
each kind of frame, the default alpha and the models-folder setting.

Import-light on purpose (standard library only, no numpy): the command line's argument parsers, the service's
settings and query validation, the evaluation and the library all read these names, so a new method, layer or
default is changed here once and every front end follows.
"""

from __future__ import annotations

import os
from collections.abc import Collection
from pathlib import Path

#: The illumination layers a frame may carry (docs/frame-format.md): ``direct`` and ``indirect`` when the
#: renderer separates illumination, ``color`` for an unseparated frame. Order = channel order in files.
ILLUMINATION_LAYERS: tuple[str, ...] = ("direct", "indirect", "color")
#: The layers of a separated frame (the default render), in contract order.
SEPARATED_LAYERS: tuple[str, ...] = ("direct", "indirect")

#: The screened Poisson data weight (l1/l2, and the network's truncated L1 prior) when none is given.
DEFAULT_ALPHA: float = 0.2

#: The environment variable naming the folder of exported models, and its fallback (relative to the cwd).
MODELS_ENV = "GRADSEP_MODELS"
DEFAULT_MODELS_DIR = "models"

#: Every reconstruction method (model/reconstruct.py documents each).
METHODS: tuple[str, ...] = ("network", "l1", "l2", "oidn", "oidn-l1", "fused")
#: The screened Poisson solvers: the methods that take ``alpha``.
POISSON_METHODS: tuple[str, ...] = ("l1", "l2")
#: Methods that integrate gradients: a plain (gradient-free) frame cannot use them. ``oidn-l1`` needs only the direct
#: layer's (the one it refines; a frame from ``gradsep render --gradients direct``), the others every layer's
#: (model.reconstruct.missing_gradient_channels).
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
#: The one method for a plain frame (no gradient channels): the gradient methods cannot serve it.
PLAIN_METHOD = "oidn"


def preference_order() -> tuple[str, ...]:
    """Every method, best first: DEFAULT_PREFERENCE, then the rest of METHODS (read at call time, so a change
    of DEFAULT_PREFERENCE -- or a test patching it -- is seen everywhere)."""
    return (*DEFAULT_PREFERENCE, *(m for m in METHODS if m not in DEFAULT_PREFERENCE))


def default_method(served: Collection[str], *, gradients: bool = True) -> str | None:
    """The default method for a frame, given the methods that can serve it.

    A frame with gradients (on every layer, or on some: ``gradients`` True) gets the first of
    :func:`preference_order` in ``served``; a plain frame (no gradients) gets PLAIN_METHOD when served, else None
    (nothing can serve it). Used by
    model.reconstruct.choose_method per frame and by the service's /readyz and /v1/models.
    """
    if not gradients:
        return PLAIN_METHOD if PLAIN_METHOD in served else None
    return next((m for m in preference_order() if m in served), None)


def models_dir_from(value: str | os.PathLike[str] | None) -> Path:
    """The models folder: the explicit value, else $GRADSEP_MODELS, else ``models`` (relative to the cwd)."""
    return Path(value or os.environ.get(MODELS_ENV) or DEFAULT_MODELS_DIR)
