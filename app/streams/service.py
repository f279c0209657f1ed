"""Rules of a stream rewind.

A batch logged before the input bounds existed (times in epoch milliseconds, ``t=1e300``) makes
every later batch of its stream "stale". A rewind is the recorded way out: it discards every
batch after ``to_seq`` from the log, and, when the estimators had applied one of them, restarts
them from their initial state so that the processor applies batches 1..``to_seq`` again (the
outputs are then those of a run that never saw the discarded batches). Who, when, why and which
batches are kept in ``stream_rewinds``; nothing is discarded silently.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from app.auth import repository as auth_repository
from app.errors import InvalidConfig, NotFound, RewindRefused
from app.fleet import service as fleet
from app.ingest import client_seq_of
from app.models import Actuator, StreamRewind
from app.streams import repository
from estimators.base import worst_status


def rewind(
    session: Session, actuator: Actuator, to_seq: int, reason: str, *, actor: str, key_id: int | None
) -> StreamRewind:
    """Discard the actuator's batches after ``to_seq``; the caller holds the lock on the
    actuator row (as ingest does), and this locks the stream row (as the processor does).

    Raises:
        InvalidConfig: ``to_seq`` is not before the last logged batch, or no reason is given.
        RewindRefused: the estimators must re-apply from the first batch but the log no
            longer holds all of batches 1..``to_seq`` (``LOG_RETENTION_S``).
    """
    if not reason.strip():
        raise InvalidConfig("say why the stream is rewound (reason)")
    if not 0 <= to_seq < actuator.last_logged_seq:
        raise InvalidConfig(
            f"to_seq must be at least 0 and below the last logged seq {actuator.last_logged_seq}"
        )
    stream = repository.stream_for_update(session, actuator.id)
    if stream is None:
        raise NotFound(f"actuator {actuator.actuator_id!r} has no stream")
    applied = stream.last_applied_seq
    reset = applied > to_seq
    if reset and repository.payloads_kept_upto(session, actuator.id, to_seq) != to_seq:
        raise RewindRefused(
            f"the estimators applied batches after seq {to_seq} and must re-apply 1..{to_seq}, but "
            "the telemetry log no longer holds all of them (FLEETHEALTH_LOG_RETENTION_S)"
        )
    discarded = repository.batches_after(session, actuator.id, to_seq)
    record = repository.add_rewind(
        session,
        StreamRewind(
            actuator_pk=actuator.id,
            actor=actor[:200],
            key_id=key_id,
            reason=reason.strip()[:500],
            to_seq=to_seq,
            from_logged_seq=actuator.last_logged_seq,
            from_applied_seq=applied,
            estimators_reset=reset,
            discarded=[
                {
                    "seq": b.seq,
                    "batch_id": b.batch_id,
                    "n_samples": b.n_samples,
                    "t_first_s": b.t_first_s,
                    "t_last_s": b.t_last_s,
                    "received_at": b.received_at.isoformat(),
                    "applied": b.seq <= applied,
                }
                for b in discarded
            ],
        ),
    )
    repository.delete_batches_after(session, actuator.id, to_seq)
    if reset:
        repository.reset_estimators(session, actuator.id)
        stream.last_applied_seq = 0
        stream.last_applied_t_s = None
        stream.rul_t_s = stream.rul_q05_s = stream.rul_q50_s = None
        stream.status = "learning"
    else:
        stream.status = worst_status(repository.estimator_statuses(session, actuator.id))
    stream.failure = None  # the processor tries again; it marks the stream again if the cause stays
    kept = repository.batch_at(session, actuator.id, to_seq)
    actuator.last_logged_seq = to_seq
    actuator.last_logged_t_s = kept.t_last_s if kept is not None else None
    frame = repository.last_frame_id_upto(session, actuator.id, to_seq)
    actuator.last_client_seq = client_seq_of(frame) if frame is not None else None
    session.flush()
    return record


def rewinds(session: Session, actuator: Actuator) -> list[StreamRewind]:
    return repository.rewinds(session, actuator.id)


def actuator_by_name(session: Session, operator: str, tail: str, actuator_id: str, *, lock: bool = False) -> Actuator:
    """The actuator named by operator, tail and id (the CLI's way in)."""
    op = auth_repository.operator_by_name(session, operator)
    if op is None:
        raise NotFound(f"operator {operator!r} not found")
    return fleet.get_actuator(session, op.id, tail, actuator_id, lock=lock)
