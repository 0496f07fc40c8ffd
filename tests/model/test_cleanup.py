"""model/cleanup.py: a failed start removes exactly what it created, a kept one or a disabled guard nothing."""

from __future__ import annotations

from pathlib import Path

import pytest

from gradsep.model.cleanup import undone_on_failure


def _tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _make(folder: Path) -> None:
    (folder / "cache" / "direct").mkdir(parents=True, exist_ok=True)
    (folder / "cache" / "direct" / "a.npy").write_bytes(b"x")
    (folder / "old" / "new.txt").parent.mkdir(parents=True, exist_ok=True)
    (folder / "old" / "new.txt").write_text("new")


def test_a_folder_it_created_is_removed(tmp_path: Path) -> None:
    with pytest.raises(KeyboardInterrupt), undone_on_failure(tmp_path / "run"):
        _make(tmp_path / "run")
        raise KeyboardInterrupt
    assert not (tmp_path / "run").exists()


def test_in_an_existing_folder_only_new_entries_go(tmp_path: Path) -> None:
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "kept.txt").write_text("kept")
    with pytest.raises(ValueError), undone_on_failure(tmp_path):
        _make(tmp_path)
        raise ValueError("refused")
    assert _tree(tmp_path) == ["old", "old/kept.txt"]


def test_kept_or_disabled_or_successful_blocks_leave_everything(tmp_path: Path) -> None:
    with pytest.raises(ValueError), undone_on_failure(tmp_path / "a") as guard:
        _make(tmp_path / "a")
        guard.keep()
        raise ValueError("after the first result")
    with pytest.raises(ValueError), undone_on_failure(tmp_path / "b", enabled=False):
        _make(tmp_path / "b")
        raise ValueError("another rank's folder")
    with undone_on_failure(tmp_path / "c"):
        _make(tmp_path / "c")
    for name in "abc":
        assert _tree(tmp_path / name) == ["cache", "cache/direct", "cache/direct/a.npy", "old", "old/new.txt"]
