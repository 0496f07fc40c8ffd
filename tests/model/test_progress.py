"""model/progress.py: the one progress-bar helper (tqdm when wanted and installed, else silent)."""

from __future__ import annotations

import sys

import pytest

from gradsep.model.progress import ProgressBar


def test_disabled_bar_is_a_silent_no_op(capsys: pytest.CaptureFixture[str]) -> None:
    with ProgressBar(10, enabled=False, desc="x") as bar:
        bar.update(3)
        bar.describe("y")
        bar.postfix(loss="0.1")
    assert bar.bar is None and not bar.visible
    assert capsys.readouterr().err == ""


def test_enabled_bar_counts_and_labels(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("tqdm")
    with ProgressBar(10, enabled=True, desc="frames", unit="frame", initial=2) as bar:
        bar.update(3)
        bar.describe("a label longer than sixty characters " + "x" * 60)
        assert bar.visible and bar.bar.n == 5 and len(bar.bar.desc) == 60
    assert "frame" in capsys.readouterr().err


def test_write_goes_to_stderr_with_or_without_a_bar(capsys: pytest.CaptureFixture[str]) -> None:
    ProgressBar(1, enabled=False).write("note one")
    pytest.importorskip("tqdm")
    with ProgressBar(1, enabled=True) as bar:
        bar.write("note two")
    err = capsys.readouterr().err
    assert "note one\n" in err and "note two\n" in err


def test_without_tqdm_the_bar_is_silent(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "tqdm", None)  # importing tqdm now raises ImportError
    bar = ProgressBar(5, enabled=True)
    bar.update()
    bar.close()
    assert bar.bar is None and capsys.readouterr().err == ""
