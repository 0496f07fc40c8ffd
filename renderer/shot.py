"""`gradsep render SCENE --frames A-B -o out.%04d.exr`: a shot, one frame file per frame number.

A shot is a pattern of per-frame XML files (``scene.%04d.xml``) or one scene whose ``$NAME`` parameters vary
(``--animate NAME=START:END``, linear over the shot; ``-D`` fixes the others). Everything the shot needs is
checked before its first frame renders: the frame range and patterns, every per-frame XML of this shard (and the
neighbours its motion vectors need), every animated parameter, and the frames already on disk. A frame already
complete on disk -- a readable EXR whose header names this frame of this shot with these settings (its settings
hash, :data:`SETTINGS_KEY`) -- is skipped, so a restarted task does not redo work; a file at a frame's path that
is not (another shot or other settings, or not a frame) is refused before anything renders, never overwritten.

Each frame gets its own sampler seed (model.shot.frame_seed of ``--seed`` and the frame number), its own
``--seconds`` budget (the first frame's counts from the process's start, the others from their scene's load),
and ``--gradients auto`` judges once per shot: the frames share one plan-cache entry (``--plan-cache``, else a
hidden ``.gradsep-plans`` folder beside the outputs) keyed by the shot, not by each frame's scene. Scenes are
loaded once per frame; Dr.Jit reuses the compiled kernels of a scene of the same structure.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gradsep.model.errors import CommandError
from gradsep.model.shot import (
    Animation,
    FramePattern,
    frame_seed,
    parse_animations,
    parse_frames,
    parse_shard,
    shard_frames,
    shot_name,
)
from gradsep.renderer.scene import ANIMATE_PREFIX

FRAME_KEY = "gradsep.frame"
SHOT_KEY = "gradsep.shot"
#: A hash of everything that decides a frame's pixels (scene, defines, animation, budget, plan flags, seed): a
#: frame on disk with another hash is not this shot's frame.
SETTINGS_KEY = "gradsep.shot_settings"
#: The plan cache's folder beside the outputs when ``--plan-cache`` is not given.
HIDDEN_PLAN_CACHE = ".gradsep-plans"

#: The command-line settings that decide a frame's pixels, hashed into :data:`SETTINGS_KEY`.
_SETTING_NAMES = ("spp", "seconds", "width", "height", "max_depth", "seed", "layers", "shift", "gradients",
                  "offsets", "gradient_spp", "no_gradients")


@dataclass(frozen=True)
class RenderCall:
    """One frame's render: its sampler ``seed``, its ``deadline`` (``--seconds``; None with ``--spp``), the plan's
    ``gradients`` and the plan cache's entry folder and scene identity (``auto`` only; None: no cache)."""

    seed: int
    deadline: Any
    gradients: str
    plan_cache: Any = None


@dataclass(frozen=True)
class Shot:
    """A checked shot: its scene (a per-frame ``pattern`` or one XML ``scene``), frames, output pattern, animated
    parameters and fixed defines."""

    scene: str
    pattern: FramePattern | None
    frames: range
    output: FramePattern
    animations: tuple[Animation, ...]
    defines: dict[str, str]
    settings: dict[str, Any] = field(default_factory=dict)

    def scene_of(self, frame: int) -> str:
        return str(self.pattern.path(frame)) if self.pattern is not None else self.scene

    def defines_of(self, frame: int) -> dict[str, str]:
        return {**self.defines, **{a.name: a.value(frame, self.frames) for a in self.animations}}

    def header(self, frame: int) -> dict[str, str]:
        """The frame's shot keys: its number, the shot, each animated value and the settings hash."""
        meta = {FRAME_KEY: str(frame), SHOT_KEY: shot_name(self.frames)}
        meta.update({ANIMATE_PREFIX + a.name: a.value(frame, self.frames) for a in self.animations})
        identity = shot_scene_identity(self.scene_of(frame), self.defines_of(frame))
        text = json.dumps({"scene": identity, "shot": meta, "settings": self.settings}, sort_keys=True)
        meta[SETTINGS_KEY] = hashlib.sha256(text.encode()).hexdigest()[:32]
        return meta


def shot_scene_identity(scene: str, defines: dict[str, str]) -> str:
    """The plan cache's scene identity, with a procedural shot family's defines (``-D t``) added: the plan cache
    names a procedural scene by its spec alone, and a still has no defines."""
    from gradsep.renderer.plancache import scene_identity

    identity = scene_identity(scene, defines)
    if scene.startswith("procedural:") and defines:
        identity += " defines:" + ",".join(f"{k}={v}" for k, v in sorted(defines.items()))
    return identity


def checked_shot(args: argparse.Namespace) -> tuple[Shot, range]:
    """The shot and this shard's frames from the command line, every input checked (a one-line user error)."""
    from gradsep.renderer.scene import parse_defines

    scene_pattern = FramePattern(args.scene)
    output = FramePattern(args.output)
    if args.frames is None:
        given = "the output" if output.has_field else "the scene" if scene_pattern.has_field else \
            "--animate" if args.animate else "--shard"
        raise CommandError(f"{given} names a shot's frames; give --frames A-B")
    frames = parse_frames(args.frames)
    output.require_field("output")
    if not args.output.lower().endswith(".exr"):
        raise CommandError(f"output {args.output} must end in .exr")
    shard = shard_frames(frames, parse_shard(args.shard)) if args.shard is not None else frames
    animations = parse_animations(args.animate)
    defines = parse_defines(args.define)
    both = sorted({a.name for a in animations} & set(defines))
    if both:
        raise CommandError(f"--animate and -D both set {', '.join(both)}")
    animations = procedural_animations(args.scene, animations, defines)
    settings = {name: getattr(args, name, None) for name in _SETTING_NAMES}
    shot = Shot(args.scene, scene_pattern if scene_pattern.has_field else None, frames, output, animations,
                defines, settings)
    _check_scenes(shot, shard)
    for n in shard:
        if not shot.output.path(n).parent.is_dir():
            raise CommandError(f"output folder {shot.output.path(n).parent} does not exist")
    return shot, shard


def procedural_animations(scene: str, animations: tuple[Animation, ...],
                          defines: dict[str, str]) -> tuple[Animation, ...]:
    """A procedural scene's animation: none for a still family (which takes no parameter); for a shot family
    (renderer/procedural_shot.py) its one parameter ``t``, 0 on the first frame to 1 on the last unless
    ``--animate t=A:B`` (a part of the motion) or ``-D t=V`` (one instant) says otherwise. XML scenes: as given."""
    from gradsep.renderer.procedural import parse_procedural
    from gradsep.renderer.procedural_shot import TIME, parse_time
    from gradsep.renderer.scene import procedural_time

    spec = parse_procedural(scene)
    if spec is None:
        return animations
    if not spec.animated and animations:
        raise CommandError(f"--animate applies to XML scenes only and to the procedural shot families; {spec} "
                           "has no parameters")
    procedural_time(spec, {**defines, **{a.name: "0" for a in animations}})  # the names, and -D t's value
    if not spec.animated:
        return animations
    for a in animations:
        if len(a.start) != 1:
            raise CommandError(f"--animate {TIME}: {spec}'s {TIME} is a number, not a vector")
        for value in (*a.start, *a.end):
            parse_time(f"{value:g}", str(spec))
    return animations if animations or TIME in defines else (Animation(TIME, (0.0,), (1.0,)),)


def _check_scenes(shot: Shot, shard: range) -> None:
    """Every scene file this shard loads (its frames and their neighbours in the shot) exists, and has every
    animated parameter (a procedural scene's are checked by :func:`procedural_animations`)."""
    if shot.scene.startswith("procedural:"):
        return
    needed = sorted({m for n in shard for m in (n - 1, n, n + 1) if m in shot.frames}) if len(shard) else []
    paths = sorted({shot.scene_of(n) for n in needed}) if shot.pattern is not None else [shot.scene]
    for path in paths:
        if not Path(path).is_file():
            raise CommandError(f"scene file not found: {path}" + (" (a frame of the shot's per-frame XML pattern "
                                                                  f"{shot.scene})" if shot.pattern else ""))
    if not shot.animations:
        return
    for path in paths:
        try:
            names = {d.get("name") for d in ET.parse(path).getroot().findall("default")}
        except ET.ParseError as exc:
            raise CommandError(f"{path} is not valid XML: {exc}") from exc
        missing = sorted(a.name for a in shot.animations if a.name not in names)
        if missing:
            raise CommandError(f"--animate {', '.join(missing)}: {path} has no <default> parameter named "
                               f"{', '.join(missing)}")


def frames_to_render(shot: Shot, shard: range) -> list[int]:
    """This shard's frames that are not complete on disk. A file at a frame's path that is not that frame of this
    shot with these settings is a user error (nothing is overwritten, nothing has rendered yet)."""
    from gradsep.model.errors import FrameError
    from gradsep.model.exr_read import read_header

    todo = []
    for n in shard:
        path = shot.output.path(n)
        if not path.exists():
            todo.append(n)
            continue
        try:
            attributes = read_header(path).attributes
        except (FrameError, OSError) as exc:
            raise CommandError(f"{path} exists and is not a readable frame ({exc}); remove it to render frame "
                               f"{n}") from exc
        want = shot.header(n)
        if any(attributes.get(k) != want[k] for k in (FRAME_KEY, SHOT_KEY, SETTINGS_KEY)):
            found = f"frame {attributes.get(FRAME_KEY, '?')} of shot {attributes.get(SHOT_KEY, '?')}"
            raise CommandError(f"{path} holds {found} with other settings or scene, not frame {n} of shot "
                               f"{shot_name(shot.frames)} as asked; remove it or choose another output")
    return todo


class SceneWindow:
    """The loaded scenes of the frames around the one rendering (the frame, and its neighbours for motion
    vectors): each scene is loaded once and dropped once the shot has passed it."""

    def __init__(self, shot: Shot, args: argparse.Namespace) -> None:
        self.shot, self.args = shot, args
        self.loaded: dict[int, Any] = {}

    def get(self, frame: int) -> Any:
        from gradsep.renderer.scene import load_scene

        if frame not in self.shot.frames:
            return None
        if frame not in self.loaded:
            self.loaded[frame] = load_scene(self.shot.scene_of(frame), width=self.args.width,
                                            height=self.args.height, max_depth=self.args.max_depth,
                                            defines=self.shot.defines_of(frame))
        return self.loaded[frame]

    def forget_before(self, frame: int) -> None:
        import gc

        for n in [n for n in self.loaded if n < frame]:
            del self.loaded[n]
        gc.collect()  # the scene's Mitsuba objects go now, not at some later collection


def plan_cache_of(shot: Shot, args: argparse.Namespace, folder: Path | None, gradients: str) -> Any:
    """The shot's plan-cache entry folder (``auto`` only): ``folder`` (``--plan-cache``/$GRADSEP_PLAN_CACHE),
    else a hidden folder beside the outputs, created when the first judgement is stored (a shot that fails before
    that leaves nothing behind); keyed by ``--plan-key`` or the shot (its first scene, fixed defines,
    animation and frames), so every frame and every shard of the shot shares one judgement."""
    from gradsep.renderer.plancache import CacheFolder

    if gradients != "auto":
        return None
    if folder is None:
        folder = shot.output.path(shot.frames.start).parent / HIDDEN_PLAN_CACHE  # made by the first entry stored
    if args.plan_key:
        return CacheFolder(folder, f"key:{args.plan_key}")
    first = shot.scene_of(shot.frames.start)
    animated = ";".join(f"{a.name}={a.start}:{a.end}" for a in shot.animations)
    return CacheFolder(folder, f"shot:{shot_name(shot.frames)} {shot_scene_identity(first, shot.defines)}"
                               + (f" animate:{animated}" if animated else ""))


def render_shot(args: argparse.Namespace, deadline: Any, gradients: str, cache_folder: Path | None,
                render: Callable[..., tuple[Any, str]]) -> int:
    """`gradsep render --frames`: check the shot, then render and write this shard's frames that are not complete
    on disk, one line each. ``render(args, scene, call)`` is renderer.commands.render_loaded."""
    from gradsep.model.exr_write import write_frame
    from gradsep.renderer.budget import Deadline, check_seconds

    shot, shard = checked_shot(args)
    todo = frames_to_render(shot, shard)
    name = shot_name(shot.frames)
    print(f"shot {name}: {len(shard)} frames in this shard ({shard_text(shard)}), {len(shard) - len(todo)} "
          f"complete on disk, {len(todo)} to render")
    if not todo:
        return 0
    plan_cache = plan_cache_of(shot, args, cache_folder, gradients)
    from gradsep.renderer.motion import render_motion

    window = SceneWindow(shot, args)
    for i, n in enumerate(todo):
        started = time.perf_counter()
        frame_deadline = deadline if i == 0 or deadline is None else Deadline(check_seconds(args.seconds))
        # Frames n-1, n and n+1 are alive while n renders (its motion vectors need them): the scenes' objects take
        # the JIT registry's slots in a cycle of three, so Dr.Jit compiles the shot's kernels for its first three
        # frames and reuses them after.
        window.forget_before(n - 1)
        scene = window.get(n)
        seed = frame_seed(args.seed, n)
        frame, plan_text = render(args, scene, RenderCall(seed, frame_deadline, gradients, plan_cache))
        frame.motion = render_motion(scene, window.get(n - 1), window.get(n + 1))
        frame.metadata.update(shot.header(n))
        path = shot.output.path(n)
        write_frame(path, frame)
        for note in frame.warnings:
            print(f"gradsep render: note: frame {n}: {note}", file=sys.stderr)
        print(f"{path}: frame {n}, seed {seed}, {frame.width}x{frame.height}, {frame.metadata['gradsep.spp']} spp, "
              f"{time.perf_counter() - started:.2f} s" + (f"; {plan_text}" if plan_text else ""), flush=True)
        del scene, frame
    return 0


def shard_text(frames: range) -> str:
    return "none" if not len(frames) else shot_name(frames)
