"""The evaluation's cache: rendered frames, references and per-method results, keyed by what determines them.

A full evaluation renders dozens of frames and minutes of references; a rerun after, say, a new model should
redo only the network rows. So every cached item lives under a file name that reads like its settings (scene,
size, spp, seed) followed by a short hash of *everything* that determines its content:

* frames: the scene's identity (XML bytes, or procedural seed + generator version), size, max depth, spp, seed,
  the Mitsuba version/variant and the renderer's source files;
* references: the same, with the reference module's sources and the reference spp and seed;
* results: the frame and reference keys, the method, its parameters, the SHA-256 of every model file it uses
  and the source of the code that runs and scores it.

Source files count by their *code* (:func:`code_sha256`: the syntax tree without docstrings, so comments,
docstrings and formatting do not count): changing renderer code therefore re-renders, while a comment or docstring
edit keeps a farm's cached shards valid. A procedural scene counts by its seed, family and the generator's
``GENERATOR_VERSION`` (not by renderer/procedural.py's source, which also holds the other families: a pinned
fingerprint test fails when a family's scenes change and the version was not bumped). A new
``models/direct.onnx`` recomputes ``ours`` only, and a changed reference spp re-renders the references and
rescores every method but reuses the frames. A cache file
that cannot be read (truncated by a crash, edited by hand) is treated as missing and recomputed, never trusted.
Writes are atomic (temporary file + rename), so an interrupted run leaves no half-written entries.
"""

from __future__ import annotations

import ast
import hashlib
import io
import json
import os
import re
from collections.abc import Iterable, Mapping
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.model.exr_write import write_bytes_atomic

__all__ = ["EvalCache", "code_sha256", "default_cache_dir", "file_sha256", "key_hash", "mitsuba_id", "oidn_key", "slug",
           "sources_sha256"]

REPO_ROOT = Path(__file__).resolve().parents[1]


def default_cache_dir() -> Path:
    """$GRADSEP_CACHE, else $XDG_CACHE_HOME/gradsep, else ~/.cache/gradsep; the evaluation uses ``evaluate/``.

    Outside the report folder on purpose: a report is meant to be committed, its gigabyte of EXR frames not.
    """
    explicit = os.environ.get("GRADSEP_CACHE")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "gradsep"


def key_hash(key: Mapping[str, Any], length: int = 16) -> str:
    """A short stable hash of a JSON-serialisable key (sorted keys, so dict order does not matter)."""
    text = json.dumps(key, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def code_sha256(source: str | bytes) -> str:
    """SHA-256 of a Python module's code: its syntax tree with every docstring removed, so comments, docstrings,
    blank lines and formatting do not change it and any change to what the code does does. A file that does not
    parse (not Python) is hashed as its bytes. The tree's dump depends on the Python version (3.12 added node
    fields), so, like the Mitsuba version in the keys, a farm's workers sharing a cache run one image."""
    try:
        tree = ast.parse(source)
    except (SyntaxError, ValueError):
        raw = source.encode() if isinstance(source, str) else source
        return hashlib.sha256(raw).hexdigest()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return hashlib.sha256(ast.dump(tree, include_attributes=False).encode()).hexdigest()


@cache
def _source_sha256(relative: str) -> str:
    path = REPO_ROOT / relative
    if not path.is_file():
        return "absent"
    return code_sha256(path.read_bytes()) if path.suffix == ".py" else file_sha256(path)


def sources_sha256(relatives: Iterable[str]) -> str:
    """One hash over the given repository source files, each by its code (:func:`code_sha256`): code that changes
    their output invalidates what they made; a comment or docstring edit does not."""
    return key_hash({rel: _source_sha256(rel) for rel in sorted(relatives)}, length=64)


def slug(text: str) -> str:
    """A file-name-safe rendering of a scene or method name (``procedural:90001`` -> ``procedural-90001``)."""
    out = re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-.")
    return out or "unnamed"


class EvalCache:
    """A folder of cached items; see the module docstring for what the keys contain."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)

    def entry(self, kind: str, scene: str, stem: str, key: Mapping[str, Any], suffix: str) -> Path:
        """``ROOT/kind/scene/stem-HASH.suffix``: a readable name plus the hash of the full key."""
        return self.root / kind / slug(scene) / f"{slug(stem)}-{key_hash(key)}{suffix}"

    def prepare(self) -> None:
        """Create the root, with a clear error when that is impossible."""
        self.root.mkdir(parents=True, exist_ok=True)

    # -------------------------------------------------------------------------------------------- json + npz

    @staticmethod
    def load_json(path: Path) -> dict[str, Any] | None:
        """The cached JSON object, or None when absent or unreadable (then it is recomputed)."""
        try:
            with open(path, encoding="utf-8") as fh:
                data = json.load(fh)
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) else None

    @staticmethod
    def save_json(path: Path, data: Mapping[str, Any]) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(path, json.dumps(data, indent=1, sort_keys=True, default=_json_default).encode())

    @staticmethod
    def load_arrays(path: Path, names: Iterable[str]) -> dict[str, np.ndarray] | None:
        """Named float32 arrays from an .npz, or None when absent, unreadable, non-finite or incomplete."""
        try:
            with np.load(path, allow_pickle=False) as data:
                out = {name: np.asarray(data[name], dtype=np.float32) for name in names}
        except (OSError, ValueError, KeyError, EOFError):
            return None
        if not all(np.all(np.isfinite(a)) for a in out.values()):
            return None
        return out

    @staticmethod
    def save_arrays(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **{k: np.asarray(v, dtype=np.float32) for k, v in arrays.items()})
        write_bytes_atomic(path, buffer.getvalue())


def _json_default(value: Any) -> Any:
    """numpy scalars and paths in cached JSON."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


_MITSUBA: str | None = None


def mitsuba_id() -> str:
    """Mitsuba version + variant: a different build may sample differently, so it is part of render keys."""
    global _MITSUBA
    if _MITSUBA is None:
        import mitsuba as mi

        from gradsep.renderer.variant import select_variant

        _MITSUBA = f"{mi.__version__}/{select_variant()}"
    return _MITSUBA


def oidn_key() -> dict[str, str]:
    """The OIDN choice the environment makes (``$GRADSEP_OIDN_SETTING``), in every method's cache key: it changes
    the OIDN methods' images (and so every equal-time budget) without a code change. Empty at the default, so
    results cached before this key existed stay valid."""
    from gradsep.model.oidn import METHOD_SETTING, method_setting

    setting = method_setting()
    return {"oidn_setting": setting} if setting != METHOD_SETTING else {}
