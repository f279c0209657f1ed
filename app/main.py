"""Application factory. The lifespan owns the database, the kernels, the telemetry log writer, the
processor and (PostgreSQL) the notification listener."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from app import __version__
from app.alarms import router as alarms_router
from app.auth import router as auth_router
from app.auth.service import SCOPES, KeyVerifier, ensure_key
from app.config import Settings, get_settings
from app.dashboard import router as dashboard_router
from app.db import Database
from app.errors import document_errors, install_handlers
from app.events import router as events_router
from app.faults import router as faults_router
from app.fleet import router as fleet_router
from app.health import router as health_router
from app.kernels import KernelWarmup
from app.processing import wakeups
from app.processing.apply_process import ApplyProcess
from app.processing.processor import Processor
from app.streams import router as streams_router
from app.system import router as system_router
from app.telemetry import router as telemetry_router
from app.telemetry.body import IngestMemory
from app.telemetry.service import ActuatorLookup
from app.telemetry.validation import ControlCharGuard
from app.telemetry.writer import LogWriter
from app.webhooks import router as webhooks_router
from app.webhooks.deliverer import Deliverer
from app.websocket import router as websocket_router
from estimators.registry import ESTIMATORS

log = logging.getLogger("fleethealth")

# At shutdown, how long to wait for the kernel warm-up (its compiling children are killed; a
# load from numba's cache in progress ends within about a second).
WARM_JOIN_TIMEOUT_S = 2.0

DESCRIPTION = """\
Health monitoring of aircraft actuators across a fleet: telemetry ingest per tail number,
stateful estimators per stream, health indicators, remaining useful life and fault isolation.

Authenticate with `Authorization: Bearer <key>`. Errors have one shape:
`{"error": "<Name>", "detail": "<message>"}`; for `ValidationError` (422) `detail` lists the
issues (`{"loc", "msg", "type"}`). A 503 `StorageUnavailable` (database unreachable or out of
space) stored nothing: retry after `Retry-After` seconds.
"""


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        db = Database(settings.database_url, sqlite_synchronous=settings.sqlite_synchronous)
        # PostgreSQL: wake-ups, applied marks and fleet events also cross processes (workers).
        chans = wakeups.channels(db) if not db.is_sqlite and settings.pg_notify == "on" else None
        # SQLite: the processor may run in a child process (APPLY_PROCESS=on); this process
        # then only logs, serves and hears of the applies (app/processing/apply_process.py).
        child = None
        in_child = settings.processor_enabled and settings.apply_process == "on" and db.is_sqlite and db.is_file
        local = settings.model_copy(update={"processor_enabled": False}) if in_child else settings
        kernels = KernelWarmup(
            list(ESTIMATORS),
            processes=settings.warm_kernels_processes,
            # A process that never applies (ingest only) needs no kernels.
            enabled=settings.warm_kernels and local.processor_enabled,
        )
        processor = Processor(
            db,
            local,
            applied_channel=chans.applied if chans else None,
            origin=wakeups.ORIGIN,
            ready_kinds=kernels.applicable_kinds,
        )
        if in_child:
            child = ApplyProcess(settings, kinds=list(ESTIMATORS), on_applied=processor.applied_elsewhere,
                                 on_failed=processor.hub.mark_failed, on_results=processor.results_elsewhere,
                                 on_restart=processor.resync, watched=processor.hub.streams)
            processor.forward = child.notify_many
            processor.hub.on_watch = child.watch
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
        app.state.key_verifier = KeyVerifier(db, settings.auth_cache_ttl_s, settings.lookup_cache_entries)
        app.state.actuator_lookup = ActuatorLookup(db, settings.actuator_cache_ttl_s, settings.lookup_cache_entries)
        app.state.processor = processor
        deliverer = Deliverer(db, settings) if settings.webhooks_enabled else None
        app.state.deliverer = deliverer
        app.state.log_writer = writer
        app.state.ingest_memory = IngestMemory(settings.ingest_memory_bytes, settings.ingest_memory_wait_s)
        app.state.apply_process = child
        app.state.kernels = child if child is not None else kernels
        app.state.kernels_warm = child.kernels_done if child is not None else kernels.done
        if settings.bootstrap_admin_key:
            with db.write() as s:
                ensure_key(s, settings.bootstrap_operator, settings.bootstrap_admin_key,
                           list(SCOPES), name="bootstrap")

        # Batches are accepted (and durable) while the kernels compile; the processor applies a
        # stream once the kinds of all its estimators are ready, so no apply pays a compile.
        def _kind_ready(kind: str) -> None:
            if local.processor_enabled:
                processor.recover()  # wake the streams that waited for this kind

        kernels.on_ready = _kind_ready
        if local.processor_enabled:
            processor.start()
        if child is not None:
            child.start()
        kernels.start()
        if deliverer is not None:
            deliverer.start()
        try:
            yield
        finally:
            kernels.stop(timeout_s=WARM_JOIN_TIMEOUT_S)
            writer.stop()
            if listener is not None:
                listener.stop()
            if child is not None:
                child.stop(settings.shutdown_timeout_s)
            processor.stop()
            if deliverer is not None:
                deliverer.stop()
            db.dispose()

    app = FastAPI(
        title="fleethealth",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        # /docs and /redoc are the system router's, with local assets (no CDN).
        docs_url=None,
        redoc_url=None,
        # No OpenTelemetry here (Prometheus /metrics instead): skip its per-request checks.
        telemetry={"tracing": False, "metrics": False, "logs": False, "operation_spans": False},
    )
    app.mount(
        system_router.DOCS_ASSETS_URL,
        StaticFiles(directory=system_router.DOCS_ASSETS_DIR),
        name="docs-assets",
    )
    install_handlers(app)
    app.openapi = lambda: document_errors(FastAPI.openapi(app))  # type: ignore[method-assign]
    # The common case of a telemetry POST, inside the guard (which refuses control characters
    # first); every other request goes on to the routes.
    app.add_middleware(telemetry_router.LeanIngest)
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
