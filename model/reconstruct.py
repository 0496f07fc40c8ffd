"""The one reconstruction entry point that the CLI, the service and the evaluation all call.

A frame carries one or more illumination layers (``direct``/``indirect``, or ``color`` for a frame rendered
without separation). Each layer present is reconstructed on its own -- by the screened Poisson solvers
(``l1``, ``l2``) or by the network -- and the final image is their sum. Nothing runs for an absent layer.

Output policy: every reconstructed layer is made finite (NaN/±Inf → 0, with a warning: a solver or network
that produced them has a bug, and a black pixel is easier to spot than a poisoned downstream average) and
clamped to [0, float32 max] (radiance is non-negative; the Poisson solutions ring slightly below 0 at sharp
edges). The image is the sum of these clamped layers, so ``image == Σ layers`` holds exactly for what is
written and the image is finite and ≥ 0 as well.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from model.frame import Features, Frame, Layer, read_frame, rgb_channels, write_exr
from model.poisson import DEFAULT_ALPHA, solve_l1, solve_l2

__all__ = [
    "METHODS",
    "NetworkLike",
    "Reconstruction",
    "choose_method",
    "load_network",
    "models_dir_from",
    "reconstruct",
    "reconstruct_command",
]

METHODS: tuple[str, ...] = ("network", "l1", "l2")
_F32_MAX = float(np.finfo(np.float32).max)


class NetworkLike(Protocol):
    """What ``reconstruct`` needs of a network (``model.infer.NetworkReconstructor`` provides it)."""

    def reconstruct_layer(self, name: str, layer: Layer, features: Features) -> np.ndarray: ...


@dataclass
class Reconstruction:
    """The result of :func:`reconstruct`."""

    image: np.ndarray  # (H, W, 3) float32: the sum over layers; finite and >= 0
    layers: dict[str, np.ndarray]  # each reconstructed layer, (H, W, 3) float32, finite and >= 0
    timings: dict[str, float]  # seconds per layer name
    method: str
    warnings: list[str] = field(default_factory=list)  # non-finite values the output policy replaced


def _sanitise(name: str, image: np.ndarray, shape: tuple[int, int, int], warnings: list[str]) -> np.ndarray:
    """Apply the output policy (finite, ≥ 0) to one reconstructed layer and check its shape."""
    out = np.asarray(image, dtype=np.float32)
    if out.shape != shape:
        raise RuntimeError(f"reconstruction of layer {name} has shape {out.shape}, expected {shape}")
    bad = int(np.count_nonzero(~np.isfinite(out)))
    if bad:
        warnings.append(f"reconstruction of {name} produced {bad} non-finite value(s), replaced with 0")
        out = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(out, 0.0, _F32_MAX)


def _reconstruct_layer(name: str, layer: Layer, method: str, alpha: float, network: Any,
                       features: Features | None) -> np.ndarray:
    if method == "l1":
        return solve_l1(layer.base, layer.dx, layer.dy, alpha)[0]
    if method == "l2":
        return solve_l2(layer.base, layer.dx, layer.dy, alpha)
    return network.reconstruct_layer(name, layer, features)


def choose_method(frame: Frame, network: NetworkLike | None) -> str:
    """The default method for this frame: the network when it can serve every layer present (a model for each
    and the feature channels), else L1 -- so a frame the loaded models do not cover still gets an answer."""
    if network is not None and frame.features is not None:
        if set(frame.layers) <= set(getattr(network, "layers", frame.layers)):
            return "network"
    return "l1"


def reconstruct(frame: Frame, method: str | None = None, alpha: float = DEFAULT_ALPHA,
                network: NetworkLike | None = None) -> Reconstruction:
    """Reconstruct every illumination layer of ``frame`` with ``method`` and sum them.

    ``method`` None picks :func:`choose_method` (the network when it serves the frame, else L1).
    ``alpha`` is the screened Poisson data weight (l1/l2 only). ``network`` is required for ``"network"``,
    which also needs the frame's feature channels. Raises ValueError for an unknown method, a bad alpha or a
    missing network, and :class:`model.frame.ChannelError` for a network run on a frame without features.
    """
    method = method or choose_method(frame, network)
    if method not in METHODS:
        raise ValueError(f"unknown reconstruction method {method!r}; expected one of {', '.join(METHODS)}")
    if method in ("l1", "l2") and not (math.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha must be a finite number > 0, got {alpha}")
    if method == "network":
        if network is None:
            raise ValueError("method 'network' needs a loaded network (no models available); use l1 or l2")
        if frame.features is None:
            from model.frame import FEATURE_CHANNELS, ChannelError

            raise ChannelError("the network method needs the feature channels, which this frame lacks: "
                               + ", ".join(FEATURE_CHANNELS), list(FEATURE_CHANNELS))
        served = set(getattr(network, "layers", frame.layers))
        unserved = [name for name in frame.layers if name not in served]
        if unserved:
            from model.frame import ChannelError

            raise ChannelError(f"no network model for layer(s) {', '.join(unserved)} (models loaded for: "
                               f"{', '.join(sorted(served)) or 'none'}); use method l1 or l2",
                               {"unserved_layers": unserved, "model_layers": sorted(served)})
    shape = (frame.height, frame.width, 3)
    layers: dict[str, np.ndarray] = {}
    timings: dict[str, float] = {}
    warnings: list[str] = []
    total = np.zeros(shape, dtype=np.float64)
    for name, layer in frame.layers.items():
        start = time.perf_counter()
        image = _reconstruct_layer(name, layer, method, alpha, network, frame.features)
        timings[name] = time.perf_counter() - start
        layers[name] = _sanitise(name, image, shape, warnings)
        total += layers[name]
    image = np.clip(total, 0.0, _F32_MAX).astype(np.float32)
    return Reconstruction(image, layers, timings, method, warnings)


# ------------------------------------------------------------------------------------------------ models


def models_dir_from(value: str | os.PathLike[str] | None) -> Path:
    """The models folder: the explicit value, else $GRADSEP_MODELS, else ``models`` (relative to cwd)."""
    return Path(value or os.environ.get("GRADSEP_MODELS") or "models")


def load_network(models_dir: str | os.PathLike[str] | None) -> Any:
    """The network reconstructor from ``model.infer``, or None when there are no models or no inference module.

    Same contract as the service's loader: ``NetworkReconstructor.load(folder)`` returns None for a folder
    without models and raises for models that fail to load.
    """
    folder = models_dir_from(models_dir)
    if not folder.is_dir() or importlib.util.find_spec("model.infer") is None:
        return None
    from model.infer import NetworkReconstructor  # type: ignore[import-not-found]

    return NetworkReconstructor.load(folder)


# ----------------------------------------------------------------------------------------------- command


def _check_output(path: Path) -> None:
    """Fail before the (possibly long) solve when the output cannot be written at all."""
    from gradsep.cli import CommandError

    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise CommandError(f"output {str(path)!r} is a directory")
    if not folder.is_dir():
        raise CommandError(f"output folder {str(folder)!r} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CommandError(f"output folder {str(folder)!r} is not writable")


def _resolve_network(args: argparse.Namespace, method: str | None) -> Any:
    """The network for ``--method network`` (required) or for the default (optional); None for l1/l2."""
    from gradsep.cli import CommandError

    if method not in (None, "network"):
        return None
    folder = models_dir_from(getattr(args, "models", None))
    network = load_network(folder)
    if network is None and method == "network":
        raise CommandError(f"--method network needs exported models, but none were found in {str(folder)!r} "
                           "(set --models or $GRADSEP_MODELS, or use --method l1)")
    return network


def reconstruct_command(args: argparse.Namespace) -> int:
    """``gradsep reconstruct FRAME -o OUT``: read, reconstruct every layer, write ``R G B`` (+ layers) atomically.

    Bad input raises FrameError/CommandError (the dispatcher prints one line and exits 2) before anything is
    written; the output appears only complete (temporary file + rename).
    """
    from gradsep.cli import CommandError

    output = Path(args.output)
    alpha = float(args.alpha)
    if not (math.isfinite(alpha) and alpha > 0):
        raise CommandError(f"--alpha must be a finite number > 0, got {args.alpha}")
    _check_output(output)
    frame = read_frame(args.frame, nonfinite=args.nonfinite)
    network = _resolve_network(args, args.method)
    result = reconstruct(frame, args.method, alpha, network=network)
    method = result.method

    channels = dict(rgb_channels("", result.image))
    if args.layers:
        for name, image in result.layers.items():
            channels.update(rgb_channels(name, image))
    metadata = {"gradsep.method": method, "gradsep.layers": ",".join(result.layers),
                "gradsep.source": Path(args.frame).name}
    if method in ("l1", "l2"):
        metadata["gradsep.alpha"] = f"{alpha:g}"
    warnings = [*frame.warnings, *result.warnings]
    if warnings:
        metadata["gradsep.warnings"] = "; ".join(warnings)[:2000]
    try:
        write_exr(output, channels, half=bool(args.half), metadata=metadata)
    except OSError as exc:
        raise CommandError(f"cannot write {str(output)!r}: {exc.strerror or exc}") from exc

    for warning in warnings:
        print(f"gradsep reconstruct: warning: {warning}", file=sys.stderr)
    per_layer = ", ".join(f"{name} {seconds:.2f} s" for name, seconds in result.timings.items())
    print(f"reconstructed {frame.width}x{frame.height} with {method}: {per_layer}; "
          f"total {sum(result.timings.values()):.2f} s -> {output}")
    return 0
