"""The outlier detector off the critical path, with the same result: model.outliers.split_frame measures and
searches a frame's layers in worker threads (``threads``, from ``$GRADSEP_LAYER_THREADS`` in reconstruct), and
groups few bright pixels from their coordinates instead of labelling the whole frame. Neither may change a bit of
what the detector hands on, or of a reconstruction, and an error in one layer's detection is raised as it was.

Frames: the committed example and the procedural test frame (as in test_outliers.py), with a variance channel
added, outliers as renderers make them, a light in view, NaN/Inf values and many fireflies.
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import ndimage

import gradsep.model.outliers as outliers
import gradsep.model.reconstruct as reconstruct_module
from gradsep.model.exr_read import read_frame
from gradsep.model.frame import Frame, Layer
from gradsep.model.robust import lit_level_of_luminance, luminance, robust_level
from gradsep.model.synthetic import with_outlier
from tests.model.shipped import models_for

REPO = Path(__file__).resolve().parents[2]
EXAMPLE, PROCEDURAL = REPO / "examples" / "cbox-16spp.exr", REPO / "tests" / "data" / "procedural-4242-16spp.exr"


def _with_variance(frame: Frame) -> Frame:
    """``frame`` with a variance channel (a noise of 30 % of each pixel's mean at 16 spp)."""
    return dataclasses.replace(frame, layers={
        name: Layer(layer.base, layer.dx, layer.dy, ((0.3 * layer.base.mean(-1)) ** 2 / 16).astype(np.float32))
        for name, layer in frame.layers.items()})


def _edited(frame: Frame, edit: Any) -> Frame:
    """``frame`` with ``edit(base, dx, dy, var)`` (copies, changed in place) applied to every layer."""
    layers = {}
    for name, layer in frame.layers.items():
        arrays = [None if a is None else a.copy() for a in (layer.base, layer.dx, layer.dy, layer.var)]
        edit(*arrays)
        layers[name] = Layer(*arrays)
    return dataclasses.replace(frame, layers=layers)


def _light(base: np.ndarray, dx: np.ndarray, dy: np.ndarray, var: np.ndarray) -> None:
    mean = float(base.mean())
    base[20:22, 30:32] = 1e4 * mean  # a small light whose samples agree
    var[20:22, 30:32] = 1e-3 * mean * mean
    base[60:68, 60:70] = 500 * mean  # a larger one: capped for oidn


def _nonfinite(base: np.ndarray, dx: np.ndarray, dy: np.ndarray, var: np.ndarray) -> None:
    base[5, 5], base[40, 50, 1], base[70, 10] = np.nan, np.inf, -np.inf
    dx[33, 33], dy[12, 80, 2] = np.inf, np.nan


def _many(base: np.ndarray, dx: np.ndarray, dy: np.ndarray, var: np.ndarray) -> None:
    rng = np.random.default_rng(3)
    base[rng.random(base.shape[:2]) < 0.03] += np.float32(1e4 * base.mean())  # over SPARSE_SHARE: labelled whole
    dx[rng.random(base.shape[:2]) < 0.004] = np.float32(1e5 * base.mean())


def _frames() -> dict[str, Frame]:
    plain, procedural = read_frame(EXAMPLE), _with_variance(read_frame(PROCEDURAL))
    example = _with_variance(plain)
    centre = (example.height // 2, example.width // 2)
    return {"example": example, "procedural": procedural, "no variance": plain,
            "firefly with gradients": with_outlier(example, "grad", centre, 1e6),
            "pair": with_outlier(example, "pair", (10, 20), 1e3),
            "3x3 block at a corner": with_outlier(example, "block", (0, 0), 1e12),
            "pair in one layer": with_outlier(procedural, "pair", (30, 40), 1e12, layers=("direct",)),
            "block, no variance": with_outlier(plain, "block", centre, 1e6),
            "light in view": _edited(example, _light), "NaN and Inf": _edited(example, _nonfinite),
            "many fireflies": _edited(procedural, _many)}


_cache: dict[str, dict[str, Frame]] = {}


def _frame(name: str) -> Frame:
    if not _cache:
        _cache["frames"] = _frames()
    return _cache["frames"][name]


CASES = ["example", "procedural", "no variance", "firefly with gradients", "pair", "3x3 block at a corner",
         "pair in one layer", "block, no variance", "light in view", "NaN and Inf", "many fireflies"]


def _arrays(frame: Frame, split: outliers.FrameSplit) -> dict[str, Any]:
    """Everything split_frame hands on, as arrays and numbers by name."""
    out: dict[str, Any] = {}
    for name, layer in frame.layers.items():
        for part in ("base", "dx", "dy", "var"):
            out[f"{name}.{part}"] = getattr(layer, part)
    for name, s in split.layers.items():
        spread = s.spread or (None, None, None)
        for part, value in (("rows", spread[0]), ("cols", spread[1]), ("excess", spread[2]),
                            ("in_place", s.in_place), ("pinned", s.pinned)):
            out[f"{name}.{part}"] = value
        out[f"{name}.counts"] = (s.outliers, s.lights, s.gradients, s.sources)
    out["lit"] = split.lit_levels
    return out


def _same_bits(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a.keys() == b.keys()
    for key, x in a.items():
        y = b[key]
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), key
        else:
            assert x == y, key


@pytest.mark.parametrize("case", CASES)
def test_the_detector_in_threads_and_by_coordinates_hands_on_the_same_bits(case: str, monkeypatch) -> None:
    frame = _frame(case)
    for sources in (False, True):
        alone = _arrays(*outliers.split_frame(frame, sources))
        _same_bits(_arrays(*outliers.split_frame(frame, sources, threads=2)), alone)
        _same_bits(_arrays(*outliers.split_frame(frame, sources, threads=8)), alone)
        with monkeypatch.context() as m:
            m.setattr(outliers, "SPARSE_SHARE", 0.0)  # scipy.ndimage.label on the whole frame, as before
            _same_bits(_arrays(*outliers.split_frame(frame, sources, threads=2)), alone)
    if case not in ("example", "procedural", "no variance"):  # ordinary frames: nothing to find
        assert outliers.split_frame(frame)[1].layers or outliers.split_frame(frame, True)[1].layers  # found some


def test_the_layers_are_searched_in_worker_threads(monkeypatch) -> None:
    """threads=2: each layer is measured and searched off the calling thread; threads=1: in it."""
    seen: list[str] = []
    measure, search = outliers._base_level, outliers._split_layer

    def spy(fn: Any) -> Any:
        def wrapped(*args: Any) -> Any:
            seen.append(threading.current_thread().name)
            return fn(*args)
        return wrapped

    monkeypatch.setattr(outliers, "_base_level", spy(measure))
    monkeypatch.setattr(outliers, "_split_layer", spy(search))
    frame = _frame("pair")
    outliers.split_frame(frame, threads=2)
    assert len(seen) == 4 and all(name.startswith("gradsep-outliers") for name in seen)
    seen.clear()
    outliers.split_frame(frame, threads=1)
    assert seen == [threading.current_thread().name] * 4


@pytest.mark.parametrize("stage", ["_base_level", "_split_layer"])
def test_an_error_in_one_layers_detection_is_raised_as_it_is(stage: str, monkeypatch) -> None:
    """The error of the layer that fails, unchanged (type, message); where several fail, the first in the frame's
    order, as one after the other would raise it; threads or not."""
    frame = _frame("pair")
    original = getattr(outliers, stage)
    failing: set[str] = set()

    def fail(layer: Layer, *args: Any) -> Any:
        name = next(n for n, candidate in frame.layers.items() if candidate is layer)
        if name in failing:
            raise ValueError(f"layer {name}: cannot be searched")
        return original(layer, *args)

    monkeypatch.setattr(outliers, stage, fail)
    for threads in (1, 2):
        failing.clear()
        failing.add("indirect")
        with pytest.raises(ValueError, match="^layer indirect: cannot be searched$"):
            outliers.split_frame(frame, threads=threads)
        failing.add("direct")
        with pytest.raises(ValueError, match="^layer direct: cannot be searched$"):
            outliers.split_frame(frame, threads=threads)


def test_reconstruct_runs_the_detector_in_the_layer_threads(monkeypatch) -> None:
    asked: list[int] = []
    split = outliers.split_frame

    def spy(frame: Frame, sources: bool = False, threads: int = 1) -> Any:
        asked.append(threads)
        return split(frame, sources, threads)

    monkeypatch.setattr(outliers, "split_frame", spy)
    frame = _frame("example")
    for setting, expected in (("1", 1), ("2", 2), ("3", 3)):
        monkeypatch.setenv(reconstruct_module.LAYER_THREADS_ENV, setting)
        reconstruct_module.reconstruct(frame, "oidn", models=models_for("oidn"))
        assert asked[-1] == expected


@pytest.mark.parametrize("method", ["oidn", "oidn-l1", "fused", "network"])
def test_reconstructions_do_not_depend_on_the_detectors_threads(method: str, monkeypatch) -> None:
    models = models_for(method)
    for case in ("pair", "light in view", "many fireflies"):
        frame = _frame(case)
        results = []
        for setting in ("1", "2"):
            monkeypatch.setenv(reconstruct_module.LAYER_THREADS_ENV, setting)
            results.append(reconstruct_module.reconstruct(frame, method, models=models))
        one, two = results
        assert one.image.tobytes() == two.image.tobytes() and one.warnings == two.warnings, case
        assert all(one.layers[n].tobytes() == two.layers[n].tobytes() for n in frame.layers), case


def _mask(rng: np.random.Generator, trial: int) -> np.ndarray:
    height, width = (int(v) for v in rng.integers(1, 70, 2))
    if trial % 5 == 0:  # a snake: one long chain across the rows
        over = np.zeros((height, width), bool)
        over[::2] = True
        over[1::4, -1] = over[3::4, 0] = True
        return over & (rng.random((height, width)) < 0.99)
    return rng.random((height, width)) < rng.choice([0.001, 0.01, 0.015, 0.1, 0.4, 0.7])


def test_grouping_by_coordinates_labels_as_scipy_does(monkeypatch) -> None:
    """_label's groups, numbers and boxes are scipy.ndimage.label's and find_objects' on sparse and dense masks,
    snakes included, by coordinates, and by scipy where the grouping does not settle in GROUP_ROUNDS."""
    rng = np.random.default_rng(0)
    monkeypatch.setattr(outliers, "SPARSE_SHARE", 1.0)  # every mask by coordinates
    for trial in range(400):
        over = _mask(rng, trial)
        if not over.any():
            continue
        labels, _ = ndimage.label(over, structure=np.ones((3, 3), bool))
        boxes = [(s[0].start, s[0].stop, s[1].start, s[1].stop) for s in ndimage.find_objects(labels)]
        ys, xs = np.nonzero(over)
        assert outliers._groups(over, ys, xs) is not None  # settled: the coordinates path ran
        mine, my_boxes = outliers._label(over)
        assert mine.dtype == labels.dtype and np.array_equal(mine, labels)
        assert my_boxes.tolist() == [list(b) for b in boxes]
    monkeypatch.setattr(outliers, "GROUP_ROUNDS", 0)  # never settles: scipy labels it
    over = _mask(rng, 1) | _mask(np.random.default_rng(1), 1)[:1, :1]
    assert outliers._groups(over, *np.nonzero(over)) is None
    assert np.array_equal(outliers._label(over)[0], ndimage.label(over, structure=np.ones((3, 3), bool))[0])


def test_nonzero_by_rows_is_numpys() -> None:
    rng = np.random.default_rng(1)
    for share in (0.0, 1e-5, 1e-3, 0.05, 0.5):
        mask = rng.random((300, 200)) < share
        for mine, numpys in zip(outliers._nonzero(mask), np.nonzero(mask), strict=True):
            assert mine.dtype == numpys.dtype and np.array_equal(mine, numpys)


def test_the_lit_level_skips_sanitising_only_what_needs_none() -> None:
    """lit_level_of_luminance takes the winsorised mean of a clean luminance directly, and of anything else
    (NaN, negative, float32) what robust_level makes of it: both as the definition gives them."""
    from tests.model.test_outliers import _lit_level_by_definition

    lum = luminance(_frame("procedural").layers["direct"].base)
    assert lit_level_of_luminance(lum) == robust_level(lum) == _lit_level_by_definition(lum)  # every bin lit
    for bad in (np.nan, -1.0, np.inf):
        odd = lum.copy()
        odd[3, 4] = bad
        dark = odd.copy()
        dark[: dark.shape[0] // 2] = 0.0
        for image in (odd, dark, dark.astype(np.float32)):
            level = lit_level_of_luminance(image)
            assert np.isfinite(level) and level > 0.0
    dark = lum.copy()
    dark[: dark.shape[0] // 2] = 0.0
    dark[-1, -1] = -2.0  # not clean: robust_level's reading (negatives as 0) sets the threshold
    assert lit_level_of_luminance(dark) == _lit_level_by_definition(dark)
