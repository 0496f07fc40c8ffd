"""`gradsep evaluate --shot SCENE --frames A-B`: a shot's pipelines at equal render seconds (or spp) per frame.

Each plan (:data:`PLANS`) renders the shot with ``gradsep render SCENE --frames A-B`` in a child process, as a
farm task does, so ``--seconds T`` is each frame's whole budget (the first frame's counts from the process's start,
renderer/shot.py) and any scene ``gradsep render --frames`` takes is taken here: a per-frame XML pattern, one XML
with ``--animate``/``-D``, a procedural shot. Each plan's frames are then reconstructed per frame (the frame's
default method) and temporally (model.temporal.ShotReconstructor, ``--window``). Every frame gets two independent
references (evaluation/references.py passes of Mitsuba's path tracer, each frame's scene loaded the way the
renderer loads it: renderer.shot.SceneWindow). Frames and reference passes are cached under the evaluation's
cache (evaluation/cache.py), keyed by everything that determines them; the scores are
evaluation/shot_metrics.py's and the report evaluation/shot_report.py's.
"""

from __future__ import annotations

import argparse
import gc
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.evaluation.cache import EvalCache, mitsuba_id, sources_sha256
from gradsep.evaluation.methods import PLANNER_SOURCES
from gradsep.evaluation.shot_metrics import PipelineScores, ShotTruth, reconstruct_shot, score_pipeline
from gradsep.model.errors import CommandError

__all__ = ["PLANS", "Plan", "ShotConfig", "ShotResult", "check_shot_config", "evaluate_shot"]

#: The code that renders a shot's frames: the frame renderer's, the shot loop's, the motion vectors' and the
#: planner's (``--seconds`` chooses the plan). A change re-renders the cached frames.
SHOT_SOURCES = tuple(dict.fromkeys((
    "renderer/gpt.py", "renderer/gpt_loop.py", "renderer/gpt_settings.py", "renderer/lanes.py", "renderer/vertex.py",
    "renderer/shift_protocol.py", "renderer/shift.py", "renderer/hybrid.py", "renderer/hybrid_state.py",
    "renderer/shift_geometry.py", "renderer/manifold.py", "renderer/scene.py", "renderer/variant.py",
    "renderer/shot.py", "renderer/motion.py", "renderer/plancache.py", "renderer/commands.py", "model/policy.py",
    *PLANNER_SOURCES)))
REFERENCE_SOURCES = ("renderer/reference.py", "renderer/scene.py", "renderer/variant.py", "renderer/shot.py")


@dataclass(frozen=True)
class Plan:
    """A way to render the shot's frames: ``gradsep render`` flags beside the budget."""

    name: str
    label: str
    flags: tuple[str, ...]


#: The evaluation's plans: primal frames (what a farm renders for OIDN today) and the product's default plan for
#: the budget (``--gradients auto`` with ``--seconds``); the first is the flicker baseline.
PLANS: tuple[Plan, ...] = (Plan("primal", "primal", ("--no-gradients",)), Plan("plan", "default plan", ()))


@dataclass(frozen=True)
class ShotConfig:
    """Everything that defines a shot evaluation; :func:`check_shot_config` validates it."""

    scene: str
    frames: str  # A-B, as `gradsep render --frames`
    output: Path
    cache_dir: Path
    models_dir: Path
    seconds: float | None = None  # exactly one of seconds and spp
    spp: int | None = None
    animate: tuple[str, ...] = ()
    defines: tuple[str, ...] = ()
    size: tuple[int, int] | None = None  # None: the scene's film
    ref_spp: int = 512  # each reference's spp, and the pass size when raised
    ref_spp_cap: int | None = None  # raise the references up to this while their floor is too high; None: never
    seed: int = 0
    max_depth: int | None = None
    window: int = 5

    def render_args(self, output: str, flags: Sequence[str] = ()) -> list[str]:
        """The ``gradsep render`` arguments of this shot with ``flags`` into ``output`` (a frame pattern)."""
        args = [self.scene, "--frames", self.frames, *(f for a in self.animate for f in ("--animate", a)),
                *(f for d in self.defines for f in ("-D", d)), "--seed", str(self.seed)]
        args += ["--seconds", repr(self.seconds)] if self.seconds is not None else ["--spp", str(self.spp)]
        if self.size is not None:
            args += ["--width", str(self.size[0]), "--height", str(self.size[1])]
        if self.max_depth is not None:
            args += ["--max-depth", str(self.max_depth)]
        return [*args, *flags, "-o", output]


def _render_namespace(config: ShotConfig, output: str, flags: Sequence[str] = ()) -> argparse.Namespace:
    """``gradsep render``'s parsed arguments for this shot (its own parser: its defaults and checks)."""
    from gradsep.renderer.commands import register

    parser = argparse.ArgumentParser(prog="gradsep", exit_on_error=False)
    register(parser.add_subparsers(dest="command"))
    try:
        return parser.parse_args(["render", *config.render_args(output, flags)])
    except (argparse.ArgumentError, SystemExit) as exc:
        raise CommandError(f"the shot's render arguments: {exc}") from None


def check_shot_config(config: ShotConfig) -> Any:
    """Validate everything before anything renders or is written (a CommandError naming the first problem): the
    budget, the window, the report folder, and the shot as ``gradsep render --frames`` checks it (the frame range,
    every per-frame XML, every animated parameter). Returns the checked renderer.shot.Shot."""
    from gradsep.renderer.budget import check_seconds
    from gradsep.renderer.shot import checked_shot

    if (config.seconds is None) == (config.spp is None):
        raise CommandError("--shot needs exactly one of --seconds T (equal render seconds per frame) or --spp N")
    if config.seconds is not None:
        check_seconds(config.seconds)
    if config.spp is not None and config.spp < 1:
        raise CommandError(f"--spp must be >= 1, got {config.spp}")
    if config.window < 1 or config.window % 2 == 0:
        raise CommandError(f"--window must be an odd number of frames >= 1, got {config.window}")
    if config.ref_spp < 1:
        raise CommandError(f"--ref-spp must be >= 1, got {config.ref_spp}")
    if config.ref_spp_cap is not None and config.ref_spp_cap < config.ref_spp:
        raise CommandError(f"--ref-spp-cap {config.ref_spp_cap} is below --ref-spp {config.ref_spp}")
    _check_report_folder(config.output)
    # renderer.shot checks the shot; its output pattern here only has to name an existing folder.
    shot, _ = checked_shot(_render_namespace(config, os.path.join(tempfile.gettempdir(), "check.%04d.exr")))
    if len(shot.frames) < 2:
        raise CommandError(f"--frames {config.frames}: a shot evaluation needs at least two frames (flicker is "
                           "a change between frames)")
    return shot


def _check_report_folder(output: Path) -> None:
    """The report folder can be created (or is a writable folder), without creating it."""
    if output.exists():
        if not output.is_dir():
            raise CommandError(f"output {str(output)!r} exists and is not a folder")
        if not os.access(output, os.W_OK | os.X_OK):
            raise CommandError(f"report folder {str(output)!r} is not writable")
        return
    parent = output.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise CommandError(f"cannot create the report folder {str(output)!r}: {str(parent)!r} is not writable")


# ------------------------------------------------------------------------------------------------- frames


def _frame_key(config: ShotConfig, shot: Any, plan: Plan) -> dict[str, Any]:
    from gradsep.model.shot import shot_name
    from gradsep.renderer.shot import shot_scene_identity

    return {"kind": "shot-frames", "frames": shot_name(shot.frames), "flags": list(plan.flags),
            "scenes": [shot_scene_identity(shot.scene_of(n), shot.defines_of(n)) for n in shot.frames],
            "animate": list(config.animate), "defines": list(config.defines), "seconds": config.seconds,
            "spp": config.spp, "size": config.size, "seed": config.seed, "max_depth": config.max_depth,
            "code": sources_sha256(SHOT_SOURCES), "mitsuba": mitsuba_id(), **_generator(config.scene)}


def _generator(scene: str) -> dict[str, Any]:
    """A procedural scene's generator version (its scenes change with it, not with the renderer's code, as in the
    frame evaluation's keys); nothing for a scene file (its bytes are in the key)."""
    if not scene.startswith("procedural:"):
        return {}
    from gradsep.renderer.procedural_builder import GENERATOR_VERSION

    return {"generator": GENERATOR_VERSION}


def render_plan(config: ShotConfig, shot: Any, plan: Plan, cache: EvalCache, log: Callable[[str], None]) -> list:
    """The shot's frames rendered with ``plan`` (cached: ``gradsep render`` skips the frames already complete in
    the entry's folder), read back as model.frame.Frame."""
    from gradsep.model.exr_read import read_frame

    folder = cache.entry("shots", config.scene, plan.name, _frame_key(config, shot, plan), "")
    folder.mkdir(parents=True, exist_ok=True)
    pattern = str(folder / "frame.%04d.exr")
    command = [sys.executable, "-m", "gradsep", "render", *config.render_args(pattern, plan.flags)]
    log(f"rendering the shot's {plan.label} frames -> {folder}")
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines() or [f"exit status {done.returncode}"]
        raise CommandError(f"rendering the shot ({plan.label}) failed: {lines[-1]}")
    return [read_frame(str(folder / f"frame.{n:04d}.exr")) for n in shot.frames]


# --------------------------------------------------------------------------------------------- references


class ShotReferences:
    """Two independent references per frame (evaluation/references.py: cached passes of Mitsuba's path tracer at
    ``ref_spp`` each, raised in whole passes), each frame's scene loaded as the renderer loads it
    (renderer.shot.SceneWindow), only while its passes render."""

    def __init__(self, config: ShotConfig, shot: Any, cache: EvalCache, log: Callable[[str], None]) -> None:
        from gradsep.evaluation.references import REFERENCE_SAMPLER, ReferenceSource
        from gradsep.renderer.shot import shot_scene_identity

        self.shot = shot
        self.window = _OneScene(config)
        self._groups: list[list[int]] | None = None
        code = sources_sha256(REFERENCE_SOURCES)
        self.sources = []
        for n in shot.frames:
            # the frame's scene with its animated values (a procedural family's t): a frame number alone names
            # another instant in a shot of another length
            key = {"scene": shot_scene_identity(shot.scene_of(n), shot.defines_of(n)), "frame": n, "size": config.size,
                   "max_depth": config.max_depth,
                   "seed": int(np.random.SeedSequence([config.seed, 6, n]).generate_state(1, np.uint32)[0]),
                   "code": code, "mitsuba": mitsuba_id(), "sampler": REFERENCE_SAMPLER, **_generator(config.scene)}
            self.sources.append(ReferenceSource(cache, f"shot-{config.scene}-frame{n}", key, config.ref_spp,
                                                self._renderer(shot, n), log))

    def _renderer(self, shot: Any, n: int) -> Callable[[int, int], Any]:
        def render_pass(spp: int, seed: int) -> Any:
            from gradsep.evaluation.references import REFERENCE_SAMPLER
            from gradsep.renderer.reference import render_loaded

            loaded = self.window.get(shot, n)
            return render_loaded(loaded, spp=spp, seed=seed, tile_spp=None, sampler=REFERENCE_SAMPLER,
                                 progress=False)
        return render_pass

    def truth(self, spp: int, frames: list) -> tuple[ShotTruth, list[float]]:
        """Both references of every frame at ``spp`` each (rendering the passes not cached), pooled over the
        frames of one scene (:meth:`same_scene`), and each frame's floor (model.metrics.reference_floor)."""
        from gradsep.model.metrics import reference_floor

        first, second = [], []
        for i, (n, source) in enumerate(zip(self.shot.frames, self.sources, strict=True)):
            pair = source.pair(spp)
            self.window.forget()
            want = frames[i].combined().base.shape
            if pair.first["total"].shape != want:
                raise CommandError(f"frame {n}: the reference is {pair.first['total'].shape[:2]}, the rendered "
                                   f"frame {want[:2]}")
            first.append(pair.first["total"])
            second.append(pair.second["total"])
        for group in self.same_scene():
            pooled = [np.mean([refs[k] for k in group], axis=0, dtype=np.float64).astype(np.float32)
                      for refs in (first, second)]
            for k in group:
                first[k], second[k] = pooled
        return ShotTruth(first, second, frames), [reference_floor(a, b) for a, b in zip(first, second, strict=True)]

    def same_scene(self) -> list[list[int]]:
        """The groups (frame indices, two or more) of frames whose scenes are equal in every parameter
        (:func:`scene_content`): their truth is one image, so each gets the mean of the group's references, the
        samples of all of them (a static stretch of a shot: the frames before a light is switched off). Without
        this, a reference's noise far above the pipelines' error adds the same positive term to every pipeline's
        RelMSE and pulls their ratios towards 1 (docs/evaluation.md)."""
        if self._groups is None:
            keys: dict[str, list[int]] = {}
            for i, n in enumerate(self.shot.frames):
                key = scene_content(self.window.get(self.shot, n))
                self.window.forget()
                if key is not None:
                    keys.setdefault(key, []).append(i)
            self._groups = [group for group in keys.values() if len(group) > 1]
        return self._groups


def scene_content(loaded: Any) -> str | None:
    """A hash of every parameter of a loaded scene (``mitsuba.traverse``: shapes' vertices and transforms,
    materials, textures, emitters, the sensor), by name: two frames with the same hash render the same image in
    expectation. None where a parameter is of a kind this does not read (that frame is then pooled with none)."""
    import hashlib
    import re

    import mitsuba as mi

    params = mi.traverse(loaded.scene)
    entries = []
    for key in params.keys():
        value = params[key]
        array = np.asarray(value.matrix if hasattr(value, "matrix") else value)
        if array.dtype.kind not in "biuf":
            return None
        # an unnamed object is named by its address, which differs from load to load: the name without it, and
        # the entries sorted by name and value, so two such objects hash in one order
        name = re.sub(r"\d{6,}", "#", key)
        entries.append((f"{name}:{array.dtype}:{array.shape}".encode(), np.ascontiguousarray(array).tobytes()))
    digest = hashlib.sha256()
    for name, data in sorted(entries):
        digest.update(name)
        digest.update(data)
    return digest.hexdigest()


class _OneScene:
    """One frame's loaded scene at a time, loaded by renderer.shot.SceneWindow (the renderer's own loading)."""

    def __init__(self, config: ShotConfig) -> None:
        self.args = _render_namespace(config, os.path.join(tempfile.gettempdir(), "ref.%04d.exr"))
        self.window: Any = None

    def get(self, shot: Any, n: int) -> Any:
        from gradsep.renderer.shot import SceneWindow

        if self.window is None:
            self.window = SceneWindow(shot, self.args)
        self.window.forget_before(n)
        return self.window.get(n)

    def forget(self) -> None:
        if self.window is not None:
            self.window.loaded.clear()
        gc.collect()


# -------------------------------------------------------------------------------------------------- the run


@dataclass
class ShotResult:
    """A shot's evaluation: the rows (per plan, per frame then temporal), their images, the truth and notes."""

    config: ShotConfig
    numbers: list[int]  # the frame numbers
    rows: list[PipelineScores]
    images: dict[str, list[np.ndarray]]
    truth: ShotTruth
    floors: list[float]
    changes: list[int]  # indices of frames after which the truth changed (a light switched)
    baseline: str  # the flicker baseline: the first plan's per-frame row
    per_frame_of: dict[str, str]  # row -> the per-frame row of the same frames
    ref_spp: int = 0  # the spp of each reference the scores used
    pooled: list[list[int]] = field(default_factory=list)  # frame numbers whose references were pooled (one scene)


def _models(models_dir: Path) -> Any:
    """Every model set found in ``models_dir`` (as `gradsep reconstruct` loads them for the default method)."""
    from gradsep.model import methods as table

    return table.LoadedModels.load(models_dir, tuple(table.MODEL_SETS))


@dataclass
class _Outputs:
    """A pipeline's reconstructed frames before scoring."""

    name: str
    plan: str
    images: list[np.ndarray]
    seconds: list[float]
    method: str
    spp: float  # the frames' median samples per pixel


def _reconstructed(config: ShotConfig, shot: Any, plans: Sequence[Plan], cache: EvalCache,
                   log: Callable[[str], None]) -> tuple[list[_Outputs], list]:
    """Every plan's frames rendered and reconstructed per frame and temporally; the first plan's frames (whose
    motion vectors every score follows)."""
    models = _models(config.models_dir)
    outputs, first = [], None
    for plan in plans:
        frames = render_plan(config, shot, plan, cache, log)
        first = first or frames
        render_seconds = [_frame_seconds(f) for f in frames]
        spp = float(np.median([float(f.metadata.get("gradsep.spp", "nan")) for f in frames]))
        for window, suffix in ((1, ""), (config.window, "+temporal")):
            images, seconds, method = reconstruct_shot(frames, window, models)
            outputs.append(_Outputs(plan.name + suffix, plan.name, images,
                                    [r + s for r, s in zip(render_seconds, seconds, strict=True)], method, spp))
        del frames
    assert first is not None
    return outputs, first


def _frame_seconds(frame: Any) -> float:
    """A rendered frame's seconds as its budget counts them (``--seconds``: the whole command's share, scene load
    to write), else its render's."""
    meta = frame.metadata
    return float(meta.get("gradsep.elapsed_seconds", meta.get("gradsep.render_seconds", "nan")))


def _scored(outputs: Sequence[_Outputs], truth: ShotTruth) -> list[PipelineScores]:
    rows = []
    for out in outputs:
        scores = score_pipeline(out.name, out.images, truth)
        scores.seconds, scores.method, scores.spp = out.seconds, out.method, out.spp
        rows.append(scores)
    return rows


def evaluate_shot(config: ShotConfig, plans: Sequence[Plan] = PLANS,
                  log: Callable[[str], None] = lambda m: print(m, file=sys.stderr)) -> ShotResult:
    """Render, reconstruct and score the shot (see the module docstring); writes only to the cache. The references
    are raised (in passes of ``ref_spp``, up to ``ref_spp_cap``) while their median floor is over FLOOR_FRACTION of
    the smallest RelMSE, as the frame evaluation raises its references."""
    from gradsep.evaluation.config import FLOOR_FRACTION
    from gradsep.evaluation.references import next_reference_spp
    from gradsep.evaluation.shot_metrics import changed_frames

    shot = check_shot_config(config)
    cache = EvalCache(config.cache_dir / "evaluate")
    outputs, frames = _reconstructed(config, shot, plans, cache, log)
    references = ShotReferences(config, shot, cache, log)
    spp = config.ref_spp
    while True:
        truth, floors = references.truth(spp, frames)
        rows = _scored(outputs, truth)
        raised = next_reference_spp(spp, float(np.median(floors)), min(r.relmse for r in rows), FLOOR_FRACTION,
                                    max(spp, config.ref_spp_cap or spp), step=config.ref_spp)
        if raised is None:
            break
        log(f"raising the references to {raised} spp each (median floor {np.median(floors):.3g})")
        spp = raised
    return ShotResult(config, list(shot.frames), rows, {o.name: o.images for o in outputs}, truth, floors,
                      changed_frames(truth), plans[0].name, {o.name: o.plan for o in outputs}, spp,
                      [[shot.frames[k] for k in group] for group in references.same_scene()])
