"""The telemetry log: durable, idempotent, ordered append of batches."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

import numpy as np
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.codec import encode_columns
from app.errors import IdempotencyConflict, StaleBatch
from app.ingest import TIME_COLUMN, ParsedBatch, client_seq_of
from app.models import Actuator, TelemetryBatch


@dataclass(frozen=True)
class Ack:
    actuator_pk: int
    batch_id: str
    seq: int
    n_samples: int
    t_first_s: float
    t_last_s: float
    received_at: datetime
    replayed: bool

    def body(self) -> dict[str, object]:
        return {
            "batch_id": self.batch_id,
            "seq": self.seq,
            "n_samples": self.n_samples,
            "t_first_s": self.t_first_s,
            "t_last_s": self.t_last_s,
            "received_at": self.received_at.isoformat(),
        }


def _ack(row: TelemetryBatch, replayed: bool) -> Ack:
    return Ack(
        actuator_pk=row.actuator_pk,
        batch_id=row.batch_id,
        seq=row.seq,
        n_samples=row.n_samples,
        t_first_s=row.t_first_s,
        t_last_s=row.t_last_s,
        received_at=row.received_at,
        replayed=replayed,
    )


def find_batch(session: Session, actuator_pk: int, batch_id: str) -> TelemetryBatch | None:
    return session.scalar(
        select(TelemetryBatch).where(
            TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.batch_id == batch_id
        )
    )


def append(session: Session, actuator: Actuator, batch: ParsedBatch) -> Ack:
    """Append ``batch`` to the actuator's log. The caller holds the lock on the actuator row.

    A ``batch_id`` seen before returns the first acknowledgement and appends nothing; the same id
    with different samples is a conflict.
    """
    digest = batch.content_hash()
    prior = find_batch(session, actuator.id, batch.batch_id)
    if prior is not None:
        if prior.content_hash != digest:
            raise IdempotencyConflict(
                f"batch_id {batch.batch_id!r} was already used for different samples (seq {prior.seq})"
            )
        return _ack(prior, replayed=True)
    t_first = float(batch.t_s[0])
    if actuator.last_logged_t_s is not None and t_first <= actuator.last_logged_t_s:
        raise StaleBatch(
            f"batch starts at t={t_first!r} s, not after the stream's last sample at "
            f"t={actuator.last_logged_t_s!r} s (seq {actuator.last_logged_seq}); batches must "
            "follow each other in time"
        )
    seq = actuator.last_logged_seq + 1
    payload = encode_columns({TIME_COLUMN: batch.t_s, **batch.channels})
    row = TelemetryBatch(
        actuator_pk=actuator.id,
        seq=seq,
        batch_id=batch.batch_id,
        content_hash=digest,
        n_samples=batch.n_samples,
        t_first_s=t_first,
        t_last_s=float(batch.t_s[-1]),
        payload=payload,
    )
    try:
        with session.begin_nested():
            session.add(row)
            session.flush()
    except IntegrityError:
        # Another writer logged the same batch_id between our look-up and insert.
        raise IdempotencyConflict(
            f"batch_id {batch.batch_id!r} is being logged concurrently; retry"
        ) from None
    actuator.last_logged_seq = seq
    actuator.last_logged_t_s = float(batch.t_s[-1])
    client_seq = client_seq_of(batch.batch_id)
    if client_seq is not None:
        actuator.last_client_seq = max(actuator.last_client_seq or 0, client_seq)
    session.flush()
    return _ack(row, replayed=False)


def float_or_none(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)
