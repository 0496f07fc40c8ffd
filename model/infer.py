"""ONNX Runtime inference of the exported per-layer networks, with tiling for large frames.

Runs with numpy + onnxruntime only (no torch): the serving host and `gradsep reconstruct` import this module.
``NetworkReconstructor.load(models_dir)`` opens ``direct.onnx``, ``indirect.onnx`` and ``color.onnx`` when
present, checks each file's ``gradsep.*`` metadata against this code (layer, channel order, preprocessing
version), and ``reconstruct_layer`` runs one layer of a frame:

    frame layer + features ─► model.preprocess (the same transform training used) ─► reflect-pad to the
    alignment ─► ONNX Runtime ─► crop ─► inverse transform ─► (H, W, 3) float32, finite, ≥ 0

Frames above ``TileSettings.max_untiled_pixels`` are processed in overlapping windows: each window carries
``overlap`` pixels of context on its interior sides; the outer half of that context is discarded (it saw the
window's border) and the inner half is blended with the neighbour by a linear ramp, so seams are feathered. Memory then
depends on the window size, not the frame (benchmarks/bench_network.py --memory measures it). Channel attention
pools over the window, so tiled output is close to, not bit-identical with, untiled output; windows are large
(1 Mpx cores) to keep those statistics close.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import threading
import time
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gradsep.model.onnx_session import ProviderChoice, SessionSettings, graph_session, open_session
from gradsep.model.policy import ILLUMINATION_LAYERS
from gradsep.model.preprocess import (
    DATA_INPUTS,
    DEFAULT_PRIOR,
    GRADIENT_INPUTS,
    LAYER_PLANES,
    MEASURED_PLANES,
    PREPROCESS_VERSION,
    PRIOR_KINDS,
    UNRECORDED_PRIOR_ALPHA,
    DepthRange,
    Window,
    aligned_size,
    crop_to,
    feature_planes,
    layer_planes,
    measured_planes,
    network_inputs,
    network_inputs_numpy,
    output_radiance,
    pad_to_alignment,
    poisson_prior,
    scaled_image,
    scaled_layer,
    unlit_pixels,
    with_prior,
)
from gradsep.model.robust import robust_level

if TYPE_CHECKING:
    import onnxruntime

    from gradsep.model.frame import Features, Layer

#: Model files looked for in the models folder, by layer name.
MODEL_LAYERS: tuple[str, ...] = ILLUMINATION_LAYERS
OUTPUT_NAME = "radiance_log"
log = logging.getLogger("gradsep.infer")


class ModelError(RuntimeError):
    """A model file exists but cannot be served (corrupt, or exported for another layer or preprocessing)."""


@dataclass(frozen=True)
class TileSettings:
    """Tiling: frames up to ``max_untiled_pixels`` run in one piece (1280×720 does); larger ones in windows
    of ``tile``² core pixels plus ``overlap`` pixels of context per interior side."""

    tile: int = 1024
    overlap: int = 96
    max_untiled_pixels: int = 1152 * 1152

    def __post_init__(self) -> None:
        if self.tile < 1 or self.overlap < 0 or self.max_untiled_pixels < 1:
            raise ValueError(f"invalid tile settings {self}")


@dataclass(frozen=True)
class TilePlan:
    """One window: ``core`` is the part it owns, ``window`` = core + context, both (y0, y1, x0, x1)."""

    core: Window
    window: Window


def plan_tiles(height: int, width: int, settings: TileSettings, alignment: int = 1) -> list[TilePlan]:
    """Windows covering the frame; a single window when the frame is small enough.

    Tile and overlap are rounded up to multiples of the network's alignment so every window starts on the
    same stride-2 sampling grid as the whole frame: the encoder's downsampling is not shift-invariant, and a
    window offset by a few pixels would see a differently subsampled image.
    """
    if height * width <= settings.max_untiled_pixels:
        return [TilePlan((0, height, 0, width), (0, height, 0, width))]
    tile = aligned_size(settings.tile, alignment)
    o = aligned_size(settings.overlap, alignment)
    plans = []
    for y0 in range(0, height, tile):
        y1 = min(height, y0 + tile)
        for x0 in range(0, width, tile):
            x1 = min(width, x0 + tile)
            window = (max(0, y0 - o), min(height, y1 + o), max(0, x0 - o), min(width, x1 + o))
            plans.append(TilePlan((y0, y1, x0, x1), window))
    return plans


def _ramp(lo: int, hi: int, size: int, overlap: int) -> np.ndarray:
    """1-D blend weight over a window [lo, hi) of an axis of ``size``.

    On a side where the window carries ``overlap`` pixels of context, the outer half of that context gets
    weight 0 (those pixels saw the window's zero-padded border through the convolutions) and the inner half
    ramps linearly up to 1 at the core; a side on the frame's edge keeps weight 1. The weight is 1 over the
    core, so every pixel has a positive total weight.
    """
    x = np.arange(lo, hi, dtype=np.float32)
    w = np.ones(hi - lo, dtype=np.float32)
    if overlap > 0:
        dead = overlap // 2
        span = overlap - dead + 1
        if lo > 0:
            w = np.minimum(w, np.clip((x - lo - dead + 1) / span, 0.0, 1.0))
        if hi < size:
            w = np.minimum(w, np.clip((hi - 1 - x - dead + 1) / span, 0.0, 1.0))
    return w


@dataclass
class LoadedModel:
    """One ONNX model and what ``describe`` reports about it."""

    name: str
    path: Path
    sha256: str
    metadata: dict[str, str]
    session: onnxruntime.InferenceSession
    alignment: int
    choice: ProviderChoice = ProviderChoice("cpu", "fp32", "default")

    @property
    def prior(self) -> str:
        """What the model refines (model.preprocess.PRIOR_KINDS, checked at load): ``l1``, the truncated L1 Poisson
        solve, also for a model without the key."""
        return self.metadata.get("gradsep.prior", DEFAULT_PRIOR)

    @property
    def prior_alpha(self) -> float:
        """The α of the prior the model was trained on (``gradsep.prior_alpha``, checked at load; a model without
        the key was trained with model.preprocess.UNRECORDED_PRIOR_ALPHA)."""
        return prior_alpha_of(self.metadata)

    def run(self, data: np.ndarray, gradient: np.ndarray) -> np.ndarray:
        """(C, h, w) aligned inputs → (3, h, w) log-domain output."""
        out = self.session.run([OUTPUT_NAME], {"data": data[None], "gradient": gradient[None]})[0]
        return out[0]

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "layer": self.metadata.get("gradsep.layer", self.name),
            "file": self.path.name,
            "inputs": {"data": list(DATA_INPUTS), "gradient": list(GRADIENT_INPUTS)},
            "sha256": self.sha256,
            "bytes": self.path.stat().st_size if self.path.exists() else None,
            "attention": self.metadata.get("gradsep.attention") == "true",
            "prior": self.prior,
            "prior_alpha": self.prior_alpha,
            "alignment": self.alignment,
            **self.choice.describe(),
            "metadata": dict(self.metadata),
        }


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


#: ONNX metadata ``gradsep.prior`` of a ``fused`` blend model (model/fused.py). Such a model is served by the
#: fused method (model.reconstruct.load_fused -> model.fused.FusedReconstructor), never as a network model.
BLEND_PRIOR = "blend"


def prior_alpha_of(meta: dict[str, str]) -> float:
    """A model's prior α from its metadata (``gradsep.prior_alpha``); ValueError when it is not a finite α > 0."""
    raw = meta.get("gradsep.prior_alpha")
    if raw is None:
        return UNRECORDED_PRIOR_ALPHA
    try:
        alpha = float(raw)
    except ValueError:
        alpha = math.nan
    if not (math.isfinite(alpha) and alpha > 0):
        raise ValueError(f"prior alpha {raw!r} is not a finite number > 0")
    return alpha


def _check_metadata(path: Path, name: str, meta: dict[str, str]) -> int:
    """Refuse a model this code would feed wrongly; return its alignment."""
    if meta.get("gradsep.prior") == BLEND_PRIOR:
        raise ModelError(f"{path}: a fused blend model (gradsep.prior = {BLEND_PRIOR}): the fused method serves it "
                         "(models/fused/), not the network method")
    problems = []
    if meta.get("gradsep.layer") != name:
        problems.append(f"it was trained for layer {meta.get('gradsep.layer')!r}, not {name!r}")
    try:
        inputs = json.loads(meta.get("gradsep.inputs", "{}"))
        preprocessing = json.loads(meta.get("gradsep.preprocessing", "{}"))
        alignment = int(meta.get("gradsep.alignment", "0"))
    except (ValueError, TypeError):
        raise ModelError(f"{path}: unreadable gradsep metadata") from None
    if inputs != {"data": list(DATA_INPUTS), "gradient": list(GRADIENT_INPUTS)}:
        problems.append(f"its input channels {inputs} differ from this version's")
    if meta.get("gradsep.prior", DEFAULT_PRIOR) not in PRIOR_KINDS:
        problems.append(f"its prior {meta.get('gradsep.prior')!r} is unknown to this version (known: "
                        f"{', '.join(PRIOR_KINDS)}), so it cannot be computed as the model was trained")
    try:
        prior_alpha_of(meta)
    except ValueError as exc:
        problems.append(f"its {exc}")
    if preprocessing.get("version") != PREPROCESS_VERSION:
        problems.append(f"preprocessing version {preprocessing.get('version')} != {PREPROCESS_VERSION}")
    if alignment < 1:
        problems.append("no valid gradsep.alignment")
    if problems:
        raise ModelError(f"{path}: cannot serve this model: " + "; ".join(problems) + " (re-export it)")
    return alignment


def load_model(path: str | os.PathLike[str], name: str, settings: SessionSettings | None = None) -> LoadedModel:
    """Open one exported model for layer ``name`` (model.onnx_session: this host's provider, CPU fallback);
    ModelError when it is unusable."""
    path, settings = Path(path), settings or SessionSettings()
    session, choice = open_session(graph_session(path, settings), f"model {name} ({path.name})", settings, ModelError,
                                   source=str(path))
    meta = dict(session.get_modelmeta().custom_metadata_map)
    alignment = _check_metadata(path, name, meta)
    return LoadedModel(name, path, _sha256(path), meta, session, alignment, choice)


class NetworkReconstructor:
    """The per-layer networks of a models folder; what model/reconstruct.py and the service call."""

    def __init__(self, models: dict[str, LoadedModel], tiles: TileSettings = TileSettings()) -> None:
        self.models = models
        self.tiles = tiles
        self._cache = threading.local()  # the last frame's feature planes, per thread (see _features)
        # One ONNX graph at a time per reconstructor: a frame's layers run concurrently (model.reconstruct's
        # CONCURRENT_METHODS) so that one layer's prior solve, which is single-threaded, overlaps the other's; the
        # graph already uses every core (OpenVINO's default threads), so two at once would only contend.
        self._graph_lock = threading.Lock()

    @classmethod
    def load(cls, models_dir: str | os.PathLike[str], settings: SessionSettings | None = None,
             tiles: TileSettings = TileSettings()) -> NetworkReconstructor | None:
        """Load every ``{direct,indirect,color}.onnx`` present; None when there is none. A ``fused`` blend model
        is refused (ModelError): model.reconstruct.load_fused opens those."""
        folder = Path(models_dir)
        models = {name: load_model(folder / f"{name}.onnx", name, settings)
                  for name in MODEL_LAYERS if (folder / f"{name}.onnx").is_file()}
        return cls(models, tiles) if models else None

    @property
    def layers(self) -> set[str]:
        """Layer names this reconstructor can serve."""
        return set(self.models)

    def describe(self) -> list[dict[str, Any]]:
        """One entry per loaded model (name, layer, input channels, sha256, metadata) for /v1/models."""
        return [m.describe() for m in self.models.values()]

    def warm_up(self, size: int = 64) -> float:
        """Run every model once on a small frame so the first request does not pay for allocation; seconds."""
        start = time.perf_counter()
        for model in self.models.values():
            a = model.alignment
            side = -(-size // a) * a
            model.run(np.zeros((len(DATA_INPUTS), side, side), np.float32),
                      np.zeros((len(GRADIENT_INPUTS), side, side), np.float32))
        return time.perf_counter() - start

    def reconstruct_layer(self, name: str, layer: Layer, features: Features | None) -> np.ndarray:
        """Reconstruct one illumination layer: (H, W, 3) float32, finite, ≥ 0.

        The model always runs on the layer scaled to the exposure it was trained at (its robust level at
        NETWORK_LEVEL, :func:`exposure_scale`) and its output is scaled back, so the method is the same for a
        frame at 1e-8 or 1e9 radiance and no frame-level decision depends on a single pixel.
        """
        if name not in self.models:
            raise KeyError(f"no model for layer {name!r}; loaded: {', '.join(sorted(self.models)) or 'none'}")
        _check_inputs(layer, features)
        exposure = exposure_scale(layer)
        if exposure != 1.0:
            return scaled_image(self._reconstruct(name, scaled_layer(layer, 1.0 / exposure), features), exposure)
        return self._reconstruct(name, layer, features)

    def _reconstruct(self, name: str, layer: Layer, features: Features | None) -> np.ndarray:
        """:meth:`reconstruct_layer` of a layer already at the model's exposure."""
        height, width = np.shape(layer.base)[:2]
        assert features is not None  # _check_inputs raised otherwise
        model = self.models[name]
        unlit = unlit_pixels(layer)
        plans = plan_tiles(height, width, self.tiles, model.alignment)
        overlap = aligned_size(self.tiles.overlap, model.alignment)
        depth_range = DepthRange.of(features.depth)  # per frame, shared by every window
        if len(plans) == 1:
            # one window: the measured planes are made once, and the prior is solved from them (no second
            # sanitised, transposed copy of the layer); bit-for-bit what layer_planes(layer, prior=...) gives
            planes = np.empty((LAYER_PLANES, height, width), np.float32)
            measured_planes(layer, out=planes[:MEASURED_PLANES])
            prior = poisson_prior(layer, planes=planes[:MEASURED_PLANES], alpha=model.prior_alpha)
            with_prior(planes, prior)
            result = self._run_planes(model, planes, self._features(features, depth_range))
        else:
            prior = poisson_prior(layer, alpha=model.prior_alpha)  # a global solve: once per layer, cropped per window
            total = np.zeros((height, width, 3), dtype=np.float32)
            weight = np.zeros((height, width, 1), dtype=np.float32)
            for plan in plans:
                y0, y1, x0, x1 = plan.window
                out = self._run_window(model, layer, features, depth_range, prior, plan.window)
                w = np.outer(_ramp(y0, y1, height, overlap), _ramp(x0, x1, width, overlap))
                total[y0:y1, x0:x1] += out * w[..., None]
                weight[y0:y1, x0:x1] += w[..., None]
            result = total / weight
        result[unlit] = 0.0             # no measured light: nothing to reconstruct
        return result

    def _features(self, features: Features, depth_range: DepthRange) -> np.ndarray:
        """The whole frame's feature planes, made once per frame: a frame's layers are reconstructed one after
        the other with the same Features object, so the second layer reuses the first one's (per thread, as
        concurrent requests share this reconstructor; only the last frame's are kept)."""
        cached = getattr(self._cache, "features", None)
        if cached is not None and cached[0]() is features and cached[1] == depth_range:
            return cached[2]
        planes = feature_planes(features, depth_range)
        planes.flags.writeable = False  # shared between layers: nobody may write into it
        self._cache.features = (weakref.ref(features), depth_range, planes)
        return planes

    def _graph(self, model: LoadedModel, data: np.ndarray, gradient: np.ndarray) -> np.ndarray:
        """``model.run`` under the graph lock (see __init__)."""
        with self._graph_lock:
            return model.run(data, gradient)

    def _run_planes(self, model: LoadedModel, planes: np.ndarray, features: np.ndarray) -> np.ndarray:
        """One window's (12, h, w) layer planes and (7, h, w) feature planes through the network → radiance."""
        h, w = planes.shape[1:]
        data, gradient = network_inputs_numpy(planes, features, model.alignment)
        encoded = self._graph(model, data, gradient)
        window_prior = planes[9:12].transpose(1, 2, 0)  # a failed output degrades to the Poisson prior
        return output_radiance(crop_to(encoded, h, w), fallback=window_prior)

    def _run_window(self, model: LoadedModel, layer: Layer, features: Features, depth_range: DepthRange,
                    prior: np.ndarray, window: Window) -> np.ndarray:
        planes = layer_planes(layer, window, prior)
        data, gradient = network_inputs(planes, feature_planes(features, depth_range, window))
        h, w = planes.shape[1:]
        a = model.alignment
        encoded = self._graph(model, np.ascontiguousarray(pad_to_alignment(data, a)),
                              np.ascontiguousarray(pad_to_alignment(gradient, a)))
        window_prior = planes[9:12].transpose(1, 2, 0)  # a failed output degrades to the Poisson prior
        return output_radiance(crop_to(encoded, h, w), fallback=window_prior)


#: The exposure a Poisson-prior model runs at: each layer is scaled so that its robust level (model.robust.
#: robust_level, a winsorised mean one pixel cannot move) is this value, and the output is scaled back. The shipped
#: models keep a layer's energy best around it (tests/model/test_stability.py, every decade 1e-8 .. 1e9).
NETWORK_LEVEL = 0.5


def exposure_scale(layer: Layer) -> float:
    """The factor to divide the layer by before inference (and multiply the output by): robust_level(base) /
    NETWORK_LEVEL; 1.0 for a black layer. Continuous in every pixel, so a firefly moves it by at most one order
    statistic's step over the pixel count."""
    level = robust_level(layer.base)
    if not (level > 0.0 and np.isfinite(level)):
        return 1.0
    return level / NETWORK_LEVEL


def _check_inputs(layer: Layer, features: Features | None) -> tuple[int, int]:
    """(H, W) of a consistent layer + features; ChannelError naming the channels otherwise."""
    from gradsep.model.errors import ChannelError
    from gradsep.model.frame import FEATURE_CHANNELS

    if features is None:
        raise ChannelError("the network needs the feature channels, which this frame lacks: "
                           + ", ".join(FEATURE_CHANNELS), list(FEATURE_CHANNELS))
    shape = np.shape(layer.base)
    if len(shape) != 3 or shape[2] != 3 or shape[0] < 1 or shape[1] < 1:
        raise ChannelError(f"layer base must be (H, W, 3) with H, W >= 1, got {shape}", ["R", "G", "B"])
    h, w = shape[:2]
    expected = {"dx": (layer.dx, (h, w, 3)), "dy": (layer.dy, (h, w, 3)),
                "albedo": (features.albedo, (h, w, 3)), "normal": (features.normal, (h, w, 3)),
                "depth": (features.depth, (h, w))}
    bad = [f"{k} {np.shape(a)} != {s}" for k, (a, s) in expected.items() if np.shape(a) != s]
    if bad:
        raise ChannelError("inconsistent channel shapes: " + "; ".join(bad), [b.split()[0] for b in bad])
    return int(h), int(w)

