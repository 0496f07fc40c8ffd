"""Channel layouts: the one definition of how another renderer's EXR channels map onto the frame contract.

A *layout* says which channel of a file holds which contract channel (``color.R``, ``albedo.G``, ``normal.X``,
``depth.Z``...) and which holds alpha. Reading maps a file's channels through its layout, then validates and
decodes the mapped names as usual (model/exr_read.py), so every layout gets the same checks, errors and policies.

:data:`LAYOUTS` is the table, one :class:`Layout` row per layout (``gradsep``, ``mitsuba-aov``, ``cycles``; each
row's reader says what it maps). Everything that names layouts derives from it: the names a caller may give and
their pattern (the service validates its ``channels`` query with it), the help texts of ``gradsep reconstruct
--channels``, ``gradsep client --channels`` and the service's parameter, ``auto``'s detection and the error for a
file that matches none. Adding a layout is one row (and its test).

``auto`` (the default everywhere) picks the layout when exactly one matches the file; when several match (a
Cycles view layer beside a top-level beauty, or two view layers) it refuses with a ChannelError that names the
candidates, and the caller picks one (``gradsep reconstruct --channels``, the service's ``channels`` query).
Standard library only: the argument parsers and the service's query validation import the names.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

from gradsep.model.policy import ILLUMINATION_LAYERS

#: The layout argument that detects the file's layout, and the default everywhere.
DEFAULT_LAYOUT = "auto"

ALPHA = "A"
_RGB, _XYZ = ("R", "G", "B"), ("X", "Y", "Z")
#: Feature names of Mitsuba's aov integrator (``aovs="albedo:albedo,nn:sh_normal,dd:depth"``), first match wins.
_AOV_ALBEDO: tuple[str, ...] = ("albedo",)
_AOV_NORMAL: tuple[str, ...] = ("sh_normal", "nn", "normal", "normals", "geo_normal", "gn")
_AOV_DEPTH: tuple[str, ...] = ("depth", "dd")
_AOV_DEPTH_SUFFIXES: tuple[str, ...] = ("T", "Z", "Y", "y")
#: Cycles pass names (Blender's render-pass names as a multilayer EXR stores them).
_CYCLES_COLOR: tuple[str, ...] = ("Noisy Image", "Combined")
_CYCLES_ALBEDO: tuple[str, ...] = ("Denoising Albedo",)
_CYCLES_NORMAL: tuple[str, ...] = ("Denoising Normal", "Normal")
_CYCLES_DEPTH: tuple[str, ...] = ("Denoising Depth", "Depth")
#: Cycles' motion pass: X, Y = position in the previous frame minus this one, Z, W = this position minus the one
#: in the next frame, in raster pixels with y up (Cycles' kernel/geom/primitive.h, primitive_motion_vector; its
#: camera puts raster y = 0 at the view plane's bottom). So
#: backward = (X, Y) and forward = (-Z, -W) in the contract's (Nuke's) convention: contract name -> (channel, sign).
_CYCLES_VECTOR = "Vector"
_CYCLES_MOTION: dict[str, tuple[str, float]] = {
    "backward.u": ("X", 1.0), "backward.v": ("Y", 1.0), "forward.u": ("Z", -1.0), "forward.v": ("W", -1.0)}


class LayoutError(ValueError):
    """The file matches no layout, several (``candidates``), or not the one asked for. model.exr_read turns it into
    a ChannelError (422) so callers see one error type for channel problems."""

    def __init__(self, message: str, details: dict[str, object]) -> None:
        super().__init__(message)
        self.message, self.details = message, details


@dataclass(frozen=True)
class ChannelMap:
    """How one file maps onto the contract: ``sources[contract name] = file channel``."""

    layout: str  # "gradsep", "mitsuba-aov" or "cycles:VIEWLAYER"
    sources: dict[str, str]
    alpha: str | None = None  # the file channel carried through as the output's A
    ignored: tuple[str, ...] = field(default=())  # file channels this layout does not read (a warning names them)
    signs: dict[str, float] = field(default_factory=dict)  # contract name -> factor applied on reading (default 1)

    @property
    def names(self) -> list[str]:
        """The contract names this file provides, for model.exr_read's validation."""
        return list(self.sources)

    def warnings(self) -> list[str]:
        """The warning naming the file's channels this layout does not read (none for gradsep: model.exr_read's
        validation names the channels outside the contract)."""
        if not self.ignored:
            return []
        shown = ", ".join(sorted(self.ignored)[:20]) + (", ..." if len(self.ignored) > 20 else "")
        return [f"ignored {len(self.ignored)} channel(s) outside the {self.layout} layout: {shown}"]


def _pick(present: set[str], prefixes: Sequence[str], suffixes: Sequence[str]) -> dict[int, str] | None:
    """The channels ``PREFIX.S`` for every suffix S under the first prefix that has all of them."""
    for prefix in prefixes:
        names = [f"{prefix}.{s}" for s in suffixes]
        if all(n in present for n in names):
            return dict(enumerate(names))
    return None


def _pick_one(present: set[str], prefixes: Sequence[str], suffixes: Sequence[str]) -> str | None:
    """The first ``PREFIX.S`` present (a one-channel pass whose channel letter varies by producer)."""
    return next((f"{p}.{s}" for p in prefixes for s in suffixes if f"{p}.{s}" in present), None)


def _features(present: set[str], albedo: Sequence[str], normal: Sequence[str], depth: Sequence[str],
              depth_suffixes: Sequence[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for group, prefixes, suffixes in (("albedo", albedo, _RGB), ("normal", normal, _XYZ)):
        found = _pick(present, prefixes, suffixes)
        if found:
            out.update({f"{group}.{suffixes[i]}": name for i, name in found.items()})
    one = _pick_one(present, depth, depth_suffixes)
    if one:
        out["depth.Z"] = one
    return out


def _gradsep(names: Sequence[str], _qualifier: str | None = None) -> ChannelMap:
    """The contract itself (docs/frame-format.md): ``direct.*``, ``indirect.*`` or ``color.*`` layers,
    ``albedo.*``/``normal.*``/``depth.Z`` features, and a top-level ``A`` as alpha. Every name but A passes as is:
    model.exr_read's validation names unknown channels and ignores foreign ones."""
    return ChannelMap("gradsep", {n: n for n in names if n != ALPHA}, ALPHA if ALPHA in names else None)


def _is_gradsep(names: Sequence[str]) -> list[str]:
    """A file with the contract's own layers. A top-level ``R G B`` beside them is a preview (the renderer's
    references carry one), so such a file is gradsep's alone (the row is ``exclusive``)."""
    return ["gradsep"] if any(n.split(".", 1)[0] in ILLUMINATION_LAYERS and "." in n for n in names) else []


def _mitsuba(names: Sequence[str], _qualifier: str | None = None) -> ChannelMap:
    """A single-layer beauty pass: top-level ``R G B`` (and ``A``) as the ``color`` layer. That is Mitsuba's
    ``hdrfilm`` default and most renderers' single-layer output. Features are taken from Mitsuba's ``aov``
    integrator channels when present, by the names its documentation uses: albedo ``albedo.{R,G,B}``; normal
    ``sh_normal``/``nn``/``normal``/``normals``/``geo_normal``/``gn`` ``.{X,Y,Z}`` (the first present); depth
    ``depth``/``dd`` ``.{T,Z,Y,y}`` (Mitsuba names a one-channel AOV ``NAME.T``)."""
    if not all(c in names for c in _RGB):
        raise LayoutError("channel layout mitsuba-aov needs top-level R, G and B channels",
                          {"expected": list(_RGB), "candidates": candidates(names)})
    present = set(names)
    sources = {f"color.{c}": c for c in _RGB}
    sources.update(_features(present, _AOV_ALBEDO, _AOV_NORMAL, _AOV_DEPTH, _AOV_DEPTH_SUFFIXES))
    alpha = ALPHA if ALPHA in present else None
    used = {*sources.values(), *([alpha] if alpha else [])}
    return ChannelMap("mitsuba-aov", sources, alpha, tuple(n for n in names if n not in used))


def cycles_view_layers(names: Iterable[str]) -> list[str]:
    """The view layers of a Cycles multilayer file: prefixes ``V`` with a ``V.Combined`` or ``V.Noisy Image``
    RGB. View-layer names may contain dots, so the pass name is matched from the right."""
    present = set(names)
    layers = set()
    for name in present:
        for pass_name in _CYCLES_COLOR:
            m = re.fullmatch(rf"(.+)\.{re.escape(pass_name)}\.R", name)
            if m and all(f"{m.group(1)}.{pass_name}.{c}" in present for c in _RGB):
                layers.add(m.group(1))
    return sorted(layers)


def _is_beauty(names: Sequence[str]) -> list[str]:
    return ["mitsuba-aov"] if all(c in names for c in _RGB) else []


def _cycles_layers(names: Sequence[str]) -> list[str]:
    return [f"cycles:{v}" for v in cycles_view_layers(names)]


def _cycles(names: Sequence[str], view_layer: str | None = None) -> ChannelMap:
    """A Blender Cycles multilayer EXR: ``VIEWLAYER.PASS.CHANNEL``. Colour from ``Noisy Image`` when the file has it
    (Blender's denoiser was on, so ``Combined`` is already denoised), else ``Combined``; alpha from the same
    pass's ``A``; albedo ``Denoising Albedo.{R,G,B}``; normal ``Denoising Normal.{X,Y,Z}`` (else ``Normal``);
    depth ``Denoising Depth.Z`` (else ``Depth.Z``); motion vectors from ``Vector.{X,Y,Z,W}`` (converted to the
    contract's convention: _CYCLES_MOTION). A file with several view layers names one as ``cycles:VIEWLAYER``."""
    if view_layer is None:
        view_layer = _the_view_layer(names)
    present = set(names)
    prefix = f"{view_layer}."
    color = _pick(present, [prefix + p for p in _CYCLES_COLOR], _RGB)
    if color is None:
        raise LayoutError(f"no Cycles view layer {view_layer!r} with a Combined or Noisy Image pass",
                          {"view_layers": cycles_view_layers(names)})
    sources = {f"color.{c}": color[i] for i, c in enumerate(_RGB)}
    color_pass = color[0].rsplit(".", 1)[0]
    alpha = f"{color_pass}.A" if f"{color_pass}.A" in present else None
    sources.update(_features(present, [prefix + p for p in _CYCLES_ALBEDO], [prefix + p for p in _CYCLES_NORMAL],
                             [prefix + p for p in _CYCLES_DEPTH], ("Z",)))
    vector = {name: (f"{prefix}{_CYCLES_VECTOR}.{c}", sign) for name, (c, sign) in _CYCLES_MOTION.items()}
    signs: dict[str, float] = {}
    if all(channel in present for channel, _ in vector.values()):
        sources.update({name: channel for name, (channel, _) in vector.items()})
        signs = {name: sign for name, (_, sign) in vector.items() if sign != 1.0}
    used = {*sources.values(), *([alpha] if alpha else [])}
    return ChannelMap(f"cycles:{view_layer}", sources, alpha, tuple(n for n in names if n not in used), signs)


def _the_view_layer(names: Sequence[str]) -> str:
    """The file's one Cycles view layer, or the LayoutError naming the choices (none, or several)."""
    view_layers = cycles_view_layers(names)
    if len(view_layers) == 1:
        return view_layers[0]
    problem = "has no Cycles view layer" if not view_layers else "has several Cycles view layers"
    raise LayoutError(f"channel layout cycles: the file {problem} (VIEWLAYER.Combined.R ...); "
                      + (f"name one: {', '.join(f'cycles:{v}' for v in view_layers)}" if view_layers
                         else "expected e.g. ViewLayer.Combined.R"),
                      {"candidates": [f"cycles:{v}" for v in view_layers]})


@dataclass(frozen=True)
class Layout:
    """One row of the layout table: what a caller names, how a file is recognised and how it is read."""

    name: str  # what a caller names: lowercase letters, digits and '-'
    describes: str  # the kind of file, for the help texts
    expects: str  # what such a file carries, for the error on a file that matches no layout
    matches: Callable[[Sequence[str]], list[str]]  # the names a file matches under this row ([] for none)
    read: Callable[[Sequence[str], str | None], ChannelMap]  # map a file's channels (a qualifier, if named)
    qualifier: str | None = None  # e.g. "VIEWLAYER": the row also takes NAME:QUALIFIER
    exclusive: bool = False  # a file this row matches matches no other row

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[a-z0-9][a-z0-9-]*", self.name) or self.name == DEFAULT_LAYOUT:
            raise ValueError(f"a layout's name is lowercase letters, digits and '-', not {DEFAULT_LAYOUT!r}: "
                             f"{self.name!r}")


#: The channel layouts, by name, in the order the help texts list them.
LAYOUTS: dict[str, Layout] = {row.name: row for row in (
    Layout("gradsep", "gradsep's own channels", "direct.*, indirect.* or color.* channels", _is_gradsep, _gradsep,
           exclusive=True),
    Layout("mitsuba-aov", "a top-level R G B [A] beauty with Mitsuba aov features", "a top-level R G B beauty pass",
           _is_beauty, _mitsuba),
    Layout("cycles", "a Blender Cycles multilayer EXR", "a Cycles multilayer VIEWLAYER.Combined.R ...",
           _cycles_layers, _cycles, qualifier="VIEWLAYER"),
)}
_QUALIFIER = ":.{1,200}"  # what may follow NAME: in a layout argument


def layout_choices() -> tuple[str, ...]:
    """The layout names a caller may give (``auto`` first); a row with a qualifier also takes NAME:QUALIFIER."""
    return (DEFAULT_LAYOUT, *LAYOUTS)


def layout_pattern() -> str:
    """The pattern a layout argument must match (the service validates its query parameter with it)."""
    names = [f"{row.name}({_QUALIFIER})?" if row.qualifier else row.name for row in LAYOUTS.values()]
    return rf"^({'|'.join((DEFAULT_LAYOUT, *names))})$"


def choices_text() -> str:
    """``auto, gradsep, mitsuba-aov, cycles or cycles:VIEWLAYER``: every form a layout argument takes."""
    forms = [*layout_choices(), *(f"{r.name}:{r.qualifier}" for r in LAYOUTS.values() if r.qualifier)]
    return ", ".join(forms[:-1]) + " or " + forms[-1]


def layouts_text() -> str:
    """What each layout reads, for the help texts: ``gradsep's own channels, ... or a Blender Cycles ...``."""
    kinds = [row.describes for row in LAYOUTS.values()]
    return ", ".join(kinds[:-1]) + " or " + kinds[-1] if len(kinds) > 1 else kinds[0]


def expected_text() -> str:
    """What a frame must carry, for the error on a file with no illumination layer."""
    kinds = [row.expects for row in LAYOUTS.values()]
    return ", ".join(kinds[:-1]) + ", or " + kinds[-1] if len(kinds) > 1 else kinds[0]


def candidates(names: Sequence[str]) -> list[str]:
    """Every layout this file matches, as a caller would name it (``cycles:V`` per view layer)."""
    found: list[str] = []
    for row in LAYOUTS.values():
        matched = row.matches(names)
        if matched and row.exclusive:
            return matched
        found += matched
    return found


def check_layout(layout: str) -> str:
    """``layout`` when it is a valid choice, else a ValueError naming the choices."""
    if not re.fullmatch(layout_pattern(), layout or ""):
        raise ValueError(f"unknown channel layout {layout!r}; expected one of {choices_text()}")
    return layout


def map_channels(names: Sequence[str], layout: str = DEFAULT_LAYOUT) -> ChannelMap:
    """Map a file's channel names through ``layout`` (``auto``: the one layout the file matches).

    Raises LayoutError when nothing matches, when ``auto`` finds several candidates (named in the message and in
    ``details["candidates"]``), or when a named layout does not fit the file.
    """
    names = list(names)
    check_layout(layout)
    if layout == DEFAULT_LAYOUT:
        found = candidates(names)
        if not found:
            return _gradsep(names)  # model.exr_read's validation then says what the contract expected
        if len(found) > 1:
            raise LayoutError(
                f"ambiguous channel layout: the file matches {', '.join(found)}; choose one "
                "(gradsep reconstruct --channels, or the service's channels query parameter)",
                {"candidates": found})
        layout = found[0]
    name, _, qualifier = layout.partition(":")
    return LAYOUTS[name].read(names, qualifier or None)
