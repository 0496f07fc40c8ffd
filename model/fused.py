"""The ``fused`` method: a per-pixel learned blend of gradient-domain and denoised candidates.

The paper's dual-branch CBAM network (model/blend_net.py: the same encoders, bottleneck, decoder and attention
as model/network.py) sees K *candidate* reconstructions of a layer side by side and predicts, per pixel, softmax
weights over them; the output is the convex blend ``Σ_k w_k · candidate_k``. The candidates (``CANDIDATES``):

* ``oidn``        -- OIDN's denoise of the base with the frame's albedo/normal (``OIDN_SETTING``: raw features,
  quality fast, the ``level`` exposure the blend models were trained on), computed once per layer; the other
  kind starts from it;
* ``refine-fast`` -- that image refined by the layer's gradients: the L1 screened Poisson solve with OIDN's image
  as the data term (model/refine.py explains it), solved cheaply (3 IRLS passes of 1 multigrid V-cycle): too
  rough alone, but a candidate the network can weigh.

The direct layer's served image is no blend candidate but the ``refine-direct`` kind (FIXED_KINDS, below): the
``oidn-l1`` method's refinement with its trust rule, at fused's CG budget, its settings read from model/refine.py
at call time.

Per layer (chosen on held-out seeds): the indirect layer is the learned blend
of {oidn, refine-fast} (models/fused/indirect.onnx); the direct layer, where no learned blend beat it, is the
``oidn-l1`` method's refinement alone at a cheaper CG budget (``FIXED_LAYERS``, ``DIRECT_CG``), so the blend network
runs once per frame. Where that direct layer is clean as a whole (the trust rule's frame weight), it is averaged with
a second, independent gradient-domain estimate, the ``network`` method's image (the paper's network on its
truncated-L1 prior), wherever the two agree (``CLEAN_AVERAGE``); a noisy layer runs no network there.

A convex blend cannot leave the hull of its candidates: it never invents energy, never rings below 0 (every
candidate is >= 0), and an untrained model (zero head) returns their plain average. The weights are computed
from the layer at a normalised exposure (base, gradients and candidates multiplied by s with the robust level of
s·OIDN at FUSED_MEAN, model.preprocess.prior_exposure), and the blend is taken of the frame's own candidates, so the
method is the same for a frame at 1e-8 or 1e9 radiance and HDR values are never clipped.

This module is numpy + ONNX Runtime only (inference); the same ``layer_candidates``/``blend_inputs`` build the
training cache (training/fused.py), so training and inference see identical numbers.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.model.frame import FLOAT32_MAX, Features, Layer
from gradsep.model.infer import BLEND_PRIOR
from gradsep.model.onnx_session import ProviderChoice
from gradsep.model.preprocess import (
    RADIANCE_MAX,
    TRANSFER,
    DepthRange,
    aligned_size,
    feature_planes,
    prior_exposure,
    scaled_image,
    scaled_layer,
)

#: The candidate kinds a blend model may use (its metadata ``gradsep.candidates`` names its own, in order).
CANDIDATES: tuple[str, ...] = ("oidn", "refine-fast")
#: The refinement solve of the ``refine-fast`` candidate: (IRLS passes, CG steps per pass), multigrid-preconditioned
#: (model.poisson.solve_l1), α = REFINE_ALPHA. Pinned here, not read from model/refine.py, because a model is
#: trained on the numbers one solve gives (3 passes of 1 V-cycle).
REFINE_SOLVES: dict[str, tuple[int, int]] = {"refine-fast": (3, 1)}
REFINE_PRECONDITIONER = "mg"
REFINE_ALPHA = 1.0
#: The OIDN setting every candidate starts from (model.oidn.SETTINGS): raw features, quality fast, and the ``level``
#: exposure the shipped blend models were trained on (the ``oidn`` method has since moved to the ``lit`` exposure).
OIDN_SETTING = "raw-fast-level"
#: Blend models written before OIDN's settings named their exposure record this setting as ``raw-fast``.
LEGACY_SETTING_NAMES = {"raw-fast": "raw-fast-level"}
#: The kind a layer served without a network may use besides CANDIDATES: ``refine-direct``, the ``oidn-l1``
#: method's refinement (model.refine.refine_layer: its data weight, preconditioner and passes, read at call time) at
#: fused's own CG budget, DIRECT_CG. No model consumes it, so unlike the candidates it need not be pinned to a
#: training run.
FIXED_KINDS: tuple[str, ...] = ("refine-direct",)
#: The CG budget of ``refine-direct``: each IRLS pass stops at a relative residual of 0.1 or after 4 V-cycle-
#: preconditioned steps (the same as model.refine.REFINE_CG_TOLERANCE / REFINE_MAX_CG_STEPS today, kept apart so
#: either can be re-budgeted alone). Looser budgets lost frames on held-out renders.
DIRECT_CG: tuple[float, int] = (0.1, 4)
#: Layers the method serves with one candidate alone, no network, unless the models folder has a model for them.
#: The direct layer is OIDN refined by its gradients (the oidn-l1 method's refinement at DIRECT_CG): on held-out
#: frames every learned blend for it was worse than that candidate alone, while the indirect layer's blend of
#: oidn + refine-fast beats any fixed weighting of the two. So the network runs where it pays, and once per frame.
FIXED_LAYERS: dict[str, str] = {"direct": "refine-direct"}
#: The clean-layer average: on a direct layer the trust rule
#: calls clean as a whole (model.refine.clean_weight w_f > 0), the served refinement is averaged with a second,
#: independent gradient-domain estimate, the ``network`` method's image (the paper's network on its truncated-L1
#: prior, models/direct.onnx), wherever the two agree: out = refined + CLEAN_AVERAGE_WEIGHT·w_f·g(ρ)·(net −
#: refined), ρ per pixel = mean_rgb (a − b)² / (mean_rgb ((a + b)/2)² + CLEAN_AVERAGE_EPSILON) of the two at the
#: refinement's normalised exposure, g = 1 at ρ ≤ CLEAN_AVERAGE[0], 0 at ρ ≥ CLEAN_AVERAGE[1], log-linear between.
#: Two estimates with partly independent errors average to a lower one where both are right; where they disagree
#: by more than noise one of them is biased and the refinement stays. Chosen on held-out procedural frames, never on
#: the evaluation's scenes. A noisy layer (w_f = 0) runs no network: its image is the refinement alone, bit for bit.
CLEAN_AVERAGE: tuple[float, float] = (0.01, 0.1)
CLEAN_AVERAGE_WEIGHT = 0.5
CLEAN_AVERAGE_EPSILON = 0.01
#: The network model the clean-layer average reads, beside the fused folder (the ``network`` method's own file).
CLEAN_AVERAGE_MODEL = Path("..") / "direct.onnx"
#: "2": the refine candidates are the multigrid solves above (format "1" models were trained on a DCT solve).
BLEND_FORMAT = "2"
INPUT_NAMES = ("data", "gradient")
OUTPUT_NAME = "weights"

log = logging.getLogger("gradsep.fused")


class BlendModelError(ValueError):
    """A fused model file cannot be used (wrong prior kind, candidates, layer...); the message says why."""


def data_channels(k: int) -> int:
    """Channels of the data input for K candidates: C(base), C(candidate_1..K), albedo, normal, depth."""
    return 3 + 3 * k + 7


def refine(kind: str, oidn: np.ndarray, scaled: Layer) -> np.ndarray:
    """OIDN's image refined by the layer's gradients with the ``kind`` solve of REFINE_SOLVES: the oidn-l1
    refinement (model.refine.refine_layer: the L1 screened Poisson problem with OIDN's image as the data term,
    solved at robust level 1) with every setting of the solve pinned here. (H, W, 3) float32, finite."""
    from gradsep.model.refine import RefineSolve, refine_layer

    passes, cg_steps = REFINE_SOLVES[kind]
    # "direct": refine this layer whatever its name
    return refine_layer("direct", oidn, scaled, REFINE_ALPHA,
                        solve=RefineSolve(REFINE_PRECONDITIONER, cg_steps=cg_steps, passes=passes))


def refine_direct(oidn: np.ndarray, scaled: Layer, report: dict[str, float] | None = None) -> np.ndarray:
    """The ``refine-direct`` image: OIDN's image refined by the layer's gradients as the oidn-l1 method refines it,
    at fused's CG budget DIRECT_CG. ``report``: see model.refine.refine_layer (the trust rule's w_f)."""
    from gradsep.model.refine import RefineSolve, refine_layer

    tolerance, steps = DIRECT_CG
    return refine_layer("direct", oidn, scaled, solve=RefineSolve(cg_steps=steps, cg_tolerance=tolerance),
                        report=report)


def layer_candidates(layer: Layer, aux: Any, kinds: tuple[str, ...] = CANDIDATES,
                     denoiser: Any = None, denoised: np.ndarray | None = None,
                     report: dict[str, float] | None = None) -> tuple[Layer, list[np.ndarray], float]:
    """(the layer at the normalised exposure, its candidates at that exposure (each (H, W, 3) float32, finite,
    in [0, RADIANCE_MAX]), the scale s). ``aux``: the frame's OIDN features for ``OIDN_SETTING``
    (``denoiser.prefilter(features)``), or None without features. OIDN runs once per layer; every kind is
    computed from that one image. ``denoised``: the layer's OIDN_SETTING image when the caller already has it
    (a pipeline that denoises the next layer while this one is refined), so OIDN is not run twice. ``report``:
    filled by a FIXED_KINDS refinement with the trust rule's w_f (model.refine.refine_layer's ``report``)."""
    from gradsep.model.oidn import shared_denoiser

    unknown = [k for k in kinds if k not in CANDIDATES and k not in FIXED_KINDS]
    if unknown:
        raise BlendModelError(f"unknown candidate kind(s) {unknown}; expected some of {', '.join(CANDIDATES)}")
    if denoised is None:
        den = denoiser or shared_denoiser(OIDN_SETTING)
        denoised = den.denoise(layer.base, aux)  # scale-invariant: OIDN's input is normalised to robust level 1
    scale = prior_exposure(denoised)
    scaled = scaled_layer(layer, scale)
    oidn = scaled_image(denoised, scale)
    out: list[np.ndarray] = []
    for kind in kinds:
        if kind == "oidn":
            image = oidn
        elif kind in REFINE_SOLVES:
            image = refine(kind, oidn, scaled)
        else:
            image = refine_direct(oidn, scaled, report)
        out.append(np.clip(np.nan_to_num(image, nan=0.0, posinf=RADIANCE_MAX, neginf=0.0), 0.0,
                           RADIANCE_MAX).astype(np.float32))
    return scaled, out, scale


def _chw(image: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip(np.nan_to_num(np.asarray(image, np.float32), nan=0.0, posinf=hi, neginf=lo), lo,
                   hi).transpose(2, 0, 1)


def blend_inputs(scaled: Layer, candidates: list[np.ndarray], features: Features) -> tuple[np.ndarray, np.ndarray]:
    """(data (3+3K+7, H, W), gradient (6, H, W)) float32 network inputs, from the normalised layer and candidates.

    Radiance planes go through the log transfer C (model.preprocess.TRANSFER), gradients through sign·C, the
    features as the ``network`` method normalises them (albedo, normal·0.5+0.5, depth per frame)."""
    radiance = [TRANSFER.forward(_chw(scaled.base, 0.0, RADIANCE_MAX))]
    radiance += [TRANSFER.forward(_chw(c, 0.0, RADIANCE_MAX)) for c in candidates]
    feats = feature_planes(features, DepthRange.of(features.depth))
    data = np.concatenate([*radiance, feats]).astype(np.float32)
    gradient = np.concatenate([TRANSFER.forward_signed(_chw(scaled.dx, -RADIANCE_MAX, RADIANCE_MAX)),
                               TRANSFER.forward_signed(_chw(scaled.dy, -RADIANCE_MAX, RADIANCE_MAX))])
    return data, gradient.astype(np.float32)


def blend(weights: np.ndarray, candidates: list[np.ndarray], scale: float) -> np.ndarray:
    """Σ_k w_k · candidate_k / s, float64 accumulation, as (H, W, 3) float32 finite and >= 0.

    ``weights`` (K, H, W); non-finite or negative weights (a broken model) fall back to the first candidate's
    (OIDN's) image: the method degrades to ``oidn``, never to holes."""
    w = np.asarray(weights, np.float64)
    bad = ~np.all(np.isfinite(w) & (w >= 0), axis=0)
    total = np.zeros(candidates[0].shape, np.float64)
    for k, image in enumerate(candidates):
        total += np.where(bad, 1.0 if k == 0 else 0.0, w[k])[..., None] * image
    out = total / scale
    return np.clip(np.nan_to_num(out, nan=0.0, posinf=FLOAT32_MAX, neginf=0.0), 0.0, FLOAT32_MAX).astype(np.float32)


def disagreement(refined: np.ndarray, second: np.ndarray, scale: float) -> np.ndarray:
    """CLEAN_AVERAGE's ρ per pixel, (H, W) float64: the two images' relative squared difference at exposure
    ``scale``, mean_rgb (a − b)² / (mean_rgb ((a + b)/2)² + CLEAN_AVERAGE_EPSILON). Finite inputs. The ε (at the
    level-1 exposure, as RelMSE's) keeps ρ finite where both are black (ρ = 0: they agree) and lets two dark pixels
    count as agreeing unless they differ by more than it."""
    a = np.asarray(refined, np.float64) * scale
    b = np.asarray(second, np.float64) * scale
    return np.mean(np.square(a - b), axis=-1) / (np.mean(np.square(0.5 * (a + b)), axis=-1) + CLEAN_AVERAGE_EPSILON)


def agreement_weights(refined: np.ndarray, second: np.ndarray, scale: float,
                      thresholds: tuple[float, float]) -> np.ndarray:
    """g(ρ) of CLEAN_AVERAGE, (H, W) float32 in [0, 1]: 1 where the two images agree to within ``thresholds[0]``
    of their :func:`disagreement` ρ (at exposure ``scale``), 0 from ``thresholds[1]`` on, log-linear between."""
    rho = disagreement(refined, second, scale)
    low, high = thresholds
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        g = np.log(high / np.maximum(rho, 1e-300)) / np.log(high / low)
    return np.clip(np.nan_to_num(g, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0).astype(np.float32)


def clean_average(refined: np.ndarray, second: np.ndarray, clean: float, scale: float) -> np.ndarray:
    """CLEAN_AVERAGE's image at the frame's exposure: ``refined`` + CLEAN_AVERAGE_WEIGHT·``clean``·g(ρ)·(``second``
    − ``refined``), (H, W, 3) float32, finite, ≥ 0 (a convex mix of two non-negative images, weights ≤ 1/2).
    ``clean``: the layer's w_f; ``scale``: the refinement's level-1 exposure (model.oidn.input_scale of OIDN's
    image). ``refined`` itself where w_f is 0 or ``second`` is not finite."""
    if not clean > 0.0 or not np.all(np.isfinite(second)):
        return refined
    w = np.float32(CLEAN_AVERAGE_WEIGHT * min(clean, 1.0)) * agreement_weights(refined, second, scale, CLEAN_AVERAGE)
    out = refined + w[..., None] * (np.asarray(second, np.float32) - refined)
    return np.clip(np.nan_to_num(out, nan=0.0, posinf=FLOAT32_MAX, neginf=0.0), 0.0, FLOAT32_MAX).astype(np.float32)


def _pad(x: np.ndarray, alignment: int) -> np.ndarray:
    h, w = x.shape[-2:]
    ph, pw = aligned_size(h, alignment) - h, aligned_size(w, alignment) - w
    if not (ph or pw):
        return x
    mode = "reflect" if min(h, w) > 1 else "edge"
    return np.pad(x, [(0, 0), (0, ph), (0, pw)], mode=mode)


@dataclass
class BlendModel:
    """One exported blend model (a layer's)."""

    name: str
    path: Path
    metadata: dict[str, str]
    session: Any
    candidates: tuple[str, ...]
    alignment: int
    choice: ProviderChoice  # which execution provider serves it, in which precision (model.onnx_session)

    def weights(self, data: np.ndarray, gradient: np.ndarray) -> np.ndarray:
        """(C, H, W) inputs of any size → (K, H, W) weights (padded to the alignment and cropped back)."""
        h, w = data.shape[-2:]
        out = self.session.run([OUTPUT_NAME], {"data": _pad(data, self.alignment)[None],
                                               "gradient": _pad(gradient, self.alignment)[None]})[0]
        return out[0, :, :h, :w]


def _check(path: Path, name: str, meta: dict[str, str]) -> tuple[tuple[str, ...], int]:
    prior = meta.get("gradsep.prior", "l1")
    if prior != BLEND_PRIOR:
        raise BlendModelError(f"{path}: a model of prior kind {prior!r}, not a fused blend model "
                              f"({BLEND_PRIOR!r}); re-export it into the folder of its own method")
    if meta.get("gradsep.layer") != name:
        raise BlendModelError(f"{path}: made for layer {meta.get('gradsep.layer')!r}, not {name!r}")
    try:
        kinds = tuple(json.loads(meta.get("gradsep.candidates", "")))
        alignment = int(meta.get("gradsep.alignment", ""))
    except (ValueError, TypeError) as exc:
        raise BlendModelError(f"{path}: unreadable gradsep.candidates / gradsep.alignment ({exc})") from exc
    if not kinds or any(k not in CANDIDATES for k in kinds):
        raise BlendModelError(f"{path}: candidates {kinds} are not a subset of {CANDIDATES}")
    if meta.get("gradsep.format") != BLEND_FORMAT:
        raise BlendModelError(f"{path}: blend model format {meta.get('gradsep.format')!r}, this code reads "
                              f"{BLEND_FORMAT!r} (its candidates are computed differently); retrain it "
                              "(make fused-models)")
    recorded = meta.get("gradsep.oidn_setting")
    if LEGACY_SETTING_NAMES.get(recorded, recorded) != OIDN_SETTING:
        raise BlendModelError(f"{path}: trained on OIDN setting {meta.get('gradsep.oidn_setting')!r}, this code "
                              f"computes {OIDN_SETTING!r}")
    return kinds, alignment


def load_model(path: str | os.PathLike[str], name: str) -> BlendModel:
    """Open one blend model on the provider the ``network`` method's models use (model.onnx_session.choose_provider:
    OpenVINO in bf16 where the CPU has native bf16, else ORT's CPU provider in fp32; ``GRADSEP_ONNX_PROVIDER``
    overrides), falling back to the CPU provider should the accelerated one fail; BlendModelError when unusable.
    The weights only choose among candidates (the blend itself is float64 numpy), so bf16 moves them little."""
    from gradsep.model.onnx_session import SessionSettings, graph_session, open_session

    path = Path(path)
    settings = SessionSettings()
    session, choice = open_session(graph_session(path, settings), f"fused model {name} ({path.name})", settings,
                                   BlendModelError, source=str(path))
    meta = dict(session.get_modelmeta().custom_metadata_map)
    kinds, alignment = _check(path, name, meta)
    return BlendModel(name, path, meta, session, kinds, alignment, choice)


def _load_second(path: Path, layers: set[str]) -> Any:
    """The clean-layer average's network (a model.infer.NetworkReconstructor of ``path``, a ``network`` model for
    the direct layer) when the file exists and a fixed layer it serves is among ``layers``;
    else None. An unusable file raises BlendModelError naming it."""
    if "direct" not in layers or not path.is_file():
        return None
    from gradsep.model.infer import ModelError, NetworkReconstructor
    from gradsep.model.infer import load_model as load_network_model

    try:
        return NetworkReconstructor({"direct": load_network_model(path.resolve(), "direct")})
    except ModelError as exc:
        raise BlendModelError(f"the clean-layer average's network model: {exc}") from exc


class FusedReconstructor:
    """The ``fused`` method's per-layer blend models (models/fused/{direct,indirect,color}.onnx), the layers served
    by one candidate (FIXED_LAYERS), and the ``network`` model (models/direct.onnx) their clean-layer average reads
    (CLEAN_AVERAGE; absent: those layers are their candidate alone)."""

    oidn_setting = OIDN_SETTING

    def __init__(self, models: dict[str, BlendModel], fixed: dict[str, str] | None = None,
                 second: Any = None) -> None:
        self.models = models
        #: layers served by one candidate alone (FIXED_LAYERS), where the folder has no model for them
        self.fixed = {n: k for n, k in (fixed or {}).items() if n not in models}
        #: the clean-layer average's second estimate (CLEAN_AVERAGE): a model.infer.NetworkReconstructor whose
        #: models serve some of the fixed layers, or None (those layers are then their candidate alone)
        self.second = second

    @classmethod
    def load(cls, folder: str | os.PathLike[str]) -> FusedReconstructor | None:
        """The models of ``folder`` plus FIXED_LAYERS, and the ``network`` method's direct model beside the folder
        (CLEAN_AVERAGE_MODEL) for the clean-layer average when it is there; None when the folder holds no blend
        model at all. A network model there that cannot be served is a BlendModelError, not a silent fallback."""
        folder = Path(folder)
        models = {n: load_model(folder / f"{n}.onnx", n) for n in ("direct", "indirect", "color")
                  if (folder / f"{n}.onnx").is_file()}
        if not models:
            return None
        return cls(models, FIXED_LAYERS, _load_second(folder / CLEAN_AVERAGE_MODEL, set(FIXED_LAYERS) - set(models)))

    def _averages(self, name: str) -> bool:
        """Whether the fixed layer ``name`` gets the clean-layer average."""
        return self.second is not None and name in self.second.models

    @property
    def layers(self) -> set[str]:
        return set(self.models) | set(self.fixed)

    def describe(self) -> list[dict[str, Any]]:
        """One entry per model, with the keys of model.infer.LoadedModel.describe (the service's /v1/models)."""
        import hashlib

        return [{"name": m.name, "layer": m.name, "file": m.path.name,
                 "inputs": {"data": data_channels(len(m.candidates)), "gradient": 6,
                            "candidates": list(m.candidates)},
                 "sha256": hashlib.sha256(m.path.read_bytes()).hexdigest(), "bytes": m.path.stat().st_size,
                 "attention": m.metadata.get("gradsep.attention") == "true", "prior": BLEND_PRIOR,
                 "alignment": m.alignment, **m.choice.describe(),
                 "metadata": dict(m.metadata)} for m in self.models.values()] + [
                {**m.describe(), "role": "clean-layer average (model/fused.py CLEAN_AVERAGE)"}
                for m in (self.second.models.values() if self.second is not None else ())]

    def warm_up(self, size: int = 64) -> float:
        import time

        start = time.perf_counter()
        for m in self.models.values():
            k = len(m.candidates)
            m.weights(np.zeros((data_channels(k), size, size), np.float32), np.zeros((6, size, size), np.float32))
        if self.second is not None:
            self.second.warm_up(size)
        return time.perf_counter() - start

    def reconstruct_layer(self, name: str, layer: Layer, features: Features | None, aux: Any = None,
                          denoised: np.ndarray | None = None) -> np.ndarray:
        """(H, W, 3) float32 >= 0: the blend of the layer's candidates with the model's per-pixel weights.
        ``denoised``: the layer's OIDN image (OIDN_SETTING) if the caller computed it already."""
        if features is None:
            raise BlendModelError("the fused method needs the frame's feature channels")
        if aux is None:
            from gradsep.model.oidn import shared_denoiser

            aux = shared_denoiser(OIDN_SETTING).prefilter(features)
        if name in self.fixed:  # no blend model for this layer: its one candidate, back at the frame's exposure
            average = self._averages(name) and layer.has_gradients
            if average and denoised is None:  # the average's exposure reads OIDN's image: denoise once, here
                from gradsep.model.oidn import shared_denoiser

                denoised = shared_denoiser(OIDN_SETTING).denoise(layer.base, aux)
            report: dict[str, float] = {}
            _, (image,), scale = layer_candidates(layer, aux, (self.fixed[name],), denoised=denoised, report=report)
            out = blend(np.ones((1, *image.shape[:2]), np.float32), [image], scale)
            if average:  # a clean layer: averaged with the network's image where the two agree (CLEAN_AVERAGE)
                from gradsep.model.oidn import input_scale

                clean = report.get("clean_weight", 0.0)  # the refinement's own w_f (model.refine.clean_weight's)
                if clean > 0.0:  # a noisy layer runs no network
                    second = self.second.reconstruct_layer(name, layer, features)
                    out = clean_average(out, second, clean, input_scale(denoised))
            return out
        model = self.models[name]
        scaled, cands, scale = layer_candidates(layer, aux, model.candidates, denoised=denoised)
        data, gradient = blend_inputs(scaled, cands, features)
        return blend(model.weights(data, gradient), cands, scale)
