"""Motion vectors in the frame contract: Motion (model/frame.py), read and written by model/exr_read.py and
model/exr_write.py, and Cycles' Vector pass read through the cycles layout (model/channels.py)."""

from __future__ import annotations

import io

import numpy as np
import OpenEXR
import pytest

from gradsep.model.errors import ChannelError
from gradsep.model.exr_read import read_frame
from gradsep.model.exr_write import encode_exr, write_frame
from gradsep.model.frame import MOTION_CHANNELS, Frame, Layer, Motion, frame_channels, sanitize_motion
from tests.model.frames import make_frame


def _motion(h: int = 6, w: int = 9, seed: int = 1) -> Motion:
    rng = np.random.default_rng(seed)
    backward = (rng.normal(size=(h, w, 2)) * 10).astype(np.float32)  # digits a half file would round away
    forward = (rng.normal(size=(h, w, 2)) * 3).astype(np.float32)
    b_ok, f_ok = rng.random((h, w)) > 0.3, rng.random((h, w)) > 0.3
    backward[~b_ok], forward[~f_ok] = 0.0, 0.0
    return Motion(backward, forward, b_ok, f_ok)


@pytest.mark.parametrize("half", [False, True])
def test_motion_vectors_round_trip_exactly_in_float_and_half_files(tmp_path, half: bool) -> None:
    frame = make_frame()
    frame.motion = _motion()
    path = tmp_path / "f.exr"
    write_frame(path, frame, half=half)
    pixels = OpenEXR.File(str(path), separate_channels=True).channels()
    assert all(pixels[c].pixels.dtype == np.float32 for c in MOTION_CHANNELS)
    assert pixels["direct.R"].pixels.dtype == (np.float16 if half else np.float32)
    back = read_frame(path)
    assert back.motion is not None and back.motion.directions == ("backward", "forward")
    for d in ("backward", "forward"):
        np.testing.assert_array_equal(back.motion.side(d)[0], frame.motion.side(d)[0])
        np.testing.assert_array_equal(back.motion.side(d)[1], frame.motion.side(d)[1])
    assert not back.warnings


def test_one_side_only_and_no_validity_channel_read() -> None:
    frame = make_frame()
    vectors = np.full((6, 9, 2), 1.5, np.float32)
    frame.motion = Motion(forward=vectors, forward_valid=np.ones((6, 9), bool))
    channels = frame.to_channels()
    del channels["forward.valid"]  # a compositing tool's file: u and v only
    back = read_frame(encode_exr(channels))
    assert back.motion.directions == ("forward",) and back.motion.backward is None
    assert back.motion.forward_valid.all()
    np.testing.assert_array_equal(back.motion.forward, vectors)


def test_a_lone_v_or_validity_channel_is_a_channel_error_naming_the_missing_ones() -> None:
    channels = make_frame().to_channels()
    channels["backward.v"] = np.zeros((6, 9), np.float32)
    with pytest.raises(ChannelError, match="backward.u"):
        read_frame(encode_exr(channels))
    channels = make_frame().to_channels()
    channels["forward.valid"] = np.ones((6, 9), np.float32)
    with pytest.raises(ChannelError, match="forward.u, forward.v"):
        read_frame(encode_exr(channels))
    channels = make_frame().to_channels()
    channels["forward.w"] = np.ones((6, 9), np.float32)  # under a contract prefix: a producer bug
    with pytest.raises(ChannelError, match="unknown channels forward.w"):
        read_frame(encode_exr(channels))


def test_non_finite_and_absurd_vectors_are_invalid_zero_and_counted() -> None:
    frame = make_frame()
    motion = _motion()
    motion.backward[0, 0] = (np.nan, 1.0)
    motion.backward[0, 1] = (np.inf, 0.0)
    motion.backward[0, 2] = (0.0, 4.0 * np.hypot(6, 9) + 1.0)  # beyond 4 diagonals
    motion.backward[0, 3] = (0.0, 4.0 * np.hypot(6, 9) - 1.0)  # long but plausible
    motion.backward_valid[0, :4] = True
    frame.motion = motion
    back = read_frame(encode_exr(frame.to_channels()))
    vectors, valid = back.motion.side("backward")
    assert not valid[0, :3].any() and valid[0, 3]
    assert np.all(vectors[0, :3] == 0) and np.all(np.isfinite(vectors))
    assert any("3 non-finite or absurd backward motion vector(s)" in w for w in back.warnings)


def test_sanitize_counts_only_pixels_that_were_valid() -> None:
    vectors = np.zeros((2, 2, 2), np.float32)
    vectors[0, 0, 0] = np.nan
    vectors[1, 1, 1] = np.nan
    out, ok, bad = sanitize_motion(vectors, np.array([[True, True], [True, False]]))
    assert bad == 1 and ok.tolist() == [[False, True], [True, False]] and np.all(out == 0)


def test_a_frame_without_motion_writes_exactly_the_channels_it_did() -> None:
    frame = make_frame()
    channels = frame.to_channels()
    assert tuple(channels) == frame_channels(("direct", "indirect"))
    by_hand = {name: channels[name] for name in frame_channels(("direct", "indirect"))}
    for half in (False, True):
        assert encode_exr(channels, half=half, metadata=frame.metadata) == encode_exr(
            by_hand, half=half, metadata=frame.metadata)
    assert read_frame(encode_exr(channels)).motion is None


def test_warp_source_follows_the_convention() -> None:
    """x_prev = x + backward.u, y_prev = y - backward.v (rows grow downward, v upward)."""
    vectors = np.zeros((4, 5, 2), np.float32)
    vectors[..., 0], vectors[..., 1] = 2.0, 1.0
    rows, cols, valid = Motion(backward=vectors, backward_valid=np.ones((4, 5))).warp_source("backward")
    assert rows[2, 1] == 1.0 and cols[2, 1] == 3.0 and valid.dtype == bool
    with pytest.raises(ValueError, match="no forward"):
        Motion(backward=vectors, backward_valid=np.ones((4, 5))).warp_source("forward")
    with pytest.raises(ValueError, match="together"):
        Motion(backward=vectors)


def _cycles_vector_file(x: float, y: float, z: float, w: float) -> bytes:
    plane = np.ones((4, 6), np.float32)
    channels = {f"ViewLayer.Combined.{c}": plane for c in "RGBA"}
    channels.update({f"ViewLayer.Vector.{c}": plane * value for c, value in zip("XYZW", (x, y, z, w), strict=True)})
    buffer = io.BytesIO()
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels).write(buffer)
    return buffer.getvalue()


def test_cycles_vector_pass_is_converted_to_the_contract_convention() -> None:
    """Cycles: X, Y = previous raster position - this one; Z, W = this one - next; raster y up."""
    frame = read_frame(_cycles_vector_file(3.0, -2.0, 1.5, 0.5))
    assert frame.layout == "cycles:ViewLayer" and frame.motion.directions == ("backward", "forward")
    assert np.all(frame.motion.backward == np.array([3.0, -2.0], np.float32))
    assert np.all(frame.motion.forward == np.array([-1.5, -0.5], np.float32))
    assert frame.motion.backward_valid.all() and frame.motion.forward_valid.all()
    assert not any("Vector" in w for w in frame.warnings)
    bad = read_frame(_cycles_vector_file(np.nan, 0.0, 0.0, 0.0))
    assert not bad.motion.backward_valid.any() and bad.motion.forward_valid.all()
    assert any("24 non-finite or absurd backward" in w for w in bad.warnings)


def test_a_frame_keeps_motion_through_its_layers() -> None:
    frame = Frame({"color": Layer(np.ones((2, 3, 3), np.float32))}, motion=_motion(2, 3))
    assert set(MOTION_CHANNELS) <= set(frame.to_channels())
