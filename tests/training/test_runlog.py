"""training/runlog.py: a run folder's log survives a cut last line, its curves are drawn only from records, and
its files are replaced whole."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from gradsep.training.runlog import (  # noqa: E402
    append_log,
    atomic_torch_save,
    atomic_write_text,
    code_version,
    plot_curves,
    read_log,
)


def test_the_log_reads_back_what_was_appended_and_skips_a_cut_last_line(tmp_path: Path) -> None:
    assert read_log(tmp_path) == []
    append_log(tmp_path, {"kind": "step", "step": 1})
    append_log(tmp_path, {"kind": "step", "step": 2})
    with open(tmp_path / "log.jsonl", "a", encoding="utf-8") as fh:
        fh.write('{"kind": "epo')  # a kill while writing
    assert [r["step"] for r in read_log(tmp_path)] == [1, 2]


def test_curves_need_records_and_are_written_from_them(tmp_path: Path) -> None:
    assert plot_curves(tmp_path) is None and not (tmp_path / "losses.png").exists()
    terms = {"data": 1.0, "grad": 0.5, "first": 0.25}
    for step in (1, 2):
        append_log(tmp_path, {"kind": "step", "step": step, **terms})
    append_log(tmp_path, {"kind": "epoch", "epoch": 1, "step": 2, "train": terms, "val": terms, "gbranch": 0.1})
    out = plot_curves(tmp_path)
    assert out == tmp_path / "losses.png" and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (tmp_path / "losses.tmp.png").exists()


def test_atomic_writes_replace_the_file_and_leave_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "config.json"
    atomic_write_text(path, json.dumps({"a": 1}))
    atomic_write_text(path, json.dumps({"a": 2}))
    assert json.loads(path.read_text()) == {"a": 2}
    atomic_torch_save({"w": torch.ones(2)}, tmp_path / "last.pt")
    assert torch.equal(torch.load(tmp_path / "last.pt", weights_only=True)["w"], torch.ones(2))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.json", "last.pt"]


def test_the_code_version_starts_with_the_package_version() -> None:
    from gradsep.model import __version__

    assert code_version().split("+")[0] == __version__
