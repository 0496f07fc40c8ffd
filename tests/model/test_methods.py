"""The table of reconstruction methods (model/methods.py): each method declared once, every front end reading it.

A toy method added in-process must show up in ``gradsep reconstruct --help``, in a freshly created service's
OpenAPI enum and in its ``/v1/models`` (and serve a request); the table refuses inconsistent declarations; the
default policy follows the declared preference.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gradsep.model import methods as table
from gradsep.model.frame import Frame, Layer
from tests.test_layering import imports

REPO = Path(__file__).resolve().parents[2]


def toy_layer(name: str, layer: Layer, ctx: Any, denoised: np.ndarray | None = None) -> np.ndarray:
    """The toy method: half the layer's base times its model set's gain (a stand-in for real work)."""
    return layer.base * 0.5 * ctx.models.get("toy-models").gain


class ToyModels:
    """A toy model set: what a loader returns and what /v1/models shows of it."""

    layers = {"direct", "indirect", "color"}
    gain = 2.0

    def describe(self) -> list[dict[str, Any]]:
        return [{"name": "toy", "provider": "cpu", "precision": "fp32", "provider_reason": "toy"}]


def load_toy(models_dir: Any) -> ToyModels:
    return ToyModels()


TOY = table.Method("toy", "a toy method for the table's test", f"{__name__}:toy_layer", gradients="none",
                   models=("toy-models",), preference=None)
TOY_SET = table.ModelSet("toy-models", f"{__name__}:load_toy", "the toy models", folder="toy")


def _choices(parser: argparse.ArgumentParser, command: str) -> list[str]:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    method = next(a for a in sub.choices[command]._actions if a.dest == "method")
    return list(method.choices)


def test_the_table_module_is_import_light() -> None:
    for module in ("model/methods.py", "model/policy.py"):
        heavy = [name for name, _, top in imports((REPO / module).read_text())
                 if top and name.split(".")[0] not in __import__("sys").stdlib_module_names
                 and not name.startswith("gradsep.model.policy")]
        assert heavy == [], f"{module} imports at module level: {heavy}"


def test_the_shipped_table() -> None:
    assert table.names() == ("network", "l1", "l2", "oidn", "oidn-l1", "fused")
    assert table.default_preference() == ("oidn-l1", "oidn", "fused", "network", "l1")
    assert table.preference_order() == (*table.default_preference(), "l2")
    assert [m.name for m in table.methods() if m.gradients == "none"] == ["oidn"]
    assert table.get("oidn").uses == ("albedo", "normal") and table.get("oidn").requires == ()
    assert table.get("network").requires == ("albedo", "normal", "depth")
    assert {m.name for m in table.methods() if m.alpha} == {"l1", "l2"}
    assert table.default_method(["l1", "l2", "oidn"], gradients=False) == "oidn"
    assert table.default_method(["l1", "l2"], gradients=False) is None
    assert table.default_method(["l2", "l1", "network"]) == "network"
    for method in table.methods():  # every function resolves
        assert callable(table.layer_function(method))


@pytest.mark.parametrize(("change", "problem"), [
    ({"requires": ("depth",)}, "required feature groups among the used ones"),
    ({"uses": ("albedo", "colour")}, "feature groups from"),
    ({"gradients": "some"}, "gradients in"),
    ({"schedule": "pipelined"}, "a denoiser for a pipelined schedule"),
    ({"denoiser": "method"}, "the 'oidn' model set"),
    ({"function": "no_colon"}, "as 'module:function'"),
    ({"name": "a,b"}, "without spaces at its ends or commas"),
])
def test_an_inconsistent_declaration_is_refused(change: dict[str, Any], problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        dataclasses.replace(TOY, models=(), **change)


def test_registering_checks_names_and_model_sets() -> None:
    with pytest.raises(ValueError, match="already registered"):
        table.register(table.get("l1"))
    with pytest.raises(ValueError, match="unknown model set"):
        table.register(dataclasses.replace(TOY, models=("nope",)))
    with pytest.raises(ValueError, match="unknown reconstruction method 'nope'; expected one of network, l1"):
        table.get("nope")
    assert "toy" not in table.names()


def test_a_toy_method_reaches_the_cli_the_service_and_reconstruct(tmp_path: Path, capsys) -> None:
    from fastapi.testclient import TestClient

    from gradsep.cli import build_parser, main
    from gradsep.model.exr_write import encode_exr
    from gradsep.model.frame import rgb_channels
    from gradsep.model.reconstruct import available_methods, reconstruct
    from gradsep.service.main import create_app
    from gradsep.service.settings import Settings

    base = np.full((8, 10, 3), 0.25, np.float32)
    frame = Frame({"color": Layer(base)})
    assert "toy" not in _choices(build_parser(), "reconstruct")
    with table.registered(TOY, TOY_SET):
        parser = build_parser()
        assert "toy" in _choices(parser, "reconstruct") and "toy" in _choices(parser, "client")
        with pytest.raises(SystemExit) as done:
            main(["reconstruct", "--help"])  # what `gradsep reconstruct --help` prints
        text = " ".join(capsys.readouterr().out.split())
        assert done.value.code == 0 and "fused,toy}" in text and "toy: a toy method for the table's test" in text
        models = table.LoadedModels.load(tmp_path)
        assert "toy" in available_methods(frame, models)
        np.testing.assert_allclose(reconstruct(frame, "toy", models=models).image, base)  # 0.5 x gain 2
        with pytest.raises(ValueError, match="needs the toy models"):
            reconstruct(frame, "toy", models=table.LoadedModels())

        app = create_app(Settings(models_dir=tmp_path, token=None, warm_up=False))
        with TestClient(app) as client:
            schema = client.get("/openapi.json").json()
            parameter = next(p for p in schema["paths"]["/v1/reconstruct"]["post"]["parameters"]
                             if p["name"] == "method")
            enum = next(s for s in parameter["schema"]["anyOf"] if "enum" in s)["enum"]
            assert enum == list(table.names()) and "toy" in enum
            deadline = __import__("time").monotonic() + 60
            while client.get("/readyz").status_code != 200:
                assert __import__("time").monotonic() < deadline
            info = client.get("/v1/models").json()
            assert "toy" in info["methods"]
            row = next(r for r in info["method_table"] if r["name"] == "toy")
            assert row["served"] and row["models"] == ["toy-models"] and row["gradients"] == "none"
            assert {"name": "toy", "provider": "cpu", "precision": "fp32", "provider_reason": "toy",
                    "method": "toy-models"} in info["models"]
            body = encode_exr(rgb_channels("color", base))
            answer = client.post("/v1/reconstruct", params={"method": "toy"}, content=body,
                                 headers={"Content-Type": "image/x-exr"})
            assert answer.status_code == 200 and answer.headers["x-reconstruction-method"] == "toy"
    assert "toy" not in table.names() and "toy-models" not in table.MODEL_SETS
    fresh = create_app(Settings(models_dir=tmp_path, token=None, warm_up=False)).openapi()
    parameter = next(p for p in fresh["paths"]["/v1/reconstruct"]["post"]["parameters"] if p["name"] == "method")
    assert "toy" not in next(s for s in parameter["schema"]["anyOf"] if "enum" in s)["enum"]


def test_a_replaced_declaration_is_restored() -> None:
    original = table.get("l2")
    with table.registered(dataclasses.replace(original, preference=0)):
        assert table.default_preference()[0] == "l2"
    assert table.get("l2") is original and table.names()[2] == "l2"


def test_the_cli_names_a_missing_model_set(tmp_path: Path, capsys, monkeypatch) -> None:
    from gradsep.cli import main
    from gradsep.model.exr_write import write_frame

    frame = tmp_path / "frame.exr"
    write_frame(frame, Frame({"color": Layer(np.full((8, 10, 3), 0.25, np.float32))}))
    out = tmp_path / "out.exr"
    assert main(["reconstruct", str(frame), "--method", "fused", "--models", str(tmp_path), "-o", str(out)]) == 2
    assert f"needs the per-layer blend networks, models/fused/*.onnx (needs pyoidn), but none was found in " \
           f"'{tmp_path / 'fused'}'" in capsys.readouterr().err
    monkeypatch.setattr("gradsep.model.oidn.available", lambda: False)
    assert main(["reconstruct", str(frame), "--method", "oidn", "-o", str(out)]) == 2
    assert "needs Intel Open Image Denoise (pip install pyoidn), which is not installed here" in capsys.readouterr().err
    assert main(["reconstruct", str(frame), "-o", str(out)]) == 2  # the default: nothing serves a plain frame
    assert "no reconstruction method can serve this frame here: oidn (needs Intel Open Image Denoise" in \
        capsys.readouterr().err
    assert not out.exists()
