"""The error classes of every user-facing failure, defined once at the bottom of the import graph.

Library modules (renderer, training, service, evaluation) raise :class:`CommandError` (or a subclass) for bad
requests; the ``gradsep`` command line (gradsep/cli.py) catches it and prints one line on stderr with exit
status 2. It lives here, not in the CLI, so that no library module has to import the command line: ``gradsep/``
is the roof and imports the packages, never the other way round. Input-frame problems have their own base,
:class:`FrameError`: each subclass carries the HTTP status and stable code the service answers with (which the
service maps without a table), and the CLI treats them as it treats a CommandError.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ChannelError", "CommandError", "FrameError", "FrameTooLargeError", "NonFiniteError", "NotExrError",
           "UnsupportedExrError"]


class CommandError(Exception):
    """A user-facing failure: printed as one line on stderr, exit status 2."""


class FrameError(ValueError):
    """Base of every problem with an input frame. ``details`` names channels or limits where it can."""

    status: int = 400
    code: str = "bad_frame"

    def __init__(self, message: str, details: Any = None) -> None:
        super().__init__(message)
        self.message = message
        self.details = details


class NotExrError(FrameError):
    """Not an OpenEXR file, or a corrupt or truncated one."""

    status, code = 400, "not_exr"


class UnsupportedExrError(FrameError):
    """A valid OpenEXR file of a kind the contract excludes: multi-part, tiled, deep, subsampled, integer."""

    status, code = 400, "unsupported_exr"


class FrameTooLargeError(FrameError):
    """The header declares more pixels or values than the reader's budget; decided before decoding."""

    status, code = 413, "too_large"


class ChannelError(FrameError):
    """Missing, unknown or inconsistent channels, or no illumination layer. ``details`` lists the channels."""

    status, code = 422, "bad_channels"


class NonFiniteError(FrameError):
    """NaN or Inf in radiance or gradients under the ``reject`` policy. ``details`` maps channel to count."""

    status, code = 422, "non_finite"

