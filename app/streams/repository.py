"""SQL of stream rewinds."""

from __future__ import annotations

from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session

from app.models import EstimatorState, Stream, StreamRewind, TelemetryBatch
from app.processing.repository import OUTPUT_MODELS


def stream_for_update(session: Session, actuator_pk: int) -> Stream | None:
    """The stream row, locked against the processor (which claims it the same way)."""
    return session.scalar(select(Stream).where(Stream.actuator_pk == actuator_pk).with_for_update())


def batches_after(session: Session, actuator_pk: int, seq: int) -> list[TelemetryBatch]:
    return list(
        session.scalars(
            select(TelemetryBatch)
            .where(TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.seq > seq)
            .order_by(TelemetryBatch.seq)
        )
    )


def batch_at(session: Session, actuator_pk: int, seq: int) -> TelemetryBatch | None:
    return session.scalar(
        select(TelemetryBatch).where(TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.seq == seq)
    )


def payloads_kept_upto(session: Session, actuator_pk: int, seq: int) -> int:
    """How many of batches 1..seq still hold their payload (retention drops applied ones)."""
    return int(
        session.scalar(
            select(func.count())
            .select_from(TelemetryBatch)
            .where(
                TelemetryBatch.actuator_pk == actuator_pk,
                TelemetryBatch.seq <= seq,
                TelemetryBatch.payload.is_not(None),
            )
        )
        or 0
    )


def last_frame_id_upto(session: Session, actuator_pk: int, seq: int) -> str | None:
    """The batch id of the last streamed frame (``ws-<client_seq>``) at or before ``seq``."""
    return session.scalar(
        select(TelemetryBatch.batch_id)
        .where(
            TelemetryBatch.actuator_pk == actuator_pk,
            TelemetryBatch.seq <= seq,
            TelemetryBatch.batch_id.like("ws-%"),
        )
        .order_by(TelemetryBatch.seq.desc())
        .limit(1)
    )


def delete_batches_after(session: Session, actuator_pk: int, seq: int) -> None:
    session.execute(
        delete(TelemetryBatch).where(TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.seq > seq)
    )


def reset_estimators(session: Session, actuator_pk: int) -> None:
    """Every estimator of the stream back to its initial state, its outputs deleted: with the
    stream's applied mark set back to 0 (by the caller), the processor applies the log again
    from the first batch."""
    for model in OUTPUT_MODELS:
        session.execute(delete(model).where(model.actuator_pk == actuator_pk))
    session.execute(
        update(EstimatorState)
        .where(EstimatorState.actuator_pk == actuator_pk)
        .values(state=None, applied_seq=0, status="learning", reasons=[], diagnosis_t_s=None, diagnosis=None)
    )


def estimator_statuses(session: Session, actuator_pk: int) -> list[str]:
    return list(session.scalars(select(EstimatorState.status).where(EstimatorState.actuator_pk == actuator_pk)))


def add_rewind(session: Session, row: StreamRewind) -> StreamRewind:
    session.add(row)
    session.flush()
    return row


def rewinds(session: Session, actuator_pk: int) -> list[StreamRewind]:
    return list(
        session.scalars(
            select(StreamRewind).where(StreamRewind.actuator_pk == actuator_pk).order_by(StreamRewind.id)
        )
    )
