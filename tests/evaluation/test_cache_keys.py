"""The evaluation cache keys code by what it does: comments, docstrings and formatting do not invalidate a
farm's cached frames and references, any change to the code does."""

from __future__ import annotations

from pathlib import Path

from gradsep.evaluation.cache import code_sha256, sources_sha256
from gradsep.evaluation.run import REFERENCE_SOURCES, RENDERER_SOURCES

MODULE = '''"""A module."""

def shade(x):
    """Twice x."""
    return 2 * x  # doubled
'''


def test_docstrings_comments_and_formatting_do_not_change_the_code_hash() -> None:
    edited = ('"""A module, documented at length."""\n\n\n'
              "def shade(x):\n    '''Twice x, said differently.'''\n    # a new comment\n    return 2*x\n")
    assert code_sha256(edited) == code_sha256(MODULE)
    no_docstring = "def shade(x):\n    return 2 * x\n"
    assert code_sha256(no_docstring) == code_sha256(MODULE)


def test_any_change_to_the_code_changes_the_hash() -> None:
    for changed in (MODULE.replace("2 * x", "3 * x"), MODULE.replace("shade", "tint"),
                    MODULE + "\nLIMIT = 4\n", MODULE.replace("return 2 * x", "y = 2 * x\n    return y")):
        assert code_sha256(changed) != code_sha256(MODULE), changed
    # a string that is not a docstring is code
    assert code_sha256(MODULE.replace("return 2 * x", '"note"\n    return 2 * x')) != code_sha256(MODULE)


def test_a_file_that_is_not_python_is_hashed_as_bytes() -> None:
    assert code_sha256(b"def (:\n") != code_sha256(b"def (: \n")


def test_the_generator_is_keyed_by_its_version_not_its_source() -> None:
    # renderer/procedural.py holds every family: a new family must not invalidate another's cached frames;
    # tests/renderer/test_procedural.py pins what each version generates instead
    assert "renderer/procedural.py" not in RENDERER_SOURCES + REFERENCE_SOURCES
    assert len(sources_sha256(RENDERER_SOURCES)) == 64


def test_fused_results_are_keyed_by_the_network_model_its_clean_layer_average_reads(tmp_path: Path) -> None:
    """fused reads models/direct.onnx on clean direct layers (model/fused.py CLEAN_AVERAGE): a new network model
    must recompute fused's results, and a models folder without it must still run fused (nothing missing)."""
    from gradsep.evaluation.config import EvalConfig
    from gradsep.evaluation.methods import evaluated_methods
    from gradsep.evaluation.run import _Runner

    models = tmp_path / "models"
    (models / "fused").mkdir(parents=True)
    (models / "fused" / "indirect.onnx").write_bytes(b"blend")
    config = EvalConfig(scenes=("cbox",), spp=(1,), width=12, height=10, ref_spp=2, output=tmp_path / "report",
                        cache_dir=tmp_path / "cache", models_dir=models, methods=("fused",), seed=0, max_depth=None,
                        alpha=0.2, table_spp=None, quick=False, ref_spp_cap=8, ref_seconds=None)
    fused = next(m for m in evaluated_methods() if m.name == "fused")

    def shas() -> dict[str, str]:
        files, missing = _Runner(config, False, lambda m: None).model_files(fused, ("direct", "indirect"))
        assert missing == []
        return files

    without = shas()
    assert set(without) == {"fused/indirect.onnx"}
    (models / "direct.onnx").write_bytes(b"network v1")
    first = shas()
    assert set(first) == {"fused/indirect.onnx", "direct.onnx"}
    (models / "direct.onnx").write_bytes(b"network v2")
    assert shas()["direct.onnx"] != first["direct.onnx"]
    assert _Runner(config, False, lambda m: None).model_files(fused, ("indirect",))[0] == without  # no direct layer


def test_the_renderer_key_holds_every_module_a_frame_is_rendered_with() -> None:
    """Every renderer/ module that renderer/render.py's G-PT path imports (renderer/gpt.py, renderer/shift.py and
    what they import, transitively) is in RENDERER_SOURCES: a change in any of them must invalidate cached frames.
    The procedural generator is keyed by its version instead (above)."""
    import ast

    root = Path(__file__).resolve().parents[2]
    seen: set[str] = set()
    todo = ["renderer/gpt.py", "renderer/shift.py"]
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        for node in ast.walk(ast.parse((root / path).read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("gradsep.renderer."):
                module = "renderer/" + node.module.split(".", 2)[2].replace(".", "/") + ".py"
                if not module.startswith("renderer/procedural"):
                    todo.append(module)
    assert seen - set(RENDERER_SOURCES) == set()
