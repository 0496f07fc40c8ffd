"""What defines an evaluation run: the presets, the options (flags first, then environment variables), the scenes.

Everything here is validated before anything renders, and bad input is one clear error naming the problem.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evaluation.cache import REPO_ROOT, default_cache_dir, file_sha256, key_hash
from evaluation.methods import METHODS
from model.errors import CommandError
from model.policy import DEFAULT_ALPHA, models_dir_from

#: The command line's --spp default (model/commands.py); with --quick it is replaced by the quick list.
CLI_DEFAULT_SPP = "1,2,4,8,16,32,64"
DEFAULT_PROCEDURAL: tuple[str, ...] = ("procedural:90001", "procedural:90002")  # training starts at seed 1000
SHARED_SCENES: tuple[str, ...] = ("cbox/cbox.xml", "teapot/teapot.xml")
#: Methods whose images the crop comparison shows, in its order (the reference comes last).
CROP_METHODS: tuple[str, ...] = ("gpt-primal", "l1", "gradnet", "ours", "path-oidn", "path-sep-oidn")


@dataclass(frozen=True)
class Preset:
    """Defaults of a full or a --quick run, chosen for the 2-core CPU target (docs/evaluation.md)."""

    width: int
    height: int
    spp: tuple[int, ...]
    ref_spp: int  # each of the two references starts here ...
    ref_spp_cap: int  # ... and is doubled (cached, additive) up to here until the floor criterion holds,
    ref_seconds: float  # ... while both references of a scene together take at most this long to render


#: Reference spp: cbox at 320x240 leaves a floor of 0.012 at 128 spp (0.0015 at 1024), teapot 0.0003 at 128
#: (measured); the spp cap and the time budget keep the full report's references within 4 minutes per scene on
#: 2 cores, so the whole report stays well under 40 minutes (docs/evaluation.md).
FULL = Preset(320, 240, (1, 2, 4, 8, 16, 32, 64), 512, 4096, 240.0)
QUICK = Preset(96, 72, (1, 4, 16), 128, 1024, 20.0)
#: The reference floor must stay under this fraction of the scene's smallest ranked RelMSE.
FLOOR_FRACTION = 0.1


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
    alpha: float = DEFAULT_ALPHA
    table_spp: int | None = None
    quick: bool = False
    ref_spp_cap: int | None = None  # None: ref_spp (a fixed reference spp)
    ref_seconds: float | None = None  # render-time budget of a scene's two references; None: no limit

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
        raise CommandError(f"{flag}: {text!r} is not an integer") from None
    if value < minimum:
        raise CommandError(f"{flag} must be >= {minimum}, got {value}")
    return value


def _float_option(args: argparse.Namespace, name: str, env: str, flag: str) -> float | None:
    """A finite number >= 0 from the flag or the environment (0 means: no limit)."""
    text = _option(args, name, env)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise CommandError(f"{flag}: {text!r} is not a number") from None
    if not (math.isfinite(value) and value >= 0):
        raise CommandError(f"{flag} must be a finite number >= 0 (0: no limit), got {text}")
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
            raise CommandError(f"--methods: unknown method {item!r}; expected a comma-separated subset of "
                         f"{', '.join(known)} (or 'ablation' for the four variants)")
    if not wanted:
        raise CommandError("--methods is empty")
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
    ref_cap = _int_option(args, "ref_spp_cap", "GRADSEP_EVAL_REF_SPP_CAP", "--ref-spp-cap", 1)
    if ref_cap is None:
        ref_cap = max(ref_spp, preset.ref_spp_cap)
    elif ref_cap < ref_spp:
        raise CommandError(f"--ref-spp-cap {ref_cap} is below --ref-spp {ref_spp}")
    ref_seconds = _float_option(args, "ref_seconds", "GRADSEP_EVAL_REF_SECONDS", "--ref-seconds")
    if ref_seconds is None:
        ref_seconds = preset.ref_seconds
    seed = _int_option(args, "seed", "GRADSEP_EVAL_SEED", "--seed", 0) or 0
    max_depth = _int_option(args, "max_depth", "GRADSEP_EVAL_MAX_DEPTH", "--max-depth", -1)
    if max_depth == 0:
        raise CommandError("--max-depth must be -1 (unbounded) or >= 1, got 0")
    table_spp = _int_option(args, "table_spp", "GRADSEP_EVAL_TABLE_SPP", "--table-spp", 1)
    if table_spp is not None and table_spp not in spp:
        raise CommandError(f"--table-spp {table_spp} is not one of the evaluated sample counts {list(spp)}")
    alpha_text = _option(args, "alpha", "GRADSEP_EVAL_ALPHA")
    alpha = DEFAULT_ALPHA
    if alpha_text is not None:
        try:
            alpha = float(alpha_text)
        except ValueError:
            raise CommandError(f"--alpha: {alpha_text!r} is not a number") from None
        if not (math.isfinite(alpha) and alpha > 0):
            raise CommandError(f"--alpha must be a finite number > 0, got {alpha_text}")
    cache = _option(args, "cache", "GRADSEP_CACHE")
    return EvalConfig(
        scenes=tuple(args.scenes) if getattr(args, "scenes", None) else (),
        spp=spp, width=width, height=height, ref_spp=ref_spp, output=Path(args.output),
        cache_dir=Path(cache) if cache else default_cache_dir(),
        models_dir=models_dir_from(getattr(args, "models", None)),
        methods=parse_methods(_option(args, "methods", "GRADSEP_EVAL_METHODS")),
        seed=seed, max_depth=max_depth, alpha=alpha, table_spp=table_spp, quick=quick, ref_spp_cap=ref_cap,
        ref_seconds=ref_seconds if ref_seconds > 0 else None)


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
        raise CommandError(f"scene {str(path)!r} not found (expected a Mitsuba XML file or procedural:SEED)")
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
    from renderer.procedural import parse_procedural  # numpy only: no Mitsuba to resolve the scene list

    for spec in specs:
        seed = parse_procedural(spec)
        if seed is not None:
            entries.append(_procedural_entry(seed))
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


def _procedural_entry(seed: int) -> SceneEntry:
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
            xml = Path(entry.identity["xml"])
            name = f"{xml.parent.parent.name}/{name}" if name == xml.parent.name else f"{xml.parent.name}/{name}"
        out.append(SceneEntry(entry.spec, name, entry.identity))
    return out
