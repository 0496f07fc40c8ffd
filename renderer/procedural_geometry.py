"""Geometry helpers of the procedural generator (renderer/procedural.py): numpy 4x4 transforms of Mitsuba's unit
shapes (y is up), the camera's look-at, and the segment tests that keep the camera's view clear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Vec = np.ndarray


@dataclass
class _Obj:
    """Footprint of a placed object, for overlap and camera-clearance checks."""

    x: float
    z: float
    r: float
    top: float
    target: bool = True  # worth pointing the camera at (objects), or only an obstacle (partition segments)



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


def _segment_hits_footprint(a: Vec, b: Vec, o: _Obj) -> bool:
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

