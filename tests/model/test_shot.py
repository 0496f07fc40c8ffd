"""model/shot.py: frame ranges, frame patterns, per-frame seeds, shards and parameter animation."""

from __future__ import annotations

from pathlib import Path

import pytest

from gradsep.model.errors import CommandError
from gradsep.model.shot import (
    FramePattern,
    frame_seed,
    parse_animation,
    parse_animations,
    parse_frames,
    parse_shard,
    shard_frames,
    shot_name,
)


def test_frame_ranges():
    assert parse_frames("1001-1100") == range(1001, 1101)
    assert parse_frames(" 7 ") == range(7, 8)
    assert parse_frames("0-0") == range(0, 1)
    assert shot_name(parse_frames("1001-1100")) == "1001-1100"


@pytest.mark.parametrize(("text", "message"), [
    ("", "empty"), ("  ", "empty"), ("10-5", "reversed"), ("a-b", "expected A-B"), ("1.5-3", "expected A-B"),
    ("-3", "expected A-B"), ("1-", "expected A-B"), ("1-2-3", "expected A-B"),
])
def test_bad_frame_ranges_name_the_range(text, message):
    with pytest.raises(CommandError, match=message):
        parse_frames(text)


@pytest.mark.parametrize(("text", "frame", "path"), [
    ("out.%04d.exr", 7, "out.0007.exr"), ("out.%d.exr", 1001, "out.1001.exr"), ("out.####.exr", 42, "out.0042.exr"),
    ("d/s_##.xml", 5, "d/s_05.xml"), ("out.%04d.exr", 12345, "out.12345.exr"),
])
def test_frame_patterns(text, frame, path):
    pattern = FramePattern(text)
    assert pattern.has_field and pattern.path(frame) == Path(path)


def test_a_pattern_without_or_with_two_fields():
    assert not FramePattern("out.exr").has_field
    with pytest.raises(CommandError, match="no frame-number field"):
        FramePattern("out.exr").require_field("output")
    with pytest.raises(CommandError, match="no frame-number field"):
        FramePattern("out.exr").path(1)
    with pytest.raises(CommandError, match="more than one"):
        FramePattern("%04d/out.####.exr")


def test_frame_seeds_are_distinct_32_bit_and_depend_on_the_seed():
    seeds = [frame_seed(0, n) for n in range(1001, 1001 + 5000)]
    assert len(set(seeds)) == len(seeds) and all(0 <= s < 2**32 for s in seeds)
    assert frame_seed(0, 1001) != frame_seed(1, 1001)
    assert frame_seed(3, 12) == frame_seed(3, 12)


@pytest.mark.parametrize("n", [1, 2, 3, 7, 150])
def test_shards_partition_the_shot_into_contiguous_chunks(n):
    frames = parse_frames("1001-1100")
    parts = [shard_frames(frames, (i, n)) for i in range(n)]
    assert sorted(f for p in parts for f in p) == list(frames)
    assert all(p.step == 1 for p in parts)
    assert max(map(len, parts)) - min(map(len, parts)) <= 1


@pytest.mark.parametrize("text", ["", "1", "2/2", "-1/2", "a/b", "0/0", "1/"])
def test_bad_shards(text):
    with pytest.raises(CommandError, match="--shard must be i/n"):
        parse_shard(text)


def test_animation_is_linear_from_first_to_last_frame():
    frames = parse_frames("1001-1005")
    a = parse_animation("x=0:2")
    assert [a.value(n, frames) for n in frames] == ["0", "0.5", "1", "1.5", "2"]
    v = parse_animation("pos=0,1,2:4,1,-2")
    assert v.value(1003, frames) == "2, 1, 0"
    assert parse_animation("x=3:5").value(9, parse_frames("9")) == "3"


@pytest.mark.parametrize(("spec", "message"), [
    ("x", "expected NAME=START:END"), ("x=1", "expected NAME=START:END"), ("1x=0:1", "expected NAME=START:END"),
    ("x=a:1", "not a number"), ("x=0,0:1", "components"), ("x=nan:1", "finite"),
])
def test_bad_animations(spec, message):
    with pytest.raises(CommandError, match=message):
        parse_animation(spec)


def test_a_parameter_animated_twice():
    with pytest.raises(CommandError, match="more than once"):
        parse_animations(["x=0:1", "x=1:2"])
