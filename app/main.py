"""Application factory. The lifespan owns the database, the kernels and the processor."""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from app import __version__
from app.api import fleet, health, stream, system, telemetry
from app.config import Settings, get_settings
from app.db import Database
from app.errors import install_handlers
from app.processing import Processor
from app.security import SCOPES, ensure_key
from estimators.registry import ESTIMATORS

log = logging.getLogger("fleethealth")

DESCRIPTION = """\
Health monitoring of aircraft actuators across a fleet: telemetry ingest per tail number,
stateful estimators per stream, health indicators, remaining useful life and fault isolation.

Authenticate with `Authorization: Bearer <key>`. Errors have one shape:
`{"error": "<Name>", "detail": "<message>"}`.
"""


def warm_kernels() -> None:
    """Compile (or load from numba's cache) every estimator kernel once."""
    for module in ESTIMATORS.values():
        module.warm_up()


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        db = Database(settings.database_url, sqlite_synchronous=settings.sqlite_synchronous)
        processor = Processor(db, settings)
        app.state.db = db
        app.state.settings = settings
        app.state.processor = processor
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
        try:
            yield
        finally:
            warm.join(timeout=60)
            processor.stop()
            db.dispose()

    app = FastAPI(
        title="fleethealth",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    install_handlers(app)
    app.include_router(system.router)
    app.include_router(fleet.router)
    app.include_router(telemetry.router)
    app.include_router(health.router)
    app.include_router(stream.router)
    return app
