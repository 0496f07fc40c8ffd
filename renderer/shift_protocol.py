"""The shift interface between the G-PT integrator (renderer/gpt_loop.py) and its shift mappings
(renderer/shift.py, renderer/hybrid.py): what an offset path reports per base vertex, and the protocols a shift
implements.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import mitsuba as mi

from gradsep.renderer.vertex import Vertex, VertexSamples


@dataclass
class OffsetEvents:
    """An offset path's contributions for the base vertex's two events, with the MIS weights of the pair.

    ``emitted``/``nee`` are the offset path's contributions already multiplied by the shift's Jacobian and
    expressed per base-path sample (0 where the offset path does not produce the event). ``w_hit``/``w_nee`` are
    the weights of this technique (base here, offset there) for the pixel pair; the mirrored technique from the
    neighbour's base path must receive ``1 - w`` for the same pair.
    """

    emitted: mi.Spectrum
    nee: mi.Spectrum
    w_hit: mi.Float
    w_nee: mi.Float


class Shift(Protocol):
    """A shift mapping: how an offset path is built from its base path, one base vertex at a time."""

    name: str
    reuses_light_samples: bool  # offsets reconnect to the base path's emitter sample (see trace_vertex)

    def ray_flags(self, scene: mi.Scene) -> mi.RayFlags:
        """What every surface interaction must carry for this shift (the base path's too)."""

    def start(self, ray: mi.Ray3f, weight: mi.Spectrum, active: mi.Bool) -> Any:
        """Offset loop state for the offset's primary ray (``active`` is False outside the image)."""

    def step(self, scene: mi.Scene, offset: Any, base: Vertex, depth: mi.UInt32, max_depth: mi.UInt32,
             samples: VertexSamples, later: bool = False) -> tuple[Any, OffsetEvents]:
        """Advance an offset path by the base path's vertex; returns the new state and its events. ``later``: the
        caller knows the vertex is not the first (depth >= 1), so primary-ray code may be left out."""

    def scale(self, offset: Any, factor: mi.Float, active: mi.Bool) -> Any:
        """Multiply the offset's throughput by ``factor`` where ``active`` (Russian roulette of the base)."""

    def kill(self, offset: Any, dead: mi.Bool) -> Any:
        """Stop the offset where ``dead`` (the base path was terminated by Russian roulette)."""


@runtime_checkable
class ConnectingShift(Shift, Protocol):
    """A shift whose offsets can end up sharing every later vertex of their base path ("connected"). From then
    on an offset's events are the base path's scaled by its own throughput, so it needs no per-vertex work:
    the integrator runs a second, cheap loop once every offset of a lane is connected or finished."""

    def settled(self, offset: Any) -> mi.Bool:
        """Per lane: the offset is finished or connected, so it can be summarised."""

    def summarize(self, offset: Any) -> Any:
        """The small loop state a settled offset continues with (it must support ``scale``/``kill``)."""

    def step_connected(self, summary: Any, base: Vertex, depth: mi.UInt32,
                       max_depth: mi.UInt32) -> tuple[Any, OffsetEvents]:
        """:meth:`step` for a summarised offset: the same events as the full step gives a connected offset."""
