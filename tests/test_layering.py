"""The import layering of docs/architecture.md, checked on the source (every import, lazy ones inside functions
included, parsed with ast -- nothing is imported):

* ``model/`` is the ground floor: it imports none of renderer/, training/, service/, evaluation/, gradsep/;
* ``gradsep/`` is the roof: no library module imports it (the error base class and the version live in model/);
* every package's ``commands.py`` imports only the standard library and the import-light ``model.errors`` /
  ``model.policy`` at module level, so building the parser needs neither numpy, torch, mitsuba nor FastAPI.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LIBRARY = ("model", "renderer", "training", "service", "evaluation")
ABOVE_MODEL = ("renderer", "training", "service", "evaluation", "gradsep")
COMMAND_MODULE_ALLOWED = ("model.errors", "model.policy")


def _is_main_block(node: ast.stmt) -> bool:
    """``if __name__ == "__main__":`` -- a script entry point, not part of the module's import graph."""
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Compare) and isinstance(test.left, ast.Name) and test.left.id == "__name__"
            and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in test.comparators))


def imports(source: str, *, main_block: bool = True) -> list[tuple[str, int, bool]]:
    """(imported module, line, at module level?) for every import statement in ``source``, lazy ones included
    (``main_block=False`` leaves out the ``if __name__ == "__main__":`` block). ``from a import b`` yields ``a``
    and ``a.b`` (b may be a submodule); relative imports are not used here."""
    tree = ast.parse(source)
    top_level = {id(node) for node in tree.body}
    if not main_block:
        tree.body = [node for node in tree.body if not _is_main_block(node)]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno, id(node) in top_level) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.append((node.module, node.lineno, id(node) in top_level))
            found += [(f"{node.module}.{alias.name}", node.lineno, id(node) in top_level) for alias in node.names]
    return found


def package_files(package: str) -> list[Path]:
    return sorted((REPO / package).rglob("*.py"))


def violations(package: str, forbidden: tuple[str, ...]) -> list[str]:
    out = []
    for path in package_files(package):
        for name, line, _ in imports(path.read_text()):
            if name.split(".")[0] in forbidden:
                out.append(f"{path.relative_to(REPO)}:{line} imports {name}")
    return sorted(set(out))


def test_the_checker_sees_lazy_and_from_imports():
    """The checks below can fail: a lazy import inside a function and a from-import are both found."""
    source = "import os\nfrom model.frame import Frame\n\ndef f():\n    from gradsep.cli import main\n    return main\n"
    found = imports(source)
    assert ("gradsep.cli", 5, False) in found and ("model.frame", 2, True) in found and ("os", 1, True) in found


def module_imports() -> dict[str, set[str]]:
    """Library + CLI module name -> every module it imports (lazy ones included, script entry blocks not)."""
    out = {}
    for package in (*LIBRARY, "gradsep"):
        for path in package_files(package):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
            out[name] = {n for n, _, _ in imports(path.read_text(), main_block=False)}
    return out


def test_no_two_modules_import_each_other():
    """An import loop (even through lazy imports) means neither module can be read or tested alone; the
    scene/procedural loop (renderer.variant and renderer.errors now hold what both need) must not come back."""
    graph = module_imports()
    mutual = {tuple(sorted((a, b))) for a, deps in graph.items() for b in deps
              if b in graph and b != a and a in graph[b]}
    assert mutual == set()


#: Who may import whom, package by package (docs/architecture.md draws it). gradsep/ loads the packages'
#: commands.py through importlib (by name), which an import statement does not show.
ALLOWED_LAYERS = {
    "model": set(),
    "renderer": {"model"},
    "training": {"model"},
    "service": {"model"},
    "evaluation": {"model", "renderer"},
    "gradsep": {"model"},
}


def test_packages_import_only_the_layers_below_them():
    graph = module_imports()
    found: dict[str, set[str]] = {package: set() for package in ALLOWED_LAYERS}
    for module, deps in graph.items():
        package = module.split(".")[0]
        found[package] |= {d.split(".")[0] for d in deps if d.split(".")[0] in ALLOWED_LAYERS} - {package}
    extra = {package: sorted(found[package] - allowed) for package, allowed in ALLOWED_LAYERS.items()
             if found[package] - allowed}
    assert extra == {}


def test_model_imports_no_package_above_it():
    assert violations("model", ABOVE_MODEL) == []


@pytest.mark.parametrize("package", LIBRARY)
def test_no_library_module_imports_the_command_line(package: str):
    assert violations(package, ("gradsep",)) == []


@pytest.mark.parametrize("path", sorted(p for package in LIBRARY for p in [REPO / package / "commands.py"]
                                        if p.is_file()), ids=lambda p: p.parent.name)
def test_command_modules_are_import_light_at_module_level(path: Path):
    heavy = [f"{name} (line {line})" for name, line, top in imports(path.read_text())
             if top and name.split(".")[0] not in sys.stdlib_module_names
             and name not in COMMAND_MODULE_ALLOWED and not name.startswith(tuple(f"{m}." for m in
                                                                                   COMMAND_MODULE_ALLOWED))]
    assert heavy == [], f"{path.relative_to(REPO)} imports at module level: {', '.join(heavy)}"


def test_every_library_package_has_a_command_module():
    """The CLI's COMMAND_MODULES are exactly the library packages' commands.py (none forgotten, none extra)."""
    from gradsep.cli import COMMAND_MODULES

    assert sorted(COMMAND_MODULES) == sorted(f"{p}.commands" for p in LIBRARY if (REPO / p / "commands.py").is_file())
    assert len(COMMAND_MODULES) == len(LIBRARY)
