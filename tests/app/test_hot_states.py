"""Estimator states held in memory between applies (app.processing.hot): used only when the row
holds exactly the bytes they came from, and then the outputs are those of a state read from
the store, bit for bit."""

from __future__ import annotations

from typing import Any

import pytest
from sqlalchemy import select

from app.db import Database
from app.models import EstimatorState, HealthWindowRow, SampleOutputRow
from app.processing import service
from app.processing.hot import HotStates
from estimators.registry import ESTIMATORS
from tests.app.conftest import Api, actuator_pk

N_BATCHES = 4
BATCH = 600


def _apply_one(db: Database, pk: int, hot: HotStates | None) -> None:
    """Apply the stream's next batch, as one worker's transaction."""
    with db.write() as s:
        res = service.apply_pending(s, pk, max_samples=10**6, max_batches=1, store_outputs=True,
                                    is_sqlite=db.is_sqlite, hot=hot)
    assert res is not None and res.batches == 1


def _outputs(db: Database, pk: int) -> tuple[Any, ...]:
    with db.read() as s:
        state = s.scalar(select(EstimatorState.state).where(EstimatorState.actuator_pk == pk))
        samples = list(s.scalars(select(SampleOutputRow.payload).where(SampleOutputRow.actuator_pk == pk)
                                 .order_by(SampleOutputRow.seq)))
        windows = [(w.seq, w.t_end_s, w.indicators, w.status) for w in s.scalars(
            select(HealthWindowRow).where(HealthWindowRow.actuator_pk == pk).order_by(HealthWindowRow.id))]
    return state, samples, windows


def test_held_state_gives_the_outputs_of_a_stored_one(api_noproc: Api, db_url: str,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """One worker applying batch after batch from its held state (the state is parsed once)
    stores what a worker reading the state from the store each time stores, bit for bit."""
    api_noproc.log_series("N1", "held", N_BATCHES, BATCH, seed=11)
    api_noproc.log_series("N1", "read", N_BATCHES, BATCH, seed=11)
    db = Database(db_url)
    try:
        held, read = actuator_pk(db, "held"), actuator_pk(db, "read")
        for _ in range(N_BATCHES):
            _apply_one(db, read, None)
        hot = HotStates()
        loads = 0
        kind = ESTIMATORS["fakf"]
        real_load = kind.load_state

        def counting_load(data: bytes) -> Any:
            nonlocal loads
            loads += 1
            return real_load(data)

        monkeypatch.setattr(kind, "load_state", counting_load)
        for _ in range(N_BATCHES):
            _apply_one(db, held, hot)
        # The first apply starts from the initial state; the second reads the state it wrote
        # back from the row once (this build's states of the stream are shown to read back);
        # the others step from the held state.
        assert loads == 1 and hot.hits == N_BATCHES - 2
        assert _outputs(db, held) == _outputs(db, read)
    finally:
        db.dispose()


def test_state_applied_elsewhere_is_read_again(api_noproc: Api, db_url: str) -> None:
    """Another process (its own engine) applies a batch in between: the state this process
    holds no longer matches the row, and is not used (stepping from it would skip that batch's
    effect on the state)."""
    api_noproc.log_series("N1", "two", N_BATCHES, BATCH, seed=11)
    api_noproc.log_series("N1", "ref", N_BATCHES, BATCH, seed=11)
    here, elsewhere = Database(db_url), Database(db_url)
    try:
        two, ref = actuator_pk(here, "two"), actuator_pk(here, "ref")
        for _ in range(N_BATCHES):
            _apply_one(elsewhere, ref, None)
        hot = HotStates()
        _apply_one(here, two, None)       # batch 1 here
        _apply_one(here, two, hot)        # batch 2 here, from the row: its new state is held
        _apply_one(elsewhere, two, None)  # batch 3 by the other process
        _apply_one(here, two, hot)        # batch 4 here: the held state is stale
        assert hot.hits == 0 and hot.misses == 2  # batch 2 (nothing held), batch 4 (stale)
        assert len(hot) == 1
        assert _outputs(here, two) == _outputs(here, ref)
    finally:
        here.dispose()
        elsewhere.dispose()


def test_rolled_back_apply_leaves_no_usable_state(api_noproc: Api, db_url: str) -> None:
    """An apply whose transaction rolls back after the state was put: the row still holds the
    old state, the entry does not match it, and the batch is applied again from the row."""
    api_noproc.log_series("N1", "rb", N_BATCHES, BATCH, seed=11)
    api_noproc.log_series("N1", "ref", N_BATCHES, BATCH, seed=11)
    db = Database(db_url)
    try:
        rb, ref = actuator_pk(db, "rb"), actuator_pk(db, "ref")
        for _ in range(N_BATCHES):
            _apply_one(db, ref, None)
        hot = HotStates()
        _apply_one(db, rb, None)
        _apply_one(db, rb, hot)  # from the row: held
        with pytest.raises(RuntimeError), db.write() as s:
            service.apply_pending(s, rb, max_samples=10**6, max_batches=1, store_outputs=True,
                                  is_sqlite=db.is_sqlite, hot=hot)
            raise RuntimeError("the commit fails")
        assert len(hot) == 1 and hot.hits == 1  # the entry of the rolled-back state (batch 3)
        misses = hot.misses
        _apply_one(db, rb, hot)  # batch 3 again, from the row
        assert hot.misses == misses + 1
        _apply_one(db, rb, hot)  # batch 4, from the held state
        assert hot.hits == 2
        assert _outputs(db, rb) == _outputs(db, ref)
    finally:
        db.dispose()


def test_bounds() -> None:
    hot = HotStates(max_entries=2, max_bytes=10)
    for pk in range(3):
        hot.put(pk, "fakf", b"abc", {}, None, None)
    assert hot.take(2, "fakf", b"abc", {}) is not None
    hot.put(2, "fakf", b"abc", {}, None, None)
    assert len(hot) == 2 and hot.take(0, "fakf", b"abc", {}) is None
    hot.put(9, "fakf", b"0123456789", {}, None, None)
    assert len(hot) == 1
    hot.put(10, "fakf", b"x" * 11, {}, None, None)  # larger than the whole budget: not held
    assert hot.take(10, "fakf", b"x" * 11, {}) is None
    assert hot.take(9, "fakf", b"0123456789", {"a": 1}) is None  # another config
