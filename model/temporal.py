"""Temporal reconstruction: frame t of a shot from a window of frames around it, through their motion vectors.

Three stages. The first brings the neighbours' *inputs* onto frame t's pixels and accumulates them into frame t
before the per-frame method (model/reconstruct.py) runs once on the result:

1. **Warp.** Each neighbour's bases, gradients and variance (``L.var.Y``) are taken where the motion vectors put
   each pixel of frame t (a neighbour two frames away through the chain of the frame between). On the grid (a
   still camera) that is the neighbour's pixel there. Between the neighbour's pixels (a camera move) it is the
   nearest one, taken whole and once (:meth:`model.warp.Sampler.nearest`): interpolated noise would be correlated
   across pixels, which OIDN keeps as detail. A tap half a pixel off is only as good as the surface it lands on,
   so it counts only where its normal matches frame t's within MOVED_TOLERANCE and its albedo is within
   TEXTURE_RATIO of frame t's, pixel by pixel (model/rejection.py); it is demodulated (times frame t's albedo over
   its own), and its gradients count only where the albedo matches within MOVED_TOLERANCE. Where the vectors say
   there is no correspondence, or the position is off screen, the neighbour contributes nothing.
2. **Reject.** Per layer and pixel, a neighbour is rejected where its luminance or its features disagree with
   frame t's by more than the noise allows (model/rejection.py).
3. **Accumulate.** Accepted neighbours are averaged with frame t, each frame weighted by the inverse of its mean
   variance (one weight per frame and layer: per-pixel inverse-variance weights favour the pixels whose few
   samples missed a bright path), and the variance channel becomes that weighted mean's, so OIDN's back-off
   (model/backoff.py) sees the lower noise. A gradient joins two pixels, so a neighbour's counts where both were
   accepted and lie next to each other in the neighbour too (not across a silhouette or a disocclusion's edge).
4. **Reconstruct.** The per-frame method (the frame's default unless one is named) on the accumulated frame.

The second stage averages frame t's first-stage result with its neighbours' first-stage results, per layer, warped
the same way, where the first stage accepted that neighbour. Consecutive outputs that denoised overlapping sample
sets still differ by what the denoiser made of the samples they do not share; averaging them where the inputs
agree removes that difference (the flicker) and more of the error. The first stage reaches FIRST_STAGE_RADIUS frames
to each side (the whole of the default window of five); a wider window's frames beyond are the second stage's, so
through the first two stages no sample from outside the window reaches frame t (through the third, a moved
neighbour's first stage brings its own neighbours').

The third is for a camera move, whose neighbours' pixels land between frame t's: each such neighbour's first-stage
result, divided by its albedo (what a warp between pixels blurs of a result is mostly texture), is warped
(bilinear: a result's noise is gone) and multiplied by frame t's albedo, and averaged in per layer and pixel where
its albedo and normal match frame t's within MOVED_TOLERANCE and its inputs pass the rejection test above (the
first stage took their inputs by the nearest pixel; their results add what the denoiser made of them). A shot in
order (:class:`ShotReconstructor`) computes each frame's first stage once; a stateless window
(:func:`reconstruct_window`) computes its moved neighbours' too.

Why accumulate inputs, and test them, rather than blend per-frame outputs alone: the inputs' noise is known from
their variance, so the test rejects on change, not on noise, and the denoiser gets one frame whose noise is lower
everywhere it can be. The decision and its measurements are in docs/decisions.md ("Temporal reconstruction").

Without motion vectors on frame t, or with one frame, this is exactly :func:`model.reconstruct.reconstruct`. A
layer without a variance channel (another renderer's frame) uses a local spatial estimate of it, with a warning.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from gradsep.model.environment import thread_map
from gradsep.model.frame import FLOAT32_MAX, Frame, Layer, Motion
from gradsep.model.methods import LoadedModels
from gradsep.model.policy import DEFAULT_ALPHA
from gradsep.model.reconstruct import Reconstruction, layer_threads, reconstruct
from gradsep.model.rejection import (
    ALBEDO_FLOOR,
    BOXES,
    MOVED_TOLERANCE,
    REJECT_K,
    Stats,
    Taken,
    agrees,
    features_agree,
    frame_stats,
    moved_pixels,
    taken_pixels,
)
from gradsep.model.warp import Sampler, chains

__all__ = ["BOXES", "DEFAULT_WINDOW", "FIRST_STAGE_RADIUS", "MOVED_TOLERANCE", "REJECT_K", "Motion",
           "ShotReconstructor", "TemporalReconstruction", "check_shot", "first_stage", "moved_stage",
           "reconstruct_window", "second_stage"]

#: The frames of a window by default: frame t and two on each side.
DEFAULT_WINDOW = 5
#: How many frames to each side the first stage accumulates (a wider window's further frames are blended by the
#: second stage): the denoiser gains more from one input with the samples of five frames than from blending the
#: outputs of three-frame inputs (docs/decisions.md).
FIRST_STAGE_RADIUS = 2
#: A neighbour's pixel within this many pixels of frame t's grid is on the grid (a still camera): the first stage
#: tests its features by FEATURE_BOX means and the second stage blends its result. Off the grid (a camera move)
#: the first stage takes the nearest pixel where it matches pixel by pixel, and the moved stage blends the result.
GRID_TOLERANCE = 0.02


@dataclass
class TemporalReconstruction(Reconstruction):
    """:class:`model.reconstruct.Reconstruction` plus which neighbours contributed."""

    #: offsets from frame t (e.g. -2, -1, 1, 2) of the neighbours with at least one accepted pixel
    neighbours: list[int] = field(default_factory=list)
    #: per offset in the window, the fraction of frame t's pixels where the neighbour was accepted (mean over layers)
    accepted: dict[int, float] = field(default_factory=dict)
    #: the first stage's acceptance per layer and neighbour, which the second stage blends by (None: no first stage)
    agreement: _Agreement | None = field(default=None, repr=False, compare=False)


# ------------------------------------------------------------------------------------------------ accumulation


@dataclass
class _LayerSums:
    """The running weighted sums of one layer over the accepted frames (float32; a frame's weight is one number,
    zero where it was rejected). The gradients have weights of their own (:func:`_gradient_weights`)."""

    weight: np.ndarray
    base: np.ndarray
    dx: np.ndarray | None
    dy: np.ndarray | None
    var: np.ndarray  # Σ w² σ²
    weight_dx: np.ndarray | None = None
    weight_dy: np.ndarray | None = None

    @classmethod
    def start(cls, layer: Layer, var: np.ndarray) -> _LayerSums:
        """Frame t's layer, weight 1 (the neighbours' weights are relative to frame t's)."""
        gradients = layer.dx is not None and layer.dy is not None
        return cls(np.ones(var.shape, np.float32), layer.base.astype(np.float32, copy=True),
                   None if layer.dx is None else layer.dx.astype(np.float32, copy=True),
                   None if layer.dy is None else layer.dy.astype(np.float32, copy=True),
                   var.astype(np.float32, copy=True),
                   np.ones(var.shape, np.float32) if gradients else None,
                   np.ones(var.shape, np.float32) if gradients else None)

    def add(self, layer: Layer, var: np.ndarray, accept: np.ndarray, weight: float,
            sample: Sampler | None = None, gradients: np.ndarray | None = None) -> None:
        """Add a warped neighbour where ``accept``; its gradients only where ``gradients`` (float32 0 / 1; None:
        everywhere) too, and where ``sample`` (the warp) puts a pixel and the next one along an axis next to each
        other (:meth:`model.warp.Sampler.steady`, :func:`_gradient_weights`)."""
        steady = None if sample is None or layer.dx is None else sample.steady()
        w = accept.astype(np.float32)
        if weight != 1.0:
            w *= np.float32(weight)
        self.weight += w
        scratch = np.empty_like(self.base)
        np.multiply(layer.base, w[..., None], out=scratch)
        self.base += scratch
        if self.dx is not None and self.dy is not None and layer.dx is not None and layer.dy is not None:
            for axis, total, image, weights in ((1, self.dx, layer.dx, self.weight_dx),
                                                (0, self.dy, layer.dy, self.weight_dy)):
                wg = _gradient_weights(w if gradients is None else w * gradients, axis,
                                       None if steady is None else steady[axis == 0])
                weights += wg  # type: ignore[operator]
                np.multiply(image, wg[..., None], out=scratch)
                total += scratch
        w *= w
        w *= var
        self.var += w

    def add_taken(self, layer: Layer, take: Taken, var: np.ndarray, accept: np.ndarray, weight: float) -> None:
        """Add a moving camera's neighbour ``layer`` by its nearest pixels (``take``) where ``accept``, demodulated:
        multiplied by frame t's albedo over the neighbour's (past float32's largest: clipped, as the moved stage
        clips), its variance by the square of that ratio's luminance; gradients where ``take.gradients``."""
        if not accept.any():
            return
        warped = _warped(layer, take.sample)
        for image in (warped.base, warped.dx, warped.dy):
            if image is not None:
                with np.errstate(over="ignore"):
                    image *= take.ratio
                np.clip(image, -FLOAT32_MAX, FLOAT32_MAX, out=image)
        self.add(warped, var * take.variance_scale, accept, weight, take.sample, take.gradients)

    def layer(self) -> Layer:
        inverse = 1.0 / self.weight
        self.base *= inverse[..., None]
        for image, weights in ((self.dx, self.weight_dx), (self.dy, self.weight_dy)):
            if image is not None and weights is not None:
                image /= weights[..., None]
        self.var *= inverse
        self.var *= inverse
        return Layer(self.base, self.dx, self.dy, self.var)


def _gradient_weights(w: np.ndarray, axis: int, steady: np.ndarray | None) -> np.ndarray:
    """A neighbour's weight for its gradients along ``axis`` (1: dx, 0: dy): a gradient is the difference of a pixel
    and the next one, so it counts only as much as the lesser of the two pixels' weights, and only where the two
    are next to each other in the neighbour as well (``steady``; None: the warp is one shift). Else a silhouette's
    or a disocclusion's edge would take the neighbour's difference across another pair of pixels, and the solver
    would carry it into frame t's pixels that the neighbour does not see."""
    out = w.copy()
    if axis == 1:
        np.minimum(out[:, :-1], w[:, 1:], out=out[:, :-1])
    else:
        np.minimum(out[:-1], w[1:], out=out[:-1])
    if steady is not None:
        out *= steady
    return out


@dataclass
class _Agreement:
    """Which neighbour agreed with frame t where: per layer and offset, the accepted pixels, and per offset where
    the neighbour's pixels lie (the second stage blends the neighbours' reconstructions through the same)."""

    samplers: dict[int, Sampler] = field(default_factory=dict)
    accept: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    #: per layer and offset, the pixels off the grid whose neighbour's result the moved stage blends
    moved: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    #: per layer and offset, the pixels off the grid whose neighbour's inputs the first stage took by the nearest pixel
    taken: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    #: this frame's albedo (the moved blend demodulates by it); None without one
    albedo: np.ndarray | None = None

    def moved_offsets(self) -> list[int]:
        """The offsets with at least one moved pixel accepted in some layer."""
        return sorted({o for masks in self.moved.values() for o, m in masks.items() if m.any()})

    def fractions(self) -> dict[int, float]:
        """Per offset, the fraction of pixels whose inputs the first stage accumulated (mean over layers)."""
        per = {o: [float(np.mean(m[o] | self.taken.get(name, {}).get(o, False))) for name, m in self.accept.items()
                   if o in m] for o in self.samplers}
        return {o: float(np.mean(v)) if v else 0.0 for o, v in per.items()}


def _accumulate(frames: Sequence[Frame | None], centre: int, chained: dict[int, Sampler | None],
                warnings: list[str]) -> tuple[Frame, _Agreement]:
    """Frame t with its accepted neighbours' samples accumulated into each layer (module docstring, steps 1-3);
    ``chained``: per offset, where that neighbour's pixels lie (:func:`model.warp.chains`)."""
    frame = frames[centre]
    assert frame is not None
    features = frame.features
    agreement = _Agreement({o: s for o, s in chained.items() if s is not None},
                           albedo=None if features is None else features.albedo)
    own = frame_stats(frame)
    agree = {o: s.on_grid(GRID_TOLERANCE) for o, s in agreement.samplers.items()}
    moved = {o: moved_pixels(frame, frames[centre + o], s, agree[o])  # type: ignore[arg-type]
             for o, s in agreement.samplers.items()}
    # off the grid the inputs are taken by the nearest pixels (features present: moved_pixels said so)
    taken = {o: taken_pixels(frame, frames[centre + o], agreement.samplers[o], agree[o])  # type: ignore[arg-type]
             for o, pixels in moved.items() if pixels is not None}
    off: dict[int, Taken] = {o: t for o, t in taken.items() if t is not None and (moved[o].any() or t.pixels.any())}
    # a neighbour with no pixel on the grid and none off it that agrees adds nothing: it is neither warped nor tested
    others = {o: frame_stats(frames[centre + o]) for o in agree if agree[o].any() or o in off}  # type: ignore[arg-type]
    for o, stats in others.items():
        if agree[o].any():  # (a camera move puts none on the grid: nothing to test the features of)
            agree[o] &= features_agree(own, stats, agreement.samplers[o])
    names = list(frame.layers)
    tested = _tested(own, {o: others[o] for o in others if agree[o].any()}, agreement.samplers, names)
    tested_off = _tested(own, {o: others[o] for o in off}, {o: t.sample for o, t in off.items()}, names)
    for name in names:  # every layer's key, in the frame's order, before the layers run concurrently
        agreement.accept[name] = {}
        for o, take in off.items():
            passes = tested_off[o, name][1]
            agreement.moved.setdefault(name, {})[o] = moved[o] & passes  # type: ignore[operator]
            agreement.taken.setdefault(name, {})[o] = take.pixels & passes
    if any(layer.dx is not None for layer in frame.layers.values()):  # once here, not raced for by the layers' threads
        for sample in [*(agreement.samplers[o] for o in others), *(take.sample for take in off.values())]:
            sample.steady()

    def accumulate(name: str) -> Layer:
        layer = frame.layers[name]
        sums = _LayerSums.start(layer, own.var[name])
        for offset, mask in agree.items():
            if offset not in others or not mask.any():
                agreement.accept[name][offset] = mask  # nowhere
                continue
            var, passes = tested[offset, name]  # warped once: read by the test and the sums
            accept = mask & passes
            agreement.accept[name][offset] = accept
            sums.add(_warped(frames[centre + offset].layers[name], agreement.samplers[offset]),  # type: ignore
                     var, accept, others[offset].weight[name] / own.weight[name], agreement.samplers[offset])
        for offset, take in off.items():
            sums.add_taken(frames[centre + offset].layers[name], take,  # type: ignore[union-attr]
                           tested_off[offset, name][0], agreement.taken[name][offset],
                           others[offset].weight[name] / own.weight[name])
        return sums.layer()

    warnings += _variance_warnings(frames, centre, list(agree))
    layers = dict(zip(frame.layers, thread_map(accumulate, list(frame.layers), layer_threads(), "gradsep-temporal"),
                      strict=True))
    out = Frame(layers, frame.features, dict(frame.metadata), list(frame.warnings), frame.alpha,
                dict(frame.image_attributes), frame.layout)
    return out, agreement


def _warped(layer: Layer, sample: Sampler) -> Layer:
    """A neighbour's layer (base and gradients) where ``sample`` puts frame t's pixels."""
    return Layer(sample(layer.base), None if layer.dx is None else sample(layer.dx),
                 None if layer.dy is None else sample(layer.dy))


def _tested(own: Stats, others: dict[int, Stats], samplers: dict[int, Sampler],
            names: list[str]) -> dict[tuple[int, str], tuple[np.ndarray, np.ndarray]]:
    """Per neighbour in ``others`` and layer, its warped variance and where it passes the rejection test: every test
    either stage reads, computed once, concurrently (the box filters release the GIL, and they are most of a
    neighbour's cost)."""
    pairs = [(o, name) for o in others for name in names]

    def test(pair: tuple[int, str]) -> tuple[np.ndarray, np.ndarray]:
        o, name = pair
        var = samplers[o](others[o].var[name], squared=True)
        return var, agrees(own, others[o], name, samplers[o], var)

    return dict(zip(pairs, thread_map(test, pairs, layer_threads(), "gradsep-temporal"), strict=True))


def _variance_warnings(frames: Sequence[Frame | None], centre: int, offsets: list[int]) -> list[str]:
    """A warning per layer without a variance channel in frame t or in a neighbour at ``offsets`` (another
    renderer's frames, or a frame that got one sample: no spread to measure)."""
    out = []
    for name, layer in frames[centre].layers.items():  # type: ignore[union-attr]
        lacking = ["t"] * (layer.var is None) + [f"{o:+d}" for o in offsets
                                                  if frames[centre + o].layers[name].var is None]  # type: ignore
        if lacking:
            out.append(f"layer {name} has no variance channel ({name}.var.Y) in frame(s) {', '.join(lacking)}: "
                       "its noise is estimated from each pixel's neighbourhood for the temporal rejection")
    return out


# ------------------------------------------------------------------------------------------------ the window


def _signature(frame: Frame) -> tuple:
    """What frames of one shot share: size, layers, which carry gradients, feature groups, alpha (not variance:
    model.frame.shot_layout)."""
    from gradsep.model.frame import feature_groups

    return (frame.height, frame.width, tuple(frame.layers), frame.gradient_layers, feature_groups(frame.features),
            frame.alpha is not None)


def check_shot(frames: Sequence[Frame | None], names: Sequence[str], reference: int = 0) -> None:
    """Raise ValueError naming the first frame whose size or channels differ from ``frames[reference]``'s."""
    want, first = _signature(frames[reference]), names[reference]  # type: ignore[arg-type]
    for frame, name in zip(frames, names, strict=True):
        if frame is not None and frame is not frames[reference]:
            _check_against(frame, name, first, want)


def _radii(window: int) -> tuple[int, int]:
    """A window of ``window`` frames (odd, >= 1) as the two stages' radii: the first accumulates frames up to
    ``r1`` = min(radius, FIRST_STAGE_RADIUS) away, the second blends reconstructions up to ``r2`` away, r1 + r2 =
    (window - 1) / 2."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"the window must be an odd number of frames >= 1, got {window}")
    radius = (window - 1) // 2
    first = min(radius, FIRST_STAGE_RADIUS)
    return first, radius - first


def first_stage(frames: Sequence[Frame | None], centre: int, method: str | None = None,
                alpha: float = DEFAULT_ALPHA, models: LoadedModels | None = None) -> TemporalReconstruction:
    """Stage one (steps 1-4 of the module docstring) for ``frames[centre]``: every other frame given is a
    neighbour. Without motion vectors on frame t, or without a neighbour that can be reached, this is
    :func:`model.reconstruct.reconstruct` of frame t, bit for bit."""
    frame = frames[centre]
    if frame is None:
        raise ValueError(f"frame {centre} of the window is missing")
    offsets = [i - centre for i in range(len(frames)) if i != centre]
    warnings: list[str] = []
    missing = [o for o in offsets if frames[centre + o] is None]
    if missing:
        warnings.append("neighbour(s) " + ", ".join(f"{o:+d}" for o in missing) + " missing: the frame was "
                        "reconstructed from the frames it has")
    chained = chains(frames, centre, offsets) if getattr(frame, "motion", None) is not None else {}
    if all(s is None for s in chained.values()):
        result = reconstruct(frame, method, alpha, models)
        return TemporalReconstruction(**{**vars(result), "warnings": [*warnings, *result.warnings]})
    accumulated, agreement = _accumulate(frames, centre, chained, warnings)
    result = reconstruct(accumulated, method, alpha, models)
    fractions = agreement.fractions()
    out = TemporalReconstruction(**{**vars(result), "warnings": [*warnings, *result.warnings]},
                                 neighbours=[o for o in offsets if fractions.get(o, 0.0) > 0.0], accepted=fractions)
    out.agreement = agreement
    return out


def second_stage(results: Sequence[TemporalReconstruction | None], centre: int) -> TemporalReconstruction:
    """Stage two: ``results[centre]`` (a first-stage result) averaged, per layer and pixel, with the first-stage
    results of its neighbours in ``results`` where the first stage accepted that neighbour's samples. The
    neighbours' reconstructions went through the same denoiser with overlapping samples; averaging them where
    the inputs agree removes what changes from one output to the next (flicker) and more of the error."""
    own = results[centre]
    if own is None:
        raise ValueError(f"the first-stage result of frame {centre} is missing")
    agreement = own.agreement
    offsets = [i - centre for i in range(len(results)) if i != centre and results[i] is not None]
    if agreement is None or not offsets:
        return own
    layers: dict[str, np.ndarray] = {}
    reached = set(own.neighbours)
    for name, image in own.layers.items():
        total = image.copy()
        count = np.ones(image.shape[:2], np.float32)
        for offset in offsets:
            mask = agreement.accept.get(name, {}).get(offset)
            other = results[centre + offset]
            if mask is None or other is None or not mask.any():
                continue
            sample = agreement.samplers[offset]
            warped = sample(other.layers[name])  # the neighbour's own array when it did not move
            total += np.multiply(warped, mask[..., None], out=None if sample.identity else warped)
            count += mask
            reached.update({offset, *(offset + o for o in other.neighbours)} - {0})
        total /= count[..., None]
        layers[name] = total
    return _blended(own, layers, reached)


def moved_stage(result: TemporalReconstruction, own: TemporalReconstruction,
                neighbours: dict[int, TemporalReconstruction | None]) -> TemporalReconstruction:
    """Stage three, for a camera move: ``result`` (frame t's second-stage result) averaged, per layer and pixel,
    with the first-stage results of its moved neighbours (``own``'s agreement: pixels between frame t's, whose
    albedo and normal match frame t's and whose inputs pass the rejection test), each demodulated: divided by its
    own albedo, warped, multiplied by frame t's. A moving camera's neighbours cannot join the first stage: their
    inputs, warped between pixels, carry noise correlated across pixels, which the denoiser keeps. Their results
    are smooth, and what a warp between pixels blurs of them is mostly texture, which demodulation takes out
    (docs/decisions.md, "A camera move joins through its results")."""
    agreement = own.agreement
    offsets = [] if agreement is None else [o for o in agreement.moved_offsets() if neighbours.get(o) is not None]
    if agreement is None or not offsets:
        return result
    mine = _demodulator(own)
    floors = {o: None if mine is None else _demodulator(neighbours[o]) for o in offsets}

    def blend(name: str) -> tuple[np.ndarray, set[int]]:
        total = result.layers[name].astype(np.float32, copy=True)
        count = np.ones(total.shape[:2], np.float32)
        used: set[int] = set()
        for offset in offsets:
            mask = agreement.moved.get(name, {}).get(offset)
            other = neighbours[offset]
            if mask is None or other is None or not mask.any() or name not in other.layers:
                continue
            theirs = floors[offset]
            source = np.asarray(other.layers[name], np.float32)
            if theirs is not None:  # capped: radiance near float32's largest over a black albedo
                with np.errstate(over="ignore"):
                    source = np.divide(source, theirs)
                np.minimum(source, FLOAT32_MAX, out=source)
            warped = agreement.samplers[offset](source)
            if theirs is not None:
                warped *= mine
            np.add(total, warped, out=total, where=mask[..., None])  # past float32's largest: inf, clipped below
            count += mask
            used.add(offset)
        total /= count[..., None]
        return np.minimum(total, FLOAT32_MAX, out=total), used

    names = list(result.layers)
    blended = thread_map(blend, names, layer_threads(), "gradsep-temporal")
    reached = set(result.neighbours).union(*(used for _, used in blended))
    return _blended(result, {name: image for name, (image, _) in zip(names, blended, strict=True)}, reached)


def _blended(base: TemporalReconstruction, layers: dict[str, np.ndarray],
             reached: set[int]) -> TemporalReconstruction:
    """``base`` with its layers replaced by ``layers`` (blended), the image their sum, the neighbours ``reached``."""
    image = np.zeros(base.image.shape, np.float64)
    for layer in layers.values():  # summed in the frame's order, as model.reconstruct sums them
        image += layer
    out = TemporalReconstruction(**{**vars(base), "image": image.astype(np.float32), "layers": layers})
    out.neighbours = sorted(reached)
    return out


def _demodulator(result: TemporalReconstruction | None) -> np.ndarray | None:
    """A result's frame's albedo plus ALBEDO_FLOOR (what the moved stage divides or multiplies by); None without."""
    albedo = None if result is None or result.agreement is None else result.agreement.albedo
    return None if albedo is None else np.asarray(albedo, np.float32) + np.float32(ALBEDO_FLOOR)


def reconstruct_window(frames: Sequence[Frame | None], centre: int, method: str | None = None,
                       alpha: float = DEFAULT_ALPHA, models: LoadedModels | None = None) -> TemporalReconstruction:
    """Reconstruct ``frames[centre]`` from the window ``frames`` (consecutive frames of one shot; None for a
    missing one, where the chain of motion vectors stops), statelessly: the first stage for frame t and for each
    frame the second stage blends, then the second stage. A shot reconstructed frame after frame shares the first
    stages between frames instead (:class:`ShotReconstructor`).

    With one frame, or without motion vectors on frame t, this is :func:`model.reconstruct.reconstruct` of frame t,
    bit for bit. Raises ValueError for an out-of-range ``centre``, a window of an even size, frames that differ in
    size or channels (:func:`check_shot`), and whatever :func:`~model.reconstruct.reconstruct` raises.
    """
    if not 0 <= centre < len(frames) or frames[centre] is None:
        raise ValueError(f"centre {centre} is not a present frame of the window (0..{len(frames) - 1})")
    check_shot(frames, [f"{i - centre:+d}" if i != centre else "t" for i in range(len(frames))], centre)
    radius = max(centre, len(frames) - 1 - centre)
    r1, r2 = _radii(2 * radius + 1)
    frame = frames[centre]
    if radius == 0 or getattr(frame, "motion", None) is None:
        return TemporalReconstruction(**vars(reconstruct(frame, method, alpha, models)))  # type: ignore[arg-type]

    def stage_one(index: int) -> TemporalReconstruction | None:
        if not 0 <= index < len(frames) or frames[index] is None:
            return None
        lo, hi = max(0, index - r1), min(len(frames), index + r1 + 1)
        return first_stage(frames[lo:hi], index - lo, method, alpha, models)

    firsts = [stage_one(centre + o) if abs(o) <= r2 else None for o in range(-centre, len(frames) - centre)]
    lo = max(0, centre - r2)
    result = second_stage(firsts[lo:centre + r2 + 1], centre - lo)
    own = firsts[centre]
    assert own is not None
    moved = [] if own.agreement is None else own.agreement.moved_offsets()
    return moved_stage(result, own, {o: firsts[centre + o] or stage_one(centre + o) for o in moved})


class ShotReconstructor:
    """A shot's frames reconstructed in order, each frame's first stage computed once and shared by the second
    stages of the frames around it (what :func:`reconstruct_window` recomputes per call). ``load(n)`` returns frame
    ``n`` or None when it does not exist; frames and first stages are kept only while a later frame needs them."""

    def __init__(self, load: Callable[[int], Frame | None], window: int = DEFAULT_WINDOW, method: str | None = None,
                 alpha: float = DEFAULT_ALPHA, models: LoadedModels | None = None) -> None:
        self.r1, self.r2 = _radii(window)
        self._load, self._method, self._alpha, self._models = load, method, alpha, models
        self._frames: dict[int, Frame | None] = {}
        self._firsts: dict[int, TemporalReconstruction | None] = {}
        self._signature: tuple[int, tuple] | None = None

    def _frame(self, n: int) -> Frame | None:
        if n not in self._frames:
            frame = self._load(n)
            if frame is not None:
                if self._signature is None:
                    self._signature = (n, _signature(frame))
                else:
                    first, want = self._signature
                    _check_against(frame, n, first, want)
            self._frames[n] = frame
        return self._frames[n]

    def _first(self, n: int) -> TemporalReconstruction | None:
        if n not in self._firsts:
            frames = [self._frame(k) for k in range(n - self.r1, n + self.r1 + 1)]
            self._firsts[n] = None if frames[self.r1] is None else first_stage(
                frames, self.r1, self._method, self._alpha, self._models)
        return self._firsts[n]

    def reconstruct(self, n: int) -> TemporalReconstruction:
        """Frame ``n`` (which must exist) from its window. Frames before ``n - window // 2`` and first stages
        before ``n - r2`` are forgotten first, so their memory is free before the new first stage's."""
        # first stages: the second stage's neighbours and the moved ones (as far as the first stage's); frames: those
        # of the first stages still to compute (an earlier one is kept, so its frames are not needed again)
        reach = max(self.r1, self.r2)
        for cache, keep in ((self._frames, n - self.r1 - self.r2), (self._firsts, n - reach)):
            for k in [k for k in cache if k < keep]:
                del cache[k]
        if self._frame(n) is None:
            raise ValueError(f"frame {n} is missing")
        firsts = [self._first(k) for k in range(n - self.r2, n + self.r2 + 1)]
        own = firsts[self.r2]
        assert own is not None
        moved = [] if own.agreement is None else own.agreement.moved_offsets()
        return moved_stage(second_stage(firsts, self.r2), own, {o: self._first(n + o) for o in moved})


def _check_against(frame: Frame, n: int | str, first: int | str, want: tuple) -> None:
    """Raise ValueError naming frame ``n`` when its size or channels differ from frame ``first``'s."""
    got = _signature(frame)
    if got[:2] != want[:2]:
        raise ValueError(f"frame {n} is {got[1]}x{got[0]}, but frame {first} is {want[1]}x{want[0]}: the frames "
                         "of one shot must have one size")
    if got != want:
        raise ValueError(f"frame {n} carries other channels than frame {first} (layers, gradients, "
                         "features or alpha differ): the frames of one shot must have one layout")
