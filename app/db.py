"""Engine, sessions and the declarative base.

SQLite runs in WAL mode. Write transactions start with ``BEGIN IMMEDIATE`` so that two writers
never both hold a read snapshot and then fail to upgrade; read transactions stay deferred so that
readers never wait on writers. SQLite has one write lock per file: within a process, writers
queue for it on a mutex (woken the moment it is free, in arrival order) instead of polling the
file lock through ``busy_timeout``; the log writer and the processor are the only frequent
writers. Across processes (``serve`` and its apply process, or a CLI command next to a server)
the writer holding that mutex then takes an exclusive ``flock`` on ``<database>.writelock``,
which blocks in the kernel until the other process's write transaction ends: no process polls.
On PostgreSQL the per-stream lease is a row lock (``SELECT ... FOR UPDATE``) on the actuator
row.
"""

from __future__ import annotations

import fcntl
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, MetaData, create_engine, event
from sqlalchemy.engine import ExceptionContext, make_url
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


def normalize_url(url: str) -> str:
    """Accept ``postgresql://`` and ``postgres://`` and use the psycopg 3 driver for them."""
    if url.startswith("postgres://"):
        url = "postgresql://" + url[len("postgres://") :]
    if url.startswith("postgresql://"):
        url = "postgresql+psycopg://" + url[len("postgresql://") :]
    return url


def is_sqlite(url: str) -> bool:
    return make_url(normalize_url(url)).get_backend_name() == "sqlite"


#: SQLite connections kept open in the pool (more are opened, up to twice as many, and closed on return).
SQLITE_POOL_SIZE = 16


def make_engine(url: str, *, sqlite_synchronous: str = "FULL", echo: bool = False) -> Engine:
    url = normalize_url(url)
    if is_sqlite(url):
        db = make_url(url).database
        if db and db != ":memory:":
            Path(db).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(
            url, echo=echo, connect_args={"timeout": 60.0, "check_same_thread": False},
            # Kept open, not opened per use: the threads that read (the request pool, the
            # parse threads, the streaming watchers) check out more than QueuePool's default 5
            # at once, and each connection opened beyond it costs its WAL set-up and PRAGMAs,
            # to be closed again on return.
            pool_size=SQLITE_POOL_SIZE, max_overflow=2 * SQLITE_POOL_SIZE,
        )
        _install_sqlite_hooks(engine, sqlite_synchronous)
        return engine
    return create_engine(url, echo=echo, pool_pre_ping=True, pool_size=10, max_overflow=20)


def _install_sqlite_hooks(engine: Engine, synchronous: str) -> None:
    @event.listens_for(engine, "connect")
    def _connect(dbapi_conn: Any, record: Any) -> None:
        # Let SQLAlchemy, not pysqlite, emit BEGIN (the documented pysqlite workaround).
        dbapi_conn.isolation_level = None
        cur = dbapi_conn.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute(f"PRAGMA synchronous={synchronous}")
        record.info["sqlite_synchronous"] = synchronous
        cur.execute("PRAGMA foreign_keys=ON")
        cur.execute("PRAGMA busy_timeout=60000")
        cur.close()

    @event.listens_for(engine, "begin")
    def _begin(conn: Any) -> None:
        opts = conn.get_execution_options()
        mode = opts.get("sqlite_begin", "DEFERRED")
        if mode == "IMMEDIATE":
            # Per transaction (it cannot change inside one): see Database.write(durable=...);
            # set only when this connection's last transaction had another.
            wanted = opts.get("sqlite_synchronous", synchronous)
            info = conn.connection.info
            if info.get("sqlite_synchronous") != wanted:
                conn.exec_driver_sql(f"PRAGMA synchronous={wanted}")
                info["sqlite_synchronous"] = wanted
        conn.exec_driver_sql(f"BEGIN {mode}")


#: How long a storage fault keeps /readyz "not ready" when no write has succeeded since.
STORAGE_FAULT_MEMORY_S = 30.0


class StorageHealth:
    """The last storage fault (a database error of operation: disk full, I/O error, lost
    connection) and whether a write transaction has committed since; read by /readyz, which a
    plain ``SELECT 1`` cannot tell about a full disk."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._fault: str | None = None
        self._fault_at = 0.0

    def fault(self, reason: str) -> None:
        with self._lock:
            self._fault, self._fault_at = reason, time.monotonic()

    def committed(self) -> None:
        with self._lock:
            self._fault = None

    def recent_fault(self) -> str | None:
        with self._lock:
            if self._fault is not None and time.monotonic() - self._fault_at < STORAGE_FAULT_MEMORY_S:
                return self._fault
            return None


class FairWriteLock:
    """A re-entrant lock granted in arrival order (tickets).

    ``threading.RLock`` lets the thread that releases it take it straight back: the processor,
    applying transaction after transaction, would starve the log writer (and every
    acknowledgement behind it). With tickets, a writer that queued is served before the next
    transaction of the thread that just committed.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._next_ticket = 0
        self._serving = 0
        self._owner: int | None = None
        self._depth = 0

    def __enter__(self) -> None:
        me = threading.get_ident()
        with self._cond:
            if self._owner == me:
                self._depth += 1
                return
            ticket = self._next_ticket
            self._next_ticket += 1
            while self._serving != ticket:
                self._cond.wait()
            self._owner, self._depth = me, 1

    def try_enter(self) -> bool:
        """Take the lock only if nobody holds it or waits for it (or this thread holds it);
        False, without waiting, otherwise."""
        me = threading.get_ident()
        with self._cond:
            if self._owner == me:
                self._depth += 1
                return True
            if self._serving != self._next_ticket:  # held, or a writer queued
                return False
            self._next_ticket += 1
            self._owner, self._depth = me, 1
            return True

    def __exit__(self, *exc: object) -> None:
        with self._cond:
            self._depth -= 1
            if self._depth == 0:
                self._owner = None
                self._serving += 1
                self._cond.notify_all()


class FileWriteLock:
    """An exclusive ``flock`` on a file beside the SQLite database, held for each write
    transaction: the write lock across processes, taken by a blocking call that sleeps in the
    kernel until the holder releases it (or exits: the kernel releases a dead process's lock).
    One per process and database; the in-process :class:`FairWriteLock` is taken first, so
    only one thread of a process ever waits here."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)

    def acquire(self, blocking: bool = True) -> bool:
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX if blocking else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        return True

    def release(self) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_UN)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __del__(self) -> None:  # a Database dropped without dispose() (tests) keeps no descriptor
        self.close()


def _file_write_lock(database: str) -> FileWriteLock | None:
    """The cross-process write lock of a SQLite database file (None where the lock file cannot
    be created: writers then fall back to SQLite's busy wait)."""
    try:
        return FileWriteLock(str(Path(database).resolve()) + ".writelock")
    except OSError:
        return None


class Database:
    """Owns the engine and the two session factories (read and write)."""

    def __init__(self, url: str, *, sqlite_synchronous: str = "FULL") -> None:
        self.url = normalize_url(url)
        self.engine = make_engine(self.url, sqlite_synchronous=sqlite_synchronous)
        self.is_sqlite = is_sqlite(self.url)
        database = make_url(self.url).database
        #: A SQLite database in a file (other processes can open it), or PostgreSQL.
        self.is_file = not self.is_sqlite or bool(database and database != ":memory:"
                                                  and not database.startswith("file:"))
        write_bind = (
            self.engine.execution_options(sqlite_begin="IMMEDIATE")
            if self.is_sqlite
            else self.engine
        )
        # Re-entrant (a write nested in another on the same thread must not deadlock on itself)
        # and first come, first served.
        self._write_mutex: FairWriteLock | None = FairWriteLock() if self.is_sqlite else None
        self._file_lock = _file_write_lock(str(database)) if self.is_sqlite and self.is_file else None
        self._holder: int | None = None  # the thread holding the cross-process lock
        self._read = sessionmaker(bind=self.engine, expire_on_commit=False)
        self._write = sessionmaker(bind=write_bind, expire_on_commit=False)
        # Writes whose loss in a power cut is harmless (they are recomputed from what is durable).
        self._write_recomputable = sessionmaker(
            bind=write_bind.execution_options(sqlite_synchronous="NORMAL") if self.is_sqlite else self.engine,
            expire_on_commit=False,
        )
        self.storage = StorageHealth()

        @event.listens_for(self.engine, "handle_error")
        def _fault(ctx: ExceptionContext) -> None:
            if isinstance(ctx.sqlalchemy_exception, OperationalError) or ctx.is_disconnect:
                orig = ctx.original_exception
                self.storage.fault(f"{type(orig).__name__}: {str(orig).strip().splitlines()[0] if str(orig).strip() else ''}"[:300])

        @event.listens_for(self._write, "after_commit")
        @event.listens_for(self._write_recomputable, "after_commit")
        def _committed(_: Session) -> None:
            self.storage.committed()

    @contextmanager
    def read(self) -> Iterator[Session]:
        with self._read() as session, session.begin():
            yield session

    @contextmanager
    def write(self, *, durable: bool = True) -> Iterator[Session]:
        """One unit of work: committed when the block exits, rolled back on an exception.

        ``durable=False`` is for transactions that can be lost in an operating-system crash or a
        power cut without harm, because they are recomputed from durable data (an apply is redone
        from the telemetry log): the commit does not wait for the disk (SQLite WAL
        ``synchronous=NORMAL``, PostgreSQL ``synchronous_commit=off``). Commits stay ordered: a
        later durable commit makes every earlier one durable too, and a process crash loses
        nothing that committed.
        """
        factory = self._write if durable else self._write_recomputable
        if self._write_mutex is None:
            with factory() as session, session.begin():
                if not durable:
                    session.connection().exec_driver_sql("SET LOCAL synchronous_commit TO OFF")
                yield session
            return
        with self._write_mutex, self._across_processes(), factory() as session, session.begin():
            yield session

    @contextmanager
    def _across_processes(self) -> Iterator[None]:
        """Hold the cross-process write lock (under the in-process mutex; re-entrant through it:
        a nested write of the same thread takes nothing more)."""
        lock = self._file_lock
        if lock is None or self._held_here():
            yield
            return
        lock.acquire()
        self._holder = threading.get_ident()
        try:
            yield
        finally:
            self._holder = None
            lock.release()

    def _held_here(self) -> bool:
        return self._holder == threading.get_ident()

    @contextmanager
    def write_if_free(self, *, durable: bool = True) -> Iterator[Session | None]:
        """SQLite: :meth:`write` when no other writer of this process holds or waits for the
        write lock and no other process holds it, else None at once (the caller does its work
        another way). PostgreSQL: always None (its writers do not share one lock)."""
        if self._write_mutex is None or not self._write_mutex.try_enter():
            yield None
            return
        try:
            lock = self._file_lock
            take = lock is not None and not self._held_here()
            if take and lock is not None and not lock.acquire(blocking=False):
                yield None  # another process writes
                return
            if take:
                self._holder = threading.get_ident()
            try:
                factory = self._write if durable else self._write_recomputable
                with factory() as session, session.begin():
                    yield session
            finally:
                if take and lock is not None:
                    self._holder = None
                    lock.release()
        finally:
            self._write_mutex.__exit__()

    def dispose(self) -> None:
        self.engine.dispose()
        if self._file_lock is not None:
            self._file_lock.close()
            self._file_lock = None
