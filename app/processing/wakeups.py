"""Wake-ups, applied marks and fleet events across processes: PostgreSQL ``LISTEN/NOTIFY``.

Two channels per database and schema (:func:`channels`):

* ``logged``: sent by the log writer in each append transaction, ``"<origin> pk,pk,..."``; worker
  processes (and API processes running the processor) wake those streams;
* ``applied``: sent by the processor in each apply transaction, one JSON object per stream,
  ``{"o": origin, "pk": ..., "seq": last applied seq, "ev": [fleet events]}``, or
  ``{"o": origin, "pk": ..., "failure": reason}`` when it marks a stream failed; API processes
  resolve their ``?wait=`` waiters, wake the stream's WebSocket connections (which read their
  results back from the store) and relay the fleet events to their subscribers.

A notification is sent when its transaction commits and only then, so nobody hears of a batch or
an apply that is not durable, and nothing has to be written twice (to the database and to a
broker). A process ignores its own notifications (it has told its hub directly). Notifications
are not durable: a listener that reconnects calls ``on_resync`` (the processor's scan and the
waiters' re-read cover whatever was missed).
"""

from __future__ import annotations

import hashlib
import logging
import os
import socket
import threading
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import orjson
import psycopg
from sqlalchemy.engine import make_url

from app.db import Database
from app.processing import repository

log = logging.getLogger("fleethealth.wakeups")

ORIGIN = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
RECONNECT_MAX_S = 5.0


@dataclass(frozen=True)
class Channels:
    logged: str
    applied: str


def channels(db: Database) -> Channels:
    """This database and schema's channel names (PostgreSQL channels are per database: tenants
    of other schemas on the same server must not hear each other)."""
    with db.read() as s:
        scope = repository.notification_scope(s)
    tag = hashlib.sha1(scope.encode()).hexdigest()[:12]
    return Channels(logged=f"fleethealth_logged_{tag}", applied=f"fleethealth_applied_{tag}")


def libpq_url(database_url: str) -> str:
    """The SQLAlchemy URL as libpq takes it (no driver suffix)."""
    return make_url(database_url).set(drivername="postgresql").render_as_string(hide_password=False)


class Listener:
    """A thread holding one autocommit connection that LISTENs and dispatches notifications."""

    def __init__(
        self,
        database_url: str,
        chans: Channels,
        *,
        on_logged: Callable[[Sequence[int]], None] | None = None,
        on_applied: Callable[[int, int, list[dict[str, Any]], bool], None] | None = None,
        on_failed: Callable[[int, str], None] | None = None,
        on_resync: Callable[[], object] | None = None,
        origin: str = ORIGIN,
    ) -> None:
        self.url = libpq_url(database_url)
        self.chans = chans
        self.on_logged = on_logged
        self.on_applied = on_applied
        self.on_failed = on_failed
        self.on_resync = on_resync
        self.origin = origin
        self.listening = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="fleethealth-listener", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self) -> None:
        delay = 0.1
        first = True
        while not self._stop.is_set():
            try:
                with psycopg.connect(self.url, autocommit=True) as conn:
                    wanted = [c for c, cb in ((self.chans.logged, self.on_logged),
                                              (self.chans.applied, self.on_applied or self.on_failed)) if cb]
                    repository.listen(conn, wanted)
                    self.listening.set()
                    if not first and self.on_resync is not None:
                        self.on_resync()
                    first = False
                    delay = 0.1
                    while not self._stop.is_set():
                        for n in conn.notifies(timeout=0.5):
                            self._dispatch(n.channel, n.payload)
            except Exception:
                self.listening.clear()
                if self._stop.is_set():
                    return
                log.exception("notification listener lost its connection; reconnecting in %.1f s", delay)
                self._stop.wait(delay)
                delay = min(delay * 2, RECONNECT_MAX_S)

    def _dispatch(self, channel: str, payload: str) -> None:
        try:
            if channel == self.chans.logged:
                origin, _, pks = payload.partition(" ")
                if origin != self.origin and self.on_logged is not None and pks:
                    self.on_logged([int(p) for p in pks.split(",")])
                return
            dispatch_applied(payload, self.origin, self.on_applied, self.on_failed)
        except Exception:
            log.exception("bad notification on %s: %.200s", channel, payload)


def dispatch_applied(
    payload: str | bytes,
    origin: str,
    on_applied: Callable[[int, int, list[dict[str, Any]], bool], None] | None,
    on_failed: Callable[[int, str], None] | None,
) -> None:
    """Hand one payload of the applied channel (``Processor._announcements``) to its callback:
    ``on_applied(pk, seq, events, wake)``, ``wake`` false when the stream's results were sent
    ahead (``"r": 1``, SQLite's apply process); ``on_failed(pk, reason)``. Ignored when sent by
    ``origin``, this process."""
    doc = orjson.loads(payload)
    if doc.get("o") == origin:
        return
    if "failure" in doc:
        if on_failed is not None:
            on_failed(int(doc["pk"]), str(doc["failure"]))
    elif on_applied is not None:
        on_applied(int(doc["pk"]), int(doc["seq"]), list(doc.get("ev") or []), not doc.get("r"))
