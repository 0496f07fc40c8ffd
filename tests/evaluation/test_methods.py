"""One table of reconstruction methods (model/methods.py): a toy method registered in-process, with its own model
set, is found by every front end that derives from the table -- the command line's ``--method`` choices, the
service's OpenAPI enum and served list, the evaluation's methods (its row, its label, its model files, its
``--methods`` name, the report's labels, a plot style) and the model sets -- and by none of them once it is gone.
tests/model/test_methods.py drives the same toy through a reconstruction and a served request.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from gradsep.model import methods as table
from gradsep.model.frame import Layer


def toy_layer(name: str, layer: Layer, ctx: Any, denoised: np.ndarray | None = None) -> np.ndarray:
    return layer.base * 0.5


def toy_files(layers: tuple[str, ...]) -> tuple[str, ...]:
    """The toy set needs one model for the indirect layer only."""
    return tuple(f"toy-{name}" for name in layers if name == "indirect")


def toy_optional(layers: tuple[str, ...]) -> tuple[str, ...]:
    return ("../shared.onnx",)


class ToyModels:
    layers = {"direct", "indirect"}

    def describe(self) -> list[dict[str, Any]]:
        return []


def load_toy(models_dir: Any) -> ToyModels | None:
    return ToyModels() if models_dir is not None and (Path(models_dir) / "toy").is_dir() else None


TOY = table.Method("toy", "a toy method for the table's test", f"{__name__}:toy_layer", gradients="direct",
                   models=("toy-set",), preference=None)
TOY_SET = table.ModelSet("toy-set", f"{__name__}:load_toy", "the toy models, models/toy/", folder="toy",
                         files=f"{__name__}:toy_files", optional_files=f"{__name__}:toy_optional")


def _method_choices(command: str) -> list[str]:
    from gradsep.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return list(next(a for a in sub.choices[command]._actions if a.dest == "method").choices)


def _openapi_methods(models_dir: Path) -> list[str]:
    from gradsep.service.main import create_app
    from gradsep.service.settings import Settings

    schema = create_app(Settings(models_dir=models_dir, token=None, warm_up=False)).openapi()
    parameter = next(p for p in schema["paths"]["/v1/reconstruct"]["post"]["parameters"] if p["name"] == "method")
    return next(s for s in parameter["schema"]["anyOf"] if "enum" in s)["enum"]


def found_in(models_dir: Path) -> dict[str, bool]:
    """Where the toy method shows, front end by front end."""
    from gradsep.evaluation.config import parse_methods
    from gradsep.evaluation.methods import evaluated_methods
    from gradsep.evaluation.report import labels
    from gradsep.service.engine import load_models

    return {
        "cli reconstruct --method": "toy" in _method_choices("reconstruct"),
        "cli client --method": "toy" in _method_choices("client"),
        "service openapi enum": "toy" in _openapi_methods(models_dir),
        "service served list": "toy" in load_models(models_dir).serves(),
        "evaluation methods": "toy" in [m.name for m in evaluated_methods()],
        "evaluation --methods": "toy" in parse_methods(None),
        "report labels": "toy" in labels(),
        "model sets": "toy-set" in table.MODEL_SETS,
    }


def test_a_toy_method_is_found_by_every_front_end_and_gone_afterwards(tmp_path: Path) -> None:
    (tmp_path / "toy").mkdir()
    before = found_in(tmp_path)
    assert not any(before.values()), before
    with table.registered(TOY, TOY_SET):
        inside = found_in(tmp_path)
        assert all(inside.values()), inside
        from gradsep.evaluation.config import parse_methods
        from gradsep.evaluation.methods import method_by_name, unavailable
        from gradsep.evaluation.plots import style_of

        spec = method_by_name("toy")
        assert (spec.kind, spec.method, spec.models, spec.gradients) == ("recon", "toy", "toy", "direct")
        assert spec.label == "toy: a toy method for the table's test" and spec.short == "toy"
        # the evaluation's model files come from the set's declaration, placed in the set's folder
        assert spec.model_names(("direct", "indirect")) == ("toy-indirect",)
        assert spec.optional_model_files(("direct", "indirect")) == ("shared.onnx",)
        assert parse_methods("toy") == ("toy",) and unavailable(spec) is None
        assert len(style_of("toy")) == 3
    after = found_in(tmp_path)
    assert not any(after.values()), after


def test_the_shipped_model_sets_declare_the_files_the_evaluation_checks() -> None:
    """The evaluation reads each shipped method's model files from its set: the network's one per layer, fused's
    none for the layers it serves without a blend model (model.fused.FIXED_LAYERS) and the network's direct
    model as an optional file."""
    from gradsep.evaluation.methods import method_by_name
    from gradsep.model.fused import FIXED_LAYERS

    layers = ("direct", "indirect")
    assert method_by_name("ours").model_names(layers) == layers
    assert method_by_name("fused").model_names(layers) == tuple(n for n in layers if n not in FIXED_LAYERS)
    assert method_by_name("fused").optional_model_files(layers) == ("direct.onnx",)
    assert method_by_name("l1").model_names(layers) == () and method_by_name("l1").optional_model_files(layers) == ()
    assert table.MODEL_SETS["oidn"].model_files(layers) == ()
