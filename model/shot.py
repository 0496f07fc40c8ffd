"""Shots: frame ranges, frame-numbered file patterns, per-frame seeds and linear parameter animation.

Standard library only, so the command-line parsers may use it. Frames are numbered as farms number them (a shot
is e.g. frames 1001-1100, both ends included).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from gradsep.model.errors import CommandError

_FIELD = re.compile(r"%(0?\d*)d|#+")
_MASK32 = 0xFFFFFFFF


def parse_frames(text: str) -> range:
    """``"1001-1100"`` (both ends included) or ``"7"`` -> the range of frame numbers; integers >= 0. An empty,
    reversed or non-integer range is a user error naming it."""
    raw = (text or "").strip()
    if not raw:
        raise CommandError("--frames is empty: expected A-B (e.g. 1001-1100) or one frame number")
    first, sep, last = raw.partition("-")
    if not re.fullmatch(r"\d+", first.strip()) or (sep and not re.fullmatch(r"\d+", last.strip())):
        raise CommandError(f"--frames {text!r}: expected A-B with integers 0 <= A <= B (e.g. 1001-1100) or one "
                           "frame number")
    a = int(first)
    b = int(last) if sep else a
    if b < a:
        raise CommandError(f"--frames {text!r} is reversed: the first frame {a} is after the last {b}")
    return range(a, b + 1)


def shot_name(frames: range) -> str:
    """The shot's frame range as written in headers: ``"A-B"``."""
    return f"{frames.start}-{frames.stop - 1}"


class FramePattern:
    """A path with one frame-number field: printf ``%d`` / ``%0Nd`` or a run of ``#`` (``####``: four digits,
    zero-padded). :attr:`has_field` says whether it has one; :meth:`path` needs one."""

    def __init__(self, text: str) -> None:
        self.text = str(text)
        fields = list(_FIELD.finditer(self.text))
        if len(fields) > 1:
            raise CommandError(f"{self.text}: more than one frame-number field")
        self._field = fields[0] if fields else None

    @property
    def has_field(self) -> bool:
        return self._field is not None

    def require_field(self, what: str) -> FramePattern:
        """``self``, or a user error naming ``what`` (an output or input of a shot needs a frame field)."""
        if self._field is None:
            raise CommandError(f"{what} {self.text} has no frame-number field (%04d, %d or ####) for a shot's "
                               "frames")
        return self

    def path(self, frame: int) -> Path:
        """The file of frame ``frame``."""
        m = self._field
        if m is None:
            raise CommandError(f"{self.text} has no frame-number field (%04d, %d or ####)")
        token = m.group(0)
        if token.startswith("#"):
            number = f"{frame:0{len(token)}d}"
        else:
            spec = m.group(1)
            number = f"{frame:{spec}d}" if spec else str(frame)
        return Path(self.text[:m.start()] + number + self.text[m.end():])


def _fmix32(x: int) -> int:
    """MurmurHash3's 32-bit finaliser: a bijection on 32-bit integers that mixes every bit."""
    x &= _MASK32
    x ^= x >> 16
    x = (x * 0x85EBCA6B) & _MASK32
    x ^= x >> 13
    x = (x * 0xC2B2AE35) & _MASK32
    return x ^ (x >> 16)


def frame_seed(seed: int, frame: int) -> int:
    """Frame ``frame``'s 32-bit sampler seed in a shot seeded ``seed``: distinct for every frame number of one shot
    below 2^32 (a bijective mix of the seed's hash plus an odd multiple of the frame), so no two frames share a
    noise pattern."""
    base = _fmix32(_fmix32(seed & _MASK32) ^ ((seed >> 32) * 0x9E3779B9))
    return _fmix32((base + frame * 0x9E3779B9) & _MASK32)


def parse_shard(text: str) -> tuple[int, int]:
    """``--shard i/n`` -> (i, n) with 0 <= i < n; else a user error."""
    i, sep, n = (text or "").partition("/")
    if not sep or not re.fullmatch(r"\d+", i.strip()) or not re.fullmatch(r"\d+", n.strip()):
        raise CommandError(f"--shard must be i/n with 0 <= i < n (e.g. 0/4), got {text!r}")
    shard = (int(i), int(n))
    if shard[1] < 1 or shard[0] >= shard[1]:
        raise CommandError(f"--shard must be i/n with 0 <= i < n (e.g. 0/4), got {text!r}")
    return shard


def shard_frames(frames: range, shard: tuple[int, int]) -> range:
    """Shard i of n's frames: a contiguous chunk (frames stay next to their neighbours, and the shard's first frame
    judges the plan for the rest). Chunk i starts at ``len * i // n``: every frame is in exactly one shard, and
    shard sizes differ by at most one frame (a shard is empty when n exceeds the shot's length)."""
    i, n = shard
    count = len(frames)
    return frames[count * i // n: count * (i + 1) // n]


@dataclass(frozen=True)
class Animation:
    """``--animate NAME=START:END``: a ``$NAME`` scene parameter interpolated linearly over the shot, a number
    or a comma-separated vector (``"0,1,2:4,1,2"``, interpolated component by component)."""

    name: str
    start: tuple[float, ...]
    end: tuple[float, ...]

    def value(self, frame: int, frames: range) -> str:
        """The parameter's value at ``frame`` as scene text: START at the shot's first frame, END at its last."""
        span = len(frames) - 1
        t = (frame - frames.start) / span if span > 0 else 0.0
        parts = [a + (b - a) * t for a, b in zip(self.start, self.end, strict=True)]
        return ", ".join(f"{v:.9g}" for v in parts)


def _numbers(text: str, spec: str) -> tuple[float, ...]:
    import math

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise CommandError(f"--animate {spec!r}: {text!r} is not a number or a comma-separated vector") from None
    if not all(math.isfinite(v) for v in values):
        raise CommandError(f"--animate {spec!r}: values must be finite")
    return values


def parse_animation(spec: str) -> Animation:
    """``"NAME=START:END"`` -> :class:`Animation`; a malformed one is a user error naming it."""
    name, sep, span = (spec or "").partition("=")
    name = name.strip()
    start, colon, end = span.partition(":")
    if not sep or not colon or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise CommandError(f"bad --animate {spec!r}: expected NAME=START:END (e.g. x=0:1 or pos=0,0,0:1,0,0)")
    a, b = _numbers(start.strip(), spec), _numbers(end.strip(), spec)
    if len(a) != len(b):
        raise CommandError(f"--animate {spec!r}: START has {len(a)} components and END {len(b)}")
    return Animation(name, a, b)


def parse_animations(specs: list[str] | None) -> tuple[Animation, ...]:
    """Every ``--animate``; a parameter animated twice is a user error."""
    out = tuple(parse_animation(s) for s in specs or [])
    names = [a.name for a in out]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise CommandError(f"--animate {', '.join(twice)} given more than once")
    return out
