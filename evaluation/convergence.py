"""Raising a scene's references until their floor is under FLOOR_FRACTION of the smallest RelMSE the report
ranks: full passes (doubled, within the time budget) and then region passes where the floor lives
(evaluation/region.py)."""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from gradsep.evaluation.config import FLOOR_FRACTION, EvalConfig
from gradsep.evaluation.references import RAISE_MARGIN, ReferencePair, ReferenceSource, next_reference_spp, within_time
from gradsep.evaluation.results import SceneRun
from gradsep.evaluation.scores import LOG_INTERPOLATED, Output
from gradsep.evaluation.timesearch import interpolate_at

__all__ = ["RunLog", "converge_references"]


class RunLog(Protocol):
    """What raising the references reads of the run: its configuration and its log."""

    config: EvalConfig

    def log(self, text: str) -> None: ...


def _smallest_ranked(outputs: list[Output], pair: ReferencePair) -> float:
    """The smallest RelMSE (product estimator) over every row of the scene: each one is ranked by the report."""
    from gradsep.model.metrics import relmse_unbiased

    def relmse(image: np.ndarray) -> float:
        return relmse_unbiased(image, pair.first["total"], pair.second["total"])

    def ranked(o: Output) -> float:  # the figure the report shows: a multi-seed row's mean over its seeds
        return float(np.mean([one(r) for r in (o, *o.replicas)]))

    def one(o: Output) -> float:  # interpolated as interpolated_scores does
        interpolation = o.interpolation()
        if interpolation is None:
            return relmse(o.image)
        target, low, high = interpolation
        return interpolate_at(target, (low.total_seconds, relmse(low.image)), (high.total_seconds, relmse(high.image)),
                              log_value="relmse" in LOG_INTERPOLATED)

    values = [ranked(o) for o in outputs]
    return min(values) if values else math.inf


def converge_references(runner: RunLog, scene: SceneRun, source: ReferenceSource,
                         outputs: list[Output]) -> ReferencePair:
    """Raise both references (cached passes re-used) until the total floor is under FLOOR_FRACTION of the
    smallest ranked RelMSE: full passes up to the spp cap and the time budget, then region passes
    (:func:`_add_region_passes`); record the outcome on ``scene``."""
    config = runner.config
    spp = config.ref_spp
    while True:
        pair = source.pair(spp)
        floor = pair.floor()
        smallest = _smallest_ranked(outputs, pair)
        following = next_reference_spp(spp, floor, smallest, FLOOR_FRACTION, config.reference_cap,
                                       step=config.ref_spp)
        if following is not None and config.ref_seconds is not None:
            following = within_time(spp, following, pair.seconds, config.ref_seconds, step=config.ref_spp,
                                     to_render=source.passes_to_render)
        if following is None:
            break
        runner.log(f"{scene.entry.name}: reference floor {floor:.3g} at {spp} spp is over "
                   f"{FLOOR_FRACTION:.0%} of the smallest ranked RelMSE {smallest:.3g}; raising to {following} spp")
        spp = following
    full_seconds = pair.seconds
    region_stop = ""
    raising = config.reference_cap > config.ref_spp  # a fixed reference spp (cap = start) is never raised
    if raising and not (smallest > 0 and pair.floor() <= FLOOR_FRACTION * smallest):
        pair, smallest, region_stop = _add_region_passes(runner, scene, source, pair, smallest, outputs)
    scene.reference = pair.mean()
    scene.reference_spp = spp
    scene.reference_region = pair.region.as_list() if pair.region is not None else None
    scene.region_spp = pair.region_spp
    scene.floor = {layer: pair.floor(layer) for layer in pair.first}
    scene.smallest = smallest
    scene.capped = not (smallest > 0 and scene.floor["total"] <= FLOOR_FRACTION * smallest)
    if scene.capped:
        full_stop = _full_stop_reason(config, spp, full_seconds)
        scene.cap_reason = full_stop + (f"; {region_stop}" if region_stop else "")
    scene.reference_seconds = pair.seconds
    return pair


def _full_stop_reason(config: EvalConfig, spp: int, seconds: float) -> str:
    """Why the full passes stopped at ``spp`` (only read when the floor criterion is not met)."""
    if spp >= config.reference_cap or config.ref_seconds is None:
        return f"the spp cap ({config.reference_cap} spp each)"
    return (f"the time budget ({config.ref_seconds:g} s of new reference rendering per scene; "
            f"{2 * spp} spp were recorded at {seconds:.0f} s)")


def _add_region_passes(runner: RunLog, scene: SceneRun, source: ReferenceSource, pair: ReferencePair,
                       smallest: float, outputs: list[Output]) -> tuple[ReferencePair, float, str]:
    """Where the full passes stopped with the floor over FLOOR_FRACTION of the smallest ranked RelMSE: region
    passes over the rectangle the pilot places (evaluation/region.py), as many as the floor inside it is
    predicted to need (it falls as 1 / the spp there; :data:`RAISE_MARGIN` more), at most the spp cap more per
    reference, and within what is left of the time budget (pilot included; cached passes cost nothing).
    ``smallest`` is the smallest ranked RelMSE against ``pair``. Returns the pair, the smallest ranked RelMSE
    against it, and why the passes stopped short (or "")."""
    config = runner.config
    base, spp = config.ref_spp, pair.spp
    per_pass = pair.seconds / (2 * spp / base) if pair.seconds > 0 else math.nan  # one full pass, recorded
    budget = config.ref_seconds
    pilots = source.pilot_passes_to_render()
    if budget is not None and pilots:
        pilot_cost = pilots * per_pass
        if not pilot_cost <= budget - source.rendered_seconds:  # NaN (no timing recorded) does not fit either
            return pair, smallest, "no region passes: their pilot does not fit the time budget"
    region = source.region()
    fraction = region.fraction(scene.width, scene.height)
    cap = config.reference_cap // base
    count = 0
    while True:
        target = FLOOR_FRACTION * smallest
        floor = pair.floor()
        if smallest > 0 and floor <= target:
            return pair, smallest, ""
        outside, inside = pair.floor_split(region)
        goal = target / RAISE_MARGIN - outside
        if smallest > 0 and goal > 0 and inside > 0:
            wanted = math.ceil(((spp + count * base) * inside / goal - spp) / base)
        else:
            wanted = cap  # the rectangle alone cannot reach the target: as far as the cap allows
        wanted = min(cap, max(wanted, count + 1))
        if wanted <= count:
            return pair, smallest, f"region passes at their cap ({cap * base} spp more each in {region.describe()})"
        if budget is not None:
            per_region = per_pass * fraction if math.isfinite(per_pass) else math.nan
            left = budget - source.rendered_seconds
            missing = np.cumsum([not cached for cached in source.region_cached(wanted)])  # per pass, both refs
            while wanted > count and not (missing[2 * wanted - 1] == 0 or missing[2 * wanted - 1] * per_region <= left):
                wanted -= 1
            if wanted <= count:
                return pair, smallest, (f"region passes stopped by the time budget at {count * base} spp more "
                                        f"each in {region.describe()}")
        runner.log(f"{scene.entry.name}: reference floor {floor:.3g} ({inside:.3g} inside {region.describe()}) is "
                   f"over {FLOOR_FRACTION:.0%} of the smallest ranked RelMSE {smallest:.3g}; "
                   f"{wanted * base} spp more each there")
        count = wanted
        pair = source.pair(spp, count)
        smallest = _smallest_ranked(outputs, pair)
