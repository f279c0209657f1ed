"""Liveness, readiness and Prometheus metrics (no authentication)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from app.errors import json_response
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


@router.get("/metrics", response_class=Response)
def metrics() -> Response:
    """Prometheus text exposition: ingest, apply, streaming and stream failure counters
    (``fleethealth_streams_failed`` counts the streams no longer applied)."""
    return Response(generate_latest(), media_type=CONTENT_TYPE_LATEST)
