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


# ------------------------------------------------------------------------------------------------ figures

#: The product's packages, whose comments and docstrings say what and why: a measured figure (a timing, a ratio, a
#: percentage, a memory size, a machine's model) goes stale unseen there; it belongs in docs/decisions.md with its
#: date and the command that produced it (issue 52, item 3).
PRODUCT = ("model", "renderer", "service", "training", "evaluation", "gradsep")
_N = r"\d+(?:\.\d+)?"
_LEAD = r"(?<![\w.])"
#: How a quoted measurement reads, unlike a constant's documentation ("the default alpha (0.2)", "a 20 s
#: budget", "TOLERANCE (5 %)"): approximate (``~0.5 s``), signed (``+0.7 %``), a range or a before/after
#: (``1.83-1.94 s``, ``4.4 → 2.0 GiB``), or with decimals.
_MEASURED = rf"(?:[~≈]\s?{_N}|\+{_N}|{_N}\s?(?:-|–|→)\s?~?{_N}|\d+\.\d+)"
_EVIDENCE = r"(?:measured|median|p50|p9\d|RelMSE|took|geometric mean|faster|slower|held-out)"
FIGURE_PATTERNS: dict[str, str] = {
    # a ratio, ``1.3x`` / ``1.3×`` / ``~7x`` / ``4–5×`` (not a size ``2×2`` nor a product ``2 x cap``; a plain
    # doubling ``2x`` is a design word: an upsample, twice a threshold)
    "ratio": rf"{_LEAD}~?(?!2(?:x|\s?×))(?:{_N}\s?(?:-|–)\s?)?{_N}(?:x|\s?×)(?![\w\d])",
    "time": rf"{_LEAD}{_MEASURED}\s?(?:s|ms|µs|us|ns|min|minutes|seconds)\b(?![-/])",
    "percent": rf"{_LEAD}(?:[~≈]\s?{_N}|\+{_N}|{_N}\s?(?:-|–|→)\s?~?{_N})\s?%",
    "memory": rf"{_LEAD}{_MEASURED}\s?(?:[KMGT]i?B|bytes)\b",
    "machine": r"\b(?:Xeon|EPYC|Ryzen|Threadripper|Opteron|Core i\d|Zen ?\d|Sapphire Rapids|Ice Lake|Cascade Lake"
               r"|Skylake|Graviton|Neoverse|Apple M\d)\b",
    # a word that quotes a measurement with a number with decimals on the same line (not ``ε = 0.01``)
    "evidence": rf"(?i:\b{_EVIDENCE}\b.*?(?<!= ){_LEAD}\d+\.\d|(?<!= ){_LEAD}\d+\.\d.*\b{_EVIDENCE}\b)",
}


def comment_and_docstring_lines(source: str) -> list[tuple[int, str]]:
    """(line number, text) of every comment and every line of a module, class or function docstring."""
    import io
    import tokenize

    found = [(tok.start[0], tok.string) for tok in tokenize.generate_tokens(io.StringIO(source).readline)
             if tok.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) \
                    and isinstance(first.value.value, str):
                found += [(first.value.lineno + i, text) for i, text in enumerate(first.value.value.splitlines())]
    return sorted(found)


def figure_kinds(text: str) -> list[str]:
    """The kinds of measured figure one comment or docstring line quotes (empty: none)."""
    return [kind for kind, pattern in FIGURE_PATTERNS.items() if re.search(pattern, text)]


def figure_offenders(files: list[Path]) -> dict[str, list[str]]:
    """Per file, its comment and docstring lines that quote a measured figure (``LINE [kinds]: text``)."""
    out: dict[str, list[str]] = {}
    for path in files:
        for line, text in comment_and_docstring_lines(path.read_text(encoding="utf-8")):
            if kinds := figure_kinds(text):
                out.setdefault(str(path.relative_to(REPO)), []).append(f"{line} {kinds}: {text.strip()}")
    return out


def product_files(folders: tuple[str, ...] = PRODUCT) -> list[Path]:
    return sorted(p for folder in folders for p in (REPO / folder).rglob("*.py"))


@pytest.mark.parametrize("text", [
    "# refinement thread CPU 0.8 s → 1.3-1.4 s", "# about 30,000 page faults and 0.3-0.6 s of kernel time",
    "#: 1.34x faster per layer, +0.7 % RelMSE", "# importing torch takes 1-2 s", "# ran ~7x slower",
    "our first models came out 4–5× too dark", "# (20 ms vs 2-6 ms for one A·p under load)",
    "# peak RSS 4.4 → 2.0 GiB", "# peaks at ~230 MB", "# on this project's Zen 5 CPU",
    "# the 2-core AMD EPYC development machine", "# oidn-l1 p50 2.005 s", "# RelMSE 0.00280 before the split",
    "# costs ~7% per sample", "# its wall time falls 14-25 % with a lower peak RSS", "# made every pass 6x dearer",
    "# sat 0.45 % above every other sampler's mean on two held-out scenes",
])
def test_the_figure_check_finds_measured_figures(text: str) -> None:
    assert figure_kinds(text), text


@pytest.mark.parametrize("text", [
    "#: the default alpha (0.2)", "# a 20 s budget", "TOLERANCE (5 %): a try within it is kept", "within ±5 %",
    "# 2x its threshold", "# nearest 2× upsampling", "# a 1280x720 frame, 2×2 max pools", "# 0 .. 2 x cap - 1",
    "# seconds per pass (s)", "ε = 0.01, on linear radiance: relmse", "# entry: name + 16 bytes",
    "#: the top 0.1 % of the pixels count as outliers", "# 64 KiB, uvicorn's own limit", "#: 4 spp antialiases edges",
    "# the 2-core target", "# BF16 flags (AVX-512 BF16 or AMX)", "# 0.01 s/spp",
])
def test_the_figure_check_leaves_constants_documentation_alone(text: str) -> None:
    assert not figure_kinds(text), (text, figure_kinds(text))


def test_the_figure_check_reads_comments_and_docstrings_only() -> None:
    source = ('"""Module: ~0.5 s a pass."""\nX = "1.3x"  # took 0.4 s\n\n\ndef f():\n    """Line one.\n\n    '
              '1.5x faster."""\n    return "0.8 s"\n')
    lines = comment_and_docstring_lines(source)
    assert [n for n, text in lines if figure_kinds(text)] == [1, 2, 8]
    assert all("X =" not in text and "return" not in text for _, text in lines)


#: The files whose figures this branch moved out (the other product files are being cleaned in parallel).
CLEANED = (*(f"{p}" for p in ("evaluation", "training", "gradsep")),
           *(f"model/{m}.py" for m in ("methods", "commands", "environment", "progress", "allocator", "cleanup",
                                        "onnx_session", "blend_net")))


def test_no_measured_figures_in_the_cleaned_files() -> None:
    files = sorted({p for entry in CLEANED for p in ([REPO / entry] if entry.endswith(".py")
                                                      else (REPO / entry).rglob("*.py"))})
    offenders = figure_offenders(files)
    assert not offenders, "\n".join(f"{f}:{line}" for f, lines in offenders.items() for line in lines)


def test_no_measured_figures_in_product_comments_or_docstrings() -> None:
    offenders = figure_offenders(product_files())
    assert not offenders, "\n".join(f"{f}:{line}" for f, lines in offenders.items() for line in lines)
