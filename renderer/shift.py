"""Shift mappings for the G-PT integrator (renderer/gpt_loop.py): how an offset path is built from its base path,
and :func:`make_shift`, the one place a shift is chosen by name (``gradsep render --shift replay|hybrid``).

A shift implements the small :class:`renderer.shift_protocol.Shift` protocol: ``start`` makes the offset's loop
state from its primary ray, ``step`` advances it by one base-path vertex and returns the offset's contributions for that
vertex's two events together with the MIS weights of the pixel pair, ``scale``/``kill`` apply the base path's
Russian roulette. The integrator never looks inside an offset state: :class:`ReplayShift` and
:class:`renderer.hybrid.HybridShift` (reconnection at rough vertices, moving onto curved specular ones,
half-vector copy at glossy ones, replay elsewhere) are interchangeable.

Random replay
-------------
The offset path of pixel ``p + delta`` consumes exactly the base path's random numbers: it *is* the path that the
base path of pixel ``p + delta`` would trace from those numbers. Seen in primary sample space (the unit hypercube
of random numbers ``u``), the shift is the identity, so its Jacobian is 1 and both techniques that can estimate a
pixel pair -- base at ``p`` shifted by ``+delta``, and base at ``p + delta`` shifted by ``-delta`` -- sample the
pair's ``u`` with the same density 1. (Path-space densities differ, ``p(x) = 1/|dx/du|`` and
``p(x') = 1/|dx'/du|``, but the path-space Jacobian ``|dx'/dx| = |dx'/du| / |dx/du|`` makes ``p(x') |dx'/dx| =
p(x)``: the same statement.) Russian roulette multiplies each technique's density by its own base path's
continuation probabilities and divides its contributions by them, so it cancels in expectation and needs no
place in the weights. The balance heuristic therefore gives each technique weight 1/2 for every event both can
produce. An event that only this technique produces -- the offset path has already ended (left the scene, hit a
zero BSDF, reached no surface for next-event estimation), so the neighbour's base path has no such event -- gets
weight 1, and the offset contributes 0 to it. The two weights of every pair sum to 1, which is all unbiasedness
needs; offset paths are traced with the very function the base path uses, so "the path has this event" is the
same predicate in both techniques.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from gradsep.renderer.hybrid import HybridShift
from gradsep.renderer.shift_protocol import OffsetEvents, Shift
from gradsep.renderer.vertex import PathState, Vertex, VertexSamples, trace_vertex

SHIFT_NAMES: tuple[str, ...] = ("replay", "hybrid")


class ReplayShift:
    """Random replay: the offset path re-runs the path tracer with the base path's random numbers."""

    name = "replay"
    reuses_light_samples = False

    def ray_flags(self, scene: mi.Scene) -> mi.RayFlags:
        return mi.RayFlags.All

    def start(self, ray: mi.Ray3f, weight: mi.Spectrum, active: mi.Bool) -> PathState:
        return PathState.start(ray, weight, active)

    def step(self, scene: mi.Scene, offset: PathState, base: Vertex, depth: mi.UInt32, max_depth: mi.UInt32,
             samples: VertexSamples, later: bool = False) -> tuple[PathState, OffsetEvents]:
        offset, v = trace_vertex(scene, offset, depth, max_depth, samples)
        events = OffsetEvents(
            emitted=v.emitted,
            nee=v.nee,
            w_hit=dr.select(v.has_hit, 0.5, 1.0),
            w_nee=dr.select(v.has_nee, 0.5, 1.0),
        )
        return offset, events

    def scale(self, offset: PathState, factor: mi.Float, active: mi.Bool) -> PathState:
        offset.throughput = dr.select(active, offset.throughput * factor, offset.throughput)
        return offset

    def kill(self, offset: PathState, dead: mi.Bool) -> PathState:
        offset.active = offset.active & ~dead
        return offset


DEFAULT_SHIFT = "hybrid"


def make_shift(name: str | None) -> Shift:
    """The shift called ``name`` (None = the default). Raises ValueError for a shift that is not available."""
    name = name or DEFAULT_SHIFT
    if name == "replay":
        return ReplayShift()
    if name == "hybrid":
        return HybridShift()
    raise ValueError(f"unknown shift {name!r}; expected one of {SHIFT_NAMES}")
