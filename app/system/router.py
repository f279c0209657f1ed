"""Liveness and readiness (no authentication) and Prometheus metrics (``metrics_access``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from fastapi.security import HTTPAuthorizationCredentials
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from app.deps import DbDep, SettingsDep, bearer, get_principal
from app.errors import NotFound, error_responses, json_response
from app.migrate import current_revision, head_revision
from app.system import repository

router = APIRouter(tags=["system"])


@router.get("/healthz")
def healthz() -> dict[str, str]:
    """The process is up."""
    return {"status": "ok"}


@router.get("/readyz", responses={503: {"description": "Not ready"}})
def readyz(request: Request) -> Response:
    """The database answers, its schema is at the head migration and the kernels are warm."""
    state = request.app.state
    checks: dict[str, str] = {}
    try:
        repository.ping(state.db.engine)
        rev = current_revision(state.db.engine)
    except Exception as exc:  # any failure to reach the database means not ready
        checks["database"] = f"unreachable: {type(exc).__name__}"
    else:
        head = head_revision(state.db.url)
        checks["database"] = "ok"
        checks["schema"] = "ok" if rev == head else f"at {rev}, head is {head}"
    checks["kernels"] = "ok" if state.kernels_warm.is_set() else "warming"
    ok = all(v == "ok" for v in checks.values())
    return json_response({"status": "ok" if ok else "not ready", "checks": checks}, status_code=200 if ok else 503)


def metrics_allowed(
    settings: SettingsDep, db: DbDep, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> None:
    """``FLEETHEALTH_METRICS_ACCESS``: ``off`` hides the endpoint (404), ``key`` needs a key with
    the read scope (any operator: the figures are fleet-wide counts, never per tenant), ``open``
    needs none."""
    if settings.metrics_access == "off":
        raise NotFound("metrics are switched off (FLEETHEALTH_METRICS_ACCESS=off)")
    if settings.metrics_access == "key":
        get_principal(db, creds).require("read")


@router.get(
    "/metrics",
    response_class=Response,
    dependencies=[Depends(metrics_allowed)],
    responses={
        200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}, "description": "Metrics"},
        **error_responses(401, 403, 404),
    },
)
def metrics() -> Response:
    """Prometheus text exposition: ingest, apply, streaming and stream failure counters
    (``fleethealth_streams_failed`` counts the streams no longer applied). Process-wide counts
    only, never per operator; access per ``FLEETHEALTH_METRICS_ACCESS`` (default: a key with
    the read scope)."""
    return Response(generate_latest(), media_type=CONTENT_TYPE_LATEST)
