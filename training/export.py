"""`gradsep export RUN_DIR -o models/NAME.onnx`: the trained network as one self-describing ONNX file.

The graph is the main network only (the G-branch exists for the training loss). Inputs ``data``
(N, 13, H, W) and ``gradient`` (N, 6, H, W), output ``radiance_log`` (N, 3, H, W), all float32, with N, H and
W dynamic (H and W multiples of ``gradsep.alignment``). Everything a consumer needs to feed it correctly is
in the file's metadata_props (``gradsep.*``): the layer, the channel order, the preprocessing constants, the
alignment, the network and training configuration, the dataset manifest hash, the code version and the
attention flag. The export is checked against PyTorch in ONNX Runtime before the file is written.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gradsep.model.network import DualBranchNet, NetworkConfig
from gradsep.model.preprocess import DATA_INPUTS, GRADIENT_INPUTS, OUTPUTS, PRIOR_ALPHA, describe_preprocessing
from gradsep.training.runlog import code_version
from gradsep.training.train import CHECKPOINT, TrainConfig

OPSET = 18
INPUT_NAMES = ("data", "gradient")
OUTPUT_NAME = "radiance_log"
#: Largest ORT-vs-PyTorch difference, relative to the output's magnitude, that an export may have.
PARITY_TOLERANCE = 1e-4
FORMAT_VERSION = "1"


class ExportError(RuntimeError):
    """The run folder cannot be exported; the message says why."""


def model_metadata(network: NetworkConfig, layer: str, extra: dict[str, Any] | None = None,
                   prior_alpha: float = PRIOR_ALPHA) -> dict[str, str]:
    """The ``gradsep.*`` metadata_props: string values (JSON where structured), as ONNX requires. No
    ``gradsep.prior`` key: the model refines the ``l1`` prior, which a model without the key refines; its α is
    ``gradsep.prior_alpha``."""
    meta = {
        "gradsep.format": FORMAT_VERSION,
        "gradsep.layer": layer,
        "gradsep.inputs": json.dumps({"data": list(DATA_INPUTS), "gradient": list(GRADIENT_INPUTS)}),
        "gradsep.outputs": json.dumps({OUTPUT_NAME: list(OUTPUTS), "domain": "log transfer (preprocessing)"}),
        "gradsep.preprocessing": json.dumps(describe_preprocessing(prior_alpha=prior_alpha)),
        "gradsep.prior_alpha": repr(float(prior_alpha)),
        "gradsep.alignment": str(network.alignment),
        "gradsep.network": json.dumps(network.to_dict()),
        "gradsep.attention": "true" if network.use_attention else "false",
        "gradsep.code_version": code_version(),
    }
    for key, value in (extra or {}).items():
        meta[f"gradsep.{key}"] = value if isinstance(value, str) else json.dumps(value)
    return meta


def _sample_inputs(network: NetworkConfig, batch: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """A non-square sample; sizes > 1 everywhere so torch.export keeps every axis symbolic."""
    a = network.alignment
    g = torch.Generator().manual_seed(0)
    h, w = 2 * a, 3 * a
    return torch.rand(batch, len(DATA_INPUTS), h, w, generator=g), torch.rand(batch, len(GRADIENT_INPUTS), h, w,
                                                                               generator=g) - 0.5


def to_onnx(model: DualBranchNet, metadata: dict[str, str]) -> Any:
    """Trace ``model`` with dynamic N/H/W to an onnx.ModelProto carrying ``metadata``."""
    import onnx

    model = model.eval()
    data, gradient = _sample_inputs(model.config)
    n, h, w = torch.export.Dim("batch"), torch.export.Dim("height"), torch.export.Dim("width")
    shapes = {"data": {0: n, 2: h, 3: w}, "gradient": {0: n, 2: h, 3: w}}
    # the exporter prints progress lines, logs that torchvision's ops are unavailable and renames axes with
    # warnings; none of it helps a user of this command (real failures still raise)
    onnx_log = logging.getLogger("torch.onnx")
    level = onnx_log.level
    onnx_log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            program = torch.onnx.export(model, (data, gradient), None, input_names=list(INPUT_NAMES),
                                        output_names=[OUTPUT_NAME], opset_version=OPSET, dynamo=True,
                                        dynamic_shapes=shapes, verbose=False)
    finally:
        onnx_log.setLevel(level)
    proto = program.model_proto
    onnx.helper.set_model_props(proto, metadata)
    proto.doc_string = "gradsep dual-branch CBAM reconstruction network; see metadata gradsep.*"
    onnx.checker.check_model(proto)
    return proto


def parity_error(model: DualBranchNet, proto: Any, sizes: tuple[tuple[int, int], ...] | None = None) -> float:
    """max |ORT − PyTorch| / max |PyTorch| over a few input sizes (dynamic shapes exercised)."""
    import onnxruntime as ort

    a = model.config.alignment
    sizes = sizes or ((2 * a, 3 * a), (5 * a, 2 * a))
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    g = torch.Generator().manual_seed(1)
    worst = 0.0
    for h, w in sizes:
        data = torch.rand(1, len(DATA_INPUTS), h, w, generator=g)
        gradient = torch.rand(1, len(GRADIENT_INPUTS), h, w, generator=g) - 0.5
        with torch.no_grad():
            ref = model.eval()(data, gradient).numpy()
        got = session.run([OUTPUT_NAME], {"data": data.numpy(), "gradient": gradient.numpy()})[0]
        scale = max(float(np.abs(ref).max()), 1e-6)
        worst = max(worst, float(np.abs(got - ref).max()) / scale)
    return worst


def save_onnx(proto: Any, path: str | os.PathLike[str]) -> Path:
    """Write one self-contained .onnx file atomically (no external-data side file)."""
    import onnx

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        onnx.save_model(proto, tmp, save_as_external_data=False)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a failed write leaves no temporary file beside the output
        raise
    return path


def load_run(run_dir: str | os.PathLike[str]) -> tuple[TrainConfig, dict[str, Any], dict[str, Any]]:
    """(training config, checkpoint state, config.json) of a run folder; ExportError if it is not one."""
    run = Path(run_dir)
    ckpt = run / "checkpoints" / CHECKPOINT
    if not (run / "config.json").is_file() or not ckpt.is_file():
        raise ExportError(f"{run} is not a trained run folder (needs config.json and checkpoints/{CHECKPOINT})")
    try:
        run_json = json.loads((run / "config.json").read_text())
        state = torch.load(ckpt, map_location="cpu", weights_only=True)
        cfg = TrainConfig.from_dict(state["config"])
    except (OSError, ValueError, KeyError, RuntimeError) as exc:
        raise ExportError(f"{run}: cannot read the run ({exc})") from exc
    return cfg, state, run_json


def export_run(run_dir: str | os.PathLike[str], output: str | os.PathLike[str]) -> dict[str, Any]:
    """Export a run's latest checkpoint; returns a summary (path, layer, parity error, ...)."""
    cfg, state, run_json = load_run(run_dir)
    model = DualBranchNet(cfg.network)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise ExportError(f"{run_dir}: checkpoint does not match its network config ({exc})") from exc
    progress = state.get("progress", {})
    extra = {
        "training": cfg.to_dict(),
        "dataset_manifest_sha256": state.get("dataset_manifest_sha256", ""),
        "trained_epochs": str(progress.get("epoch", 0)),
        "trained_steps": str(progress.get("step", 0)),
        "trained_minutes": f"{progress.get('elapsed', 0.0) / 60:.2f}",
        "run_code_version": run_json.get("code_version", ""),
    }
    proto = to_onnx(model, model_metadata(cfg.network, cfg.layer, extra, prior_alpha=cfg.prior_alpha))
    err = parity_error(model, proto)
    if not err < PARITY_TOLERANCE:
        raise ExportError(f"ONNX Runtime disagrees with PyTorch (relative error {err:.2e} >= "
                          f"{PARITY_TOLERANCE:.0e}); not writing {output}")
    path = save_onnx(proto, output)
    return {"path": str(path), "bytes": path.stat().st_size, "layer": cfg.layer,
            "attention": cfg.network.use_attention, "epochs": progress.get("epoch", 0),
            "steps": progress.get("step", 0), "parity_relative_error": err}
