"""What a G-PT render is asked for (:class:`GptSettings`) and what it gives back: the per-pixel channel layout
of one pass's sums and the finished :class:`GptResult`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gradsep.renderer.lanes import OFFSET_MODES, SHIFT_OFFSETS

# Which layers get gradients when offsets are traced: "all" of them, or the "direct" layer alone. With "direct" the
# offsets are traced only as far as the direct layer's events reach (emission seen at vertex 0, next-event
# estimation there, emission found by the BSDF sample leaving it: vertices 0 and 1) and the base path continues
# alone, so the indirect layer is a plain primal. The primal-only mode (no offsets at all) is ``shift=None``.
GRADIENT_MODES: tuple[str, ...] = ("all", "direct")


@dataclass(frozen=True)
class GptSettings:
    """What to render. ``max_depth`` follows Mitsuba (1 = emitters seen directly, 2 = direct light, -1 = no limit)."""

    max_depth: int = 6
    rr_depth: int = 5
    direct: bool = True
    indirect: bool = True
    separate: bool = True  # False: one ``color`` layer with every event (direct and indirect must both be on)
    offsets: str = "all"  # four offsets per sample, or fewer: "pair" (one axis), "single", "alternate" (OFFSET_MODES)
    gradients: str = "all"  # the layers with gradients when a shift is given: "all", or "direct" (GRADIENT_MODES)

    def layer_names(self) -> tuple[str, ...]:
        """The accumulated illumination layers, in the frame contract's order."""
        if not self.separate:
            return ("color",)
        return tuple(name for name, on in (("direct", self.direct), ("indirect", self.indirect)) if on)

    def gradient_layer_names(self) -> tuple[str, ...]:
        """The layers that carry gradients when offsets are traced (every layer, or the direct layer alone)."""
        if self.gradients == "direct":
            return tuple(name for name in self.layer_names() if name == "direct")
        return self.layer_names()

    def effective_max_depth(self) -> int:
        """The depth actually traced: a direct-only render stops after the first vertex's BSDF sample."""
        depth = self.max_depth if self.max_depth >= 0 else -1
        if not self.indirect:
            depth = 2 if depth < 0 else min(depth, 2)
        return depth

    def validate(self) -> None:
        """Reject settings that would render nothing or misbehave; the caller maps ValueError to a user error."""
        if self.max_depth == 0 or self.max_depth < -1:
            raise ValueError(f"max_depth must be -1 (unbounded) or >= 1, got {self.max_depth}")
        if self.rr_depth < 1:
            raise ValueError(f"rr_depth must be >= 1, got {self.rr_depth}")
        if not (self.direct or self.indirect):
            raise ValueError("no illumination layer requested")
        if self.offsets not in OFFSET_MODES:
            raise ValueError(f"unknown offsets mode {self.offsets!r}; expected one of {OFFSET_MODES}")
        if self.gradients not in GRADIENT_MODES:
            raise ValueError(f"unknown gradients mode {self.gradients!r}; expected one of {GRADIENT_MODES}")
        if self.gradients == "direct" and not (self.separate and self.direct):
            raise ValueError("gradients of the direct layer alone need the separated direct layer "
                             "(not an unseparated color render, nor the indirect layer alone)")
        if not self.separate and not (self.direct and self.indirect):
            raise ValueError("an unseparated (color) render carries all light: direct and indirect must both be on")
        if self.indirect and 0 < self.max_depth <= 2:
            raise ValueError(f"max_depth {self.max_depth} leaves no indirect light; render the direct layer only")



# Output channel groups of one pass (each 3 wide except depth / hit / invalid), per-pixel sums over samples.
@dataclass(frozen=True)
class Film:
    """The frame a render fills: its size, samples per pixel and seed. ``gradient_spp`` K (default ``spp``): only K
    of the ``spp`` samples trace offsets, the other ``spp - K`` are primal-only samples."""

    width: int
    height: int
    spp: int
    seed: int = 0
    gradient_spp: int | None = None


def channel_layout(settings: GptSettings, gradients: bool = True) -> dict[str, int]:
    """Name -> width of every accumulated per-pixel buffer, in scatter order."""
    layout: dict[str, int] = {}
    with_gradients = settings.gradient_layer_names() if gradients else ()
    for layer in settings.layer_names():
        layout[f"{layer}.base"] = 3
        layout[f"{layer}.sq"] = 1  # the squared luminance of each sample: the layer's per-pixel variance
        for i in range(len(SHIFT_OFFSETS) if layer in with_gradients else 0):
            layout[f"{layer}.grad{i}"] = 3
    layout.update({"albedo": 3, "normal": 3, "depth": 1, "hit": 1, "invalid": 1})
    return layout


@dataclass
class GptResult:
    """Per-pixel results as float32 numpy arrays (H, W, 3) / (H, W); gradients per the frame contract."""

    layers: dict[str, dict[str, np.ndarray]]  # layer -> {"base", "var", "dx", "dy"} (no dx/dy without gradients;
    #                                            "var" None at 1 spp: mean_variance)
    albedo: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    spp: int
    invalid_samples: int = 0
    passes: int = 1
    warnings: list[str] = field(default_factory=list)

