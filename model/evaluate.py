"""`gradsep evaluate`: error against run time for every method, the paper's Table 1 and Fig. 7 ablation, plots.

One command renders (or takes from the cache) G-PT frames at each spp and a converged reference per scene, runs
every method of model/evaluate_methods.py on each frame, scores it against the reference (RelMSE, SSIM, PSNR,
HDR-FLIP from model/metrics.py) and writes into the report folder:

* ``results.csv`` -- one row per (scene, method, spp) with render/reconstruction/total seconds and the metrics;
  ``results.json`` -- the same rows plus the configuration, machine, models and skipped methods;
* ``plots/<scene>.png`` -- RelMSE against total wall time, log-log, one curve per method (equal-time view);
* ``crops/<scene>.png`` -- the crop comparison of the paper's Fig. 6 (input, L1, GradNet-style, ours, OIDN,
  reference);
* ``report.md`` -- Table 1, the Fig. 7 ablation, the equal-time comparison, where ours loses, how it was made.

The protocol (defaults, seeds, what is timed, the cache) is documented in docs/evaluation.md. Options not yet on
the command line are read from the environment (see :func:`config_from_args`).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from model.evaluate_cache import REPO_ROOT, EvalCache, default_cache_dir, file_sha256, key_hash, sources_sha256
from model.evaluate_methods import (
    METHOD_SOURCES,
    METHODS,
    MethodContext,
    MethodSpec,
    NetworkPool,
    PathRenderer,
    method_by_name,
    run_method,
)

__all__ = [
    "CROP_METHODS",
    "EvalConfig",
    "Evaluation",
    "SceneEntry",
    "config_from_args",
    "evaluate_command",
    "parse_size",
    "parse_spp",
    "resolve_scenes",
    "run_evaluation",
    "table_spp_for",
]

#: The command line's --spp default (model/commands.py); with --quick it is replaced by the quick list.
CLI_DEFAULT_SPP = "1,2,4,8,16,32,64"
DEFAULT_PROCEDURAL: tuple[str, ...] = ("procedural:90001", "procedural:90002")  # training starts at seed 1000
SHARED_SCENES: tuple[str, ...] = ("cbox/cbox.xml", "teapot/teapot.xml")
#: Methods whose images the crop comparison shows, in its order (the reference comes last).
CROP_METHODS: tuple[str, ...] = ("gpt-primal", "l1", "gradnet", "ours", "path-oidn")
RENDERER_SOURCES = ("renderer/gpt.py", "renderer/shift.py", "renderer/render.py", "renderer/scene.py",
                    "renderer/procedural.py")
REFERENCE_SOURCES = ("renderer/reference.py", "renderer/scene.py", "renderer/procedural.py")
RESULT_FORMAT = 1  # bump when the cached result JSON changes shape


@dataclass(frozen=True)
class Preset:
    """Defaults of a full or a --quick run, chosen for the 2-core CPU target (docs/evaluation.md)."""

    width: int
    height: int
    spp: tuple[int, ...]
    ref_spp: int


FULL = Preset(320, 240, (1, 2, 4, 8, 16, 32, 64), 1024)
QUICK = Preset(96, 72, (1, 4, 16), 256)


@dataclass(frozen=True)
class EvalConfig:
    """Everything that defines an evaluation run."""

    scenes: tuple[str, ...]
    spp: tuple[int, ...]
    width: int
    height: int
    ref_spp: int
    output: Path
    cache_dir: Path
    models_dir: Path
    methods: tuple[str, ...] = tuple(m.name for m in METHODS)
    seed: int = 0
    max_depth: int | None = None
    alpha: float = 0.2
    table_spp: int | None = None
    quick: bool = False

    @property
    def crop_spp(self) -> int:
        """The spp of Table 1, the ablation and the crop comparison."""
        return self.table_spp if self.table_spp is not None else table_spp_for(self.spp)


# ----------------------------------------------------------------------------------------------- options


def _error(message: str) -> Exception:
    from gradsep.cli import CommandError

    return CommandError(message)


def parse_spp(text: str | Sequence[int]) -> tuple[int, ...]:
    """``"1,2,4"`` -> (1, 2, 4): positive integers, sorted, duplicates dropped."""
    items = text.split(",") if isinstance(text, str) else list(text)
    values = []
    for item in items:
        item_text = str(item).strip()
        if not item_text:
            continue
        try:
            value = int(item_text)
        except ValueError:
            raise _error(f"--spp: {item_text!r} is not an integer (expected e.g. 1,2,4,8)") from None
        if value < 1:
            raise _error(f"--spp: sample counts must be >= 1, got {value}")
        values.append(value)
    if not values:
        raise _error("--spp is empty; expected comma-separated sample counts such as 1,2,4,8")
    return tuple(sorted(set(values)))


def parse_size(text: str) -> tuple[int, int]:
    """``"320x240"`` -> (320, 240)."""
    parts = text.lower().replace("×", "x").split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise _error(f"size {text!r}: expected WIDTHxHEIGHT, e.g. 320x240") from None
    if width < 1 or height < 1:
        raise _error(f"size {text!r}: width and height must be >= 1")
    return width, height


def table_spp_for(spp: Sequence[int]) -> int:
    """16 spp (the paper's scenes use 16-64) when evaluated, else the evaluated count nearest to it in log2."""
    return min(spp, key=lambda s: (abs(math.log2(s) - 4.0), -s))


def _option(args: argparse.Namespace, name: str, env: str) -> str | None:
    """A command-line value when the parser has that flag and it was given, else the environment variable."""
    value = getattr(args, name, None)
    if value is not None:
        return str(value)
    return os.environ.get(env) or None


def _int_option(args: argparse.Namespace, name: str, env: str, flag: str, minimum: int) -> int | None:
    text = _option(args, name, env)
    if text is None:
        return None
    try:
        value = int(text)
    except ValueError:
        raise _error(f"{flag}: {text!r} is not an integer") from None
    if value < minimum:
        raise _error(f"{flag} must be >= {minimum}, got {value}")
    return value


def parse_methods(text: str | None) -> tuple[str, ...]:
    """Comma-separated method names (``ablation`` selects the four variants), in the canonical order."""
    known = [m.name for m in METHODS]
    if not text:
        return tuple(known)
    wanted: set[str] = set()
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        if item == "ablation":
            wanted.update(n for n in known if n.startswith("ablation/"))
        elif item in known:
            wanted.add(item)
        else:
            raise _error(f"--methods: unknown method {item!r}; expected a comma-separated subset of "
                         f"{', '.join(known)} (or 'ablation' for the four variants)")
    if not wanted:
        raise _error("--methods is empty")
    return tuple(n for n in known if n in wanted)


def config_from_args(args: argparse.Namespace) -> EvalConfig:
    """Build the run's configuration from the parsed command line and the environment.

    Flags the parser does not have yet fall back to environment variables: ``--models`` / $GRADSEP_MODELS,
    ``--cache`` / $GRADSEP_CACHE, ``--size`` / $GRADSEP_EVAL_SIZE, ``--ref-spp`` / $GRADSEP_EVAL_REF_SPP,
    ``--seed`` / $GRADSEP_EVAL_SEED, ``--methods`` / $GRADSEP_EVAL_METHODS, ``--max-depth`` /
    $GRADSEP_EVAL_MAX_DEPTH, ``--table-spp`` / $GRADSEP_EVAL_TABLE_SPP, ``--alpha`` / $GRADSEP_EVAL_ALPHA.
    """
    quick = bool(getattr(args, "quick", False))
    preset = QUICK if quick else FULL
    spp_text = getattr(args, "spp", None)
    spp = preset.spp if spp_text is None or (quick and spp_text == CLI_DEFAULT_SPP) else parse_spp(spp_text)
    size = _option(args, "size", "GRADSEP_EVAL_SIZE")
    width, height = parse_size(size) if size else (preset.width, preset.height)
    ref_spp = _int_option(args, "ref_spp", "GRADSEP_EVAL_REF_SPP", "--ref-spp", 1) or preset.ref_spp
    seed = _int_option(args, "seed", "GRADSEP_EVAL_SEED", "--seed", 0) or 0
    max_depth = _int_option(args, "max_depth", "GRADSEP_EVAL_MAX_DEPTH", "--max-depth", -1)
    if max_depth == 0:
        raise _error("--max-depth must be -1 (unbounded) or >= 1, got 0")
    table_spp = _int_option(args, "table_spp", "GRADSEP_EVAL_TABLE_SPP", "--table-spp", 1)
    if table_spp is not None and table_spp not in spp:
        raise _error(f"--table-spp {table_spp} is not one of the evaluated sample counts {list(spp)}")
    alpha_text = _option(args, "alpha", "GRADSEP_EVAL_ALPHA")
    alpha = 0.2
    if alpha_text is not None:
        try:
            alpha = float(alpha_text)
        except ValueError:
            raise _error(f"--alpha: {alpha_text!r} is not a number") from None
        if not (math.isfinite(alpha) and alpha > 0):
            raise _error(f"--alpha must be a finite number > 0, got {alpha_text}")
    from model.reconstruct import models_dir_from

    cache = _option(args, "cache", "GRADSEP_CACHE")
    return EvalConfig(
        scenes=tuple(args.scenes) if getattr(args, "scenes", None) else (),
        spp=spp, width=width, height=height, ref_spp=ref_spp, output=Path(args.output),
        cache_dir=Path(cache) if cache else default_cache_dir(),
        models_dir=models_dir_from(getattr(args, "models", None)),
        methods=parse_methods(_option(args, "methods", "GRADSEP_EVAL_METHODS")),
        seed=seed, max_depth=max_depth, alpha=alpha, table_spp=table_spp, quick=quick)


# ------------------------------------------------------------------------------------------------ scenes


@dataclass(frozen=True)
class SceneEntry:
    """A scene to evaluate: the spec load_scene takes, a unique display name and what identifies its content."""

    spec: str
    name: str
    identity: dict[str, Any]


def _xml_for(path: Path) -> Path:
    """An XML file, or a folder holding ``<folder>.xml`` or exactly one ``.xml``."""
    if path.is_dir():
        named = path / f"{path.name}.xml"
        if named.is_file():
            return named
        found = sorted(path.glob("*.xml"))
        if len(found) == 1:
            return found[0]
        raise _error(f"scene folder {str(path)!r} holds {len(found)} .xml files; name the one to evaluate")
    if not path.is_file():
        raise _error(f"scene {str(path)!r} not found (expected a Mitsuba XML file or procedural:SEED)")
    return path


def resolve_scenes(specs: Sequence[str]) -> tuple[list[SceneEntry], list[str]]:
    """Scene entries for ``specs`` (the defaults when empty) and notes about defaults that are missing."""
    notes: list[str] = []
    if not specs:
        shared = REPO_ROOT.parent / "shared" / "scenes"
        specs = []
        for rel in SHARED_SCENES:
            if (shared / rel).is_file():
                specs.append(str(shared / rel))
            else:
                notes.append(f"default scene {shared / rel} not found; evaluated without it")
        specs = [*specs, *DEFAULT_PROCEDURAL]
    entries: list[SceneEntry] = []
    for spec in specs:
        if spec.startswith("procedural:"):
            entries.append(_procedural_entry(spec))
        else:
            xml = _xml_for(Path(spec).expanduser())
            entries.append(SceneEntry(str(xml), xml.stem, {"xml": str(xml.resolve()), "sha256": file_sha256(xml)}))
    return _unique_names(entries), notes


def _procedural_entry(spec: str) -> SceneEntry:
    text = spec[len("procedural:"):]
    try:
        seed = int(text)
    except ValueError:
        raise _error(f"bad scene {spec!r}: expected procedural:SEED with an integer seed") from None
    if seed < 0:
        raise _error(f"bad scene {spec!r}: the seed must be >= 0")
    from renderer.procedural import GENERATOR_VERSION

    return SceneEntry(f"procedural:{seed}", f"procedural:{seed}", {"procedural": seed, "generator": GENERATOR_VERSION})


def _unique_names(entries: list[SceneEntry]) -> list[SceneEntry]:
    """Disambiguate equal display names (two ``scene.xml`` in different folders) with their folder names;
    drop exact repeats of one scene."""
    seen: set[str] = set()
    unique = []
    for entry in entries:
        key = key_hash(entry.identity)
        if key in seen:
            continue
        seen.add(key)
        unique.append(entry)
    names = [e.name for e in unique]
    out = []
    for entry in unique:
        name = entry.name
        if names.count(name) > 1 and "xml" in entry.identity:
            name = f"{Path(entry.identity['xml']).parent.name}/{name}"
        out.append(SceneEntry(entry.spec, name, entry.identity))
    return out


# ---------------------------------------------------------------------------------------------- the run


@dataclass
class SceneRun:
    """What the report needs about one evaluated scene."""

    entry: SceneEntry
    width: int
    height: int
    max_depth: int
    layers: tuple[str, ...]
    reference: np.ndarray  # (H, W, 3) total
    reference_layers: dict[str, np.ndarray]  # direct and, when the depth allows it, indirect
    reference_meta: dict[str, str]
    crop_images: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Evaluation:
    """The outcome of :func:`run_evaluation`: rows plus what the report says about how they were made."""

    config: EvalConfig
    rows: list[dict[str, Any]]
    scenes: list[SceneRun]
    skipped: dict[str, list[str]]  # method -> the model files it needs that are missing
    models: dict[str, str]  # model file (relative to the models folder) -> sha256
    notes: list[str]
    computed: dict[str, int]  # what this run computed rather than took from the cache
    outputs: dict[str, Path] = field(default_factory=dict)


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
        self.skipped: dict[str, list[str]] = {}  # method -> missing model files
        self._warm_scenes: set[int] = set()
        self.renderer_code = sources_sha256(RENDERER_SOURCES)
        self.reference_code = sources_sha256(REFERENCE_SOURCES)
        self.method_code = sources_sha256(METHOD_SOURCES)

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
        return shas, missing

    def skip(self, method: str, missing: Iterable[str]) -> None:
        """Record a method skipped for want of model files (the union over scenes is reported)."""
        files = self.skipped.setdefault(method, [])
        files.extend(f for f in missing if f not in files)

    # -------------------------------------------------------------------------------------- references

    def reference(self, entry: SceneEntry, loaded: Any) -> tuple[Any, str]:
        """The scene's reference (renderer.reference.Reference) and its cache key hash; rendered when not cached."""
        from model.frame import FrameError
        from renderer.reference import load_reference, render_reference, write_reference

        c = self.config
        seed = _derived_seed(c.seed, 1, 0)
        key = {"kind": "reference", "scene": entry.identity, "size": [loaded.width, loaded.height],
               "max_depth": loaded.max_depth, "spp": c.ref_spp, "seed": seed, "code": self.reference_code,
               "mitsuba": _mitsuba_id()}
        stem = f"{loaded.width}x{loaded.height}-d{loaded.max_depth}-spp{c.ref_spp}-seed{c.seed}"
        path = self.cache.entry("references", entry.name, stem, key, ".exr")
        tag = key_hash(key)
        if path.is_file():
            try:
                ref = load_reference(str(path))
                if ref.metadata.get("gradsep.eval_key") == tag and ref.total.shape == (loaded.height,
                                                                                       loaded.width, 3):
                    return ref, tag
            except FrameError:
                pass
            self.log(f"cache entry {path} unreadable; re-rendering the reference")
        ref = render_reference(entry.spec, spp=c.ref_spp, width=loaded.width, height=loaded.height,
                               max_depth=loaded.max_depth, seed=seed,
                               progress=False if self.progress is False else None)
        ref.metadata["gradsep.eval_key"] = tag
        path.parent.mkdir(parents=True, exist_ok=True)
        write_reference(path, ref)
        self.computed["references"] += 1
        return ref, tag

    # ------------------------------------------------------------------------------------------ frames

    def frame(self, entry: SceneEntry, loaded: Any, spp: int) -> tuple[Any, float, str]:
        """The G-PT frame at ``spp``, its render seconds and cache key hash (rendered when not cached)."""
        from model.frame import FrameError, read_frame, write_frame
        from renderer.render import render_frame
        from renderer.shift import DEFAULT_SHIFT

        seed = _derived_seed(self.config.seed, 2, spp)
        key = {"kind": "gpt-frame", "scene": entry.identity, "size": [loaded.width, loaded.height],
               "max_depth": loaded.max_depth, "spp": spp, "seed": seed, "shift": DEFAULT_SHIFT,
               "code": self.renderer_code, "mitsuba": _mitsuba_id()}
        stem = f"{loaded.width}x{loaded.height}-d{loaded.max_depth}-spp{spp}-seed{self.config.seed}"
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
        if id(loaded) not in self._warm_scenes:  # the first render of a scene pays Dr.Jit's compilation
            render_frame(loaded, spp=1, seed=_derived_seed(self.config.seed, 4, 0))
            self._warm_scenes.add(id(loaded))
        frame = render_frame(loaded, spp=spp, seed=seed)
        seconds = float(frame.metadata["gradsep.render_seconds"])
        frame.metadata["gradsep.eval_key"] = tag
        path.parent.mkdir(parents=True, exist_ok=True)
        write_frame(path, frame)
        self.computed["frames"] += 1
        return frame, seconds, tag

    # ----------------------------------------------------------------------------------------- results

    def result(self, spec: MethodSpec, scene: SceneRun, spp: int, ctx: MethodContext, key: dict[str, Any],
               want_image: bool) -> tuple[dict[str, Any], np.ndarray | None]:
        """One (scene, method, spp) row and, when ``want_image``, its image; from the cache when possible."""
        c = self.config
        stem = f"{spec.name}-{scene.width}x{scene.height}-spp{spp}-seed{c.seed}"
        path = self.cache.entry("results", scene.entry.name, stem, key, ".json")
        image_path = path.with_suffix(".npz")
        cached = self.cache.load_json(path)
        if cached is not None and cached.get("key") == key and isinstance(cached.get("row"), dict):
            image = self.cache.load_arrays(image_path, ["image"]) if want_image else None
            if not want_image or image is not None:
                # the display name is not part of the content key: take this run's
                return {**cached["row"], "scene": scene.entry.name}, (image["image"] if image else None)
        from model.metrics import all_metrics, relmse

        out = run_method(spec, ctx)
        for warning in out.warnings:
            self.log(f"{scene.entry.name} {spec.name} {spp} spp: {warning}")
        metrics = all_metrics(out.image, scene.reference)
        row: dict[str, Any] = {
            "scene": scene.entry.name, "method": spec.name, "spp": spp, "method_spp": out.method_spp,
            "width": scene.width, "height": scene.height,
            "render_seconds": out.render_seconds, "reconstruct_seconds": out.reconstruct_seconds,
            "total_seconds": out.render_seconds + out.reconstruct_seconds,
            "relmse": metrics["relmse"], "ssim": metrics["ssim"], "psnr": metrics["psnr"], "flip": metrics["flip"],
        }
        for layer in ("direct", "indirect"):
            ref_layer = scene.reference_layers.get(layer)
            row[f"relmse_{layer}"] = (relmse(out.layers[layer], ref_layer)
                                      if layer in out.layers and ref_layer is not None else None)
        row.update({k: v for k, v in out.extra.items() if k in ("target_seconds", "budget_method", "capped")})
        row["machine"] = machine_summary()
        self.cache.save_json(path, {"format": RESULT_FORMAT, "key": key, "row": row})
        if want_image:
            self.cache.save_arrays(image_path, {"image": out.image})
        self.computed["results"] += 1
        return row, out.image


_MITSUBA: str | None = None


def _mitsuba_id() -> str:
    """Mitsuba version + variant: a different build may sample differently, so it is part of render keys."""
    global _MITSUBA
    if _MITSUBA is None:
        import mitsuba as mi

        from renderer.scene import select_variant

        _MITSUBA = f"{mi.__version__}/{select_variant()}"
    return _MITSUBA


def machine_summary() -> str:
    """``CPU model, N logical cores`` (+ GPU variant when Mitsuba runs on CUDA): where a timing was taken."""
    cpu = ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import platform

    cpu = cpu or platform.processor() or platform.machine()
    return f"{cpu}, {os.cpu_count()} logical cores"


class _Progress:
    """One tqdm bar over the run's steps (hidden when progress is off, or not a terminal when it is None)."""

    def __init__(self, total: int, enabled: bool | None) -> None:
        self.bar = None
        if enabled is False:
            return
        try:
            from tqdm import tqdm
        except ImportError:
            return
        self.bar = tqdm(total=total, unit="step", desc="evaluate", dynamic_ncols=True,
                        disable=None if enabled is None else not enabled, file=sys.stderr)

    def step(self, description: str) -> None:
        if self.bar is not None:
            self.bar.set_description_str(description[:60])

    def advance(self, n: int = 1) -> None:
        if self.bar is not None:
            self.bar.update(n)

    def write(self, message: str) -> None:
        if self.bar is not None and not self.bar.disable:
            self.bar.write(message, file=sys.stderr)
        else:
            print(message, file=sys.stderr)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _budget_method(rows: dict[str, dict[str, Any]]) -> str | None:
    """The method whose total time is the equal-time budget: ours, else L1 (None: the G-PT render alone)."""
    for name in ("ours", "l1"):
        if name in rows:
            return name
    return None


def run_evaluation(config: EvalConfig, *, progress: bool | None = None,
                   log: Callable[[str], None] | None = None) -> Evaluation:
    """Run the whole evaluation and write every output into ``config.output``; see the module docstring."""
    from model.frame import SEPARATED_LAYERS
    from renderer.render import plan_layers
    from renderer.scene import load_scene

    entries, notes = resolve_scenes(config.scenes)
    _prepare_output(config.output)
    methods = [method_by_name(name) for name in config.methods]
    total = len(entries) * (1 + len(config.spp) * (1 + len(methods)))
    bar = _Progress(total, progress)
    runner = _Runner(config, progress, log or bar.write)
    try:
        runner.cache.prepare()
    except OSError as exc:
        raise _error(f"cache folder {str(runner.cache.root)!r} cannot be created: {exc.strerror or exc}") from exc
    rows: list[dict[str, Any]] = []
    scenes: list[SceneRun] = []
    # every scene is loaded (and so validated) before anything renders: a typo in the last scene should not
    # surface after an hour of work on the first ones
    loaded_scenes = [load_scene(e.spec, width=config.width, height=config.height, max_depth=config.max_depth)
                     for e in entries]
    try:
        for entry, loaded in zip(entries, loaded_scenes, strict=True):
            layers, _ = plan_layers(SEPARATED_LAYERS, loaded.max_depth)
            bar.step(f"{entry.name}: reference {config.ref_spp} spp")
            reference, ref_tag = runner.reference(entry, loaded)
            bar.advance()
            ref_layers = {"direct": reference.direct}
            if reference.indirect is not None:
                ref_layers["indirect"] = reference.indirect
            scene = SceneRun(entry, loaded.width, loaded.height, loaded.max_depth, layers, reference.total,
                             ref_layers, dict(reference.metadata))
            scenes.append(scene)
            path_renderer: list[PathRenderer] = []

            def get_path(loaded: Any = loaded, cell: list[PathRenderer] = path_renderer) -> PathRenderer:
                if not cell:
                    cell.append(PathRenderer(loaded))
                return cell[0]

            for spp in config.spp:
                bar.step(f"{entry.name}: G-PT {spp} spp")
                frame, seconds, frame_tag = runner.frame(entry, loaded, spp)
                bar.advance()
                done: dict[str, dict[str, Any]] = {}
                keys: dict[str, str] = {}
                for spec in methods:
                    bar.step(f"{entry.name} {spp} spp: {spec.name}")
                    row = _evaluate_one(runner, spec, scene, spp, frame, seconds, frame_tag, ref_tag, get_path,
                                        done, keys)
                    if row is not None:
                        rows.append(row)
                    bar.advance()
    finally:
        bar.close()
    evaluation = Evaluation(config, rows, scenes, runner.skipped, dict(sorted(runner.model_shas.items())),
                            notes, runner.computed)
    from model.evaluate_report import write_outputs

    evaluation.outputs = write_outputs(evaluation)
    return evaluation


def _evaluate_one(runner: _Runner, spec: MethodSpec, scene: SceneRun, spp: int, frame: Any, seconds: float,
                  frame_tag: str, ref_tag: str, get_path: Callable[[], PathRenderer], done: dict[str, dict[str, Any]],
                  keys: dict[str, str]) -> dict[str, Any] | None:
    """One method on one frame: skip it (with the reason) when its models are absent, else the cached or new row."""
    c = runner.config
    shas, missing = runner.model_files(spec, scene.layers)
    if missing:
        runner.skip(spec.name, missing)
        return None
    key: dict[str, Any] = {"format": RESULT_FORMAT, "method": spec.name, "frame": frame_tag, "reference": ref_tag,
                           "models": shas, "code": runner.method_code}
    if spec.kind == "poisson":
        key["alpha"] = c.alpha
    ctx = MethodContext(frame=frame, render_seconds=seconds, spp=spp, seed=_derived_seed(c.seed, 3, spp),
                        alpha=c.alpha, models_dir=c.models_dir, networks=runner.networks, path=get_path)
    if spec.kind in ("path", "oidn"):
        budget = _budget_method(done)
        if budget is None:
            ctx.budget_seconds, ctx.budget_method = seconds, "G-PT render only"
        else:
            ctx.budget_seconds, ctx.budget_method = float(done[budget]["total_seconds"]), budget
        key["budget"] = keys.get(budget or "", "render:" + frame_tag)
        key["seed"] = ctx.seed
    want_image = spp == c.crop_spp and spec.name in CROP_METHODS
    from model.infer import ModelError

    try:
        row, image = runner.result(spec, scene, spp, ctx, key, want_image)
    except ModelError as exc:
        raise _error(f"{spec.name}: {exc}") from exc
    done[spec.name] = row
    keys[spec.name] = key_hash(key)
    if image is not None:
        scene.crop_images[spec.name] = image
    return row


def _prepare_output(output: Path) -> None:
    """Create the report folder (and its parents), or fail before any rendering when that is impossible."""
    if output.exists() and not output.is_dir():
        raise _error(f"output {str(output)!r} exists and is not a folder")
    try:
        output.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _error(f"cannot create the report folder {str(output)!r}: {exc.strerror or exc}") from exc
    if not os.access(output, os.W_OK | os.X_OK):
        raise _error(f"report folder {str(output)!r} is not writable")


# ----------------------------------------------------------------------------------------------- command


def evaluate_command(args: argparse.Namespace) -> int:
    """``gradsep evaluate``: run the evaluation, print where the outputs are and which methods were skipped."""
    config = config_from_args(args)
    start = time.perf_counter()
    evaluation = run_evaluation(config, progress=None)
    elapsed = time.perf_counter() - start
    for method, missing in evaluation.skipped.items():
        print(f"gradsep evaluate: skipped {method}: not found: {', '.join(missing)}", file=sys.stderr)
    for note in evaluation.notes:
        print(f"gradsep evaluate: note: {note}", file=sys.stderr)
    computed = evaluation.computed
    print(f"evaluated {len(evaluation.scenes)} scene(s), {len(evaluation.rows)} rows in {elapsed:.0f} s "
          f"(computed {computed['frames']} frames, {computed['references']} references, {computed['results']} "
          f"results; the rest from {config.cache_dir / 'evaluate'}) -> {evaluation.outputs['report']}")
    return 0
