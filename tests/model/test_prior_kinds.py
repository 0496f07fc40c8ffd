"""The prior a network refines is a property of the model (issue 15): chosen at training, recorded in the exported
ONNX metadata (``gradsep.prior``), and solved at inference from the loaded model's metadata. No training here:
untrained exported networks, whose zero-initialised head makes their output the prior they were fed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

import model.preprocess as preprocess  # noqa: E402
from gradsep.model.frame import Features, Layer  # noqa: E402
from gradsep.model.infer import ModelError, NetworkReconstructor, exposure_scale  # noqa: E402
from gradsep.model.network import DualBranchNet, NetworkConfig  # noqa: E402
from gradsep.model.reconstruct import load_network  # noqa: E402
from gradsep.training.export import ExportError, model_metadata, prior_metadata, save_onnx, to_onnx  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
TINY = NetworkConfig(width=4, residual_blocks=0, use_attention=False)
POISSON = tuple(preprocess.POISSON_PRIORS)


@pytest.fixture(scope="module")
def graph():  # noqa: ANN201 - an onnx.ModelProto
    """One tiny untrained network exported once (torch's exporter takes seconds); each test re-labels copies."""
    torch.manual_seed(0)
    return to_onnx(DualBranchNet(TINY).eval(), model_metadata(TINY, "direct"))


def _export(graph, folder: Path, prior: str, meta_prior: str | None = None) -> None:  # noqa: ANN001
    """direct.onnx and indirect.onnx labelled as trained (here: untrained) on ``prior``, with the metadata
    training/export.py writes for that kind; ``meta_prior`` overrides the recorded ``gradsep.prior`` (to forge an
    unknown kind)."""
    import onnx

    folder.mkdir(parents=True, exist_ok=True)
    for layer in ("direct", "indirect"):
        meta = model_metadata(TINY, layer, prior_metadata(prior), prior=prior)
        if meta_prior is not None:
            meta["gradsep.prior"] = meta_prior
        proto = onnx.ModelProto()
        proto.CopyFrom(graph)
        del proto.metadata_props[:]
        onnx.helper.set_model_props(proto, meta)
        save_onnx(proto, folder / f"{layer}.onnx")


def _frame(h: int = 24, w: int = 40, seed: int = 5) -> tuple[Layer, Features]:
    """A noisy layer with an outlier gradient, so the L1 and L2 solves differ visibly."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    clean = (1.0 + 0.5 * np.sin(xx / 5.0))[..., None] * np.array([0.9, 0.6, 0.3], np.float32)
    base = (clean * rng.lognormal(0.0, 0.4, clean.shape)).astype(np.float32)
    dx = np.zeros_like(clean)
    dy = np.zeros_like(clean)
    dx[:, :-1] = clean[:, 1:] - clean[:, :-1]
    dy[:-1] = clean[1:] - clean[:-1]
    dx[h // 2, w // 2] = 40.0  # a firefly in the gradients: the L2 solve smears it, the robust one discards it
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1.0
    return Layer(base, dx, dy), Features(np.full((h, w, 3), 0.5, np.float32), normal, (1 + yy / h).astype(np.float32))


def test_the_command_lines_choices_are_the_shipped_models_priors() -> None:
    """``gradsep train --prior`` offers what the shipped network models refine, each a kind inference computes."""
    import onnx

    from gradsep.training.commands import PRIOR_CHOICES

    assert set(PRIOR_CHOICES) <= set(preprocess.PRIOR_KINDS)
    shipped = {dict((p.key, p.value) for p in onnx.load(str(path), load_external_data=False).metadata_props).get(
        "gradsep.prior", preprocess.DEFAULT_PRIOR) for path in (REPO / "models").rglob("*.onnx")
        if "fused" not in path.parts}
    assert shipped and shipped <= set(PRIOR_CHOICES), shipped
    assert preprocess.DEFAULT_PRIOR == "l1" and {"l1", "l2", "oidn"} <= set(preprocess.PRIOR_KINDS)


def test_l1_models_keep_their_metadata_and_prior_bit_for_bit() -> None:
    """Today's models: no gradsep.prior key, the same preprocessing description, the same solve."""
    assert prior_metadata("l1") == {}
    assert model_metadata(TINY, "direct") == model_metadata(TINY, "direct", prior="l1")
    assert preprocess.describe_preprocessing() == preprocess.describe_preprocessing(prior="l1")
    assert "5 passes x 2 CG steps" in preprocess.describe_preprocessing()["prior"]
    layer, _ = _frame()
    np.testing.assert_array_equal(preprocess.poisson_prior(layer), preprocess.poisson_prior(layer, kind="l1"))


def test_every_kind_solves_its_own_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[tuple] = []

    def spy(base, dx, dy, alpha, **kwargs):
        seen.append((kwargs["iterations"], kwargs["cg_iterations"], kwargs["preconditioner"]))
        return np.zeros_like(base), None

    monkeypatch.setattr(preprocess, "solve_l1", spy)
    layer, _ = _frame(16, 16)
    for kind in POISSON:
        preprocess.poisson_prior(layer, kind=kind)
    assert seen == [(5, 2, "dct"), (1, 1, "dct"), (3, 2, "mg"), (1, 1, "dct")]


def test_l2_kind_is_the_exact_screened_poisson_solve() -> None:
    from gradsep.model.poisson import solve_l2

    layer, _ = _frame()
    exact = np.clip(solve_l2(layer.base, layer.dx, layer.dy, preprocess.PRIOR_ALPHA), 0, None)
    got = preprocess.poisson_prior(layer, kind="l2")
    assert np.abs(got - exact).max() <= 1e-4 * float(np.abs(exact).max())
    assert "L2 screened Poisson" in preprocess.describe_preprocessing(prior="l2")["prior"]


def test_l2_clamp_kind_is_the_l2_solve_of_the_clamped_data() -> None:
    """``l2-clamp`` = ``l2`` on clamp_outliers' data: an isolated firefly (and the gradients around it) is clamped
    to OUTLIER_CLAMP x its neighbourhood before the solve, so the prior does not smear it; a frame without
    outliers is solved as ``l2``; the clamp is scale-invariant and its compiled and numpy paths agree."""
    from gradsep.model import kernels
    from gradsep.model.frame import Layer, forward_differences

    yy, xx = np.mgrid[0:24, 0:40].astype(np.float32)
    smooth = ((1.0 + 0.5 * np.sin(xx / 5.0) * np.cos(yy / 7.0))[..., None] * np.array([0.9, 0.6, 0.3])).astype(
        np.float32)
    layer = Layer(smooth, *forward_differences(smooth))
    assert np.array_equal(preprocess.poisson_prior(layer, kind="l2-clamp"), preprocess.poisson_prior(layer, kind="l2"))
    base = layer.base.copy()
    base[20, 20] = 1e4  # a firefly, in the base and (as OIDN's shifted paths would) in its gradients
    dx, dy = forward_differences(base)
    hot = Layer(base, dx, dy)
    smeared = preprocess.poisson_prior(hot, kind="l2")
    clamped = preprocess.poisson_prior(hot, kind="l2-clamp")
    around = (slice(16, 25), slice(16, 25))
    assert smeared[20, 20].max() > 0.9e4  # consistent data: the L2 solve keeps the firefly whole
    # clamped: the base to 4x its neighbours, each gradient to 4x the clamped base around it
    assert clamped[around].max() <= preprocess.OUTLIER_CLAMP**2 * layer.base[around].max() * 1.01
    for scale in (1e-8, 1e9):
        s = np.float32(scale)
        out = preprocess.clamp_outliers(base * s, dx * s, dy * s)
        ref = preprocess.clamp_outliers(base, dx, dy)
        for a, b in zip(out, ref, strict=True):
            np.testing.assert_allclose(a / s, b, rtol=1e-5, atol=1e-30)
    if kernels.AVAILABLE:
        compiled = preprocess.clamp_outliers(base, dx, dy)
        kernels.AVAILABLE = False
        try:
            plain = preprocess.clamp_outliers(base, dx, dy)
        finally:
            kernels.AVAILABLE = True
        for a, b in zip(compiled, plain, strict=True):
            np.testing.assert_array_equal(a, b)
    assert "clamping outliers" in preprocess.describe_preprocessing(prior="l2-clamp")["prior"]


def test_unknown_kind_is_an_error_everywhere() -> None:
    layer, _ = _frame(8, 8)
    with pytest.raises(ValueError, match="l3"):
        preprocess.poisson_prior(layer, kind="l3")
    with pytest.raises(ValueError, match="l3"):
        preprocess.describe_prior("l3")
    with pytest.raises(ExportError, match="l3"):
        prior_metadata("l3")


@pytest.mark.parametrize("kind", POISSON)
def test_kind_round_trips_from_export_metadata_to_the_served_prior(graph, kind: str, tmp_path: Path) -> None:  # noqa: ANN001
    _export(graph, tmp_path, kind)
    rec = load_network(tmp_path)  # the network method's loader accepts every Poisson kind
    assert rec is not None
    for entry in rec.describe():
        assert entry["prior"] == kind
        assert json.loads(entry["metadata"]["gradsep.preprocessing"])["prior"] == preprocess.describe_prior(kind)
        assert ("gradsep.prior" in entry["metadata"]) == (kind != "l1")
    layer, features = _frame()
    s = exposure_scale(layer)  # the network runs at its trained exposure (the L1 priors' regulariser is absolute)
    priors = {k: s * preprocess.poisson_prior(preprocess.scaled_layer(layer, 1.0 / s), kind=k) for k in POISSON}
    out = rec.reconstruct_layer("direct", layer, features)
    # untrained: the output is C⁻¹(C(prior)) of the model's own kind (up to float32 rounding of the transfer) ...
    scale = float(priors[kind].max())
    assert np.abs(out - priors[kind]).max() <= 1e-4 * scale
    # ... and visibly not another kind's
    for other in POISSON:
        if other != kind:
            assert np.abs(out - priors[other]).max() > 1e-2 * scale, other


def test_the_kind_is_per_model(graph, tmp_path: Path) -> None:  # noqa: ANN001
    """A folder may mix kinds: each layer's model gets its own prior."""
    _export(graph, tmp_path / "mixed", "l1")
    _export(graph, tmp_path / "l2", "l2")
    (tmp_path / "l2" / "indirect.onnx").replace(tmp_path / "mixed" / "indirect.onnx")
    rec = NetworkReconstructor.load(tmp_path / "mixed")
    assert {n: m.prior for n, m in rec.models.items()} == {"direct": "l1", "indirect": "l2"}


def test_a_model_naming_an_unknown_prior_is_refused_at_load(graph, tmp_path: Path) -> None:  # noqa: ANN001
    _export(graph, tmp_path, "l2", meta_prior="l3-multigrid")
    with pytest.raises(ModelError, match="'l3-multigrid' is unknown"):
        NetworkReconstructor.load(tmp_path)
    with pytest.raises(ModelError, match="l3-multigrid"):
        load_network(tmp_path)


def test_the_shipped_models_are_served_with_the_prior_their_metadata_names() -> None:
    rec = load_network(REPO / "models")
    if rec is None:
        pytest.skip("no models in models/")
    for name, model in rec.models.items():
        assert model.prior in preprocess.POISSON_PRIORS, name
        exported = json.loads(model.metadata["gradsep.preprocessing"])
        assert exported["prior"] == preprocess.describe_prior(model.prior), name
