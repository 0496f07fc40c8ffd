"""training/export.py: `gradsep export` writes one self-describing ONNX file that matches PyTorch."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from gradsep.cli import main as cli_main  # noqa: E402
from gradsep.model.network import DualBranchNet, GBranch  # noqa: E402
from gradsep.model.preprocess import (  # noqa: E402
    DATA_INPUTS,
    GRADIENT_INPUTS,
    PREPROCESS_VERSION,  # noqa: E402
)
from gradsep.training.export import PARITY_TOLERANCE, export_run, parity_error, to_onnx  # noqa: E402
from gradsep.training.train import TrainConfig, train  # noqa: E402


def parameter_count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


@pytest.fixture(scope="module")
def exported(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    from tests.training.conftest import tiny_config

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("export")
    cfg = tiny_config(tiny_dataset, root / "run", epochs=1)
    train(cfg, quiet=True)
    summary = export_run(cfg.output, root / "models" / "direct.onnx")
    return Path(cfg.output), Path(summary["path"]), summary


@pytest.mark.train
@pytest.mark.slow
def test_file_metadata_and_dynamic_axes(exported: tuple[Path, Path, dict], tiny_dataset: Path) -> None:
    run, path, summary = exported
    model = onnx.load(path)
    assert not list(path.parent.glob("*.data"))                       # one self-contained file
    assert max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= 17
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["gradsep.layer"] == "direct" and meta["gradsep.attention"] == "true"
    assert json.loads(meta["gradsep.inputs"]) == {"data": list(DATA_INPUTS), "gradient": list(GRADIENT_INPUTS)}
    pre = json.loads(meta["gradsep.preprocessing"])
    assert pre["mu"] == 16.0 and pre["max_value"] == 65504.0 and pre["version"] == PREPROCESS_VERSION
    assert meta["gradsep.alignment"] == "8"
    assert json.loads(meta["gradsep.network"])["width"] == 4
    assert json.loads(meta["gradsep.training"])["patch"] == 32
    trained_alpha = json.loads(meta["gradsep.training"])["prior_alpha"]
    assert float(meta["gradsep.prior_alpha"]) == trained_alpha and f"alpha={trained_alpha}" in pre["prior"]
    manifest_hash = hashlib.sha256((tiny_dataset / "manifest.json").read_bytes()).hexdigest()
    assert meta["gradsep.dataset_manifest_sha256"] == manifest_hash
    assert meta["gradsep.code_version"].startswith("0.") and meta["gradsep.trained_steps"] == "5"
    for inp in model.graph.input:
        dims = inp.type.tensor_type.shape.dim
        assert [bool(d.dim_param) for d in dims] == [True, False, True, True], inp.name
    assert summary["parity_relative_error"] < PARITY_TOLERANCE


@pytest.mark.train
def test_graph_holds_the_main_network_only(exported: tuple[Path, Path, dict]) -> None:
    run, path, _ = exported
    cfg = TrainConfig.from_dict(json.loads((run / "config.json").read_text())["train"])
    model = onnx.load(path)
    stored = sum(int(np.prod(t.dims)) for t in model.graph.initializer)
    # every weight of the main network, plus a few scalar constants of the graph, and no G-branch weights
    assert 0 <= stored - parameter_count(DualBranchNet(cfg.network)) < 16
    assert parameter_count(GBranch(cfg.network)) > 1000


@pytest.mark.train
@pytest.mark.parametrize(("h", "w"), [(8, 8), (24, 40), (56, 16)])
def test_onnx_runtime_matches_pytorch(exported: tuple[Path, Path, dict], h: int, w: int) -> None:
    run, path, _ = exported
    state = torch.load(run / "checkpoints" / "last.pt", weights_only=True)
    net = DualBranchNet(TrainConfig.from_dict(state["config"]).network)
    net.load_state_dict(state["model"])
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    g = torch.Generator().manual_seed(h * w)
    data = torch.rand(2, len(DATA_INPUTS), h, w, generator=g)
    grad = torch.randn(2, len(GRADIENT_INPUTS), h, w, generator=g)
    with torch.no_grad():
        ref = net.eval()(data, grad).numpy()
    got = session.run(None, {"data": data.numpy(), "gradient": grad.numpy()})[0]
    assert got.shape == ref.shape
    assert np.abs(got - ref).max() / np.abs(ref).max() < 1e-4


@pytest.mark.slow
def test_no_attention_export_is_flagged() -> None:
    from gradsep.model.network import NetworkConfig
    from gradsep.training.export import model_metadata

    cfg = NetworkConfig(width=2, residual_blocks=0, use_attention=False)
    net = DualBranchNet(cfg)
    proto = to_onnx(net, model_metadata(cfg, "color"))
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["gradsep.attention"] == "false" and meta["gradsep.layer"] == "color"
    assert not any(n.op_type == "Sigmoid" for n in proto.graph.node)    # CBAM's gates are gone
    assert parity_error(net, proto) < PARITY_TOLERANCE


@pytest.mark.train
@pytest.mark.slow
def test_export_command(exported: tuple[Path, Path, dict], tmp_path: Path,
                        capsys: pytest.CaptureFixture[str]) -> None:
    run, _, _ = exported
    out = tmp_path / "m" / "direct.onnx"
    assert cli_main(["export", str(run), "-o", str(out)]) == 0
    assert out.is_file() and "wrote" in capsys.readouterr().out
    assert cli_main(["export", str(tmp_path), "-o", str(tmp_path / "x.onnx")]) == 2
    assert "not a trained run folder" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()


@pytest.mark.train
@pytest.mark.slow
def test_init_warm_starts_from_an_exported_model_or_a_checkpoint(exported: tuple[Path, Path, dict],
                                                                   tiny_dataset: Path, tmp_path: Path) -> None:
    """--init: the exported ONNX's initializers (and a run's checkpoint) load into a fresh run's network, names
    and shapes checked; a fresh run then starts from them, not at random."""
    from gradsep.training.train import initial_weights
    from tests.training.conftest import tiny_config

    run, onnx_path, _ = exported
    trained = torch.load(run / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)["model"]
    cfg = tiny_config(tiny_dataset, tmp_path / "warm", epochs=1, lr=0.0, init=str(onnx_path))
    for source in (onnx_path, run / "checkpoints" / "last.pt"):
        state = initial_weights(source, cfg)
        assert state.keys() == trained.keys()
        for key, value in trained.items():
            torch.testing.assert_close(state[key], value)
    train(cfg, quiet=True)  # lr 0: the run's weights are the init's, unchanged by its epoch
    warm = torch.load(tmp_path / "warm" / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)
    for key, value in trained.items():
        torch.testing.assert_close(warm["model"][key], value)
    assert json.loads((tmp_path / "warm" / "config.json").read_text())["train"]["init"] == str(onnx_path)


@pytest.mark.train
@pytest.mark.slow
@pytest.mark.parametrize("change", ["layer", "prior", "missing", "not-a-model"])
def test_init_refuses_weights_that_do_not_fit(exported: tuple[Path, Path, dict], tiny_dataset: Path,
                                              tmp_path: Path, change: str) -> None:
    from gradsep.training.train import TrainingError, initial_weights
    from tests.training.conftest import tiny_config

    _, onnx_path, _ = exported
    overrides: dict[str, object] = {"layer": "indirect"} if change == "layer" else {}
    cfg = tiny_config(tiny_dataset, tmp_path / "run", **overrides)
    source = onnx_path
    if change == "prior":  # a model refining another prior than this run's (l1, the only kind trained here)
        proto = onnx.load(onnx_path)
        onnx.helper.set_model_props(proto, {**{p.key: p.value for p in proto.metadata_props}, "gradsep.prior": "l2"})
        source = tmp_path / "other-prior.onnx"
        onnx.save(proto, source)
    elif change == "missing":
        source = tmp_path / "nothing.onnx"
    elif change == "not-a-model":
        source = tmp_path / "junk.onnx"
        source.write_bytes(b"not an onnx file")
    with pytest.raises(TrainingError, match="--init") as info:
        initial_weights(source, cfg)
    assert {"layer": "indirect", "prior": "'l2'", "missing": "no such file",
            "not-a-model": "not a readable ONNX"}[change] in str(info.value)
