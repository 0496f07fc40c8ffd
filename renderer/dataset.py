"""`gradsep dataset`: procedural G-PT training frames plus a manifest; shardable across a farm, resumable.

Layout of a dataset folder ``DIR`` (docs/training.md, "Datasets", has the full description)::

    DIR/frames/proc_001000.exr           one frame per seed (the frame contract, written atomically)
    DIR/frames/proc_001000.b.exr         with ``--pairs``: an independent second realization of the same frame
                                         (another sampler seed), the Noise2Noise target of training
    DIR/manifest.d/shard-0-of-4.json     what shard 0 of 4 has finished: written only by that shard
    DIR/manifest.json                    all parts merged: what training reads

Frames are rendered to a sample count (``--spp S``) or to a wall-time budget (``--seconds T``: each frame, and
each pair's second realization, through the render planner of `gradsep render --seconds T`, renderer/planner.py,
with the plan training reads, DATASET_PLAN; each record keeps the samples its budget bought).

Why it is built this way:

* **Concurrent shards never clobber each other.** A shard writes only its own part file (atomically: temp file
  plus rename) and holds an exclusive ``flock`` on ``shard-i-of-n.lock`` while it runs, so a second process
  started on the same shard is refused. ``manifest.json`` is rebuilt from every part under a folder-wide merge
  lock, after the part is written, so the last merge always sees every finished frame.
* **Resume never redoes a finished frame and never trusts an unfinished one.** A frame counts as finished only
  when its EXR was renamed into place *and* a part records it (with its size and SHA-256); a run skips exactly
  those. An EXR without a record (killed between the two steps) is rendered again.
* **The manifest hash names the data.** :func:`manifest_hash` covers the render settings and every frame's file
  name, seed and SHA-256 (so any changed byte changes it), not timings, shard layout or completion times, so
  re-merging or moving a dataset keeps it; the exporter records it next to a trained model. Re-rendering gives a
  new hash: frame headers carry render times, and Mitsuba orders a scene's emitters differently from process to
  process, so renders with one seed are equal in distribution, not bit for bit.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import hashlib
import json
import os
import re
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from gradsep.model.errors import CommandError
from gradsep.model.exr_write import write_bytes_atomic
from gradsep.model.progress import ProgressBar

MANIFEST_VERSION = 1
MANIFEST_NAME = "manifest.json"
PARTS_DIR = "manifest.d"
FRAMES_DIR = "frames"
MERGE_LOCK = ".manifest.lock"
MERGE_INTERVAL_S = 10.0  # re-merge manifest.json at most this often while rendering (and always at the end)
MAX_SIDE = 8192  # the frame contract's reading budget is 8192 x 8192 pixels


class DatasetError(CommandError):
    """A bad dataset request or folder; printed as one line by the CLI (exit status 2)."""


# ----------------------------------------------------------------------------------------------------------
# Records and the manifest
# ----------------------------------------------------------------------------------------------------------

@dataclass
class FrameRecord:
    """One finished frame, as stored in a manifest part and in manifest.json."""

    file: str                  # relative to the dataset folder, e.g. "frames/proc_001000.exr"
    seed: int                  # procedural scene seed (scene "procedural:<seed>", or "procedural:<family>:<seed>")
    spp: int                   # the frame's samples (with --seconds: what its budget bought)
    render_seconds: float
    layers: list[str]          # illumination layers present, e.g. ["direct", "indirect"]
    shard: str                 # "i/n" of the job that rendered it
    sampler_seed: int = 0      # the G-PT sampler seed (the scene seed modulo 2^32)
    bytes: int = 0             # file size, checked on resume
    sha256: str = ""           # of the EXR file: part of the manifest hash
    finished_at: str = ""      # UTC, ISO 8601
    target: str = ""           # with --pairs: the second realization, e.g. "frames/proc_001000.b.exr"
    target_sampler_seed: int = 0
    target_bytes: int = 0
    target_sha256: str = ""

    @classmethod
    def from_json(cls, item: dict[str, Any], where: str) -> FrameRecord:
        try:
            return cls(file=str(item["file"]), seed=int(item["seed"]), spp=int(item["spp"]),
                       render_seconds=float(item["render_seconds"]), layers=[str(x) for x in item["layers"]],
                       shard=str(item.get("shard", "")), sampler_seed=int(item.get("sampler_seed", 0)),
                       bytes=int(item.get("bytes", 0)), sha256=str(item.get("sha256", "")),
                       finished_at=str(item.get("finished_at", "")), target=str(item.get("target", "")),
                       target_sampler_seed=int(item.get("target_sampler_seed", 0)),
                       target_bytes=int(item.get("target_bytes", 0)),
                       target_sha256=str(item.get("target_sha256", "")))
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetError(f"{where}: malformed frame record {item!r} ({exc})") from None


@dataclass
class Manifest:
    """A dataset's manifest: render settings and the finished frames, sorted by seed."""

    spp: int | None                            # None: each frame rendered to ``seconds`` (its spp in its record)
    size: tuple[int, int]                      # (width, height)
    frames: list[FrameRecord]
    count: int = 0                             # frames requested (the largest count any run asked for)
    first_seed: int = 0
    max_depth: int | None = None               # None: the procedural generator's default
    generator_version: int = 0
    pairs: bool = False                        # every frame has an independent second realization (target)
    family: str = "mixed"                      # the procedural family (renderer.procedural.FAMILIES)
    seconds: float | None = None               # --seconds: each frame's wall-time budget
    version: int = MANIFEST_VERSION
    root: Path | None = field(default=None, compare=False)  # the dataset folder (when loaded from disk)

    def to_json(self) -> dict[str, Any]:
        done = {f.seed for f in self.frames}
        missing = [s for s in range(self.first_seed, self.first_seed + self.count) if s not in done]
        return {"version": self.version, "spp": self.spp, "size": list(self.size), "count": self.count,
                "first_seed": self.first_seed, "max_depth": self.max_depth,
                "generator_version": self.generator_version, "pairs": self.pairs,
                **({"family": self.family} if self.family != "mixed" else {}),
                **({"seconds": self.seconds} if self.seconds is not None else {}), "complete": not missing,
                "missing": len(missing), "hash": manifest_hash(self),
                "frames": [asdict(f) for f in self.frames]}

    def paths(self) -> list[Path]:
        """Absolute paths of the frames (needs ``root``: a manifest loaded with :func:`load_manifest`)."""
        if self.root is None:
            raise DatasetError("this manifest was not loaded from a folder; its frame paths are unknown")
        return [self.root / f.file for f in self.frames]

    @property
    def hash(self) -> str:
        return manifest_hash(self)


def manifest_hash(manifest: Manifest | str | os.PathLike[str]) -> str:
    """SHA-256 of what defines the data: settings plus each frame's file, seed, spp, layers and file SHA-256.

    Timings, shard layout and completion times are left out: re-rendering the same frames with another farm
    layout gives the same hash, while any changed pixel changes it.
    """
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    content: dict[str, Any] = {
        "version": m.version, "spp": m.spp, "size": list(m.size), "max_depth": m.max_depth,
        "generator_version": m.generator_version,
        "frames": [[f.file, f.seed, f.spp, sorted(f.layers), f.sha256,
                    *([f.target, f.target_sha256] if f.target else [])]
                   for f in sorted(m.frames, key=lambda f: f.seed)]}
    if m.pairs:  # only then, so the hash of a dataset without pairs is what it always was
        content["pairs"] = True
    if m.family != "mixed":  # likewise: the room family's datasets keep their hash
        content["family"] = m.family
    if m.seconds is not None:  # and a dataset rendered to a sample count
        content["seconds"] = m.seconds
    text = json.dumps(content, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def load_manifest(folder: str | os.PathLike[str], *, check_files: bool = True) -> Manifest:
    """The dataset in ``folder``: manifest.json, or the merge of manifest.d/ when manifest.json is absent.

    ``check_files``: every listed frame must exist with its recorded size (a clear error names the first that
    does not), so training fails before an epoch rather than in the middle of one.
    """
    root = Path(folder)
    path = root / MANIFEST_NAME
    if path.is_file():
        data = _read_json(path)
        manifest = _manifest_from_json(data, str(path))
    elif (root / PARTS_DIR).is_dir():
        manifest = _merge_parts(root)
    else:
        raise DatasetError(f"{root} is not a dataset folder (no {MANIFEST_NAME} and no {PARTS_DIR}/)")
    manifest.root = root.resolve()
    if check_files:
        for rec in manifest.frames:
            for file, size in ((rec.file, rec.bytes), (rec.target, rec.target_bytes)):
                if not file:
                    continue
                frame = root / file
                if not frame.is_file():
                    raise DatasetError(f"{root}: frame {file} listed in the manifest is missing")
                if size and frame.stat().st_size != size:
                    raise DatasetError(f"{root}: frame {file} has {frame.stat().st_size} bytes, the manifest "
                                       f"recorded {size} (truncated or replaced)")
    return manifest


def _manifest_from_json(data: Any, where: str) -> Manifest:
    if not isinstance(data, dict):
        raise DatasetError(f"{where}: expected a JSON object")
    version = data.get("version")
    if version != MANIFEST_VERSION:
        raise DatasetError(f"{where}: manifest version {version!r} is not supported (expected {MANIFEST_VERSION})")
    try:
        size = data["size"]
        if not (isinstance(size, list) and len(size) == 2):
            raise ValueError("size must be [width, height]")
        frames = [FrameRecord.from_json(item, where) for item in data["frames"]]
        return Manifest(spp=_optional(data["spp"], int), size=(int(size[0]), int(size[1])),
                        frames=sorted(frames, key=lambda f: f.seed), count=int(data.get("count", len(frames))),
                        first_seed=int(data.get("first_seed", min((f.seed for f in frames), default=0))),
                        max_depth=None if data.get("max_depth") is None else int(data["max_depth"]),
                        generator_version=int(data.get("generator_version", 0)), pairs=bool(data.get("pairs", False)),
                        family=str(data.get("family", "mixed")), seconds=_optional(data.get("seconds"), float))
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{where}: malformed manifest ({exc})") from None


def _optional(value: Any, kind: type) -> Any:
    return None if value is None else kind(value)


# ----------------------------------------------------------------------------------------------------------
# Parts, locks and merging
# ----------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Job:
    """The settings of one `gradsep dataset` run (what must agree across the parts of a folder)."""

    count: int
    spp: int | None  # None: each frame rendered to ``seconds``
    width: int
    height: int
    first_seed: int
    max_depth: int | None
    shard: int
    shards: int
    generator_version: int
    pairs: bool = False
    family: str = "mixed"  # the procedural family of the scenes (renderer.procedural.FAMILIES)
    seconds: float | None = None  # --seconds: each frame's wall-time budget (instead of ``spp``)

    @property
    def shard_name(self) -> str:
        return f"{self.shard}/{self.shards}"

    def params(self) -> dict[str, Any]:
        params = {"spp": self.spp, "size": [self.width, self.height], "first_seed": self.first_seed,
                  "max_depth": self.max_depth, "generator_version": self.generator_version}
        if self.pairs:  # only then, so folders rendered before --pairs existed stay compatible
            params["pairs"] = True
        if self.family != "mixed":  # likewise for folders rendered before --family existed
            params["family"] = self.family
        if self.seconds is not None:  # and before --seconds
            params["seconds"] = self.seconds
        return params

    def scene(self, seed: int) -> str:
        """The scene spec of frame ``seed``: ``procedural:SEED`` (rooms) or ``procedural:FAMILY:SEED``."""
        from gradsep.renderer.procedural import ProceduralSpec

        return str(ProceduralSpec(seed, self.family))

    def seeds(self) -> list[int]:
        """This shard's frames: i, i+n, i+2n, ... of the whole dataset, as scene seeds."""
        return [self.first_seed + i for i in range(self.shard, self.count, self.shards)]


def part_path(root: Path, shard: int, shards: int) -> Path:
    return root / PARTS_DIR / f"shard-{shard}-of-{shards}.json"


def _read_parts(root: Path) -> list[tuple[Path, dict[str, Any]]]:
    parts_dir = root / PARTS_DIR
    if not parts_dir.is_dir():
        return []
    out = []
    for path in sorted(parts_dir.glob("shard-*-of-*.json")):
        data = _read_json(path)
        if not isinstance(data, dict) or data.get("version") != MANIFEST_VERSION or "params" not in data:
            raise DatasetError(f"{path}: not a manifest part of version {MANIFEST_VERSION}")
        out.append((path, data))
    return out


def _merge_parts(root: Path) -> Manifest:
    """All parts of ``root`` as one manifest; one record per seed (the latest finished, should two exist)."""
    parts = _read_parts(root)
    if not parts:
        raise DatasetError(f"{root}: no manifest parts in {PARTS_DIR}/")
    params = parts[0][1]["params"]
    for path, data in parts[1:]:
        if data["params"] != params:
            raise DatasetError(f"{path}: settings {data['params']} differ from {parts[0][0].name}'s {params}")
    by_seed: dict[int, FrameRecord] = {}
    count = 0
    for path, data in parts:
        count = max(count, int(data.get("count", 0)))
        for item in data.get("frames", []):
            rec = FrameRecord.from_json(item, str(path))
            old = by_seed.get(rec.seed)
            if old is None or rec.finished_at > old.finished_at:
                by_seed[rec.seed] = rec
    return Manifest(spp=_optional(params["spp"], int), size=(int(params["size"][0]), int(params["size"][1])),
                    frames=[by_seed[s] for s in sorted(by_seed)], count=count,
                    first_seed=int(params["first_seed"]), max_depth=params["max_depth"],
                    generator_version=int(params["generator_version"]), pairs=bool(params.get("pairs", False)),
                    family=str(params.get("family", "mixed")), seconds=_optional(params.get("seconds"), float))


def merge_manifest(root: str | os.PathLike[str]) -> Manifest:
    """Rebuild ``manifest.json`` from every part present, under the folder's merge lock; returns it."""
    root = Path(root)
    with _flock(root / MERGE_LOCK, blocking=True):
        manifest = _merge_parts(root)
        _write_json_atomic(root / MANIFEST_NAME, manifest.to_json())
    manifest.root = root.resolve()
    return manifest


@contextlib.contextmanager
def _flock(path: Path, *, blocking: bool) -> Iterator[None]:
    """An exclusive advisory lock on ``path`` (released by the kernel even if the process dies)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except BlockingIOError:
            raise DatasetError(f"{path.name} is held by another running process "
                               f"(this shard is already being rendered)") from None
        yield
    finally:
        os.close(fd)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from None


def _write_json_atomic(path: Path, data: Any) -> None:
    """Readers see the old or the new file, never a partial one."""
    write_bytes_atomic(path, (json.dumps(data, indent=1) + "\n").encode())


def _check_compatible(root: Path, job: Job) -> None:
    """Refuse to mix settings in one folder: every part must have been rendered with this job's settings."""
    for path, data in _read_parts(root):
        if data["params"] != job.params():
            theirs, ours = data["params"], job.params()
            keys = [*ours, *(k for k in theirs if k not in ours)]  # a key only one side has (pairs, family) too
            diff = ", ".join(f"{k} {theirs.get(k)!r} (this run: {ours.get(k)!r})" for k in keys
                             if theirs.get(k) != ours.get(k))
            raise DatasetError(f"{root} already holds frames rendered with other settings ({path.name}: {diff}); "
                               "use a new folder or the same settings")


def finished_frames(root: Path) -> dict[int, FrameRecord]:
    """Frames recorded by any part whose EXR is in place with the recorded size: the ones a run may skip."""
    done: dict[int, FrameRecord] = {}
    for path, data in _read_parts(root):
        for item in data.get("frames", []):
            rec = FrameRecord.from_json(item, str(path))
            if all(_intact(root / file, size) for file, size in ((rec.file, rec.bytes), (rec.target, rec.target_bytes))
                   if file):
                done[rec.seed] = rec
    return done


def _intact(path: Path, size: int) -> bool:
    return path.is_file() and (not size or path.stat().st_size == size)


# ----------------------------------------------------------------------------------------------------------
# The job
# ----------------------------------------------------------------------------------------------------------

def frame_file(seed: int) -> str:
    return f"{FRAMES_DIR}/proc_{seed:06d}.exr"


def target_file(seed: int) -> str:
    """The second realization of frame ``seed`` (``--pairs``)."""
    return f"{FRAMES_DIR}/proc_{seed:06d}.b.exr"


def target_sampler_seed(seed: int) -> int:
    """The second realization's sampler seed: the frame's own seed with the top bit flipped, so it differs from
    every frame's first-realization seed of any dataset with seeds below 2^31 (the sampler hashes the seed with
    the pixel index, sample_tea_32, so distinct seeds give independent streams)."""
    return (seed % 2**32) ^ 2**31

def run_dataset(root: str | os.PathLike[str], job: Job, *, progress: bool | None = None) -> Manifest:
    """Render this shard's unfinished frames into ``root``; returns the merged manifest afterwards."""

    root = Path(root)
    own_path = part_path(root, job.shard, job.shards)
    created = [p for p in (root, root / FRAMES_DIR, root / PARTS_DIR, root / MANIFEST_NAME,
                           own_path.with_suffix(".lock"), root / MERGE_LOCK) if not p.exists()]
    had_part = own_path.is_file()
    state = _RunState()
    try:
        return _run_dataset(root, job, progress, state)
    except BaseException:
        if state.locked and not state.started and not had_part:  # never undo another process's start
            _undo_start(root, own_path, created)
        raise


@dataclass
class _RunState:
    locked: bool = False  # this run holds its shard's lock (so the shard's part is its own)
    started: bool = False  # this run recorded a finished frame: from then on, nothing is undone


def _undo_start(root: Path, own_path: Path, created: list[Path]) -> None:
    """A run that failed before its first frame removes what it created: its frameless part (so the folder no
    longer claims its settings and the corrected retry is not refused), then -- only where this run created
    them and nothing else is left in them -- the merged manifest, the lock files and the folders. Never another
    shard's file: folders are shared by the shards of a farm, which may be writing into them right now."""
    with contextlib.suppress(OSError, ValueError, DatasetError):
        if own_path.is_file() and not _read_json(own_path).get("frames"):
            own_path.unlink()
        others = (root / PARTS_DIR).is_dir() and any((root / PARTS_DIR).glob("*.json"))
        if others:
            merge_manifest(root)  # the merge without this run's part
        else:  # no shard has a part here: nobody merges, so this run's manifest and merge lock can go
            for path in (root / MANIFEST_NAME, root / MERGE_LOCK):
                if path in created:
                    path.unlink(missing_ok=True)
        if own_path.with_suffix(".lock") in created:
            own_path.with_suffix(".lock").unlink(missing_ok=True)
        for folder in (root / FRAMES_DIR, root / PARTS_DIR):
            if folder in created:
                with contextlib.suppress(OSError):
                    folder.rmdir()  # only when empty
        if root in created:
            root.rmdir()  # only when empty


def _run_dataset(root: Path, job: Job, progress: bool | None, state: _RunState) -> Manifest:
    (root / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
    (root / PARTS_DIR).mkdir(exist_ok=True)
    with _flock(part_path(root, job.shard, job.shards).with_suffix(".lock"), blocking=False):
        state.locked = True
        _check_compatible(root, job)
        own_path = part_path(root, job.shard, job.shards)
        own: list[dict[str, Any]] = []
        count = job.count
        if own_path.is_file():
            previous = _read_json(own_path)
            own = list(previous.get("frames", []))
            count = max(count, int(previous.get("count", 0)))  # a shorter rerun does not shrink the dataset
        done = finished_frames(root)
        todo = [s for s in job.seeds() if s not in done]
        pending = set(todo)
        own = [item for item in own if int(item["seed"]) not in pending]  # records whose file is gone or cut
        _write_part(own_path, job, own, count)  # claims the settings in the folder even before the first frame
        last_merge = 0.0
        bar = _bar(len(todo), len(job.seeds()) - len(todo), job, progress)
        try:
            for seed in todo:
                rel = frame_file(seed)
                frame, data = _render_to(root, rel, job, seed, seed % 2**32)
                record = FrameRecord(
                    file=rel, seed=seed, spp=int(frame.metadata.get("gradsep.spp", job.spp or 0)),
                    render_seconds=float(frame.metadata.get("gradsep.render_seconds", "nan")),
                    layers=list(frame.layers), shard=job.shard_name, sampler_seed=seed % 2**32, bytes=len(data),
                    sha256=hashlib.sha256(data).hexdigest())
                if job.pairs:
                    record.target, record.target_sampler_seed = target_file(seed), target_sampler_seed(seed)
                    _, blob = _render_to(root, record.target, job, seed, record.target_sampler_seed)
                    record.target_bytes, record.target_sha256 = len(blob), hashlib.sha256(blob).hexdigest()
                record.finished_at = _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")
                own.append(asdict(record))
                _write_part(own_path, job, own, count)  # the frame is finished from here on
                state.started = True
                bar.update(1)
                if time.monotonic() - last_merge > MERGE_INTERVAL_S:
                    merge_manifest(root)
                    last_merge = time.monotonic()
        finally:
            bar.close()
            merge_manifest(root)
    return load_manifest(root, check_files=False)


#: The plan of a frame rendered with --seconds: every layer's gradients, what training reads
#: (model.preprocess.layer_planes) and what a --spp dataset frame has. `auto` may choose a plain frame.
DATASET_PLAN = "all"


def _render_to(root: Path, rel: str, job: Job, seed: int, sampler_seed: int) -> tuple[Any, bytes]:
    """Render procedural scene ``seed`` with ``sampler_seed`` into ``root/rel`` (atomically); (frame, file bytes).
    With ``job.seconds`` the frame's budget counts from here (its scene's load) to its file in place: the render
    planner's deadline (renderer/planner.py, as `gradsep render --seconds`), which reserves the write."""
    from gradsep.model.exr_write import write_frame
    from gradsep.renderer import render

    if job.seconds is None:
        frame = render.render_frame(job.scene(seed), spp=job.spp or 0, seed=sampler_seed,
                                    options=render.FrameOptions(width=job.width, height=job.height,
                                                                max_depth=job.max_depth))
    else:
        from gradsep.renderer import planned_frame
        from gradsep.renderer.budget import Deadline
        from gradsep.renderer.frame_budget import FrameBudget
        from gradsep.renderer.scene import load_scene

        budget = FrameBudget(Deadline(job.seconds))
        loaded = load_scene(job.scene(seed), width=job.width, height=job.height, max_depth=job.max_depth)
        frame, _ = planned_frame.render_planned_frame(loaded, budget, planned_frame.PlanRequest(
            seed=sampler_seed, gradients=DATASET_PLAN))
    write_frame(root / rel, frame)  # atomic: temp file + rename
    return frame, (root / rel).read_bytes()


def _write_part(path: Path, job: Job, frames: list[dict[str, Any]], count: int) -> None:
    _write_json_atomic(path, {"version": MANIFEST_VERSION, "shard": job.shard_name, "count": count,
                              "params": job.params(), "frames": sorted(frames, key=lambda f: int(f["seed"]))})


def _bar(total: int, skipped: int, job: Job, progress: bool | None) -> ProgressBar:
    """A bar over this run's frames with ETA; frames finished by earlier runs are named in the label."""
    label = f"dataset shard {job.shard_name}" + (f" ({skipped} done before)" if skipped else "")
    return ProgressBar(total, enabled=progress, desc=label, unit="frame")


# ----------------------------------------------------------------------------------------------------------
# Command
# ----------------------------------------------------------------------------------------------------------

def parse_size(text: str) -> tuple[int, int]:
    """``"256x256"`` -> (256, 256); a clear error otherwise."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text or "")
    if not m:
        raise DatasetError(f"--size must be WIDTHxHEIGHT (e.g. 256x256), got {text!r}")
    w, h = int(m.group(1)), int(m.group(2))
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise DatasetError(f"--size {w}x{h}: width and height must be between 1 and {MAX_SIDE}")
    return w, h


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/n"`` -> (i, n) with 0 <= i < n; a clear error otherwise."""
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text or "")
    if not m:
        raise DatasetError(f"--shard must be i/n (e.g. 0/4 for the first of four shards), got {text!r}")
    i, n = int(m.group(1)), int(m.group(2))
    if n < 1 or i >= n:
        raise DatasetError(f"--shard {i}/{n}: need n >= 1 and 0 <= i < n (shards are numbered from 0)")
    return i, n


@dataclass(frozen=True)
class JobOptions:
    """`gradsep dataset`'s options as given, before :func:`make_job` validates them into a :class:`Job`."""

    count: int
    spp: int | None
    size: str  # WxH
    shard: str  # i/n
    first_seed: int
    max_depth: int | None
    pairs: bool = False
    family: str = "mixed"
    seconds: object = None  # a wall-time budget per frame (instead of ``spp``), checked by renderer.budget


def make_job(options: JobOptions) -> Job:
    """Validate the command's options into a :class:`Job`: exactly one of ``spp`` and ``seconds``."""
    from gradsep.renderer.budget import check_seconds
    from gradsep.renderer.procedural import FAMILIES
    from gradsep.renderer.procedural_builder import GENERATOR_VERSION

    o = options
    if (o.spp is None) == (o.seconds is None):
        raise DatasetError("give exactly one of --spp (samples per pixel) or --seconds (a wall-time budget per frame)")
    budget = None
    if o.seconds is not None:
        try:
            budget = check_seconds(o.seconds)
        except CommandError as exc:
            raise DatasetError(str(exc)) from None

    if o.family not in FAMILIES:
        raise DatasetError(f"--family must be one of {', '.join(FAMILIES)}, got {o.family!r}")
    if o.count < 1:
        raise DatasetError(f"--count must be a positive integer, got {o.count}")
    if o.spp is not None and o.spp < 1:
        raise DatasetError(f"--spp must be a positive integer, got {o.spp}")
    if o.first_seed < 0:
        raise DatasetError(f"--first-seed must be non-negative, got {o.first_seed}")
    if o.max_depth is not None and (o.max_depth == 0 or o.max_depth < -1):
        raise DatasetError(f"--max-depth must be -1 (unbounded) or a positive integer, got {o.max_depth}")
    w, h = parse_size(o.size)
    i, n = parse_shard(o.shard)
    return Job(count=o.count, spp=o.spp, width=w, height=h, first_seed=o.first_seed, max_depth=o.max_depth, shard=i,
               shards=n, generator_version=GENERATOR_VERSION, pairs=o.pairs, family=o.family, seconds=budget)
