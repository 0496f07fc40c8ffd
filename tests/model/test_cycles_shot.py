"""A Blender Cycles shot end to end: multilayer EXRs (``ViewLayer.Combined``, the denoising features and the
``Vector`` pass, no variance and no validity channel, as Cycles writes them) through ``gradsep reconstruct
--frames``. The same frames written in the contract's own layout are the control: the Cycles shot must give the
same images bit for bit, so the ``cycles`` layout's reading of colour, features and motion is what a temporal
window sees, and the window must beat the per-frame method against the known truth."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from gradsep.model.exr_read import read_header
from gradsep.model.exr_write import encode_exr
from gradsep.model.metrics import relmse

pytest.importorskip("pyoidn", reason="the per-frame method of a plain frame is oidn")

SIZE, FRAMES, SHIFT = 48, 5, 1.0  # a whole-frame pan, SHIFT pixels right per frame


def _truth(n: int) -> np.ndarray:
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    xx = xx - SHIFT * n
    grey = 0.5 + 0.2 * np.sin(xx / 6.0) * np.cos(yy / 8.0) + 0.3 * (xx > SIZE / 2)
    return np.repeat(grey[..., None], 3, axis=-1).astype(np.float32)


def _channels(n: int, cycles: bool) -> dict[str, np.ndarray]:
    """Frame ``n`` of the pan: noisy colour, constant features, and its motion in the layout's own convention
    (Cycles: X, Y = previous raster position - this one; Z, W = this one - next; the contract: backward.u =
    previous - this, forward.u = next - this)."""
    rng = np.random.default_rng(n)
    truth = _truth(n)
    noisy = np.maximum(truth * (1 + 0.3 * rng.standard_normal(truth.shape[:2]))[..., None], 0).astype(np.float32)
    zero, one = np.zeros((SIZE, SIZE), np.float32), np.ones((SIZE, SIZE), np.float32)
    colour = {c: noisy[..., i] for i, c in enumerate("RGB")}
    if cycles:
        out = {f"ViewLayer.Combined.{c}": v for c, v in colour.items()} | {"ViewLayer.Combined.A": one}
        out |= {f"ViewLayer.Denoising Albedo.{c}": one * 0.5 for c in "RGB"}
        out |= {"ViewLayer.Denoising Normal.X": zero, "ViewLayer.Denoising Normal.Y": zero,
                "ViewLayer.Denoising Normal.Z": one, "ViewLayer.Denoising Depth.Z": one * 3.0}
        return out | {f"ViewLayer.Vector.{c}": one * v for c, v in zip("XYZW", (-SHIFT, 0.0, -SHIFT, 0.0),
                                                                          strict=True)}
    out = {f"color.{c}": v for c, v in colour.items()} | {"A": one}
    out |= {f"albedo.{c}": one * 0.5 for c in "RGB"}
    out |= {"normal.X": zero, "normal.Y": zero, "normal.Z": one, "depth.Z": one * 3.0}
    return out | {"backward.u": one * -SHIFT, "backward.v": zero, "forward.u": one * SHIFT, "forward.v": zero}


def _reconstruct(folder: Path, name: str, window: int) -> list[np.ndarray]:
    out = subprocess.run([sys.executable, "-m", "gradsep", "reconstruct", str(folder / f"{name}.%04d.exr"),
                          "--frames", f"1-{FRAMES}", "--window", str(window), "-o",
                          str(folder / f"{name}-w{window}.%04d.exr")], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    images = []
    for n in range(1, FRAMES + 1):
        with OpenEXR.File(str(folder / f"{name}-w{window}.{n:04d}.exr")) as f:
            images.append(np.asarray(f.channels()["RGBA"].pixels[..., :3], np.float32))
    return images


@pytest.mark.slow
def test_a_cycles_shot_reconstructs_temporally_as_the_same_frames_in_the_contract_layout(tmp_path: Path) -> None:
    for n in range(1, FRAMES + 1):
        (tmp_path / f"cycles.{n:04d}.exr").write_bytes(encode_exr(_channels(n, cycles=True)))
        (tmp_path / f"contract.{n:04d}.exr").write_bytes(encode_exr(_channels(n, cycles=False)))
    cycles = _reconstruct(tmp_path, "cycles", 3)
    contract = _reconstruct(tmp_path, "contract", 3)
    for a, b in zip(cycles, contract, strict=True):
        np.testing.assert_array_equal(a, b)
    assert read_header(tmp_path / "cycles-w3.0003.exr").attributes["gradsep.temporal.neighbours"] == "2,4"
    per_frame = _reconstruct(tmp_path, "cycles", 1)
    inner = range(1, FRAMES - 1)  # frames with both neighbours
    temporal_error = np.mean([relmse(cycles[i], _truth(i + 1)) for i in inner])
    per_frame_error = np.mean([relmse(per_frame[i], _truth(i + 1)) for i in inner])
    assert all(np.isfinite(image).all() for image in cycles)
    assert temporal_error < 0.9 * per_frame_error
