"""Writing (model/exr_write.py): a half file saturates instead of overflowing, and a write is atomic."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from gradsep.model.exr_write import write_exr


def test_half_output_saturates_instead_of_overflowing(tmp_path) -> None:
    write_exr(tmp_path / "o.exr", {"R": np.full((2, 2), 1e6, np.float32)}, half=True)
    pixels = OpenEXR.File(str(tmp_path / "o.exr"), separate_channels=True).channels()["R"].pixels
    assert pixels.dtype == np.float16 and np.isfinite(pixels).all() and pixels.max() == 65504


def test_write_is_atomic(tmp_path, monkeypatch) -> None:
    target = tmp_path / "out.exr"
    target.write_bytes(b"previous")

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("gradsep.model.exr_write.os.replace", boom)
    with pytest.raises(OSError):
        write_exr(target, {"R": np.zeros((2, 2), np.float32)})
    assert target.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["out.exr"]
