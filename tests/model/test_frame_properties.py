"""Property-based tests (hypothesis) of the frame contract: any channel set, any size 1..64, half or float,
NaN/Inf anywhere -- a frame either reads back exactly what was written or fails with the documented error.

Pixel values come from numpy generators seeded by hypothesis (drawing 64x64x30 floats element by element would
be slow and shrink badly); what hypothesis chooses -- layers, features, extra channels, sizes, dtype, where the
non-finite values go -- is what the contract branches on, so that is what it explores and shrinks.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gradsep.model.errors import ChannelError, NonFiniteError
from gradsep.model.exr_read import read_frame
from gradsep.model.exr_write import encode_exr
from gradsep.model.frame import FEATURE_CHANNELS, layer_channels
from gradsep.model.policy import FEATURE_GROUPS
from tests.service.frames import channels_bytes

SETTINGS = settings(max_examples=40, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
LAYER_SETS = [("direct",), ("indirect",), ("direct", "indirect"), ("color",)]
HALF_MAX = 65504.0


@st.composite
def frames(draw) -> dict:
    """A valid frame's channels: layers, optional features, optional foreign channels, size, dtype, pixels."""
    layers = draw(st.sampled_from(LAYER_SETS))
    gradients = draw(st.booleans())  # False: a plain path-traced frame (base radiance only)
    gradient_layers = layers if gradients else ()
    if gradients and len(layers) > 1 and draw(st.booleans()):  # gradients on one layer only (per-layer contract)
        gradient_layers = (draw(st.sampled_from(layers)),)
    features = draw(st.booleans())
    foreign = draw(st.lists(st.sampled_from(["A", "Z", "custom.R", "aov.normal.X"]), unique=True, max_size=2))
    h, w = draw(st.integers(1, 64)), draw(st.integers(1, 64))
    half = draw(st.booleans())
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    peak = HALF_MAX if half else 1e30
    channels = {}
    names = [c for layer in layers for c in layer_channels(layer, layer in gradient_layers)]
    for name in (*names, *(FEATURE_CHANNELS if features else ())):
        if name in FEATURE_CHANNELS:
            channels[name] = rng.uniform(0, 1, (h, w))
        else:  # radiance over many decades, gradients signed
            magnitude = 10.0 ** rng.uniform(-6, np.log10(peak), (h, w))
            sign = 1.0 if name.count(".") == 1 else rng.choice([-1.0, 1.0], (h, w))
            channels[name] = np.minimum(magnitude, peak) * sign
    for name in foreign:
        channels[name] = rng.uniform(0, 1, (h, w))
    channels = {k: v.astype(np.float16 if half else np.float32).astype(np.float32) for k, v in channels.items()}
    return {"layers": layers, "gradient_layers": gradient_layers, "features": features, "foreign": foreign,
            "h": h, "w": w, "half": half, "channels": channels}


def _assert_same(frame, channels: dict[str, np.ndarray]) -> None:
    got = frame.to_channels()
    assert set(got) == {k for k in channels if not _foreign(k)}
    for name, value in got.items():
        np.testing.assert_array_equal(value, channels[name], err_msg=name)


def _foreign(name: str) -> bool:
    """Channels the contract ignores (with a warning); ``A`` is not one of them: it is alpha, carried through."""
    return name != "A" and name.split(".", 1)[0] not in ("direct", "indirect", "color", "albedo", "normal", "depth")


@SETTINGS
@given(frames())
def test_round_trip_is_exact(spec: dict) -> None:
    """Write then read: the same layers, features and pixels (bit-exact: the values are representable in the
    stored type), foreign channels ignored with one warning that names them."""
    data = encode_exr(spec["channels"], half=spec["half"])
    frame = read_frame(data)
    assert list(frame.layers) == list(spec["layers"])
    assert (frame.height, frame.width) == (spec["h"], spec["w"])
    assert (frame.features is not None) == spec["features"]
    assert frame.gradient_layers == spec["gradient_layers"]
    assert frame.has_gradients == (spec["gradient_layers"] == spec["layers"])
    _assert_same(frame, spec["channels"])
    ignored = [name for name in spec["foreign"] if _foreign(name)]
    if ignored:
        assert len(frame.warnings) == 1 and all(name in frame.warnings[0] for name in ignored)
    else:
        assert frame.warnings == []


@SETTINGS
@given(frames(), st.data())
def test_missing_or_unknown_channel_is_named(spec: dict, data) -> None:
    channels = dict(spec["channels"])
    # a one-channel feature group (depth.Z) dropped is an absent group, which a frame may be (each group optional)
    required = [c for c in channels if not _foreign(c) and c != "A" and (c,) not in FEATURE_GROUPS.values()]
    dropped = data.draw(st.sampled_from(required), label="dropped")
    del channels[dropped]
    unknown = data.draw(st.sampled_from([None, f"{spec['layers'][0]}.dz.R", "albedo.A"]), label="unknown")
    if unknown:
        channels[unknown] = np.zeros((spec["h"], spec["w"]), np.float32)
    with pytest.raises(ChannelError) as info:
        read_frame(encode_exr(channels, half=spec["half"]))
    assert dropped in str(info.value)
    if unknown:
        assert unknown in str(info.value)


@SETTINGS
@given(frames(), st.data())
def test_non_finite_values_rejected_or_zeroed_as_documented(spec: dict, data) -> None:
    """NaN/±Inf anywhere in radiance or gradients: ``reject`` raises NonFiniteError with exact per-channel
    counts; ``zero`` replaces exactly those values with 0 and says so; in features they become 0 silently."""
    h, w = spec["h"], spec["w"]
    channels = {k: v.copy() for k, v in spec["channels"].items()}
    targets = [c for c in channels if not _foreign(c) and c != "A"]
    pokes = data.draw(st.lists(st.tuples(st.sampled_from(targets), st.integers(0, h - 1), st.integers(0, w - 1),
                                         st.sampled_from([np.nan, np.inf, -np.inf])),
                               min_size=1, max_size=6), label="pokes")
    for name, y, x, value in pokes:
        channels[name][y, x] = value
    raw = channels_bytes(channels, half=spec["half"])  # OpenEXR directly: half Inf stays Inf
    counts = {n: int(np.count_nonzero(~np.isfinite(v))) for n, v in channels.items() if n not in FEATURE_CHANNELS}
    counts = {n: k for n, k in counts.items() if k}
    if counts:
        with pytest.raises(NonFiniteError) as info:
            read_frame(raw)
        assert info.value.details == counts
    else:  # only features were poked: read as is, their non-finite values become 0
        assert not any(m.startswith("replaced non-finite") for m in read_frame(raw).warnings)
    frame = read_frame(raw, nonfinite="zero")
    expected = {k: np.where(np.isfinite(v), v, 0.0).astype(np.float32) for k, v in channels.items()}
    _assert_same(frame, expected)
    zero_warnings = [m for m in frame.warnings if m.startswith("replaced non-finite")]
    assert bool(zero_warnings) == bool(counts)
    for name, k in counts.items():
        assert f"{name} ({k})" in zero_warnings[0]


@SETTINGS
@given(frames())
def test_half_writer_saturates_instead_of_writing_inf(spec: dict) -> None:
    """Our half writer clips to ±65504 (a float32 frame above half range must not turn into Inf on disk)."""
    channels = {k: v * np.float32(1e3) for k, v in spec["channels"].items()}
    frame = read_frame(encode_exr(channels, half=True))
    for name, value in frame.to_channels().items():
        want = np.clip(channels[name], -HALF_MAX, HALF_MAX).astype(np.float16).astype(np.float32)
        np.testing.assert_array_equal(value, want, err_msg=name)
