"""The contract's constants, in one place: layer names, feature groups, the default alpha and the models-folder
setting (the methods and what each needs are the table in model/methods.py).

Import-light on purpose (standard library only, no numpy): the command line's argument parsers, the service's
settings and query validation, the evaluation and the library all read these names, so a new layer or default is
changed here once and every front end follows.
"""

from __future__ import annotations

import os
from pathlib import Path

#: The illumination layers a frame may carry (docs/frame-format.md): ``direct`` and ``indirect`` when the
#: renderer separates illumination, ``color`` for an unseparated frame. Order = channel order in files.
ILLUMINATION_LAYERS: tuple[str, ...] = ("direct", "indirect", "color")
#: The layers of a separated frame (the default render), in contract order.
SEPARATED_LAYERS: tuple[str, ...] = ("direct", "indirect")

#: The feature groups a frame may carry, each optional and each all-or-nothing (its channels, in file order):
#: docs/frame-format.md. Which method uses or needs which group is declared in model/methods.py.
FEATURE_GROUPS: dict[str, tuple[str, ...]] = {
    "albedo": ("albedo.R", "albedo.G", "albedo.B"),
    "normal": ("normal.X", "normal.Y", "normal.Z"),
    "depth": ("depth.Z",),
}

#: Rec. 709 luminance weights of linear RGB: the contract's ``Y`` (a layer's variance channel ``L.var.Y`` is the
#: variance of this weighted sum of ``L.R L.G L.B``), and the weights every metric and exposure rule uses.
LUMINANCE: tuple[float, float, float] = (0.2126, 0.7152, 0.0722)

#: The screened Poisson data weight (l1/l2, and the network's truncated L1 prior) when none is given.
DEFAULT_ALPHA: float = 0.2

#: The environment variable naming the folder of exported models, and its fallback (relative to the cwd).
MODELS_ENV = "GRADSEP_MODELS"
DEFAULT_MODELS_DIR = "models"


def models_dir_from(value: str | os.PathLike[str] | None) -> Path:
    """The models folder: the explicit value, else $GRADSEP_MODELS, else ``models`` (relative to the cwd)."""
    return Path(value or os.environ.get(MODELS_ENV) or DEFAULT_MODELS_DIR)
