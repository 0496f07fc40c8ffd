"""The equal-time renderers on one scene (:class:`PathRenderer`: Mitsuba ``path`` and its ``aov`` feature pass, our
primal-only and ``--gradients direct`` G-PT renders, the planned row's priors and reconstruction tail), each with
its cost model, and OIDN as the ``path-oidn`` baseline runs it."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from gradsep.evaluation.methods import EQUAL_TIME_OFFSETS
from gradsep.evaluation.timesearch import Attempt, CostModel, SearchRules, TimeSearch
from gradsep.model.frame import FLOAT32_MAX

__all__ = ["MAX_WAVEFRONT", "PathRenderer", "denoise", "sanitise", "split_features"]

MAX_WAVEFRONT = (1 << 32) - 1  # Mitsuba's samples per launch


def sanitise(image: np.ndarray) -> np.ndarray:
    """Finite and >= 0, as model.reconstruct does for its outputs (the combined-model path bypasses it)."""
    out = np.nan_to_num(np.asarray(image, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(out, 0.0, FLOAT32_MAX)


class PathRenderer:
    """The equal-time renderers on one loaded scene, each with its cost model.

    Kinds: ``path`` (Mitsuba ``path``, raw colour), ``features`` (Mitsuba ``aov``: albedo and shading normal
    only, the cheap pass feeding OIDN), ``primal`` (our renderer's primal-only mode, a gradient-free Frame) and
    ``gpt-direct`` (our G-PT renderer, ``--gradients direct``, offsets :data:`EQUAL_TIME_OFFSETS`: a Frame).
    """

    #: Calibration renders grow ×4 from 1 spp until one takes this long: shorter ones are all noise and
    #: overhead on a busy machine.
    CALIBRATION_SECONDS = 0.25
    #: A prediction more than this many times the largest measured spp is probed at a quarter first.
    EXTRAPOLATION = 8
    #: A render is accepted when its measured time is within this fraction of its target.
    TOLERANCE = 0.05
    #: Tries (distinct spp) per row before the one closest to the target is kept.
    MAX_ATTEMPTS = 8
    #: Tries shorter than this are timed REPEATS times and their median used (noise is a larger share of them).
    REPEAT_BELOW = 2.0
    REPEATS = 3

    def __init__(self, loaded: Any) -> None:
        import mitsuba as mi

        self.loaded = loaded
        path = {"type": "path", "max_depth": int(loaded.max_depth), "rr_depth": int(loaded.rr_depth)}
        self.integrators = {
            "path": mi.load_dict(path),
            # albedo and shading normal only (no nested integrator): what a production renderer writes cheaply
            "features": mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal"}),
        }
        self.max_spp = max(1, MAX_WAVEFRONT // max(1, loaded.width * loaded.height))
        self._costs: dict[str, CostModel] = {}
        self._post_seconds: dict[str, float] = {}
        self._warm: set[str] = set()
        self._priors: dict[tuple[str, ...], Any] = {}  # layers -> renderer.passes.Priors (planner_priors)

    def render(self, kind: str, spp: int, seed: int) -> tuple[Any, float]:
        """The raw render (an (H, W, C) float32 array, or a Frame for ``primal``) and its wall seconds (recorded
        in the cost model once calibrated)."""
        start = time.perf_counter()
        if kind == "primal":
            from gradsep.renderer.render import render_frame

            output: Any = render_frame(self.loaded, spp=int(spp), seed=int(seed) % (1 << 32), gradients=False)
        elif kind == "gpt-direct":
            from gradsep.renderer.render import FrameOptions, render_frame

            output = render_frame(self.loaded, spp=int(spp), seed=int(seed) % (1 << 32), gradients="direct",
                                  options=FrameOptions(offsets=EQUAL_TIME_OFFSETS))
        else:
            import mitsuba as mi

            image = mi.render(self.loaded.scene, sensor=self.loaded.sensor, integrator=self.integrators[kind],
                              spp=int(spp), seed=int(seed) % (1 << 32))
            output = np.array(image, dtype=np.float32)
        seconds = time.perf_counter() - start
        if kind in self._costs:
            self._costs[kind].add(spp, seconds)
        return output, seconds

    def warm(self, kind: str) -> None:
        """One untimed 1-spp render: Dr.Jit's kernel compilation, paid once per scene and kind."""
        if kind not in self._warm:
            self.render(kind, 1, 7)
            self._warm.add(kind)

    def planner_tail(self, layers: tuple[str, ...]) -> float:
        """The planned row's reconstruction time on this scene: the slowest of the planner's candidates' default
        reconstructions (model.reconstruct's default for the candidate's frame: ``oidn-l1`` with gradients,
        ``oidn`` for a plain frame; the plan is not known before its pilot), each measured by
        :meth:`post_seconds` on a 1-spp frame of that candidate. Measured once per scene; the first call also
        compiles each candidate's kernel and runs the reconstruction once on the pilot's tile size (one-time
        costs, untimed like every row's)."""
        from gradsep.model.reconstruct import reconstruct
        from gradsep.renderer.checkpoint import tiles
        from gradsep.renderer.passes import Passes, as_frame, crop
        from gradsep.renderer.plans import judged_plans as applicable

        seconds = []
        for c in applicable(layers):
            name = f"gpt-auto:{c.name}"
            if name not in self._post_seconds:
                passes = Passes(self.loaded, layers, seed=29)
                passes.run(c, 1)  # compiles (or loads) the candidate's kernel
                frame = as_frame(passes.frame_result(c))
                reconstruct(crop(frame, tiles(frame.width, frame.height)[0]))  # the pilot's tile size
                self.post_seconds(name, lambda frame=frame: reconstruct(frame))
            seconds.append(self._post_seconds[name])
        return max(seconds)

    def planner_priors(self, layers: tuple[str, ...]) -> Any:
        """What the planned row starts from (renderer.passes.Priors), measured once per scene like every searched
        row's cost model (:meth:`cost`), untimed: each candidate's warm passes, from 1 spp doubling until one takes
        :data:`CALIBRATION_SECONDS` (each size twice, the faster kept; the last two sizes make its cost line), and
        the reconstruction's seconds per pixel (:meth:`planner_tail`'s slowest, over the frame's pixels)."""
        from gradsep.renderer.budget import PassCosts
        from gradsep.renderer.passes import Passes, Priors
        from gradsep.renderer.plans import judged_plans as applicable

        if layers not in self._priors:
            priors = Priors(reconstruct_rate=self.planner_tail(layers) / (self.loaded.width * self.loaded.height),
                            reconstruct_seconds={c.name: self._post_seconds[f"gpt-auto:{c.name}"]
                                                 for c in applicable(layers)})
            for c in applicable(layers):
                passes = Passes(self.loaded, layers, seed=37)
                passes.run(c, 1)  # its kernel (loaded from Dr.Jit's cache: planner_tail compiled it)

                def timed(spp: int, passes: Any = passes, c: Any = c) -> float:
                    start = time.perf_counter()
                    passes.run(c, spp)
                    return time.perf_counter() - start

                sizes = self._calibration(lambda spp: min(timed(spp), timed(spp)), passes.max_spp, growth=2)
                costs = PassCosts(first_pass=passes.kind(c).costs.first_pass)
                for size, took in sizes[-2:]:
                    costs.record(size, took)
                priors.costs[c.name] = costs
            self._priors[layers] = priors
        return self._priors[layers]

    def cost(self, kind: str) -> CostModel:
        """The cost model of ``kind``, measured once per scene after an untimed compile render.

        Each calibration spp is rendered twice and the faster time kept: on a shared machine noise only ever
        adds time. At least two spp are measured, the last taking :data:`CALIBRATION_SECONDS` or more.
        """
        if kind not in self._costs:
            self.warm(kind)
            model = CostModel(self.max_spp)
            for spp, seconds in self._calibration(
                    lambda spp: min(self.render(kind, spp, 11)[1], self.render(kind, spp, 13)[1]), self.max_spp,
                    growth=4):
                model.add(spp, seconds)
            self._costs[kind] = model
        return self._costs[kind]

    def _calibration(self, seconds_at: Callable[[int], float], max_spp: int, growth: int) -> list[tuple[int, float]]:
        """(spp, seconds) of calibration renders (``seconds_at(spp)``, the caller's timing: the faster of two),
        from 1 spp growing ``growth``-fold until one takes :data:`CALIBRATION_SECONDS` or more with two sizes
        measured, or ``max_spp`` is reached."""
        sizes: list[tuple[int, float]] = []
        spp = 1
        while True:
            seconds = seconds_at(spp)
            sizes.append((spp, seconds))
            if (seconds >= self.CALIBRATION_SECONDS and len(sizes) >= 2) or spp >= max_spp:
                return sizes
            spp = min(max_spp, spp * growth)

    def spp_for(self, kind: str, seconds: float) -> int:
        """The spp of ``kind`` that fits ``seconds``; far extrapolations are checked by a render at a quarter of
        the prediction first (its cost is a fraction of the final render's)."""
        model = self.cost(kind)
        spp = model.spp_for(seconds)
        while spp > self.EXTRAPOLATION * model.largest_sampled:
            self.render(kind, max(1, spp // 4), 19)
            spp = model.spp_for(seconds)
        return spp

    def render_within(self, kind: str, seconds: float, seed: int, post: Callable[[Any], Any] | None = None,
                      post_estimate: float = 0.0) -> Attempt:
        """Render ``kind`` (then run ``post`` on the render, e.g. the denoiser) at the spp whose measured time,
        render + ``post``, is within :data:`TOLERANCE` of ``seconds``: :class:`TimeSearch` from the cost line's
        prediction (``post_estimate`` off the budget), with the line's slope. The try closest to the target is
        kept, with the reason when it is still outside the tolerance."""
        first = self.spp_for(kind, max(1e-6, seconds - post_estimate))
        overhead, per_spp = self.cost(kind).fit()
        rules = SearchRules(self.TOLERANCE, self.MAX_ATTEMPTS, self.REPEAT_BELOW, self.REPEATS)
        search = TimeSearch(seconds, per_spp, self.max_spp, overhead=overhead + post_estimate, rules=rules)

        def measure(spp: int) -> tuple[Any, float, float]:
            output, took = self.render(kind, spp, seed)
            start = time.perf_counter()
            result = post(output) if post is not None else output
            return result, took, (time.perf_counter() - start if post is not None else 0.0)

        return search.run(measure, first)

    def post_seconds(self, name: str, run: Callable[[], object]) -> float:
        """The time of a row's fixed post-processing ``run`` (a denoiser call) on this scene's frame size,
        measured once per scene on a warm device (the first call initialises it): the faster of two, as noise
        on a shared machine only adds time."""
        if name not in self._post_seconds:
            run()
            timings = []
            for _ in range(2):
                start = time.perf_counter()
                run()
                timings.append(time.perf_counter() - start)
            self._post_seconds[name] = min(timings)
        return self._post_seconds[name]


def split_features(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """albedo, normal of an ``aov(albedo, sh_normal)`` render: the 6 AOV channels come last (Mitsuba puts
    any film channels, e.g. RGB(A) of a nested integrator, before them)."""
    if image.ndim != 3 or image.shape[-1] < 6:
        raise RuntimeError(f"aov render has shape {image.shape}; expected albedo + normal channels last")
    return np.ascontiguousarray(image[..., -6:-3]), np.ascontiguousarray(image[..., -3:])


def denoise(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Intel Open Image Denoise as model/oidn.py runs it for the ``oidn`` method (one definition): the RT filter
    on HDR input at the method's setting (model.oidn.method_setting: auxiliary images, quality), exact exposure
    scaling: the baseline is OIDN as its users run it."""
    from gradsep.model.frame import Features
    from gradsep.model.oidn import method_setting, shared_denoiser

    denoiser = shared_denoiser(method_setting())
    aux = denoiser.prefilter(Features(np.ascontiguousarray(albedo, np.float32),
                                      np.ascontiguousarray(normal, np.float32),
                                      np.zeros(color.shape[:2], np.float32)))
    return sanitise(denoiser.denoise(np.ascontiguousarray(color, np.float32), aux))
