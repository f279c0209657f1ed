"""Liveness and readiness (no authentication) and Prometheus metrics (``metrics_access``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from fastapi.security import HTTPAuthorizationCredentials
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from app.config import Settings
from app.db import Database
from app.deps import DbDep, SettingsDep, bearer, get_principal
from app.errors import NotFound, error_responses, json_response
from app.migrate import current_revision, head_revision
from app.system import repository

router = APIRouter(tags=["system"])


@router.get("/healthz")
def healthz() -> dict[str, str]:
    """The process is up."""
    return {"status": "ok"}


_READY_SCHEMA = {
    "type": "object",
    "properties": {
        "status": {"type": "string"},
        "checks": {"type": "object", "additionalProperties": {"type": "string"}},
        "error": {"type": "string"},
        "detail": {"type": "string"},
    },
    "required": ["status", "checks"],
}


@router.get(
    "/readyz",
    response_class=Response,
    responses={
        200: {"description": "Ready", "content": {"application/json": {"schema": _READY_SCHEMA}}},
        503: {"description": "Not ready (the detail names the failing checks)",
              "content": {"application/json": {"schema": _READY_SCHEMA}}},
    },
)
def readyz(request: Request) -> Response:
    """The database answers, its schema is at the head migration, it can store (no write
    failed for lack of space or connection since the last one that committed; a SQLite file
    system has ``storage_min_free_bytes`` free) and the kernels are warm."""
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
    checks["storage"] = _storage_check(state.db, state.settings)
    checks["kernels"] = "ok" if state.kernels_warm.is_set() else "warming"
    failing = {k: v for k, v in checks.items() if v != "ok"}
    if not failing:
        return json_response({"status": "ok", "checks": checks})
    return json_response(
        {
            "error": "NotReady",
            "detail": "; ".join(f"{k}: {v}" for k, v in failing.items()),
            "status": "not ready",
            "checks": checks,
        },
        status_code=503,
        headers={"Retry-After": str(state.settings.storage_retry_after_s)},
    )


def _storage_check(db: Database, settings: Settings) -> str:
    fault = db.storage.recent_fault()
    if fault is not None:
        return f"last write failed: {fault}"
    free = repository.sqlite_free_bytes(db.url)
    if free is not None and free < settings.storage_min_free_bytes:
        return f"disk full: {free} bytes free, below FLEETHEALTH_STORAGE_MIN_FREE_BYTES"
    return "ok"


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
