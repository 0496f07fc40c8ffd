"""A command that fails before doing any work leaves nothing behind, so the corrected retry just works.

:func:`undone_on_failure` wraps the start of a command that creates files under a folder (a training run folder,
a dataset folder): if the block raises before the command marks its first real result with ``keep()``, every
file and folder it created there is removed again -- the folder itself when it did not exist -- and what was
there before is left exactly as it was. Without it a failed start (e.g. ``gradsep train`` refusing a dataset whose
frames are smaller than the patch) leaves a run folder that then refuses the corrected command as "a different
run".
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path


class Guard:
    """Handed to the block: ``keep()`` once the command has produced something worth keeping."""

    def __init__(self) -> None:
        self.kept = False

    def keep(self) -> None:
        self.kept = True


def _entries(folder: Path) -> set[str]:
    """Every file and folder under ``folder``, as paths relative to it."""
    found: set[str] = set()
    for parent, dirs, files in os.walk(folder):
        rel = os.path.relpath(parent, folder)
        found.update(os.path.normpath(os.path.join(rel, name)) for name in (*dirs, *files))
    return found


def _remove_new(folder: Path, before: set[str]) -> None:
    """Remove what is under ``folder`` now and was not before (deepest first); never what was there."""
    for rel in sorted(_entries(folder) - before, key=lambda p: p.count(os.sep), reverse=True):
        path = folder / rel
        with contextlib.suppress(FileNotFoundError):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink()


@contextlib.contextmanager
def undone_on_failure(folder: str | os.PathLike[str], enabled: bool = True) -> Iterator[Guard]:
    """If the block raises (any exception, ^C included) before ``guard.keep()``, remove what it created under
    ``folder``. ``enabled=False`` (e.g. a non-zero rank of a distributed run) makes it a no-op."""
    folder = Path(folder)
    guard = Guard()
    existed = folder.exists()
    before = _entries(folder) if existed and folder.is_dir() else set()
    try:
        yield guard
    except BaseException:
        if enabled and not guard.kept:
            if not existed:
                shutil.rmtree(folder, ignore_errors=True)
            elif folder.is_dir():
                _remove_new(folder, before)
        raise
