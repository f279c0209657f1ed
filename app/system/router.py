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


@router.get("/readyz", responses={503: {"description": "Not ready (the body says what is missing)"}})
def readyz(request: Request) -> Response:
    """The database answers, its schema is at the head migration and every estimator kind's
    kernels are ready.

    ``checks`` holds ``database``, ``schema`` and ``kernels`` (``ok`` or what is missing);
    ``kernels`` holds each estimator kind's warm-up: ``{"status": "waiting" | "compiling" |
    "loading" | "ready" | "failed", "seconds": ..., "error": ...}``. While kernels compile the
    service already accepts telemetry (durable), and each kind's streams are applied as soon as
    that kind is ready: ``database`` and ``schema`` at ``ok`` mean batches can be sent.
    """
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
    kernels = state.kernels.snapshot()
    waiting = sorted(kind for kind, k in kernels.items() if k["status"] != "ready")
    checks["kernels"] = "ok" if not waiting else "not ready: " + ", ".join(
        f"{kind} {kernels[kind]['status']}" for kind in waiting
    )
    ok = all(v == "ok" for v in checks.values())
    body = {"status": "ok" if ok else "not ready", "checks": checks, "kernels": kernels}
    return json_response(body, status_code=200 if ok else 503)


@router.get("/metrics", response_class=Response)
def metrics() -> Response:
    """Prometheus text exposition: ingest, apply, streaming and stream failure counters
    (``fleethealth_streams_failed`` counts the streams no longer applied)."""
    return Response(generate_latest(), media_type=CONTENT_TYPE_LATEST)
