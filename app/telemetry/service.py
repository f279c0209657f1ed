"""The telemetry log: durable, idempotent, ordered append of batches.

:func:`log_batch` holds the rules and is the one way into the log, for REST batches
(:func:`ingest_body`) and streamed frames (:func:`prepare_frame`, then the writer). Both are
acknowledged only once their append is committed, by the log writer's group commit
(:mod:`app.telemetry.writer`): an acknowledgement means the batch is durable.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

from starlette.concurrency import run_in_threadpool

from app.cache import TtlCache
from app.db import Database
from app.errors import ActuatorDeleted, IdempotencyConflict, StaleBatch
from app.fleet import service as fleet
from app.ingest import ParsedBatch, TimeParams, client_seq_of, parse_body, parse_frame
from app.telemetry.body import RELEASE_AFTER_BYTES, RequestBody, Reservation, release_memory
from app.telemetry.repository import LoggedBatch, LogHead
from app.telemetry.validation import DEFAULT_LIMITS, BatchLimits, check_batch, decoding_guard
from app.telemetry.writer import LogWriter
from app.websocket.hub import inbox


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


def log_batch(
    head: LogHead,
    batch: ParsedBatch,
    prior: LoggedBatch | None,
    received_at: datetime,
) -> tuple[Ack, dict[str, object] | None]:
    """Append ``batch`` at ``head`` (the actuator's locked log position, advanced in place).

    Returns the acknowledgement and the log row to insert (None for a replay). A ``batch_id``
    seen before (``prior``) returns the first acknowledgement and appends nothing; the same id
    with different samples (or another end-of-run marker) is a conflict. A streamed frame must
    come after the last logged frame (``client_seq``), and every batch after the stream's last
    sample in time.
    """
    digest = batch.digest
    if prior is not None:
        if prior.content_hash != digest:
            raise IdempotencyConflict(
                f"batch_id {batch.batch_id!r} was already used for different samples (seq {prior.seq})"
            )
        return Ack(head.actuator_pk, prior.batch_id, prior.seq, prior.n_samples, prior.t_first_s,
                   prior.t_last_s, prior.received_at, prior.end_of_run, replayed=True), None
    client_seq = client_seq_of(batch.batch_id)
    last_client_seq = head.last_client_seq or 0
    if client_seq is not None and client_seq <= last_client_seq:
        raise StaleBatch(
            f"client_seq {client_seq} is not after the last logged frame ({last_client_seq}); "
            "resume after the last_client_seq the server announced"
        )
    t_first, t_last = float(batch.t_s[0]), float(batch.t_s[-1])
    if head.last_logged_t_s is not None and t_first <= head.last_logged_t_s:
        raise StaleBatch(
            f"batch starts at t={t_first!r} s, not after the stream's last sample at "
            f"t={head.last_logged_t_s!r} s (seq {head.last_logged_seq}); batches must "
            "follow each other in time"
        )
    seq = head.last_logged_seq + 1
    row: dict[str, object] = {
        "actuator_pk": head.actuator_pk,
        "seq": seq,
        "batch_id": batch.batch_id,
        "content_hash": digest,
        "n_samples": batch.n_samples,
        "t_first_s": t_first,
        "t_last_s": t_last,
        "received_at": received_at,
        "end_of_run": batch.end_of_run,
        "payload": batch.log_payload,
    }
    head.last_logged_seq = seq
    head.last_logged_t_s = t_last
    if client_seq is not None:
        head.last_client_seq = max(last_client_seq, client_seq)
    ack = Ack(head.actuator_pk, batch.batch_id, seq, batch.n_samples, t_first, t_last, received_at,
              batch.end_of_run, replayed=False)
    return ack, row


@dataclass(frozen=True)
class IngestTarget:
    """What an append needs of the actuator a path names."""

    actuator_pk: int
    channels: tuple[str, ...]


class ActuatorLookup:
    """The actuator a telemetry path names, per operator, remembered for ``ttl_s``
    (``FLEETHEALTH_ACTUATOR_CACHE_TTL_S``) so that an append usually reads nothing before the
    log writer's transaction. Staleness cannot let a batch into a deleted stream: the writer
    checks each append against the locked actuator row and refuses it
    (:class:`~app.errors.ActuatorDeleted`), upon which :func:`ingest_body` forgets the entry and
    looks again (404, 410, or the actuator now at that path)."""

    def __init__(self, db: Database, ttl_s: float, max_entries: int) -> None:
        self.db = db
        self.cache: TtlCache[tuple[int, str, str], IngestTarget] = TtlCache(ttl_s, max_entries)

    def resolve(self, operator_id: int, tail: str, actuator_id: str) -> IngestTarget:
        """From the database (blocking); 404 or 410 as :func:`app.fleet.service.get_actuator`."""
        key = (operator_id, tail, actuator_id)
        generation = self.cache.generation()
        with self.db.read() as s:
            act = fleet.get_actuator(s, operator_id, tail, actuator_id)
            target = IngestTarget(act.id, tuple(act.channels))
        self.cache.put(key, target, generation)
        return target


# Bodies up to this size are parsed in the event loop: a worker-thread hop costs more than
# decoding a few hundred samples; larger ones are parsed in a worker thread so that the loop
# keeps serving other requests meanwhile, and let go as soon as they are decoded.
INLINE_PARSE_MAX_BYTES = 16 * 1024


def _parse_body(
    body: RequestBody,
    media_type: str,
    params: TimeParams,
    channels: Sequence[str],
    max_samples: int,
    limits: BatchLimits,
    reservation: Reservation | None,
) -> ParsedBatch:
    reserve = reservation.take if reservation is not None else None
    release = body.close if body.size > INLINE_PARSE_MAX_BYTES else None
    with decoding_guard():
        parsed = parse_body(body.data, media_type, params, list(channels), max_samples, limits.max_decoded_bytes,
                            reserve=reserve, release_body=release)
    check_batch(parsed, limits)
    parsed.prepare_log()
    return parsed


async def ingest_body(
    writer: LogWriter,
    lookup: ActuatorLookup,
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
    while it is decoded); the append joins the log writer's next group commit
    (:mod:`app.telemetry.writer`), which locks the actuator row and checks it is not deleted.
    A small body whose actuator is remembered never leaves the event loop but for that commit;
    a large one is parsed in a worker thread and let go as soon as it is decoded.
    ``reservation`` (the request's share of the process's ingest memory) is taken by the
    decoder before it allocates, for the decoding and the log encoding at once; the caller
    gives it back once the answer is known. A request that held much hands its freed memory
    back to the OS before it answers.
    """
    key = (operator_id, tail, actuator_id)
    try:
        target = lookup.cache.get(key)
        from_cache = target is not None
        if target is None:
            target = await run_in_threadpool(lookup.resolve, operator_id, tail, actuator_id)
        args = (body, media_type, params, target.channels, max_samples, limits, reservation)
        parsed = _parse_body(*args) if body.size <= INLINE_PARSE_MAX_BYTES else await run_in_threadpool(
            _parse_body, *args
        )
        while True:
            try:
                # Resolved through the loop's inbox: the acks of one group commit reach the
                # loop in one wake-up, not one call_soon_threadsafe each.
                return await inbox(asyncio.get_running_loop()).wrap(writer.submit(target.actuator_pk, parsed))
            except ActuatorDeleted:
                if not from_cache:
                    raise
                # Deleted since it was remembered (by any process): answer as a fresh look-up
                # does (404, 410), or log into the actuator now registered at that path.
                lookup.cache.invalidate(key)
                fresh = await run_in_threadpool(lookup.resolve, operator_id, tail, actuator_id)
                from_cache = False
                if fresh.channels != target.channels:
                    if body.size > INLINE_PARSE_MAX_BYTES:
                        raise  # the body is let go already; the client's retry decodes it anew
                    parsed = _parse_body(body, media_type, params, fresh.channels, max_samples, limits, None)
                target = fresh
    finally:
        body.close()
        held = reservation.total if reservation is not None else 0
        if max(body.size, held) >= RELEASE_AFTER_BYTES:
            await run_in_threadpool(release_memory)


def prepare_frame(
    data: str | bytes, channels: Sequence[str], max_samples: int, limits: BatchLimits = DEFAULT_LIMITS
) -> tuple[int, ParsedBatch]:
    """Parse and check a WebSocket frame (blocking): ``(client_seq, batch)``, ready for
    :meth:`LogWriter.submit <app.telemetry.writer.LogWriter.submit>`.

    The same value checks as a REST batch (:func:`app.telemetry.validation.check_batch`). Which
    thread runs it, and how the commit's acknowledgement reaches the event loop, is the stream
    connection's choice (:mod:`app.websocket.router`): both are per-frame costs there.
    """
    with decoding_guard():
        client_seq, parsed = parse_frame(data, list(channels), max_samples, limits.max_decoded_bytes)
    check_batch(parsed, limits)
    parsed.prepare_log()
    return client_seq, parsed
