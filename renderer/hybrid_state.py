"""The hybrid shift's state (renderer/hybrid.py): an offset path's loop state between two iterations, its
summary once connected, and what one step computes on the way (strategy, transition, own vertex, arrival).
"""

from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi

NOT_CONNECTED, RECENTLY_CONNECTED, CONNECTED, PENDING = 0, 1, 2, 3  # PENDING: waiting to connect past a mirror


@dataclass
class HybridState:
    """Loop state of one hybrid offset path ȳ, between two iterations.

    In Kettunen et al.'s names: the offset sits at its vertex ``y_k`` (``vertex``, with the offset's own incoming
    direction; for a recently connected offset, the base path's vertex seen from the offset's previous vertex),
    and the base path has just left ``x_k``; the ``base_*`` fields stash what the transition into the next vertex
    needs from the base path's step out of ``x_k``. The ``mirror_*`` fields are set while the offset waits for a
    manifold reconnection through the base path's mirror vertex ``x_{k+1}``.
    """

    active: mi.Bool
    status: mi.UInt32  # NOT_CONNECTED, RECENTLY_CONNECTED, CONNECTED or PENDING (waiting at a mirror)
    throughput: mi.Spectrum  # f(offset prefix) * Jacobians / p(base prefix), with the base's roulette
    ratio: mi.Float  # p(offset prefix as a base path) * Jacobians / p(base prefix); roulette excluded
    ray: mi.Ray3f  # primary ray (first iteration only)
    vertex: mi.SurfaceInteraction3f  # y_k
    vertex_bsdf: mi.BSDFPtr  # the BSDF at y_k, and its flags
    vertex_flags: mi.UInt32
    replay_lobe: mi.Float  # the base path's random numbers at x_k, for a replay at y_k
    replay_direction: mi.Point2f
    base_point: mi.Point3f  # x_k
    base_flags: mi.UInt32  # BSDF flags at x_k
    base_bsdf_id: mi.UInt32  # the registry id of the BSDF at x_k (same id: same material, same IOR)
    base_wi: mi.Vector3f  # the base path's incoming and outgoing directions at x_k, in its local shading frame
    base_wo: mi.Vector3f
    base_out_dir: mi.Vector3f  # the outgoing direction in world space
    base_out_pdf: mi.Float  # its solid-angle pdf
    base_out_weight: mi.Spectrum  # its BSDF weight (value * cos / pdf)
    base_out_delta: mi.Bool  # it came from a delta lobe
    base_out_eta: mi.Float  # its relative index of refraction (1 for reflections)
    mirror_si: mi.SurfaceInteraction3f  # PENDING: the base path's mirror vertex x_{k+1}
    mirror_origin: mi.Point3f  # PENDING: the base path's vertex x_k before the mirror
    mirror_origin_pdf: mi.Float  # PENDING: the pdf of the base path's direction from x_k to the mirror


@dataclass
class ConnectedState:
    """A connected hybrid offset, summarised: its events are the base path's times its throughput."""

    active: mi.Bool
    throughput: mi.Spectrum
    ratio: mi.Float  # fixed once connected: the shared vertices have the same density in both paths
    next_weight: mi.Spectrum  # BSDF weight of the direction leaving the previous (shared) vertex: the base
    #                           path's, or, just after the reconnection, the offset's own for its incoming direction
    next_ratio: mi.Float  # density ratio of that direction: 1 (shared), or the offset's pdf / the base path's
    own_next_pdf: mi.Float  # just after the reconnection: the offset's pdf of that direction, for its emission MIS
    just_connected: mi.Bool  # just reconnected: the next vertex's emission is weighted with ``own_next_pdf``


@dataclass
class Strategy:
    """How each offset leaves its vertex ``y_k`` in this iteration (per-lane masks; see :class:`HybridShift`),
    and the vertex classes they were decided from."""

    first: mi.Bool  # the offset's primary ray (depth 0)
    recent: mi.Bool  # reconnected last iteration: its BSDF at the shared vertex for the base path's direction
    connected: mi.Bool  # shares every vertex: the base path's BSDF weight
    pending: mi.Bool  # waited at a mirror last iteration: manifold reconnection now
    reconnect: mi.Bool  # to the base path's next vertex x_{k+1} (or its direction, at infinity)
    follow: mi.Bool  # onto a curved specular x_{k+1}, staying on its own from there
    wait: mi.Bool  # at y_k, for a manifold reconnection through the mirror x_{k+1} next iteration
    copy: mi.Bool  # half-vector copy at y_k
    replay: mi.Bool  # the base path's random numbers at y_k
    base_rough: mi.Bool  # x_k has a non-delta lobe
    off_rough: mi.Bool  # y_k has one
    glossy_pair: mi.Bool  # both are glossy (:func:`is_glossy`)

    @property
    def to_vertex(self) -> mi.Bool:
        """The offset moves onto the base path's vertex x_{k+1}."""
        return self.reconnect | self.follow


@dataclass
class Transition:
    """The offset's step from ``y_k`` into its next vertex: direction evaluated at ``y_k`` by a reconnection,
    follow, half-vector copy or manifold reconnection, the step's throughput factor and density ratio, and
    where the shift fails."""

    evaluated: mi.Bool  # the BSDF at y_k was evaluated for a direction not sampled by the offset
    pdf: mi.Float  # the offset's pdf of that direction
    step_f: mi.Spectrum  # throughput factor (BSDF value * Jacobian / base pdf)
    step_r: mi.Float  # density-ratio factor
    fail: mi.Bool
    reconnection_dir: mi.Vector3f  # y_k -> x_{k+1} (world)
    copy_dir: mi.Vector3f  # the half-vector copy's direction (world), where ``copy``
    mirror: mi.Bool  # the manifold reconnection through the mirror succeeded
    mirror_wi: mi.Vector3f  # after it: the offset's incoming direction at x_{k+2} (local)


@dataclass
class OwnVertex:
    """The vertex an offset finds by tracing its own ray (primary ray, replay, half-vector copy)."""

    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    flags: mi.UInt32
    sample: mi.BSDFSample3f  # the replayed BSDF sample at y_k
    weight: mi.Spectrum  # its BSDF weight


@dataclass
class Arrival:
    """Where an offset is after this iteration's transition, and how it arrived (for its emitter/BSDF MIS)."""

    active: mi.Bool
    throughput: mi.Spectrum
    ratio: mi.Float
    status: mi.UInt32
    si: mi.SurfaceInteraction3f  # its vertex (its own, the base path's with its own wi, or y_k while waiting)
    bsdf: mi.BSDFPtr
    flags: mi.UInt32
    prev: mi.Interaction3f  # y_k
    prev_pdf: mi.Float  # pdf of the direction that led here, and whether it was a delta lobe
    prev_delta: mi.Bool
    shared: mi.Bool  # this vertex is the base path's
    reuse: mi.Bool  # connected before this vertex: emission and next-event estimate are the base path's
    evaluate: mi.Bool  # its own events must be evaluated here


