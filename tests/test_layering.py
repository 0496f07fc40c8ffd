"""The import layering of docs/architecture.md, checked on the source (every import, lazy ones inside functions
included, parsed with ast -- nothing is imported):

* ``gradsep.model`` (``model/``) is the ground floor: it imports none of the renderer, training, service,
  evaluation packages or the command line;
* the command line (``gradsep.cli``) is the roof: no library module imports it (the error base class and the
  version live in ``gradsep.model``);
* every package's ``commands.py`` imports only the standard library and the import-light ``gradsep.model.errors``,
  ``gradsep.model.policy`` and ``gradsep.model.methods`` at module level, so building the parser needs neither
  numpy, torch, mitsuba nor FastAPI;
* no import cycle of any length (strongly connected components of the module graph).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: The library's folders; each installs as ``gradsep.<folder>`` (setup.py).
LIBRARY = ("model", "renderer", "training", "service", "evaluation")
#: The command line's modules (the gradsep/ folder): the roof of the graph.
CLI = "cli"
ABOVE_MODEL = ("renderer", "training", "service", "evaluation", CLI)
#: Standard-library-only modules of the contract's names (errors, policy, methods, channel layouts) a parser may read.
COMMAND_MODULE_ALLOWED = ("gradsep.model.errors", "gradsep.model.policy", "gradsep.model.methods",
                          "gradsep.model.channels")


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


def layer_of(module: str) -> str | None:
    """The layer a dotted module name belongs to: ``gradsep.model.frame`` -> ``model``, ``gradsep.cli`` and
    ``gradsep`` itself -> ``cli``; None for anything outside gradsep."""
    parts = module.split(".")
    if parts[0] != "gradsep":
        return None
    return parts[1] if len(parts) > 1 and parts[1] in LIBRARY else CLI


def module_name(path: Path) -> str:
    """The installed dotted name of a source file: ``model/frame.py`` -> ``gradsep.model.frame``."""
    return "gradsep." + ".".join(path.relative_to(REPO).with_suffix("").parts).removeprefix("gradsep.") \
        .removesuffix(".__init__")


def violations(package: str, forbidden: tuple[str, ...]) -> list[str]:
    out = []
    for path in package_files(package):
        for name, line, _ in imports(path.read_text()):
            if layer_of(name) in forbidden and name != "gradsep":
                out.append(f"{path.relative_to(REPO)}:{line} imports {name}")
    return sorted(set(out))


def test_the_checker_sees_lazy_and_from_imports():
    """The checks below can fail: a lazy import inside a function and a from-import are both found."""
    source = ("import os\nfrom gradsep.model.frame import Frame\n\n"
              "def f():\n    from gradsep.cli import main\n    return main\n")
    found = imports(source)
    assert ("gradsep.cli", 5, False) in found and ("gradsep.model.frame", 2, True) in found
    assert ("os", 1, True) in found


def module_imports() -> dict[str, set[str]]:
    """Library + CLI module name -> every module it imports: lazy ones and those of a script entry block
    (``if __name__ == "__main__":``) included -- ``python -m`` / ``torchrun -m`` runs that block, and a cycle
    through it is a cycle all the same."""
    out = {}
    for package in (*LIBRARY, "gradsep"):
        for path in package_files(package):
            out[module_name(path)] = {n for n, _, _ in imports(path.read_text())}
    return out


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every import cycle, as the strongly connected components of more than one module (or a module importing
    itself), found with Tarjan's algorithm (iterative: no recursion limit). Edges to modules outside ``graph`` are
    ignored; a package's ``__init__`` counts as the package name."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(d for d in graph[root] if d in graph)))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(d for d in graph[child] if d in graph))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1 or node in graph[node]:
                    components.append(sorted(component))
    return sorted(components)


def test_the_cycle_finder_sees_cycles_of_any_length():
    """A three-module cycle (no two of its modules import each other directly), a self-import and a pair are
    all found; an acyclic graph with a diamond has none."""
    three = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a", "os"}}
    assert import_cycles(three) == [["a", "b", "c"]]
    assert import_cycles({"a": {"a"}, "b": set()}) == [["a"]]
    assert import_cycles({"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"e"}, "e": {"c"}}) == [["a", "b"],
                                                                                         ["c", "d", "e"]]
    assert import_cycles({"a": {"b", "c"}, "b": {"d"}, "c": {"d"}, "d": set()}) == []


def test_the_layering_check_fails_on_a_three_module_cycle(tmp_path: Path):
    """The module-graph check itself (source parsed as in the repository) fails on a synthetic package whose
    three modules import each other in a ring."""
    ring = {"x": "y", "y": "z", "z": "x"}
    graph = {f"gradsep.toy.{a}": {n for n, _, _ in imports(f"from gradsep.toy.{b} import thing\n")}
             for a, b in ring.items()}
    assert import_cycles(graph) == [["gradsep.toy.x", "gradsep.toy.y", "gradsep.toy.z"]]


def test_the_layering_check_sees_a_cycle_through_a_script_entry_block(tmp_path: Path):
    """A module whose ``if __name__ == "__main__":`` block imports the command module that lazily imports it back
    (the shape of a ``torchrun -m`` entry) is a cycle: the graph of the repository's files keeps that block."""
    package = tmp_path / "toy"
    package.mkdir()
    (package / "train.py").write_text("def train():\n    return 0\n\n\nif __name__ == \"__main__\":\n"
                                      "    from gradsep.toy.commands import main\n    main()\n")
    (package / "commands.py").write_text("def main():\n    from gradsep.toy.train import train\n"
                                         "    return train()\n")
    graph = {f"gradsep.toy.{p.stem}": {n for n, _, _ in imports(p.read_text())} for p in package.glob("*.py")}
    assert import_cycles(graph) == [["gradsep.toy.commands", "gradsep.toy.train"]]
    without_entry = {f"gradsep.toy.{p.stem}": {n for n, _, _ in imports(p.read_text(), main_block=False)}
                     for p in package.glob("*.py")}
    assert import_cycles(without_entry) == []  # what the check missed while it left entry blocks out


def test_no_import_cycles():
    """An import cycle of any length (even through lazy imports) means none of its modules can be read or tested
    alone. A package imports its ``__init__``, which is left out: importing ``gradsep.model.frame`` runs
    ``gradsep/__init__`` and ``model/__init__`` first by Python's rules, not by a cycle of ours."""
    graph = module_imports()
    packages = {m for m in graph if any(other.startswith(m + ".") for other in graph)}
    graph = {m: {d for d in deps if d not in packages and d != m} for m, deps in graph.items() if m not in packages}
    assert import_cycles(graph) == []


#: Who may import whom, package by package (docs/architecture.md draws it). gradsep/ loads the packages'
#: commands.py through importlib (by name), which an import statement does not show.
ALLOWED_LAYERS = {
    "model": set(),
    "renderer": {"model"},
    "training": {"model"},
    "service": {"model"},
    "evaluation": {"model", "renderer"},
    CLI: {"model"},
}


def test_packages_import_only_the_layers_below_them():
    graph = module_imports()
    found: dict[str, set[str]] = {package: set() for package in ALLOWED_LAYERS}
    for module, deps in graph.items():
        package = layer_of(module)
        found[package] |= {layer_of(d) for d in deps if d != "gradsep" and layer_of(d) in ALLOWED_LAYERS} - {package}
    extra = {package: sorted(found[package] - allowed) for package, allowed in ALLOWED_LAYERS.items()
             if found[package] - allowed}
    assert extra == {}


def test_model_imports_no_package_above_it():
    assert violations("model", ABOVE_MODEL) == []


@pytest.mark.parametrize("package", LIBRARY)
def test_no_library_module_imports_the_command_line(package: str):
    assert violations(package, (CLI,)) == []


def test_the_allowed_modules_are_themselves_standard_library_only():
    for module in COMMAND_MODULE_ALLOWED:
        path = REPO / "model" / f"{module.rsplit('.', 1)[1]}.py"
        heavy = [name for name, _, top in imports(path.read_text()) if top
                 and name.split(".")[0] not in sys.stdlib_module_names and name not in COMMAND_MODULE_ALLOWED
                 and not name.startswith(tuple(f"{m}." for m in COMMAND_MODULE_ALLOWED))]
        assert heavy == [], f"{module} imports at module level: {', '.join(heavy)}"


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

    assert sorted(COMMAND_MODULES) == sorted(f"gradsep.{p}.commands" for p in LIBRARY
                                             if (REPO / p / "commands.py").is_file())
    assert len(COMMAND_MODULES) == len(LIBRARY)
