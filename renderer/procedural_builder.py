"""The procedural generator's scene builder (renderer/procedural.py): draws one scene -- room, occluders,
objects, lights, camera, in that fixed order -- from a seeded generator into a plain plan.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from gradsep.renderer.procedural_geometry import (
    Vec,
    _box,
    _facing,
    _look_at,
    _Obj,
    _segment_hits_footprint,
    _segment_hits_rect,
    _unit,
)
from gradsep.renderer.procedural_materials import (
    _albedo,
    _light_tint,
    _material,
    _reflectance,
    _rgb,
    _sky,
    _texture,
    _twosided,
)

# What a seed produces is this builder's: changing it must bump the version, which datasets record next to
# each seed (renderer/procedural.py re-exports it).
GENERATOR_VERSION = 1
_WALLS = ("north", "south", "east", "west")


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
        self.shot = ""  # a shot family's motion in words (renderer/procedural_shot.py); "" for a still scene

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
        """Framing, not a room's viewpoint: the cluster's bounding sphere fills a random share of the view (``fill``)
        from a random azimuth, level to 50 degrees above; returns the azimuth."""
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
        out = {
            "generator_version": GENERATOR_VERSION,
            "room": {"kind": self.kind, "size": [round(float(x), 3) for x in self.size], "open": list(self.open)},
            "object_kinds": dict(self.object_kinds),
            "materials": dict(self.materials),
            "occluders": list(self.occluders),
            "lights": list(self.lights),
            "camera": {"fov": round(float(self.camera["fov"]), 2),
                       "origin": [round(float(x), 3) for x in self.camera["origin"]]},
        }
        if self.shot:
            out["shot"] = self.shot
        return out

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
        # The target is kept (not in the plan): the shot families (renderer/procedural_shot.py) move around it.
        self.camera = {"fov": fov, "origin": origin, "target": target, "to_world": _look_at(origin, target, up)}

