"""The one progress bar helper: a tqdm bar when tqdm is installed and the bar is wanted, else nothing.

Every long loop (reference passes, dataset frames, training epochs, the evaluation's steps) uses it, so the
rules live once: ``enabled`` True always shows the bar, None shows it only on a terminal (tqdm's own test), False
never; tqdm is optional (an extra of the render/train roles), and without it the loops run silently.
"""

from __future__ import annotations

import sys
from types import TracebackType
from typing import Any

__all__ = ["ProgressBar"]


class ProgressBar:
    """A bar over ``total`` units (``initial`` already done), or a no-op. Use as a context manager or close()."""

    def __init__(self, total: int, *, enabled: bool | None = None, desc: str = "", unit: str = "it",
                 initial: int = 0, leave: bool = True) -> None:
        self.bar: Any = None
        if enabled is False:
            return
        try:
            from tqdm import tqdm
        except ImportError:
            return
        self.bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, leave=leave, dynamic_ncols=True,
                        disable=None if enabled is None else not enabled, file=sys.stderr)

    @property
    def visible(self) -> bool:
        return self.bar is not None and not self.bar.disable

    def update(self, n: int = 1) -> None:
        if self.bar is not None:
            self.bar.update(n)

    def describe(self, text: str) -> None:
        """Replace the bar's label (what is being done now), cut to 60 characters so the bar keeps its room."""
        if self.bar is not None:
            self.bar.set_description_str(text[:60])

    def postfix(self, **values: Any) -> None:
        """Show ``name=value`` pairs after the bar (e.g. the current losses)."""
        if self.bar is not None:
            self.bar.set_postfix(**values)

    def write(self, message: str) -> None:
        """A log line on stderr that does not tear the bar."""
        if self.visible:
            self.bar.write(message, file=sys.stderr)
        else:
            print(message, file=sys.stderr)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()
