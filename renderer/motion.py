"""Motion vectors of a shot's frame: where each pixel's surface point is in the previous and the next frame.

One ray through each pixel centre of the current frame (the lens centre for a thin-lens camera) finds the pixel's
surface point. The point is named by its shape (``shape.id()``; a shape without an id by its place among those
without one) and, on a mesh, its primitive and barycentric coordinates; on another shape (sphere, rectangle,
disk...) by its coordinates in the shape's local frame (its ``to_world``). The same shape in the neighbouring
frame's scene (same id, and for a mesh the same faces) gives the point's position there; the neighbour's sensor
projects it to pixel coordinates, as its film does; a ray from the neighbour's camera towards it checks that it is
visible there (the first hit is the same shape, at the point's distance within VISIBILITY_TOLERANCE). Camera
motion and object motion both come out of this.

A pixel whose first hit is specular (a mirror, glass, or a glossy lobe sharper than the features' NEAR_SPECULAR_PDF),
or whose ray leaves the scene, shows another surface's image (or the environment), whose motion is not the first
hit's. Such a pixel is *replayed*: its chain is followed to the first non-specular vertex (the features' rule, each
lobe sampled at its centre) in both frames, from each frame's own camera. Where the other frame's chain meets the
same shapes at the same points (within VISIBILITY_TOLERANCE of the path's length; the same primitive and surface
(u, v) too, so a shape that slid along itself counts as moved) and ends the same way, the pixel's
image has not moved: vector 0, valid. Anything else on that chain moving (the camera, the mirror, the reflected
object, an occluder between them) makes the pixel invalid: such an image's motion is not traced.

A pixel has no correspondence (invalid, vector 0) when its replayed chain differs in the other frame, or is longer
than MAX_CHAIN; when the hit shape is not one of the scene's shapes (inside an instance); when the shape is missing
in the other frame, its id is not unique, the frames have different numbers of shapes without an id, or its
topology differs; when the point is off the other frame's screen or behind its camera; and when it is hidden there.

Vectors follow the frame contract (model/frame.py :class:`~gradsep.model.frame.Motion`): u to the right and v
upward, in pixels: ``x_prev = x + backward.u``, ``y_prev = y - backward.v`` with y the row.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gradsep.model.frame import Motion, sanitize_motion
from gradsep.renderer.gpt_loop import NEAR_SPECULAR_PDF
from gradsep.renderer.scene import LoadedScene

#: A point counts as visible in the other frame when the first hit from that camera is the same shape within this
#: fraction of the distance to the point (float32 hit distances and barycentric positions agree far closer).
VISIBILITY_TOLERANCE = 1e-3

#: Vertices a replayed chain follows (specular ones, then the first non-specular one or the way out of the scene);
#: a longer chain (mirrors facing each other) stays invalid.
MAX_CHAIN = 8

#: A replayed chain's vertex shape where its ray left the scene (its point holds the ray's direction).
MISS = -2

#: A function of the pixels' hits that gives their positions in the other frame (N, 3) (rows of hits on shapes
#: that are not this one are ignored).
Mover = Callable[["Hits", np.ndarray], np.ndarray]


@dataclass
class Hits:
    """The first surface point of each pixel's centre ray in the current frame, flattened in row order."""

    shape: np.ndarray  # (N,) index into scene.shapes(); -1: no usable hit (miss, specular, unknown shape)
    prim: np.ndarray  # (N,) primitive index
    bary: np.ndarray  # (N, 2) the hit's (b1, b2) on a triangle (Mitsuba's prim_uv)
    point: np.ndarray  # (N, 3) world position


def render_motion(current: LoadedScene, previous: LoadedScene | None,
                  following: LoadedScene | None) -> Motion:
    """Backward vectors to ``previous`` and forward vectors to ``following`` (None: that side is None)."""
    if previous is None and following is None:
        return Motion()
    hits = primary_hits(current)
    replay = np.flatnonzero(hits.shape < 0)  # specular first hits, misses (and unknown shapes, which stay invalid)
    chains = specular_chains(current, replay)
    sides: dict[str, np.ndarray | None] = {}
    for direction, other in (("backward", previous), ("forward", following)):
        if other is None:
            continue
        vectors, valid = _side(current, hits, other)
        still = replay[_replayed_still(current, replay, chains, other)]
        vectors.reshape(-1, 2)[still], valid.reshape(-1)[still] = 0.0, True
        vectors, valid, _ = sanitize_motion(vectors, valid)
        sides[direction], sides[f"{direction}_valid"] = vectors, valid
    return Motion(**sides)


def _centre_rays(loaded: LoadedScene, pixels: np.ndarray | None = None) -> Any:
    """One ray per pixel centre (``pixels``: these flat indices; None: all, row order), through the lens centre."""
    import drjit as dr
    import mitsuba as mi

    w, h = loaded.width, loaded.height
    index = dr.arange(mi.UInt32, w * h) if pixels is None else mi.UInt32(pixels.astype(np.uint32))
    col, row = mi.Float(index % w), mi.Float(index // w)
    position = mi.Point2f((col + 0.5) / w, (row + 0.5) / h)
    ray, _ = loaded.sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5, 0.5))
    return ray


def _registry_index(scene: Any, shape_ptrs: Any) -> np.ndarray:
    """Per lane, the index of the hit shape in ``scene.shapes()`` (-1 for none or a shape not listed there)."""
    import drjit as dr
    import mitsuba as mi

    ids = np.asarray(dr.reinterpret_array(mi.UInt32, shape_ptrs), dtype=np.int64)
    known = np.asarray(dr.reinterpret_array(mi.UInt32, scene.shapes_dr()), dtype=np.int64)
    lookup = np.full(max(int(known.max(initial=0)), int(ids.max(initial=0))) + 1, -1, dtype=np.int64)
    lookup[known] = np.arange(len(known))
    lookup[0] = -1  # a null shape pointer: no hit
    return lookup[ids]


def _specular_sample(loaded: LoadedScene, si: Any, ray: Any, valid: Any) -> tuple[Any, Any]:
    """(whether the hit is specular by the features' rule with the lobe sampled at its centre, that sample)."""
    import drjit as dr
    import mitsuba as mi

    bsdf = si.bsdf(ray)
    flags = dr.select(valid, bsdf.flags(), 0)
    has_diffuse = mi.has_flag(flags, mi.BSDFFlags.Diffuse)
    bs, _ = bsdf.sample(mi.BSDFContext(), si, 0.5, mi.Point2f(0.5, 0.5), valid & ~has_diffuse)
    specular = ~has_diffuse & (mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                               | (mi.has_flag(bs.sampled_type, mi.BSDFFlags.Glossy) & (bs.pdf > NEAR_SPECULAR_PDF)))
    return valid & specular, bs


def primary_hits(loaded: LoadedScene) -> Hits:
    """The first vertex of every pixel's centre ray, kept only where it is not specular (the features' rule with
    the lobe sampled at its centre)."""
    import drjit as dr

    ray = _centre_rays(loaded)
    pi = loaded.scene.ray_intersect_preliminary(ray, coherent=True)
    si = pi.compute_surface_interaction(ray)
    valid = si.is_valid()
    specular, _ = _specular_sample(loaded, si, ray, valid)
    usable = valid & ~specular
    dr.eval(usable, pi.shape, pi.prim_index, pi.prim_uv, si.p)  # one kernel for every output read below
    shape = _registry_index(loaded.scene, pi.shape)
    shape[~np.asarray(usable, dtype=bool)] = -1
    return Hits(shape=shape, prim=np.asarray(pi.prim_index, dtype=np.int64),
                bary=np.stack([np.asarray(pi.prim_uv.x), np.asarray(pi.prim_uv.y)], axis=-1),
                point=np.stack([np.asarray(si.p.x), np.asarray(si.p.y), np.asarray(si.p.z)], axis=-1))


@dataclass
class Chains:
    """Pixel centres' paths through specular vertices to the first non-specular one (or out of the scene); K is
    the longest chain among them, at most MAX_CHAIN."""

    shape: np.ndarray  # (N, K) index into scene.shapes() per vertex; MISS: left the scene; -1: none/unknown
    point: np.ndarray  # (N, K, 3) world position (a MISS: the ray's direction)
    surface: np.ndarray  # (N, K, 3) the point on its shape: primitive index and surface (u, v)
    reach: np.ndarray  # (N, K) path length from the camera to each vertex
    length: np.ndarray  # (N,) vertices up to the chain's end; 0: no end within MAX_CHAIN


def specular_chains(loaded: LoadedScene, pixels: np.ndarray) -> Chains:
    """Follow the centre rays of ``pixels`` (flat indices) through specular vertices, each lobe sampled at its
    centre."""
    import drjit as dr
    import mitsuba as mi

    steps: list[tuple[np.ndarray, ...]] = []
    length = np.zeros(len(pixels), dtype=np.int64)
    if not len(pixels):
        return Chains(np.zeros((0, 0), np.int64), np.zeros((0, 0, 3)), np.zeros((0, 0, 3)), np.zeros((0, 0)), length)
    ray = _centre_rays(loaded, pixels)
    active = dr.full(mi.Bool, True, len(pixels))
    travelled = dr.zeros(mi.Float, len(pixels))
    for k in range(MAX_CHAIN):
        pi = loaded.scene.ray_intersect_preliminary(ray, coherent=False, active=active)
        si = pi.compute_surface_interaction(ray, active=active)
        valid = active & si.is_valid()
        specular, bs = _specular_sample(loaded, si, ray, valid)
        travelled = travelled + dr.select(valid, si.t, 0.0)
        where = dr.select(valid, si.p, ray.d)
        uv = dr.select(valid, si.uv, 0.0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        # one kernel per step, the same at every step: the next step starts from evaluated rays
        dr.eval(valid, specular, pi.shape, pi.prim_index, uv, where, travelled, active, ray)
        on, hit, mirror = (np.asarray(x, dtype=bool) for x in (active, valid, specular))
        shape = np.where(hit, _registry_index(loaded.scene, pi.shape), np.where(on, MISS, -1))
        prim = np.where(hit, np.asarray(pi.prim_index, dtype=np.float64), 0.0)
        steps.append((shape, np.stack([np.asarray(c, dtype=np.float64) for c in (where.x, where.y, where.z)], -1),
                      np.stack([prim, np.asarray(uv.x, dtype=np.float64), np.asarray(uv.y, dtype=np.float64)], -1),
                      np.asarray(travelled, dtype=np.float64)))
        length[on & ~mirror] = k + 1
        if not mirror.any():
            break
        active = specular
    shape, point, surface, reach = (np.stack(parts, axis=1) for parts in zip(*steps, strict=True))
    return Chains(shape=shape, point=point, surface=surface, reach=reach, length=length)


def _matrix(transform: Any) -> np.ndarray:
    """A Mitsuba transform's 4x4 matrix as float64 numpy."""
    return np.asarray(transform.matrix, dtype=np.float64).reshape(4, 4)


def _mesh_arrays(params: Any) -> tuple[np.ndarray, np.ndarray]:
    return (np.asarray(params["vertex_positions"], dtype=np.float64).reshape(-1, 3),
            np.asarray(params["faces"], dtype=np.int64).reshape(-1, 3))


def _mover(shape: Any, other_shape: Any) -> Mover | None:
    """How points on ``shape`` move to ``other_shape`` (the same object in the other frame), or None when there is
    no correspondence (different topology, or a shape with neither vertices nor a to_world)."""
    import mitsuba as mi

    mine, theirs = mi.traverse(shape), mi.traverse(other_shape)
    if "vertex_positions" in mine and "faces" in mine:
        if "vertex_positions" not in theirs or "faces" not in theirs:
            return None
        (v_mine, f_mine), (v_other, f_other) = _mesh_arrays(mine), _mesh_arrays(theirs)
        if v_mine.shape != v_other.shape or not np.array_equal(f_mine, f_other):
            return None

        def on_mesh(hits: Hits, rows: np.ndarray) -> np.ndarray:
            corners = v_other[f_other[np.clip(hits.prim[rows], 0, len(f_other) - 1)]]  # (n, 3 corners, 3)
            b1, b2 = hits.bary[rows, 0:1], hits.bary[rows, 1:2]
            return (1.0 - b1 - b2) * corners[:, 0] + b1 * corners[:, 1] + b2 * corners[:, 2]

        return on_mesh
    if "to_world" in mine and "to_world" in theirs:
        carry = _matrix(theirs["to_world"]) @ np.linalg.inv(_matrix(mine["to_world"]))

        def rigid(hits: Hits, rows: np.ndarray) -> np.ndarray:
            return hits.point[rows] @ carry[:3, :3].T + carry[:3, 3]

        return rigid
    return None


def _shape_keys(scene: Any) -> dict[tuple[str, ...], int]:
    """How shapes are matched across frames -> index in scene.shapes(): ``("id", ID)`` for an id that occurs once;
    ``("unnamed", K, CLASS)`` for the K-th shape without an id (Mitsuba gives a shape declared without one the id
    ""), matched by its place among them: per-frame files of one shot declare their shapes in the same order."""
    ids = [shape.id() for shape in scene.shapes()]
    keys: dict[tuple[str, ...], int] = {("id", name): i for i, name in enumerate(ids) if name and ids.count(name) == 1}
    unnamed = [i for i, name in enumerate(ids) if not name]
    keys.update({("unnamed", str(k), type(scene.shapes()[i]).__name__): i for k, i in enumerate(unnamed)})
    return keys


def _positions_in(current: LoadedScene, hits: Hits, other: LoadedScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions in the other frame (N, 3), the other scene's shape index per pixel, whether there is one)."""
    mine, theirs = _shape_keys(current.scene), _shape_keys(other.scene)
    if sum(k[0] == "unnamed" for k in mine) != sum(k[0] == "unnamed" for k in theirs):
        mine = {k: i for k, i in mine.items() if k[0] != "unnamed"}  # places among unnamed shapes do not match
    shapes, other_shapes = current.scene.shapes(), other.scene.shapes()
    positions = np.zeros_like(hits.point)
    target = np.full(hits.shape.shape, -1, dtype=np.int64)
    for key, index in mine.items():
        rows = np.flatnonzero(hits.shape == index)
        if not rows.size or key not in theirs:
            continue
        mover = _mover(shapes[index], other_shapes[theirs[key]])
        if mover is not None:
            positions[rows] = mover(hits, rows)
            target[rows] = theirs[key]
    return positions, target, target >= 0


def _project(other: LoadedScene, positions: np.ndarray, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (x right, y down, pixel centres at +0.5) of ``positions`` on the other frame's film, and
    whether they are on screen in front of its camera."""
    import drjit as dr
    import mitsuba as mi

    it = mi.Interaction3f()
    it.p = mi.Point3f(*(positions[:, k].astype(np.float32) for k in range(3)))
    ds, _ = other.sensor.sample_direction(it, mi.Point2f(0.5, 0.5), mi.Bool(active))
    dr.eval(ds.uv, ds.pdf)
    uv = np.stack([np.asarray(ds.uv.x, dtype=np.float64), np.asarray(ds.uv.y, dtype=np.float64)], axis=-1)
    inside = ((np.asarray(ds.pdf) > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < other.width)
              & (uv[:, 1] >= 0) & (uv[:, 1] < other.height))
    return uv, active & inside


def _visible(other: LoadedScene, positions: np.ndarray, target: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Whether the first hit from the other frame's camera towards each position is that shape, at that distance."""
    import drjit as dr
    import mitsuba as mi

    origin = _matrix(other.sensor.world_transform())[:3, 3]
    offset = positions - origin
    distance = np.linalg.norm(offset, axis=-1)
    direction = offset / np.maximum(distance, 1e-30)[:, None]
    ray = mi.Ray3f(mi.Point3f(*(np.full(len(positions), c, np.float32) for c in origin)),
                   mi.Vector3f(*(direction[:, k].astype(np.float32) for k in range(3))))
    pi = other.scene.ray_intersect_preliminary(ray, coherent=True, active=mi.Bool(active))
    dr.eval(pi.shape, pi.t)
    hit_shape = _registry_index(other.scene, pi.shape)
    t = np.asarray(pi.t, dtype=np.float64)
    return active & (hit_shape == target) & (np.abs(t - distance) <= VISIBILITY_TOLERANCE * distance)


def _side(current: LoadedScene, hits: Hits, other: LoadedScene) -> tuple[np.ndarray, np.ndarray]:
    """(vectors (H, W, 2) in the contract's convention, validity (H, W)) towards ``other``."""
    positions, target, found = _positions_in(current, hits, other)
    pixel, on_screen = _project(other, positions, found)
    valid = _visible(other, positions, target, on_screen)
    h, w = current.height, current.width
    rows, cols = np.divmod(np.arange(h * w), w)
    u = pixel[:, 0] - (cols + 0.5)
    v = (rows + 0.5) - pixel[:, 1]  # v grows upward
    vectors = np.stack([u, v], axis=-1).astype(np.float32)
    vectors[~valid] = 0.0
    return vectors.reshape(h, w, 2), valid.reshape(h, w)


def _replayed_still(current: LoadedScene, replay: np.ndarray, chains: Chains, other: LoadedScene) -> np.ndarray:
    """Which of the pixels ``replay`` (flat indices; their ``chains`` in the current frame) trace the same chain in
    ``other``: the same shapes, at the same points and places on them, ending the same way."""
    there = specular_chains(other, replay)
    steps = min(chains.shape.shape[1], there.shape.shape[1])
    if not steps:
        return np.zeros(len(replay), dtype=bool)
    mine, theirs = _shape_keys(current.scene), _shape_keys(other.scene)
    if sum(k[0] == "unnamed" for k in mine) != sum(k[0] == "unnamed" for k in theirs):
        mine = {k: i for k, i in mine.items() if k[0] != "unnamed"}
    to_other = np.full(len(current.scene.shapes()) + 1, -1, dtype=np.int64)  # the last entry maps -1 to -1
    for key, index in mine.items():
        to_other[index] = theirs.get(key, -1)
    shape = chains.shape[:, :steps]
    expected = np.where(shape == MISS, MISS, to_other[np.where(shape >= 0, shape, -1)])
    same = (expected == there.shape[:, :steps]) & ((shape >= 0) | (shape == MISS))
    tolerance = VISIBILITY_TOLERANCE * np.where(shape == MISS, 1.0, np.maximum(chains.reach[:, :steps], 1e-6))
    same &= np.abs(chains.point[:, :steps] - there.point[:, :steps]).max(axis=-1) <= tolerance
    # the same place on the shape too: a face sliding along its own plane leaves the world point where it was
    mine_uv, their_uv = chains.surface[:, :steps], there.surface[:, :steps]
    uv_tolerance = VISIBILITY_TOLERANCE * np.maximum(1.0, np.abs(mine_uv[..., 1:]).max(axis=-1))
    same &= (mine_uv[..., 0] == their_uv[..., 0]) & (np.abs(mine_uv[..., 1:] - their_uv[..., 1:]).max(axis=-1)
                                                    <= uv_tolerance)
    taken = np.arange(steps)[None, :] < chains.length[:, None]
    return (chains.length > 0) & (there.length == chains.length) & np.all(~taken | same, axis=1)
