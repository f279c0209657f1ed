"""Application factory. The lifespan owns the database, the kernels, the telemetry log writer, the
processor and (PostgreSQL) the notification listener."""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from app import __version__
from app.alarms import router as alarms_router
from app.auth import router as auth_router
from app.auth.service import SCOPES, ensure_key
from app.config import Settings, get_settings
from app.dashboard import router as dashboard_router
from app.db import Database
from app.errors import document_errors, install_handlers
from app.events import router as events_router
from app.faults import router as faults_router
from app.fleet import router as fleet_router
from app.health import router as health_router
from app.processing import wakeups
from app.processing.processor import Processor
from app.streams import router as streams_router
from app.system import router as system_router
from app.telemetry import router as telemetry_router
from app.telemetry.validation import ControlCharGuard
from app.telemetry.writer import LogWriter
from app.webhooks import router as webhooks_router
from app.webhooks.deliverer import Deliverer
from app.websocket import router as websocket_router
from estimators.registry import ESTIMATORS

log = logging.getLogger("fleethealth")

# At shutdown, how long to wait for a kernel warm-up still running (a first numba compile of
# every kernel takes tens of seconds on a cold cache).
WARM_JOIN_TIMEOUT_S = 60.0

DESCRIPTION = """\
Health monitoring of aircraft actuators across a fleet: telemetry ingest per tail number,
stateful estimators per stream, health indicators, remaining useful life and fault isolation.

Authenticate with `Authorization: Bearer <key>`. Errors have one shape:
`{"error": "<Name>", "detail": "<message>"}`; for `ValidationError` (422) `detail` lists the
issues (`{"loc", "msg", "type"}`). A 503 `StorageUnavailable` (database unreachable or out of
space) stored nothing: retry after `Retry-After` seconds.
"""


def warm_kernels() -> None:
    """Compile (or load from numba's cache) every estimator kernel once."""
    for kind in ESTIMATORS.values():
        kind.warm_up()


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        db = Database(settings.database_url, sqlite_synchronous=settings.sqlite_synchronous)
        # PostgreSQL: wake-ups, applied marks and fleet events also cross processes (workers).
        chans = wakeups.channels(db) if not db.is_sqlite and settings.pg_notify == "on" else None
        processor = Processor(db, settings, applied_channel=chans.applied if chans else None, origin=wakeups.ORIGIN)
        writer = LogWriter(
            db,
            max_group=settings.log_writer_max_group,
            on_logged=processor.notify_many,
            notify_channel=chans.logged if chans else None,
            origin=wakeups.ORIGIN,
            recent=processor.recent,
        )
        writer.start()
        listener = None
        if chans is not None:
            listener = wakeups.Listener(
                settings.database_url,
                chans,
                on_logged=processor.notify_many if settings.processor_enabled else None,
                on_applied=processor.applied_elsewhere,
                on_failed=processor.hub.mark_failed,
                on_resync=processor.resync,
            )
            listener.start()
        app.state.db = db
        app.state.settings = settings
        app.state.processor = processor
        deliverer = Deliverer(db, settings) if settings.webhooks_enabled else None
        app.state.deliverer = deliverer
        app.state.log_writer = writer
        app.state.kernels_warm = threading.Event()
        if settings.bootstrap_admin_key:
            with db.write() as s:
                ensure_key(s, settings.bootstrap_operator, settings.bootstrap_admin_key,
                           list(SCOPES), name="bootstrap")

        def _warm_then_process() -> None:
            # Batches are accepted (and durable) while the kernels compile; the processor starts
            # once they are ready so that no apply pays a compile.
            if settings.warm_kernels:
                warm_kernels()
            app.state.kernels_warm.set()
            if settings.processor_enabled:
                processor.start()

        warm = threading.Thread(target=_warm_then_process, name="fleethealth-warm", daemon=True)
        warm.start()
        if deliverer is not None:
            deliverer.start()
        try:
            yield
        finally:
            warm.join(timeout=WARM_JOIN_TIMEOUT_S)
            writer.stop()
            if listener is not None:
                listener.stop()
            processor.stop()
            if deliverer is not None:
                deliverer.stop()
            db.dispose()

    app = FastAPI(
        title="fleethealth",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    install_handlers(app)
    app.openapi = lambda: document_errors(FastAPI.openapi(app))  # type: ignore[method-assign]
    app.add_middleware(ControlCharGuard)
    for module in (
        system_router,
        fleet_router,
        auth_router,
        telemetry_router,
        streams_router,
        health_router,
        faults_router,
        websocket_router,
        events_router,
        alarms_router,
        webhooks_router,
    ):
        app.include_router(module.router)
    dashboard_router.install(app)
    return app
