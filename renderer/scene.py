"""Scene loading for the renderer: Mitsuba 3 XML files and ``procedural:SEED`` scenes, validated for G-PT.

Every scene is loaded with the box reconstruction filter and the requested film size forced onto its first
sensor: a wider filter would spread one sample over several pixels and correlate neighbouring pixels' noise and
gradients, which both the gradient estimator's pixel pairing and the denoiser assume away. For XML files this is
done by rewriting the sensor's ``<film>`` element with ``xml.etree`` before Mitsuba parses the text, with the
file's folder on Mitsuba's file resolver so relative mesh and texture paths keep working; ``<default>``
parameters can be overridden (``-D name=value``) exactly as ``mi.load_file(path, **params)`` does.

Scenes the G-PT integrator cannot render correctly are refused with a :class:`SceneError` naming the problem
(no emitter, participating media, a sensor other than a perspective or thin-lens camera) instead of rendering
something wrong.
"""

from __future__ import annotations

import re
import threading
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gradsep.renderer.errors import SceneError
from gradsep.renderer.procedural import ProceduralSpec, generate, parse_procedural
from gradsep.renderer.procedural_builder import GENERATOR_VERSION
from gradsep.renderer.procedural_shot import TIME, parse_time
from gradsep.renderer.variant import select_variant

SUPPORTED_SENSORS: tuple[str, ...] = ("PerspectiveCamera", "ThinLensCamera")
DEFAULT_MAX_DEPTH = 6  # Mitsuba's own default for path tracers
DEFAULT_RR_DEPTH = 5
DEFAULT_PROCEDURAL_SIZE = 256
MITSUBA_DEFAULT_FILM = (768, 576)  # hdrfilm's size when a scene gives none
MAX_FILM_PIXELS = 8192 * 8192  # the frame contract's reading budget: larger frames could not be read back
_resolver_lock = threading.Lock()
#: A frame's animated values in its header: ``gradsep.animate.NAME`` (a shot's ``--animate`` parameters, and a
#: procedural shot family's ``t`` and what it moved).
ANIMATE_PREFIX = "gradsep.animate."


@dataclass
class LoadedScene:
    """A loaded, validated Mitsuba scene plus the settings resolved for it."""

    scene: Any  # mi.Scene
    spec: str  # what the user asked for: an XML path or procedural:SEED
    width: int
    height: int
    max_depth: int  # Mitsuba's convention: -1 unbounded, 1 emitters only, 2 direct light
    rr_depth: int
    defines: dict[str, str] = field(default_factory=dict)
    animation: dict[str, str] = field(default_factory=dict)  # a procedural shot family's values at its t

    @property
    def sensor(self) -> Any:
        return self.scene.sensors()[0]

    def scene_metadata(self) -> dict[str, str]:
        """The ``gradsep.*`` header attributes that name the scene: spec, overrides, generator version."""
        meta = {"gradsep.scene": self.spec}
        if self.defines:
            meta["gradsep.defines"] = ",".join(f"{k}={v}" for k, v in sorted(self.defines.items()))
        if parse_procedural(self.spec) is not None:  # a seed names a scene only for one generator version
            meta["gradsep.procedural_version"] = str(GENERATOR_VERSION)
        meta.update({ANIMATE_PREFIX + name: value for name, value in self.animation.items()})
        return meta


# ---------------------------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------------------------


def parse_defines(pairs: list[str] | None) -> dict[str, str]:
    """``["spp=16", "res=64"]`` -> dict; a malformed pair is a user error naming it."""
    out: dict[str, str] = {}
    for pair in pairs or []:
        name, sep, value = pair.partition("=")
        name = name.strip()
        if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise SceneError(f"bad --define {pair!r}: expected NAME=VALUE with NAME a <default> parameter name")
        out[name] = value.strip()
    return out


def load_scene(spec: str, *, width: int | None = None, height: int | None = None, max_depth: int | None = None,
               defines: Mapping[str, str] | None = None) -> LoadedScene:
    """Load and validate ``spec`` (XML path or ``procedural:SEED``) with a box filter and the requested film size.

    ``max_depth`` defaults to the scene's own integrator setting (Mitsuba's ``direct`` integrator counts as 2).
    """
    import mitsuba as mi

    select_variant()
    defines = dict(defines or {})
    for name, value in (("width", width), ("height", height)):
        if value is not None and value < 1:
            raise SceneError(f"--{name} must be >= 1, got {value}")
    if max_depth is not None and (max_depth == 0 or max_depth < -1):
        raise SceneError(f"--max-depth must be -1 (unbounded) or >= 1, got {max_depth}")

    procedural = parse_procedural(spec)
    animation: dict[str, str] = {}
    if procedural is not None:
        scene, animation = _load_procedural(procedural, width, height, max_depth, procedural_time(procedural, defines))
    else:
        scene = _load_xml(spec, width, height, defines)
    del mi

    validate_scene(scene, spec)
    film = scene.sensors()[0].film()
    w, h = (int(v) for v in film.size())
    if w * h > MAX_FILM_PIXELS:
        raise SceneError(f"film {w}x{h} exceeds the frame budget of {MAX_FILM_PIXELS} pixels")
    scene_depth, rr_depth = integrator_depths(scene)
    return LoadedScene(scene=scene, spec=spec, width=w, height=h,
                       max_depth=max_depth if max_depth is not None else scene_depth, rr_depth=rr_depth,
                       defines=defines, animation=animation)


def procedural_time(spec: ProceduralSpec, defines: Mapping[str, str]) -> float:
    """The ``t`` of a procedural shot family's scene from its defines (0 when not given); a still procedural scene
    takes no define, a shot family only ``t`` in [0, 1]: else a SceneError naming the problem."""
    if not spec.animated:
        if defines:
            raise SceneError("--define applies to XML scenes only; procedural scenes are named by their seed")
        return 0.0
    other = sorted(set(defines) - {TIME})
    if other:
        raise SceneError(f"{spec} has no parameter named {', '.join(other)}: its one parameter is {TIME}, the "
                         "frame's position in the shot (0 to 1)")
    return parse_time(defines[TIME], str(spec)) if TIME in defines else 0.0


def _load_procedural(spec: ProceduralSpec, width: int | None, height: int | None, max_depth: int | None,
                     t: float) -> tuple[Any, dict[str, str]]:
    """The Mitsuba scene of ``spec`` (at ``t``, a shot family's) and its animation values."""
    import mitsuba as mi

    w = width or (height or DEFAULT_PROCEDURAL_SIZE)
    h = height or (width or DEFAULT_PROCEDURAL_SIZE)
    generated = generate(spec.seed, w, h, max_depth, spec.family, t)
    scene_dict = generated.to_mitsuba()
    force_film_dict(scene_dict, w, h)
    try:
        return _instantiate(lambda config: mi.parser.parse_dict(config, scene_dict)), generated.animation
    except Exception as exc:
        raise SceneError(f"procedural scene {spec} failed to load: {_one_line(exc)}") from exc


# Shape plugins that are not meshes: Mitsuba's mesh merge keeps them, like every non-shape, in declaration order.
_NON_MESH_SHAPES = frozenset({"sphere", "cylinder", "disk", "bsplinecurve", "linearcurve", "sdfgrid", "ellipsoids",
                              "instance", "shapegroup"})


def _instantiate(parse: Callable[[Any], Any]) -> Any:
    """What ``mi.load_dict``/``mi.load_string`` do (``parse(config)`` gives the parser state), with an emitter order
    that is the same in every process.

    Mitsuba's mesh merge (its ``merge`` shape) lists the meshes it is given in the order of a hash table keyed by
    object addresses, which differ from process to process, and the scene's emitter list -- so which light a
    sample picks -- follows the shapes. A mesh carrying an emitter is merged with nothing (its key holds its own
    emitter), so such meshes are kept out of the merge and listed after the scene's other children in declaration
    order: the emitters come in Mitsuba's order wherever that was already fixed (the non-mesh ones first, as
    declared), and the other meshes are merged as before.
    """
    import mitsuba as mi

    config = mi.parser.ParserConfig(mi.variant())
    config.merge_meshes = False  # done below instead
    state = parse(config)
    mi.parser.transform_all(config, state)
    if state.root.type == mi.ObjectType.Scene:
        root = state.root.props
        merge = mi.parser.SceneNode()
        merge.type = mi.ObjectType.Shape
        merge.props.set_plugin_name("merge")
        for key in root.keys():
            kind = _child_kind(state, root, key)
            if kind == "shape":
                merge.props[key] = root[key]
                del root[key]
            elif kind == "emitting mesh":  # to the end, in declaration order
                ref = root[key]
                del root[key]
                root[key] = ref
        if merge.props.keys():
            root["gradsep.merged"] = mi.Properties.ResolvedReference(len(state.nodes))  # no dict key has a dot
            state.nodes.append(merge)
    return mi.parser.instantiate(config, state)


def _child_kind(state: Any, props: Any, key: str) -> str:
    """``props[key]`` as a scene child: "shape" (no emitter), "emitting mesh", "emitting shape" or "other"."""
    import mitsuba as mi

    def node(name: str, owner: Any) -> Any:
        if owner.type(name) != mi.Properties.Type.ResolvedReference:
            return None
        return state.nodes[owner[name].index()]

    shape = node(key, props)
    if shape is None or shape.type != mi.ObjectType.Shape:
        return "other"
    if not any(getattr(node(name, shape.props), "type", None) == mi.ObjectType.Emitter for name in shape.props.keys()):
        return "shape"
    return "emitting shape" if shape.props.plugin_name() in _NON_MESH_SHAPES else "emitting mesh"


def force_film_dict(scene_dict: dict[str, Any], width: int, height: int) -> None:
    """Force the box filter and ``width``x``height`` onto the first sensor of a ``mi.load_dict`` scene dict."""
    for value in scene_dict.values():
        if isinstance(value, dict) and value.get("type") in ("perspective", "thinlens", "orthographic"):
            film = value.setdefault("film", {"type": "hdrfilm"})
            film["width"], film["height"] = int(width), int(height)
            film["rfilter"] = {"type": "box"}
            for key in ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"):
                film.pop(key, None)
            return


def _load_xml(spec: str, width: int | None, height: int | None, defines: dict[str, str]) -> Any:
    import mitsuba as mi

    path = Path(spec)
    if not path.is_file():
        raise SceneError(f"scene file not found: {spec}")
    try:
        tree = ET.parse(path)
    except ET.ParseError as exc:
        raise SceneError(f"{spec} is not valid XML: {exc}") from exc
    root = tree.getroot()
    if root.tag != "scene":
        raise SceneError(f"{spec}: the root element is <{root.tag}>, expected a Mitsuba <scene>")
    unknown = sorted(set(defines) - {d.get("name") for d in root.findall("default")})
    if unknown:
        raise SceneError(f"{spec} has no <default> parameter named {', '.join(unknown)}")
    force_film_xml(root, width, height, _resolved_defaults(root, defines))
    text = ET.tostring(root, encoding="unicode")
    # A parameter that only sized the film is no longer referenced once --width/--height replaced it; Mitsuba
    # refuses unused parameters, and the explicit size wins anyway.
    used = {name: value for name, value in defines.items() if f"${name}" in text}
    with _resolver_path(path.resolve().parent):
        try:
            return _instantiate(lambda config: mi.parser.parse_string(config, text, **used))
        except Exception as exc:
            raise SceneError(f"{spec} failed to load: {_one_line(exc)}") from exc


def _resolved_defaults(root: ET.Element, defines: Mapping[str, str]) -> dict[str, str]:
    """The scene's ``<default>`` values with the overrides applied (for reading the original film size)."""
    values = {d.get("name", ""): d.get("value", "") for d in root.findall("default")}
    values.update(defines)
    return values


def _film_value(film: ET.Element | None, name: str, params: Mapping[str, str], fallback: int) -> int:
    """An integer film property, with ``$param`` substitution; ``fallback`` where absent or unparseable."""
    if film is None:
        return fallback
    for child in film.findall("integer"):
        if child.get("name") == name:
            raw = re.sub(r"\$(\w+)", lambda m: params.get(m.group(1), m.group(0)), child.get("value", ""))
            try:
                return int(raw)
            except ValueError:
                return fallback
    return fallback


def force_film_xml(root: ET.Element, width: int | None, height: int | None, params: Mapping[str, str]) -> None:
    """Rewrite the first sensor's film in place: box filter, no crop window, the requested (or own) size.

    Giving only one of width/height keeps the film's aspect ratio.
    """
    sensor = root.find("sensor")
    if sensor is None:  # Mitsuba adds a default perspective sensor; give it a film we control
        sensor = ET.SubElement(root, "sensor", {"type": "perspective"})
    film = sensor.find("film")
    w0 = _film_value(film, "width", params, MITSUBA_DEFAULT_FILM[0])
    h0 = _film_value(film, "height", params, MITSUBA_DEFAULT_FILM[1])
    if width is None and height is None:
        width, height = w0, h0
    elif width is None:
        width = max(1, round(height * w0 / max(h0, 1)))
    elif height is None:
        height = max(1, round(width * h0 / max(w0, 1)))
    if film is None:
        film = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
    for child in list(film):
        drop_names = ("width", "height", "crop_offset_x", "crop_offset_y", "crop_width", "crop_height")
        if child.tag == "rfilter" or child.get("name") in drop_names:
            film.remove(child)
    ET.SubElement(film, "integer", {"name": "width", "value": str(int(width))})
    ET.SubElement(film, "integer", {"name": "height", "value": str(int(height))})
    ET.SubElement(film, "rfilter", {"type": "box"})


@contextmanager
def _resolver_path(folder: Path) -> Iterator[None]:
    """Put ``folder`` first on Mitsuba's (process-wide) file resolver while loading, then restore its paths."""
    import mitsuba as mi

    with _resolver_lock:
        resolver = mi.file_resolver()
        saved = [str(resolver[i]) for i in range(len(resolver))]
        resolver.prepend(str(folder))
        try:
            yield
        finally:
            resolver.clear()
            for entry in saved:
                resolver.append(entry)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) < 400 else text[:400] + " ..."


# ---------------------------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------------------------


def validate_scene(scene: Any, spec: str) -> None:
    """Refuse scenes G-PT cannot render: no emitter, participating media, unsupported sensor."""
    sensors = scene.sensors()
    if not sensors:
        raise SceneError(f"{spec}: the scene has no sensor")
    sensor = sensors[0]
    kind = sensor.class_name()
    if kind not in SUPPORTED_SENSORS:
        raise SceneError(f"{spec}: unsupported sensor {kind}; G-PT needs a perspective or thinlens camera "
                         "(pixel-shifted primary rays)")
    if not scene.emitters():
        raise SceneError(f"{spec}: the scene has no emitter, so every pixel would be black")
    media = []
    if sensor.get_medium() is not None:
        media.append("the sensor")
    for shape in scene.shapes():
        if shape.interior_medium() is not None or shape.exterior_medium() is not None:
            media.append(f"shape {shape.id() or '(unnamed)'}")
    for emitter in scene.emitters():
        if emitter.get_medium() is not None:
            media.append(f"emitter {emitter.id() or '(unnamed)'}")
    if media:
        raise SceneError(f"{spec}: participating media are not supported by the G-PT renderer "
                         f"(attached to {', '.join(media[:4])})")


def integrator_depths(scene: Any) -> tuple[int, int]:
    """(max_depth, rr_depth) of the scene's own integrator, Mitsuba's defaults where it has none.

    Mitsuba exposes these only through the integrator's description, so they are read from it; the ``direct``
    integrator renders exactly what ``max_depth = 2`` does.
    """
    integrator = scene.integrator()
    if integrator is None:
        return DEFAULT_MAX_DEPTH, DEFAULT_RR_DEPTH
    if integrator.class_name() == "DirectIntegrator":
        return 2, DEFAULT_RR_DEPTH
    text = str(integrator)
    depth_match = re.search(r"max_depth\s*=\s*(-?\d+)", text)
    rr_match = re.search(r"rr_depth\s*=\s*(-?\d+)", text)
    depth = int(depth_match.group(1)) if depth_match else DEFAULT_MAX_DEPTH
    if depth < 0 or depth >= 0xFFFFFFFF:
        depth = -1
    rr = int(rr_match.group(1)) if rr_match else DEFAULT_RR_DEPTH
    return depth, max(1, rr)
