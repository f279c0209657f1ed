"""Rules of a stream connection: where a (re)connecting client resumes, and the results it
missed."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Final

from app.auth.service import Principal, authenticate, recheck
from app.db import Database
from app.errors import DomainError
from app.fleet import service as fleet
from app.ingest import client_seq_of
from app.processing import repository as processing_repository
from app.processing.service import applied_results
from app.websocket import repository


@dataclass(frozen=True)
class StreamStart:
    """What a connection announces in its ``ready`` message, and the frames it still owes
    results for (logged before a dropped connection, not applied yet)."""

    actuator_pk: int
    channels: list[str]
    last_client_seq: int | None
    last_applied_client_seq: int | None
    last_logged_seq: int
    last_applied_seq: int
    failure: str | None
    pending: list[tuple[int, int | None]]


def authenticate_key(db: Database, authorization: str) -> Principal:
    with db.read() as s:
        return authenticate(s, authorization)


def recheck_key(db: Database, principal: Principal, scope: str) -> None:
    """Raise Unauthorized / Forbidden when the key was revoked or lost ``scope``."""
    with db.read() as s:
        recheck(s, principal, scope)


class _Stale:
    """No reading of the key young enough: read it again."""


STALE: Final = _Stale()


class KeyChecks:
    """The latest reading of each (key, scope) an open WebSocket depends on, shared by every
    connection of the process: a thousand connections of one key cost one read per
    ``max_age_s``, not a thousand. A reading is the refusal it produced (``Unauthorized``,
    ``Forbidden``) or None while the key is still good.

    :meth:`cached` runs in the event loop (no I/O); :meth:`read` in a worker thread, at most
    one at a time per key and scope (the others wait for it and take its reading).
    """

    def __init__(self, db: Database, max_age_s: float) -> None:
        self.db = db
        self.max_age_s = max_age_s
        self._seen: dict[tuple[int, str], tuple[float, DomainError | None]] = {}
        self._locks: dict[tuple[int, str], threading.Lock] = {}
        self._guard = threading.Lock()

    def cached(self, principal: Principal, scope: str) -> DomainError | None | _Stale:
        hit = self._seen.get((principal.key_id, scope))
        if hit is None or time.monotonic() - hit[0] >= self.max_age_s:
            return STALE
        return hit[1]

    def read(self, principal: Principal, scope: str) -> DomainError | None:
        key = (principal.key_id, scope)
        with self._guard:
            lock = self._locks.setdefault(key, threading.Lock())
        with lock:
            hit = self._seen.get(key)
            if hit is not None and time.monotonic() - hit[0] < self.max_age_s:
                return hit[1]  # read by another connection while this one waited
            try:
                recheck_key(self.db, principal, scope)
                refusal: DomainError | None = None
            except DomainError as exc:
                refusal = exc
            now = time.monotonic()
            with self._guard:
                self._seen[key] = (now, refusal)
                # Keys no connection asked about for a while (closed ones) are forgotten.
                for old in [k for k, (at, _) in self._seen.items() if now - at > 20 * self.max_age_s]:
                    self._seen.pop(old, None)
                    self._locks.pop(old, None)
            return refusal


def stream_start(db: Database, principal: Principal, tail: str, actuator_id: str) -> StreamStart:
    with db.read() as s:
        act = fleet.get_actuator(s, principal.operator_id, tail, actuator_id)
        st = repository.stream(s, act.id)
        applied = st.last_applied_seq if st is not None else 0
        last_frame = repository.last_frame_id_upto(s, act.id, applied)
        return StreamStart(
            actuator_pk=act.id,
            channels=list(act.channels),
            last_client_seq=act.last_client_seq,
            last_applied_client_seq=client_seq_of(last_frame) if last_frame else None,
            last_logged_seq=act.last_logged_seq,
            last_applied_seq=applied,
            failure=st.failure if st is not None else None,
            pending=[(seq, client_seq_of(bid)) for seq, bid in repository.pending(s, act.id, applied)],
        )


def missed_results(
    db: Database, actuator_pk: int, seqs: list[int]
) -> tuple[list[dict[str, Any]], str | None]:
    """``result`` messages of those of ``seqs`` already applied, read back from the store, and
    why the stream is no longer applied (None while it is)."""
    with db.read() as s:
        applied, failure = processing_repository.applied_mark(s, actuator_pk)
        done = [q for q in seqs if q <= applied]
        return [r.message() for r in applied_results(s, actuator_pk, done)], failure
