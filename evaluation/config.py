"""What defines an evaluation run: the presets, the options (flags first, then ``GRADSEP_EVAL_*`` environment
variables, loaded by one pydantic-settings class), the scenes.

Everything here is validated before anything renders, and bad input is one clear error naming the problem.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic_settings import BaseSettings, SettingsConfigDict

from gradsep.evaluation.cache import REPO_ROOT, default_cache_dir, file_sha256, key_hash
from gradsep.evaluation.methods import evaluated_methods
from gradsep.model.errors import CommandError
from gradsep.model.policy import DEFAULT_ALPHA, models_dir_from

if TYPE_CHECKING:
    from gradsep.renderer.procedural import ProceduralSpec

#: The command line's --spp default (model/commands.py); with --quick it is replaced by the quick list.
CLI_DEFAULT_SPP = "1,2,4,8,16,32,64"
DEFAULT_PROCEDURAL: tuple[str, ...] = ("procedural:90001", "procedural:90002")  # training starts at seed 1000
SHARED_SCENES: tuple[str, ...] = ("cbox/cbox.xml", "teapot/teapot.xml")
#: The equal-time rows the crop comparison shows after the table's methods.
_CROP_BASELINES: tuple[str, ...] = ("path-oidn", "path-sep-oidn", "gpt-oidn-l1")


def crop_methods() -> tuple[str, ...]:
    """Methods whose images the crop comparison shows, in its order (the reference comes last): the input, the
    GradNet-style baseline, each method of the table that the default policy may pick (model/methods.py), then the
    equal-time rows with OIDN."""
    from gradsep.evaluation.methods import evaluation_name
    from gradsep.model import methods as table

    ranked = [m.name for m in table.methods() if m.preference is not None]  # in the table's order
    return ("gpt-primal", "gradnet", *(evaluation_name(m) for m in ranked), *_CROP_BASELINES)


@dataclass(frozen=True)
class Preset:
    """Defaults of a full or a --quick run, chosen for the 2-core CPU target (docs/evaluation.md)."""

    width: int
    height: int
    spp: tuple[int, ...]
    ref_spp: int  # each of the two references starts here ...
    ref_spp_cap: int  # ... and is doubled (cached, additive) up to here until the floor criterion holds,
    ref_seconds: float  # ... while both references of a scene together take at most this long to render


#: Reference spp, doubled up to the cap until the references' floor is under the scenes' ranked RelMSEs
#: (docs/evaluation.md has the floors measured); the cap and the time budget bound each scene's references, and so
#: the full report's time on the CPU target (docs/evaluation.md).
FULL = Preset(320, 240, (1, 2, 4, 8, 16, 32, 64), 512, 4096, 240.0)
QUICK = Preset(96, 72, (1, 4, 16), 128, 1024, 20.0)
#: The reference floor must stay under this fraction of the scene's smallest ranked RelMSE.
FLOOR_FRACTION = 0.1
#: Most seeds per equal-time row (``--time-seeds``): each one is a full time search and render of the row.
MAX_TIME_SEEDS = 64
#: Most G-PT frames per (scene, spp) (``--frame-seeds``): each one is a render and every fixed-spp method on it.
MAX_FRAME_SEEDS = 64


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
    methods: tuple[str, ...] = field(default_factory=lambda: tuple(m.name for m in evaluated_methods()))
    seed: int = 0
    max_depth: int | None = None
    alpha: float = DEFAULT_ALPHA
    table_spp: int | None = None
    quick: bool = False
    ref_spp_cap: int | None = None  # None: ref_spp (a fixed reference spp)
    ref_seconds: float | None = None  # render-time budget of a scene's two references; None: no limit
    time_seeds: int = 1  # seeds per equal-time row (each its own time search); the row is their mean
    frame_seeds: int = 1  # G-PT frames (render seeds) per (scene, spp); a fixed-spp row is the mean over them

    @property
    def reference_cap(self) -> int:
        """The most spp of each reference: the cap, never below the starting spp."""
        return max(self.ref_spp, self.ref_spp_cap or self.ref_spp)

    @property
    def crop_spp(self) -> int:
        """The spp of Table 1, the ablation and the crop comparison."""
        return self.table_spp if self.table_spp is not None else table_spp_for(self.spp)


# ----------------------------------------------------------------------------------------------- options


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
            raise CommandError(f"--spp: {item_text!r} is not an integer (expected e.g. 1,2,4,8)") from None
        if value < 1:
            raise CommandError(f"--spp: sample counts must be >= 1, got {value}")
        values.append(value)
    if not values:
        raise CommandError("--spp is empty; expected comma-separated sample counts such as 1,2,4,8")
    return tuple(sorted(set(values)))


def parse_size(text: str) -> tuple[int, int]:
    """``"320x240"`` -> (320, 240)."""
    parts = text.lower().replace("×", "x").split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise CommandError(f"size {text!r}: expected WIDTHxHEIGHT, e.g. 320x240") from None
    if width < 1 or height < 1:
        raise CommandError(f"size {text!r}: width and height must be >= 1")
    return width, height


def table_spp_for(spp: Sequence[int]) -> int:
    """16 spp (the paper's scenes use 16-64) when evaluated, else the evaluated count nearest to it in log2."""
    return min(spp, key=lambda s: (abs(math.log2(s) - 4.0), -s))


class EvalSettings(BaseSettings):
    """The options of `gradsep evaluate` that a flag or a ``GRADSEP_EVAL_*`` environment variable can set.

    Loaded in one place (:func:`load_settings`): a flag given on the command line wins over its variable
    (``--ref-spp`` over ``GRADSEP_EVAL_REF_SPP``); an empty variable counts as unset. pydantic checks the types;
    :func:`make_config` checks the ranges, with the same messages whichever of the two set a value. None means
    unset: the preset decides.
    """

    model_config = SettingsConfigDict(env_prefix="GRADSEP_EVAL_", env_ignore_empty=True, extra="ignore")

    size: str | None = None  # WxH
    ref_spp: int | None = None
    ref_spp_cap: int | None = None
    ref_seconds: float | None = None  # 0: no limit
    seed: int | None = None
    methods: str | None = None  # comma-separated; "ablation" = the four variants
    max_depth: int | None = None
    table_spp: int | None = None
    alpha: float | None = None
    time_seeds: int | None = None
    frame_seeds: int | None = None

    @classmethod
    def variable(cls, name: str) -> str:
        """The environment variable of option ``name`` (``ref_spp`` -> ``GRADSEP_EVAL_REF_SPP``)."""
        return f"{cls.model_config['env_prefix']}{name.upper()}"


def load_settings(**flags: Any) -> EvalSettings:
    """The options from the flags given (None = not given) over the environment; a malformed variable is a
    CommandError naming it."""
    from pydantic import ValidationError

    try:
        return EvalSettings(**{name: value for name, value in flags.items() if value is not None})
    except ValidationError as exc:
        problems = "; ".join(f"{EvalSettings.variable(str(e['loc'][0]))}: {e['msg']}" for e in exc.errors())
        raise CommandError(f"invalid evaluation settings: {problems}") from None


def _at_least(value: int | None, minimum: int, flag: str) -> int | None:
    if value is not None and value < minimum:
        raise CommandError(f"{flag} must be >= {minimum}, got {value}")
    return value


def _seed_count(value: int | None, flag: str, cap: int) -> int:
    """A seeds-per-row option: 1 when not given, else 1..``cap`` (a CommandError naming ``flag`` otherwise)."""
    count = _at_least(value, 1, flag) or 1
    if count > cap:
        raise CommandError(f"{flag} must be <= {cap}, got {count}")
    return count


def _reference_budget(settings: EvalSettings, preset: Preset) -> tuple[int, int, float | None]:
    """(starting spp, spp cap, seconds or None = no limit) of each scene's references."""
    ref_spp = _at_least(settings.ref_spp, 1, "--ref-spp") or preset.ref_spp
    ref_cap = _at_least(settings.ref_spp_cap, 1, "--ref-spp-cap")
    if ref_cap is None:
        ref_cap = max(ref_spp, preset.ref_spp_cap)
    elif ref_cap < ref_spp:
        raise CommandError(f"--ref-spp-cap {ref_cap} is below --ref-spp {ref_spp}")
    seconds = settings.ref_seconds
    if seconds is not None and not (math.isfinite(seconds) and seconds >= 0):
        raise CommandError(f"--ref-seconds must be a finite number >= 0 (0: no limit), got {seconds}")
    seconds = preset.ref_seconds if seconds is None else seconds
    return ref_spp, ref_cap, seconds if seconds > 0 else None


def parse_methods(text: str | None) -> tuple[str, ...]:
    """Comma-separated method names (``ablation`` selects the four variants), in the canonical order."""
    known = [m.name for m in evaluated_methods()]
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
            raise CommandError(f"--methods: unknown method {item!r}; expected a comma-separated subset of "
                               f"{', '.join(known)} (or 'ablation' for the four variants)")
    if not wanted:
        raise CommandError("--methods is empty")
    return tuple(n for n in known if n in wanted)


def make_config(settings: EvalSettings, *, output: str | Path, scenes: Sequence[str] = (),
                spp: str | Sequence[int] | None = None, quick: bool = False, models: str | Path | None = None,
                cache: str | Path | None = None) -> EvalConfig:
    """The run's configuration: the preset (full or ``quick``), overridden by ``settings`` and the arguments.

    ``spp`` None (or the command line's default list with ``quick``) takes the preset's list; ``models`` None
    is $GRADSEP_MODELS or ``models/`` (model.policy), ``cache`` None is $GRADSEP_CACHE or the user cache
    (evaluation.cache). Raises CommandError naming the first bad value.
    """
    preset = QUICK if quick else FULL
    spp_list = preset.spp if spp is None or (quick and spp == CLI_DEFAULT_SPP) else parse_spp(spp)
    width, height = parse_size(settings.size) if settings.size else (preset.width, preset.height)
    ref_spp, ref_cap, ref_seconds = _reference_budget(settings, preset)
    seed = _at_least(settings.seed, 0, "--seed") or 0
    max_depth = _at_least(settings.max_depth, -1, "--max-depth")
    if max_depth == 0:
        raise CommandError("--max-depth must be -1 (unbounded) or >= 1, got 0")
    table_spp = _at_least(settings.table_spp, 1, "--table-spp")
    if table_spp is not None and table_spp not in spp_list:
        raise CommandError(f"--table-spp {table_spp} is not one of the evaluated sample counts {list(spp_list)}")
    alpha = DEFAULT_ALPHA if settings.alpha is None else settings.alpha
    if not (math.isfinite(alpha) and alpha > 0):
        raise CommandError(f"--alpha must be a finite number > 0, got {alpha}")
    time_seeds = _seed_count(settings.time_seeds, "--time-seeds", MAX_TIME_SEEDS)
    frame_seeds = _seed_count(settings.frame_seeds, "--frame-seeds", MAX_FRAME_SEEDS)
    return EvalConfig(
        scenes=tuple(scenes or ()), spp=spp_list, width=width, height=height, ref_spp=ref_spp, output=Path(output),
        cache_dir=Path(cache) if cache else default_cache_dir(), models_dir=models_dir_from(models),
        methods=parse_methods(settings.methods), seed=seed, max_depth=max_depth, alpha=alpha, table_spp=table_spp,
        quick=quick, ref_spp_cap=ref_cap, ref_seconds=ref_seconds, time_seeds=time_seeds, frame_seeds=frame_seeds)


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
        raise CommandError(f"scene folder {str(path)!r} holds {len(found)} .xml files; name the one to evaluate")
    if not path.is_file():
        raise CommandError(f"scene {str(path)!r} not found (expected a Mitsuba XML file, procedural:SEED or "
                           "procedural:studio:SEED)")
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
    from gradsep.renderer.procedural import parse_procedural  # numpy only: no Mitsuba to resolve the scene list

    for spec in specs:
        procedural = parse_procedural(spec)
        if procedural is not None:
            entries.append(_procedural_entry(procedural))
        else:
            xml = _xml_for(Path(spec).expanduser())
            entries.append(SceneEntry(str(xml), scene_label(xml), {"xml": str(xml.resolve()),
                                                                   "sha256": file_sha256(xml)}))
    return _unique_names(entries), notes


def scene_label(xml: Path) -> str:
    """The display name of an XML scene: its stem, or its folder's name when the file is a generic ``scene.xml``
    (``bathroom/scene.xml`` is "bathroom", not "scene")."""
    if xml.stem.lower() == "scene" and xml.resolve().parent.name:
        return xml.resolve().parent.name
    return xml.stem


def _procedural_entry(spec: ProceduralSpec) -> SceneEntry:
    from gradsep.renderer.procedural_builder import GENERATOR_VERSION

    identity: dict = {"procedural": spec.seed, "generator": GENERATOR_VERSION}
    if spec.family != "mixed":  # the mixed family's identity (and so its cache keys) is what it always was
        identity["family"] = spec.family
    return SceneEntry(str(spec), str(spec), identity)


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
            xml = Path(entry.identity["xml"])
            name = f"{xml.parent.parent.name}/{name}" if name == xml.parent.name else f"{xml.parent.name}/{name}"
        out.append(SceneEntry(entry.spec, name, entry.identity))
    return out
