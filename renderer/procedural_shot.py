"""Procedural animated shots: ``procedural:FAMILY:SEED`` with FAMILY one of :data:`SHOT_FAMILIES`.

Each is the room of ``procedural:SEED`` (the same builder on the same stream, so a seed held out of training is a
room nobody trained on, and the four families of one seed share their room) plus a motion drawn from a stream of
its own, evaluated at the scene's one parameter ``t`` in [0, 1]: the frame's position in the shot (0 on the first
frame, 1 on the last, as ``--animate`` interpolates; a still, and a one-frame shot, is t = 0). The motion is drawn
before ``t`` is looked at, so every frame of a shot has the same path and only its point on it changes. A frame
outside the shot has no t: nothing is drawn past the path's ends (t outside [0, 1] is refused), and the shot's
first and last frames carry motion vectors on one side only, as an XML shot's do.

- ``moving``: a static camera; a diffuse sphere (:data:`MOVER_ID`) floats just above the floor and crosses the view
  sideways in front of the camera's target, so its shadow moves over the floor.
- ``dolly``: the camera pushes in along its view towards its target (back out where it stands too close to it).
- ``orbit``: the camera turns about the vertical through its target, still looking at it.
- ``lightoff``: a static camera; a sphere lamp (:data:`LAMP_ID`) above the target, the key light there, is on for
  t < :data:`SWITCH_AT` and off (radiance 0) from then on. The room's own lights stay on, so no frame is black; the
  lamp stays in the scene, so shapes and ids are the same in every frame.

Shapes keep their ids in every frame, so motion vectors (renderer/motion.py) follow the camera and the sphere.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from gradsep.renderer.errors import SceneError
from gradsep.renderer.procedural_geometry import Vec, _look_at, _segment_hits_footprint, _segment_hits_rect, _unit
from gradsep.renderer.procedural_materials import _albedo, _light_tint, _reflectance, _rgb

SHOT_FAMILIES = ("moving", "dolly", "orbit", "lightoff")
#: The one parameter of a shot family's scene: the frame's position in the shot, 0 to 1.
TIME = "t"
#: The light-off family's lamp is on before this t and off from it on: the middle of the shot.
SWITCH_AT = 0.5
MOVER_ID = "shot_object"
LAMP_ID = "shot_lamp"
#: How far off the view's axis (a share of tan(fov / 2), both axes) the moving sphere's path may go.
_IN_VIEW = 0.7


def parse_time(text: str, spec: str) -> float:
    """``t`` from its text (``-D t=...``, ``--animate t=...``): a number in [0, 1], else a SceneError naming it."""
    try:
        t = float(text)
    except ValueError:
        raise SceneError(f"{spec}: t={text!r} is not a number (t is the frame's position in the shot, 0 to 1)") \
            from None
    if not 0.0 <= t <= 1.0:  # also refuses nan
        raise SceneError(f"{spec}: t={text} is outside [0, 1] (0 is the shot's first frame, 1 its last)")
    return t


def number_text(values: Any) -> str:
    """A value for the header, as ``--animate`` writes its values (``"1, 0.5, 2"``)."""
    return ", ".join(f"{float(v):.9g}" for v in np.atleast_1d(values))


def animate(builder: Any, family: str, rng: np.random.Generator, t: float) -> dict[str, str]:
    """Draw ``family``'s motion for the built room ``builder`` (renderer/procedural_builder._Builder) from ``rng``,
    put it into the builder at ``t``, and return the frame's animation values (header text) and a summary line in
    ``builder.shot``."""
    apply: dict[str, Callable[[Any, np.random.Generator, float], dict[str, str]]] = {
        "moving": _moving, "dolly": _dolly, "orbit": _orbit, "lightoff": _lightoff}
    return {TIME: number_text(t), **apply[family](builder, rng, t)}


def _view(builder: Any) -> tuple[Vec, Vec, np.ndarray]:
    """The room's camera: origin, target and the 3x3 basis (left, up, forward) of its to_world."""
    camera = builder.camera
    origin = np.asarray(camera["origin"], dtype=float)
    basis = np.asarray(camera["to_world"], dtype=float)[:3, :3]
    target = np.asarray(camera.get("target", origin + 3.0 * basis[:, 2]), dtype=float)
    return origin, target, basis


def _set_camera(builder: Any, origin: Vec, target: Vec) -> None:
    direction = _unit(target - origin)
    up = np.array([1.0, 0, 0]) if abs(direction[1]) > 0.95 else np.array([0, 1.0, 0])
    builder.camera = {**builder.camera, "origin": origin, "to_world": _look_at(origin, target, up)}


def _in_room(builder: Any, point: Vec, margin: float) -> bool:
    if builder.kind != "room":
        return True
    wx, h, wz = builder.size
    return abs(point[0]) <= wx / 2 - margin and abs(point[2]) <= wz / 2 - margin and margin <= point[1] <= h - margin


def _camera_clear(builder: Any, origin: Vec, target: Vec) -> bool:
    """A camera position inside the room, out of objects and lights, with its target not behind a blocker."""
    return (_in_room(builder, origin, 0.1)
            and all(math.hypot(origin[0] - o.x, origin[2] - o.z) > o.r + 0.25 or origin[1] > o.top + 0.1
                    for o in builder.footprints)
            and all(np.linalg.norm(origin - c) > r for c, r in builder.keep_out)
            and not any(_segment_hits_rect(origin, target, m) for m in builder.blockers))


# -- the families ------------------------------------------------------------------------------------------


def _moving(builder: Any, rng: np.random.Generator, t: float) -> dict[str, str]:
    """A sphere crossing the view sideways in front of the target, a small gap above the floor (raised towards the
    view's axis where the floor there is out of view)."""
    origin, target, basis = _view(builder)
    radius, gap = float(rng.uniform(0.2, 0.4)), float(rng.uniform(0.05, 0.25))
    reach, side = float(rng.uniform(0.3, 0.55)), float(rng.choice([-1.0, 1.0]))
    reflectance, _ = _reflectance(rng, 0.5, 0.2, 0.8)  # diffuse: its motion vectors are valid (not specular)
    tan_half = math.tan(math.radians(0.5 * builder.camera["fov"]))
    left = _unit(np.array([basis[0, 0], 0.0, basis[2, 0]]))
    best: tuple[int, Vec, Vec, float] = (-1, origin, origin, radius)
    for lift, fraction in [(k, f) for k in (0.0, 0.5, 1.0) for f in (0.45, 0.6, 0.35, 0.75, 0.9, 1.0, 0.3)]:
        ahead = origin + fraction * (target - origin)
        # No more than about a sixth of the view across where the target is close: a smaller sphere.
        size = min(radius, 0.3 * tan_half * max(float(np.dot(ahead - origin, basis[:, 2])), 0.0))
        centre = np.array([ahead[0], size + gap + lift * max(ahead[1] - size - gap, 0.0), ahead[2]])
        start, end = _across(centre, origin, basis, left, side * reach * tan_half)
        score = _placement_score(builder, origin, basis, tan_half, size, start, end)
        if score > best[0]:
            best = (score, start, end, size)
        if score == 7:
            break
    _, start, end, radius = best
    position = start + t * (end - start)
    builder.items[MOVER_ID] = {"type": "sphere", "center": [float(x) for x in position], "radius": radius,
                               "bsdf": {"type": "diffuse", "reflectance": reflectance}}
    builder.shot = (f"a sphere (r {radius:.2f}) {position[1] - radius:.2f} above the floor crossing "
                    f"{np.linalg.norm(end - start):.2f} m of the view")
    return {"object_position": number_text(position)}


def _across(centre: Vec, origin: Vec, basis: np.ndarray, left: Vec, share: float) -> tuple[Vec, Vec]:
    """A sideways path through ``centre`` spanning ``share`` of the view's half width at its depth."""
    half = share * max(float(np.dot(centre - origin, basis[:, 2])), 0.0)
    return centre - half * left, centre + half * left


def _placement_score(builder: Any, origin: Vec, basis: np.ndarray, tan_half: float, radius: float, start: Vec,
                     end: Vec) -> int:
    """4: in view all the way (and not tiny); 2: nothing between it and the camera; 1: it runs through no object
    and stays in the room."""
    path = [start + s * (end - start) for s in np.linspace(0.0, 1.0, 5)]
    seen = all(_in_view(point, origin, basis, tan_half, radius) for point in path) and radius >= 0.08
    unblocked = not any(_segment_hits_footprint(origin, point, o) for point in path for o in builder.footprints) \
        and not any(_segment_hits_rect(origin, point, m) for point in path for m in builder.blockers)
    free = _path_clear(builder, start, end, radius) and _in_room(builder, start, 0.0) and _in_room(builder, end, 0.0)
    return 4 * int(seen) + 2 * int(unblocked) + int(free)


def _in_view(point: Vec, origin: Vec, basis: np.ndarray, tan_half: float, radius: float) -> bool:
    local = basis.T @ (point - origin)  # (left, up, forward)
    return bool(local[2] > radius + 0.3 and abs(local[0]) <= _IN_VIEW * tan_half * local[2]
                and abs(local[1]) <= _IN_VIEW * tan_half * local[2])


def _path_clear(builder: Any, start: Vec, end: Vec, radius: float) -> bool:
    """Whether a sphere of ``radius`` sliding from ``start`` to ``end`` passes through no placed object."""
    for s in np.linspace(0.0, 1.0, 9):
        p = start + s * (end - start)
        if any(math.hypot(p[0] - o.x, p[2] - o.z) < o.r / 1.5 + radius and p[1] - radius < o.top
               for o in builder.footprints):
            return False
    return True


def _dolly(builder: Any, rng: np.random.Generator, t: float) -> dict[str, str]:
    """The camera on a straight track along its view: in towards the target, or out where it is too close."""
    origin, target, _ = _view(builder)
    distance = float(np.linalg.norm(target - origin))
    share = float(rng.uniform(0.25, 0.45))
    push = min(share, max(0.0, 1.0 - 0.9 / max(distance, 1e-6)))  # stop 0.9 m short of the target
    amount = push if push >= 0.1 else -share  # already close: pull out instead
    for tried in (amount, -share, amount / 2, -share / 2, amount / 4):  # else the other way, or a shorter track
        end = origin + tried * (target - origin)
        if _camera_clear(builder, end, target) and not any(
                _segment_hits_footprint(origin, end, o) for o in builder.footprints):
            amount = tried
            break
    else:
        amount /= 4  # nowhere clear: the shortest track
    position = origin + t * amount * (target - origin)
    _set_camera(builder, position, target)
    builder.shot = f"the camera dollies {'in' if amount > 0 else 'out'} {abs(amount) * distance:.2f} m"
    return {"camera_origin": number_text(position)}


def _orbit(builder: Any, rng: np.random.Generator, t: float) -> dict[str, str]:
    """The camera turns about the vertical through its target by 15-35 degrees, looking at the target all the way.
    Where the arc would leave the room (a camera near a wall or in a corner) the other way round is tried, then
    the arc is drawn closer to the target (down to half the distance, no nearer than 1 m), then the turn halved."""
    origin, target, _ = _view(builder)
    angle = float(rng.choice([-1.0, 1.0])) * float(rng.uniform(math.radians(15), math.radians(35)))
    flat = np.array([origin[0] - target[0], 0.0, origin[2] - target[2]])
    reach = float(np.linalg.norm(flat))
    chosen, start = angle / 4, origin  # nowhere clear: the smallest turn from the room's camera
    candidates = [(a, share) for turn in (angle, angle / 2, angle / 4) for share in (1.0, 0.8, 0.65, 0.5)
                  for a in (turn, -turn)]
    for tried, share in candidates:
        nearer = origin - (1.0 - share) * flat if share * reach >= 1.0 or share == 1.0 else None
        if nearer is not None and all(_camera_clear(builder, _turned(nearer, target, tried * s), target)
                                      for s in np.linspace(0, 1, 9)):
            chosen, start = tried, nearer
            break
    position = _turned(start, target, chosen * t)
    _set_camera(builder, position, target)
    builder.shot = (f"the camera orbits the target by {math.degrees(chosen):.0f} degrees, "
                    f"{np.linalg.norm((start - target)[[0, 2]]):.2f} m from it")
    return {"camera_origin": number_text(position)}


def _turned(origin: Vec, target: Vec, angle: float) -> Vec:
    """``origin`` turned by ``angle`` about the vertical through ``target``."""
    c, s = math.cos(angle), math.sin(angle)
    dx, dz = origin[0] - target[0], origin[2] - target[2]
    return np.array([target[0] + c * dx - s * dz, origin[1], target[2] + s * dx + c * dz])


def _lightoff(builder: Any, rng: np.random.Generator, t: float) -> dict[str, str]:
    """A sphere lamp over the target, on before :data:`SWITCH_AT` and off from it on."""
    _, target, _ = _view(builder)
    wx, h, wz = builder.size
    radius = float(rng.uniform(0.06, 0.15))
    strength = float(rng.uniform(0.75, 1.5))
    tint = _light_tint(rng)
    if builder.kind == "room":
        y = min(h - radius - 0.2, max(float(target[1]) + 1.2, 1.6))
    else:
        y = float(rng.uniform(1.8, 3.0))
    centre = [float(target[0]), y, float(target[2])]
    # The key light: at the target, ``strength`` times the irradiance that gives a diffuse albedo of 0.5 the
    # scene's exposure (E = P / (4 pi d^2) = strength * pi * exposure / 0.5), as the studio family sets its lights.
    distance = max(y - float(target[1]), 0.5)
    power = strength * 8 * np.pi ** 2 * builder.exposure * distance ** 2
    scale = 1.0 if t < SWITCH_AT else 0.0
    radiance = scale * power / (4 * np.pi ** 2 * radius * radius) * tint
    builder.items[LAMP_ID] = {"type": "sphere", "center": centre, "radius": radius,
                              "bsdf": {"type": "diffuse", "reflectance": _rgb(_albedo(rng, 0.5, 0.8))},
                              "emitter": {"type": "area", "radiance": _rgb(radiance)}}
    builder.shot = f"a sphere lamp (r {radius:.2f}) {y:.2f} above the floor over the target, off from t = {SWITCH_AT:g}"
    return {"lamp": number_text(scale)}

