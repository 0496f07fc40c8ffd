"""The plan cache (`gradsep render --gradients auto --plan-cache DIR`): a checkpoint's choice, kept for the next
frames of the same shot.

Why: `--gradients auto` judges its plan at a checkpoint on every frame (renderer/checkpoint.py), and the judgement
costs part of the frame's samples (its tile reconstructions, the reconstruction library's start-up, primal's cost
passes) whatever it decides; on held-out rooms it kept `direct-alternate` on most frames. A farm
renders a shot one frame per process. With a folder the shot's frames share, its first frame judges and writes
the decision; the others render the plan it chose as a fixed plan, at that plan's own cost, and carry its
judgement in their headers.

An entry is one JSON file named by the hash of its key (:func:`entry_key`): the scene (``--plan-key``, else the
scene file's content and its ``-D`` defines, or the procedural spec), the frame's size, layers, depth and shift,
the budget (``--seconds`` T or ``--spp`` N: the samples a plan gets decide which is better) and the machine's CPU
(model and count: what the budget buys). It holds the chosen plan, each judged plan's assessment and the
checkpoint's figures. Entries are written atomically, only by a frame whose checkpoint judged (a budget too small
for one leaves nothing to share); a farm's concurrent first frames each write theirs and the last one stays. An
entry that cannot be used (unreadable, another version or key, a plan this frame cannot render) is judged afresh
and replaced, with a note.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
import os
import platform
from pathlib import Path
from typing import Any

from gradsep.model.errors import CommandError

#: Version of an entry's layout; an entry of another version is judged afresh.
CACHE_VERSION = 1
#: The judging frame's own error estimate (renderer/check.py: its halves) in an entry and in a cached plan's trace:
#: {"relmse": at its samples, "spp": its samples}; a frame that reads the entry and has no check of its own carries
#: it to its samples (renderer.render.frame_check).
FRAME_ESTIMATE = "frame_estimate"
#: Environment variable naming the cache folder when ``--plan-cache`` is not given (a farm sets it once).
CACHE_ENV = "GRADSEP_PLAN_CACHE"


def check_folder(folder: str | os.PathLike[str]) -> Path:
    """``folder`` as the cache's: an existing folder this process can write, else a one-line user error."""
    path = Path(folder).expanduser()
    if not path.is_dir():
        raise CommandError(f"--plan-cache {folder}: not a folder (create it first; a farm's frames share it)")
    if not os.access(path, os.W_OK | os.X_OK):
        raise CommandError(f"--plan-cache {folder}: not writable")
    return path


def scene_identity(spec: str, defines: dict[str, str] | None = None) -> str:
    """What names a scene in an entry's key: a procedural spec as it is; a scene file by the SHA-256 of its bytes
    and its ``-D`` defines (the same shot in another checkout shares its entries; an edited file does not)."""
    if spec.startswith("procedural:"):
        return spec
    digest = hashlib.sha256(Path(spec).read_bytes()).hexdigest()
    given = ",".join(f"{k}={v}" for k, v in sorted((defines or {}).items()))
    return f"sha256:{digest}" + (f" defines:{given}" if given else "")


def cpu_identity() -> str:
    """The machine's CPU model and logical core count: what decides the samples a budget buys each plan."""
    from gradsep.model.environment import cpu_model

    return f"{cpu_model()} x{os.cpu_count() or 0}"


@dataclasses.dataclass(frozen=True)
class FrameKey:
    """The frame's part of an entry's key: its size, layers, depth and shift, and its budget (``seconds`` T or
    ``spp`` N)."""

    width: int
    height: int
    layers: tuple[str, ...]
    max_depth: int
    shift: str
    seconds: float | None
    spp: int | None


def entry_key(scene: str, frame: FrameKey, cpu: str | None = None) -> dict[str, Any]:
    """What must agree for two frames to share a decision (see the module docstring): the scene's identity, the
    frame's key and the CPU (default: this machine's)."""
    budget = f"seconds={frame.seconds:g}" if frame.seconds is not None else f"spp={frame.spp}"
    return {"scene": scene, "size": [frame.width, frame.height], "layers": list(frame.layers),
            "max_depth": frame.max_depth, "shift": frame.shift, "budget": budget,
            "cpu": cpu if cpu is not None else cpu_identity()}


@dataclasses.dataclass(frozen=True)
class CacheFolder:
    """``--plan-cache DIR`` and the scene's identity (:func:`scene_identity`, or ``--plan-key``): the frame's
    entry is made once its layers are known (:meth:`entry`)."""

    folder: Path
    scene: str

    def entry(self, frame: FrameKey) -> PlanCache:
        """The entry of this scene and frame."""
        return PlanCache(self.folder, entry_key(self.scene, frame))


class PlanCache:
    """One entry of the cache folder: :meth:`load` it before the frame, :meth:`store` a checkpoint's plan after."""

    def __init__(self, folder: Path, key: dict[str, Any]) -> None:
        self.key = key
        name = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:20]
        self.path = folder / f"plan-{name}.json"

    def load(self):  # -> tuple[renderer.checkpoint.Judgement | None, str | None]
        """(the cached plan, None), (None, None) where there is no entry, or (None, why) where the entry cannot be
        used: the frame judges afresh and replaces it."""
        from gradsep.renderer.checkpoint import Assessment, Judgement
        from gradsep.renderer.plans import judged_plans

        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return None, None
        except OSError as exc:
            return None, f"plan cache entry {self.path.name} not used ({exc}): judged afresh"
        try:
            data = json.loads(text)
            if not isinstance(data, dict) or data.get("version") != CACHE_VERSION:
                raise ValueError(f"not a version {CACHE_VERSION} entry")
            if data.get("key") != self.key:
                raise ValueError("its key differs from this frame's (a hash collision or an edited file)")
            judged = {c.name: c for c in judged_plans(tuple(self.key["layers"]))}
            chosen = judged.get(data.get("chosen"))
            if chosen is None:
                raise ValueError(f"plan {data.get('chosen')!r} is not one this frame can render")
            names = {f.name for f in dataclasses.fields(Assessment)}
            assessments = []
            for item in data["assessments"]:
                a = Assessment(**{k: v for k, v in item.items() if k in names})
                if a.name not in judged or not all(math.isfinite(float(getattr(a, n))) for n in
                                                   ("measured_relmse", "per_sample", "predicted_relmse",
                                                    "budget_spp", "exponent")):
                    raise ValueError(f"assessment of {a.name!r} is not usable")
                assessments.append(a)
            if chosen.name not in {a.name for a in assessments}:
                raise ValueError("the chosen plan has no assessment")
            trace = data.get("trace") or {}
            if not isinstance(trace, dict):
                raise ValueError("its trace is not an object")
            estimate = data.get(FRAME_ESTIMATE)
            if estimate is not None:
                relmse, spp = float(estimate["relmse"]), int(estimate["spp"])
                if not (math.isfinite(relmse) and relmse >= 0 and spp > 0):
                    raise ValueError("its frame estimate is not usable")
                trace = {**trace, FRAME_ESTIMATE: {"relmse": relmse, "spp": spp}}
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            return None, f"plan cache entry {self.path.name} not used ({exc}): judged afresh"
        note = f"judged by an earlier frame (plan cache {self.path.name})"
        return Judgement(chosen, assessments, 0.0, note, {**trace, "cached": self.path.name}), None

    def store(self, judgement: Any, seed: int, estimate: tuple[float, int] | None = None) -> str | None:
        """Write ``judgement`` (renderer.checkpoint.Judgement, a checkpoint's: with assessments) as the entry, with
        the frame's own error estimate (RelMSE, at its spp) where it made one; returns a note where it could not be
        written (the frame is kept either way)."""
        from gradsep.model.exr_write import write_bytes_atomic

        entry: dict[str, Any] = {
            "version": CACHE_VERSION, "key": self.key, "chosen": judgement.chosen.name,
            "assessments": [dataclasses.asdict(a) for a in judgement.assessments], "trace": judgement.trace,
            "judged": {"seed": seed, "host": platform.node(),
                       "at": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}}
        if estimate is not None and math.isfinite(estimate[0]):
            entry[FRAME_ESTIMATE] = {"relmse": estimate[0], "spp": estimate[1]}
        try:
            self.path.parent.mkdir(exist_ok=True)  # a hidden shot folder is made by its first entry, not up front
            write_bytes_atomic(self.path, (json.dumps(entry, indent=1) + "\n").encode())
        except OSError as exc:
            return f"plan cache entry {self.path.name} not written ({exc})"
        return None
