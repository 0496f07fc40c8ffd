"""The gradient-domain path tracer (G-PT, Kettunen et al. 2015) on Mitsuba 3 / Dr.Jit, with the direct/indirect
illumination separation of Ma et al. 2024.

One wavefront lane is one pixel sample. Each lane carries five paths through one symbolic Dr.Jit loop (one
compiled kernel, one iteration per path vertex): the *base* path of its pixel and four *offset* paths whose
primary rays go through the same sub-pixel position of the pixels to the right, left, below and above. How an
offset path follows its base path is the *shift mapping*, kept out of this file (``renderer/shift.py``): every
iteration the base path advances one vertex here, the shift advances each offset path given that vertex, and this
file turns the two sets of contributions into the primal image and the gradients.

Estimators (see docs/renderer.md for the derivation):

* **Primal**: the base paths alone, i.e. an ordinary path tracer (next-event estimation + BSDF sampling combined
  with the power heuristic, Russian roulette from vertex ``rr_depth`` on as in Mitsuba). It is unbiased and its noise is
  independent from pixel to pixel, which the unsupervised denoiser relies on; the MIS combination of all five
  paths would lower the primal's variance but correlate neighbouring pixels. Sub-pixel positions are stratified
  within each pixel (a jittered grid over the pass's samples), which keeps pixels independent.
* **Gradients**: each contribution ("event": emission found at vertex d, next-event estimation at vertex d) of a
  base path at pixel p gives ``w * (f_offset - f_base)``, an estimate of ``I(p + delta) - I(p)``. The same pixel
  pair is also estimated from the base path at ``p + delta`` with the opposite shift; ``w`` is the MIS weight of
  the pair between these two techniques and is supplied by the shift (1/2 for random replay when both paths
  exist, 1 when only this technique can produce the pair). ``dx(p)`` therefore sums the ``+x`` estimate of the
  samples of pixel p and the negated ``-x`` estimate of the samples of pixel p+1: both directions, no double
  counting.
* **Russian roulette** is decided on the base path and applied to the whole lane (the offsets are divided by the
  base path's continuation probability too), so it cancels in the MIS weights.
* **Separation**: events at the first camera-visible vertex (emission seen directly; next-event estimation from
  that vertex; emission found by the BSDF sample leaving it) go to ``direct``, all later events to ``indirect``.
  Offsets have the same length as their base path, so each gradient term lands in its base term's layer and
  ``direct + indirect`` is exactly the unseparated estimate.
* **Features** (base path only): at the first vertex that is not specular (delta lobes, and glossy samples with a
  pdf above :data:`NEAR_SPECULAR_PDF`, are followed): albedo, camera-space normal, distance along the chain.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import drjit as dr
import mitsuba as mi
import numpy as np

from gradsep.model.frame import VARIANCE_MAX
from gradsep.model.policy import LUMINANCE

# A sample's squared luminance is capped at the contract's VARIANCE_MAX (and so is the variance it feeds): a 1e20
# firefly squared would overflow float32 to Inf; capped, its pixel still reads as "very noisy", which is what the
# variance is for.
SQUARE_CAP = VARIANCE_MAX

# Pixel offsets of the four offset paths, (dx, dy) with y growing downward: right, left, down, up.
SHIFT_OFFSETS: tuple[tuple[int, int], ...] = ((1, 0), (-1, 0), (0, 1), (0, -1))

# Which offsets a sample traces: "all" four of SHIFT_OFFSETS; "pair": the two of one axis, right and left
# (SHIFT_OFFSETS[0:2]) or down and up ([2:4]); "single": one of the four. The group is chosen per sample
# (offset_group) and its gradient terms count OFFSET_GROUPS[mode] times (the group's inverse probability).
# "alternate": one offset per axis, right or left and down or up, chosen so that neighbouring pixels pair up
# (alternate_offsets): on a given sample pixel x traces right exactly when pixel x+1 traces left, so each pixel
# pair gets both of its MIS techniques on half the samples; every offset is traced with probability 1/2.
OFFSET_MODES: tuple[str, ...] = ("all", "pair", "single", "alternate")
OFFSET_GROUPS: dict[str, int] = {"all": 1, "pair": 2, "single": 4, "alternate": 2}

# Which layers get gradients when offsets are traced: "all" of them, or the "direct" layer alone. With "direct" the
# offsets are traced only as far as the direct layer's events reach (emission seen at vertex 0, next-event
# estimation there, emission found by the BSDF sample leaving it: vertices 0 and 1) and the base path continues
# alone, so the indirect layer is a plain primal. The primal-only mode (no offsets at all) is ``shift=None``.
GRADIENT_MODES: tuple[str, ...] = ("all", "direct")
# Vertices whose events belong to the direct layer (emission at depth <= 1, NEE at depth 0): _route's rule.
DIRECT_VERTICES = 2

# A glossy lobe whose sampled direction has a solid-angle pdf above this is treated as a mirror when looking for
# the feature vertex: a GGX lobe reaches ~100 sr^-1 near alpha 0.05, where reflections are still sharp images.
NEAR_SPECULAR_PDF = 100.0

# Lanes per pass. A lane's state lives in the kernel's registers, not in memory, so a pass needs only its
# per-pixel sums; every further pass pays the loop's recording, a launch and the float64 read-back and sum
# again (~0.5 s per pass for a 1280x720 G-PT frame). 2^26 renders a 1280x720 frame in one pass up to 72 spp;
# against 2^22 its wall time falls 14-25 % with a lower peak RSS (docs/decisions.md, "Lanes per pass"). The lane
# index is a UInt32: render_pass refuses 2^32 lanes.
MAX_LANES_PER_PASS = 1 << 26

# The --gradients direct mode runs the shift's ``for_direct_layer()`` (where it has one: the hybrid shift without
# its manifold solve, which cannot change a direct-layer event); False keeps the full shift (to compare, and tests).
DIRECT_LAYER_SHIFT = True

# Trace the first vertex before the symbolic loop, where its depth is a literal 0 (see _run_loops; not in the
# primal-only mode).
PEEL_FIRST_VERTEX = True

# Mitsuba's convention for an unbounded path length.
UNBOUNDED = 0xFFFFFFFF


# ---------------------------------------------------------------------------------------------------------------
# Path state and one path vertex: shared by the base path and by shifts that trace offsets the same way
# ---------------------------------------------------------------------------------------------------------------


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

    # Emission found by the ray (area emitter or environment), MIS-weighted against next-event estimation from
    # the previous vertex. At the camera prev_delta is set, so the emitter pdf is 0 and the weight is 1.
    ds = mi.DirectionSample3f(scene, si=si, ref=path.prev)
    em_pdf = scene.pdf_emitter_direction(path.prev, ds, path.active & ~path.prev_delta)
    emission = dr.select(path.active, ds.emitter.eval(si, path.active), 0.0)
    emitted_weight = mis_power(path.prev_pdf, em_pdf) * emission
    emitted = path.throughput * emitted_weight

    # Next-event estimation at this vertex.
    has_nee = path.active & si.is_valid() & (depth + 1 < max_depth)
    bsdf = si.bsdf(path.ray)
    bsdf_flags = dr.select(si.is_valid(), bsdf.flags(), 0)
    active_em = has_nee & mi.has_flag(bsdf_flags, mi.BSDFFlags.Smooth)
    # Visibility is tested separately so that ``ds_em.pdf`` stays the unoccluded density: a shift may reuse this
    # light sample from another vertex, which can see the emitter point even where this vertex cannot.
    ds_em, em_weight = scene.sample_emitter_direction(si, samples.light, False, active_em)
    active_em &= (ds_em.pdf > 0.0) & dr.isfinite(ds_em.pdf)  # a vertex in the emitter's plane has no sample
    light_infinite = mi.Bool(False)
    if strict_light_pdf:
        density = scene.pdf_emitter_direction(si, ds_em, active_em & ~ds_em.delta)
        active_em &= ds_em.delta | (density > 0.0)
        light_infinite = mi.has_flag(ds_em.emitter.flags(), mi.EmitterFlags.Infinite)
    light_visible = ~scene.ray_test(si.spawn_ray_to(ds_em.p), active_em)
    em_weight = dr.select(light_visible, em_weight, 0.0)
    # One BSDF call evaluates the emitter direction and samples the continuation (as Mitsuba's `path` does):
    # each BSDF call site in the kernel costs a dispatch over the BSDF instances.
    bsdf_val, bsdf_pdf, bs, bs_weight = bsdf.eval_pdf_sample(ctx, si, si.to_local(ds_em.d), samples.lobe,
                                                             samples.direction, has_nee)
    mis_em = dr.select(ds_em.delta, 1.0, mis_power(ds_em.pdf, bsdf_pdf))
    nee_weight = dr.select(active_em, mis_em * bsdf_val * em_weight, 0.0)
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
                    sample_weight=bs_weight, light=ds_em, light_weight=em_weight, light_visible=light_visible,
                    nee_sampled=active_em, light_infinite=light_infinite)
    return nxt, vertex


# ---------------------------------------------------------------------------------------------------------------
# The shift interface (implementations in renderer/shift.py)
# ---------------------------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------------------------
# Settings, per-lane accumulators, output
# ---------------------------------------------------------------------------------------------------------------


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


@dataclass
class LayerSums:
    """Per-lane sums of one illumination layer: base radiance and one gradient estimate per shift."""

    base: mi.Spectrum
    grads: list[mi.Spectrum]

    @staticmethod
    def zeros(n_offsets: int = len(SHIFT_OFFSETS)) -> LayerSums:
        """Zero sums, one gradient estimate per traced offset (none: the layer carries the base radiance only)."""
        return LayerSums(base=mi.Spectrum(0.0), grads=[mi.Spectrum(0.0) for _ in range(n_offsets)])


@dataclass
class FeatureState:
    """The feature vertex search along the base path (loop state)."""

    pending: mi.Bool  # still following a specular chain
    albedo: mi.Color3f
    normal: mi.Vector3f  # camera space, facing the viewer
    distance: mi.Float  # along the chain so far / to the feature vertex
    hit: mi.Float  # 1 when the chain ended on a surface, 0 on a miss

    @staticmethod
    def start() -> FeatureState:
        return FeatureState(pending=mi.Bool(True), albedo=mi.Color3f(0.0), normal=mi.Vector3f(0.0, 0.0, 1.0),
                            distance=mi.Float(0.0), hit=mi.Float(0.0))


# Output channel groups of one pass (each 3 wide except depth / hit / invalid), per-pixel sums over samples.
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


# ---------------------------------------------------------------------------------------------------------------
# The algorithm
# ---------------------------------------------------------------------------------------------------------------


def stratified_sub_pixel(u: mi.Point2f, sample: mi.UInt32, strata: mi.UInt32) -> mi.Point2f:
    """Jitter the pixel's first ``strata^2`` samples over a ``strata x strata`` grid (sample ``i`` in cell
    ``(i mod strata, i div strata)``); later samples stay uniform. Each sample is uniform within its cell, so the
    pixel's mean is unbiased; coverage of edges (silhouettes, light boundaries) is estimated with far less noise
    than by independent positions, for the primal and -- since base and offset rays share the position -- for the
    gradients. Pixels stay independent of each other (the jitter is the pixel's own random numbers)."""
    cells = strata * strata
    cell = mi.Point2f(mi.Float(sample % strata), mi.Float(sample // strata))
    return dr.select(sample < cells, (cell + u) / mi.Float(strata), u)


def offset_group(pixel: mi.UInt32, sample: mi.UInt32, strata: mi.UInt32, seed: mi.UInt32,
                 groups: int) -> mi.UInt32:
    """Which group of offsets (of ``groups`` equal groups of SHIFT_OFFSETS: 2 axes, or 4 single offsets) sample
    ``sample`` of ``pixel`` traces when a sample traces fewer than all four.

    The pixel's stratified samples (one per cell of its ``strata x strata`` grid) are dealt out along the grid's
    diagonals -- cell (cx, cy) gets ``cx + (groups // 2) cy`` (a checkerboard for two groups) -- later samples in
    turn, and a random offset per pixel and pass (a hash of the pixel and the pass's seed) rotates the groups.
    So every sample traces each group with probability exactly ``1/groups``, whatever its sub-pixel position --
    counting its gradient terms ``groups`` times keeps every gradient estimate unbiased -- and each group's
    samples still spread over the pixel (every row of the grid holds every group)."""
    rotate = mi.sample_tea_32(pixel, seed)[0]
    cell = sample % strata + (groups // 2) * (sample // strata)
    return (dr.select(sample < strata * strata, cell, sample) + rotate) % groups


def alternate_offsets(px: mi.Int32, py: mi.Int32, sample: mi.UInt32, strata: mi.UInt32,
                      seed: mi.UInt32) -> tuple[mi.UInt32, mi.UInt32]:
    """Which offset of each axis sample ``sample`` of pixel (px, py) traces in the "alternate" mode: indices into
    SHIFT_OFFSETS, right (0) or left (1), and down (2) or up (3).

    Pixel x traces right where ``x + c + r`` is even and left where it is odd, with ``c`` the sample's place in
    the pixel's stratified grid (cell (cx, cy) -> cx + cy, a checkerboard, so each direction's samples cover
    every row and column of the grid; later samples: the sample index) and ``r`` a random bit per image row and
    pass (a hash of the row and the pass's seed). So on every sample pixel x traces right exactly when pixel x+1
    traces left -- the pair (x, x+1) gets both of its MIS techniques on the same half of the samples, and the
    weights of the two techniques still sum to 1 -- and, over ``r``, each sample traces each direction with
    probability exactly 1/2 whatever its sub-pixel position: counted twice (OFFSET_GROUPS), every gradient
    estimate stays unbiased. Vertically likewise, with a bit per column."""
    diagonal = dr.select(sample < strata * strata, sample % strata + sample // strata, sample)
    row_bits = mi.sample_tea_32(mi.UInt32(py), seed)[0]
    column_bits = mi.sample_tea_32(mi.UInt32(px), seed)[1]
    horizontal = (mi.UInt32(px) + diagonal + row_bits) & 1
    vertical = (mi.UInt32(py) + diagonal + column_bits) & 1
    return horizontal, vertical + 2


def _offsets_by_index(targets: Sequence[mi.UInt32]) -> list[tuple[mi.Int32, mi.Int32]]:
    """Per-lane pixel shifts (dx, dy) of the offsets ``targets`` (indices into SHIFT_OFFSETS)."""
    shifts = []
    for target in targets:
        ox, oy = mi.Int32(SHIFT_OFFSETS[0][0]), mi.Int32(SHIFT_OFFSETS[0][1])
        for i, (cx, cy) in enumerate(SHIFT_OFFSETS[1:], start=1):
            ox = dr.select(target == i, cx, ox)
            oy = dr.select(target == i, cy, oy)
        shifts.append((ox, oy))
    return shifts


def _camera_rays(sensor: mi.Sensor, sampler: mi.Sampler, px: mi.Int32, py: mi.Int32, size: mi.Vector2f,
                 res: tuple[mi.Int32, mi.Int32], sample: mi.UInt32, strata: mi.UInt32,
                 shifts: Sequence[tuple[int | mi.Int32, int | mi.Int32]] = SHIFT_OFFSETS,
                 ) -> tuple[list[tuple[mi.Ray3f, mi.Spectrum, mi.Bool]], mi.Bool]:
    """Primary rays of the base pixel and of the shifted pixels (``shifts``; none for a primal-only render), all
    through the same sub-pixel sample (``sample``-th of the pixel, stratified: :func:`stratified_sub_pixel`).

    The shifted pixel index is formed in integers first, so an offset ray and the base ray of the neighbouring
    pixel it stands for are computed bit for bit alike.
    """
    sub_pixel = stratified_sub_pixel(sampler.next_2d(), sample, strata)
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    time = sensor.shutter_open()
    if sensor.shutter_open_time() > 0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    width, height = res
    rays = []
    for ox, oy in ((0, 0), *shifts):
        qx, qy = px + ox, py + oy
        inside = (qx >= 0) & (qx < width) & (qy >= 0) & (qy < height)
        pos = (mi.Point2f(mi.Float(qx), mi.Float(qy)) + sub_pixel) / size
        ray, weight = sensor.sample_ray(time, 0.5, pos, aperture, inside)
        rays.append((ray, mi.Spectrum(weight), inside))
    return rays, rays[0][2]


def _camera_normal(to_camera: mi.Transform4f, si: mi.SurfaceInteraction3f, ray_d: mi.Vector3f) -> mi.Vector3f:
    """Shading normal turned towards the incoming ray, in camera space with x right, y up, z towards the viewer.

    Mitsuba's camera frame looks along +z with +x to the left; flipping x and z gives the usual right-handed
    view space in which surfaces facing the camera have z > 0.
    """
    n = si.sh_frame.n
    n = dr.select(dr.dot(n, ray_d) > 0, -n, n)
    local = to_camera @ n
    return dr.normalize(mi.Vector3f(-local.x, local.y, -local.z))


def _update_features(feat: FeatureState, base_active: mi.Bool, v: Vertex, ray_d: mi.Vector3f,
                     to_camera: mi.Transform4f) -> FeatureState:
    """Record features at this base vertex if the specular-chain search is still on; continue past mirrors."""
    rec = feat.pending & base_active
    valid = v.si.is_valid()
    flags = v.bsdf_flags
    has_diffuse = mi.has_flag(flags, mi.BSDFFlags.Diffuse)
    # Diffuse reflectance where the BSDF has a diffuse lobe; elsewhere the sampled weight, a one-sample estimate
    # of the directional albedo that averages to the right colour over the pixel's samples (metals, glass).
    diffuse = v.bsdf.eval_diffuse_reflectance(v.si, rec & valid & has_diffuse)
    albedo = dr.clip(dr.select(has_diffuse, diffuse, v.sample_weight), 0.0, 1.0)
    albedo = dr.select(dr.isfinite(albedo), albedo, 0.0)  # clip keeps NaN (a broken BSDF): 0, as the reader does
    sampled = v.sample.sampled_type
    specular = ~has_diffuse & (mi.has_flag(sampled, mi.BSDFFlags.Delta)
                               | (mi.has_flag(sampled, mi.BSDFFlags.Glossy) & (v.sample.pdf > NEAR_SPECULAR_PDF)))
    distance = feat.distance + dr.select(rec & valid, v.si.t, 0.0)
    normal = _camera_normal(to_camera, v.si, ray_d)
    stop = rec & (~valid | ~specular)
    return FeatureState(
        pending=feat.pending & ~stop,
        albedo=dr.select(rec, dr.select(valid, albedo, 0.0), feat.albedo),
        normal=dr.select(rec & valid, normal, dr.select(rec, mi.Vector3f(0.0, 0.0, 1.0), feat.normal)),
        distance=dr.select(rec & ~valid, 0.0, distance),
        hit=dr.select(rec, dr.select(valid, 1.0, 0.0), feat.hit),
    )


def _route(sums: dict[str, LayerSums], depth: mi.UInt32, settings: GptSettings, hit_value: mi.Spectrum,
           nee_value: mi.Spectrum, hit_grads: list[mi.Spectrum], nee_grads: list[mi.Spectrum]) -> None:
    """Add one vertex's events to their layer: emission at depth <= 1 and NEE at depth 0 are direct light; an
    unseparated render (``color``) takes every event. A layer's gradient sums take the offsets' terms when this
    vertex has any (``hit_grads`` empty: no offsets are traced any more; a layer without gradients has none)."""
    if "color" in sums:
        s = sums["color"]
        s.base = s.base + hit_value + nee_value
        for i in range(len(s.grads) if hit_grads else 0):
            s.grads[i] = s.grads[i] + hit_grads[i] + nee_grads[i]
        return
    hit_direct = depth <= 1
    nee_direct = depth == 0
    for layer, sel_hit, sel_nee in (("direct", hit_direct, nee_direct), ("indirect", ~hit_direct, ~nee_direct)):
        if layer not in sums:
            continue
        s = sums[layer]
        s.base = s.base + dr.select(sel_hit, hit_value, 0.0) + dr.select(sel_nee, nee_value, 0.0)
        for i in range(len(s.grads) if hit_grads else 0):
            s.grads[i] = s.grads[i] + dr.select(sel_hit, hit_grads[i], 0.0) + dr.select(sel_nee, nee_grads[i], 0.0)


def _finite(x: Any) -> tuple[Any, mi.Bool]:
    """Zero non-finite values (degenerate geometry); returns the cleaned value and a per-lane 'was bad' mask."""
    ok = dr.isfinite(x)
    bad = ~dr.all(ok) if dr.size_v(x) > 1 else ~ok
    return dr.select(ok, x, 0.0), bad


def scene_has_hittable_emitters(scene: mi.Scene) -> bool:
    """Whether a ray can find emission: an area light or an environment. Point, spot and directional lights
    (delta in position or direction) are reached only by next-event estimation, so in a scene lit by them alone
    the last ray of a path (traced only to look for emission) can be skipped, by `path` and G-PT alike."""
    delta = int(mi.EmitterFlags.DeltaPosition | mi.EmitterFlags.DeltaDirection)
    return any(not int(emitter.flags()) & delta for emitter in scene.emitters())


def _drop_non_finite(sums: dict[str, LayerSums]) -> tuple[dict[str, LayerSums], mi.Bool]:
    """Primal-only lanes: a sample whose sum is not finite (degenerate geometry) contributes 0 to every layer;
    returns the cleaned sums and the per-lane 'was bad' mask."""
    bad = mi.Bool(False)
    for s in sums.values():
        bad |= ~dr.all(dr.isfinite(s.base))
    for s in sums.values():
        s.base = dr.select(bad, 0.0, s.base)
    return sums, bad


@dataclass
class LoopState:
    """Loop state of one wavefront lane (one pixel sample), declared once for both G-PT loops (Dr.Jit traverses
    dataclasses: this is the tuple Mitsuba's ``prb.py`` spells out as its loop state). Kettunen et al.'s names:
    the base path x̄ of the lane's pixel and one offset path ȳ per pixel shift."""

    sampler: mi.Sampler
    depth: mi.UInt32  # index of the vertex this iteration finds (0: the camera ray's hit)
    base: PathState  # x̄
    offsets: list[Any]  # ȳ per entry of SHIFT_OFFSETS: the shift's state (first loop) or its summary (second)
    sums: dict[str, LayerSums]  # per layer: base radiance and one gradient estimate per shift
    feat: FeatureState  # the feature-vertex search along x̄
    invalid: mi.Bool  # some event of the lane was not finite (and was zeroed)


@dataclass
class PassKernel:
    """What the loop body of one pass reads and never changes: the scene, the shift and the opaque limits."""

    scene: mi.Scene
    shift: Shift | None  # None: primal only (no offsets)
    settings: GptSettings
    max_depth: mi.UInt32  # opaque: one compiled kernel serves every depth limit
    rr_depth: mi.UInt32
    to_camera: mi.Transform4f  # world -> camera, for the normal feature
    ray_flags: mi.RayFlags
    strict_light_pdf: bool
    hittable: bool  # some emitter can be found by a ray (scene_has_hittable_emitters)
    # per lane and traced offset, the index in SHIFT_OFFSETS whose gradient sums it feeds; None: all four, in order
    offset_targets: list[mi.UInt32] | None

    @property
    def gradients(self) -> bool:
        return self.shift is not None


# How an offset advances by one base vertex: the shift's full step, or the second loop's connected step.
OffsetStep = Callable[[Any, Vertex, Any, VertexSamples], tuple[Any, OffsetEvents]]  # (offset, vertex, depth, samples)


def _start_lanes(scene: mi.Scene, shift: Shift | None, settings: GptSettings, width: int, height: int, spp: int,
                 seed: int) -> tuple[PassKernel, LoopState, mi.UInt32]:
    """One lane per pixel sample: its sampler stream, primary rays (base and offsets) and zero sums. Sizes, seed
    and depth limits enter as opaque values. Returns the pass's constants, the initial state and each lane's
    pixel index."""
    sensor = scene.sensors()[0]
    lanes = width * height * spp
    w_o = dr.opaque(mi.Int32, width)
    h_o = dr.opaque(mi.Int32, height)
    spp_o = dr.opaque(mi.UInt32, spp)
    max_depth = settings.effective_max_depth()
    gradients = shift is not None
    kernel = PassKernel(
        scene=scene, shift=shift, settings=settings,
        max_depth=dr.opaque(mi.UInt32, UNBOUNDED if max_depth < 0 else max_depth),
        rr_depth=dr.opaque(mi.UInt32, settings.rr_depth), to_camera=sensor.world_transform().inverse(),
        ray_flags=shift.ray_flags(scene) if gradients else mi.RayFlags.All,
        strict_light_pdf=shift.reuses_light_samples if gradients else False,
        hittable=scene_has_hittable_emitters(scene), offset_targets=None)

    seed_o = dr.opaque(mi.UInt32, seed & 0xFFFFFFFF)
    sampler = mi.load_dict({"type": "independent", "sample_count": spp})
    sampler.seed(seed_o, lanes)
    idx = dr.arange(mi.UInt32, lanes)
    pixel = idx // spp_o
    py = mi.Int32(pixel // mi.UInt32(w_o))
    px = mi.Int32(pixel) - py * w_o
    size = mi.Vector2f(mi.Float(w_o), mi.Float(h_o))
    strata_o = dr.opaque(mi.UInt32, math.isqrt(spp))
    sample = idx % spp_o
    shifts: Sequence[tuple[int | mi.Int32, int | mi.Int32]] = SHIFT_OFFSETS if gradients else ()
    groups = OFFSET_GROUPS[settings.offsets]
    with_gradients = settings.gradient_layer_names() if gradients else ()
    if gradients and settings.offsets == "alternate":
        kernel.offset_targets = list(alternate_offsets(px, py, sample, strata_o, seed_o))
        shifts = _offsets_by_index(kernel.offset_targets)
    elif gradients and groups > 1:
        group = offset_group(pixel, sample, strata_o, seed_o, groups)
        per_group = len(SHIFT_OFFSETS) // groups
        # the k-th offset of the lane's group
        kernel.offset_targets = [group * per_group + k for k in range(per_group)]
        shifts = _offsets_by_index(kernel.offset_targets)
    rays, _ = _camera_rays(sensor, sampler, px, py, size, (w_o, h_o), sample, strata_o, shifts)
    state = LoopState(
        sampler=sampler, depth=mi.UInt32(0), base=PathState.start(*rays[0]),
        offsets=[shift.start(*r) for r in rays[1:]] if shift is not None else [],
        sums={name: LayerSums.zeros(len(shifts) if name in with_gradients else 0) for name in settings.layer_names()},
        feat=FeatureState.start(), invalid=mi.Bool(False))
    return kernel, state, pixel


def _offset_events(k: PassKernel, s: LoopState, v: Vertex, samples: VertexSamples,
                   step_offset: OffsetStep) -> tuple[list[mi.Spectrum], list[mi.Spectrum], mi.Bool]:
    """Advance every offset by the base vertex ``v`` (in place in ``s.offsets``); returns per offset the
    gradient terms ``w (f_offset - f_base)`` of the emission and next-event events, zeroed where not finite,
    and the lane's 'was not finite' mask."""
    hit_grads, nee_grads = [], []
    bad = mi.Bool(False)
    for i, off in enumerate(s.offsets):
        s.offsets[i], ev = step_offset(off, v, s.depth, samples)
        # An event the base path does not have belongs to the mirrored technique alone (weight 1 there).
        off_nee = dr.select(v.has_nee, ev.nee, 0.0)
        gh, bad_h = _finite(ev.w_hit * (ev.emitted - v.emitted))
        gn, bad_n = _finite(ev.w_nee * (off_nee - v.nee))
        bad |= bad_h | bad_n
        hit_grads.append(gh)
        nee_grads.append(gn)
    return hit_grads, nee_grads, bad


def _russian_roulette(k: PassKernel, s: LoopState) -> None:
    """Russian roulette on the base path (Mitsuba's rule), applied to the whole lane: the offsets are scaled by
    the same 1/q and die with their base path (in place)."""
    base = s.base
    q = dr.minimum(dr.max(base.throughput) * base.eta * base.eta, 0.95)
    # Mitsuba's rule: roulette from the rr_depth-th vertex on (its `path` counts the vertex just found before
    # comparing with rr_depth; rr_depth 1 may end a path at the first visible surface).
    rr_active = base.active & (s.depth + 1 >= k.rr_depth)
    survive = s.sampler.next_1d() < q
    inv_q = dr.select(rr_active, dr.rcp(q), 1.0)
    base.throughput = base.throughput * inv_q
    dead = rr_active & ~survive
    base.active = base.active & ~dead
    if k.shift is not None:
        s.offsets = [k.shift.kill(k.shift.scale(o, inv_q, rr_active), dead) for o in s.offsets]


def _vertex(k: PassKernel, s: LoopState, step_offset: OffsetStep) -> LoopState:
    """One loop iteration: the base path's next vertex, every offset's, their events into the layer sums, the
    feature search, Russian roulette."""
    samples = VertexSamples.draw(s.sampler)
    ray_d = mi.Vector3f(s.base.ray.d)
    base_active = mi.Bool(s.base.active)
    s.base, v = trace_vertex(k.scene, s.base, s.depth, k.max_depth, samples, k.strict_light_pdf, k.ray_flags)
    if k.gradients:
        hit_grads, nee_grads, bad = _offset_events(k, s, v, samples, step_offset)
        hit_value, bad_h = _finite(v.emitted)
        nee_value, bad_n = _finite(v.nee)
        bad |= bad_h | bad_n
    else:  # checked once per lane after the loop (_drop_non_finite): one check instead of two per vertex
        hit_grads, nee_grads = [], []
        hit_value, nee_value, bad = v.emitted, v.nee, mi.Bool(False)
    _route(s.sums, s.depth, k.settings, hit_value, nee_value, hit_grads, nee_grads)
    s.feat = _update_features(s.feat, base_active, v, ray_d, k.to_camera)
    if not k.hittable:
        # No emitter can be found by a ray: the next vertex is needed only for next-event estimation there (or to
        # continue the feature search past a mirror); its emission event is always 0.
        s.base.active &= (s.depth + 2 < k.max_depth) | s.feat.pending
    _russian_roulette(k, s)
    s.depth = s.depth + 1
    s.invalid = s.invalid | bad
    return s


def _run_loops(k: PassKernel, s: LoopState) -> LoopState:
    """The symbolic loops over path vertices. With a :class:`ConnectingShift`: a first loop while some offset of
    the lane still has vertices of its own, then a second, cheap one carrying the settled offsets' summaries."""
    shift = k.shift

    def loop(state: LoopState, cond: Callable[[LoopState], mi.Bool], step_offset: OffsetStep,
             label: str, peel: bool = False, step_later: OffsetStep | None = None) -> LoopState:
        if peel:
            # The first vertex outside the symbolic loop (same kernel): its depth is the literal 0 there, so
            # everything the shift does only after the primary ray (transitions, replays, reconnection rays, BSDF
            # calls masked by ``depth > 0``) folds away instead of running masked in every SIMD packet; inside
            # the loop every vertex is a later one (``step_later``: the primary-ray code folds away there).
            state = _vertex(k, state, step_offset)
        body_step = step_later if peel and step_later is not None else step_offset
        (state,) = dr.while_loop(state=(state,), cond=cond, body=lambda st: (_vertex(k, st, body_step),),
                                 label=label)
        return state

    # The primal-only mode's loop is not peeled: its small body gains nothing and the larger kernel measured
    # 5-10 % slower (the peel itself: docs/decisions.md, "Tracing the first vertex before the loop").
    peel = PEEL_FIRST_VERTEX and shift is not None

    def full_step(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        assert shift is not None  # only called for offsets, which exist only with a shift
        return shift.step(k.scene, off, v, depth, k.max_depth, samples)

    def later_step(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        assert shift is not None
        return shift.step(k.scene, off, v, depth, k.max_depth, samples, later=True)

    def base_alive(st: LoopState) -> mi.Bool:
        return st.base.active

    if k.settings.gradients == "direct" and shift is not None:
        return _run_direct_gradient_loops(k, s, loop, base_alive)
    if not isinstance(shift, ConnectingShift):
        return loop(s, base_alive, full_step, "gpt", peel=peel, step_later=later_step)

    def unsettled(st: LoopState) -> mi.Bool:
        settled = mi.Bool(True)
        for off in st.offsets:
            settled &= shift.settled(off)
        return st.base.active & ~settled

    def connected_step(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        return shift.step_connected(off, v, depth, k.max_depth)

    s = loop(s, unsettled, full_step, "gpt", peel=peel, step_later=later_step)
    s.offsets = [shift.summarize(off) for off in s.offsets]
    return loop(s, base_alive, connected_step, "gpt_connected")


LoopRunner = Callable[..., LoopState]  # (state, cond, step, label, peel=False)


def _run_direct_gradient_loops(k: PassKernel, s: LoopState, loop: LoopRunner,
                               base_alive: Callable[[LoopState], mi.Bool]) -> LoopState:
    """Gradients of the direct layer alone (``GptSettings.gradients == "direct"``): every offset takes the
    shift's full step at the first DIRECT_VERTICES vertices -- the direct layer's events are emission at depth
    0 and 1 and next-event estimation at depth 0 -- and is then dropped; the base path continues alone for the
    indirect layer's primal, in a loop with no offset work at all.

    The offsets take the very step (and random numbers) of an ``all`` render there, so the direct layer's base
    and gradients are that render's. Their depth limit is capped at DIRECT_VERTICES: the offsets' next-event
    estimate at depth 1 (an indirect event, whose gradient is not kept) is not evaluated (no emitter sample
    reconnection, no shadow ray); nothing the direct layer reads depends on that limit (the emission found at
    depth 1 does not, and the next-event estimate at depth 0 needs only ``1 < limit``). In a scene where no ray can
    find emission (point, spot and directional lights only: ``k.hittable`` False) the emission event at depth 1
    is 0 for base and offsets alike, so the offsets stop after vertex 0 (the ``all`` render adds 0 there too).
    render_gpt hands this mode the shift's ``for_direct_layer()`` where it has one (DIRECT_LAYER_SHIFT).
    """
    shift = k.shift
    assert shift is not None
    offset_max_depth = dr.minimum(k.max_depth, mi.UInt32(DIRECT_VERTICES))
    vertices = DIRECT_VERTICES if k.hittable else 1

    def direct_step(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        return shift.step(k.scene, off, v, depth, offset_max_depth, samples)

    def direct_later(off: Any, v: Vertex, depth: mi.UInt32, samples: VertexSamples) -> tuple[Any, OffsetEvents]:
        return shift.step(k.scene, off, v, depth, offset_max_depth, samples, later=True)

    def direct_vertices(st: LoopState) -> mi.Bool:
        return st.base.active & (st.depth < vertices)

    def no_offsets(*_: Any) -> tuple[Any, OffsetEvents]:
        raise AssertionError("no offsets are traced past the direct layer's vertices")

    s = loop(s, direct_vertices, direct_step, "gpt_direct", peel=PEEL_FIRST_VERTEX, step_later=direct_later)
    s.offsets = []
    return loop(s, base_alive, no_offsets, "gpt_base")


def _pixel_sums(settings: GptSettings, s: LoopState, pixel: mi.UInt32, width: int, height: int,
                gradients: bool, offset_targets: list[mi.UInt32] | None = None) -> dict[str, np.ndarray]:
    """Scatter-add every lane's sums and features into per-pixel buffers (one launch, fused with the loops)."""
    sums, invalid = (s.sums, s.invalid) if gradients else _drop_non_finite(s.sums)
    feat = s.feat
    n_pixels = width * height
    layout = channel_layout(settings, gradients)
    values: dict[str, Sequence[mi.Float]] = {}
    for layer, ls in sums.items():
        values[f"{layer}.base"] = [ls.base.x, ls.base.y, ls.base.z]
        y = LUMINANCE[0] * ls.base.x + LUMINANCE[1] * ls.base.y + LUMINANCE[2] * ls.base.z
        values[f"{layer}.sq"] = [dr.minimum(y * y, SQUARE_CAP)]
        for i, g in enumerate(ls.grads):
            values[f"{layer}.grad{i}"] = [g.x, g.y, g.z]
    values["albedo"] = [feat.albedo.x * feat.hit, feat.albedo.y * feat.hit, feat.albedo.z * feat.hit]
    values["normal"] = [feat.normal.x, feat.normal.y, feat.normal.z]
    values["depth"] = [feat.distance * feat.hit]
    values["hit"] = [feat.hit]
    values["invalid"] = [dr.select(invalid, 1.0, 0.0)]
    n_channels = sum(layout.values())
    target = dr.zeros(mi.Float, n_channels * n_pixels)
    channel = 0
    for name, width_c in layout.items():
        for comp in values.get(name, [])[:width_c]:
            index = pixel + channel * n_pixels
            if offset_targets is not None and ".grad" in name:
                # fewer offsets per lane: its k-th estimate belongs to offset offset_targets[k] (grad channels: 3 each)
                k = int(name.rsplit(".grad", 1)[1])
                index = index + (offset_targets[k] - k) * (3 * n_pixels)
            dr.scatter_reduce(dr.ReduceOp.Add, target, comp, index)
            channel += 1
        channel += width_c - len(values.get(name, [])[:width_c])
    dr.eval(target)
    flat = target.numpy().reshape(n_channels, height, width)
    out: dict[str, np.ndarray] = {}
    channel = 0
    for name, width_c in layout.items():
        out[name] = np.moveaxis(flat[channel:channel + width_c], 0, -1).astype(np.float64)
        channel += width_c
    return out


def render_pass(scene: mi.Scene, shift: Shift | None, settings: GptSettings, width: int, height: int, spp: int,
                seed: int) -> dict[str, np.ndarray]:
    """Trace ``width*height*spp`` lanes in one kernel; returns per-pixel *sums* (not means) per channel group.

    ``shift`` None renders the primal alone: the base paths with the same routing and features, no offsets.
    Sizes, seed and depth limits enter the kernel as opaque values, so one compiled kernel serves every seed and
    sample count of a scene; not every resolution: the scene is loaded with its film at the frame's size, and a
    scene loaded at another size compiles again (measured: a kernel compiled at 16x16 was compiled again at
    192x192 and 160x160), so a farm pays one compile per scene and frame size.
    """
    lanes = width * height * spp
    if lanes >= 1 << 32:
        raise ValueError(f"{lanes} samples in one pass exceed 2^32; use fewer samples per pass")
    kernel, state, pixel = _start_lanes(scene, shift, settings, width, height, spp, seed)
    state = _run_loops(kernel, state)
    return _pixel_sums(settings, state, pixel, width, height, kernel.gradients, kernel.offset_targets)


def pass_plan(width: int, height: int, spp: int, max_lanes: int = MAX_LANES_PER_PASS) -> list[int]:
    """Samples per pass: as many as fit in ``max_lanes`` lanes, at least one."""
    per_pass = max(1, min(spp, max_lanes // max(1, width * height)))
    plan = [per_pass] * (spp // per_pass)
    if spp % per_pass:
        plan.append(spp % per_pass)
    return plan


def pass_seed(seed: int, index: int) -> int:
    """A 32-bit seed for pass ``index`` of a render seeded ``seed`` (splitmix-style mix: distinct streams)."""
    z = (seed * 0x9E3779B97F4A7C15 + (index + 1) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return (z ^ (z >> 31)) & 0xFFFFFFFF


def render_gpt(scene: mi.Scene, shift: Shift | None, settings: GptSettings, width: int, height: int, spp: int,
               seed: int = 0, progress: Callable[[int, int], None] | None = None,
               max_lanes: int = MAX_LANES_PER_PASS, gradient_spp: int | None = None) -> GptResult:
    """Render ``spp`` samples per pixel in passes and combine them into per-layer base/dx/dy images + features.

    ``shift`` None is the primal-only mode: the same base paths, layers and features, no offsets and no
    gradients (each layer carries ``base`` alone).

    ``gradient_spp`` K (default ``spp``; needs a shift): only K of the ``spp`` samples trace offsets; the other
    ``spp - K`` are primal-only samples. The primal-only mode's bases and features are the same estimator as
    G-PT's primal, so the layers' bases and the features are per-pixel sums over all ``spp`` samples (the
    spp-weighted mean of the two renders, features normalised by their combined hit counts exactly as one
    render's), and the gradients come from the K G-PT samples alone. The primal-only passes continue the pass
    index after the G-PT passes, so every pass has its own seed stream (``pass_seed``). K == ``spp`` is the
    plain render, bit for bit."""
    settings.validate()
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    k = spp if gradient_spp is None else int(gradient_spp)
    if not 1 <= k <= spp:
        raise ValueError(f"gradient_spp must be in [1, spp={spp}], got {gradient_spp}")
    if shift is None and k != spp:
        raise ValueError("gradient_spp needs gradients: the primal-only mode traces no offsets")
    if shift is not None and settings.gradients == "direct" and DIRECT_LAYER_SHIFT:
        shift = getattr(shift, "for_direct_layer", lambda: shift)()
    plan = [(shift, settings, n) for n in pass_plan(width, height, k, max_lanes)]
    if k < spp:  # the primal-only mode's own settings (what render_frame's gradients="none" passes)
        primal = dataclasses.replace(settings, gradients="all", offsets="all")
        plan += [(None, primal, n) for n in pass_plan(width, height, spp - k, max_lanes)]
    totals: dict[str, np.ndarray] | None = None
    done = 0
    for i, (pass_shift, pass_settings, n) in enumerate(plan):
        sums = render_pass(scene, pass_shift, pass_settings, width, height, n, pass_seed(seed, i))
        # a primal-only pass has no gradient sums: those stay the G-PT passes' (keys of the first pass)
        totals = sums if totals is None else {key: v + sums[key] if key in sums else v for key, v in totals.items()}
        done += n
        if progress is not None:
            progress(done, spp)
    assert totals is not None
    return _finish(totals, settings, spp, len(plan), k)


def finish(totals: dict[str, np.ndarray], settings: GptSettings, spp: int, passes: int,
           gradient_spp: int | None = None) -> GptResult:
    """Added :func:`render_pass` sums -> a GptResult (what render_gpt returns): the bases and features are sums over
    ``spp`` samples, the gradients (where ``totals`` has them) over ``gradient_spp`` (default ``spp``). For callers
    that run the passes themselves (renderer/plan.py: passes of several plans, sized to a deadline)."""
    return _finish(totals, settings, spp, passes, gradient_spp)


def mean_variance(sums: np.ndarray, squares: np.ndarray, spp: int) -> np.ndarray | None:
    """The variance of each pixel's mean luminance, from the per-pixel sums of its ``spp`` samples' RGB and
    squared luminance: the unbiased sample variance over ``spp``, float32 (H, W), or None for one sample (no
    estimate). Rounding can leave a tiny negative difference for a pixel whose samples are all equal: that is 0. A
    pixel with a sample whose square was capped (SQUARE_CAP) has the largest variance, SQUARE_CAP."""
    if spp < 2:
        return None
    y = np.asarray(sums, np.float64) @ np.array(LUMINANCE)
    sq = np.asarray(squares, np.float64)[..., 0]
    spread = np.maximum(sq - y * y / spp, 0.0)
    var = np.where(sq >= SQUARE_CAP, SQUARE_CAP, np.minimum(spread / (spp * (spp - 1.0)), SQUARE_CAP))
    return var.astype(np.float32)


def _finish(t: dict[str, np.ndarray], settings: GptSettings, spp: int, passes: int,
            gradient_spp: int | None = None) -> GptResult:
    """Per-pixel sums -> means; the two one-sided gradient estimates -> dx, dy per the frame contract. The
    bases and features are sums over ``spp`` samples, the gradients over ``gradient_spp`` (default ``spp``)."""
    layers: dict[str, dict[str, np.ndarray]] = {}
    for layer in settings.layer_names():
        variance = mean_variance(t[f"{layer}.base"], t[f"{layer}.sq"], spp)
        if f"{layer}.grad0" not in t:  # primal-only render
            layers[layer] = {"base": (t[f"{layer}.base"] / spp).astype(np.float32), "var": variance}
            continue
        g = [t[f"{layer}.grad{i}"] for i in range(len(SHIFT_OFFSETS))]  # right, left, down, up
        dx = g[0].copy()
        dx[:, :-1] -= g[1][:, 1:]  # base at x+1 shifted left estimates I(x) - I(x+1) = -dx(x)
        dx[:, -1] = 0.0
        dy = g[2].copy()
        dy[:-1, :] -= g[3][1:, :]
        dy[-1, :] = 0.0
        # fewer offsets per sample: each traced its group with probability 1/groups, so its terms count groups times
        per_axis = (spp if gradient_spp is None else gradient_spp) / OFFSET_GROUPS[settings.offsets]
        layers[layer] = {"base": (t[f"{layer}.base"] / spp).astype(np.float32), "var": variance,
                         "dx": (dx / per_axis).astype(np.float32), "dy": (dy / per_axis).astype(np.float32)}
    hits = t["hit"][..., 0]
    safe = np.maximum(hits, 1.0)[..., None]
    albedo = np.clip(t["albedo"] / safe, 0.0, 1.0)
    normal = t["normal"]
    norm = np.linalg.norm(normal, axis=-1, keepdims=True)
    facing = np.broadcast_to(np.array([0.0, 0.0, 1.0]), normal.shape)
    normal = np.where(norm > 1e-6, normal / np.maximum(norm, 1e-12), facing)
    depth = np.where(hits > 0, t["depth"][..., 0] / np.maximum(hits, 1.0), 0.0)
    invalid = int(round(float(t["invalid"].sum())))
    warnings = []
    if invalid:
        warnings.append(f"{invalid} samples produced non-finite values; their contributions were set to 0")
    return GptResult(layers=layers, albedo=albedo.astype(np.float32), normal=normal.astype(np.float32),
                     depth=depth.astype(np.float32), spp=spp, invalid_samples=invalid, passes=passes,
                     warnings=warnings)
