"""The admission gate: a capacity limiter plus a bounded waiting room, and the Retry-After a refused client gets.

Why a gate of our own rather than ``anyio.to_thread.run_sync(limiter=...)`` alone: a thread cannot be killed, so
when a request passes its timeout (504) its reconstruction keeps running in the background. anyio would release
the limiter's slot as soon as the waiting request gave up, letting a new inference start beside the abandoned
one and oversubscribing the CPU. Here every job runs in a task of the app's own task group that holds its slot
until the thread really ends; the request only waits for the job's completion event, with a deadline. A job
whose request gave up while it was still queued never starts. Shutdown (the lifespan's task group closing)
waits for running jobs, so in-flight work finishes.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import anyio
from anyio.abc import TaskGroup

from gradsep.service.errors import ServiceError

T = TypeVar("T")


@dataclass(eq=False)
class _Job(Generic[T]):
    fn: Callable[[], T]
    done: anyio.Event = field(default_factory=anyio.Event)
    result: T | None = None
    error: BaseException | None = None
    abandoned: bool = False
    queued_at: float = field(default_factory=time.perf_counter)
    started_at: float | None = None


class DrainMeter:
    """The gate's measured drain rate: jobs finished per second of busy time (time with a job running), over the
    last ``window`` jobs. Busy time, not wall time, so the idle gaps between bursts do not read as a slow queue.
    Only touched on the event loop."""

    def __init__(self, window: int = 16, clock: Callable[[], float] = time.perf_counter) -> None:
        self._clock = clock
        self._busy_before = 0.0  # busy seconds up to the start of the current busy period
        self._busy_since: float | None = None  # start of the current busy period; None while idle
        self._marks: deque[float] = deque([0.0], maxlen=window + 1)  # the busy clock at each finish

    def busy(self) -> float:
        """Seconds the gate has had at least one job running."""
        current = self._clock() - self._busy_since if self._busy_since is not None else 0.0
        return self._busy_before + current

    def started(self, running_before: int) -> None:
        if running_before == 0:
            self._busy_since = self._clock()

    def finished(self, running_after: int) -> None:
        mark = self.busy()
        self._marks.append(mark)
        if running_after == 0:
            self._busy_before, self._busy_since = mark, None

    def rate(self) -> float | None:
        """Jobs per busy second over the window; None until a job has finished."""
        span = self._marks[-1] - self._marks[0]
        return (len(self._marks) - 1) / span if len(self._marks) > 1 and span > 0 else None

    def seconds_to_drain(self, backlog: int, concurrency: int) -> float:
        """Seconds until ``backlog`` admitted jobs are done at the measured rate. Before any job has finished, the
        running jobs' age stands in for a job's duration: a lower bound, so an early client retries soon and
        meets a measured estimate."""
        rate = self.rate()
        if rate is None:
            return backlog * self.busy() / concurrency
        return backlog / rate


class InferenceGate:
    """At most ``concurrency`` jobs run (each in a worker thread); at most ``queue_size`` more wait.

    ``waiting`` and ``running`` are only touched on the event loop, so plain ints are safe. ``running`` counts
    threads until they return, including those whose request already timed out.
    """

    def __init__(self, concurrency: int, queue_size: int, task_group: TaskGroup) -> None:
        self.concurrency, self.queue_size = concurrency, queue_size
        self._slots = anyio.CapacityLimiter(concurrency)
        self._threads = anyio.CapacityLimiter(concurrency)  # our own, so Starlette's thread pool can't starve us
        self._tg = task_group
        self.waiting = 0
        self.running = 0
        self.drain = DrainMeter()

    @property
    def full(self) -> bool:
        return self.waiting + self.running >= self.concurrency + self.queue_size

    def retry_after(self) -> int:
        """Seconds a rejected client should wait: the time to drain what is admitted now, at the measured drain
        rate; whole seconds (HTTP's delta-seconds), rounded, 1 to 60."""
        seconds = self.drain.seconds_to_drain(self.waiting + self.running, self.concurrency)
        return int(min(60, max(1, round(seconds))))

    def queue_full_error(self) -> ServiceError:
        retry = self.retry_after()
        return ServiceError(
            503, "queue_full",
            f"inference queue is full ({self.running} running, {self.waiting} waiting); retry in {retry} s",
            {"running": self.running, "waiting": self.waiting, "queue_size": self.queue_size},
            headers={"Retry-After": str(retry)})

    async def run(self, fn: Callable[[], T], timeout: float) -> tuple[T, float]:
        """Run ``fn`` in a worker thread; return (result, seconds spent queued). 503 if full, 504 on timeout."""
        if self.full:
            raise self.queue_full_error()
        job: _Job[T] = _Job(fn)
        self.waiting += 1
        self._tg.start_soon(self._execute, job)
        try:
            with anyio.fail_after(timeout):
                await job.done.wait()
        except TimeoutError:
            job.abandoned = True
            state = "still running in the background" if job.started_at is not None else "never started"
            raise ServiceError(
                504, "timeout", f"inference did not finish within {timeout:g} s (the job {state})",
                {"timeout_seconds": timeout, "started": job.started_at is not None}) from None
        finally:
            job.abandoned = job.abandoned or not job.done.is_set()  # the request was cancelled (disconnect)
        if job.error is not None:
            raise job.error
        assert job.started_at is not None
        return job.result, job.started_at - job.queued_at  # type: ignore[return-value]

    async def _execute(self, job: _Job[Any]) -> None:
        queued = True
        try:
            async with self._slots:
                self.waiting -= 1
                queued = False
                if job.abandoned:
                    return
                job.started_at = time.perf_counter()
                self.drain.started(self.running)
                self.running += 1
                try:
                    job.result = await anyio.to_thread.run_sync(job.fn, limiter=self._threads)
                except Exception as exc:  # handed to the waiting request, which re-raises it
                    job.error = exc
                finally:
                    self.running -= 1
                    self.drain.finished(self.running)
        finally:
            if queued:
                self.waiting -= 1
            job.done.set()
