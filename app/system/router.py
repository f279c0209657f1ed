"""Liveness, readiness, Prometheus metrics and the API docs pages (no authentication)."""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import APIRouter, Request
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import HTMLResponse, Response
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
