"""Group commit of appends and applies, and ``?wait=`` as an awaitable (both backends)."""

from __future__ import annotations

import asyncio
import re
import threading
from concurrent.futures import Future

import numpy as np
import pytest
from sqlalchemy import func, select

from app.db import Database
from app.errors import StaleBatch
from app.ingest import ParsedBatch
from app.models import Actuator, HealthWindowRow, Stream, TelemetryBatch
from app.processing.processor import Processor
from app.telemetry.service import Ack
from app.telemetry.writer import LogWriter
from app.websocket.hub import Hub
from estimators.registry import ESTIMATORS
from tests.app.conftest import Api, make_settings
from tests.conftest import make_series


def _batch(batch_id: str, t: np.ndarray, s) -> ParsedBatch:  # type: ignore[no-untyped-def]
    idx = np.searchsorted(s.t_s, t)
    return ParsedBatch(batch_id, t, {"current": s.current[idx], "voltage": s.voltage[idx]})


def _pks(db: Database) -> dict[str, int]:
    with db.read() as s:
        return {a.actuator_id: a.id for a in s.scalars(select(Actuator))}


class _Groups:
    """Counts the writer's transactions: the appends each one committed."""

    def __init__(self, writer: LogWriter) -> None:
        self.sizes: list[int] = []
        real = writer._commit

        def counting(group):  # type: ignore[no-untyped-def]
            out = real(group)
            self.sizes.append(len(group))
            return out

        writer._commit = counting  # type: ignore[method-assign]


def test_an_append_whose_waiter_went_away_is_committed_and_the_writer_goes_on(api_noproc: Api, db_url: str) -> None:
    """A WebSocket dropped mid-frame cancels its append's future: the append still commits and
    the writer thread keeps serving the next ones (it used to die on the cancelled future)."""
    api_noproc.setup_actuator(act="a")
    s = make_series(200, seed=6)
    db = Database(db_url)
    pks = _pks(db)
    writer = LogWriter(db)
    writer.start()
    try:
        lock_holder = db.write()
        session = lock_holder.__enter__()
        session.get(Actuator, pks["a"], with_for_update=True)
        if db.is_sqlite:
            session.connection()  # BEGIN IMMEDIATE: the file's write lock
        gone = writer.submit(pks["a"], _batch("a0", s.t_s[0:100], s))
        assert gone.cancel()
        lock_holder.__exit__(None, None, None)
        later = writer.submit(pks["a"], _batch("a1", s.t_s[100:200], s))
        assert later.result(30).seq == 2
        # The sender that never saw its ack resends: the first answer, logged once.
        again = writer.submit(pks["a"], _batch("a0", s.t_s[0:100], s)).result(30)
        assert again.seq == 1 and again.replayed
    finally:
        writer.stop()
    db.dispose()


def test_queued_appends_commit_together_and_a_refused_one_spoils_nothing(api_noproc: Api, db_url: str) -> None:
    for act in ("a", "b"):
        api_noproc.setup_actuator(act=act)
    s = make_series(400, seed=5)
    db = Database(db_url)
    pks = _pks(db)
    writer = LogWriter(db)
    groups = _Groups(writer)
    writer.start()
    try:
        # Hold the writer on a first append (its transaction waits for the lock we hold), so that
        # the others queue behind it.
        lock_holder = db.write()
        session = lock_holder.__enter__()
        session.get(Actuator, pks["a"], with_for_update=True)
        if db.is_sqlite:
            session.connection()  # BEGIN IMMEDIATE: the file's write lock
        first = writer.submit(pks["a"], _batch("a0", s.t_s[0:100], s))
        futures: list[Future[Ack]] = [
            writer.submit(pks["b"], _batch("b0", s.t_s[0:100], s)),
            writer.submit(pks["a"], _batch("a1", s.t_s[100:200], s)),
            writer.submit(pks["a"], _batch("stale", s.t_s[50:60], s)),  # before a1 in time: refused
            writer.submit(pks["b"], _batch("b1", s.t_s[100:200], s)),
            writer.submit(pks["a"], _batch("a0", s.t_s[0:100], s)),  # a retry: the first answer
        ]
        assert not first.done()
        lock_holder.__exit__(None, None, None)
        assert first.result(30).seq == 1
        acks = [f.result(30) if i != 2 else None for i, f in enumerate(futures)]
        with pytest.raises(StaleBatch):
            futures[2].result(30)
    finally:
        writer.stop()
    assert [a.seq for a in acks if a is not None] == [1, 2, 2, 1]
    assert acks[4] is not None and acks[4].replayed
    # Six appends, at most two transactions: those queued while the writer waited for the lock
    # went together (how many the writer had taken before it blocked is a race; one by one
    # they would take six).
    assert sum(groups.sizes) == 6 and len(groups.sizes) <= 2
    with db.read() as session:
        rows = session.execute(select(TelemetryBatch.batch_id, TelemetryBatch.seq).order_by(TelemetryBatch.id)).all()
        logged = {a.actuator_id: a.last_logged_seq for a in session.scalars(select(Actuator))}
    db.dispose()
    assert sorted(tuple(r) for r in rows) == [("a0", 1), ("a1", 2), ("b0", 1), ("b1", 2)]
    assert logged == {"a": 2, "b": 2}


def test_each_ack_waits_for_its_own_commit(api_noproc: Api, db_url: str) -> None:
    """A future resolves only after its group committed: a second engine sees the batch then."""
    api_noproc.setup_actuator()
    s = make_series(1000, seed=6)
    db = Database(db_url)
    pk = _pks(db)["ema1"]
    writer = LogWriter(db)
    writer.start()
    other = Database(db_url)
    seen: list[bool] = []
    try:
        futures = [writer.submit(pk, _batch(f"b{k}", s.t_s[100 * k:100 * (k + 1)], s)) for k in range(10)]
        for f in futures:
            ack = f.result(30)
            with other.read() as session:
                seen.append(session.scalar(
                    select(func.count()).select_from(TelemetryBatch).where(TelemetryBatch.seq == ack.seq)) == 1)
    finally:
        writer.stop()
        other.dispose()
        db.dispose()
    assert seen == [True] * 10


def test_many_streams_applied_in_one_transaction_and_a_failing_one_alone_rolls_back(
    api_noproc: Api, db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    acts = ["s0", "s1", "s2", "bad"]
    for act in acts:
        api_noproc.setup_actuator(act=act)
    for act in acts:
        # The failing stream's samples come later in time: the step recognises them by that.
        s = make_series(500, seed=7, t0=100.0 if act == "bad" else 0.0)
        for k in range(2):
            sl = slice(250 * k, 250 * (k + 1))
            r = api_noproc.send_arrow("N1", act, f"{act}-{k}", s.t_s[sl], {"current": s.current[sl],
                                      "voltage": s.voltage[sl]}, wait=0)
            assert r.status_code == 202, r.text
    db = Database(db_url)
    pks = _pks(db)
    fakf = ESTIMATORS["fakf"]
    real_step = fakf.step

    def step(cfg, state, batch):  # type: ignore[no-untyped-def]
        out = real_step(cfg, state, batch)  # the failure comes after the estimator ran
        if float(batch.t_s[0]) >= 100.0:
            raise RuntimeError("simulated failure of one stream")
        return out

    # The start-up warm-up calls the module's step too: let it finish before the patch.
    assert api_noproc.app.state.kernels_warm.wait(300)
    monkeypatch.setattr(fakf, "step", step)
    # A generous time budget: the point is that the three streams share one transaction.
    processor = Processor(db, make_settings(db_url, processor_max_attempts=1, processor_txn_budget_s=60.0,
                                         processor_compute_budget_s=60.0))
    writes: list[int] = []
    real_write = db.write

    def counting_write(**kw):  # type: ignore[no-untyped-def]
        writes.append(1)
        return real_write(**kw)

    monkeypatch.setattr(db, "write", counting_write)
    applied = processor.apply_streams([pks[a] for a in acts])
    assert applied == 6
    with db.read() as session:
        marks = {pk: (seq, failure) for pk, seq, failure in
                 session.execute(select(Stream.actuator_pk, Stream.last_applied_seq, Stream.failure))}
        bad_windows = session.scalar(select(func.count()).select_from(HealthWindowRow)
                                     .where(HealthWindowRow.actuator_pk == pks["bad"]))
    db.dispose()
    for act in ("s0", "s1", "s2"):
        assert marks[pks[act]] == (2, None)
    assert marks[pks["bad"]][0] == 0 and "simulated failure" in (marks[pks["bad"]][1] or "")
    assert bad_windows == 0
    # One transaction applied the three good streams; one more marked "bad" failed.
    assert len(writes) == 2


def test_wait_is_an_awaitable_resolved_by_the_commit() -> None:
    hub = Hub()

    async def run() -> tuple[tuple[bool, str | None], tuple[bool, str | None], bool]:
        w5 = hub.watch_applied(1, 5)
        w9 = hub.watch_applied(1, 9)
        other = hub.watch_applied(2, 1)
        # Resolved from another thread, as the processor or the notification listener does.
        threading.Thread(target=hub.mark_applied, args=(1, 7)).start()
        got5 = await asyncio.wait_for(w5.future, 10)
        assert not w9.future.done()
        threading.Thread(target=hub.mark_failed, args=(1, "broken")).start()
        got9 = await asyncio.wait_for(w9.future, 10)
        hub.unwatch(2, other)
        return got5, got9, other.future.done()

    got5, got9, other_done = asyncio.run(run())
    assert got5 == (True, None)
    assert got9 == (False, "broken")
    assert not other_done
    assert hub.watched_streams() == []


def test_each_write_transaction_has_its_own_durability(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """SQLite: a durable write after a recomputable one on the same pooled connection waits
    for the disk again (``synchronous`` is set only when it changes, never left behind)."""
    from sqlalchemy import text

    from tests.conftest import migrated_sqlite

    db = Database(migrated_sqlite(tmp_path / "sync.db"))
    seen = []
    for durable in (False, True, True, False, False, True):
        with db.write(durable=durable) as s:
            seen.append(s.execute(text("PRAGMA synchronous")).scalar())
    db.dispose()
    assert seen == [1, 2, 2, 1, 1, 2]  # NORMAL, FULL


def _logged_streams(api: Api, acts: list[str]) -> None:
    for act in acts:
        api.setup_actuator(act=act)
        s = make_series(500, seed=7)
        for k in range(2):
            sl = slice(250 * k, 250 * (k + 1))
            r = api.send_arrow("N1", act, f"{act}-{k}", s.t_s[sl], {"current": s.current[sl],
                               "voltage": s.voltage[sl]}, wait=0)
            assert r.status_code == 202, r.text


def _writes_seen(db: Database) -> list[str]:
    """The write statements the engine runs from now on, as ``"UPDATE streams"``,
    ``"INSERT health_windows"``, ``"SAVEPOINT sa_savepoint_1"``."""
    from sqlalchemy import event

    statements: list[str] = []

    def seen(conn, cursor, statement, params, context, executemany):  # type: ignore[no-untyped-def]
        m = re.match(r"\s*(UPDATE|INSERT INTO|SAVEPOINT)\s+(\w+)", statement, re.IGNORECASE)
        if m:
            statements.append(f"{m.group(1).split()[0].upper()} {m.group(2)}")

    event.listen(db.engine, "before_cursor_execute", seen)
    return statements


def test_a_group_is_stored_with_one_statement_per_table_and_one_savepoint(
    api_noproc: Api, db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Not a savepoint and a set of statements per stream: one of each for the whole group."""
    acts = ["s0", "s1", "s2"]
    _logged_streams(api_noproc, acts)
    db = Database(db_url)
    pks = _pks(db)
    statements = _writes_seen(db)
    processor = Processor(db, make_settings(db_url, processor_txn_budget_s=60.0,
                                         processor_compute_budget_s=60.0))
    assert processor.apply_streams([pks[a] for a in acts]) == 6
    with db.read() as session:
        marks = sorted(session.scalars(select(Stream.last_applied_seq)))
    db.dispose()
    assert marks == [2, 2, 2]
    assert sum(s.startswith("SAVEPOINT") for s in statements) <= 1
    updates = [s for s in statements if s.startswith("UPDATE")]
    assert updates.count("UPDATE streams") == 1 and updates.count("UPDATE estimator_states") == 1
    assert statements.count("INSERT health_windows") <= 1


@pytest.mark.parametrize(("compute_budget_s", "groups"), [(60.0, 1), (1e-9, 3)])
def test_a_group_computed_outside_the_lock_is_bounded_by_the_compute_budget(
    api_noproc: Api, db_url: str, compute_budget_s: float, groups: int
) -> None:
    """SQLite, computed outside the write lock (as the apply process does): the group's length
    is bounded by ``processor_compute_budget_s``, not by the write transaction's
    ``processor_txn_budget_s``: with the latter spent at once, the three streams still share
    one group while the compute budget lasts, and take one group each when it does not."""
    if not db_url.startswith("sqlite"):
        pytest.skip("PostgreSQL applies in one transaction under the streams' row locks")
    acts = ["s0", "s1", "s2"]
    _logged_streams(api_noproc, acts)
    db = Database(db_url)
    pks = _pks(db)
    statements = _writes_seen(db)
    settings = make_settings(db_url, processor_txn_budget_s=1e-9, processor_compute_budget_s=compute_budget_s)
    processor = Processor(db, settings, in_lock_applies=False)
    assert processor.apply_streams([pks[a] for a in acts]) == 6
    with db.read() as session:
        marks = sorted(session.scalars(select(Stream.last_applied_seq)))
    db.dispose()
    assert marks == [2, 2, 2]
    assert statements.count("UPDATE streams") == groups  # one per group


@pytest.mark.parametrize(
    ("samples", "compute_budget_s", "groups"),
    [(1200, 60.0, 1), (1200, 1e-9, 3), (120, 60.0, 3)],
)
def test_a_postgresql_group_of_large_applies_is_bounded_by_the_compute_budget(
    api_noproc: Api, db_url: str, samples: int, compute_budget_s: float, groups: int
) -> None:
    """PostgreSQL: a group whose applies average ``LARGE_APPLY_SAMPLES`` samples or more per
    stream may run for ``processor_compute_budget_s``; smaller ones keep the transaction's
    ``processor_txn_budget_s``. With the latter spent at once, three streams of 1,200-sample
    applies share one group while the compute budget lasts (one each when it does not), and
    three of 120 samples take one group each whatever the compute budget."""
    from app.processing.processor import LARGE_APPLY_SAMPLES

    if db_url.startswith("sqlite"):
        pytest.skip("SQLite bounds its groups computed outside the write lock by the compute budget")
    assert (samples >= LARGE_APPLY_SAMPLES) == (samples == 1200)
    acts = ["s0", "s1", "s2"]
    s = make_series(samples, seed=7)
    for act in acts:
        api_noproc.setup_actuator(act=act)
        r = api_noproc.send_arrow("N1", act, f"{act}-0", s.t_s, {"current": s.current, "voltage": s.voltage},
                                  wait=0)
        assert r.status_code == 202, r.text
    db = Database(db_url)
    pks = _pks(db)
    statements = _writes_seen(db)
    settings = make_settings(db_url, processor_txn_budget_s=1e-9, processor_compute_budget_s=compute_budget_s)
    assert Processor(db, settings).apply_streams([pks[a] for a in acts]) == 3
    with db.read() as session:
        marks = sorted(session.scalars(select(Stream.last_applied_seq)))
    db.dispose()
    assert marks == [1, 1, 1]
    assert statements.count("UPDATE streams") == groups  # one per group


def test_a_group_whose_store_fails_is_stored_stream_by_stream(
    api_noproc: Api, db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stream whose rows cannot be stored spoils the group's common store: that is rolled
    back, the streams are stored one by one, and only the faulty one is left out (once each:
    nothing of the rolled-back store remains)."""
    from app.events import service as events
    from app.processing import processor as processor_module

    acts = ["s0", "s1", "bad"]
    _logged_streams(api_noproc, acts)
    db = Database(db_url)
    pks = _pks(db)
    real_record = events.record_apply

    def record(session, result):  # type: ignore[no-untyped-def]
        if result.actuator_pk == pks["bad"]:
            raise RuntimeError("simulated store failure of one stream")
        return real_record(session, result)

    monkeypatch.setattr(events, "record_apply", record)
    splits = processor_module.GROUP_STORE_SPLITS._value.get()
    processor = Processor(db, make_settings(db_url, processor_max_attempts=1, processor_txn_budget_s=60.0,
                                         processor_compute_budget_s=60.0))
    assert processor.apply_streams([pks[a] for a in acts]) == 4
    with db.read() as session:
        marks = {pk: (seq, failure) for pk, seq, failure in
                 session.execute(select(Stream.actuator_pk, Stream.last_applied_seq, Stream.failure))}
        windows = dict(session.execute(select(HealthWindowRow.actuator_pk, func.count())
                                       .group_by(HealthWindowRow.actuator_pk)).all())
    db.dispose()
    assert processor_module.GROUP_STORE_SPLITS._value.get() == splits + 1
    for act in ("s0", "s1"):
        assert marks[pks[act]] == (2, None)
    assert marks[pks["bad"]][0] == 0 and "simulated store failure" in (marks[pks["bad"]][1] or "")
    assert pks["bad"] not in windows
    assert windows[pks["s0"]] == windows[pks["s1"]] > 0
