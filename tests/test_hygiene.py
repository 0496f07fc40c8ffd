"""The repository's shape (issue 37): benchmarks/ holds maintained benchmarks that the tests never import, and the
README stays a short page for users, not a research log.

Cheap on purpose (ast and glob over the checkout, one ``--help`` per benchmark), so it runs in every suite.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = REPO / "benchmarks"
README_LIMIT = 12_000
#: What a research log leaves in a README: design or round numbers, session numbers, ISO dates.
LOG_PATTERNS = (r"\bdesigns? \d+", r"\brounds? \d+", r"\bsessions? \d+", r"\b\d{4}-\d{2}-\d{2}\b")


def benchmark_imports(source: str) -> list[str]:
    """How a Python source reaches benchmarks/: ``import benchmarks.x``, ``from benchmarks ...``, or a string that
    is a path into it (``"benchmarks"``, ``"benchmarks/study_x.py"``: a sys.path insert or an importlib load)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.split(".")[0] == "benchmarks"]
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "benchmarks":
            found.append(node.module)
        elif (isinstance(node, ast.Constant) and isinstance(node.value, str)
              and re.fullmatch(r"benchmarks(/\S*)?", node.value)):
            found.append(node.value)  # a path into benchmarks/: a sys.path insert or a file loaded by importlib
    return found


def log_lines(text: str) -> list[str]:
    """The lines of ``text`` that carry a design/round/session number or an ISO date."""
    return [line for line in text.splitlines() if any(re.search(p, line, re.IGNORECASE) for p in LOG_PATTERNS)]


def test_no_test_module_imports_from_benchmarks() -> None:
    offenders = {str(path.relative_to(REPO)): found for path in sorted((REPO / "tests").rglob("*.py"))
                 if path.resolve() != Path(__file__).resolve()
                 and (found := benchmark_imports(path.read_text(encoding="utf-8")))}
    assert not offenders, offenders


def test_the_import_check_finds_each_way_of_reaching_benchmarks() -> None:
    assert benchmark_imports("from benchmarks.bench_service import synthetic_frame\n")
    assert benchmark_imports("import benchmarks.study_x as s\n")
    assert benchmark_imports("import importlib.util\n"
                             "spec = importlib.util.spec_from_file_location('m', 'benchmarks/study_x.py')\n")
    assert benchmark_imports("import sys\nfrom pathlib import Path\n"
                             "sys.path.insert(0, str(Path(__file__).parents[2] / \"benchmarks\"))\n")
    assert not benchmark_imports("from gradsep.model.synthetic import synthetic_frame\n")


def test_benchmarks_hold_no_studies_or_ab_probes() -> None:
    studies = sorted(p.name for p in BENCHMARKS.iterdir() if p.name.startswith(("study_", "ab_")))
    assert not studies, f"{studies}: record the study in docs/decisions.md and delete it from benchmarks/"


def test_benchmarks_import_only_gradsep_and_libraries() -> None:
    """A kept benchmark reaches the product through ``gradsep.*``: no sys.path inserts, no importing a sibling."""
    siblings = {p.stem for p in BENCHMARKS.glob("*.py")}
    for path in sorted(BENCHMARKS.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and ast.unparse(node.func) == "sys.path.insert":
                pytest.fail(f"{path.name}: sys.path.insert ({ast.unparse(node)})")
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                top = name.split(".")[0]
                assert top not in siblings | {"benchmarks", "model", "renderer", "service", "training",
                                              "evaluation"}, f"{path.name} imports {name}"


def test_every_benchmark_is_documented_in_its_readme() -> None:
    readme = (BENCHMARKS / "README.md").read_text(encoding="utf-8")
    missing = [p.name for p in sorted(BENCHMARKS.glob("*.py")) if p.name not in readme]
    assert not missing, f"benchmarks/README.md does not describe {missing}"


@pytest.mark.parametrize("script", sorted(p.name for p in BENCHMARKS.glob("*.py")))
def test_each_benchmark_parses_its_arguments(script: str) -> None:
    """``--help`` imports the script and builds its parser: a renamed product function breaks it here."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, str(BENCHMARKS / script), "--help"], capture_output=True, text=True,
                          timeout=120, env=env, cwd=REPO)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "usage:" in done.stdout


def test_the_readme_is_short_and_no_research_log() -> None:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    assert len(text) <= README_LIMIT, f"README.md has {len(text)} characters (at most {README_LIMIT})"
    assert not log_lines(text), log_lines(text)


def test_the_log_check_finds_design_round_session_numbers_and_dates() -> None:
    assert log_lines("rejected as design 27 was")
    assert log_lines("since Round 3 of the solver")
    assert log_lines("measured in session 19")
    assert log_lines("on 2026-12-04 at 16:54")
    assert not log_lines("the design: direct and indirect layers, 3 rounds of tests, 1280x720 at 16 spp")


def heading_anchors(markdown: str) -> set[str]:
    """GitHub's anchors of a Markdown file's headings: lower case, punctuation dropped, spaces to hyphens."""
    anchors = set()
    in_code = False
    for line in markdown.splitlines():
        if line.startswith("```"):
            in_code = not in_code
        elif not in_code and (m := re.match(r"#{1,6} (.*)", line)):
            anchors.add(re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-"))
    return anchors


def broken_links(path: Path) -> list[str]:
    """The relative links of a Markdown file whose file or heading anchor does not exist."""
    text = path.read_text(encoding="utf-8")
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto: not checked offline
        file, _, anchor = target.partition("#")
        resolved = (path.parent / file).resolve() if file else path
        if not resolved.exists():
            broken.append(target)
        elif anchor and resolved.suffix == ".md" and anchor not in heading_anchors(resolved.read_text("utf-8")):
            broken.append(target)
    return broken


def test_the_anchor_rule_is_githubs() -> None:
    assert heading_anchors("# The `oidn-l1` method\n## Runtime (2-core CPU)\n```\n# not a heading\n```\n") == {
        "the-oidn-l1-method", "runtime-2-core-cpu"}


@pytest.mark.parametrize("doc", ["README.md", "benchmarks/README.md",
                                 *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md"))])
def test_every_relative_link_resolves(doc: str) -> None:
    assert not broken_links(REPO / doc), broken_links(REPO / doc)
