"""Shared test fixtures: databases (a real SQLite file and a real PostgreSQL), data, clients."""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import pytest
from sqlalchemy import create_engine, text

PG_URL = os.environ.get("FLEETHEALTH_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
REQUIRE_PG = os.environ.get("FLEETHEALTH_REQUIRE_PG") == "1"


def _pg_available() -> str | None:
    try:
        eng = create_engine(PG_URL, connect_args={"connect_timeout": 3})
        with eng.connect() as c:
            c.execute(text("SELECT 1"))
        eng.dispose()
        return None
    except Exception as exc:  # any failure: report why
        return f"PostgreSQL at {PG_URL} is not reachable: {type(exc).__name__}: {exc}"


_PG_PROBLEM = _pg_available()


@pytest.fixture(scope="session", autouse=True)
def kernels_prepared_beside_the_tests() -> Iterator[None]:
    """Every estimator kind's kernels prepared from the session's start, one kind at a time in
    a child process beside the tests (the server's own warm-up, ``app.kernels``).

    On a cold numba cache (a fresh clone) whichever test first applied a kind used to wait for
    its whole compile, and each test's server that stopped meanwhile threw its half-done compile
    away; now the compiles overlap the tests, the servers' children wait for the compile lock
    and load from the cache, and this process holds every kernel once it is done.
    """
    from app.kernels import KernelWarmup
    from estimators.registry import ESTIMATORS

    warmup = KernelWarmup(list(ESTIMATORS), processes=1)
    warmup.start()
    yield
    warmup.stop()


_SQLITE_TEMPLATE: list[str] = []


def migrated_sqlite(path: os.PathLike[str] | str) -> str:
    """The URL of a SQLite file at ``path`` migrated to head: a copy of one file that Alembic
    migrated once per session (the same bytes as migrating each file, without the cost)."""
    from app.migrate import upgrade

    if not _SQLITE_TEMPLATE:
        template = os.path.join(tempfile.mkdtemp(prefix="fleethealth-schema-"), "template.db")
        upgrade(f"sqlite:///{template}")
        _SQLITE_TEMPLATE.append(template)
    shutil.copyfile(_SQLITE_TEMPLATE[0], path)
    return f"sqlite:///{path}"


@contextmanager
def migrated_pg_schema() -> Iterator[str]:
    """A fresh schema in the test PostgreSQL, migrated to head, dropped afterwards (the test is
    skipped, or failed with FLEETHEALTH_REQUIRE_PG=1, when PostgreSQL is not reachable)."""
    from app.migrate import upgrade

    if _PG_PROBLEM:
        if REQUIRE_PG:
            pytest.fail(_PG_PROBLEM)
        pytest.skip(_PG_PROBLEM)
    schema = "t_" + uuid.uuid4().hex[:12]
    admin = create_engine(PG_URL)
    with admin.begin() as c:
        c.execute(text(f'CREATE SCHEMA "{schema}"'))
    url = f"{PG_URL}?options=-csearch_path%3D{schema}"
    try:
        upgrade(url)
        yield url
    finally:
        with admin.begin() as c:
            c.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def db_url(request: pytest.FixtureRequest, tmp_path) -> Iterator[str]:  # type: ignore[no-untyped-def]
    """A migrated, empty database: a SQLite file, or a fresh schema in PostgreSQL."""
    if request.param == "sqlite":
        yield migrated_sqlite(tmp_path / "fleethealth.db")
        return
    with migrated_pg_schema() as url:
        yield url


@dataclass(frozen=True)
class Series:
    t_s: np.ndarray
    current: np.ndarray
    voltage: np.ndarray


def make_series(n: int, seed: int = 0, dt: float = 0.001, t0: float = 0.0) -> Series:
    """Current and noisy voltage from a known stable second-order ARX model (eq. 15 form)."""
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) * dt
    i = 3.0 * np.sin(2 * np.pi * 0.7 * t) + 1.5 * np.sin(2 * np.pi * 3.1 * t) + rng.normal(0, 0.2, n)
    v = np.zeros(n)
    for k in range(2, n):
        v[k] = 0.45 * v[k - 1] + 0.04 * v[k - 2] - 0.8 * i[k] + 5.9 * i[k - 1] - 3.6 * i[k - 2]
    return Series(t_s=t, current=i, voltage=v + rng.normal(0, 0.8, n))
