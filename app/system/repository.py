"""SQL (and the file system) of the readiness check."""

from __future__ import annotations

import shutil
from pathlib import Path

from sqlalchemy import Engine, text
from sqlalchemy.engine import make_url


def ping(engine: Engine) -> None:
    """Raise unless the database answers."""
    with engine.connect() as conn:
        conn.execute(text("SELECT 1"))


def sqlite_free_bytes(url: str) -> int | None:
    """Free bytes of the file system holding a SQLite database file (None for other backends
    and in-memory databases)."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or not parsed.database or parsed.database == ":memory:":
        return None
    return shutil.disk_usage(Path(parsed.database).resolve().parent).free
