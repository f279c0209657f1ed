"""The telemetry log: durable, idempotent, ordered append of batches.

:func:`log_batch` holds the rules and is the one way into the log, for REST batches
(:func:`ingest_body`) and streamed frames (:func:`ingest_frame`). Both return only once their
append is committed, by the log writer's group commit (:mod:`app.telemetry.writer`): an
acknowledgement means the batch is durable.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from app.codec import encode_columns
from app.db import Database
from app.errors import IdempotencyConflict, StaleBatch
from app.fleet import service as fleet
from app.ingest import TIME_COLUMN, ParsedBatch, TimeParams, client_seq_of, parse_body, parse_frame
from app.models import Actuator, TelemetryBatch
from app.telemetry import repository
from app.telemetry.body import RELEASE_AFTER_BYTES, RequestBody, Reservation, release_memory
from app.telemetry.validation import DEFAULT_LIMITS, BatchLimits, check_batch, decoding_guard
from app.telemetry.writer import LogWriter


@dataclass(frozen=True)
class Ack:
    actuator_pk: int
    batch_id: str
    seq: int
    n_samples: int
    t_first_s: float
    t_last_s: float
    received_at: datetime
    end_of_run: bool
    replayed: bool

    def body(self) -> dict[str, object]:
        return {
            "batch_id": self.batch_id,
            "seq": self.seq,
            "n_samples": self.n_samples,
            "t_first_s": self.t_first_s,
            "t_last_s": self.t_last_s,
            "end_of_run": self.end_of_run,
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
        end_of_run=row.end_of_run,
        replayed=replayed,
    )


def log_batch(session: Session, actuator: Actuator, batch: ParsedBatch) -> Ack:
    """Append ``batch`` to the actuator's log. The caller holds the lock on the actuator row.

    A ``batch_id`` seen before returns the first acknowledgement and appends nothing; the same
    id with different samples (or another end-of-run marker) is a conflict. A streamed frame
    must come after the last logged frame (``client_seq``), and every batch after the stream's
    last sample in time.
    """
    digest = batch.content_hash()
    prior = repository.batch_by_id(session, actuator.id, batch.batch_id)
    if prior is not None:
        if prior.content_hash != digest:
            raise IdempotencyConflict(
                f"batch_id {batch.batch_id!r} was already used for different samples (seq {prior.seq})"
            )
        return _ack(prior, replayed=True)
    client_seq = client_seq_of(batch.batch_id)
    last_client_seq = actuator.last_client_seq or 0
    if client_seq is not None and client_seq <= last_client_seq:
        raise StaleBatch(
            f"client_seq {client_seq} is not after the last logged frame ({last_client_seq}); "
            "resume after the last_client_seq the server announced"
        )
    t_first = float(batch.t_s[0])
    if actuator.last_logged_t_s is not None and t_first <= actuator.last_logged_t_s:
        raise StaleBatch(
            f"batch starts at t={t_first!r} s, not after the stream's last sample at "
            f"t={actuator.last_logged_t_s!r} s (seq {actuator.last_logged_seq}); batches must "
            "follow each other in time"
        )
    seq = actuator.last_logged_seq + 1
    row = TelemetryBatch(
        actuator_pk=actuator.id,
        seq=seq,
        batch_id=batch.batch_id,
        content_hash=digest,
        n_samples=batch.n_samples,
        t_first_s=t_first,
        t_last_s=float(batch.t_s[-1]),
        end_of_run=batch.end_of_run,
        payload=encode_columns({TIME_COLUMN: batch.t_s, **batch.channels}),
    )
    if not repository.add_batch(session, row):
        # Another writer logged the same batch_id between our look-up and insert.
        raise IdempotencyConflict(f"batch_id {batch.batch_id!r} is being logged concurrently; retry")
    actuator.last_logged_seq = seq
    actuator.last_logged_t_s = float(batch.t_s[-1])
    if client_seq is not None:
        actuator.last_client_seq = max(last_client_seq, client_seq)
    session.flush()
    return _ack(row, replayed=False)


def _prepare_body(
    db: Database,
    operator_id: int,
    tail: str,
    actuator_id: str,
    body: RequestBody,
    media_type: str,
    params: TimeParams,
    max_samples: int,
    limits: BatchLimits,
    reservation: Reservation | None,
) -> tuple[int, ParsedBatch]:
    with db.read() as s:
        act = fleet.get_actuator(s, operator_id, tail, actuator_id)
        pk, channels = act.id, list(act.channels)
    reserve = reservation.take if reservation is not None else None
    with decoding_guard():
        parsed = parse_body(body.data, media_type, params, channels, max_samples, limits.max_decoded_bytes,
                            reserve=reserve, release_body=body.close)
    check_batch(parsed, limits)
    return pk, parsed


async def ingest_body(
    writer: LogWriter,
    db: Database,
    operator_id: int,
    tail: str,
    actuator_id: str,
    body: RequestBody,
    media_type: str,
    params: TimeParams,
    max_samples: int,
    limits: BatchLimits = DEFAULT_LIMITS,
    reservation: Reservation | None = None,
) -> Ack:
    """Parse a REST body and log it; returns once the append is committed.

    The body is parsed outside the write transaction (a large batch never holds the log's lock
    while it is decoded), in a worker thread, and let go as soon as it is decoded; the append
    joins the log writer's next group commit (:mod:`app.telemetry.writer`), which locks the
    actuator row again. ``reservation`` (the request's share of the process's ingest memory)
    is taken by the decoder before it allocates, for the decoding and the log encoding at once;
    the caller gives it back once the answer is known. A request that held much hands its freed memory back to the
    OS before it answers.
    """
    try:
        pk, parsed = await run_in_threadpool(
            _prepare_body, db, operator_id, tail, actuator_id, body, media_type, params, max_samples,
            limits, reservation,
        )
        appended = writer.submit(pk, parsed)
        del parsed  # the writer holds it until its commit, and no longer
        return await asyncio.wrap_future(appended)
    finally:
        body.close()
        held = reservation.total if reservation is not None else 0
        if max(body.size, held) >= RELEASE_AFTER_BYTES:
            await run_in_threadpool(release_memory)


def _prepare_frame(
    data: str | bytes, channels: list[str], max_samples: int, limits: BatchLimits
) -> tuple[int, ParsedBatch]:
    with decoding_guard():
        client_seq, parsed = parse_frame(data, channels, max_samples, limits.max_decoded_bytes)
    check_batch(parsed, limits)
    return client_seq, parsed


async def ingest_frame(
    writer: LogWriter,
    actuator_pk: int,
    channels: list[str],
    data: str | bytes,
    max_samples: int,
    limits: BatchLimits = DEFAULT_LIMITS,
) -> tuple[int, Ack]:
    """Parse a WebSocket frame and log it; returns ``(client_seq, ack)`` once the append is
    committed.

    The same value checks as a REST batch (:func:`app.telemetry.validation.check_batch`). Even a
    small frame is parsed in a worker thread: the decoders release and re-take the GIL, and in
    the event loop each re-take waits behind the busy writer and processor threads (measured:
    a third fewer frames per second on one connection).
    """
    client_seq, parsed = await run_in_threadpool(_prepare_frame, data, channels, max_samples, limits)
    ack = await asyncio.wrap_future(writer.submit(actuator_pk, parsed))
    return client_seq, ack
