"""Randomized scenes, each named by an integer seed (`procedural:SEED`; `procedural:studio:SEED`, below).

The network is trained without ground truth, so its only teacher is the variety of the frames it sees. The
generator therefore draws from a broad distribution rather than a few hand-made rooms: rooms of random size with
some walls or the ceiling left open, occluders that cast large shadows (shelves, partitions, pillars), objects
with diffuse, plastic, rough and smooth conductor and dielectric materials (some textured with Mitsuba's
checkerboard or a small procedural noise bitmap), area lights of varied power and colour (ceiling panels, panels
facing a wall or the ceiling so that most of the room is lit only indirectly, small bright spheres, sometimes a
spot light) and sometimes an environment light (constant, or a small procedurally painted sky with a sun; nothing
is downloaded). `docs/training.md` documents the distribution. The builder (renderer/procedural_builder.py)
draws a scene from its parts (renderer/procedural_geometry.py, renderer/procedural_materials.py).

Animated shots, ``procedural:FAMILY:SEED`` with FAMILY one of SHOT_FAMILIES (moving, dolly, orbit, lightoff), are
the room of ``procedural:SEED`` with a motion, at the scene's one parameter ``t`` (renderer/procedural_shot.py).

A second family, ``procedural:studio:SEED``, is the product shot: the same objects, materials and lights, but no
room, no ground and no sky, so the object cluster hangs in an empty (black) background lit by point, spot and
small sphere lights. Almost all of its light is direct and its silhouettes are against nothing, the kind of frame
the room family never makes (scenes with walls everywhere); the held-out studies use it so that a rule for such
frames is chosen on seeds, not on the shared teapot.

Everything is drawn from ``numpy.random.Generator(PCG64(seed))`` *before* the film size is looked at, so one
seed gives the same scene at every resolution. The generator first builds a plain *plan* (the Mitsuba dict with
numpy matrices and arrays in place of Mitsuba objects) that can be compared, hashed and summarised without a
Mitsuba variant; :func:`procedural_scene` converts it for ``mi.load_dict``. Changing what a seed produces must
bump :data:`GENERATOR_VERSION`, which datasets record next to each seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.renderer.errors import SceneError
from gradsep.renderer.procedural_builder import GENERATOR_VERSION, _Builder
from gradsep.renderer.procedural_shot import SHOT_FAMILIES, animate

PROCEDURAL_PREFIX = "procedural:"  # a scene spec naming a procedural scene: procedural:SEED
#: The scene families: "mixed" (rooms and outdoor ground planes: ``procedural:SEED``, what datasets train on) and
#: "studio" (objects and small lights in an empty background: ``procedural:studio:SEED``).
FAMILIES = ("mixed", "studio")
DEFAULT_MAX_DEPTH = 8  # deep enough for glass and multi-bounce indirect light; Russian roulette trims the rest


@dataclass
class ProceduralScene:
    """A generated scene: the plan (Mitsuba dict with numpy values) plus a summary for manifests."""

    seed: int
    plan: dict[str, Any]
    summary: dict[str, Any] = field(default_factory=dict)
    family: str = "mixed"
    #: A shot family's values at this t (``{"t": "0.5", "camera_origin": "x, y, z"}``, header text); else empty.
    animation: dict[str, str] = field(default_factory=dict)

    def to_mitsuba(self) -> dict[str, Any]:
        """The dict for ``mi.load_dict`` (needs a Mitsuba variant to be set)."""
        return _to_mitsuba(self.plan)

    def describe(self) -> str:
        """One human-readable line: what this seed contains."""
        s = self.summary
        room = s["room"]
        if room["kind"] == "outdoor":
            where = "outdoor ground plane"
        elif room["kind"] == "studio":
            where = "studio (empty background)"
        else:
            opened = ", ".join(room["open"]) or "none"
            where = f"room {room['size'][0]:.1f}x{room['size'][1]:.1f}x{room['size'][2]:.1f} (open: {opened})"
        objects = ", ".join(f"{n} {k}" for k, n in sorted(s["object_kinds"].items()))
        materials = ", ".join(f"{n} {k}" for k, n in sorted(s["materials"].items()))
        lights = ", ".join(s["lights"])
        shot = f"; shot: {s['shot']}" if "shot" in s else ""
        return (f"{ProceduralSpec(self.seed, self.family)} (generator v{GENERATOR_VERSION}): {where}; "
                f"objects: {objects or 'none'}; "
                f"occluders: {', '.join(s['occluders']) or 'none'}; materials: {materials}; lights: {lights}; "
                f"camera fov {s['camera']['fov']:.0f} deg{shot}")


# ----------------------------------------------------------------------------------------------------------
# Public entry points
# ----------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ProceduralSpec:
    """A parsed ``procedural:[FAMILY:]SEED`` scene spec (FAMILY a still family or a shot family); ``str()`` gives
    its canonical spelling."""

    seed: int
    family: str = "mixed"

    @property
    def animated(self) -> bool:
        """Whether the scene is a shot family's: it has the parameter ``t``."""
        return self.family in SHOT_FAMILIES

    def __str__(self) -> str:
        middle = "" if self.family == "mixed" else f"{self.family}:"
        return f"{PROCEDURAL_PREFIX}{middle}{self.seed}"


def parse_procedural(spec: str) -> ProceduralSpec | None:
    """The parsed ``procedural:SEED``, ``procedural:studio:SEED`` or ``procedural:SHOT_FAMILY:SEED`` scene spec, or
    None when ``spec`` names no procedural scene (an XML path). The one parser of the spec: scene loading, the
    dataset and the evaluation all use it. A malformed or negative seed or an unknown family is a SceneError
    naming the spec."""
    if not spec.startswith(PROCEDURAL_PREFIX):
        return None
    named, colon, text = spec[len(PROCEDURAL_PREFIX):].rpartition(":")
    if colon and (named == "mixed" or named not in FAMILIES + SHOT_FAMILIES):  # mixed is spelled without a name
        raise SceneError(f"bad scene {spec!r}: unknown procedural family {named!r} (expected procedural:SEED, "
                         f"procedural:studio:SEED or a shot, procedural:{'|'.join(SHOT_FAMILIES)}:SEED)")
    family = named or "mixed"
    try:
        seed = int(text)
    except ValueError:
        raise SceneError(f"bad scene {spec!r}: expected procedural:SEED with an integer seed") from None
    if seed < 0:
        raise SceneError(f"bad scene {spec!r}: the seed must be >= 0")
    return ProceduralSpec(seed, family)


def procedural_scene(seed: int, width: int = 256, height: int = 256, max_depth: int | None = None,
                     family: str = "mixed", t: float = 0.0) -> dict:
    """The Mitsuba scene dict of ``procedural:[FAMILY:]SEED`` (for ``mi.load_dict``) at ``t`` (shot families only);
    deterministic per seed."""
    return generate(seed, width, height, max_depth, family, t).to_mitsuba()


def describe(seed: int, family: str = "mixed") -> str:  # a shot family: its first frame
    """A one-line description of the scene a seed produces (the film size does not change the scene)."""
    return generate(seed, family=family).describe()


def generate(seed: int, width: int = 256, height: int = 256, max_depth: int | None = None,
             family: str = "mixed", t: float = 0.0) -> ProceduralScene:
    """Build the plan of ``procedural:[FAMILY:]SEED`` (a shot family's at ``t`` in [0, 1]); validates the
    arguments with clear errors. The still families draw from independent streams: a studio seed shares nothing
    with the mixed scene of that seed. A shot family is the mixed room of its seed plus a motion from a stream of
    its own."""
    _check_args(seed, width, height, max_depth)
    if family not in FAMILIES + SHOT_FAMILIES:
        raise ValueError(f"procedural family must be one of {', '.join(FAMILIES + SHOT_FAMILIES)}, got {family!r}")
    if not 0.0 <= t <= 1.0 or (t and family not in SHOT_FAMILIES):
        raise ValueError(f"t must be in [0, 1], and only a shot family has it; got t={t!r} for {family!r}")
    # The mixed family keeps its original stream (its seeds name the same scenes as before the studio family).
    entropy = [seed, FAMILIES.index(family)] if family in FAMILIES and family != "mixed" else seed
    builder = _Builder(np.random.Generator(np.random.PCG64(entropy)))
    if family == "studio":
        builder.build_studio()
    else:
        builder.build()
    animation = {}
    if family in SHOT_FAMILIES:
        motion = np.random.Generator(np.random.PCG64([seed, len(FAMILIES) + SHOT_FAMILIES.index(family)]))
        animation = animate(builder, family, motion, float(t))
    plan = builder.finish(width, height, DEFAULT_MAX_DEPTH if max_depth is None else max_depth)
    return ProceduralScene(seed=seed, plan=plan, summary=builder.summary(), family=family, animation=animation)


def _check_args(seed: int, width: int, height: int, max_depth: int | None) -> None:
    """Reject arguments Mitsuba or numpy would otherwise fail on with an obscure message."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"procedural seed must be a non-negative integer, got {seed!r}")
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"procedural scene {name} must be a positive integer, got {value!r}")
    if max_depth is not None and (isinstance(max_depth, bool) or not isinstance(max_depth, (int, np.integer))
                                  or max_depth == 0 or max_depth < -1):
        raise ValueError(f"max_depth must be -1 (unbounded) or a positive integer, got {max_depth!r}")


# ----------------------------------------------------------------------------------------------------------
# Plan -> Mitsuba objects
# ----------------------------------------------------------------------------------------------------------

def _to_mitsuba(node: Any, key: str = "") -> Any:
    """Replace the plan's numpy values by Mitsuba objects: 4x4 -> Transform4f, 3x3 -> Transform3f, images -> Bitmap."""
    import mitsuba as mi

    if mi.variant() is None:
        _ensure_variant()
    if isinstance(node, dict):
        return {k: _to_mitsuba(v, k) for k, v in node.items()}
    if isinstance(node, np.ndarray):
        if key == "bitmap":
            return mi.Bitmap(np.ascontiguousarray(node, dtype=np.float32))
        if node.shape == (4, 4):
            return mi.ScalarTransform4f(node.tolist())
        if node.shape == (3, 3):
            return mi.ScalarTransform3f(node.tolist())
        raise ValueError(f"unexpected array for {key!r} in a procedural plan: shape {node.shape}")
    return node


def _ensure_variant() -> None:
    """Pick the project's variant when no caller has yet: renderer.variant owns that choice (CUDA or LLVM)."""
    from gradsep.renderer.variant import select_variant

    select_variant()
