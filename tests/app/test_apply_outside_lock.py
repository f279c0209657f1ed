"""Applies computed outside the write lock (SQLite): the estimators run while another writer
holds the database's one write lock, and a stream whose rows changed between the computation
and the store is applied again under the lock, so each batch is still applied once, in order.
A small apply while nobody holds or waits for the lock runs in one write transaction instead,
with the same outputs."""

from __future__ import annotations

import threading

import pytest
from sqlalchemy import event, select

from app.db import Database
from app.models import EstimatorState, HealthWindowRow, SampleOutputRow, Stream
from app.processing import processor as processor_module
from app.processing import service
from app.processing.processor import Processor
from estimators.registry import ESTIMATORS
from tests.app.conftest import Api, actuator_pk, make_settings

BATCH = 250


def _applied(db: Database, pk: int) -> tuple[int, list[int], list[int]]:
    """The stream's applied mark, and the seq of each stored per-sample output and window."""
    with db.read() as s:
        mark = int(s.scalar(select(Stream.last_applied_seq).where(Stream.actuator_pk == pk)))  # type: ignore[arg-type]
        outs = list(s.scalars(select(SampleOutputRow.seq).where(SampleOutputRow.actuator_pk == pk)
                              .order_by(SampleOutputRow.id)))
        wins = list(s.scalars(select(HealthWindowRow.seq).where(HealthWindowRow.actuator_pk == pk)
                              .order_by(HealthWindowRow.id)))
    return mark, outs, wins


def test_rows_changed_since_the_computation_are_applied_again_not_twice(api_noproc: Api, db_url: str) -> None:
    """Another worker applies the stream between this one's computation and its store: the
    store sees rows other than those it computed from and applies the next batch instead."""
    api_noproc.log_series("N1", "raced", 2, BATCH, seed=5)
    db = Database(db_url)
    pk = actuator_pk(db, "raced")
    processor = Processor(db, make_settings(db_url, processor_max_batches_per_txn=1))
    limits = {"max_batches": 1, "store_outputs": True, "is_sqlite": db.is_sqlite}
    with db.read() as rs:
        prepared = service.prepare_apply(rs, pk, max_samples=10**6, **limits)
    assert prepared is not None and prepared.result.last_applied_seq == 1
    with db.write() as s:  # the other worker, first to store batch 1
        other = service.apply_pending(s, pk, max_samples=10**6, **limits)
    assert other is not None and other.last_applied_seq == 1
    with db.write() as s:
        current = service.load_current(s, [pk], is_sqlite=db.is_sqlite)
        assert not service.still_current(prepared, current)
        results = processor._store(s, [prepared], [], True, current)
    assert [r.last_applied_seq for r in results] == [2]
    mark, outs, wins = _applied(db, pk)
    db.dispose()
    assert mark == 2
    assert outs == [1, 2]  # each batch's outputs once
    assert wins == [1, 2]


def test_unchanged_rows_are_stored_as_computed(api_noproc: Api, db_url: str) -> None:
    """Nothing happened between computation and store: the prepared apply is what is stored,
    the same as one transaction doing both."""
    api_noproc.log_series("N1", "calm", 2, BATCH, seed=5)
    db = Database(db_url)
    pk = actuator_pk(db, "calm")
    limits = {"max_batches": 1, "store_outputs": True, "is_sqlite": db.is_sqlite}
    with db.read() as rs:
        prepared = service.prepare_apply(rs, pk, max_samples=10**6, **limits)
    assert prepared is not None
    with db.write() as s:
        assert service.still_current(prepared, service.load_current(s, [pk], is_sqlite=db.is_sqlite))
        service.store_apply(s, prepared)
    with db.write() as s:
        service.apply_pending(s, pk, max_samples=10**6, **limits)
    mark, outs, wins = _applied(db, pk)
    db.dispose()
    assert (mark, outs, wins) == (2, [1, 2], [1, 2])


@pytest.mark.parametrize("last_size", [None, 1], ids=["size-unknown", "last-apply-small"])
def test_estimators_run_while_another_writer_holds_the_lock(
    api_noproc: Api, db_url: str, monkeypatch: pytest.MonkeyPatch, last_size: int | None
) -> None:
    """SQLite: the processor computes an apply without the write lock, so a log commit (here:
    any writer holding the lock) does not wait for the estimators, only for the store; also
    for a stream whose last apply was small (that one would run inside the lock were it free)."""
    db = Database(db_url)
    if not db.is_sqlite:
        db.dispose()
        pytest.skip("PostgreSQL applies under the streams' row locks; its writers do not share one lock")
    api_noproc.log_series("N1", "busy", 1, BATCH, seed=5)
    pk = actuator_pk(db, "busy")
    assert api_noproc.app.state.kernels_warm.wait(300)
    fakf = ESTIMATORS["fakf"]
    real_step = fakf.step
    stepped = threading.Event()

    def step(cfg, state, batch):  # type: ignore[no-untyped-def]
        stepped.set()
        return real_step(cfg, state, batch)

    monkeypatch.setattr(fakf, "step", step)
    processor = Processor(db, make_settings(db_url))
    if last_size is not None:
        processor._sizes[pk] = last_size
    holder = db.write()
    session = holder.__enter__()
    session.connection()  # BEGIN IMMEDIATE: the file's write lock, and the process's mutex
    worker = threading.Thread(target=processor.apply_streams, args=([pk],))
    worker.start()
    try:
        ran_while_locked = stepped.wait(60)
    finally:
        holder.__exit__(None, None, None)
    worker.join(60)
    mark, outs, _ = _applied(db, pk)
    db.dispose()
    assert ran_while_locked
    assert not worker.is_alive()
    assert (mark, outs) == (1, [1])


def _stored(db: Database, pk: int) -> tuple[int, list[tuple[int, bytes]], list[tuple[int, object]], bytes | None]:
    """Everything an apply stores for a stream, for comparing two streams fed the same series."""
    with db.read() as s:
        mark = int(s.scalar(select(Stream.last_applied_seq).where(Stream.actuator_pk == pk)))  # type: ignore[arg-type]
        outs = [(r.seq, r.payload) for r in s.scalars(
            select(SampleOutputRow).where(SampleOutputRow.actuator_pk == pk).order_by(SampleOutputRow.id))]
        wins = [(r.seq, r.indicators) for r in s.scalars(
            select(HealthWindowRow).where(HealthWindowRow.actuator_pk == pk).order_by(HealthWindowRow.id))]
        state = s.scalar(select(EstimatorState.state).where(EstimatorState.actuator_pk == pk))
    return mark, outs, wins, state


def test_small_applies_with_the_lock_free_take_one_transaction_and_store_the_same(
    api_noproc: Api, db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SQLite: once a stream's applies are known to be small and nobody waits for the write
    lock, an apply is one write transaction (not a read transaction and a write transaction);
    what it stores is bit for bit what applies computed outside the lock store."""
    db = Database(db_url)
    if not db.is_sqlite:
        db.dispose()
        pytest.skip("PostgreSQL applies in one transaction under the streams' row locks anyway")
    n, size = 12, 10
    api_noproc.log_series("N1", "inlock", n, size, seed=5)
    api_noproc.log_series("N1", "outside", n, size, seed=5)
    pk_in, pk_out = actuator_pk(db, "inlock"), actuator_pk(db, "outside")
    settings = make_settings(db_url, processor_max_batches_per_txn=1)
    begins: list[str] = []
    event.listen(db.engine, "begin", lambda conn: begins.append("begin"))

    def transactions_of_one_apply(processor: Processor, pk: int) -> int:
        begins.clear()
        assert processor._apply_group([pk], {})[1] == 1
        return len(begins)

    in_lock = Processor(db, settings)
    counts_in = [transactions_of_one_apply(in_lock, pk_in) for _ in range(n)]
    monkeypatch.setattr(processor_module, "IN_LOCK_MAX_SAMPLES", 0)  # always computed outside
    outside = Processor(db, settings)
    counts_out = [transactions_of_one_apply(outside, pk_out) for _ in range(n)]
    got_in, got_out = _stored(db, pk_in), _stored(db, pk_out)
    db.dispose()
    assert counts_in == [2] + [1] * (n - 1)  # the first apply's size is not known yet
    assert counts_out == [2] * n
    assert got_in[0] == got_out[0] == n
    assert [seq for seq, _ in got_in[1]] == list(range(1, n + 1))  # each batch once, in order
    assert got_in[1:] == got_out[1:]  # outputs, windows and the state, bit for bit


def test_a_larger_batch_after_small_ones_is_computed_outside_the_lock(api_noproc: Api, db_url: str) -> None:
    """SQLite: a stream whose last apply was small sends a larger batch: the one-transaction
    path finds it over the bound and writes nothing, and the batch is computed outside the lock
    and applied once."""
    db = Database(db_url)
    if not db.is_sqlite:
        db.dispose()
        pytest.skip("PostgreSQL applies in one transaction under the streams' row locks anyway")
    api_noproc.log_series("N1", "grows", 1, BATCH, seed=5)  # one batch of BATCH samples, above the bound
    pk = actuator_pk(db, "grows")
    processor = Processor(db, make_settings(db_url))
    processor._sizes[pk] = 1  # as if its last apply had been one sample
    begins: list[str] = []
    event.listen(db.engine, "begin", lambda conn: begins.append("begin"))
    assert processor._apply_group([pk], {})[1] == 1
    transactions = len(begins)
    mark, outs, _ = _applied(db, pk)
    db.dispose()
    assert transactions == 3  # the write transaction left empty, then the read and the store
    assert (mark, outs) == (1, [1])
    assert processor._sizes[pk] == BATCH
