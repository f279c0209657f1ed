"""Rules of a stream connection: where a (re)connecting client resumes, and the results it
missed."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

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


def read_keys(db: Database, keys: dict[tuple[int, str], Principal]) -> dict[tuple[int, str], DomainError | None]:
    """Re-read every (key id, scope) in one transaction: the refusal each produces now
    (``Unauthorized``, ``Forbidden``), None while the key is still good."""
    out: dict[tuple[int, str], DomainError | None] = {}
    with db.read() as s:
        for (key_id, scope), principal in keys.items():
            try:
                recheck(s, principal, scope)
                out[(key_id, scope)] = None
            except DomainError as exc:
                out[(key_id, scope)] = exc
    return out


def applied_marks(db: Database, actuator_pks: list[int]) -> dict[int, tuple[int, str | None]]:
    """The applied mark and failure of each stream (streams with none yet are left out)."""
    with db.read() as s:
        return repository.applied_marks(s, actuator_pks)


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
