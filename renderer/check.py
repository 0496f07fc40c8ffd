"""The frame's own error estimate (``gradsep.predicted_relmse`` of a planned frame): the final frame's passes,
dealt into GROUPS groups as they are rendered, judge each half of the frame against the other half's groups.

The checkpoint's prediction (renderer/checkpoint.py) is read at a fraction of the frame's samples and carried far
in samples with an assumed error-vs-spp law, which read high on held-out rooms (docs/decisions.md). Here the
estimate is read at the frame's own samples instead:

- once the check is known to fit (with --gradients auto from the frame's first pass on: the checkpoint judges the
  plans on these halves; for a fixed plan after its first pass), the passes so far go to half ``A``'s first group
  as one lump, and every later pass to the half with fewer samples, there to its group
  with the fewest (the first half of the groups is half ``A``, the rest half ``B``); ``A``'s sums are kept whole
  (bases, features, squares and each plan's gradients), ``B``'s are the frame's less ``A``'s, and each group
  keeps its base image;
- each half is reconstructed with the method (and OIDN setting) that serves the frame, and its error estimated
  against the groups of the other half, which are independent of it (renderer.estimate.cross_relmse: no
  reference, bias included; with k groups the estimate's noise from the groups' own noise is k / (k - 1) of its
  least: twice it with two groups, four thirds of it with four);
- each half's estimate is carried from its samples to the frame's (a factor of about two) with the plan's
  error-vs-spp exponent (renderer.estimate.ERROR_EXPONENT), and the two are averaged;
- given several reconstructions (OIDN settings), each is judged so, and their paired difference on the same
  groups, where the groups' noise cancels, chooses between them (:func:`check_frame`).

It costs two reconstructions at the frame's size per option (:func:`check_seconds` predicts them from the
checkpoint's, or from a tile a fixed plan times), so a render makes it only where they fit a small share of the
budget (renderer.planned_frame.CHECK_SHARE); elsewhere the header keeps the checkpoint's prediction, and
``gradsep.predicted_from`` says which it is.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gradsep.model.header_keys import CHECK_KEY
from gradsep.renderer.estimate import at_budget, cross_relmse, cross_terms, mean_and_se, relative_weights

#: Groups the passes are dealt into: half of them make each half of the frame.
GROUPS = 8
#: The check's predicted time is the pilot's reconstruction time per pixel times the frame's pixels, twice (one
#: per half), times this margin: a shared machine's swings, and the pilot's tiles are too small to time exactly
#: (a smaller margin overran under load: docs/decisions.md).
CHECK_MARGIN = 2.0


class Split:
    """A frame's passes dealt into GROUPS groups as they are rendered (see the module's docstring)."""

    def __init__(self) -> None:
        self.spp = [0] * GROUPS
        self.passes = [0] * GROUPS
        self.images: list[np.ndarray | None] = [None] * GROUPS  # each group's base image, summed over its samples
        self.half: dict[str, np.ndarray] | None = None  # half A's bases, features and squares (sums)
        self.half_gradients: dict[str, tuple[dict[str, np.ndarray], int]] = {}  # plan -> (A's gradient sums, spp)

    def add(self, plan: str, bases: dict[str, np.ndarray], grads: dict[str, np.ndarray], spp: int) -> None:
        """Deal one pass (its sums over ``spp`` samples, rendered with ``plan``: ``bases`` with features and
        squares, and ``grads``, its gradient sums or none) to the half with fewer samples (A on a tie), and there
        to its group with the fewest: the halves stay within one pass of each other even when the frame ends in a
        few large passes. The pass's arrays are never written to."""
        h = GROUPS // 2
        first = 0 if sum(self.spp[:h]) <= sum(self.spp[h:]) else h
        q = first + int(np.argmin(self.spp[first:first + h]))
        image = base_sum(bases)
        self.images[q] = image if self.images[q] is None else self.images[q] + image
        self.spp[q] += spp
        self.passes[q] += 1
        if q >= h:
            return
        self.half = _add(self.half, bases)
        if grads:
            have, n = self.half_gradients.get(plan, (None, 0))
            self.half_gradients[plan] = (_add(have, grads), n + spp)

    def add_lump(self, bases: dict[str, np.ndarray], gradients: dict[str, tuple[dict[str, np.ndarray], int]],
                 spp: int, passes: int) -> None:
        """Deal the frame so far, ``passes`` passes of ``spp`` samples (``bases``, and each plan's gradient sums
        with their samples), to half A's first group as one lump: a split started after a pilot, whose passes
        were rendered before the check was known to fit. Nothing is copied from a split that holds passes."""
        assert not any(self.spp), "a lump goes into an empty split"
        self.images[0] = base_sum(bases)
        self.spp[0], self.passes[0] = spp, passes
        self.half = _add(None, bases)
        self.half_gradients = {plan: (_add(None, sums), n) for plan, (sums, n) in gradients.items()}

    def ready(self, plan: str, gradients: bool, total_gradient_spp: int) -> bool:
        """Whether both halves can be judged: each half has samples in two groups or more, and with ``gradients``
        some of ``plan``'s gradient samples."""
        h = GROUPS // 2
        if self.half is None or min(sum(n > 0 for n in self.spp[:h]), sum(n > 0 for n in self.spp[h:])) < 2:
            return False
        if not gradients:
            return True
        a = self.half_gradients.get(plan, ({}, 0))[1]
        return 0 < a < total_gradient_spp

    def halves(self, plan: str, bases: dict[str, np.ndarray], gradients: dict[str, np.ndarray], spp: int,
               gradient_spp: int) -> list[tuple[dict[str, np.ndarray], int, int, int | None]]:
        """Both halves as (sums, spp, passes, gradient spp or None), from the frame's ``bases`` and ``plan``'s
        ``gradients`` (sums over ``spp`` and ``gradient_spp`` samples)."""
        assert self.half is not None
        a_grads, a_n = self.half_gradients.get(plan, ({}, 0))
        h = GROUPS // 2
        a_spp, a_passes = sum(self.spp[:h]), sum(self.passes[:h])
        b_passes = sum(self.passes[h:])
        half_a = {**self.half, **a_grads}
        half_b = {k: v - self.half[k] for k, v in bases.items()}
        half_b.update({k: v - a_grads[k] for k, v in gradients.items()})
        grad = bool(gradients)
        return [(half_a, a_spp, a_passes, a_n if grad else None),
                (half_b, spp - a_spp, b_passes, gradient_spp - a_n if grad else None)]

    def batches(self, half: int) -> list[tuple[np.ndarray, int]]:
        """The other half's groups that have samples, as mean images with their samples: independent of
        ``half``."""
        h = GROUPS // 2
        others = range(h, GROUPS) if half == 0 else range(h)
        return [(self.images[q] / self.spp[q], self.spp[q]) for q in others if self.spp[q]]  # type: ignore[operator]


def base_sum(sums: dict[str, np.ndarray]) -> np.ndarray:
    """The radiance summed over a pass's (or passes') layers: its ``L.base`` sums added."""
    return sum(v for k, v in sums.items() if k.endswith(".base"))  # type: ignore[return-value]


def check_seconds(reconstruct_rate: float, pixels: int, extra_per_pixel: float = 0.0, options: int = 1) -> float:
    """Predicted seconds of :func:`check_frame` on a frame of ``pixels``: each half reconstructed ``options``
    times at the pilot's measured ``reconstruct_rate`` (seconds per pixel), plus ``extra_per_pixel`` once per
    half (what a slower OIDN setting among them adds over the pilot's), with CHECK_MARGIN."""
    return 2.0 * CHECK_MARGIN * pixels * (options * max(reconstruct_rate, 0.0) + max(extra_per_pixel, 0.0))


def _add(total: dict[str, np.ndarray] | None, sums: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if total is None:
        return {k: np.array(v, dtype=np.float64, copy=True) for k, v in sums.items()}
    for k, v in total.items():
        np.add(v, sums[k], out=v)
    return total


@dataclass
class Option:
    """One reconstruction of the frame (e.g. an OIDN setting) as the check judged it."""

    relmse: float  # the whole frame's, estimated: the halves' estimates carried to its samples, averaged
    halves: list[tuple[int, float, float]]  # per half: samples, estimated RelMSE of its reconstruction, standard error


@dataclass
class Check:
    """The frame's own error estimate, for each reconstruction it was asked to judge."""

    options: dict[str, Option]  # the frame's own reconstruction first
    chosen: str  # the option the frame will be reconstructed with
    #: per other option: its estimate less the first's (averaged over the halves, at the halves' samples, with the
    #: same weights for both) and that difference's standard error
    differences: dict[str, tuple[float, float]]
    exponent: float  # error-vs-spp exponent each half's estimate was carried to the frame's samples with
    seconds: float
    predicted_seconds: float | None = None  # what the render held back for it (None: no deadline)

    @property
    def relmse(self) -> float:
        return self.options[self.chosen].relmse

    def metadata(self) -> dict[str, str]:
        def halves(o: Option) -> list[list[float]]:
            return [[n, float(f"{e:.4g}"), float(f"{s:.3g}")] for n, e, s in o.halves]

        figures: dict[str, Any] = {"halves": halves(self.options[self.chosen])}  # the estimate's, as served
        if len(self.options) > 1:
            figures.update({"options": {k: halves(o) for k, o in self.options.items()}, "chosen": self.chosen,
                            "differences": {k: [float(f"{d:.3g}"), float(f"{e:.3g}")]
                                            for k, (d, e) in self.differences.items()}})
        figures.update({"exponent": round(self.exponent, 3), "seconds": round(self.seconds, 3),
                        "held_seconds": None if self.predicted_seconds is None else round(self.predicted_seconds, 3)})
        return {CHECK_KEY: json.dumps(figures, separators=(",", ":"))}


#: One half of a frame for :func:`check_frame`: its Frame, its samples, and the other half's groups (mean images
#: with their samples: :meth:`Split.batches`).
Half = tuple[Any, int, list[tuple[np.ndarray, int]]]
#: Another option replaces the frame's own reconstruction only when its estimated error is lower by more than
#: this many standard errors of the paired difference.
SWITCH_SE = 2.0


def check_frame(halves: list[Half], spp: int, exponent: float,
                reconstruct: Callable[[Any], np.ndarray] | dict[str, Callable[[Any], np.ndarray]],
                clock: Callable[[], float] = time.perf_counter) -> Check:
    """Estimate the frame's reconstructed RelMSE from its two ``halves``, each reconstructed with ``reconstruct``
    and judged against the other half's groups, then carried to the frame's ``spp`` with ``exponent``. An
    estimate lost in the other half's noise counts as its noise (as the checkpoint's: renderer/checkpoint.py).

    With several reconstructions (``reconstruct`` a dict, the frame's own first), each is judged so, and each
    other one is compared with the first on the same groups with the same weights (the mean of the two
    reconstructions'), where the groups' own noise cancels (renderer.estimate.cross_terms); the lowest of those
    whose difference is below the first's by more than SWITCH_SE standard errors is chosen, else the first."""
    start = clock()
    options = reconstruct if isinstance(reconstruct, dict) else {"": reconstruct}
    images = {k: [np.asarray(fn(frame), dtype=np.float64) for frame, _, _ in halves] for k, fn in options.items()}
    judged: dict[str, Option] = {}
    for k, ims in images.items():
        figures: list[tuple[int, float, float]] = []
        carried: list[float] = []
        for image, (_, n, batches) in zip(ims, halves, strict=True):
            value, se = cross_relmse(image, batches, relative_weights(image))
            figures.append((n, value, se))
            carried.append(at_budget(max(value, se), n, spp, exponent))
        judged[k] = Option(float(np.mean(carried)), figures)
    first = next(iter(options))
    differences: dict[str, tuple[float, float]] = {}
    for k in list(options)[1:]:
        diffs = []
        for a, b, (_, _, batches) in zip(images[k], images[first], halves, strict=True):
            w = relative_weights(0.5 * (a + b))
            diffs.append(cross_terms(a, batches, w) - cross_terms(b, batches, w))
        d = np.concatenate([x.ravel() for x in diffs])
        differences[k] = mean_and_se(d)
    better = [k for k, (d, se) in differences.items() if d < -SWITCH_SE * se]
    chosen = min(better, key=lambda k: differences[k][0]) if better else first
    return Check(judged, chosen, differences, exponent, clock() - start)
