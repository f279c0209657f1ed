"""The hand-over of streamed frames from an event loop to the parse threads and the log writer.

A frame read from a stream connection is parsed and checked in a parse thread (the decoders
release and re-take the GIL: in the event loop each re-take waits behind the busy writer and
processor threads; measured: parsed in the loop, 20 % more server CPU per frame), handed from
there to the log writer, and its outcome (the acknowledgement once committed, or the error that
refused it) comes back to the loop through its :class:`~app.websocket.hub.Inbox`.

:class:`FrameFeed` does this for every stream connection of one loop together: the frames put
during one pass of the loop go to the pool as one job per ``burst`` frames, not one
``Executor.submit`` (a future, its condition and lock, a work item, a thread wake-up) per frame,
and each frame's outcome resolves the loop's own future directly (no thread-side future per
frame). Frames of one connection are put one at a time (the next once this one is
acknowledged), so they reach the log in order; a job parses and hands over its frames in the
order they were put.
"""

from __future__ import annotations

import asyncio
import os
import weakref
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import Any

from app.ingest import ParsedBatch
from app.telemetry.service import Ack, prepare_frame
from app.telemetry.validation import BatchLimits
from app.websocket.hub import Inbox, inbox

#: Frames parsed by one job of the pool: enough that a busy loop's pass is a few jobs, few enough
#: that the pool's threads share a large pass.
BURST = 32

# (raw frame, expected channels, max samples, limits) -> (client_seq, batch)
Prepare = Callable[[str | bytes, Sequence[str], int, BatchLimits], tuple[int, ParsedBatch]]
# (stream, batch) -> the append's future, resolved once committed
Submit = Callable[[int, ParsedBatch], "Future[Ack]"]


class FrameSource:
    """What a frame needs to be parsed and logged: its stream and that stream's rules."""

    __slots__ = ("actuator_pk", "channels", "max_samples", "limits", "submit")

    def __init__(self, actuator_pk: int, channels: Sequence[str], max_samples: int, limits: BatchLimits,
                 submit: Submit) -> None:
        self.actuator_pk = actuator_pk
        self.channels = list(channels)
        self.max_samples = max_samples
        self.limits = limits
        self.submit = submit


_Item = tuple[FrameSource, "str | bytes", "asyncio.Future[tuple[int, Ack]]"]


class FrameFeed:
    """Frames of one event loop's stream connections, parsed and logged in bursts."""

    def __init__(self, loop: asyncio.AbstractEventLoop, pool: Executor, box: Inbox, prepare: Prepare,
                 burst: int = BURST) -> None:
        self.loop = loop
        self.pool = pool
        self.box = box
        self.prepare = prepare
        self.burst = burst
        self._items: list[_Item] = []
        self._scheduled = False

    def put(self, source: FrameSource, data: str | bytes) -> asyncio.Future[tuple[int, Ack]]:
        """Parse and log ``data`` (call it in the loop): resolves with (client_seq, its
        acknowledgement) once committed, or with the error that refused it. Cancelling the
        future leaves the frame alone: once handed over it is logged anyway."""
        out: asyncio.Future[tuple[int, Ack]] = self.loop.create_future()
        self._items.append((source, data, out))
        if not self._scheduled:
            self._scheduled = True
            self.loop.call_soon(self._flush)  # after every task ready in this pass has run
        return out

    def _flush(self) -> None:
        items, self._items = self._items, []
        self._scheduled = False
        for i in range(0, len(items), self.burst):
            part = items[i : i + self.burst]
            try:
                self.pool.submit(self._run, part)
            except RuntimeError as exc:  # the pool is shut down (the server is stopping)
                for _, _, out in part:
                    _settle(out, None, exc)

    def _run(self, items: list[_Item]) -> None:  # in a parse thread
        for source, data, out in items:
            try:
                client_seq, batch = self.prepare(data, source.channels, source.max_samples, source.limits)
                appended = source.submit(source.actuator_pk, batch)
            except BaseException as exc:
                self.box.put(_settle, out, None, exc)
                continue
            appended.add_done_callback(self._answer(client_seq, out))

    def _answer(self, client_seq: int, out: asyncio.Future[tuple[int, Ack]]) -> Callable[[Future[Ack]], None]:
        def appended(done: Future[Ack]) -> None:  # in the log writer's thread
            try:
                self.box.put(_settle, out, (client_seq, done.result()), None)
            except BaseException as exc:
                self.box.put(_settle, out, None, exc)

        return appended


def _settle(out: asyncio.Future[Any], result: Any, exc: BaseException | None) -> None:
    if out.done():  # cancelled: its connection is gone
        return
    if exc is not None:
        out.set_exception(exc)
    else:
        out.set_result(result)


_feeds: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, FrameFeed] = weakref.WeakKeyDictionary()


def frame_feed(loop: asyncio.AbstractEventLoop) -> FrameFeed:
    """The :class:`FrameFeed` of ``loop`` (one per loop, made on first use, in the loop)."""
    feed = _feeds.get(loop)
    if feed is None:
        feed = _feeds[loop] = FrameFeed(loop, parse_pool(), inbox(loop), prepare_frame)
    return feed


_POOL: Executor | None = None


def parse_pool() -> Executor:
    """The threads that parse streamed frames, shared by every connection of the process (made
    on first use; idle threads cost nothing)."""
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1), thread_name_prefix="fleethealth-ws-parse")
    return _POOL
