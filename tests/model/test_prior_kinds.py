"""The prior a network refines is a property of the model, recorded in its ONNX metadata (``gradsep.prior``; absent
means ``l1``, the truncated L1 Poisson solve every shipped network model refines). This code computes ``l1`` only: a
model naming any other kind is refused at load with a clear ModelError, and training refuses any other kind. No
training here: untrained exported networks, whose zero-initialised head makes their output the prior they were
fed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

import gradsep.model.preprocess as preprocess  # noqa: E402
from gradsep.model.frame import Features, Layer  # noqa: E402
from gradsep.model.infer import ModelError, NetworkReconstructor, exposure_scale  # noqa: E402
from gradsep.model.network import DualBranchNet, NetworkConfig  # noqa: E402
from gradsep.model.reconstruct import load_network  # noqa: E402
from gradsep.training.export import model_metadata, save_onnx, to_onnx  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
TINY = NetworkConfig(width=4, residual_blocks=0, use_attention=False)


@pytest.fixture(scope="module")
def graph():  # noqa: ANN201 - an onnx.ModelProto
    """One tiny untrained network exported once (torch's exporter takes seconds); each test re-labels copies."""
    torch.manual_seed(0)
    return to_onnx(DualBranchNet(TINY).eval(), model_metadata(TINY, "direct"))


def _export(graph, folder: Path, meta_prior: str | None = None,  # noqa: ANN001
            meta_alpha: str | None = "keep") -> None:
    """direct.onnx and indirect.onnx with the metadata training/export.py writes; ``meta_prior`` sets a
    ``gradsep.prior`` (to forge a kind this code does not compute), ``meta_alpha`` a ``gradsep.prior_alpha`` (None:
    no key, as on models exported before it existed)."""
    import onnx

    folder.mkdir(parents=True, exist_ok=True)
    for layer in ("direct", "indirect"):
        meta = model_metadata(TINY, layer)
        if meta_prior is not None:
            meta["gradsep.prior"] = meta_prior
        if meta_alpha is None:
            del meta["gradsep.prior_alpha"]
        elif meta_alpha != "keep":
            meta["gradsep.prior_alpha"] = meta_alpha
        proto = onnx.ModelProto()
        proto.CopyFrom(graph)
        del proto.metadata_props[:]
        onnx.helper.set_model_props(proto, meta)
        save_onnx(proto, folder / f"{layer}.onnx")


def _frame(h: int = 24, w: int = 40, seed: int = 5) -> tuple[Layer, Features]:
    """A noisy layer with an outlier gradient."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    clean = (1.0 + 0.5 * np.sin(xx / 5.0))[..., None] * np.array([0.9, 0.6, 0.3], np.float32)
    base = (clean * rng.lognormal(0.0, 0.4, clean.shape)).astype(np.float32)
    dx = np.zeros_like(clean)
    dy = np.zeros_like(clean)
    dx[:, :-1] = clean[:, 1:] - clean[:, :-1]
    dy[:-1] = clean[1:] - clean[:-1]
    dx[h // 2, w // 2] = 40.0
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1.0
    return Layer(base, dx, dy), Features(np.full((h, w, 3), 0.5, np.float32), normal, (1 + yy / h).astype(np.float32))


def test_the_shipped_models_refine_the_prior_training_and_inference_compute() -> None:
    """Every shipped network model refines a prior inference computes, the one `gradsep train` trains (it has no
    choice to offer: TrainConfig's default)."""
    import onnx

    from gradsep.training.train import TrainConfig

    shipped = {dict((p.key, p.value) for p in onnx.load(str(path), load_external_data=False).metadata_props).get(
        "gradsep.prior", preprocess.DEFAULT_PRIOR) for path in (REPO / "models").rglob("*.onnx")
        if "fused" not in path.parts}
    assert shipped and shipped <= set(preprocess.PRIOR_KINDS), shipped
    assert TrainConfig.prior in preprocess.PRIOR_KINDS and TrainConfig.prior == preprocess.DEFAULT_PRIOR


def test_exported_metadata_names_no_prior_and_describes_the_l1_solve() -> None:
    """Exported models carry no gradsep.prior key (l1) and the same preprocessing description as the shipped ones."""
    meta = model_metadata(TINY, "direct")
    assert "gradsep.prior" not in meta
    assert json.loads(meta["gradsep.preprocessing"]) == preprocess.describe_preprocessing()
    assert "5 passes x 2 CG steps" in preprocess.describe_prior()
    assert float(meta["gradsep.prior_alpha"]) == preprocess.PRIOR_ALPHA
    assert f"alpha={preprocess.PRIOR_ALPHA}" in preprocess.describe_prior()


def test_training_refuses_another_prior(tmp_path: Path) -> None:
    from gradsep.training.train import TrainConfig

    with pytest.raises(ValueError, match="prior must be one of"):
        TrainConfig(data=str(tmp_path), layer="direct", output=str(tmp_path / "run"), prior="l2")


def test_an_exported_model_is_served_with_the_l1_prior(graph, tmp_path: Path) -> None:  # noqa: ANN001
    _export(graph, tmp_path)
    rec = load_network(tmp_path)
    assert rec is not None
    for entry in rec.describe():
        assert entry["prior"] == "l1" and "gradsep.prior" not in entry["metadata"]
        assert json.loads(entry["metadata"]["gradsep.preprocessing"])["prior"] == preprocess.describe_prior()
    layer, features = _frame()
    s = exposure_scale(layer)  # the network runs at its trained exposure (the L1 prior's regulariser is absolute)
    prior = s * preprocess.poisson_prior(preprocess.scaled_layer(layer, 1.0 / s))
    out = rec.reconstruct_layer("direct", layer, features)
    # untrained: the output is C⁻¹(C(prior)) (up to float32 rounding of the transfer)
    assert np.abs(out - prior).max() <= 1e-4 * float(prior.max())


@pytest.mark.parametrize("kind", ["l3-multigrid", "l2", "oidn"])
def test_a_model_naming_another_prior_is_refused_at_load(graph, tmp_path: Path, kind: str) -> None:  # noqa: ANN001
    _export(graph, tmp_path, meta_prior=kind)
    with pytest.raises(ModelError, match=f"'{kind}' is unknown"):
        NetworkReconstructor.load(tmp_path)
    with pytest.raises(ModelError, match=kind):
        load_network(tmp_path)


def test_the_shipped_models_are_served_with_the_prior_their_metadata_names() -> None:
    rec = load_network(REPO / "models")
    if rec is None:
        pytest.skip("no models in models/")
    for name, model in rec.models.items():
        assert model.prior == "l1", name
        exported = json.loads(model.metadata["gradsep.preprocessing"])
        assert exported["prior"] == preprocess.describe_prior(model.prior_alpha), name


def _untrained_output_and_priors(rec: NetworkReconstructor, *alphas: float) -> tuple[np.ndarray, list[np.ndarray]]:
    layer, features = _frame()
    s = exposure_scale(layer)
    priors = [s * preprocess.poisson_prior(preprocess.scaled_layer(layer, 1.0 / s), alpha=a) for a in alphas]
    return rec.reconstruct_layer("direct", layer, features), priors


def test_a_model_is_served_with_the_alpha_it_was_trained_on(graph, tmp_path: Path) -> None:  # noqa: ANN001
    """The prior's α is the model's (gradsep.prior_alpha), not a constant of this code: a model trained on another
    α is fed the prior it learned to refine."""
    other = 4 * preprocess.PRIOR_ALPHA
    _export(graph, tmp_path, meta_alpha=repr(other))
    rec = NetworkReconstructor.load(tmp_path)
    assert rec is not None and {m.prior_alpha for m in rec.models.values()} == {other}
    assert {e["prior_alpha"] for e in rec.describe()} == {other}
    out, (own, default) = _untrained_output_and_priors(rec, other, preprocess.PRIOR_ALPHA)
    assert np.abs(own - default).max() > 100 * 1e-4 * float(own.max())  # the two α give different priors
    assert np.abs(out - own).max() <= 1e-4 * float(own.max())


def test_a_model_without_the_alpha_key_is_served_with_the_unrecorded_alpha(graph, tmp_path: Path) -> None:  # noqa: ANN001
    _export(graph, tmp_path, meta_alpha=None)
    rec = NetworkReconstructor.load(tmp_path)
    assert rec is not None and {m.prior_alpha for m in rec.models.values()} == {preprocess.UNRECORDED_PRIOR_ALPHA}
    out, (own,) = _untrained_output_and_priors(rec, preprocess.UNRECORDED_PRIOR_ALPHA)
    assert np.abs(out - own).max() <= 1e-4 * float(own.max())


@pytest.mark.parametrize("alpha", ["nan", "inf", "0", "-0.2", "abc", ""])
def test_a_model_with_an_unusable_alpha_is_refused_at_load(graph, tmp_path: Path, alpha: str) -> None:  # noqa: ANN001
    _export(graph, tmp_path, meta_alpha=alpha)
    with pytest.raises(ModelError, match=f"prior alpha {alpha!r} is not a finite number > 0"):
        NetworkReconstructor.load(tmp_path)
