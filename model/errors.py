"""The error base class of every user-facing failure, defined once at the bottom of the import graph.

Library modules (renderer, training, service, evaluation) raise :class:`CommandError` (or a subclass) for bad
requests; the ``gradsep`` command line (gradsep/cli.py) catches it and prints one line on stderr with exit
status 2. It lives here, not in the CLI, so that no library module has to import the command line: ``gradsep/``
is the roof and imports the packages, never the other way round. Input-frame problems have their own base,
:class:`model.frame.FrameError` (with an HTTP status and a machine code), which the CLI treats the same way.
"""

from __future__ import annotations

__all__ = ["CommandError"]


class CommandError(Exception):
    """A user-facing failure: printed as one line on stderr, exit status 2."""
