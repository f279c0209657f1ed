"""The decoded-batch shortcut (``app.processing.recent``): the log writer holds each batch it
commits, decoded, from before its commit, so that an apply woken by that very commit (on
PostgreSQL its ``NOTIFY``) takes it instead of decoding it from the log; a batch whose commit
failed is never taken (both backends)."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, select
from sqlalchemy.orm import Session

from app.db import Database
from app.ingest import ParsedBatch
from app.main import create_app
from app.models import Stream
from app.processing.processor import Processor
from app.processing.recent import RecentBatches
from app.telemetry.writer import LogWriter
from tests.app.conftest import Api, actuator_pk, make_settings
from tests.conftest import make_series, migrated_pg_schema

WRITER_THREAD = "fleethealth-log-writer"


def _batch(batch_id: str, lo: int, hi: int) -> ParsedBatch:
    s = make_series(1000, seed=11)
    return ParsedBatch(batch_id, s.t_s[lo:hi], {"current": s.current[lo:hi], "voltage": s.voltage[lo:hi]})


@pytest.fixture
def writer_commits() -> Iterator[list[threading.Event]]:
    """Hooks run in the log writer's thread right after each of its commits returned (before the
    writer goes on): append a callable to the list."""
    hooks: list = []

    def after_commit(session: Session) -> None:
        if threading.current_thread().name == WRITER_THREAD:
            for hook in list(hooks):
                hook()

    event.listen(Session, "after_commit", after_commit)
    try:
        yield hooks
    finally:
        event.remove(Session, "after_commit", after_commit)


def test_the_batch_is_held_when_its_commit_lands(api_noproc: Api, db_url: str, writer_commits: list) -> None:
    api_noproc.setup_actuator()
    db = Database(db_url)
    recent = RecentBatches()
    writer = LogWriter(db, recent=recent)
    held_at_commit: list[int] = []
    writer_commits.append(lambda: held_at_commit.append(len(recent)))
    writer.start()
    try:
        ack = writer.submit(actuator_pk(db), _batch("b0", 0, 200)).result(30)
    finally:
        writer.stop()
        db.dispose()
    # Put before the commit: a processor woken by the commit finds it (after it, it would not).
    assert held_at_commit == [1]
    got = recent.take(ack.actuator_pk, ack.seq, "b0")
    assert got is not None and got.t_s.flags.writeable and got.t_s.shape == (200,)
    assert len(recent) == 0


@pytest.fixture
def pg_url() -> Iterator[str]:
    with migrated_pg_schema() as url:
        yield url


@pytest.mark.postgres
def test_an_apply_woken_by_the_commit_takes_the_decoded_batch(pg_url: str, writer_commits: list) -> None:
    """PostgreSQL: the race of the commit's NOTIFY, made certain: an apply starts the moment
    the writer's commit returned and reaches the shortcut before the writer runs on. It takes
    the held batch (it waits for the writer's word that the commit succeeded), nothing is
    decoded from the log and nothing stays held. (SQLite cannot race so: the writer holds the
    file's write lock until it runs on.)"""
    db_url = pg_url
    with TestClient(create_app(make_settings(db_url, processor_enabled=False))) as client:
        api = Api(client)
        api.setup_actuator()
        assert api.app.state.kernels_warm.wait(300)
    db = Database(db_url)
    pk = actuator_pk(db)
    processor = Processor(db, make_settings(db_url))
    recent = processor.recent
    assert recent is not None
    entered, returned = threading.Event(), threading.Event()
    real_take = recent.take

    def take(actuator_pk: int, seq: int, batch_id: str):  # type: ignore[no-untyped-def]
        entered.set()
        try:
            return real_take(actuator_pk, seq, batch_id)
        finally:
            returned.set()

    recent.take = take  # type: ignore[method-assign]
    applies: list[threading.Thread] = []

    def apply_now() -> None:
        th = threading.Thread(target=processor.apply_streams, args=([pk],))
        applies.append(th)
        th.start()
        # Hold the writer until the apply is inside the shortcut, and a little longer.
        assert entered.wait(300)
        returned.wait(0.3)

    writer_commits.append(apply_now)
    writer = LogWriter(db, recent=recent)
    writer.start()
    try:
        writer.submit(pk, _batch("b0", 0, 300)).result(90)
    finally:
        writer.stop()
    for th in applies:
        th.join(600)
    with db.read() as s:
        applied = s.scalar(select(Stream.last_applied_seq).where(Stream.actuator_pk == pk))
    db.dispose()
    assert applied == 1
    assert (recent.hits, recent.misses, len(recent)) == (1, 0, 0)


def test_a_failed_commit_leaves_nothing_held(api_noproc: Api, db_url: str) -> None:
    api_noproc.setup_actuator()
    db = Database(db_url)
    recent = RecentBatches()
    writer = LogWriter(db, recent=recent)
    fail = [True]

    def before_commit(session: Session) -> None:
        if threading.current_thread().name == WRITER_THREAD and fail and fail.pop():
            raise RuntimeError("simulated commit failure")

    event.listen(Session, "before_commit", before_commit)
    writer.start()
    try:
        with pytest.raises(RuntimeError, match="simulated"):
            writer.submit(actuator_pk(db), _batch("b0", 0, 100)).result(30)
        assert len(recent) == 0
        # The position the failed append had is given to the next batch: the held one is it.
        ack = writer.submit(actuator_pk(db), _batch("b1", 100, 200)).result(30)
    finally:
        event.remove(Session, "before_commit", before_commit)
        writer.stop()
        db.dispose()
    assert ack.seq == 1
    assert recent.take(ack.actuator_pk, 1, "b0") is None
    assert len(recent) == 0  # a take of the wrong batch id lets the entry go too
    assert recent.misses == 1


def test_a_taker_waits_for_the_writers_verdict() -> None:
    t = np.arange(10.0)
    chans = {"x": np.ones(10)}
    recent = RecentBatches(confirm_wait_s=30.0)
    kept = recent.put(1, 1, "a", t, chans, False)
    dropped = recent.put(1, 2, "b", t, chans, False)
    assert kept is not None and dropped is not None
    got: dict[int, object] = {}

    def take(seq: int, batch_id: str) -> None:
        got[seq] = recent.take(1, seq, batch_id)

    takers = [threading.Thread(target=take, args=a) for a in ((1, "a"), (2, "b"))]
    for th in takers:
        th.start()
    takers[0].join(0.2)
    assert takers[0].is_alive() and takers[1].is_alive()  # tentative: nobody takes yet
    recent.confirm([kept])
    recent.drop([dropped])
    for th in takers:
        th.join(30)
    assert got[1] is not None and got[2] is None
    assert (recent.hits, recent.misses, len(recent)) == (1, 1, 0)


def test_a_tentative_entry_is_not_taken_past_the_wait() -> None:
    recent = RecentBatches(confirm_wait_s=0.05)
    recent.put(1, 1, "a", np.arange(3.0), {"x": np.zeros(3)}, False)
    assert recent.take(1, 1, "a") is None
    assert len(recent) == 1  # still the writer's to confirm or drop


def test_at_the_bound_the_oldest_stay_unless_stale() -> None:
    """Under a backlog the held batches are the next ones applied: a new batch is not held at
    the bound; an entry held past ``stale_s`` (applied elsewhere) gives way."""
    recent = RecentBatches(max_samples=20, stale_s=3600.0)
    keys = [recent.put(1, seq, f"b{seq}", np.arange(10.0), {"x": np.zeros(10)}, False) for seq in (1, 2, 3)]
    assert keys[2] is None and len(recent) == 2
    recent.confirm([k for k in keys if k is not None])
    assert recent.take(1, 1, "b1") is not None  # the oldest: still held
    recent.stale_s = 0.0  # every held entry is now stale
    assert recent.put(1, 4, "b4", np.arange(10.0), {"x": np.zeros(10)}, False) is not None
    assert recent.put(1, 5, "b5", np.arange(10.0), {"x": np.zeros(10)}, False) is not None
    assert recent.take(1, 2, "b2") is None  # gave way
    assert len(recent) == 2
