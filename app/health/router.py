"""Health, per-sample outputs, events and RUL over HTTP."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query

from app.deps import ActuatorDep, ReadSessionDep
from app.errors import error_responses
from app.health import schemas, service

router = APIRouter(prefix="/v1", tags=["health"])
ACT = "/aircraft/{tail}/actuators/{actuator_id}"
StreamTime = Annotated[float | None, Query(description="Stream time, seconds")]


@router.get(f"{ACT}/health", response_model=schemas.ActuatorHealth, responses=error_responses(401, 403, 404))
def actuator_health(tail: str, act: ActuatorDep, s: ReadSessionDep) -> schemas.ActuatorHealth:
    """Latest health indicators of each estimator, with its status; the actuator's status is the
    worst of them (or `failed`, with `failure`, when its stream can no longer be applied)."""
    return schemas.ActuatorHealth.model_validate(service.latest_health(s, tail, act))


@router.get(
    f"{ACT}/health/history", response_model=schemas.HealthHistory, responses=error_responses(401, 403, 404)
)
def actuator_health_history(
    act: ActuatorDep,
    s: ReadSessionDep,
    estimator: str | None = None,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000,
) -> schemas.HealthHistory:
    """Health windows whose time span meets [from_s, to_s], oldest first."""
    items = service.health_history(s, act, estimator, from_s, to_s, limit)
    return schemas.HealthHistory.model_validate({"items": items})


@router.get(f"{ACT}/outputs", response_model=schemas.SampleOutputs, responses=error_responses(401, 403, 404))
def actuator_outputs(
    act: ActuatorDep,
    s: ReadSessionDep,
    estimator: str,
    from_s: float | None = None,
    to_s: float | None = None,
    max_samples: Annotated[int, Query(ge=1, le=1_000_000)] = 100_000,
) -> schemas.SampleOutputs:
    """Per-sample estimator outputs (e.g. the FAKF voltage estimate) over a time range."""
    return schemas.SampleOutputs.model_validate(
        service.sample_outputs(s, act, estimator, from_s, to_s, max_samples)
    )


@router.get(f"{ACT}/events", response_model=schemas.EventList, responses=error_responses(401, 403, 404))
def actuator_events(
    act: ActuatorDep,
    s: ReadSessionDep,
    from_s: float | None = None,
    to_s: float | None = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 1000,
) -> schemas.EventList:
    """Estimator events (model identified, identification failed, ...), oldest first."""
    return schemas.EventList.model_validate({"items": service.events(s, act, from_s, to_s, limit)})


@router.get(f"{ACT}/rul", response_model=schemas.ActuatorRul, responses=error_responses(401, 403, 404))
def actuator_rul(
    tail: str,
    act: ActuatorDep,
    s: ReadSessionDep,
    estimator: str | None = None,
    from_s: StreamTime = None,
    to_s: StreamTime = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 1000,
) -> schemas.ActuatorRul:
    """Remaining useful life: the latest prognosis of each estimator, and the prognoses made in
    [from_s, to_s] (oldest first). Times are seconds of stream time; a null RUL means the failure
    threshold is not reached within the prediction horizon."""
    return schemas.ActuatorRul.model_validate(service.rul(s, tail, act, estimator, from_s, to_s, limit))


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
        service.series(s, act, estimator, source, wanted, from_s, to_s, points)
    )
