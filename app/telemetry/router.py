"""Telemetry ingest over HTTP: the durable, idempotent entry of the data flow."""

from __future__ import annotations

from contextlib import ExitStack
from typing import Annotated, Any

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import Response, StreamingResponse
from prometheus_client import Counter

from app import series
from app.config import Settings
from app.deps import (
    ActuatorDep,
    DbDep,
    IngestDep,
    ReadDep,
    ReadSessionDep,
)
from app.errors import DomainError, StreamFailed, error_responses, json_response
from app.fleet import service as fleet
from app.ingest import TimeParams, media_type
from app.pagination import CursorQuery, OrderQuery, decode_cursor, encode_cursor
from app.processing.processor import Processor
from app.telemetry import readback, schemas, service
from app.telemetry.body import Reservation, read_body
from app.telemetry.validation import BatchLimits

router = APIRouter(prefix="/v1", tags=["telemetry"])

BATCHES_LOGGED = Counter("fleethealth_batches_logged_total", "Batches committed to the telemetry log")
SAMPLES_LOGGED = Counter("fleethealth_samples_logged_total", "Samples committed to the telemetry log")
BATCHES_REPLAYED = Counter("fleethealth_batches_replayed_total", "Retries answered from the log")
BATCHES_REJECTED = Counter("fleethealth_batches_rejected_total", "Rejected batches", ["error"])

_NUM_LIST = {"type": "array", "items": {"type": ["number", "null"]}}
_BODY_DOC: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {
                "schema": {
                    "type": "object",
                    "required": ["batch_id", "channels"],
                    "properties": {
                        "batch_id": {"type": "string", "maxLength": 128},
                        "t": {**_NUM_LIST, "description": "Sample times in seconds, strictly increasing"},
                        "t0": {"type": "number", "description": "Time of the first sample (with sample_rate_hz)"},
                        "sample_rate_hz": {"type": "number", "exclusiveMinimum": 0},
                        "channels": {
                            "type": "object",
                            "additionalProperties": _NUM_LIST,
                            "description": "Channel name -> values; null = no sample at that time",
                        },
                        "end_of_run": {
                            "type": "boolean",
                            "default": False,
                            "description": "This batch ends a run (the estimators close their windows)",
                        },
                    },
                }
            },
            "text/csv": {
                "schema": {"type": "string"},
                "example": "t,current,voltage\n0.00,0.31,-8.85\n0.01,0.36,\n",
            },
            "application/vnd.apache.arrow.stream": {
                "schema": {"type": "string", "format": "binary"},
            },
        },
    }
}


@router.post(
    "/aircraft/{tail}/actuators/{actuator_id}/telemetry",
    status_code=202,
    responses={
        202: {"description": "Batch committed to the telemetry log", "model": None},
        **error_responses(400, 401, 403, 404, 409, 413, 415),
    },
    openapi_extra=_BODY_DOC,
    response_model=None,
)
async def post_telemetry(
    request: Request,
    tail: str,
    actuator_id: str,
    p: IngestDep,
    batch_id: Annotated[str | None, Query(description="Client batch id (CSV and Arrow bodies)")] = None,
    t0: Annotated[float | None, Query(description="Time of the first sample, seconds")] = None,
    sample_rate_hz: Annotated[float | None, Query(gt=0)] = None,
    end_of_run: Annotated[
        bool, Query(description="This batch ends a run (CSV and Arrow bodies; JSON: the field)")
    ] = False,
    wait: Annotated[float, Query(ge=0, description="Seconds to wait until the batch is applied")] = 0.0,
    idempotency_key: Annotated[str | None, Header()] = None,
) -> Response:
    """Append a batch of samples to the actuator's telemetry log (ingest scope).

    JSON, CSV (header row = channel names, optional `t` column) or an Arrow IPC stream. A 202
    means the batch is committed in the log; the estimators apply it in stream order. The same
    `batch_id` again returns the first answer (header `Idempotent-Replayed: true`) and appends
    nothing. With `wait` the answer comes once the batch is applied (or the wait runs out); a
    409 `StreamFailed` says at once that the stream is no longer applied, and why (the batch is
    logged all the same).
    """
    # The app's objects straight from its state: each dependency FastAPI resolves costs this
    # hot path more than the look-up.
    settings: Settings = request.app.state.settings
    # The request's share of the process's ingest memory, held until the batch is logged.
    reservation = Reservation(request.app.state.ingest_memory)
    try:
        mt = media_type(request.headers.get("content-type"))
        body = await read_body(request, settings.max_body_bytes, settings.body_spool_bytes, reservation)
        params = TimeParams(
            batch_id=batch_id or idempotency_key, t0=t0, sample_rate_hz=sample_rate_hz, end_of_run=end_of_run
        )
        ack = await service.ingest_body(
            request.app.state.log_writer, request.app.state.actuator_lookup, p.operator_id, tail, actuator_id,
            body, mt, params, settings.max_batch_samples, BatchLimits.from_settings(settings), reservation,
        )
    except DomainError as exc:
        BATCHES_REJECTED.labels(exc.name).inc()
        raise
    finally:
        reservation.close()
    if ack.replayed:
        BATCHES_REPLAYED.inc()
    else:
        BATCHES_LOGGED.inc()
        SAMPLES_LOGGED.inc(ack.n_samples)
    if wait > 0:
        processor: Processor = request.app.state.processor
        outcome = await processor.wait_applied(ack.actuator_pk, ack.seq, min(wait, settings.max_wait_s))
        if outcome.failure is not None:
            raise StreamFailed(
                f"batch {ack.batch_id!r} is logged as seq {ack.seq} but the stream is no longer "
                f"applied: {outcome.failure}"
            )
    headers = {"Idempotent-Replayed": "true"} if ack.replayed else None
    return json_response(ack.body(), status_code=202, headers=headers)


# ----------------------------------------------------------------------------- read-back
TEL = "/aircraft/{tail}/actuators/{actuator_id}/telemetry"
READ_ERRORS = error_responses(400, 401, 403, 404, 410, 422)
StreamTime = Annotated[float | None, Query(description="Stream time, seconds")]


@router.get(f"{TEL}", response_model=schemas.TelemetryPage, responses=READ_ERRORS)
def read_telemetry(
    act: ActuatorDep,
    s: ReadSessionDep,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    max_samples: Annotated[int, Query(ge=1, le=1_000_000, description="Samples per page")] = 100_000,
    cursor: CursorQuery = None,
    order: OrderQuery = "desc",
) -> schemas.TelemetryPage:
    """Raw samples as logged, in [from_s, to_s], newest first (`order=asc`: oldest first),
    `max_samples` per page; `next_cursor` gives the next page. A missing sample is null;
    batches whose samples retention dropped are listed in `dropped`. For whole series use
    `.../telemetry/export`."""
    key = decode_cursor(cursor, "telemetry", order, 1)
    body, last = readback.read(s, act, from_s, to_s, None if key is None else float(key[0]), order, max_samples)
    return schemas.TelemetryPage.model_validate(
        {**body, "next_cursor": encode_cursor("telemetry", order, [last]) if last is not None else None}
    )


@router.get(f"{TEL}/export", response_class=StreamingResponse, responses={**series.EXPORT_RESPONSES, **READ_ERRORS})
def export_telemetry(
    tail: str,
    actuator_id: str,
    db: DbDep,
    p: ReadDep,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    format: Annotated[series.ExportFormat, Query(description="arrow (IPC stream), csv or parquet")] = "arrow",
) -> StreamingResponse:
    """Raw telemetry in [from_s, to_s], oldest first, as one file streamed batch by batch:
    column `t` (seconds) and the actuator's channels, a missing sample null: the same columns
    an Arrow upload carries."""
    with ExitStack() as stack:
        # The read transaction outlives this function: the body is written after it returns.
        s = stack.enter_context(db.read())
        act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
        schema, blocks = readback.export_blocks(s, act, from_s, to_s)
        return series.export_response(stack.pop_all(), series.export(blocks, schema, format), format,
                                      f"{tail}_{actuator_id}_telemetry")
