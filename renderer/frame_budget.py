"""A planned frame's budget as one object: a deadline (``--seconds``) or a sample count (``--spp``), and what must
be left free when the last pass ends (the frame's write, the interpreter's exit, the frame's own check).

The deadline itself (renderer.budget.Deadline: its seconds, the time spent, the time left) and the sizing of
passes to it (renderer.budget.fill_with_filler) are standard-library code tested against a fake clock; this
module adds what needs the frame: the write, predicted by encoding bands of the frame so far.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gradsep.model.errors import CommandError
from gradsep.model.frame import Frame
from gradsep.renderer.budget import Deadline
from gradsep.renderer.passes import Passes, as_frame
from gradsep.renderer.plans import RenderPlan

#: The interpreter's exit after the frame is written (part of the command's wall time), with a margin: before and
#: after the reconstruction libraries are loaded (docs/decisions.md).
EXIT_SECONDS = (0.15, 0.3)
#: The write is predicted from WRITE_BANDS bands spread over the frame's height (content, and so the encoder's
#: cost, differs by region), each of WRITE_ROWS rows per thread of OpenEXR's pool (model.frame.configure_exr_threads:
#: ZIP compresses blocks of 16 rows, one per thread, so a band of one block would time one core), with a margin
#: for a shared machine's swings (WRITE_MARGIN), plus the file's creation, fsync and rename (WRITE_FIXED), and a
#: second measurement near the end (WRITE_REMEASURE).
WRITE_ROWS = 16
WRITE_BANDS = 3
WRITE_MARGIN = 1.35
WRITE_FIXED = 0.05
#: The write is measured again once the time left is below this many predicted writes (the frame's last passes).
WRITE_REMEASURE = 5.0
#: Passes the rest of the frame is expected to take once the plan is chosen (renderer.budget.fill_to_deadline's
#: passes shrink as the deadline nears): each pays the plan's fixed cost per pass.
FINAL_PASSES = 4
#: The most the checkpoint's own cost (primal's kernel, the reconstructions' start-up and work) may take of a
#: ``--seconds`` budget: above it the fallback is rendered with no checkpoint.
PILOT_SHARE = 0.1


def exit_seconds() -> float:
    """The interpreter's predicted exit time (EXIT_SECONDS) given what this process has loaded."""
    return EXIT_SECONDS[1] if "pyoidn" in sys.modules else EXIT_SECONDS[0]


def startup_error(seconds: float, needed: float) -> CommandError:
    return CommandError(f"--seconds {seconds:g} is below this machine's start-up cost: process start, scene load, "
                        f"kernel compile, one 1-spp pass and the write took {needed:.2f} s here; give more time")


def write_seconds(band: Callable[[tuple[slice, slice]], Frame], width: int, height: int, rows: int | None = None,
                  bands: int = WRITE_BANDS, margin: float = WRITE_MARGIN) -> float:
    """Predicted seconds from the last pass's end to the frame on disk: assembling the frame from the passes' sums
    (``band(window)``: the frame of one window of rows), its channels, and their EXR encoding. Each of ``bands``
    bands of ``rows`` rows (default: WRITE_ROWS per thread of OpenEXR's pool) spread over the height is assembled
    and encoded after one untimed warm-up (the first encode in a process pays a one-time set-up), and the time is
    scaled to the frame's height (the encoder and the assembly are linear in the rows)."""
    import OpenEXR

    from gradsep.model.exr_write import encode_exr

    if rows is None:
        rows = WRITE_ROWS * max(1, OpenEXR.global_thread_count())
    rows = max(1, min(rows, height))
    starts = sorted({round(f * (height - rows)) for f in np.linspace(0.0, 1.0, max(1, bands))})
    windows = [(slice(y, y + rows), slice(0, width)) for y in starts]
    encode_exr(band((slice(0, 1), slice(0, width))).to_channels())  # warm-up
    start = time.perf_counter()
    for window in windows:
        encode_exr(band(window).to_channels())
    seconds = time.perf_counter() - start
    return margin * seconds * height / (rows * len(windows)) + WRITE_FIXED


@dataclass
class FrameBudget:
    """What a planned frame may spend: ``deadline`` (``--seconds``; its ``tail``, where an in-process caller gives
    one, replaces the write and the exit) or ``spp`` samples, and what is held back after the last pass.

    The planner binds the frame's passes (:meth:`bind`); the budget then measures the write on the frame so far,
    after its first pass (the start-up check: :meth:`after_first_pass`) and once more near the end, on the
    rendered plan's frame and at the machine's load of that moment."""

    deadline: Deadline | None = None
    spp: int | None = None
    held: float | None = None  # seconds held back for the frame's own check (None: no check)
    write: float = 0.0  # predicted seconds to assemble, encode and write the frame
    #: the plans whose frame would be written: the first pass's, then the rendered one (the write is measured
    #: again only once both are known)
    written: list[RenderPlan] = field(default_factory=list)
    _passes: Passes | None = field(default=None, init=False, repr=False)
    _measured_at: int = field(default=0, init=False)  # the passes' index when the write was measured (0: never)
    _remeasured: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        if (self.deadline is None) == (self.spp is None):
            raise ValueError("give a deadline or a sample count, not both")

    @property
    def seconds(self) -> float | None:
        """``--seconds`` (None with a sample count)."""
        return self.deadline.seconds if self.deadline is not None else None

    @property
    def has_tail(self) -> bool:
        """Whether an in-process caller keeps its own tail (Deadline.tail: nothing to write here)."""
        return self.deadline is not None and self.deadline.tail is not None

    def bind(self, passes: Passes) -> None:
        self._passes = passes

    def checkpoint_allowance(self) -> float:
        """The most seconds the checkpoint's own cost may take (PILOT_SHARE of the budget; no limit with --spp)."""
        return PILOT_SHARE * self.deadline.seconds if self.deadline is not None else math.inf

    def _measure_write(self) -> float:
        passes = self._passes
        assert passes is not None, "bind the frame's passes first"
        self._measured_at = passes.index
        return write_seconds(lambda window: as_frame(passes.frame_result(self.written[-1], window)),
                             passes.loaded.width, passes.loaded.height)

    def reserve(self) -> float:
        """What must be left when the last pass ends: the caller's tail, or the write and the interpreter's exit;
        and the frame's check. The frame's last passes (the plan chosen, a pass since the last measurement) measure
        the write again, at the machine's load of now and on the rendered plan's frame."""
        d = self.deadline
        if d is not None and d.tail is not None:
            return d.tail + (self.held or 0.0)
        passes = self._passes
        if (d is not None and len(self.written) > 1 and not self._remeasured and passes is not None
                and passes.index > self._measured_at and d.left() < WRITE_REMEASURE * self.write):
            self._remeasured = True
            self.write = self._measure_write()
        return self.write + exit_seconds() + (self.held or 0.0)

    def after_first_pass(self, plan: RenderPlan) -> None:
        """The start-up check: one pass of ``plan`` done, its frame must still be writable in time."""
        self.written.append(plan)
        if self.deadline is None:  # a sample count: no deadline to keep
            return
        if self.deadline.tail is None:  # an in-process caller (Deadline.tail) writes nothing: no write to measure
            self.write = self._measure_write()
        if self.deadline.left() < self.reserve():
            raise startup_error(self.deadline.seconds, self.deadline.elapsed() + self.reserve())

    def buys(self, assessment: Any) -> float:
        """The frame's samples if the rest of the budget went to the assessed plan's passes (its fixed cost per
        pass and its marginal cost per sample: renderer.checkpoint.Assessment); ``spp`` with a sample count."""
        if self.deadline is None:
            return float(self.spp)  # type: ignore[arg-type]
        assert self._passes is not None, "bind the frame's passes first"
        usable = self.deadline.left() - self.reserve() - FINAL_PASSES * assessment.pass_seconds
        return self._passes.spp + max(0.0, usable) / assessment.per_sample
