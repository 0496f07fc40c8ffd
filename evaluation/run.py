"""`gradsep evaluate`: error against run time for every method, the paper's Table 1 and Fig. 7 ablation, plots.

One command renders (or takes from the cache) G-PT frames at each spp and two independent references per scene,
runs every method of evaluation/methods.py on each frame, scores it (RelMSE with the references' noise removed
by the product estimator, SSIM, PSNR, HDR-FLIP against the references' mean; model/metrics.py) and writes into
the report folder:

* ``results.csv`` -- one row per (scene, method, spp) with render/reconstruction/total seconds and the metrics;
  ``results.json`` -- the same rows plus the configuration, machine, models, references and skipped methods;
* ``plots/<scene>.png`` -- RelMSE against total wall time, log-log, one curve per method (equal-time view);
* ``crops/<scene>.png`` -- the crop comparison of the paper's Fig. 6;
* ``report.md`` -- Table 1, the Fig. 7 ablation, the equal-time comparison, where ours loses, the reference
  floors, how it was made.

Per scene: every method's output first (cached without reference: a method's image does not depend on it), then
the references are raised until their floor is under 10 % of the scene's smallest ranked RelMSE (or the cap),
then everything is scored (scores cached per output and reference pair). The protocol is in docs/evaluation.md.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.evaluation.baselines import PathRenderer
from gradsep.evaluation.cache import EvalCache, file_sha256, key_hash, sources_sha256
from gradsep.evaluation.config import FLOOR_FRACTION, EvalConfig, SceneEntry, crop_methods, resolve_scenes
from gradsep.evaluation.methods import (
    EQUAL_TIME_KINDS,
    METHOD_SOURCES,
    PLAN_ROW_KEYS,
    PLANNER_SOURCES,
    BracketOutput,
    MethodOutput,
    MethodSpec,
    method_by_name,
    unavailable,
)
from gradsep.evaluation.references import (
    RAISE_MARGIN,
    REFERENCE_SAMPLER,
    ReferencePair,
    ReferenceSource,
    next_reference_spp,
)
from gradsep.evaluation.region import Region
from gradsep.evaluation.results import Evaluation, SceneRun, machine_summary, row_seconds
from gradsep.evaluation.runners import MethodContext, NetworkPool, run_method
from gradsep.evaluation.timesearch import interpolate_at
from gradsep.model.errors import CommandError
from gradsep.model.methods import get as table_method
from gradsep.model.policy import SEPARATED_LAYERS
from gradsep.model.progress import ProgressBar

__all__ = ["Evaluation", "SceneRun", "machine_summary", "run_evaluation"]

#: The code that renders a frame / a reference pass (by code, evaluation.cache.code_sha256). Not
#: renderer/procedural.py: a procedural scene is keyed by its seed, family and GENERATOR_VERSION (evaluation.config),
#: which tests/renderer/test_procedural.py's pinned fingerprints hold to the generator's output.
RENDERER_SOURCES = ("renderer/gpt.py", "renderer/shift.py", "renderer/render.py", "renderer/scene.py",
                    "renderer/variant.py", "model/policy.py")
REFERENCE_SOURCES = ("renderer/reference.py", "renderer/scene.py", "renderer/variant.py")
RESULT_FORMAT = 3  # bump when the cached output/score JSON changes shape
SCORE_SOURCES = ("model/metrics.py", "evaluation/run.py")


# ---------------------------------------------------------------------------------------------- the run


def _derived_seed(*parts: int) -> int:
    """A 32-bit seed from integers (distinct runs, spp and purposes never share sampler streams)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, dtype=np.uint32)[0])


@dataclass
class _Output:
    """One method's output on one (scene, spp): the row without scores, its images, its cache key hash."""

    spec: MethodSpec
    spp: int
    row: dict[str, Any]
    image: np.ndarray
    layers: dict[str, np.ndarray]
    tag: str
    bracket: list[BracketOutput] = field(default_factory=list)  # see MethodOutput.bracket
    #: The same equal-time row rendered with the other ``--time-seeds`` seeds (each its own time search), or the
    #: same fixed-spp method on the other ``--frame-seeds`` frames; the row's metrics are the mean over this
    #: output and these (:func:`seed_mean`).
    replicas: list[_Output] = field(default_factory=list)

    def interpolation(self) -> tuple[float, BracketOutput, BracketOutput] | None:
        """(budget, too-fast try, too-slow try) when this row's metrics are interpolated to its budget, else None."""
        target = self.row.get("target_seconds")
        if len(self.bracket) != 2 or not target:
            return None
        return float(target), self.bracket[0], self.bracket[1]


#: Metrics interpolated in log value (errors: a power of time is a line in log-log); the others (SSIM, PSNR,
#: already a logarithm) linearly in value. Both in log time.
LOG_INTERPOLATED = ("relmse", "flip", *(f"relmse_{layer}" for layer in SEPARATED_LAYERS))


class _Runner:
    """Runs the evaluation scene by scene; holds the cache, the loaded networks and the counters."""

    def __init__(self, config: EvalConfig, progress: bool | None, log: Callable[[str], None]) -> None:
        self.config = config
        self.cache = EvalCache(config.cache_dir / "evaluate")
        self.networks = NetworkPool()
        self.log = log
        self.progress = progress
        self.computed = {"frames": 0, "references": 0, "results": 0}
        self.model_shas: dict[str, str] = {}
        self.skipped: dict[str, list[str]] = {}  # method -> reasons
        self.missing: dict[str, list[str]] = {}  # method -> missing model files
        self._warm_scenes: set[tuple[int, str]] = set()
        self.renderer_code = sources_sha256(RENDERER_SOURCES)
        self.reference_code = sources_sha256(REFERENCE_SOURCES)
        self.method_code = sources_sha256(METHOD_SOURCES)
        self.planner_code = sources_sha256(PLANNER_SOURCES)
        self.score_code = sources_sha256(SCORE_SOURCES)

    # ------------------------------------------------------------------------------------------ models

    def _model_sha(self, relative: str) -> str | None:
        path = self.config.models_dir / relative
        if not path.is_file():
            return None
        if relative not in self.model_shas:
            self.model_shas[relative] = file_sha256(path)
        return self.model_shas[relative]

    def model_files(self, spec: MethodSpec, layers: tuple[str, ...]) -> tuple[dict[str, str], list[str]]:
        """(relative file -> sha256 of every model ``spec`` needs for ``layers``, the missing files' paths)."""
        shas: dict[str, str] = {}
        missing = []
        for name in spec.model_names(layers):
            relative = str(Path(spec.models or "") / f"{name}.onnx")
            sha = self._model_sha(relative)
            if sha is None:
                missing.append(str(self.config.models_dir / relative))
            else:
                shas[relative] = sha
        for relative in spec.optional_model_files(layers):  # read when present (fused's clean-layer average)
            sha = self._model_sha(relative)
            if sha is not None:
                shas[relative] = sha
        return shas, missing

    def skip(self, method: str, reasons: Iterable[str]) -> None:
        """Record a skipped method and why (the union over scenes is reported)."""
        known = self.skipped.setdefault(method, [])
        known.extend(r for r in reasons if r not in known)

    def skip_missing(self, method: str, missing: Iterable[str]) -> None:
        """Record a method skipped for want of model files: one "not found" reason listing every file."""
        files = self.missing.setdefault(method, [])
        files.extend(f for f in missing if f not in files)
        known = [r for r in self.skipped.get(method, []) if not r.startswith("not found: ")]
        self.skipped[method] = [*known, "not found: " + ", ".join(files)]

    # -------------------------------------------------------------------------------------- references

    def release_scene(self) -> None:
        """Forget the scene just evaluated (its kernels' warm-up marks, keyed by the loaded scene's id, which a later
        scene may reuse) and free its objects."""
        self._warm_scenes.clear()
        gc.collect()

    def references(self, entry: SceneEntry, loaded: Any) -> ReferenceSource:
        """The scene's reference passes (cached); see evaluation/references.py."""
        from gradsep.evaluation.region import render_region
        from gradsep.renderer.reference import render_loaded

        c = self.config
        # The sampler is in the key by name (not only through the reference code's hash), so a cache rendered
        # with another sampler is never mixed into these references.
        key = {"scene": entry.identity, "size": [loaded.width, loaded.height], "max_depth": loaded.max_depth,
               "seed": c.seed, "code": self.reference_code, "mitsuba": _mitsuba_id(), "sampler": REFERENCE_SAMPLER}

        def render_pass(spp: int, seed: int) -> Any:
            self.computed["references"] += 1
            return render_loaded(loaded, spp=spp, seed=seed, tile_spp=None, sampler=REFERENCE_SAMPLER,
                                 progress=False if self.progress is False else None)

        def render_crop(region: Region, spp: int, seed: int) -> Any:
            self.computed["references"] += 1
            return render_region(loaded, region, spp=spp, seed=seed, sampler=REFERENCE_SAMPLER)

        return ReferenceSource(self.cache, entry.name, key, c.ref_spp, render_pass, self.log, render_crop)

    # ------------------------------------------------------------------------------------------ frames

    def frame(self, entry: SceneEntry, loaded: Any, spp: int, gradients: str = "all",
              replica: int = 0) -> tuple[Any, float, str]:
        """The G-PT frame at ``spp`` in render mode ``gradients`` (``all`` or ``direct``: renderer.render), its
        render seconds and cache key hash (rendered when not cached). Both modes use the same seed, so the
        ``direct`` frame's direct layer is the ``all`` frame's and its indirect base the same primal.
        ``replica`` k > 0: the k-th extra frame of ``--frame-seeds``, rendered with its own seed."""
        from gradsep.model.frame import FrameError, read_frame, write_frame
        from gradsep.renderer.render import render_frame
        from gradsep.renderer.shift import DEFAULT_SHIFT

        seed = _derived_seed(self.config.seed, 2, spp, *((replica,) if replica else ()))
        key = {"kind": "gpt-frame", "scene": entry.identity, "size": [loaded.width, loaded.height],
               "max_depth": loaded.max_depth, "spp": spp, "seed": seed, "shift": DEFAULT_SHIFT,
               "gradients": gradients, "code": self.renderer_code, "mitsuba": _mitsuba_id()}
        mode = "" if gradients == "all" else f"-{gradients}"
        stem = (f"{loaded.width}x{loaded.height}-d{loaded.max_depth}-spp{spp}-seed{self.config.seed}{mode}"
                + (f"-r{replica}" if replica else ""))
        path = self.cache.entry("frames", entry.name, stem, key, ".exr")
        tag = key_hash(key)
        if path.is_file():
            try:
                frame = read_frame(str(path), nonfinite="zero")
                seconds = float(frame.metadata.get("gradsep.render_seconds", "nan"))
                if frame.metadata.get("gradsep.eval_key") == tag and math.isfinite(seconds):
                    return frame, seconds, tag
            except (FrameError, ValueError):
                pass
            self.log(f"cache entry {path} unreadable; re-rendering the frame")
        if (id(loaded), gradients) not in self._warm_scenes:  # the first render of a kernel pays its compilation
            render_frame(loaded, spp=1, seed=_derived_seed(self.config.seed, 4, 0), gradients=gradients)
            self._warm_scenes.add((id(loaded), gradients))
        frame = render_frame(loaded, spp=spp, seed=seed, gradients=gradients)
        seconds = float(frame.metadata["gradsep.render_seconds"])
        frame.metadata["gradsep.eval_key"] = tag
        path.parent.mkdir(parents=True, exist_ok=True)
        write_frame(path, frame)
        self.computed["frames"] += 1
        return frame, seconds, tag

    # ----------------------------------------------------------------------------------------- outputs

    def output(self, spec: MethodSpec, scene: SceneRun, spp: int, ctx: MethodContext,
               key: dict[str, Any], replica: int = 0) -> _Output:
        """One method's output on one (scene, spp), from the cache when possible (it does not depend on the
        references, so raising them re-scores without re-running anything). ``replica`` k > 0: the k-th extra
        seed of an equal-time row (``--time-seeds``) or the method on the k-th extra frame (``--frame-seeds``):
        the key tells them apart."""
        c = self.config
        stem = f"{spec.name}-{scene.width}x{scene.height}-spp{spp}-seed{c.seed}" + (f"-r{replica}" if replica else "")
        path = self.cache.entry("results", scene.entry.name, stem, key, ".json")
        tag = key_hash(key)
        cached = self.cache.load_json(path)
        if cached is not None and cached.get("key") == key and isinstance(cached.get("row"), dict):
            brackets = cached.get("bracket", [])
            names = ["image", *cached.get("layers", [])]
            names += [f"bracket{i}{suffix}" for i, b in enumerate(brackets)
                      for suffix in ("", *(f".{n}" for n in b["layers"]))]
            arrays = self.cache.load_arrays(path.with_suffix(".npz"), names)
            if arrays is not None:
                layers = {n: arrays[n] for n in cached.get("layers", [])}
                bracket = [BracketOutput(int(b["spp"]), float(b["render_seconds"]), float(b["reconstruct_seconds"]),
                                         arrays[f"bracket{i}"], {n: arrays[f"bracket{i}.{n}"] for n in b["layers"]})
                           for i, b in enumerate(brackets)]
                return _Output(spec, spp, {**cached["row"], "scene": scene.entry.name}, arrays["image"], layers, tag,
                               bracket)
        out: MethodOutput = run_method(spec, ctx)
        for warning in out.warnings:
            self.log(f"{scene.entry.name} {spec.name} {spp} spp: {warning}")
        row: dict[str, Any] = {
            "scene": scene.entry.name, "method": spec.name, "spp": spp, "method_spp": out.method_spp,
            "width": scene.width, "height": scene.height,
            "render_seconds": out.render_seconds, "reconstruct_seconds": out.reconstruct_seconds,
            "total_seconds": out.render_seconds + out.reconstruct_seconds, "gradients": spec.gradients,
        }
        row.update({k: v for k, v in out.extra.items()
                    if k in ("target_seconds", "budget_method", "capped", "attempts", "feature_spp",
                             "time_search", "time_tries", "time_note", "gradients", *PLAN_ROW_KEYS)})
        row["machine"] = machine_summary()
        layers = {n: out.layers[n] for n in SEPARATED_LAYERS if n in out.layers}
        arrays = {"image": out.image, **layers}
        brackets = []
        for i, b in enumerate(out.bracket):
            kept = [n for n in SEPARATED_LAYERS if n in b.layers]
            arrays[f"bracket{i}"] = b.image
            arrays.update({f"bracket{i}.{n}": b.layers[n] for n in kept})
            brackets.append({"spp": b.spp, "render_seconds": b.render_seconds,
                             "reconstruct_seconds": b.reconstruct_seconds, "layers": kept})
        if brackets:
            row["time_bracket"] = [{"spp": b["spp"], "total_seconds": b["render_seconds"] + b["reconstruct_seconds"]}
                                   for b in brackets]
        self.cache.save_arrays(path.with_suffix(".npz"), arrays)
        self.cache.save_json(path, {"format": RESULT_FORMAT, "key": key, "row": row, "layers": list(layers),
                                    "bracket": brackets})
        self.computed["results"] += 1
        return _Output(spec, spp, row, out.image, layers, tag, list(out.bracket))

    def row(self, output: _Output, scene: SceneRun, pair: ReferencePair) -> dict[str, Any]:
        """The output's report row: its own row and scores, or with replicas (``--time-seeds``,
        ``--frame-seeds``) the mean over the seeds (:func:`seed_mean`)."""
        if not output.replicas:
            return {**output.row, **self.score(output, scene, pair)}
        return seed_mean([{**o.row, **self.score(o, scene, pair)} for o in (output, *output.replicas)])

    def score(self, output: _Output, scene: SceneRun, pair: ReferencePair) -> dict[str, Any]:
        """The output's metrics against the pair (:func:`image_scores`; an equal-time row with a bracket:
        :func:`interpolated_scores`). Cached per (output, pair)."""
        key = {"format": RESULT_FORMAT, "output": output.tag, "references": pair.tag, "code": self.score_code}
        path = self.cache.entry("scores", scene.entry.name, f"{output.spec.name}-spp{output.spp}", key, ".json")
        cached = self.cache.load_json(path)
        if cached is not None and cached.get("key") == key and isinstance(cached.get("scores"), dict):
            return cached["scores"]
        interpolation = output.interpolation()
        if interpolation is not None:
            target, low, high = interpolation
            scores = interpolated_scores(target, [low, high], pair)
        else:
            scores = image_scores(output.image, output.layers, pair)
        self.cache.save_json(path, {"key": key, "scores": scores})
        return scores


def image_scores(image: np.ndarray, layers: dict[str, np.ndarray], pair: ReferencePair) -> dict[str, Any]:
    """RelMSE (total and per layer) by the product estimator; SSIM, PSNR and FLIP against the pair's mean."""
    from gradsep.model.metrics import flip, psnr, relmse_unbiased, ssim

    mean = pair.mean()
    scores: dict[str, Any] = {"relmse": relmse_unbiased(image, pair.first["total"], pair.second["total"]),
                              "ssim": ssim(image, mean), "psnr": psnr(image, mean), "flip": flip(image, mean)}
    for layer in SEPARATED_LAYERS:
        have = layer in layers and layer in pair.first
        scores[f"relmse_{layer}"] = (relmse_unbiased(layers[layer], pair.first[layer], pair.second[layer])
                                     if have else None)
    return scores


def interpolated_scores(target: float, bracket: list[BracketOutput], pair: ReferencePair) -> dict[str, Any]:
    """An equal-time row that no spp could bring within the tolerance (one sample costs more than 5 % of the
    budget, or the timings were too noisy): every metric of its two bracketing tries, interpolated to the budget
    ``target`` in log time (errors in log value, :data:`LOG_INTERPOLATED`). ``time_interpolated`` says between
    what it was interpolated."""
    low, high = bracket
    sides = [image_scores(b.image, b.layers, pair) for b in bracket]
    scores: dict[str, Any] = {}
    for name, v0 in sides[0].items():
        v1 = sides[1][name]
        if v0 is None or v1 is None or not (math.isfinite(v0) and math.isfinite(v1)):
            scores[name] = v0 if abs(target - low.total_seconds) <= abs(target - high.total_seconds) else v1
            continue
        scores[name] = interpolate_at(target, (low.total_seconds, float(v0)), (high.total_seconds, float(v1)),
                                      log_value=name in LOG_INTERPOLATED)
    scores["time_interpolated"] = (f"{low.spp} spp ({low.total_seconds:.3g} s, RelMSE {sides[0]['relmse']:.4g}) and "
                                   f"{high.spp} spp ({high.total_seconds:.3g} s, RelMSE {sides[1]['relmse']:.4g})")
    return scores


#: Metrics a multi-seed row averages (the others are the first seed's, with the per-seed values beside them).
SEED_MEAN_METRICS = ("relmse", "ssim", "psnr", "flip", *(f"relmse_{layer}" for layer in SEPARATED_LAYERS))


def seed_mean(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One row from the same row rendered with several seeds (an equal-time row's ``--time-seeds``, each its own
    time search; a fixed-spp row's ``--frame-seeds``, each its own G-PT frame; every row already scored): every
    metric of :data:`SEED_MEAN_METRICS` is the mean over the seeds (None when
    a seed has none), the time the mean of the seeds' times (:func:`row_seconds`: the budget for a seed
    interpolated to it), ``method_spp`` the seeds' median. ``seeds``, ``seed_relmse``, ``seed_spp`` and
    ``seed_seconds`` keep the seeds' own values, ``relmse_stderr`` the standard error of the mean RelMSE (sample
    standard deviation / √seeds). A seed interpolated to the budget is named in ``time_interpolated``. The planned
    row (``gpt-auto``) also keeps each seed's ``seed_plan``, ``seed_predicted_relmse`` and ``seed_predicted_note``;
    its ``plan`` is the seeds' plans (``primal/all`` where they differ), its ``predicted_relmse`` their mean (None
    when a seed has none), like its RelMSE."""
    import statistics

    first = rows[0]
    out = dict(first)
    for name in SEED_MEAN_METRICS:
        values = [r.get(name) for r in rows]
        out[name] = (float(np.mean([float(v) for v in values]))
                     if all(v is not None and math.isfinite(float(v)) for v in values) else None)
    seconds = [row_seconds(r) for r in rows]
    relmse = [float(r["relmse"]) for r in rows]
    out.update({"seeds": len(rows), "seed_relmse": relmse, "seed_spp": [int(r["method_spp"]) for r in rows],
                "seed_seconds": seconds, "total_seconds": float(np.mean(seconds)),
                "render_seconds": float(np.mean([float(r["render_seconds"]) for r in rows])),
                "reconstruct_seconds": float(np.mean([float(r["reconstruct_seconds"]) for r in rows])),
                "method_spp": int(statistics.median_low([int(r["method_spp"]) for r in rows])),
                "relmse_stderr": statistics.stdev(relmse) / math.sqrt(len(rows)) if len(rows) > 1 else 0.0})
    if any("plan" in r for r in rows):  # the planned row: each seed's own plan and prediction
        predicted = [r.get("predicted_relmse") for r in rows]
        out.update({"seed_plan": [r.get("plan") for r in rows], "seed_predicted_relmse": predicted,
                    "seed_predicted_note": [r.get("predicted_note") for r in rows],
                    "plan": "/".join(dict.fromkeys(str(r.get("plan")) for r in rows)),
                    "predicted_relmse": (float(np.mean(predicted)) if all(p is not None for p in predicted)
                                         else None)})
    interpolated = [f"seed {k}: {r['time_interpolated']}" for k, r in enumerate(rows) if r.get("time_interpolated")]
    out.pop("time_interpolated", None)
    out.pop("time_bracket", None)
    if interpolated:
        out["time_interpolated"] = "; ".join(interpolated)
    return out


_MITSUBA: str | None = None


def _mitsuba_id() -> str:
    """Mitsuba version + variant: a different build may sample differently, so it is part of render keys."""
    global _MITSUBA
    if _MITSUBA is None:
        import mitsuba as mi

        from gradsep.renderer.scene import select_variant

        _MITSUBA = f"{mi.__version__}/{select_variant()}"
    return _MITSUBA


def _budget_method(rows: dict[str, dict[str, Any]]) -> str | None:
    """The method whose total time is the equal-time budget: the product's default for a G-PT frame (the first
    of the methods table's default preference that ran; its ``network`` is the evaluation's ``ours``; None: the
    G-PT render alone)."""
    from gradsep.evaluation.methods import evaluation_name
    from gradsep.model import methods as table

    for method in table.default_preference():
        name = evaluation_name(method)
        if name in rows:
            return name
    return None


def run_evaluation(config: EvalConfig, *, progress: bool | None = None,
                   log: Callable[[str], None] | None = None) -> Evaluation:
    """Run the whole evaluation and write every output into ``config.output``; see the module docstring."""
    from gradsep.renderer.scene import load_scene

    entries, notes = resolve_scenes(config.scenes)
    _prepare_output(config.output)
    methods = [method_by_name(name) for name in config.methods]
    total = len(entries) * (2 + len(config.spp) * (1 + len(methods)))
    bar = ProgressBar(total, enabled=progress, desc="evaluate", unit="step")
    runner = _Runner(config, progress, log or bar.write)
    try:
        runner.cache.prepare()
    except OSError as exc:
        raise CommandError(f"cache folder {str(runner.cache.root)!r} cannot be created: {exc.strerror or exc}") from exc
    # every scene is loaded (and so validated) before anything renders, since a typo in the last scene should not
    # surface after an hour of work on the first ones; then released, and each loaded again for its own work only: a
    # loaded scene's objects stay registered with Dr.Jit, and every render traces its virtual calls over all of them
    # (a small G-PT pass is several times slower with other scenes loaded than alone)
    for e in entries:
        load_scene(e.spec, width=config.width, height=config.height, max_depth=config.max_depth)
    gc.collect()
    rows: list[dict[str, Any]] = []
    scenes: list[SceneRun] = []
    try:
        for entry in entries:
            loaded = load_scene(entry.spec, width=config.width, height=config.height, max_depth=config.max_depth)
            scene, scene_rows = _run_scene(runner, entry, loaded, methods, bar)
            scenes.append(scene)
            rows += scene_rows
            del loaded
            runner.release_scene()
    finally:
        bar.close()
    evaluation = Evaluation(config, rows, scenes, runner.skipped, dict(sorted(runner.model_shas.items())),
                            notes, runner.computed)
    from gradsep.evaluation.report import write_outputs

    evaluation.outputs = write_outputs(evaluation)
    return evaluation


def _run_scene(runner: _Runner, entry: SceneEntry, loaded: Any, methods: list[MethodSpec],
               bar: ProgressBar) -> tuple[SceneRun, list[dict[str, Any]]]:
    """One scene: every method's output, then references raised until the floor criterion holds, then scores."""
    from gradsep.model.frame import SEPARATED_LAYERS
    from gradsep.renderer.render import plan_layers

    config = runner.config
    layers, _ = plan_layers(SEPARATED_LAYERS, loaded.max_depth)
    scene = SceneRun(entry, loaded.width, loaded.height, loaded.max_depth, layers,
                     np.zeros((loaded.height, loaded.width, 3), np.float32))
    cell: list[PathRenderer] = []

    def get_path() -> PathRenderer:
        if not cell:
            cell.append(PathRenderer(loaded))
        return cell[0]

    outputs: list[_Output] = []
    for spp in config.spp:
        bar.describe(f"{entry.name}: G-PT {spp} spp")
        frames = {"all": runner.frame(entry, loaded, spp)}
        bar.update()
        done: dict[str, dict[str, Any]] = {}
        keys: dict[str, str] = {}
        for spec in methods:
            bar.describe(f"{entry.name} {spp} spp: {spec.name}")
            if spec.gradients not in frames and unavailable(spec) is None:
                frames[spec.gradients] = runner.frame(entry, loaded, spp, spec.gradients)
            frame, seconds, frame_tag = frames.get(spec.gradients, frames["all"])
            out = _evaluate_one(runner, spec, scene, spp, frame, seconds, frame_tag, get_path, done, keys)
            if out is not None:
                if spec.kind not in EQUAL_TIME_KINDS:  # --frame-seeds: the method on the other frames too
                    for k in range(1, config.frame_seeds):
                        extra = runner.frame(entry, loaded, spp, spec.gradients, replica=k)
                        more = _evaluate_one(runner, spec, scene, spp, *extra, get_path, done, keys, replica=k)
                        if more is not None:
                            out.replicas.append(more)
                outputs.append(out)
            bar.update()
    bar.describe(f"{entry.name}: references")
    pair = _converge_references(runner, scene, runner.references(entry, loaded), outputs)
    bar.update()
    bar.describe(f"{entry.name}: scoring")
    rows = []
    for out in outputs:
        rows.append(runner.row(out, scene, pair))
        if out.spp == config.crop_spp and out.spec.name in crop_methods():
            scene.crop_images[out.spec.name] = out.image
    bar.update()
    return scene, rows


def _smallest_ranked(outputs: list[_Output], pair: ReferencePair) -> float:
    """The smallest RelMSE (product estimator) over every row of the scene: each one is ranked by the report."""
    from gradsep.model.metrics import relmse_unbiased

    def relmse(image: np.ndarray) -> float:
        return relmse_unbiased(image, pair.first["total"], pair.second["total"])

    def ranked(o: _Output) -> float:  # the figure the report shows: a multi-seed row's mean over its seeds
        return float(np.mean([one(r) for r in (o, *o.replicas)]))

    def one(o: _Output) -> float:  # interpolated as interpolated_scores does
        interpolation = o.interpolation()
        if interpolation is None:
            return relmse(o.image)
        target, low, high = interpolation
        return interpolate_at(target, (low.total_seconds, relmse(low.image)), (high.total_seconds, relmse(high.image)),
                              log_value="relmse" in LOG_INTERPOLATED)

    values = [ranked(o) for o in outputs]
    return min(values) if values else math.inf


def _converge_references(runner: _Runner, scene: SceneRun, source: ReferenceSource,
                         outputs: list[_Output]) -> ReferencePair:
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
            following = _within_time(spp, following, pair.seconds, config.ref_seconds, step=config.ref_spp,
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


def _add_region_passes(runner: _Runner, scene: SceneRun, source: ReferenceSource, pair: ReferencePair,
                       smallest: float, outputs: list[_Output]) -> tuple[ReferencePair, float, str]:
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


def _within_time(spp: int, wanted: int, seconds: float, budget: float, step: int | None = None,
                 to_render: Callable[[int], int] | None = None) -> int | None:
    """The largest spp up to ``wanted`` whose new rendering (both references) is predicted to fit ``budget``
    seconds: a power-of-two multiple of ``spp`` (``step`` None) or a multiple of ``step`` (the pass spp); None
    when nothing above ``spp`` fits. Render time is predicted linearly in spp from the ``seconds`` the current
    ``spp`` took. With ``to_render`` (spp -> passes of that level not in the cache yet, ``step`` given), only
    those count: passes already cached (a farm's shards, an earlier run) cost this run nothing, whatever time
    they were recorded with; without it every pass above the current ``spp`` is new."""
    if not (seconds > 0 and math.isfinite(seconds)):
        return wanted  # no timing recorded: the spp cap alone decides
    if step is not None:
        per_pass = seconds / (2 * spp / step)  # both references: two passes per step
        level = wanted // step * step
        while level > spp:
            new = to_render(level) if to_render is not None else 2 * (level - spp) // step
            if new * per_pass <= budget:
                return level
            level -= step
        return None
    best = None
    level = spp * 2
    while level <= wanted and seconds * (level - spp) / spp <= budget:
        best = level
        level *= 2
    return best


def oidn_key() -> dict[str, str]:
    """The OIDN choices the environment makes (``$GRADSEP_OIDN_SETTING``, ``$GRADSEP_OIDN_RUNTIME``), in every
    method's cache key: they change the OIDN methods' images (and so every equal-time budget) without a code
    change. Empty at the defaults, so results cached before these keys existed stay valid."""
    from gradsep.model.oidn import METHOD_SETTING, method_setting, runtime_setting

    setting, runtime = method_setting(), runtime_setting()
    return {**({"oidn_setting": setting} if setting != METHOD_SETTING else {}),
            **({"oidn_runtime": runtime} if runtime != "library" else {})}


def _evaluate_one(runner: _Runner, spec: MethodSpec, scene: SceneRun, spp: int, frame: Any, seconds: float,
                  frame_tag: str, get_path: Callable[[], PathRenderer], done: dict[str, dict[str, Any]],
                  keys: dict[str, str], replica: int = 0) -> _Output | None:
    """One method on one frame: skip it (with the reason) when it cannot run, else the cached or new output.
    ``replica`` k > 0: a fixed-spp method on the k-th extra frame (``--frame-seeds``); it leaves ``done`` and
    ``keys`` (the equal-time budgets come from the first frame) as they are."""
    c = runner.config
    reason = unavailable(spec)
    if reason is not None:
        runner.skip(spec.name, [reason])
        return None
    shas, missing = runner.model_files(spec, scene.layers)
    if missing:
        runner.skip_missing(spec.name, missing)
        return None
    key: dict[str, Any] = {"format": RESULT_FORMAT, "method": spec.name, "frame": frame_tag, "models": shas,
                           "code": runner.method_code, **oidn_key()}
    if spec.kind == "recon" and table_method(str(spec.method)).alpha:
        key["alpha"] = c.alpha
    ctx = MethodContext(frame=frame, render_seconds=seconds, spp=spp, seed=_derived_seed(c.seed, 3, spp),
                        alpha=c.alpha, models_dir=c.models_dir, networks=runner.networks, path=get_path)
    if spec.kind in EQUAL_TIME_KINDS:
        budget = _budget_method(done)
        if budget is None:
            ctx.budget_seconds, ctx.budget_method = seconds, "G-PT render only"
        else:
            ctx.budget_seconds, ctx.budget_method = float(done[budget]["total_seconds"]), budget
        key["budget"] = keys.get(budget or "", "render:" + frame_tag)
        key["seed"] = ctx.seed
        if spec.kind in ("sep-oidn", "gpt-equal", "gpt-auto"):  # our renderer's code renders it
            key["renderer"] = runner.renderer_code
        if spec.kind == "gpt-auto":  # and the planner plans it
            key["planner"] = runner.planner_code
        if spec.kind == "gpt-equal":
            from gradsep.evaluation.methods import EQUAL_TIME_OFFSETS

            key["offsets"] = EQUAL_TIME_OFFSETS
    from gradsep.model.infer import ModelError

    try:
        out = runner.output(spec, scene, spp, ctx, key, replica)
        if replica:
            return out
        if spec.kind in EQUAL_TIME_KINDS:  # --time-seeds: the same budget, the other seeds' own searches
            for k in range(1, c.time_seeds):
                seeded = dataclasses.replace(ctx, seed=_derived_seed(c.seed, 3, spp, k))
                out.replicas.append(runner.output(spec, scene, spp, seeded, {**key, "seed": seeded.seed}, k))
    except ModelError as exc:
        raise CommandError(f"{spec.name}: {exc}") from exc
    done[spec.name] = out.row
    keys[spec.name] = out.tag
    return out


def _prepare_output(output: Path) -> None:
    """Create the report folder (and its parents), or fail before any rendering when that is impossible."""
    if output.exists() and not output.is_dir():
        raise CommandError(f"output {str(output)!r} exists and is not a folder")
    try:
        output.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CommandError(f"cannot create the report folder {str(output)!r}: {exc.strerror or exc}") from exc
    if not os.access(output, os.W_OK | os.X_OK):
        raise CommandError(f"report folder {str(output)!r} is not writable")
