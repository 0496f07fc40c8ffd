"""The reconstruction entry point and the `gradsep reconstruct` command."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from gradsep.cli import main
from gradsep.model import methods as table
from gradsep.model.errors import ChannelError
from gradsep.model.exr_read import read_frame
from gradsep.model.exr_write import write_exr, write_frame
from gradsep.model.frame import Features, Frame, Layer, forward_differences, layer_channels
from gradsep.model.methods import LoadedModels
from gradsep.model.poisson import solve_l1, solve_l2
from gradsep.model.reconstruct import choose_method, reconstruct

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def _no_models(tmp_path: Path, monkeypatch) -> None:
    """The CLI's default method depends on the models folder: keep these tests independent of models/."""
    monkeypatch.setenv("GRADSEP_MODELS", str(tmp_path / "no-models"))


def _layer(h: int, w: int, scale: float, seed: int, noise: float = 0.0) -> Layer:
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    image = np.stack([scale * (0.4 + 0.3 * np.sin(4 * xx + c) * np.cos(3 * yy)) for c in range(3)], -1)
    dx, dy = forward_differences(image)
    rng = np.random.default_rng(seed)
    base = image + noise * rng.normal(size=image.shape)
    return Layer(*(a.astype(np.float32) for a in (base, dx, dy)))


def _features(h: int, w: int) -> Features:
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1
    return Features(np.full((h, w, 3), 0.5, np.float32), normal, np.ones((h, w), np.float32))


def _frame(layers=("direct", "indirect"), h: int = 18, w: int = 23, noise: float = 0.05,
           features: bool = True) -> Frame:
    made = {name: _layer(h, w, 1.0 / (i + 1), seed=i, noise=noise) for i, name in enumerate(layers)}
    return Frame(made, _features(h, w) if features else None)


class HalfBase:
    """A stand-in network: returns half of the base (enough to check the plumbing), records its calls."""

    def __init__(self, result=None) -> None:
        self.calls: list[str] = []
        self.result = result

    def reconstruct_layer(self, name: str, layer: Layer, features: Features) -> np.ndarray:
        assert isinstance(features, Features)
        self.calls.append(name)
        return layer.base * 0.5 if self.result is None else self.result


# ------------------------------------------------------------------------------------------ reconstruct()


@pytest.mark.parametrize("method", ["l1", "l2"])
def test_reconstruct_sums_the_layers_each_solved_on_its_own(method: str) -> None:
    frame = _frame()
    result = reconstruct(frame, method, alpha=0.3)
    assert result.method == method and list(result.layers) == ["direct", "indirect"]
    assert set(result.timings) == {"direct", "indirect"} and all(t >= 0 for t in result.timings.values())
    for name, layer in frame.layers.items():
        solo = solve_l1(layer.base, layer.dx, layer.dy, 0.3)[0] if method == "l1" else solve_l2(
            layer.base, layer.dx, layer.dy, 0.3)
        np.testing.assert_allclose(result.layers[name], np.clip(solo, 0, None), atol=1e-6)
    assert result.image.dtype == np.float32 and result.image.shape == (18, 23, 3)
    np.testing.assert_allclose(result.image, result.layers["direct"] + result.layers["indirect"], atol=1e-6)


def test_reconstruct_runs_nothing_for_absent_layers() -> None:
    network = HalfBase()
    result = reconstruct(_frame(layers=("direct",)), "network", models=LoadedModels(network=network))
    assert network.calls == ["direct"] and list(result.layers) == ["direct"]
    color = reconstruct(_frame(layers=("color",)), "network", models=LoadedModels(network=network))
    assert network.calls == ["direct", "color"] and list(color.layers) == ["color"]
    np.testing.assert_allclose(color.image, color.layers["color"])


def test_reconstruct_output_is_finite_and_non_negative() -> None:
    bad = np.full((18, 23, 3), -1.0, np.float32)
    bad[0, 0] = np.nan
    bad[1, 1] = np.inf
    bad[2, 2] = 5.0
    result = reconstruct(_frame(), "network", models=LoadedModels(network=HalfBase(bad)))
    assert np.isfinite(result.image).all() and (result.image >= 0).all()
    assert result.image[2, 2, 0] == 10.0 and result.image[1, 1, 0] == 0.0 and result.image[5, 5, 0] == 0.0
    assert len(result.warnings) == 2 and "direct" in result.warnings[0] and "6 non-finite" in result.warnings[0]


def test_reconstruct_errors_are_clear() -> None:
    frame = _frame()
    with pytest.raises(ValueError, match="unknown reconstruction method 'l3'"):
        reconstruct(frame, "l3")
    with pytest.raises(ValueError, match="needs the per-layer networks, models/"):
        reconstruct(frame, "network")
    with pytest.raises(ValueError, match="needs the per-layer blend networks, models/fused"):
        reconstruct(frame, "fused")
    with pytest.raises(ChannelError, match="feature group.*albedo, normal, depth"):
        reconstruct(_frame(features=False), "network", models=LoadedModels(network=HalfBase()))
    with pytest.raises(ValueError, match="alpha"):
        reconstruct(frame, "l2", alpha=0.0)
    with pytest.raises(RuntimeError, match="shape"):
        reconstruct(frame, "network", models=LoadedModels(network=HalfBase(np.zeros((2, 2, 3), np.float32))))
    assert table.names() == ("network", "l1", "l2", "oidn", "oidn-l1", "fused")


def test_network_refuses_layers_it_has_no_model_for() -> None:
    only_direct = HalfBase()
    only_direct.layers = {"direct"}
    with pytest.raises(ChannelError, match="no network model for layer.*indirect") as err:
        reconstruct(_frame(), "network", models=LoadedModels(network=only_direct))
    assert err.value.details["unserved_layers"] == ["indirect"] and only_direct.calls == []


def test_default_method_is_the_first_preferred_method_that_serves_the_frame(monkeypatch) -> None:
    network, fused = HalfBase(), HalfBase()
    network.layers = fused.layers = {"direct", "indirect"}
    both = LoadedModels(network=network, fused=fused)
    assert choose_method(_frame(), both) == "oidn-l1"  # first in the table's preference (held-out study)
    assert choose_method(_frame(), LoadedModels(network=network)) == "oidn-l1"  # OIDN (here) ranks above network
    assert choose_method(_frame(features=False), both) == "oidn-l1"  # features are optional for it
    plain = Frame({n: Layer(layer.base) for n, layer in _frame().layers.items()}, _frame().features)
    assert choose_method(plain, both) == "oidn"  # oidn-l1 needs gradients
    fused.layers = {"direct"}  # fused models that do not cover the frame are passed over
    assert choose_method(_frame(), both) == "oidn-l1"
    assert reconstruct(_frame(), models=both).method == "oidn-l1"
    fused.layers = {"direct", "indirect"}
    with table.registered(dataclasses.replace(table.get("fused"), preference=0)):
        assert choose_method(_frame(), both) == "fused"  # the order is data: a policy change is one line
    assert choose_method(_frame(), both) == "oidn-l1"  # and the table is restored
    monkeypatch.setattr("gradsep.model.oidn.available", lambda: False)  # a host without pyoidn
    assert choose_method(_frame(), LoadedModels(network=network)) == "network"
    network.layers = {"direct"}
    assert choose_method(_frame(), LoadedModels(network=network)) == "l1"
    assert reconstruct(_frame(), models=LoadedModels(network=network)).method == "l1"


def _direct_gradients_only(frame: Frame) -> Frame:
    """The frame `gradsep render --gradients direct` writes: the direct layer's gradients, a plain indirect."""
    layers = {name: layer if name == "direct" else Layer(layer.base) for name, layer in frame.layers.items()}
    return Frame(layers, frame.features)


def test_a_frame_with_the_direct_layers_gradients_only(monkeypatch) -> None:
    """oidn-l1 (the default) and oidn serve it; oidn-l1 gives what it gives the full frame (it refines the
    direct layer alone); the methods that integrate every layer's gradients refuse it naming the channels."""
    full = _frame(noise=0.2)
    mixed = _direct_gradients_only(full)
    network, fused = HalfBase(), HalfBase()
    network.layers = fused.layers = {"direct", "indirect"}
    both = LoadedModels(network=network, fused=fused)
    assert choose_method(mixed, both) == "oidn-l1"
    result = reconstruct(mixed)
    assert result.method == "oidn-l1"
    np.testing.assert_array_equal(result.image, reconstruct(full, "oidn-l1").image)
    assert not np.array_equal(result.layers["direct"], reconstruct(mixed, "oidn").layers["direct"])
    missing = [f"indirect.{g}.{c}" for g in ("dx", "dy") for c in "RGB"]
    for method in ("l1", "l2", "network", "fused"):
        with pytest.raises(ChannelError, match="indirect.dx.R") as err:
            reconstruct(mixed, method, models=both)
        assert err.value.details["missing"] == missing, method
    # the direct layer without gradients and the indirect with them: oidn-l1 cannot refine, oidn serves it
    other = Frame({"direct": Layer(full.layers["direct"].base), "indirect": full.layers["indirect"]}, full.features)
    assert choose_method(other, both) == "oidn"
    with pytest.raises(ChannelError) as err:
        reconstruct(other, "oidn-l1")
    assert err.value.details["missing"] == [f"direct.{g}.{c}" for g in ("dx", "dy") for c in "RGB"]
    monkeypatch.setattr("gradsep.model.oidn.available", lambda: False)  # a host without pyoidn: nothing serves it
    with pytest.raises(ChannelError, match=r"oidn-l1 \(needs Intel Open Image Denoise"):
        choose_method(mixed, LoadedModels(network=network, fused=fused))


def test_cli_reconstructs_a_frame_with_the_direct_layers_gradients_only(tmp_path: Path, capsys) -> None:
    write_frame(tmp_path / "mixed.exr", _direct_gradients_only(_frame()))
    code, out, err = _run([str(tmp_path / "mixed.exr"), "-o", str(tmp_path / "out.exr")], capsys)
    assert code == 0 and np.isfinite(_rgb(tmp_path / "out.exr")).all(), err
    assert _open_exr(tmp_path / "out.exr").header()["gradsep.method"] == "oidn-l1"
    code, _, err = _run([str(tmp_path / "mixed.exr"), "--method", "l1", "-o", str(tmp_path / "l1.exr")], capsys)
    assert code == 2 and "indirect.dx.R" in err and not (tmp_path / "l1.exr").exists()


# ---------------------------------------------------------------------------------------------- the CLI


def _open_exr(path: Path) -> OpenEXR.File:
    return OpenEXR.File(str(path), separate_channels=True)


def _exr_types(path: Path) -> dict[str, np.dtype]:
    return {name: ch.pixels.dtype for name, ch in _open_exr(path).channels().items()}


def _rgb(path: Path) -> np.ndarray:
    channels = _open_exr(path).channels()
    return np.stack([channels[c].pixels for c in "RGB"], -1)


def _run(args: list[str], capsys) -> tuple[int, str, str]:
    code = main(["reconstruct", *args])
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_writes_a_readable_sum(tmp_path: Path, capsys) -> None:
    frame = _frame()
    write_frame(tmp_path / "in.exr", frame)
    code, out, err = _run([str(tmp_path / "in.exr"), "-o", str(tmp_path / "out.exr")], capsys)
    assert code == 0, err
    assert "oidn" in out and "direct" in out and "indirect" in out and len(out.strip().splitlines()) == 1
    types = _exr_types(tmp_path / "out.exr")
    assert set(types) == {"R", "G", "B"} and all(t == np.float32 for t in types.values())
    written = _open_exr(tmp_path / "out.exr")
    want = reconstruct(read_frame(tmp_path / "in.exr"), "oidn-l1").image  # the default for a G-PT frame
    np.testing.assert_allclose(_rgb(tmp_path / "out.exr"), want, rtol=1e-5, atol=1e-7)
    assert written.header()["gradsep.method"] == "oidn-l1"
    assert sorted(os.listdir(tmp_path)) == ["in.exr", "out.exr"]


def test_cli_half_and_layers(tmp_path: Path, capsys) -> None:
    write_frame(tmp_path / "in.exr", _frame())
    out = tmp_path / "out.exr"
    code, _, err = _run([str(tmp_path / "in.exr"), "-o", str(out), "--half", "--layers", "--method", "l2",
                         "--alpha", "0.5"], capsys)
    assert code == 0, err
    types = _exr_types(out)
    want = {"R", "G", "B", *(f"{layer}.{c}" for layer in ("direct", "indirect") for c in "RGB")}
    assert set(types) == want and all(t == np.float16 for t in types.values())
    file = _open_exr(out)
    px = {k: v.pixels.astype(np.float32) for k, v in file.channels().items()}
    assert file.header()["gradsep.method"] == "l2" and file.header()["gradsep.alpha"] == "0.5"
    np.testing.assert_allclose(px["R"], px["direct.R"] + px["indirect.R"], rtol=2e-3, atol=2e-3)


def _bad_input_leaves_output_alone(tmp_path: Path, capsys, source: Path, expect: str) -> None:
    out = tmp_path / "out.exr"
    out.write_bytes(b"previous result")
    before = sorted(os.listdir(tmp_path))
    code, stdout, err = _run([str(source), "-o", str(out)], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gradsep reconstruct: error:") and expect in lines[0]
    assert out.read_bytes() == b"previous result"  # not replaced, not truncated
    assert sorted(os.listdir(tmp_path)) == before  # no temporary file left behind
    out.unlink()
    assert _run([str(source), "-o", str(out)], capsys)[0] == 2
    assert not out.exists()


def test_cli_garbage_file_exits_2(tmp_path: Path, capsys) -> None:
    source = tmp_path / "garbage.exr"
    source.write_bytes(b"not an exr at all " * 50)
    _bad_input_leaves_output_alone(tmp_path, capsys, source, "OpenEXR")


def test_cli_missing_channels_exit_2_naming_them(tmp_path: Path, capsys) -> None:
    channels = _frame(layers=("direct",)).to_channels()
    for name in layer_channels("direct")[6:]:  # drop direct.dy.*
        del channels[name]
    write_exr(tmp_path / "partial.exr", channels)
    _bad_input_leaves_output_alone(tmp_path, capsys, tmp_path / "partial.exr", "direct.dy.R")


def test_cli_truncated_file_exits_2(tmp_path: Path, capsys) -> None:
    write_frame(tmp_path / "full.exr", _frame())
    data = (tmp_path / "full.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    (tmp_path / "full.exr").unlink()
    _bad_input_leaves_output_alone(tmp_path, capsys, tmp_path / "cut.exr", "")


@pytest.mark.parametrize(
    ("extra", "expect"),
    [
        (["--alpha", "0"], "--alpha"),
        (["--alpha", "nan"], "--alpha"),
        (["--method", "network"], "models"),
    ],
)
def test_cli_bad_options_exit_2(tmp_path: Path, capsys, monkeypatch, extra: list[str], expect: str) -> None:
    monkeypatch.setenv("GRADSEP_MODELS", str(tmp_path / "no-models"))
    write_frame(tmp_path / "in.exr", _frame())
    code, _, err = _run([str(tmp_path / "in.exr"), "-o", str(tmp_path / "out.exr"), *extra], capsys)
    assert code == 2 and expect in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out.exr").exists()


def test_cli_missing_input_and_output_folder(tmp_path: Path, capsys) -> None:
    code, _, err = _run([str(tmp_path / "absent.exr"), "-o", str(tmp_path / "out.exr")], capsys)
    assert code == 2 and "absent.exr" in err
    write_frame(tmp_path / "in.exr", _frame())
    code, _, err = _run([str(tmp_path / "in.exr"), "-o", str(tmp_path / "nowhere" / "out.exr")], capsys)
    assert code == 2 and "does not exist" in err


def test_cli_nonfinite_policy(tmp_path: Path, capsys) -> None:
    channels = _frame().to_channels()
    channels["indirect.dx.G"][3, 4] = np.inf
    channels["indirect.dx.G"][5, 6] = np.nan
    write_exr(tmp_path / "inf.exr", channels)  # float32: Inf and NaN survive writing
    code, _, err = _run([str(tmp_path / "inf.exr"), "-o", str(tmp_path / "out.exr")], capsys)
    assert code == 2 and "indirect.dx.G (2)" in err and not (tmp_path / "out.exr").exists()
    code, _, err = _run([str(tmp_path / "inf.exr"), "-o", str(tmp_path / "out.exr"), "--nonfinite", "zero"],
                        capsys)
    assert code == 0 and "warning" in err and "indirect.dx.G (2)" in err
    rgb = _rgb(tmp_path / "out.exr")
    assert np.isfinite(rgb).all() and (rgb >= 0).all()


def test_console_command_end_to_end(tmp_path: Path) -> None:
    """The real `python -m gradsep` process: exit statuses and stderr as a user sees them."""
    write_frame(tmp_path / "in.exr", _frame())
    (tmp_path / "bad.exr").write_bytes(b"\x00" * 100)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    ok = subprocess.run([sys.executable, "-m", "gradsep", "reconstruct", str(tmp_path / "in.exr"), "-o",
                         str(tmp_path / "out.exr")], capture_output=True, text=True, env=env, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert _rgb(tmp_path / "out.exr").shape == (18, 23, 3)
    bad = subprocess.run([sys.executable, "-m", "gradsep", "reconstruct", str(tmp_path / "bad.exr"), "-o",
                          str(tmp_path / "out2.exr")], capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out2.exr").exists()



# ------------------------------------------------------------------------------------ concurrent layers


def _methods_here() -> list[str]:
    from gradsep.model.oidn import available

    shipped_fused = (REPO / "models" / "fused" / "indirect.onnx").is_file()
    return ["l1", "l2", *(["oidn", "oidn-l1"] if available() else []),
            *(["fused"] if available() and shipped_fused else [])]


def _shipped_fused(method: str):
    """The shipped fused models for ``fused`` (its pipelined path: OIDN here, the rest in a worker), else None."""
    from gradsep.model.reconstruct import load_fused

    return load_fused(REPO / "models") if method == "fused" else None


@pytest.mark.parametrize("method", _methods_here())
def test_concurrent_layers_give_the_sequential_result_bit_for_bit(method: str, monkeypatch) -> None:
    spec = table.get(method)
    threaded = spec if spec.schedule != "sequential" else dataclasses.replace(spec, schedule="concurrent")
    frame = _frame(h=40, w=56, noise=0.1)
    models = LoadedModels(fused=_shipped_fused(method))
    with table.registered(threaded):  # the threaded path for every method
        monkeypatch.setenv("GRADSEP_LAYER_THREADS", "1")
        sequential = reconstruct(frame, method, alpha=0.3, models=models)
        monkeypatch.setenv("GRADSEP_LAYER_THREADS", "2")
        concurrent = reconstruct(frame, method, alpha=0.3, models=models)
    assert list(concurrent.layers) == list(sequential.layers) == ["direct", "indirect"]
    for name in sequential.layers:
        np.testing.assert_array_equal(concurrent.layers[name], sequential.layers[name])
    np.testing.assert_array_equal(concurrent.image, sequential.image)
    assert set(concurrent.timings) >= {"direct", "indirect"}


def test_concurrent_layers_run_in_worker_threads_and_keep_errors(monkeypatch) -> None:
    import threading

    seen: set[str] = set()

    class Recording(HalfBase):
        def reconstruct_layer(self, name, layer, features):
            seen.add(threading.current_thread().name)
            return super().reconstruct_layer(name, layer, features)

    monkeypatch.setenv("GRADSEP_LAYER_THREADS", "2")
    result = reconstruct(_frame(), "network", models=LoadedModels(network=Recording()))
    assert seen and all(n.startswith("gradsep-layer") for n in seen)
    np.testing.assert_array_equal(result.layers["direct"], np.clip(_frame().layers["direct"].base * 0.5, 0, None))
    with pytest.raises(RuntimeError, match="shape"):  # a worker's exception reaches the caller unchanged
        reconstruct(_frame(), "network", models=LoadedModels(network=HalfBase(np.zeros((2, 2, 3), np.float32))))



@pytest.mark.parametrize("value", ["0", "-1", "two"])
def test_a_bad_layer_thread_setting_is_named(value: str, monkeypatch) -> None:
    monkeypatch.setenv("GRADSEP_LAYER_THREADS", value)
    with pytest.raises(ValueError, match="GRADSEP_LAYER_THREADS"):
        reconstruct(_frame(), "l2")
