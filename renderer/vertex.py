"""One path vertex, traced exactly as Mitsuba's ``path`` integrator does (minus Russian roulette): the path's
loop state, the random numbers one vertex consumes, and the vertex's two events (emission found by the ray,
next-event estimation). The G-PT integrator (renderer/gpt_loop.py) traces its base path with it, and the random
replay shift (renderer/shift.py) its offset paths.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class PathState:
    """Loop state of one path (Dr.Jit traverses dataclasses, so this can be a loop variable)."""

    ray: mi.Ray3f
    throughput: mi.Spectrum  # product of BSDF sample weights (and 1/q of Russian roulette)
    active: mi.Bool  # the path has a ray to trace in this iteration
    eta: mi.Float  # relative IOR along the path, for Mitsuba's Russian roulette rule
    prev: mi.Interaction3f  # previous vertex, for the MIS weight of emission hit by a BSDF sample
    prev_pdf: mi.Float  # solid-angle pdf of the BSDF sample that produced ``ray``
    prev_delta: mi.Bool  # that sample came from a delta lobe (no next-event estimation could have found it)

    @staticmethod
    def start(ray: mi.Ray3f, weight: mi.Spectrum, active: mi.Bool) -> PathState:
        """A path at the camera: ``prev_delta`` makes emission at the first vertex count with MIS weight 1."""
        return PathState(ray=mi.Ray3f(ray), throughput=mi.Spectrum(weight), active=mi.Bool(active),
                         eta=mi.Float(1.0), prev=dr.zeros(mi.Interaction3f), prev_pdf=mi.Float(1.0),
                         prev_delta=mi.Bool(True))


@dataclass
class VertexSamples:
    """The random numbers one path vertex consumes; random replay hands the base path's to every offset."""

    light: mi.Point2f  # emitter sample for next-event estimation
    lobe: mi.Float  # BSDF lobe selection
    direction: mi.Point2f  # BSDF direction sample

    @staticmethod
    def draw(sampler: mi.Sampler) -> VertexSamples:
        """Draw unconditionally in every lane, so lanes of one pixel sample stay on one random stream."""
        return VertexSamples(light=sampler.next_2d(), lobe=sampler.next_1d(), direction=sampler.next_2d())


@dataclass
class Vertex:
    """What one path did at one vertex: its two contributions ("events") and the data later code needs."""

    emitted: mi.Spectrum  # throughput * MIS * emission found by the ray (emitter hit or environment)
    emitted_weight: mi.Spectrum  # the same without the throughput: MIS * emission
    emission: mi.Spectrum  # the emission alone, and the emitter-sampling pdf it is MIS-weighted against
    emitter_pdf: mi.Float
    has_hit: mi.Bool  # the emission event exists: the path traced a ray in this iteration
    nee: mi.Spectrum  # throughput * MIS * next-event estimate at this vertex
    nee_weight: mi.Spectrum  # the same without the throughput
    has_nee: mi.Bool  # the next-event event exists: a surface vertex below the depth limit
    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    bsdf_flags: mi.UInt32  # of ``bsdf`` (0 where the ray left the scene)
    sample: mi.BSDFSample3f  # the BSDF sample that continues the path
    sample_weight: mi.Spectrum  # BSDF weight (value * cos / pdf) of that sample
    light: mi.DirectionSample3f  # the emitter sample of next-event estimation (valid where nee_sampled)
    light_weight: mi.Spectrum  # emitted radiance / light pdf, 0 where occluded
    light_visible: mi.Bool  # the emitter point is visible from this vertex
    nee_sampled: mi.Bool  # an emitter sample was drawn and has a nonzero (unoccluded) pdf
    light_infinite: mi.Bool  # that emitter is infinitely distant (only computed with ``strict_light_pdf``)


def mis_power(pdf_a: mi.Float, pdf_b: mi.Float) -> mi.Float:
    """Power-heuristic weight of technique a (Mitsuba's ``path`` uses the same), 0 where undefined."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0.0)


def trace_vertex(scene: mi.Scene, path: PathState, depth: mi.UInt32, max_depth: mi.UInt32,
                 samples: VertexSamples, strict_light_pdf: bool = False,
                 ray_flags: mi.RayFlags = mi.RayFlags.All) -> tuple[PathState, Vertex]:
    """Advance one path by one vertex exactly as Mitsuba's ``path`` integrator does, minus Russian roulette.

    Returns the updated path (ray towards the next vertex, throughput, liveness) and the vertex's events. Whether
    a path continues is decided only by its own geometry and the depth limit; Russian roulette is the caller's,
    because G-PT decides it on the base path for the whole lane.

    ``strict_light_pdf`` makes ``nee_sampled`` mean "emitter sampling has a nonzero density for this point as
    ``pdf_emitter_direction`` reports it": behind a one-sided emitter Mitsuba's sampling still returns a point
    with a nonzero pdf (and zero weight). A shift that reuses the light sample on another path needs the event
    to exist by one definition on both paths.
    """
    ctx = mi.BSDFContext()
    si = scene.ray_intersect(path.ray, ray_flags=ray_flags, coherent=depth == 0, active=path.active)
    emitted_weight, emission, em_pdf = _emission_found(scene, path, si)
    emitted = path.throughput * emitted_weight

    # Next-event estimation at this vertex.
    has_nee = path.active & si.is_valid() & (depth + 1 < max_depth)
    bsdf = si.bsdf(path.ray)
    bsdf_flags = dr.select(si.is_valid(), bsdf.flags(), 0)
    light = _light_sample(scene, si, has_nee & mi.has_flag(bsdf_flags, mi.BSDFFlags.Smooth), samples.light,
                          strict_light_pdf)
    # One BSDF call evaluates the emitter direction and samples the continuation (as Mitsuba's `path` does):
    # each BSDF call site in the kernel costs a dispatch over the BSDF instances.
    bsdf_val, bsdf_pdf, bs, bs_weight = bsdf.eval_pdf_sample(ctx, si, si.to_local(light.ds.d), samples.lobe,
                                                             samples.direction, has_nee)
    mis_em = dr.select(light.ds.delta, 1.0, mis_power(light.ds.pdf, bsdf_pdf))
    nee_weight = dr.select(light.sampled, mis_em * bsdf_val * light.weight, 0.0)
    nee = path.throughput * nee_weight

    # BSDF sampling continues the path.
    bs_weight = dr.select(has_nee, bs_weight, 0.0)
    prev = dr.zeros(mi.Interaction3f)
    prev.t, prev.time, prev.p, prev.n = si.t, si.time, si.p, si.n
    throughput = path.throughput * bs_weight
    nxt = PathState(
        ray=si.spawn_ray(si.to_world(bs.wo)),
        throughput=throughput,
        active=has_nee & (dr.max(throughput) != 0.0),
        eta=path.eta * bs.eta,
        prev=prev,
        prev_pdf=bs.pdf,
        prev_delta=mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta),
    )
    vertex = Vertex(emitted=emitted, emitted_weight=emitted_weight, emission=emission, emitter_pdf=em_pdf,
                    has_hit=mi.Bool(path.active), nee=nee,
                    nee_weight=nee_weight, has_nee=has_nee, si=si, bsdf=bsdf, bsdf_flags=bsdf_flags, sample=bs,
                    sample_weight=bs_weight, light=light.ds, light_weight=light.weight,
                    light_visible=light.visible, nee_sampled=light.sampled, light_infinite=light.infinite)
    return nxt, vertex


def _emission_found(scene: mi.Scene, path: PathState,
                    si: mi.SurfaceInteraction3f) -> tuple[mi.Spectrum, mi.Spectrum, mi.Float]:
    """Emission found by the ray (area emitter or environment), MIS-weighted against next-event estimation from
    the previous vertex: (MIS * emission, emission, emitter pdf). At the camera ``prev_delta`` is set, so the
    emitter pdf is 0 and the weight is 1."""
    ds = mi.DirectionSample3f(scene, si=si, ref=path.prev)
    em_pdf = scene.pdf_emitter_direction(path.prev, ds, path.active & ~path.prev_delta)
    emission = dr.select(path.active, ds.emitter.eval(si, path.active), 0.0)
    return mis_power(path.prev_pdf, em_pdf) * emission, emission, em_pdf


@dataclass
class LightSample:
    """The emitter sample of one vertex's next-event estimation."""

    ds: mi.DirectionSample3f  # the sampled emitter point; ``ds.pdf`` its unoccluded density
    weight: mi.Spectrum  # emitted radiance / light pdf, 0 where occluded
    sampled: mi.Bool  # drawn, with a nonzero (and, strictly, reported) density
    infinite: mi.Bool  # the emitter is infinitely distant (only computed strictly)
    visible: mi.Bool  # the emitter point is visible from the vertex


def _light_sample(scene: mi.Scene, si: mi.SurfaceInteraction3f, active: mi.Bool, u: mi.Point2f,
                  strict_light_pdf: bool) -> LightSample:
    """Sample an emitter for next-event estimation where ``active`` (see :func:`trace_vertex` for ``strict``)."""
    # Visibility is tested separately so that ``ds.pdf`` stays the unoccluded density: a shift may reuse this
    # light sample from another vertex, which can see the emitter point even where this vertex cannot.
    ds, weight = scene.sample_emitter_direction(si, u, False, active)
    active &= (ds.pdf > 0.0) & dr.isfinite(ds.pdf)  # a vertex in the emitter's plane has no sample
    infinite = mi.Bool(False)
    if strict_light_pdf:
        density = scene.pdf_emitter_direction(si, ds, active & ~ds.delta)
        active &= ds.delta | (density > 0.0)
        infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
    visible = ~scene.ray_test(si.spawn_ray_to(ds.p), active)
    return LightSample(ds=ds, weight=dr.select(visible, weight, 0.0), sampled=active, infinite=infinite,
                       visible=visible)
