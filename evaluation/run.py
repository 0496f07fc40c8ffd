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
from gradsep.evaluation.cache import EvalCache, file_sha256, key_hash, mitsuba_id, oidn_key, sources_sha256
from gradsep.evaluation.config import EvalConfig, SceneEntry, crop_methods, resolve_scenes
from gradsep.evaluation.convergence import converge_references
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
    REFERENCE_SAMPLER,
    ReferencePair,
    ReferenceSource,
)
from gradsep.evaluation.region import Region
from gradsep.evaluation.results import Evaluation, SceneRun, machine_summary
from gradsep.evaluation.runners import MethodContext, NetworkPool, run_method
from gradsep.evaluation.scores import Output, image_scores, interpolated_scores, seed_mean
from gradsep.model.errors import CommandError
from gradsep.model.methods import get as table_method
from gradsep.model.policy import SEPARATED_LAYERS
from gradsep.model.progress import ProgressBar

__all__ = ["run_evaluation"]

#: The code that renders a frame / a reference pass (by code, evaluation.cache.code_sha256). Not
#: renderer/procedural.py: a procedural scene is keyed by its seed, family and GENERATOR_VERSION (evaluation.config),
#: which tests/renderer/test_procedural.py's pinned fingerprints hold to the generator's output.
RENDERER_SOURCES = ("renderer/gpt.py", "renderer/gpt_loop.py", "renderer/gpt_settings.py", "renderer/lanes.py",
                    "renderer/vertex.py", "renderer/shift_protocol.py", "renderer/shift.py", "renderer/hybrid.py",
                    "renderer/hybrid_state.py", "renderer/shift_geometry.py", "renderer/manifold.py",
                    "renderer/render.py", "renderer/scene.py", "renderer/variant.py", "model/policy.py")
REFERENCE_SOURCES = ("renderer/reference.py", "renderer/scene.py", "renderer/variant.py")
RESULT_FORMAT = 3  # bump when the cached output/score JSON changes shape
SCORE_SOURCES = ("model/metrics.py", "evaluation/scores.py", "evaluation/run.py")


# ---------------------------------------------------------------------------------------------- the run


def _derived_seed(*parts: int) -> int:
    """A 32-bit seed from integers (distinct runs, spp and purposes never share sampler streams)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, dtype=np.uint32)[0])


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
               "seed": c.seed, "code": self.reference_code, "mitsuba": mitsuba_id(), "sampler": REFERENCE_SAMPLER}

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
        from gradsep.model.errors import FrameError
        from gradsep.model.exr_read import read_frame
        from gradsep.model.exr_write import write_frame
        from gradsep.renderer.render import render_frame
        from gradsep.renderer.shift import DEFAULT_SHIFT

        seed = _derived_seed(self.config.seed, 2, spp, *((replica,) if replica else ()))
        key = {"kind": "gpt-frame", "scene": entry.identity, "size": [loaded.width, loaded.height],
               "max_depth": loaded.max_depth, "spp": spp, "seed": seed, "shift": DEFAULT_SHIFT,
               "gradients": gradients, "code": self.renderer_code, "mitsuba": mitsuba_id()}
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
               key: dict[str, Any], replica: int = 0) -> Output:
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
                return Output(spec, spp, {**cached["row"], "scene": scene.entry.name}, arrays["image"], layers, tag,
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
        return Output(spec, spp, row, out.image, layers, tag, list(out.bracket))

    def row(self, output: Output, scene: SceneRun, pair: ReferencePair) -> dict[str, Any]:
        """The output's report row: its own row and scores, or with replicas (``--time-seeds``,
        ``--frame-seeds``) the mean over the seeds (:func:`seed_mean`)."""
        if not output.replicas:
            return {**output.row, **self.score(output, scene, pair)}
        return seed_mean([{**o.row, **self.score(o, scene, pair)} for o in (output, *output.replicas)])

    def score(self, output: Output, scene: SceneRun, pair: ReferencePair) -> dict[str, Any]:
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
    from gradsep.model.policy import SEPARATED_LAYERS
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

    outputs: list[Output] = []
    for spp in config.spp:
        bar.describe(f"{entry.name}: G-PT {spp} spp")
        frames = {"all": runner.frame(entry, loaded, spp)}
        bar.update()
        state = _SppState(get_path)
        for spec in methods:
            bar.describe(f"{entry.name} {spp} spp: {spec.name}")
            if spec.gradients not in frames and unavailable(spec) is None:
                frames[spec.gradients] = runner.frame(entry, loaded, spp, spec.gradients)
            out = _evaluate_one(runner, spec, scene, spp, frames.get(spec.gradients, frames["all"]), state)
            if out is not None:
                if spec.kind not in EQUAL_TIME_KINDS:  # --frame-seeds: the method on the other frames too
                    for k in range(1, config.frame_seeds):
                        extra = runner.frame(entry, loaded, spp, spec.gradients, replica=k)
                        more = _evaluate_one(runner, spec, scene, spp, extra, state, replica=k)
                        if more is not None:
                            out.replicas.append(more)
                outputs.append(out)
            bar.update()
    bar.describe(f"{entry.name}: references")
    pair = converge_references(runner, scene, runner.references(entry, loaded), outputs)
    bar.update()
    bar.describe(f"{entry.name}: scoring")
    rows = []
    for out in outputs:
        rows.append(runner.row(out, scene, pair))
        if out.spp == config.crop_spp and out.spec.name in crop_methods():
            scene.crop_images[out.spec.name] = out.image
    bar.update()
    return scene, rows


@dataclass
class _SppState:
    """What the methods of one (scene, spp) share: the scene's equal-time renderer (built on first use), the rows
    done so far (the equal-time budget is read from them) and their cache key hashes."""

    path: Callable[[], PathRenderer]
    done: dict[str, dict[str, Any]] = field(default_factory=dict)
    keys: dict[str, str] = field(default_factory=dict)


def _evaluate_one(runner: _Runner, spec: MethodSpec, scene: SceneRun, spp: int, rendered: tuple[Any, float, str],
                  state: _SppState, replica: int = 0) -> Output | None:
    """One method on one frame (``rendered``: the frame, its render seconds, its cache tag): skip it (with the
    reason) when it cannot run, else the cached or new output. ``replica`` k > 0: a fixed-spp method on the k-th
    extra frame (``--frame-seeds``); it leaves ``state``'s rows and keys (the equal-time budgets come from the
    first frame) as they are."""
    c = runner.config
    frame, seconds, frame_tag = rendered
    get_path, done, keys = state.path, state.done, state.keys
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
