"""Health, per-sample outputs (read and exported), events and RUL over HTTP."""

from __future__ import annotations

from contextlib import ExitStack
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query
from fastapi.responses import StreamingResponse

from app import series
from app.deps import ActuatorDep, DbDep, ReadDep, ReadSessionDep
from app.errors import error_responses
from app.fleet import service as fleet
from app.health import schemas, service
from app.pagination import CursorQuery, Order, OrderQuery, decode_cursor, encode_cursor

router = APIRouter(prefix="/v1", tags=["health"])
ACT = "/aircraft/{tail}/actuators/{actuator_id}"
StreamTime = Annotated[float | None, Query(description="Stream time, seconds")]
ERRORS = error_responses(400, 401, 403, 404, 410, 422)


def _cursor(scope: str, order: Order, key: list[Any] | None) -> str | None:
    return encode_cursor(scope, order, key) if key is not None else None


def _after_t(cursor: str | None, scope: str, order: Order) -> float | None:
    key = decode_cursor(cursor, scope, order, 1)
    return None if key is None else float(key[0])


@router.get(f"{ACT}/health", response_model=schemas.ActuatorHealth, responses=error_responses(401, 403, 404, 410))
def actuator_health(tail: str, act: ActuatorDep, s: ReadSessionDep) -> schemas.ActuatorHealth:
    """Latest health indicators of each estimator in its current baseline, with its status; the
    actuator's status is the worst of them (or `failed`, with `failure`, when its stream can no
    longer be applied)."""
    return schemas.ActuatorHealth.model_validate(service.latest_health(s, tail, act))


@router.get(f"{ACT}/health/history", response_model=schemas.HealthHistory, responses=ERRORS)
def actuator_health_history(
    act: ActuatorDep,
    s: ReadSessionDep,
    estimator: str | None = None,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    limit: Annotated[int, Query(ge=1, le=100_000, description="Windows per page")] = 10_000,
    cursor: CursorQuery = None,
    order: OrderQuery = "desc",
) -> schemas.HealthHistory:
    """Health windows whose time span meets [from_s, to_s], newest first (`order=asc`: oldest
    first), a page at a time (`next_cursor`); each says its config version and baseline."""
    after = decode_cursor(cursor, "windows", order, 2)
    items, last = service.health_history(s, act, estimator, from_s, to_s, after, order, limit)
    return schemas.HealthHistory.model_validate({"items": items, "next_cursor": _cursor("windows", order, last)})


@router.get(f"{ACT}/outputs", response_model=schemas.SampleOutputs, responses=ERRORS)
def actuator_outputs(
    act: ActuatorDep,
    s: ReadSessionDep,
    estimator: str,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    max_samples: Annotated[int, Query(ge=1, le=1_000_000, description="Samples per page")] = 100_000,
    cursor: CursorQuery = None,
    order: OrderQuery = "desc",
) -> schemas.SampleOutputs:
    """Per-sample estimator outputs (e.g. the FAKF voltage estimate) over a time range, newest
    sample first (`order=asc`: oldest first), `max_samples` per page; `next_cursor` gives the
    next page. For whole series use `.../outputs/export`."""
    body, last = service.sample_outputs(
        s, act, estimator, from_s, to_s, _after_t(cursor, "outputs", order), order, max_samples
    )
    return schemas.SampleOutputs.model_validate(
        {**body, "truncated": last is not None, "next_cursor": _cursor("outputs", order, None if last is None else [last])}
    )


@router.get(f"{ACT}/outputs/export", response_class=StreamingResponse, responses={**series.EXPORT_RESPONSES, **ERRORS})
def export_outputs(
    tail: str,
    actuator_id: str,
    db: DbDep,
    p: ReadDep,
    estimator: str,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    format: Annotated[series.ExportFormat, Query(description="arrow (IPC stream), csv or parquet")] = "arrow",
) -> StreamingResponse:
    """An estimator's per-sample outputs in [from_s, to_s], oldest first, as one file streamed
    block by block: columns `t`, each output, and the `seq`, `config_version` and `baseline`
    of the batch that produced each sample; a non-finite output is null."""
    with ExitStack() as stack:
        # The read transaction outlives this function: the body is written after it returns.
        s = stack.enter_context(db.read())
        act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
        schema, blocks = service.output_export(s, act, estimator, from_s, to_s)
        return series.export_response(stack.pop_all(), series.export(blocks, schema, format), format,
                               f"{tail}_{actuator_id}_{estimator}")


@router.get(f"{ACT}/events", response_model=schemas.EventList, responses=ERRORS)
def actuator_events(
    act: ActuatorDep,
    s: ReadSessionDep,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    limit: Annotated[int, Query(ge=1, le=100_000, description="Events per page")] = 1000,
    cursor: CursorQuery = None,
    order: OrderQuery = "desc",
) -> schemas.EventList:
    """Estimator events (model identified, identification failed, ...), newest first, a page at
    a time."""
    items, last = service.events(s, act, from_s, to_s, decode_cursor(cursor, "events", order, 2), order, limit)
    return schemas.EventList.model_validate({"items": items, "next_cursor": _cursor("events", order, last)})


@router.get(f"{ACT}/rul", response_model=schemas.ActuatorRul, responses=ERRORS)
def actuator_rul(
    tail: str,
    act: ActuatorDep,
    s: ReadSessionDep,
    estimator: str | None = None,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    limit: Annotated[int, Query(ge=1, le=100_000, description="Prognoses per page")] = 1000,
    cursor: CursorQuery = None,
    order: OrderQuery = "desc",
) -> schemas.ActuatorRul:
    """Remaining useful life: the latest prognosis of each estimator in its current baseline,
    and the prognoses made in [from_s, to_s] (newest first, a page at a time). Times are
    seconds of stream time; a null RUL means the failure threshold is not reached within the
    prediction horizon. Each prognosis also gives `event_state` (normalized health, 1 new, 0
    failed), `time_of_event` (absolute UTC when the stream's clock is epoch seconds) and, when
    the actuator sends an `operating_hours` or `cycles` counter channel, the RUL in those units."""
    body, last = service.rul(
        s, tail, act, estimator, from_s, to_s, decode_cursor(cursor, "rul", order, 2), order, limit
    )
    return schemas.ActuatorRul.model_validate(
        {**body, "truncated": last is not None, "next_cursor": _cursor("rul", order, last)}
    )


@router.get(f"{ACT}/series", response_model=schemas.SeriesPublic, responses=error_responses(400, 401, 403, 404))
def actuator_series(
    act: ActuatorDep,
    s: ReadSessionDep,
    estimator: Annotated[str | None, Query(description="Estimator (needed for outputs and health)")] = None,
    source: Annotated[
        Literal["outputs", "health", "telemetry"],
        Query(
            description="`outputs`: per-sample outputs; `health`: health-window indicators at each "
            "window's end; `telemetry`: the channels of the batches the log still holds"
        ),
    ] = "outputs",
    names: Annotated[
        str | None, Query(description="Comma-separated series to return (default: all of the source)")
    ] = None,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    points: Annotated[int, Query(ge=2, le=20_000, description="Width of the plot in pixels")] = 1000,
) -> schemas.SeriesPublic:
    """A series for plotting: at most `points` samples of the outputs (or health indicators) of
    one estimator, or of the logged telemetry, over [from_s, to_s]. Longer spans keep, per `points / 2` equal time buckets,
    each series' minimum and maximum in their order, so the plot shows every peak and trough;
    zooming in asks for a shorter span and gets finer data."""
    wanted = None if names is None else [n for n in (p.strip() for p in names.split(",")) if n]
    return schemas.SeriesPublic.model_validate(
        service.plot_series(s, act, estimator, source, wanted, from_s, to_s, points)
    )
