"""SQL of a stream connection's start: where the log and the applied mark stand."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.ingest import FRAME_ID_PREFIX
from app.models import Stream, TelemetryBatch


def applied_marks(session: Session, actuator_pks: list[int]) -> dict[int, tuple[int, str | None]]:
    """(last applied seq, failure) of each of the streams that has a row."""
    rows = session.execute(
        select(Stream.actuator_pk, Stream.last_applied_seq, Stream.failure).where(Stream.actuator_pk.in_(actuator_pks))
    )
    return {int(pk): (int(seq), failure) for pk, seq, failure in rows}


def stream(session: Session, actuator_pk: int) -> Stream | None:
    return session.get(Stream, actuator_pk)


def pending(session: Session, actuator_pk: int, after_seq: int) -> list[tuple[int, str]]:
    """(seq, batch id) of the logged batches after ``after_seq``, in stream order."""
    rows = session.execute(
        select(TelemetryBatch.seq, TelemetryBatch.batch_id)
        .where(TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.seq > after_seq)
        .order_by(TelemetryBatch.seq)
    )
    return [(int(seq), str(bid)) for seq, bid in rows]


def last_frame_id_upto(session: Session, actuator_pk: int, upto_seq: int) -> str | None:
    """The batch id of the last streamed frame at or before ``upto_seq``."""
    return session.scalar(
        select(TelemetryBatch.batch_id)
        .where(
            TelemetryBatch.actuator_pk == actuator_pk,
            TelemetryBatch.seq <= upto_seq,
            TelemetryBatch.batch_id.like(f"{FRAME_ID_PREFIX}%"),
        )
        .order_by(TelemetryBatch.seq.desc())
        .limit(1)
    )
