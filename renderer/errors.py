"""The renderer's user-facing error (its own module so that scene loading, the Mitsuba variant choice and the
procedural generator can all raise it without importing each other)."""

from __future__ import annotations

from gradsep.model.errors import CommandError

__all__ = ["SceneError"]


class SceneError(CommandError):
    """A scene that cannot be loaded or rendered by G-PT; the message says why. Printed as one line by the CLI."""
