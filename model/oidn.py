"""Intel Open Image Denoise as a reconstruction method and as the first candidate of the ``fused`` blend.

OIDN's ``RT`` filter is a pretrained, feature-guided denoiser: it sees one noisy HDR image plus (optionally) the
albedo and normal of the first visible surface. It is used per illumination layer: the direct and the indirect
layer are denoised apart, then summed, because each layer's noise is more uniform than the mix (docs/decisions.md
has the comparison with denoising the sum).

How OIDN is run is a :class:`Setting` (docs/oidn.md): the auxiliary images (``prefiltered``: albedo and normal
denoised once per frame by their own filters, OIDN's recipe for noisy features, then ``cleanAux``, which at
quality ``high`` selects OIDN's large model; ``raw``: the frame's own noisy features, OIDN's default mode, no
prefilter), the colour filter's quality preset and the exposure. :data:`SETTINGS` holds the settings something
runs: the ``oidn`` method's (:data:`METHOD_SETTING`, chosen by an error-against-time study to fit the service's
latency target: docs/decisions.md, "OIDN's setting for the oidn method"), the one a ``--seconds`` render may ask
for in its header, and the one the ``fused`` blend models were trained with (model/fused.py ``OIDN_SETTING``).
``$GRADSEP_OIDN_SETTING`` selects one of them for the ``oidn`` method. The auxiliary images are prepared once per
frame and reused for every layer.

Numerics: inputs are sanitised (NaN → 0, ±Inf → the largest finite float32 / 0, radiance clamped ≥ 0), and the
colour filter is given an explicit ``inputScale`` (the setting's *exposure*, :func:`exposure_scale`): by default
OIDN's own key, 0.18, over the layer's lit part (model.robust.lit_level: a winsorised mean over OIDN's
autoexposure bins that are not black), where OIDN's autoexposure takes a log-average that dark corners drag down
and one firefly moves. So a frame scaled by 1e-8 or 1e9 is denoised as the same frame at unit exposure (up to float
rounding), the result scales with the input, and no single pixel sets the exposure of the rest. A layer with no
light is returned black without running the filter. This module needs ``pyoidn`` (the ``evaluate`` and ``serve``
extras); importing it does not, so the service starts without it and reports the method as unavailable.
"""

from __future__ import annotations

import importlib.util
import math
import os
import sys
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from gradsep.model.frame import FLOAT32_MAX
from gradsep.model.header_keys import OIDN_SETTING_KEY
from gradsep.model.robust import lit_level, robust_level

if TYPE_CHECKING:
    from gradsep.model.frame import Features

#: The albedo/normal prefilter's quality preset (it scored as ``high`` does: docs/decisions.md).
AUX_QUALITY = "fast"
#: The exposure the colour filter sees (``Setting.exposure``): ``lit`` scales the layer so that the mean luminance of
#: its lit part (model.robust.lit_level) is OIDN's autoexposure key, 0.18; ``level`` (kept for the ``fused`` blend
#: models trained on it) scales it so that its robust level over the whole frame is 1 (docs/decisions.md, "OIDN's
#: exposure").
EXPOSURES: dict[str, float] = {"lit": 0.18, "level": 1.0}
DEFAULT_EXPOSURE = "lit"
#: OIDN's U-Net loses energy on images a few pixels across: smaller images are mirror-padded to this many pixels per
#: side and cropped back, and their colour output is rescaled per channel to the input's mean (padding alone still
#: moves a coloured 1×1 pixel: with no neighbours there is nothing to denoise it with, and the frame's energy is
#: what is kept).
MIN_SIDE = 16


def available() -> bool:
    """True when pyoidn can be imported (checked without importing it)."""
    return importlib.util.find_spec("pyoidn") is not None


@dataclass(frozen=True)
class Setting:
    """How OIDN is run: which auxiliary images the colour filter gets and at which quality preset.

    ``aux``: ``prefiltered`` (albedo and normal denoised once per frame by their own filters, then ``cleanAux``)
    or ``raw`` (the frame's noisy albedo and normal passed as they are: OIDN's default mode, no prefilter).
    ``quality``: the colour filter's preset (``high`` or ``fast``). OIDN's ``high`` preset with ``cleanAux`` runs its
    large model, several times the cost of the same call on raw features (docs/oidn.md).
    """

    aux: str
    quality: str
    aux_quality: str = AUX_QUALITY
    exposure: str = DEFAULT_EXPOSURE

    @property
    def name(self) -> str:
        suffix = "" if self.exposure == DEFAULT_EXPOSURE else f"-{self.exposure}"
        return f"{self.aux}-{self.quality}{suffix}"


#: The settings something runs, by name (``<aux>-<quality>``, ``-level`` for the ``level`` exposure): the ``oidn``
#: method's (and so the served default's and the evaluation's OIDN baselines'), the one a ``--seconds`` render may
#: ask for in its header (renderer.render.FARM_OIDN_SETTING), and the ``fused`` candidates' (model.fused.OIDN_SETTING).
SETTINGS: dict[str, Setting] = {s.name: s for s in (Setting("raw", "fast"), Setting("prefiltered", "high"),
                                                    Setting("raw", "fast", exposure="level"))}
#: The ``oidn`` method's setting: chosen by error against time on held-out frames (docs/oidn.md);
#: ``$GRADSEP_OIDN_SETTING`` selects another one of :data:`SETTINGS`.
METHOD_SETTING = "raw-fast"
SETTING_ENV = "GRADSEP_OIDN_SETTING"


def frame_setting(metadata: dict[str, str]) -> tuple[str, str | None]:
    """(the setting the ``oidn`` method runs for a frame with header ``metadata``, a warning or None):
    ``$GRADSEP_OIDN_SETTING`` when set (the operator's choice wins), else the setting the frame's render plan asked
    for (model.header_keys.OIDN_SETTING_KEY, renderer.render.reconstruction_setting) when it names one, else
    :data:`METHOD_SETTING`. A header naming no setting is ignored with a warning, never an error."""
    if os.environ.get(SETTING_ENV, "").strip():
        return method_setting(), None
    asked = str(metadata.get(OIDN_SETTING_KEY, "")).strip()
    if not asked or asked in SETTINGS:
        return asked or METHOD_SETTING, None
    return METHOD_SETTING, (f"the frame asks for OIDN setting {asked[:40]!r} ({OIDN_SETTING_KEY}), which is not one "
                            f"of {', '.join(SETTINGS)}; ran {METHOD_SETTING}")


def method_setting() -> str:
    """The ``oidn`` method's setting name: ``$GRADSEP_OIDN_SETTING`` when set, else :data:`METHOD_SETTING`."""
    name = os.environ.get(SETTING_ENV, "").strip() or METHOD_SETTING
    if name not in SETTINGS:
        raise ValueError(f"${SETTING_ENV}={name!r} is not an OIDN setting; use one of {', '.join(SETTINGS)}")
    return name


@dataclass(frozen=True)
class CleanAux:
    """The auxiliary features one frame's colour filters get, (H, W, 3) float32 each: prefiltered (``clean``,
    passed with ``cleanAux``) or the frame's own, sanitised (``clean`` False)."""

    albedo: np.ndarray  # in [0, 1]
    normal: np.ndarray  # in [-1, 1]
    clean: bool = True


def _finite(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    out = np.array(x, dtype=np.float32, order="C")
    np.nan_to_num(out, copy=False, nan=0.0, posinf=hi, neginf=lo)
    return np.clip(out, lo, hi, out=out)


def exposure_scale(image: np.ndarray, exposure: str = DEFAULT_EXPOSURE, lit: float | None = None) -> float:
    """The colour filter's ``inputScale`` for ``image`` under ``exposure`` (:data:`EXPOSURES`): the key over the
    layer's lit level (``lit``) or over its robust level (``level``, :func:`input_scale`); 1.0 if black. ``lit``:
    ``image``'s model.robust.lit_level when the caller measured it already."""
    if exposure == "level":
        return input_scale(image)
    level = lit_level(image) if lit is None else lit
    if not (math.isfinite(level) and level > 0.0):
        return 1.0
    return EXPOSURES[exposure] / level


def input_scale(image: np.ndarray) -> float:
    """s such that the robust level of ``image * s`` (model.robust.robust_level, a winsorised mean one pixel cannot
    move) is 1: exactly the reciprocal, so scaled frames denoise alike; 1.0 if black."""
    level = robust_level(image)
    if not (math.isfinite(level) and level > 0.0):
        return 1.0
    return EXPOSURES["level"] / level


_import_lock = threading.Lock()


def import_pyoidn() -> Any:
    """``import pyoidn`` without the PyTorch it would import for its optional tensor interface, which gradsep never
    uses (it passes numpy arrays): importing torch would spend seconds of a render budget (`gradsep render
    --seconds` reconstructs in its pilot) and of a service's start. Where torch is already imported, nothing
    changes; where it is not, pyoidn sees it as unavailable (its numpy interface is unaffected) and torch stays
    importable."""
    if "pyoidn" in sys.modules or "torch" in sys.modules:
        import pyoidn

        return pyoidn
    with _import_lock:
        sys.modules["torch"] = None  # type: ignore[assignment]  # makes `import torch` raise ImportError
        try:
            import pyoidn
        finally:
            if sys.modules.get("torch", 0) is None:
                del sys.modules["torch"]
    return pyoidn


class Denoiser:
    """One OIDN device and its three filters (albedo prefilter, normal prefilter, HDR colour), run as ``setting``.

    Thread-safe: calls are serialised by a lock (OIDN already uses every core for one image, so running two
    images at once would not be faster on the target's few cores). Create one per process and reuse it: the device
    and the filters' weights are set up once.
    """

    def __init__(self, setting: Setting | str = METHOD_SETTING) -> None:
        pyoidn = import_pyoidn()

        if isinstance(setting, str):
            if setting not in SETTINGS:
                raise ValueError(f"unknown OIDN setting {setting!r}; use one of {', '.join(SETTINGS)}")
            setting = SETTINGS[setting]
        self.setting = setting
        quality, aux_quality = setting.quality, setting.aux_quality

        self._oidn = pyoidn
        presets = {"high": pyoidn.OIDN_QUALITY_HIGH, "fast": pyoidn.OIDN_QUALITY_FAST}
        self._quality = {"color": presets[quality], "albedo": presets[aux_quality], "normal": presets[aux_quality]}
        self.quality, self.aux_quality = quality, aux_quality
        self._lock = threading.Lock()
        self._device = pyoidn.Device()
        self._device.commit()
        self._check("device creation")
        self._filters: dict[str, Any] = {}

    # ------------------------------------------------------------------------------------------- plumbing

    def _check(self, what: str) -> None:
        message = self._device.get_error()
        if message:
            raise RuntimeError(f"OIDN {what} failed: {message}")

    def _filter(self, purpose: str) -> Any:
        flt = self._filters.get(purpose)
        if flt is None:
            flt = self._oidn.Filter(self._device, self._oidn.OIDN_FILTER_TYPE_RT)
            self._check("filter creation")
            self._filters[purpose] = flt
        return flt

    def _run(self, purpose: str, images: dict[str, np.ndarray], output: np.ndarray,
             flags: dict[str, bool], scale: float | None = None) -> np.ndarray:
        """Bind ``images`` (+ output) to the purpose's filter, execute, and return ``output``."""
        height, width = output.shape[:2]
        if min(height, width) < MIN_SIDE:
            pads = ((0, max(0, MIN_SIDE - height)), (0, max(0, MIN_SIDE - width)), (0, 0))
            padded = {k: np.ascontiguousarray(np.pad(v, pads, mode="symmetric")) for k, v in images.items()}
            big = self._run(purpose, padded, np.empty_like(next(iter(padded.values()))), flags, scale)
            output[...] = big[:height, :width]
            return output
        fmt = self._oidn.OIDN_FORMAT_FLOAT3
        flt = self._filter(purpose)
        for name in ("color", "albedo", "normal"):
            if name not in images:
                flt.unset_image(name)
        for name, image in images.items():
            flt.set_image(name, image, fmt)
        flt.set_image("output", output, fmt)
        for name, value in flags.items():
            flt.set_bool(name, value)
        if scale is not None:
            flt.set_float("inputScale", scale)
        flt.set_quality(self._quality[purpose])
        flt.commit()
        self._check(f"{purpose} filter setup")
        flt.execute()
        self._check(f"{purpose} filter execution")
        return output

    # ----------------------------------------------------------------------------------------------- API

    def prefilter(self, features: Features) -> CleanAux | None:
        """The frame's auxiliary images for every layer's colour filter, computed once per frame: albedo and
        normal denoised (setting ``prefiltered``, OIDN's recipe for noisy auxiliary images) or sanitised only
        (``raw``)."""
        albedo = _finite(features.albedo, 0.0, 1.0)
        normal = _finite(features.normal, -1.0, 1.0)
        if self.setting.aux == "raw":
            return CleanAux(albedo, normal, clean=False)
        with self._lock:
            clean_albedo = self._run("albedo", {"albedo": albedo}, np.empty_like(albedo), {})
            clean_normal = self._run("normal", {"normal": normal}, np.empty_like(normal), {})
        np.clip(clean_albedo, 0.0, 1.0, out=clean_albedo)
        np.clip(clean_normal, -1.0, 1.0, out=clean_normal)
        return CleanAux(clean_albedo, clean_normal)

    def denoise(self, color: np.ndarray, aux: CleanAux | None = None, lit: float | None = None) -> np.ndarray:
        """(H, W, 3) float32 HDR radiance → denoised, finite, ≥ 0; ``aux`` from :meth:`prefilter` or None;
        ``lit``: model.robust.lit_level of ``color`` when the caller measured it (``color`` finite, ≥ 0)."""
        radiance = _finite(color, 0.0, FLOAT32_MAX)
        scale = exposure_scale(radiance, self.setting.exposure, lit)
        if scale == 1.0 and not radiance.any():
            return radiance  # no light: nothing to denoise (and OIDN is not asked to invent any)
        images = {"color": radiance}
        if aux is not None:
            if aux.albedo.shape != radiance.shape or aux.normal.shape != radiance.shape:
                raise ValueError(f"auxiliary features {aux.albedo.shape} do not match the image {radiance.shape}")
            images |= {"albedo": aux.albedo, "normal": aux.normal}
        with self._lock:
            out = self._run("color", images, np.empty_like(radiance),
                            {"hdr": True, "cleanAux": aux is not None and aux.clean}, scale=scale)
        np.nan_to_num(out, copy=False, nan=0.0, posinf=FLOAT32_MAX, neginf=0.0)
        np.clip(out, 0.0, FLOAT32_MAX, out=out)
        if min(radiance.shape[:2]) < MIN_SIDE:
            _match_channel_means(out, radiance)
        return out

    def describe(self) -> dict[str, Any]:
        """What runs the colour filter, for /v1/models and the logs: the setting."""
        return {"setting": self.setting.name}

    def close(self) -> None:
        with self._lock:
            for flt in self._filters.values():
                flt.release()
            self._filters.clear()
            self._device.release()


def _match_channel_means(out: np.ndarray, source: np.ndarray) -> None:
    """Rescale each colour channel of ``out`` in place so its mean equals ``source``'s (float64 statistics)."""
    for c in range(out.shape[-1]):
        want = float(np.mean(source[..., c], dtype=np.float64))
        got = float(np.mean(out[..., c], dtype=np.float64))
        if got > 0.0 and math.isfinite(want / got):
            out[..., c] = np.clip(out[..., c].astype(np.float64) * (want / got), 0.0, FLOAT32_MAX)
        else:
            out[..., c] = source[..., c]


_shared: dict[str, Denoiser] = {}
_shared_lock = threading.Lock()


def shared_denoiser(setting: str = METHOD_SETTING) -> Denoiser:
    """The process-wide :class:`Denoiser` of ``setting``, created on first use. The ``oidn`` method asks for
    :func:`method_setting` (``$GRADSEP_OIDN_SETTING`` honoured)."""
    with _shared_lock:
        if setting not in _shared:
            _shared[setting] = Denoiser(setting)
        return _shared[setting]
