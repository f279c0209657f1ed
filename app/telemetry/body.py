"""Request bodies of telemetry batches, and the memory a batch request may hold.

A body is read once, as it arrives, and never copied: up to ``body_spool_bytes`` into memory; a
larger one is spooled into an unlinked temporary file (``TMPDIR``) chunk by chunk and mapped
read-only for decoding, so an oversize upload without ``Content-Length`` is refused at
``max_body_bytes`` having held one chunk, not the whole body. A mapped body's pages are file
pages: the kernel may drop them under pressure (and counts them as ``RssFile``, not
``RssAnon``).

:class:`IngestMemory` is the process-wide budget of what batch requests hold in memory:
in-memory bodies and what their decoding and log encoding allocate (each decoder reserves its
bound before it allocates, :class:`app.ingest.DecodeLimits`). A request that cannot have its
share within ``ingest_memory_wait_s`` is answered 503 with ``Retry-After``; one whose share alone
exceeds the budget, 413. So N parallel large uploads hold at most ``ingest_memory_bytes``
between them, plus the mapped bodies.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import mmap
import tempfile
import threading
from collections.abc import Callable
from typing import IO

import pyarrow as pa
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from app.errors import IngestBusy, PayloadTooLarge

#: In-memory body bytes reserved at a time while a body without Content-Length arrives.
_RESERVE_STEP = 64 * 1024
#: A request that held at least this much hands freed memory back to the OS when it ends.
RELEASE_AFTER_BYTES = 16 * 1024 * 1024


class IngestMemory:
    """A budget of bytes shared by every batch request of the process (thread-safe)."""

    def __init__(self, capacity_bytes: int, wait_s: float) -> None:
        self.capacity = capacity_bytes
        self.wait_s = wait_s
        self.held = 0
        self.peak_held = 0
        self._cond = threading.Condition()

    def try_take(self, n: int) -> bool:
        with self._cond:
            if self.held + n > self.capacity:
                return False
            self._take(n)
            return True

    def take(self, n: int) -> None:
        """Take ``n`` bytes, waiting at most ``wait_s`` for other requests to give theirs back.

        Raises:
            PayloadTooLarge: ``n`` exceeds the whole budget (the request can never fit).
            IngestBusy: the budget stayed short for ``wait_s``.
        """
        if n > self.capacity:
            raise PayloadTooLarge(
                f"this batch needs {n} bytes of memory to be taken in, more than the "
                f"{self.capacity} bytes all batch requests may hold (FLEETHEALTH_INGEST_MEMORY_BYTES): split it"
            )
        with self._cond:
            if not self._cond.wait_for(lambda: self.held + n <= self.capacity, timeout=self.wait_s):
                raise IngestBusy(
                    f"the server holds {self.held} of {self.capacity} bytes for batches being taken "
                    f"in (FLEETHEALTH_INGEST_MEMORY_BYTES) and this one needs {n} more: retry later"
                )
            self._take(n)

    def _take(self, n: int) -> None:
        self.held += n
        self.peak_held = max(self.peak_held, self.held)

    def give(self, n: int) -> None:
        with self._cond:
            self.held -= n
            self._cond.notify_all()


class Reservation:
    """One request's share of :class:`IngestMemory`, given back whole by :meth:`close`."""

    def __init__(self, budget: IngestMemory) -> None:
        self.budget = budget
        self.held = 0
        self.total = 0

    def take(self, n: int) -> None:
        """Blocking (call from a worker thread)."""
        if n <= 0:
            return
        self.budget.take(n)
        self.held += n
        self.total += n

    async def take_async(self, n: int) -> None:
        """From the event loop: immediate when the budget has room, else waits in a thread."""
        if n <= 0:
            return
        if self.budget.try_take(n):
            self.held += n
            self.total += n
            return
        await run_in_threadpool(self.take, n)

    def close(self) -> None:
        held, self.held = self.held, 0
        if held:
            self.budget.give(held)


class RequestBody:
    """A body read whole: :attr:`data` is bytes-like (a ``bytearray`` or a read-only map of
    the spool file); :meth:`close` lets it go as soon as it is decoded."""

    def __init__(self, memory: bytearray | None, spool: IO[bytes] | None, size: int) -> None:
        self.size = size
        self._memory = memory
        self._spool = spool
        self._map: mmap.mmap | None = None
        if spool is not None and size:
            spool.flush()
            self._map = mmap.mmap(spool.fileno(), size, access=mmap.ACCESS_READ)

    @property
    def spooled(self) -> bool:
        return self._spool is not None

    @property
    def data(self) -> bytearray | mmap.mmap:
        if self._map is not None:
            return self._map
        return self._memory if self._memory is not None else bytearray()

    def close(self) -> None:
        """Drop the body. Arrays decoded without a copy (Arrow) keep their part of it alive."""
        self._memory = None
        if self._map is not None:
            # Exported to decoded arrays (BufferError): unmapped when they are freed.
            with contextlib.suppress(BufferError):
                self._map.close()
            self._map = None
        if self._spool is not None:
            self._spool.close()
            self._spool = None


def _spool_file() -> IO[bytes]:
    """An unlinked temporary file in ``TMPDIR``, closed by :meth:`RequestBody.close`."""
    return tempfile.TemporaryFile(prefix="fleethealth-body-")  # noqa: SIM115


async def read_body(request: Request, limit: int, spool_bytes: int, reservation: Reservation) -> RequestBody:
    """Read a request body of at most ``limit`` bytes, as described in the module docstring.

    Raises:
        PayloadTooLarge: the declared or the received length exceeds ``limit`` (checked per
            chunk: an oversize body without Content-Length is refused as soon as it passes it).
    """
    declared = request.headers.get("content-length")
    expected = int(declared) if declared is not None and declared.isdigit() else None
    if expected is not None and expected > limit:
        raise PayloadTooLarge(f"body of {declared} bytes exceeds the limit of {limit} bytes")
    in_memory = expected is None or expected <= spool_bytes
    memory: bytearray | None = bytearray() if in_memory else None
    spool: IO[bytes] | None = None if in_memory else _spool_file()
    if memory is not None and expected is not None:
        await reservation.take_async(expected)
        # A body of declared length is read into one buffer of that size, each chunk copied
        # once into its place (appending would grow and copy the buffer as it goes).
        return await _read_declared(request, expected)
    size = 0
    try:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise PayloadTooLarge(f"body exceeds the limit of {limit} bytes")
            if memory is not None and size > spool_bytes:
                # A body without Content-Length outgrew memory: the rest goes to a file.
                spool = _spool_file()
                spool.write(memory)
                memory = None
            if memory is not None:
                if expected is None and size > reservation.held:
                    await reservation.take_async(max(_RESERVE_STEP, size - reservation.held))
                memory += chunk
            else:
                assert spool is not None
                spool.write(chunk)
        return RequestBody(memory, spool, size)
    except BaseException:
        if spool is not None:
            spool.close()
        raise


async def _read_declared(request: Request, expected: int) -> RequestBody:
    """A body of ``expected`` bytes (its Content-Length, within the limits) into memory."""
    memory = bytearray(expected)
    size = 0
    with memoryview(memory) as view:
        async for chunk in request.stream():
            end = size + len(chunk)
            if end > expected:  # more than declared: the server's framing should never let it
                raise PayloadTooLarge(f"body exceeds its declared length of {expected} bytes")
            view[size:end] = chunk
            size = end
    if size < expected:  # the stream ended early (a disconnect is raised by the stream itself)
        del memory[size:]
    return RequestBody(memory, None, size)


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    try:
        trim: Callable[[int], int] = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError, TypeError):  # no libc found, or not glibc (musl has none)
        return None
    return trim


def release_memory() -> None:
    """Hand freed memory back to the OS: Arrow's pool caches, then glibc's free lists
    (``malloc_trim``: without it, the heap a large batch grew stays resident after it is freed)."""
    pa.default_memory_pool().release_unused()
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
