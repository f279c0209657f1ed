"""Telemetry ingest over HTTP: the durable, idempotent entry of the data flow."""

from __future__ import annotations

import re
from contextlib import ExitStack
from typing import Annotated, Any

import orjson
from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import Response, StreamingResponse
from prometheus_client import Counter
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Receive, Scope, Send

from app import series
from app.config import Settings
from app.deps import (
    ActuatorDep,
    DbDep,
    IngestDep,
    ReadDep,
    ReadSessionDep,
)
from app.errors import (
    STORAGE_FAULTS,
    DomainError,
    StreamFailed,
    domain_error_response,
    error_responses,
    json_response,
    storage_fault_response,
)
from app.fleet import service as fleet
from app.ingest import TimeParams, media_type
from app.pagination import CursorQuery, OrderQuery, decode_cursor, encode_cursor
from app.processing.processor import Processor
from app.telemetry import readback, schemas, service
from app.telemetry.body import RequestBody, Reservation, read_body
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
    state = request.app.state
    settings: Settings = state.settings
    # The request's share of the process's ingest memory, held until the batch is logged.
    reservation = Reservation(state.ingest_memory)
    try:
        mt = media_type(request.headers.get("content-type"))
        body = await read_body(request, settings.max_body_bytes, settings.body_spool_bytes, reservation)
        params = TimeParams(
            batch_id=batch_id or idempotency_key, t0=t0, sample_rate_hz=sample_rate_hz, end_of_run=end_of_run
        )
        ack = await _log(state, p.operator_id, tail, actuator_id, body, mt, params, reservation)
    except DomainError as exc:
        BATCHES_REJECTED.labels(exc.name).inc()
        raise
    finally:
        reservation.close()
    if wait > 0:
        processor: Processor = state.processor
        outcome = await processor.wait_applied(ack.actuator_pk, ack.seq, min(wait, settings.max_wait_s))
        if outcome.failure is not None:
            raise StreamFailed(
                f"batch {ack.batch_id!r} is logged as seq {ack.seq} but the stream is no longer "
                f"applied: {outcome.failure}"
            )
    headers = {"Idempotent-Replayed": "true"} if ack.replayed else None
    return json_response(ack.body(), status_code=202, headers=headers)


async def _log(
    state: Any, operator_id: int, tail: str, actuator_id: str, body: RequestBody, mt: str, params: TimeParams,
    reservation: Reservation,
) -> service.Ack:
    """Log a batch read whole (both ways in: :func:`post_telemetry` and :class:`LeanIngest`)."""
    settings: Settings = state.settings
    ack = await service.ingest_body(
        state.log_writer, state.actuator_lookup, operator_id, tail, actuator_id, body, mt, params,
        settings.max_batch_samples, BatchLimits.from_settings(settings), reservation,
    )
    if ack.replayed:
        BATCHES_REPLAYED.inc()
    else:
        BATCHES_LOGGED.inc()
        SAMPLES_LOGGED.inc(ack.n_samples)
    return ack


_INGEST_PATH = re.compile(r"/v1/aircraft/([^/]+)/actuators/([^/]+)/telemetry")
_ACCEPTED_HEADERS = [(b"content-type", b"application/json")]
_REPLAYED_HEADER = (b"idempotent-replayed", b"true")


class LeanIngest:
    """ASGI middleware: the common case of :func:`post_telemetry`, answered without FastAPI's
    routing, dependency injection and parameter validation (about two thirds of the event
    loop's time for a one-sample batch).

    It takes a request only when nothing but the body can make it fail: a POST to the ingest
    path with no query string, a small body of declared length in a supported media type, an
    API key the :class:`~app.auth.service.KeyVerifier` remembers with the ingest scope and an
    actuator the :class:`~app.telemetry.service.ActuatorLookup` remembers. Any other request (a
    query, an unknown key, a cache miss, a large or chunked body, ...) goes on to the route,
    whose answers are the contract. From the body on,
    both share :func:`_log` and give the same answers: 202 with the same body and headers, a
    :class:`~app.errors.DomainError` or a storage fault in the one error shape
    (:func:`app.errors.domain_error_response`, :func:`app.errors.storage_fault_response`),
    anything else raised to the server-error handler (500). Install it inside
    :class:`~app.telemetry.validation.ControlCharGuard`, which refuses control characters first.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or scope["method"] != "POST"
            or scope["query_string"]
            or scope.get("root_path")
            or (match := _INGEST_PATH.fullmatch(scope["path"])) is None
        ):
            await self.app(scope, receive, send)
            return
        taken = self._take(scope, match.group(1), match.group(2))
        if taken is None:
            await self.app(scope, receive, send)
            return
        state, operator_id, mt, length, idempotency_key = taken
        reservation = Reservation(state.ingest_memory)
        try:
            try:
                await reservation.take_async(length)
                body = await self._read(receive)
                params = TimeParams(batch_id=idempotency_key, t0=None, sample_rate_hz=None)
                ack = await _log(state, operator_id, match.group(1), match.group(2), body, mt, params, reservation)
            except DomainError as exc:
                BATCHES_REJECTED.labels(exc.name).inc()
                raise
            finally:
                reservation.close()
        except DomainError as exc:
            await domain_error_response(exc, state.settings.storage_retry_after_s)(scope, receive, send)
            return
        except STORAGE_FAULTS as exc:
            response = storage_fault_response(scope["path"], exc, state.settings.storage_retry_after_s)
            await response(scope, receive, send)
            return
        content = orjson.dumps(ack.body())
        headers = [(b"content-length", str(len(content)).encode()), *_ACCEPTED_HEADERS]
        if ack.replayed:
            headers.insert(0, _REPLAYED_HEADER)
        await send({"type": "http.response.start", "status": 202, "headers": headers})
        await send({"type": "http.response.body", "body": content})

    @staticmethod
    def _take(
        scope: Scope, tail: str, actuator_id: str
    ) -> tuple[Any, int, str, int, str | None] | None:
        """What the request needs when this path may answer it, else None: the route answers.
        Of a repeated header, the first counts (as for the route)."""
        state = scope["app"].state
        authorization: str | None = None
        content_type: str | None = None
        length: bytes | None = None
        idempotency_key: str | None = None
        for name, value in scope["headers"]:
            if name == b"authorization":
                authorization = value.decode("latin-1") if authorization is None else authorization
            elif name == b"content-type":
                content_type = value.decode("latin-1") if content_type is None else content_type
            elif name == b"content-length":
                length = value if length is None else length
            elif name == b"idempotency-key":
                idempotency_key = value.decode("latin-1") if idempotency_key is None else idempotency_key
            elif name == b"transfer-encoding":
                return None
        settings: Settings = state.settings
        if authorization is None or length is None or not length.isdigit():
            return None
        size = int(length)
        if size > min(service.INLINE_PARSE_MAX_BYTES, settings.body_spool_bytes, settings.max_body_bytes):
            return None
        try:
            principal = state.key_verifier.cached(authorization)
            mt = media_type(content_type)
        except DomainError:
            return None
        if principal is None or not principal.has("ingest"):
            return None
        if state.actuator_lookup.cache.get((principal.operator_id, tail, actuator_id)) is None:
            return None
        return state, principal.operator_id, mt, size, idempotency_key

    @staticmethod
    async def _read(receive: Receive) -> RequestBody:
        """The body (of the declared length: the server frames it)."""
        memory = bytearray()
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                raise ClientDisconnect()
            memory += message.get("body", b"")
            if not message.get("more_body", False):
                return RequestBody(memory, None, len(memory))


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
