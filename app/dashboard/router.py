"""The dashboard page at ``/`` and its static assets under ``/dashboard/``.

The page and its scripts hold no data: they call the read endpoints with the key the user enters
(kept in the browser session), so they are served without authentication. Everything, the chart
library included, comes from this app (no CDN): the Content-Security-Policy lets the page load
nothing from another host.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

STATIC = Path(__file__).resolve().parent / "static"
CHART_LIBRARY = STATIC / "vendor" / "uPlot.iife.min.js"
CSP = (
    "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
    "connect-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
MISSING_ASSETS = """<!doctype html><html lang="en"><meta charset="utf-8"><title>fleethealth</title>
<p>The dashboard's chart library is not installed: run <code>make</code> (it runs
<code>npm ci</code> and copies uPlot into app/dashboard/static/vendor), then reload.</p></html>"""

router = APIRouter(include_in_schema=False)


@router.get("/", response_class=HTMLResponse)
def dashboard() -> HTMLResponse:
    """The dashboard page (fleet board and actuator pages, routed by the URL fragment)."""
    if not CHART_LIBRARY.is_file():
        return HTMLResponse(MISSING_ASSETS, status_code=503)
    return HTMLResponse((STATIC / "index.html").read_text(), headers={"Content-Security-Policy": CSP})


def install(app: FastAPI) -> None:
    """Serve the page and its assets."""
    app.include_router(router)
    app.mount("/dashboard", StaticFiles(directory=STATIC), name="dashboard")
