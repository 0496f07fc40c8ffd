"""A temporal window in one stateless request: frame t in the multipart field ``frame``, its neighbours in the
repeatable fields ``previous`` and ``next``, nearest first (the first ``previous`` part is frame t - 1, the second
t - 2; the first ``next`` part t + 1). An empty part stands for a missing frame, so the parts after it keep their
offsets. The answer is frame t reconstructed by :func:`model.temporal.reconstruct_window`, so any replica serves
any frame of a shot.

The neighbours are checked against frame t from their headers before any pixel is decoded: another size, another
layout (channels, motion vectors left out: a shot's first and last frames carry one side only) or another shot
(``gradsep.shot``, where both carry one) is a 422 naming the part; a neighbour that does not decode is its own
error (400 for a truncated file) naming the part.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from gradsep.model.errors import FrameError
from gradsep.model.exr_read import HeaderInfo, ReadLimits, read_frame, read_header
from gradsep.model.frame import shot_layout
from gradsep.service.bodies import Upload
from gradsep.service.errors import ServiceError, body_too_large

#: The multipart fields of the neighbours before and after frame t, and the offset sign of each.
SIDES: dict[str, int] = {"previous": -1, "next": 1}
#: The most neighbours a request carries on each side (a window of up to 2 * 8 + 1 frames).
MAX_NEIGHBOURS = 8
#: The header attribute naming a frame's shot; frames of two shots are never one window.
SHOT_KEY = "gradsep.shot"
#: The answer's header attribute listing the offsets of the neighbours used (``-1,+1``), as X-Gradsep-Neighbours.
OFFSETS_KEY = "gradsep.temporal.offsets"


@dataclass
class Part:
    """One neighbour of a window request: its multipart field, its place in that field (1: nearest), and its
    body (None for an empty part: a missing frame)."""

    field: str
    index: int
    upload: Upload | None

    @property
    def offset(self) -> int:
        return SIDES[self.field] * self.index

    @property
    def name(self) -> str:
        return f"{self.field} #{self.index} (frame t{self.offset:+d})"

    def details(self, **more: Any) -> dict[str, Any]:
        return {"part": self.field, "index": self.index, "offset": self.offset, **more}


@dataclass
class Window:
    """A request's frame t and its neighbours (none for a single-frame request)."""

    frame: Upload
    parts: list[Part] = field(default_factory=list)

    def close(self) -> None:
        """Let every body go (idempotent, any thread)."""
        self.frame.close()
        for part in self.parts:
            if part.upload is not None:
                part.upload.close()

    @property
    def missing(self) -> list[int]:
        return [p.offset for p in self.parts if p.upload is None]


def window_parts(lists: dict[str, list[Any]], is_file: Any) -> list[Part]:
    """The neighbour parts of a form (``lists``: field -> its values, in order); 400 for a neighbour field that is
    not a file or for more than MAX_NEIGHBOURS on a side. ``is_file(value)`` says whether a value is a file part
    (an UploadFile) and returns its Upload, or None for a text field."""
    parts: list[Part] = []
    for name in SIDES:
        values = lists.get(name, [])
        if len(values) > MAX_NEIGHBOURS:
            raise ServiceError(400, "too_many_neighbours", f"{len(values)} '{name}' parts: a request carries at most "
                               f"{MAX_NEIGHBOURS} neighbours on each side", {"max_neighbours": MAX_NEIGHBOURS})
        for index, value in enumerate(values, start=1):
            upload = is_file(value)
            if upload is None:
                raise ServiceError(400, "bad_request", f"multipart field '{name}' #{index} is not a file part "
                                   f"(curl -F {name}=@f.exr)", {"part": name, "index": index})
            parts.append(Part(name, index, upload if upload.size > 0 else None))
    return parts


def check_neighbours(window: Window, frame: HeaderInfo, limits: ReadLimits) -> None:
    """Each present neighbour's header against frame t's: 400 for one that is not an EXR, 413 for one over the
    limits, 422 for another size, layout or shot; every error names the part."""
    for part in window.parts:
        if part.upload is None:
            continue
        try:
            part.upload.file.seek(0)
            info = read_header(part.upload.file, limits)
        except FrameError as exc:
            raise _named(exc, part) from None
        if (info.width, info.height) != (frame.width, frame.height):
            raise ServiceError(422, "window_mismatch", f"neighbour {part.name} is {info.width}x{info.height}, but "
                               f"the frame is {frame.width}x{frame.height}: a window's frames must have one size",
                               part.details(width=info.width, height=info.height))
        if shot_layout(info.channels) != shot_layout(frame.channels):
            differing = sorted(set(shot_layout(info.channels)) ^ set(shot_layout(frame.channels)))
            raise ServiceError(422, "window_mismatch", f"neighbour {part.name} carries other channels than the "
                               f"frame (differing: {', '.join(differing[:6])}): a window's frames must have one "
                               "layout", part.details(differing=differing[:16]))
        theirs, ours = info.attributes.get(SHOT_KEY), frame.attributes.get(SHOT_KEY)
        if theirs is not None and ours is not None and theirs != ours:
            raise ServiceError(422, "window_mismatch", f"neighbour {part.name} is of shot {theirs[:100]!r}, but the "
                               f"frame is of shot {ours[:100]!r}", part.details(shot=theirs[:100]))


def _named(exc: FrameError, part: Part) -> ServiceError:
    details = exc.details if isinstance(exc.details, dict) else ({"detail": exc.details} if exc.details else {})
    return ServiceError(exc.status, exc.code, f"neighbour {part.name}: {exc.message}", {**details, **part.details()})


def read_window(window: Window, centre: Any, limits: ReadLimits, nonfinite: str,
                layout: str) -> tuple[list[Any], int]:
    """The window's frames in order (None where missing) and frame t's index: ``centre`` is frame t, decoded;
    each neighbour is decoded here, its errors naming the part."""
    before = max((p.index for p in window.parts if p.field == "previous"), default=0)
    after = max((p.index for p in window.parts if p.field == "next"), default=0)
    frames: list[Any] = [None] * (before + 1 + after)
    frames[before] = centre
    for part in window.parts:
        if part.upload is None:
            continue
        part.upload.file.seek(0)
        try:
            frames[before + part.offset] = read_frame(part.upload.file, limits=limits, nonfinite=nonfinite,
                                                      layout=layout)
        except FrameError as exc:
            raise _named(exc, part) from None
    return frames, before


def multipart_boundary(content_type: str | None) -> bytes | None:
    """The boundary of a ``multipart/form-data`` Content-Type; None for any other body."""
    media, _, options = (content_type or "").partition(";")
    if media.strip().lower() != "multipart/form-data":
        return None
    for option in options.split(";"):
        key, _, value = option.strip().partition("=")
        if key.strip().lower() == "boundary" and value.strip().strip('"'):
            return value.strip().strip('"').encode("latin-1", "replace")
    return None


class FirstPart:
    """The size of a multipart body's first part (its delimiter, headers and content: the bytes one frame of a
    window takes), found as the body streams past: the distance between its first two delimiters."""

    def __init__(self, boundary: bytes) -> None:
        self.delimiter = b"--" + boundary
        self.starts: list[int] = []
        self.offset = 0  # bytes fed so far
        self.tail = b""  # the last bytes fed, in case a delimiter spans two chunks

    @property
    def size(self) -> int | None:
        return self.starts[1] - self.starts[0] if len(self.starts) == 2 else None

    def feed(self, chunk: bytes) -> None:
        if len(self.starts) == 2 or not chunk:
            return
        data, base = self.tail + chunk, self.offset - len(self.tail)
        at = data.find(self.delimiter)
        while at >= 0 and len(self.starts) < 2:
            self.starts.append(base + at)
            at = data.find(self.delimiter, at + len(self.delimiter))
        self.tail = data[-(len(self.delimiter) - 1):]
        self.offset += len(chunk)


def window_too_large(limit: int, first: FirstPart, received: int | None = None) -> ServiceError:
    """:func:`service.errors.body_too_large` for a multipart body, saying how many frames the size of its first
    part fit."""
    base = body_too_large(limit, received)
    details, size = dict(base.details), first.size
    if size is None:
        fit = "its first part alone is over the limit: not one frame of that size fits"
        details["frames_fit"] = 0
    else:
        details.update(frame_bytes=size, frames_fit=limit // size)
        fit = (f"{limit // size} frame(s) of {size} bytes (the size of its first part) fit: send a smaller window "
               "or split the frames")
    return ServiceError(base.status, base.code, f"{base.message}; {fit}", details, base.headers)
