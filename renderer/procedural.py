"""Randomized scenes, each named by an integer seed (`procedural:SEED`; `procedural:studio:SEED`, below).

The network is trained without ground truth, so its only teacher is the variety of the frames it sees. The
generator therefore draws from a broad distribution rather than a few hand-made rooms: rooms of random size with
some walls or the ceiling left open, occluders that cast large shadows (shelves, partitions, pillars), objects
with diffuse, plastic, rough and smooth conductor and dielectric materials (some textured with Mitsuba's
checkerboard or a small procedural noise bitmap), area lights of varied power and colour (ceiling panels, panels
facing a wall or the ceiling so that most of the room is lit only indirectly, small bright spheres, sometimes a
spot light) and sometimes an environment light (constant, or a small procedurally painted sky with a sun; nothing
is downloaded). `docs/training.md` documents the distribution.

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

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.model.policy import LUMINANCE
from gradsep.renderer.errors import SceneError

GENERATOR_VERSION = 1
PROCEDURAL_PREFIX = "procedural:"  # a scene spec naming a procedural scene: procedural:SEED
#: The scene families: "mixed" (rooms and outdoor ground planes: ``procedural:SEED``, what datasets train on) and
#: "studio" (objects and small lights in an empty background: ``procedural:studio:SEED``).
FAMILIES = ("mixed", "studio")
DEFAULT_MAX_DEPTH = 8  # deep enough for glass and multi-bounce indirect light; Russian roulette trims the rest
_WALLS = ("north", "south", "east", "west")

Vec = np.ndarray


@dataclass
class ProceduralScene:
    """A generated scene: the plan (Mitsuba dict with numpy values) plus a summary for manifests."""

    seed: int
    plan: dict[str, Any]
    summary: dict[str, Any] = field(default_factory=dict)
    family: str = "mixed"

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
        return (f"{ProceduralSpec(self.seed, self.family)} (generator v{GENERATOR_VERSION}): {where}; "
                f"objects: {objects or 'none'}; "
                f"occluders: {', '.join(s['occluders']) or 'none'}; materials: {materials}; lights: {lights}; "
                f"camera fov {s['camera']['fov']:.0f} deg")


# ----------------------------------------------------------------------------------------------------------
# Public entry points
# ----------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ProceduralSpec:
    """A parsed ``procedural:[FAMILY:]SEED`` scene spec; ``str()`` gives its canonical spelling."""

    seed: int
    family: str = "mixed"

    def __str__(self) -> str:
        middle = "" if self.family == "mixed" else f"{self.family}:"
        return f"{PROCEDURAL_PREFIX}{middle}{self.seed}"


def parse_procedural(spec: str) -> ProceduralSpec | None:
    """The parsed ``procedural:SEED`` or ``procedural:studio:SEED`` scene spec, or None when ``spec`` names no
    procedural scene (an XML path). The one parser of the spec: scene loading, the dataset and the evaluation all
    use it. A malformed or negative seed or an unknown family is a SceneError naming the spec."""
    if not spec.startswith(PROCEDURAL_PREFIX):
        return None
    named, colon, text = spec[len(PROCEDURAL_PREFIX):].rpartition(":")
    if colon and (named == "mixed" or named not in FAMILIES):  # the mixed family is spelled without a name
        raise SceneError(f"bad scene {spec!r}: unknown procedural family {named!r} "
                         f"(expected procedural:SEED or procedural:studio:SEED)")
    family = named or "mixed"
    try:
        seed = int(text)
    except ValueError:
        raise SceneError(f"bad scene {spec!r}: expected procedural:SEED with an integer seed") from None
    if seed < 0:
        raise SceneError(f"bad scene {spec!r}: the seed must be >= 0")
    return ProceduralSpec(seed, family)


def procedural_scene(seed: int, width: int = 256, height: int = 256, max_depth: int | None = None,
                     family: str = "mixed") -> dict:
    """The Mitsuba scene dict of ``procedural:[FAMILY:]SEED`` (for ``mi.load_dict``); deterministic per seed."""
    return generate(seed, width, height, max_depth, family).to_mitsuba()


def describe(seed: int, family: str = "mixed") -> str:
    """A one-line description of the scene a seed produces (the film size does not change the scene)."""
    return generate(seed, family=family).describe()


def scene_summary(seed: int, family: str = "mixed") -> dict[str, Any]:
    """JSON-ready summary of a seed's scene (room, object kinds, materials, lights) for dataset manifests."""
    return generate(seed, family=family).summary


def generate(seed: int, width: int = 256, height: int = 256, max_depth: int | None = None,
             family: str = "mixed") -> ProceduralScene:
    """Build the plan of ``procedural:[FAMILY:]SEED``; validates the arguments with clear errors. The two
    families draw from independent streams: a studio seed shares nothing with the mixed scene of that seed."""
    _check_args(seed, width, height, max_depth)
    if family not in FAMILIES:
        raise ValueError(f"procedural family must be one of {', '.join(FAMILIES)}, got {family!r}")
    # The mixed family keeps its original stream (its seeds name the same scenes as before the studio family).
    entropy = seed if family == "mixed" else [seed, FAMILIES.index(family)]
    rng = np.random.Generator(np.random.PCG64(entropy))
    builder = _Builder(rng)
    if family == "studio":
        builder.build_studio()
    else:
        builder.build()
    plan = builder.finish(width, height, DEFAULT_MAX_DEPTH if max_depth is None else max_depth)
    return ProceduralScene(seed=seed, plan=plan, summary=builder.summary(), family=family)


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
# Geometry helpers (numpy 4x4 matrices; y is up)
# ----------------------------------------------------------------------------------------------------------

def _frame(center: Vec, u: Vec, v: Vec, su: float, sv: float, sn: float = 1.0) -> np.ndarray:
    """Affine map of Mitsuba's unit shapes: local x -> su*u, y -> sv*v, z -> sn*(u x v), origin -> center.

    Right-handed by construction, so a rectangle's or disk's normal (local +z) ends up along u x v.
    """
    u = _unit(u)
    n = _unit(np.cross(u, v))
    v = np.cross(n, u)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u * su, v * sv, n * sn, center
    return m


def _facing(center: Vec, normal: Vec, su: float, sv: float, sn: float = 1.0) -> np.ndarray:
    """Transform placing a unit rectangle/disk at ``center`` with its front side facing ``normal``."""
    n = _unit(normal)
    helper = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = _unit(np.cross(helper, n))
    v = np.cross(n, u)
    return _frame(center, u, v, su, sv, sn)


def _box(center: Vec, half: Vec, yaw: float) -> np.ndarray:
    """Transform of Mitsuba's unit cube ([-1,1]^3) to a box of half-extents ``half`` turned by ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    return _frame(center, np.array([c, 0.0, -s]), np.array([0.0, 1.0, 0.0]), half[0], half[1], half[2])


def _look_at(origin: Vec, target: Vec, up: Vec) -> np.ndarray:
    """Mitsuba's look_at convention: camera looks along local +z, local +y is up, local +x points left."""
    d = _unit(target - origin)
    left = _unit(np.cross(up, d))
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, origin
    return m


def _unit(v: Vec) -> Vec:
    return np.asarray(v, dtype=float) / float(np.linalg.norm(v))


def _segment_hits_rect(a: Vec, b: Vec, to_world: np.ndarray) -> bool:
    """Whether segment a->b crosses the rectangle ``to_world`` maps [-1,1]^2 onto (camera visibility check)."""
    inv = np.linalg.inv(to_world)
    pa = inv[:3, :3] @ a + inv[:3, 3]
    pb = inv[:3, :3] @ b + inv[:3, 3]
    if pa[2] * pb[2] > 0 or pa[2] == pb[2]:
        return False
    t = pa[2] / (pa[2] - pb[2])
    p = pa + t * (pb - pa)
    return abs(p[0]) <= 1.0 and abs(p[1]) <= 1.0


def _segment_hits_footprint(a: Vec, b: Vec, o: _Obj) -> bool:  # noqa: F821 (defined below)
    """Whether segment a->b passes through the vertical column of an object standing between its ends.

    The column containing the end point (the object looked at) does not count.
    """
    if math.hypot(b[0] - o.x, b[2] - o.z) <= o.r:
        return False
    d = b - a
    dxz = d[0] ** 2 + d[2] ** 2
    if dxz < 1e-12:
        return False
    t = min(max(((o.x - a[0]) * d[0] + (o.z - a[2]) * d[2]) / dxz, 0.0), 1.0)
    p = a + t * d
    return math.hypot(p[0] - o.x, p[2] - o.z) < o.r and p[1] < o.top


# ----------------------------------------------------------------------------------------------------------
# Colours, textures and materials (plain dicts; numpy arrays where Mitsuba needs objects)
# ----------------------------------------------------------------------------------------------------------

def _rgb(value: Vec) -> dict:
    return {"type": "rgb", "value": [float(x) for x in value]}


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _light_tint(rng: np.random.Generator) -> np.ndarray:
    """Mostly white-ish light with a warm or cool cast; luminance normalised to 1 so power stays as drawn."""
    warm = np.array([1.0, 0.78, 0.52])
    cool = np.array([0.72, 0.85, 1.0])
    t = rng.uniform(-1.0, 1.0)
    tint = 1.0 + max(t, 0.0) * (warm - 1.0) + max(-t, 0.0) * (cool - 1.0)
    if rng.random() < 0.1:  # an occasional saturated coloured light
        tint = 0.3 + 0.7 * _hsv_to_rgb(rng.random(), rng.uniform(0.4, 0.8), 1.0)
    return tint / float(tint @ np.array(LUMINANCE))


def _albedo(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.9) -> np.ndarray:
    """A random surface colour: varied hue and saturation, brightness kept physically plausible (< 0.9)."""
    h, s = rng.random(), rng.uniform(0.0, 0.85) ** 1.5
    return np.clip(_hsv_to_rgb(h, s, rng.uniform(lo, hi)), 0.01, 0.95)


def _noise(rng: np.random.Generator, size: int = 64, cells: int | None = None) -> np.ndarray:
    """Smooth value noise in [0, 1] of shape (size, size): a few octaves of bilinearly upsampled random grids."""
    from scipy.ndimage import zoom

    out = np.zeros((size, size))
    amp, total = 1.0, 0.0
    cells = cells or int(rng.integers(3, 9))
    while cells <= size // 2:
        grid = rng.random((cells, cells))
        out += amp * zoom(grid, size / cells, order=1, mode="grid-wrap", grid_mode=True)[:size, :size]
        total += amp
        amp *= 0.5
        cells *= 2
    out /= total
    return (out - out.min()) / max(float(np.ptp(out)), 1e-6)


def _texture(rng: np.random.Generator, base: np.ndarray) -> dict:
    """A checkerboard (Mitsuba plugin) or a procedural noise/stripe bitmap around colour ``base``."""
    other = _albedo(rng)
    scale = float(rng.choice([2.0, 4.0, 6.0, 8.0, 12.0]))
    to_uv = np.diag([scale, scale, 1.0])
    if rng.random() < 0.6:
        return {"type": "checkerboard", "color0": _rgb(base), "color1": _rgb(other), "to_uv": to_uv}
    n = _noise(rng)
    if rng.random() < 0.4:  # stripes warped by the noise: wood-grain-like high frequencies
        x = np.linspace(0.0, 1.0, n.shape[1], endpoint=False)[None, :]
        n = 0.5 + 0.5 * np.sin(2 * np.pi * (rng.integers(3, 10) * x + 2.0 * n))
    image = (base[None, None, :] * (1 - n[..., None]) + other[None, None, :] * n[..., None]).astype(np.float32)
    return {"type": "bitmap", "bitmap": image, "filter_type": "bilinear", "wrap_mode": "repeat",
            "to_uv": np.diag([scale / 4, scale / 4, 1.0])}


def _reflectance(rng: np.random.Generator, textured_p: float, lo: float = 0.05, hi: float = 0.9) -> tuple:
    base = _albedo(rng, lo, hi)
    if rng.random() < textured_p:
        tex = _texture(rng, base)
        return tex, f"textured-{tex['type']}"
    return _rgb(base), "plain"


_CONDUCTORS = ("Au", "Ag", "Al", "Cu", "Cr", "W", "Rh", "Ni_palik")  # names Mitsuba ships data for


def _material(rng: np.random.Generator, closed: bool) -> tuple[dict, str]:
    """A random object material and its category name. ``closed``: the shape encloses a volume (dielectrics)."""
    kinds = ["diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "dielectric", "roughdielectric"]
    weights = np.array([0.36, 0.07, 0.10, 0.09, 0.16, 0.12, 0.10])
    kind = str(rng.choice(kinds, p=weights / weights.sum()))
    if kind == "diffuse":
        refl, tex = _reflectance(rng, 0.35)
        return {"type": "diffuse", "reflectance": refl}, "diffuse" + ("" if tex == "plain" else "-textured")
    if kind in ("plastic", "roughplastic"):
        refl, tex = _reflectance(rng, 0.25)
        bsdf = {"type": kind, "diffuse_reflectance": refl, "int_ior": float(rng.uniform(1.4, 1.7))}
        if kind == "roughplastic":
            bsdf["alpha"] = float(rng.uniform(0.05, 0.4))
        return bsdf, kind
    if kind in ("conductor", "roughconductor"):
        if rng.random() < 0.6:
            bsdf: dict = {"type": kind, "material": str(rng.choice(_CONDUCTORS))}
        else:  # an idealised tinted mirror
            bsdf = {"type": kind, "material": "none",
                    "specular_reflectance": _rgb(np.clip(_albedo(rng, 0.5, 0.95), 0.3, 0.95))}
        if kind == "roughconductor":
            bsdf["alpha"] = float(rng.uniform(0.03, 0.5))
            bsdf["distribution"] = str(rng.choice(["ggx", "beckmann"]))
        return bsdf, kind
    ior = float(rng.uniform(1.3, 1.8))
    if not closed:  # a sheet has no inside: a thin dielectric (window-like pane) is the consistent model
        return {"type": "thindielectric", "int_ior": ior}, "thindielectric"
    bsdf = {"type": kind, "int_ior": ior}
    if kind == "roughdielectric":
        bsdf["alpha"] = float(rng.uniform(0.03, 0.35))
    if rng.random() < 0.3:  # tinted glass
        bsdf["specular_transmittance"] = _rgb(np.clip(_albedo(rng, 0.6, 1.0), 0.4, 1.0))
    return bsdf, kind


def _twosided(bsdf: dict) -> dict:
    return {"type": "twosided", "bsdf": bsdf}


def _sky(rng: np.random.Generator, width: int = 128) -> tuple[np.ndarray, dict]:
    """A small equirectangular sky: zenith-to-horizon gradient, a ground colour, soft clouds and a sun."""
    h = width // 2
    theta = (np.arange(h) + 0.5) / h * np.pi               # 0 at the zenith (+y)
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    elev = (np.pi / 2 - theta)[:, None] * np.ones((1, width))
    zenith = np.array([0.25, 0.45, 1.0]) * rng.uniform(0.5, 1.5)
    horizon = np.array([1.0, 0.9, 0.8]) * rng.uniform(0.6, 1.6)
    ground = _albedo(rng, 0.1, 0.5) * rng.uniform(0.2, 0.6)
    t = np.clip(elev / (np.pi / 2), 0.0, 1.0)[..., None] ** 0.5
    img = np.where(elev[..., None] > 0, horizon * (1 - t) + zenith * t, ground)
    clouds = _noise(rng, size=width)[:h, :]
    cover = rng.uniform(0.0, 0.8)
    mask = np.clip((clouds - (1 - cover)) * 4.0, 0.0, 1.0)[..., None] * (elev[..., None] > 0)
    img = img * (1 - mask) + mask * np.array([1.0, 1.0, 1.0]) * rng.uniform(0.8, 1.4)
    sun_el = rng.uniform(np.radians(8), np.radians(65))
    sun_az = rng.uniform(0, 2 * np.pi)
    sun_power = 0.0
    if rng.random() < 0.7:
        sun_dir = np.array([np.cos(sun_el) * np.cos(sun_az), np.sin(sun_el), np.cos(sun_el) * np.sin(sun_az)])
        dirs = np.stack([np.sin(theta)[:, None] * np.cos(phi)[None, :],
                         np.cos(theta)[:, None] * np.ones((1, width)),
                         np.sin(theta)[:, None] * np.sin(phi)[None, :]], axis=-1)
        ang = np.arccos(np.clip(dirs @ sun_dir, -1.0, 1.0))
        sun_power = float(rng.uniform(30.0, 300.0))
        img = img + (sun_power * np.exp(-0.5 * (ang / np.radians(2.5)) ** 2))[..., None] * np.array(
            [1.0, 0.9, 0.75])
    info = {"sun": sun_power > 0, "cloud_cover": round(float(cover), 3)}
    return img.astype(np.float32), info


# ----------------------------------------------------------------------------------------------------------
# The scene builder
# ----------------------------------------------------------------------------------------------------------

@dataclass
class _Obj:
    """Footprint of a placed object, for overlap and camera-clearance checks."""

    x: float
    z: float
    r: float
    top: float
    target: bool = True  # worth pointing the camera at (objects), or only an obstacle (partition segments)


class _Builder:
    """Draws one scene: room, occluders, objects, lights, camera, in that fixed order (determinism)."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.items: dict[str, dict] = {}
        self.footprints: list[_Obj] = []
        self.blockers: list[np.ndarray] = []       # rectangles (to_world) the camera must not look through
        self.keep_out: list[tuple[np.ndarray, float]] = []  # spheres the camera must stay out of (lights)
        self.object_kinds: dict[str, int] = {}
        self.materials: dict[str, int] = {}
        self.lights: list[str] = []
        self.occluders: list[str] = []
        self.open: list[str] = []
        self.kind = "room"
        self.size = np.zeros(3)
        self.exposure = 1.0
        self.focus = np.zeros(2)        # (x, z) the objects cluster around and the camera looks at
        self.spread = 1.0
        self.camera: dict[str, Any] = {}

    # -- orchestration ---------------------------------------------------------------------------------
    def build(self) -> None:
        rng = self.rng
        self.kind = "outdoor" if rng.random() < 0.12 else "room"
        self.exposure = float(np.exp(rng.uniform(np.log(0.15), np.log(1.5))))  # target mean radiance
        if self.kind == "room":
            self._room()
            self.focus = np.array([rng.uniform(-0.3, 0.3) * self.size[0], rng.uniform(-0.3, 0.3) * self.size[2]])
            self._occluders()
        else:
            self._ground()
        self.spread = float(rng.uniform(0.5, 1.8))
        self._objects()
        self._lights()
        self._camera()

    def build_studio(self) -> None:
        """The studio family: objects and 1-3 small lights (point, spot, sphere) with nothing around them."""
        rng = self.rng
        self.kind = "studio"
        self.exposure = float(np.exp(rng.uniform(np.log(0.15), np.log(1.5))))
        self.spread = float(rng.uniform(0.3, 1.2))
        self._objects()
        if not self.footprints:  # every placement failed (rare): one sphere, so the camera has a subject
            bsdf, mat = _material(rng, True)
            self.items["object_00"] = {"type": "sphere", "center": [0.0, 0.5, 0.0], "radius": 0.5, "bsdf": bsdf}
            self.footprints.append(_Obj(0.0, 0.0, 0.75, 1.0))
            self._count(self.object_kinds, "sphere")
            self._count(self.materials, mat)
        # The cluster's bounding sphere (footprint circles and heights) sets the framing and the lights' distance.
        centre = np.array([np.mean([o.x for o in self.footprints]), 0.0, np.mean([o.z for o in self.footprints])])
        centre[1] = 0.5 * max(o.top for o in self.footprints)
        radius = max(max(math.hypot(o.x - centre[0], o.z - centre[2]) + o.r / 1.5,
                         abs(o.top - centre[1])) for o in self.footprints)
        azimuth = self._studio_camera(centre, radius)
        kinds = [str(rng.choice(["point", "spot", "sphere"], p=[0.5, 0.2, 0.3]))
                 for _ in range(int(rng.choice([1, 2, 2, 3])))]
        shares = rng.dirichlet(np.full(len(kinds), 2.0))
        for i, (kind, share) in enumerate(zip(kinds, shares, strict=True)):
            # Key, fill and rim lights: from the camera's side up to somewhat behind the cluster.
            light_azimuth = azimuth + float(rng.uniform(-1.9, 1.9))
            self._light_studio(f"light_{i}", kind, float(share), centre, radius, light_azimuth, _light_tint(rng))
            self.lights.append(kind)

    def _studio_camera(self, centre: Vec, radius: float) -> float:
        """Framing, not a room's viewpoint: the cluster's bounding sphere fills 40-90 % of the view from a random
        azimuth, level to 50 degrees above; returns the azimuth."""
        rng = self.rng
        fov = float(rng.uniform(30.0, 70.0))
        fill = float(rng.uniform(0.4, 0.9))
        dist = radius / math.sin(math.radians(0.5 * fov) * fill)
        azimuth, elevation = float(rng.uniform(0, 2 * np.pi)), float(rng.uniform(0.0, 0.9))
        origin = centre + dist * np.array([math.cos(elevation) * math.cos(azimuth), math.sin(elevation),
                                           math.cos(elevation) * math.sin(azimuth)])
        target = centre + rng.normal(0.0, 0.1 * radius, 3)
        self.camera = {"fov": fov, "origin": origin, "to_world": _look_at(origin, target, np.array([0, 1.0, 0]))}
        return azimuth

    def _light_studio(self, name: str, kind: str, share: float, centre: Vec, radius: float, azimuth: float,
                      tint: np.ndarray) -> None:
        """A point, spot or small sphere light 1.5-4 cluster radii from the cluster's centre, from level to high
        above, its intensity set so the cluster's irradiance follows the scene's exposure (E = I / d^2)."""
        rng = self.rng
        d = float(rng.uniform(1.5, 4.0)) * max(radius, 0.5)
        elevation = rng.uniform(-0.2, 1.3)
        origin = centre + d * np.array([math.cos(elevation) * math.cos(azimuth), math.sin(elevation),
                                        math.cos(elevation) * math.sin(azimuth)])
        intensity = share * self.exposure * np.pi * d * d / 0.5  # a diffuse albedo of about 0.5
        self.keep_out.append((origin, 0.5))
        if kind == "point":
            self.items[name] = {"type": "point", "position": [float(x) for x in origin],
                                "intensity": _rgb(intensity * tint)}
        elif kind == "spot":
            cutoff = float(rng.uniform(15.0, 50.0))
            target = centre + rng.normal(0.0, 0.3, 3)
            self.items[name] = {"type": "spot", "to_world": _look_at(origin, target, np.array([0, 1.0, 0])
                                                                     if abs(_unit(target - origin)[1]) < 0.9
                                                                     else np.array([1.0, 0, 0])),
                                "cutoff_angle": cutoff, "beam_width": cutoff * float(rng.uniform(0.5, 0.95)),
                                "intensity": _rgb(intensity * tint)}
        else:  # a sphere of radius r and radiance L has intensity L * pi * r^2 towards the cluster
            r = float(rng.uniform(0.04, 0.25))
            self._emitter_shape(name, {"type": "sphere", "center": [float(x) for x in origin], "radius": r},
                                intensity / (np.pi * r * r) * tint)

    def finish(self, width: int, height: int, max_depth: int) -> dict[str, Any]:
        """Assemble the plan; only here do the film size and depth enter (they do not change the scene)."""
        fov_axis = "x" if width >= height else "y"
        sensor = {
            "type": "perspective",
            "fov": self.camera["fov"],
            "fov_axis": fov_axis,
            "near_clip": 0.01,
            "far_clip": 1000.0,
            "to_world": self.camera["to_world"],
            "sampler": {"type": "independent", "sample_count": 16},
            "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "component_format": "float32"},
        }
        plan: dict[str, Any] = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth)},
                                "sensor": sensor}
        plan.update(self.items)
        return plan

    def summary(self) -> dict[str, Any]:
        return {
            "generator_version": GENERATOR_VERSION,
            "room": {"kind": self.kind, "size": [round(float(x), 3) for x in self.size], "open": list(self.open)},
            "object_kinds": dict(self.object_kinds),
            "materials": dict(self.materials),
            "occluders": list(self.occluders),
            "lights": list(self.lights),
            "camera": {"fov": round(float(self.camera["fov"]), 2),
                       "origin": [round(float(x), 3) for x in self.camera["origin"]]},
        }

    def _count(self, table: dict[str, int], key: str) -> None:
        table[key] = table.get(key, 0) + 1

    # -- room ------------------------------------------------------------------------------------------
    def _room(self) -> None:
        rng = self.rng
        wx, wz = rng.uniform(3.5, 10.0), rng.uniform(3.5, 10.0)
        h = rng.uniform(2.4, 4.5)
        self.size = np.array([wx, h, wz])
        floor_refl, _ = _reflectance(rng, 0.6, 0.1, 0.8)
        floor_bsdf: dict = {"type": "diffuse", "reflectance": floor_refl}
        if rng.random() < 0.25:  # polished floor: glossy reflections of the room
            floor_bsdf = {"type": "roughplastic", "diffuse_reflectance": floor_refl,
                          "alpha": float(rng.uniform(0.05, 0.3))}
        self.items["floor"] = {"type": "rectangle", "to_world": _facing(np.array([0, 0, 0]), np.array([0, 1, 0]),
                                                                          wx / 2, wz / 2),
                               "bsdf": _twosided(floor_bsdf)}
        open_ceiling = rng.random() < 0.2
        opened = [w for w in _WALLS if rng.random() < 0.18]
        if len(opened) == 4:
            opened = opened[:2]
        if not open_ceiling:
            refl, _ = _reflectance(rng, 0.1, 0.5, 0.9)
            self.items["ceiling"] = {"type": "rectangle",
                                     "to_world": _facing(np.array([0, h, 0]), np.array([0, -1, 0]), wx / 2, wz / 2),
                                     "bsdf": _twosided({"type": "diffuse", "reflectance": refl})}
        else:
            self.open.append("ceiling")
        wall_color = _albedo(rng, 0.3, 0.85)
        walls = {"north": (np.array([0, h / 2, -wz / 2]), np.array([0, 0, 1.0]), wx / 2),
                 "south": (np.array([0, h / 2, wz / 2]), np.array([0, 0, -1.0]), wx / 2),
                 "east": (np.array([wx / 2, h / 2, 0]), np.array([-1.0, 0, 0]), wz / 2),
                 "west": (np.array([-wx / 2, h / 2, 0]), np.array([1.0, 0, 0]), wz / 2)}
        for name in _WALLS:
            accent = _albedo(rng, 0.2, 0.85)
            textured = rng.random() < 0.15
            if name in opened:
                self.open.append(name)
                continue
            center, normal, half = walls[name]
            color = accent if rng.random() < 0.3 else wall_color
            refl = _texture(rng, color) if textured else _rgb(color)
            self.items[f"wall_{name}"] = {"type": "rectangle", "to_world": _facing(center, normal, half, h / 2),
                                          "bsdf": _twosided({"type": "diffuse", "reflectance": refl})}

    def _ground(self) -> None:
        rng = self.rng
        self.size = np.array([12.0, 0.0, 12.0])
        refl, _ = _reflectance(rng, 0.6, 0.1, 0.7)
        self.items["floor"] = {"type": "rectangle",
                               "to_world": _facing(np.zeros(3), np.array([0, 1.0, 0]), 30.0, 30.0),
                               "bsdf": _twosided({"type": "diffuse", "reflectance": refl})}

    # -- occluders: shadows and regions reached only by indirect light ------------------------------------
    def _occluders(self) -> None:
        rng = self.rng
        wx, h, wz = self.size
        for i in range(int(rng.choice([0, 1, 1, 2, 2, 3]))):
            kind = str(rng.choice(["shelf", "partition", "pillar"], p=[0.4, 0.35, 0.25]))
            refl, _ = _reflectance(rng, 0.2, 0.2, 0.8)
            bsdf = _twosided({"type": "diffuse", "reflectance": refl})
            if kind == "shelf":
                cx, cz = rng.uniform(-wx / 3, wx / 3), rng.uniform(-wz / 3, wz / 3)
                y = rng.uniform(0.45, 0.8) * h
                sx, sz = rng.uniform(0.3, 1.2), rng.uniform(0.3, 1.2)
                m = _facing(np.array([cx, y, cz]), np.array([0, 1.0, 0]), sx, sz)
                self.items[f"occluder_{i}"] = {"type": "rectangle", "to_world": m, "bsdf": bsdf}
                self.blockers.append(m)
            elif kind == "partition":
                along_x = rng.random() < 0.5
                span = (wx if along_x else wz) * rng.uniform(0.3, 0.65)
                offset = rng.uniform(-0.3, 0.3) * (wz if along_x else wx)
                slide = rng.choice([-1.0, 1.0]) * ((wx if along_x else wz) / 2 - span / 2)
                top = rng.uniform(0.5, 0.9) * h
                center = (np.array([slide, top / 2, offset]) if along_x else np.array([offset, top / 2, slide]))
                normal = np.array([0, 0, 1.0]) if along_x else np.array([1.0, 0, 0])
                m = _facing(center, normal, span / 2, top / 2)
                self.items[f"occluder_{i}"] = {"type": "rectangle", "to_world": m, "bsdf": bsdf}
                self.blockers.append(m)
                for t in np.linspace(-span / 2, span / 2, max(2, int(span / 0.3))):  # keep objects out of it
                    px, pz = (center[0] + t, center[2]) if along_x else (center[0], center[2] + t)
                    self.footprints.append(_Obj(float(px), float(pz), 0.1, float(top), target=False))
            else:
                r = rng.uniform(0.15, 0.4)
                x, z = rng.uniform(-wx / 2 + r, wx / 2 - r), rng.uniform(-wz / 2 + r, wz / 2 - r)
                self.items[f"occluder_{i}"] = {"type": "cube", "to_world": _box(np.array([x, h / 2, z]),
                                                                                 np.array([r, h / 2, r]),
                                                                                 rng.uniform(0, np.pi)),
                                               "bsdf": bsdf}
                self.footprints.append(_Obj(float(x), float(z), float(r * 1.5), float(h), target=False))
            self.occluders.append(kind)

    # -- objects -----------------------------------------------------------------------------------------
    def _free_spot(self, r: float, lim_x: float, lim_z: float) -> tuple[float, float] | None:
        """A floor position whose footprint circle of radius ``r`` overlaps no placed object (rejection)."""
        for _ in range(30):
            x, z = self.focus + self.rng.normal(0.0, self.spread, 2)
            x, z = np.clip(x, -lim_x + r, lim_x - r), np.clip(z, -lim_z + r, lim_z - r)
            if all(math.hypot(x - o.x, z - o.z) > r + o.r + 0.05 for o in self.footprints):
                return float(x), float(z)
        return None

    def _objects(self) -> None:
        rng = self.rng
        n = int(rng.integers(3, 11))
        lim_x, lim_z = (self.size[0] / 2 - 0.3, self.size[2] / 2 - 0.3) if self.kind == "room" else (3.5, 3.5)
        for i in range(n):
            kind = str(rng.choice(["sphere", "cube", "cylinder", "panel", "disk"], p=[0.36, 0.32, 0.12, 0.1, 0.1]))
            size = float(rng.uniform(0.1, 0.5)) * (1.0 if self.kind == "room" else 1.5)
            lift = float(rng.uniform(0.2, 1.2)) if rng.random() < 0.2 else 0.0
            yaw = float(rng.uniform(0, 2 * np.pi))
            closed = kind in ("sphere", "cube")
            bsdf, mat = _material(rng, closed)
            spot = self._free_spot(size * 1.5, lim_x, lim_z)
            if spot is None:
                continue
            x, z = spot
            name = f"object_{i:02d}"
            if kind == "sphere":
                y = size + lift
                shape = {"type": "sphere", "center": [x, y, z], "radius": size}
                top = y + size
            elif kind == "cube":
                half = np.array([size, size * rng.uniform(0.4, 1.6), size * rng.uniform(0.5, 1.2)])
                shape = {"type": "cube", "to_world": _box(np.array([x, half[1] + lift, z]), half, yaw)}
                top = 2 * half[1] + lift
            elif kind == "cylinder":
                height = size * rng.uniform(1.0, 4.0)
                shape = {"type": "cylinder", "p0": [x, lift, z], "p1": [x, lift + height, z], "radius": size * 0.6}
                top = lift + height
                if mat != "thindielectric":  # a cap keeps an opaque cylinder from looking hollow from above
                    self.items[f"{name}_cap"] = {"type": "disk", "to_world": _facing(
                        np.array([x, top, z]), np.array([0, 1.0, 0]), size * 0.6, size * 0.6),
                        "bsdf": _twosided(bsdf)}
            else:  # a tilted sheet (panel: rectangle, or disk) standing on or above the floor
                tilt = float(rng.uniform(0.0, 1.3))
                normal = np.array([math.sin(tilt) * math.cos(yaw), math.cos(tilt), math.sin(tilt) * math.sin(yaw)])
                y = size * math.sin(tilt) + 0.02 + lift
                shape = {"type": "rectangle" if kind == "panel" else "disk",
                         "to_world": _facing(np.array([x, y, z]), normal, size, size * rng.uniform(0.5, 1.0))}
                top = y + size
            # Open surfaces are seen from both sides; transmissive BSDFs are two-sided already.
            shape["bsdf"] = _twosided(bsdf) if ("dielectric" not in mat and not closed) else bsdf
            self.items[name] = shape
            self.footprints.append(_Obj(x, z, size * 1.5, top))
            self._count(self.object_kinds, kind)
            self._count(self.materials, mat)

    # -- lights ------------------------------------------------------------------------------------------
    def _lights(self) -> None:
        rng = self.rng
        wx, h, wz = self.size
        # Power budget: mean radiance of a diffuse room ~ P / (pi * surface area), so P follows the room size.
        area = 2 * (wx * wz + wx * h + wz * h) if self.kind == "room" else 60.0
        budget = self.exposure * np.pi * area
        env = self.kind == "outdoor" or (bool(self.open) and rng.random() < 0.8)
        if self.kind == "room":
            n_area = int(rng.choice([1, 1, 2, 2, 3]))
            kinds = [str(rng.choice(["ceiling", "wall_wash", "uplight", "sphere", "spot"],
                                    p=[0.38, 0.2, 0.12, 0.2, 0.1])) for _ in range(n_area)]
            if "ceiling" in self.open:  # nothing to bounce an uplight off
                kinds = ["sphere" if k == "uplight" else k for k in kinds]
        else:
            kinds = ["sphere"] * int(rng.choice([0, 0, 1]))
        # Each light (and the sky) takes a random share of the budget: sometimes one dominates, sometimes not.
        shares = rng.dirichlet(np.full(len(kinds) + int(env), 2.0))
        for i, kind in enumerate(kinds):
            getattr(self, f"_light_{kind}")(f"light_{i}", budget * float(shares[i]), _light_tint(rng))
            self.lights.append(kind)
        if env:
            self._environment(float(shares[-1]))

    def _emitter_shape(self, name: str, shape: dict, radiance: np.ndarray) -> None:
        shape["emitter"] = {"type": "area", "radiance": _rgb(radiance)}
        shape.setdefault("bsdf", {"type": "diffuse", "reflectance": _rgb(np.array([0.2, 0.2, 0.2]))})
        self.items[name] = shape

    def _light_ceiling(self, name: str, power: float, tint: np.ndarray) -> None:
        """A panel just below the ceiling facing down: direct light with shadows under objects and shelves."""
        rng = self.rng
        wx, h, wz = self.size
        sx, sz = rng.uniform(0.15, 0.8), rng.uniform(0.15, 0.8)
        if rng.random() < 0.5:  # above the objects, so their shadows fall where the camera looks
            lim = np.array([wx / 2 - sx, wz / 2 - sz])
            x, z = np.clip(self.focus + rng.normal(0.0, 1.0, 2), -lim, lim)
        else:
            x, z = rng.uniform(-wx / 3, wx / 3), rng.uniform(-wz / 3, wz / 3)
        c = np.array([x, h - 0.01, z])
        radiance = power / (np.pi * 4 * sx * sz)
        self._emitter_shape(name, {"type": "rectangle", "to_world": _facing(c, np.array([0, -1.0, 0]), sx, sz)},
                            radiance * tint)

    def _light_wall_wash(self, name: str, power: float, tint: np.ndarray) -> None:
        """A panel close to a wall facing it: the rest of the room sees only the bounced (indirect) light."""
        rng = self.rng
        wx, h, wz = self.size
        wall = int(rng.integers(4))
        d = rng.uniform(0.15, 0.5)
        y = rng.uniform(0.3, 0.8) * h
        s1, s2 = rng.uniform(0.2, 0.7), rng.uniform(0.2, 0.5)
        targets = [(np.array([rng.uniform(-wx / 3, wx / 3), y, -wz / 2 + d]), np.array([0, 0, -1.0])),
                   (np.array([rng.uniform(-wx / 3, wx / 3), y, wz / 2 - d]), np.array([0, 0, 1.0])),
                   (np.array([wx / 2 - d, y, rng.uniform(-wz / 3, wz / 3)]), np.array([1.0, 0, 0])),
                   (np.array([-wx / 2 + d, y, rng.uniform(-wz / 3, wz / 3)]), np.array([-1.0, 0, 0]))]
        c, n = targets[wall]
        self.keep_out.append((c, max(s1, s2) + d + 0.5))  # a camera there would see only the panel
        radiance = 2.0 * power / (np.pi * 4 * s1 * s2)  # most of its light is absorbed by the first bounce
        self._emitter_shape(name, {"type": "rectangle", "to_world": _facing(c, n, s1, s2)}, radiance * tint)

    def _light_uplight(self, name: str, power: float, tint: np.ndarray) -> None:
        """A panel facing the ceiling (cove lighting): the floor is lit by the ceiling's reflection only."""
        rng = self.rng
        wx, h, wz = self.size
        s1, s2 = rng.uniform(0.2, 0.8), rng.uniform(0.2, 0.8)
        c = np.array([rng.uniform(-wx / 3, wx / 3), rng.uniform(0.6, 0.85) * h, rng.uniform(-wz / 3, wz / 3)])
        radiance = 2.0 * power / (np.pi * 4 * s1 * s2)
        # A shade under it hides the panel from below, so the floor gets no direct light from it.
        self.items[f"{name}_shade"] = {"type": "rectangle",
                                       "to_world": _facing(c - np.array([0, 0.02, 0]), np.array([0, -1.0, 0]),
                                                           s1 * 1.2, s2 * 1.2),
                                       "bsdf": _twosided({"type": "diffuse", "reflectance": _rgb(_albedo(rng))})}
        self._emitter_shape(name, {"type": "rectangle", "to_world": _facing(c, np.array([0, 1.0, 0]), s1, s2)},
                            radiance * tint)

    def _light_sphere(self, name: str, power: float, tint: np.ndarray) -> None:
        """A small bright sphere: sharp shadows and caustics through glass objects."""
        rng = self.rng
        wx, h, wz = self.size
        r = float(rng.uniform(0.04, 0.2))
        top = max((o.top for o in self.footprints), default=0.0)
        lim_x, lim_z = (wx / 2 - 0.4, wz / 2 - 0.4) if self.kind == "room" else (4.0, 4.0)
        ceiling = h - r - 0.1 if self.kind == "room" else 4.0
        y = float(rng.uniform(min(top + r + 0.1, ceiling), ceiling))
        center = [float(rng.uniform(-lim_x, lim_x)), y, float(rng.uniform(-lim_z, lim_z))]
        radiance = power / (4 * np.pi**2 * r * r)
        self._emitter_shape(name, {"type": "sphere", "center": center, "radius": r}, radiance * tint)

    def _light_spot(self, name: str, power: float, tint: np.ndarray) -> None:
        """A delta spot light aimed at the floor: hard-edged light pool, exercises delta emitters."""
        rng = self.rng
        wx, h, wz = self.size
        cutoff = float(rng.uniform(15.0, 50.0))
        origin = np.array([rng.uniform(-wx / 3, wx / 3), h - 0.2, rng.uniform(-wz / 3, wz / 3)])
        target = np.array([rng.uniform(-wx / 3, wx / 3), 0.0, rng.uniform(-wz / 3, wz / 3)])
        intensity = power / (2 * np.pi * (1 - math.cos(math.radians(cutoff))))
        up = np.array([1.0, 0, 0]) if abs(_unit(target - origin)[1]) > 0.9 else np.array([0, 1.0, 0])
        self.items[name] = {"type": "spot", "to_world": _look_at(origin, target, up),
                            "cutoff_angle": cutoff, "beam_width": cutoff * float(rng.uniform(0.5, 0.95)),
                            "intensity": _rgb(intensity * tint)}

    def _environment(self, share: float) -> None:
        """A constant sky or a small painted sky with a sun; only rooms with openings (or outdoors) get one."""
        rng = self.rng
        # Outdoors the sky is the main light: it alone sets the exposure; through openings it is one share of it.
        level = self.exposure * float(rng.uniform(0.5, 2.0)) * (1.0 if self.kind == "outdoor" else 2.0 * share)
        if rng.random() < 0.35:
            self.items["environment"] = {"type": "constant", "radiance": _rgb(level * _light_tint(rng))}
            self.lights.append("environment-constant")
            return
        image, _info = _sky(rng)
        mean = float(image.mean())
        yaw = float(rng.uniform(0, 2 * np.pi))
        c, s = math.cos(yaw), math.sin(yaw)
        to_world = np.eye(4)
        to_world[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        self.items["environment"] = {"type": "envmap", "bitmap": image, "scale": level / max(mean, 1e-6),
                                     "to_world": to_world}
        self.lights.append("environment-map")

    # -- camera ------------------------------------------------------------------------------------------
    def _camera(self) -> None:
        """A few metres from the object cluster, clear of objects, looking at it (its shadows in view) past
        occluders; the room's walls bound the distance."""
        rng = self.rng
        wx, h, wz = self.size
        fov = float(rng.uniform(40.0, 80.0))
        targets = [np.array([o.x, min(o.top, 1.5) * 0.5, o.z]) for o in self.footprints if o.target]
        best: tuple[int, np.ndarray, np.ndarray] | None = None
        for _ in range(100):
            ang = rng.uniform(0, 2 * np.pi)
            dist = rng.uniform(1.5, 5.0) if self.kind == "room" else rng.uniform(3.0, 9.0)
            x, z = self.focus + dist * np.array([math.cos(ang), math.sin(ang)])
            top = min(h - 0.3, 2.5) if self.kind == "room" else 3.0
            if self.kind == "room":
                x, z = np.clip(x, -wx / 2 + 0.3, wx / 2 - 0.3), np.clip(z, -wz / 2 + 0.3, wz / 2 - 0.3)
            origin = np.array([x, rng.uniform(0.4, top), z])
            if targets and rng.random() < 0.5:
                target = targets[int(rng.integers(len(targets)))] + rng.normal(0.0, 0.3, 3) * np.array([1, 0.3, 1])
            else:
                target = np.array([self.focus[0], rng.uniform(0.0, 0.8), self.focus[1]]) + rng.normal(0.0, 0.3, 3)
            # Clear of objects, and far enough that none fills the view (subtends less than ~35 degrees).
            clear = all(math.hypot(origin[0] - o.x, origin[2] - o.z) > max(o.r + 0.25, 3.5 * o.r)
                        for o in self.footprints)
            far = np.linalg.norm(target - origin) > 1.2
            seen = not any(_segment_hits_rect(origin, target, m) for m in self.blockers)
            seen = seen and not any(_segment_hits_footprint(origin, target, o) for o in self.footprints)
            clear = clear and all(np.linalg.norm(origin - c) > r for c, r in self.keep_out)
            score = 2 * int(clear) + int(seen) + int(far)  # crowded rooms: keep the least bad view
            if best is None or score > best[0]:
                best = (score, origin, target)
            if score == 4:
                break
        assert best is not None
        _, origin, target = best
        if np.linalg.norm(target - origin) < 1e-3:
            target = origin + np.array([0.0, 0.0, 1.0])
        direction = _unit(target - origin)
        up = np.array([1.0, 0, 0]) if abs(direction[1]) > 0.95 else np.array([0, 1.0, 0])
        self.camera = {"fov": fov, "origin": origin, "to_world": _look_at(origin, target, up)}


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
