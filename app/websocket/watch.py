"""The periodic checks of open WebSockets, one per process (per event loop) instead of one per
connection: a thousand connections cost one timer and one database reading per interval, not a
thousand timers and a thousand readings.

* :class:`KeyGuard` re-reads the key of every open WebSocket (each key and scope once) and ends
  the connections whose key was revoked or lost the scope they need.
* :class:`ResultSweep` finds the stream connections waiting for a result that is already in the
  store (a wake-up lost: another process applied the batch and its notification did not arrive)
  and tells only those to read it back.

Each runs as one task of the loop while it has members, and stops with the last.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Hashable
from typing import Any, Generic, TypeVar

from sqlalchemy.exc import SQLAlchemyError
from starlette.concurrency import run_in_threadpool

from app.auth.service import Principal
from app.db import Database
from app.errors import DomainError
from app.websocket import service
from app.websocket.hub import Subscription

log = logging.getLogger("fleethealth.stream")
M = TypeVar("M", bound=Hashable)


class _Periodic(Generic[M]):
    """Members of one event loop, looked at together every ``interval_s`` by :meth:`_check`
    (in the loop; a task that runs while there are members)."""

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self.loop = asyncio.get_running_loop()
        self.members: set[M] = set()
        self._task: asyncio.Task[None] | None = None

    def _add(self, member: M) -> None:
        self.members.add(member)
        if self._task is None or self._task.done():
            self._task = self.loop.create_task(self._run())

    def _discard(self, member: M) -> None:
        self.members.discard(member)
        if not self.members and self._task is not None:
            self._task.cancel()  # no timer outlives the last connection
            self._task = None

    async def _run(self) -> None:
        while self.members:
            await asyncio.sleep(self.interval_s)
            try:
                await self._check()
            except SQLAlchemyError as exc:  # the database is unreachable now: look again later
                log.warning("%s could not read the database: %s", type(self).__name__, type(exc).__name__)
            except Exception:  # one bad round must not end the checks of every connection
                log.exception("%s failed; looking again in %.1f s", type(self).__name__, self.interval_s)

    async def _check(self) -> None:
        raise NotImplementedError


class KeyWatch:
    """One connection's watch on its key: :attr:`refused` resolves with the refusal once the
    key is revoked or lacks ``scope``."""

    def __init__(self, principal: Principal, scope: str) -> None:
        self.principal = principal
        self.scope = scope
        self.refused: asyncio.Future[DomainError] = asyncio.get_running_loop().create_future()


class KeyGuard(_Periodic[KeyWatch]):
    """Re-reads, every ``interval_s``, each (key, scope) that an open WebSocket of the loop
    depends on, all in one transaction in one worker thread. Reading the database (not an
    in-process notice) makes a revocation by any process, or by the CLI, count."""

    def __init__(self, db: Database, interval_s: float) -> None:
        super().__init__(interval_s)
        self.db = db

    def watch(self, principal: Principal, scope: str) -> KeyWatch:
        w = KeyWatch(principal, scope)
        self._add(w)
        return w

    def unwatch(self, w: KeyWatch) -> None:
        self._discard(w)

    async def _check(self) -> None:
        keys = {(w.principal.key_id, w.scope): w.principal for w in self.members}
        if not keys:
            return
        refusals = await run_in_threadpool(service.read_keys, self.db, keys)
        for w in list(self.members):
            refusal = refusals.get((w.principal.key_id, w.scope))
            if refusal is not None and not w.refused.done():
                w.refused.set_result(refusal)
                self.members.discard(w)


class ResultSweep(_Periodic[Subscription]):
    """Every ``interval_s``, the applied marks of the streams whose connections wait for a
    result, read in one query; a connection whose awaited batch is applied (or whose stream is
    failed) without its result having reached it is told to read it back (its subscription
    marked stale). The pushes of this process and the notifications of others make this a
    rare fallback: it only bounds how long a lost wake-up can hold a result back."""

    def __init__(self, db: Database, interval_s: float) -> None:
        super().__init__(interval_s)
        self.db = db
        # subscription -> the stream and the batch its connection waits for (None: none)
        self.waiting: dict[Subscription, Callable[[], tuple[int, int] | None]] = {}

    def add(self, sub: Subscription, waiting_for: Callable[[], tuple[int, int] | None]) -> None:
        self.waiting[sub] = waiting_for
        self._add(sub)

    def discard(self, sub: Subscription) -> None:
        self.waiting.pop(sub, None)
        self._discard(sub)

    async def _check(self) -> None:
        heads = {sub: head for sub, f in self.waiting.items() if (head := f()) is not None}
        if not heads:
            return
        marks = await run_in_threadpool(service.applied_marks, self.db, sorted({pk for pk, _ in heads.values()}))
        for sub, (pk, seq) in heads.items():
            applied, failure = marks.get(pk, (0, None))
            if applied >= seq or failure is not None:
                sub.mark_stale()


P = TypeVar("P", bound=_Periodic[Any])


def per_loop(state: object, name: str, make: Callable[[], P]) -> P:
    """The instance kept on ``state`` (the app's) for the running loop, made on first use."""
    cur: P | None = getattr(state, name, None)
    if cur is None or cur.loop is not asyncio.get_running_loop():
        cur = make()
        setattr(state, name, cur)
    return cur
