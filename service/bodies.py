"""Request bodies held within a bound: one byte pool shared by every open upload, and bodies that spill to disk.

A raw body is read into a :class:`SpooledBody`. Its bytes stay in memory while the app's :class:`BytePool`
(``GRADSEP_BODY_MEMORY_BYTES``) grants them; a body the pool cannot hold moves to a temporary file in
``GRADSEP_SPOOL_DIR`` and goes on there. The pool is never overdrawn, so the bytes held in memory for request
bodies, across all open uploads, never pass the setting; bodies over ``GRADSEP_MAX_BODY_BYTES`` are cut off by the
body-limit middleware as they cross it, on disk or in memory. A body whose Content-Length the pool cannot grant
at once starts on disk (no copy out of memory later).

The pool is shared by the event loop (uploads) and the worker threads (a finished or abandoned job closes its
body), hence its lock.
"""

from __future__ import annotations

import io
import tempfile
import threading
from collections.abc import AsyncIterable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import anyio

from gradsep.service.errors import ServiceError

#: Retry-After of a body that could not be spooled (a full or missing spool folder clears on an operator's time).
SPOOL_RETRY_SECONDS = 30


@dataclass
class Upload:
    """A request's frame as a seekable stream, its size, and how to let it go (idempotent, any thread)."""

    file: BinaryIO
    size: int
    close: Callable[[], None]


class BytePool:
    """A count of bytes that never passes ``capacity``: :meth:`take` grants all of a request or nothing."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.held = 0
        self.peak = 0  # the most ever held at once (for tests and metrics)
        self._lock = threading.Lock()

    def take(self, n: int) -> bool:
        with self._lock:
            if self.held + n > self.capacity:
                return False
            self.held += n
            self.peak = max(self.peak, self.held)
            return True

    def give(self, n: int) -> None:
        with self._lock:
            self.held -= n


class SpooledBody:
    """One request body: in memory while the pool grants its bytes, else in an unnamed temporary file.

    ``file`` is the body as a seekable binary stream (what the frame reader takes). :meth:`close` returns the
    pool's bytes and deletes the file; it is idempotent and may run in any thread.
    """

    def __init__(self, pool: BytePool, spool_dir: Path | None = None, declared: int | None = None) -> None:
        self.pool, self.spool_dir = pool, spool_dir
        self.size = 0
        self.file: BinaryIO = io.BytesIO()
        self._held = 0  # bytes of the pool this body holds
        self._reserved = 0  # of those, granted up front for a declared Content-Length and not yet written
        self._to_disk = False  # memory is no longer tried for this body
        self._on_disk = False  # ``file`` is the temporary file
        self._closed = False
        self._lock = threading.Lock()
        if declared and pool.take(declared):
            self._held = self._reserved = declared
            self.file = _presized(declared)
        elif declared:
            self._to_disk = True  # the file is opened by the first write, off the event loop

    @property
    def on_disk(self) -> bool:
        return self._on_disk

    async def write(self, chunk: bytes) -> None:
        if not chunk:
            return
        if not self._to_disk and self._grant(len(chunk)):
            self.file.write(chunk)
        else:
            try:
                if not self._on_disk:
                    await self._spill()
                await anyio.to_thread.run_sync(self.file.write, chunk)
            except OSError as exc:  # the spool folder is full or gone: the server's trouble, not the client's
                raise ServiceError(503, "spool_failed", f"the request body could not be spooled to disk "
                                   f"({exc.strerror or exc}); retry later", None,
                                   {"Retry-After": str(SPOOL_RETRY_SECONDS)}) from None
        self.size += len(chunk)

    def _grant(self, n: int) -> bool:
        """Pool bytes for ``n`` more bytes in memory: from the up-front reservation, else from the pool."""
        from_reservation = min(n, self._reserved)
        self._reserved -= from_reservation
        if n == from_reservation or self.pool.take(n - from_reservation):
            self._held += n - from_reservation
            return True
        self._reserved += from_reservation
        return False

    async def _spill(self) -> None:
        """Move the body to a temporary file and give its memory back to the pool."""
        memory = self.file
        target = await anyio.to_thread.run_sync(self._temporary_file)
        try:
            with memory.getbuffer() as view, view[:self.size] as written:  # type: ignore[attr-defined]
                await anyio.to_thread.run_sync(target.write, written)  # a presized buffer may be longer
        except BaseException:
            target.close()
            raise
        self.file, self._on_disk, self._to_disk = target, True, True
        memory.close()
        self._release()

    def _temporary_file(self) -> BinaryIO:
        folder = str(self.spool_dir) if self.spool_dir is not None else None
        return tempfile.TemporaryFile(prefix="gradsep-body-", dir=folder)  # unnamed: gone when closed

    def finish(self) -> None:
        """The body is complete: unused reservation back to the pool, the stream at its start."""
        with self._lock:
            if self._reserved:
                self.pool.give(self._reserved)
                self._held -= self._reserved
                self._reserved = 0
        if not self._on_disk:
            self.file.truncate(self.size)  # a presized buffer longer than what came
        self.file.seek(0)

    def _release(self) -> None:
        with self._lock:
            held, self._held, self._reserved = self._held, 0, 0
        if held:
            self.pool.give(held)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._release()
        self.file.close()


def _presized(size: int) -> io.BytesIO:
    """An empty in-memory stream whose buffer already holds ``size`` bytes: a body written into it in chunks is
    not copied again each time the buffer grows (BytesIO grows by an eighth)."""
    buffer = io.BytesIO()
    buffer.seek(size - 1)
    buffer.write(b"\0")
    buffer.seek(0)
    return buffer


async def read_body(stream: AsyncIterable[bytes], pool: BytePool, spool_dir: Path | None,
                    declared: int | None) -> SpooledBody:
    """The whole body of ``stream`` as a :class:`SpooledBody` (closed again if reading it fails)."""
    body = SpooledBody(pool, spool_dir, declared)
    try:
        async for chunk in stream:
            await body.write(chunk)
        body.finish()
    except BaseException:
        body.close()
        raise
    return body
