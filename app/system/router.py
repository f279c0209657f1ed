"""Liveness and readiness (no authentication), Prometheus metrics (``metrics_access``) and the
API docs pages."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Annotated

import fastapi_offline
from fastapi import APIRouter, Depends, Request
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import HTMLResponse, Response
from fastapi.security import HTTPAuthorizationCredentials
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from prometheus_client.metrics_core import Metric
from prometheus_client.registry import REGISTRY, Collector, CollectorRegistry

from app.config import Settings
from app.db import Database
from app.deps import SettingsDep, bearer, verify_principal
from app.errors import NotFound, error_responses, json_response
from app.migrate import current_revision, head_revision
from app.processing.apply_process import merged_families
from app.system import repository, threads

router = APIRouter(tags=["system"])


@router.get("/healthz")
async def healthz() -> dict[str, str]:
    """The process is up."""
    return {"status": "ok"}


_READY_SCHEMA = {
    "type": "object",
    "properties": {
        "status": {"type": "string"},
        "checks": {"type": "object", "additionalProperties": {"type": "string"}},
        "kernels": {"type": "object", "additionalProperties": {"type": "object"}},
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
    system has ``storage_min_free_bytes`` free) and every estimator kind's kernels are ready.

    ``checks`` holds ``database``, ``schema``, ``storage`` and ``kernels`` (``ok`` or what is
    missing); ``kernels`` holds each estimator kind's warm-up: ``{"status": "waiting" |
    "compiling" | "loading" | "ready" | "failed", "seconds": ..., "error": ...}``. While kernels
    compile the service already accepts telemetry (durable), and each kind's streams are applied
    as soon as that kind is ready: ``database``, ``schema`` and ``storage`` at ``ok`` mean
    batches can be sent.
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
    checks["storage"] = _storage_check(state.db, state.settings)
    kernels = state.kernels.snapshot()
    waiting = sorted(kind for kind, k in kernels.items() if k["status"] != "ready")
    checks["kernels"] = "ok" if not waiting else "not ready: " + ", ".join(
        f"{kind} {kernels[kind]['status']}" for kind in waiting
    )
    failing = {k: v for k, v in checks.items() if v != "ok"}
    if not failing:
        return json_response({"status": "ok", "checks": checks, "kernels": kernels})
    return json_response(
        {
            "error": "NotReady",
            "detail": "; ".join(f"{k}: {v}" for k, v in failing.items()),
            "status": "not ready",
            "checks": checks,
            "kernels": kernels,
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
    request: Request, settings: SettingsDep,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> None:
    """``FLEETHEALTH_METRICS_ACCESS``: ``off`` hides the endpoint (404), ``key`` needs a key with
    the read scope (any operator: the figures are fleet-wide counts, never per tenant), ``open``
    needs none."""
    if settings.metrics_access == "off":
        raise NotFound("metrics are switched off (FLEETHEALTH_METRICS_ACCESS=off)")
    if settings.metrics_access == "key":
        verify_principal(request, creds).require("read")


@router.get(
    "/metrics",
    response_class=Response,
    dependencies=[Depends(metrics_allowed)],
    responses={
        200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}, "description": "Metrics"},
        **error_responses(401, 403, 404),
    },
)
def metrics(request: Request) -> Response:
    """Prometheus text exposition: ingest, apply, streaming and stream failure counters
    (``fleethealth_streams_failed`` counts the streams no longer applied), and the CPU seconds
    of the process's threads by name (``fleethealth_thread_cpu_seconds_total``). With SQLite's
    apply process (``APPLY_PROCESS=on``) its counts are added to this process's and its threads
    are named ``apply:<thread>``. Process-wide counts only, never per operator; access per
    ``FLEETHEALTH_METRICS_ACCESS`` (default: a key with the read scope)."""
    child = getattr(request.app.state, "apply_process", None)
    if child is None:
        return Response(generate_latest(), media_type=CONTENT_TYPE_LATEST)
    registry = CollectorRegistry()
    registry.register(_Families(merged_families(REGISTRY.collect(), child.metric_families())))
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)


class _Families(Collector):
    """Metric families already collected, to render."""

    def __init__(self, families: list[Metric]) -> None:
        self.families = families

    def collect(self) -> Iterable[Metric]:
        return self.families


threads.register()


# ----------------------------------------------------------------------------------- API docs
#: The Swagger UI and ReDoc assets shipped by the fastapi-offline package, served by the app at
#: DOCS_ASSETS_URL (create_app mounts them): /docs and /redoc work with no internet.
DOCS_ASSETS_DIR = Path(fastapi_offline.__file__).parent / "static"
DOCS_ASSETS_URL = "/docs/assets"
OAUTH2_REDIRECT_URL = "/docs/oauth2-redirect"
#: The browser loads nothing from another host: ReDoc's bundle shows a vendor logo from its
#: CDN, which this blocks (the image is then left out). Inline scripts and styles are the
#: pages' own; ReDoc's search runs in a blob: worker.
DOCS_CSP = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'"
)


def _docs_page(page: HTMLResponse) -> HTMLResponse:
    page.headers["Content-Security-Policy"] = DOCS_CSP
    return page


@router.get("/docs", include_in_schema=False)
def swagger_ui(request: Request) -> HTMLResponse:
    """Swagger UI over /openapi.json, with local assets."""
    root = request.scope.get("root_path", "")
    return _docs_page(
        get_swagger_ui_html(
            openapi_url=f"{root}{request.app.openapi_url}",
            title=f"{request.app.title} - Swagger UI",
            oauth2_redirect_url=f"{root}{OAUTH2_REDIRECT_URL}",
            swagger_js_url=f"{root}{DOCS_ASSETS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{DOCS_ASSETS_URL}/swagger-ui.css",
            swagger_favicon_url=f"{root}{DOCS_ASSETS_URL}/favicon.png",
            # No validator badge: it would load an image from the validator's host.
            swagger_ui_parameters={"validatorUrl": None},
        )
    )


@router.get(OAUTH2_REDIRECT_URL, include_in_schema=False)
def swagger_ui_redirect() -> HTMLResponse:
    return _docs_page(get_swagger_ui_oauth2_redirect_html())


@router.get("/redoc", include_in_schema=False)
def redoc(request: Request) -> HTMLResponse:
    """ReDoc over /openapi.json, with local assets and no web fonts."""
    root = request.scope.get("root_path", "")
    return _docs_page(
        get_redoc_html(
            openapi_url=f"{root}{request.app.openapi_url}",
            title=f"{request.app.title} - ReDoc",
            redoc_js_url=f"{root}{DOCS_ASSETS_URL}/redoc.standalone.js",
            redoc_favicon_url=f"{root}{DOCS_ASSETS_URL}/favicon.png",
            with_google_fonts=False,
        )
    )
