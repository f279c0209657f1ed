"""The parts of SQLite's apply process that a live server does not single out: the write lock
across processes and the merge of the child's metrics (the process itself:
tests/e2e/test_apply_process.py)."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import orjson
from prometheus_client.metrics_core import Metric
from prometheus_client.samples import Sample
from sqlalchemy import text

from app.config import Settings
from app.db import Database
from app.processing import wakeups
from app.processing.apply_process import merged_families
from app.processing.processor import Processor
from app.processing.service import ApplyResult
from app.websocket.hub import Hub, StreamMeta

HOLD_LOCK = """
import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
print("held", flush=True)
sys.stdin.read()
"""


def test_a_write_waits_for_another_process_holding_the_write_lock(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'w.db'}"
    db = Database(url)
    with db.write() as s:
        s.execute(text("CREATE TABLE t (x INTEGER)"))
    # Another process holds the lock file only: SQLite itself is not locked at all, so a write
    # that goes through is one that ignored the lock.
    other = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(tmp_path / "w.db.writelock")],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert other.stdout is not None and other.stdout.readline() == b"held\n"
        with db.write_if_free() as s:
            assert s is None  # the other process writes: not free
        wrote = threading.Event()

        def write() -> None:
            with db.write() as s:
                s.execute(text("INSERT INTO t VALUES (1)"))
            wrote.set()

        th = threading.Thread(target=write, daemon=True)
        th.start()
        assert not wrote.wait(0.5)  # blocked while the other process holds the lock
        assert other.stdin is not None
        other.stdin.close()  # it exits: the kernel releases its lock
        other.wait(10)
        assert wrote.wait(10)
        with db.write_if_free() as s:
            assert s is not None
    finally:
        if other.poll() is None:
            other.kill()
        db.dispose()


def test_two_databases_of_one_file_exclude_each_other(tmp_path: Path) -> None:
    """Each ``Database`` holds its own descriptor of the lock file, as each process does."""
    url = f"sqlite:///{tmp_path / 'w.db'}"
    a, b = Database(url), Database(url)
    try:
        with a.write():
            with b.write_if_free() as s:
                assert s is None
            with a.write() as inner:  # re-entrant within the holder's thread
                inner.execute(text("SELECT 1"))
        with b.write_if_free() as s:
            assert s is not None
    finally:
        a.dispose()
        b.dispose()


def _family(name: str, typ: str, samples: list[Sample]) -> Metric:
    fam = Metric(name, "help", typ)
    fam.samples.extend(samples)
    return fam


def test_the_childs_metrics_are_added_to_serves() -> None:
    own = [
        _family("fleethealth_batches_applied", "counter", [
            Sample("fleethealth_batches_applied_total", {}, 0.0),
            Sample("fleethealth_batches_applied_created", {}, 200.0),
        ]),
        _family("fleethealth_thread_cpu_seconds", "counter", [
            Sample("fleethealth_thread_cpu_seconds_total", {"thread": "MainThread"}, 3.0),
        ]),
    ]
    child = [
        ["fleethealth_batches_applied", "counter", "help", [
            ["fleethealth_batches_applied_total", {}, 7.0],
            ["fleethealth_batches_applied_created", {}, 100.0],
        ]],
        ["fleethealth_thread_cpu_seconds", "counter", "help", [
            ["fleethealth_thread_cpu_seconds_total", {"thread": "apply:MainThread"}, 1.5],
        ]],
        ["fleethealth_streams_failed", "gauge", "help", [["fleethealth_streams_failed", {}, 2.0]]],
    ]
    merged = {f.name: {(s.name, tuple(sorted(s.labels.items()))): s.value for s in f.samples}
              for f in merged_families(own, child)}
    assert merged["fleethealth_batches_applied"] == {
        ("fleethealth_batches_applied_total", ()): 7.0,  # summed
        ("fleethealth_batches_applied_created", ()): 100.0,  # the earlier start
    }
    assert merged["fleethealth_thread_cpu_seconds"] == {
        ("fleethealth_thread_cpu_seconds_total", (("thread", "MainThread"),)): 3.0,
        ("fleethealth_thread_cpu_seconds_total", (("thread", "apply:MainThread"),)): 1.5,
    }
    assert merged["fleethealth_streams_failed"] == {("fleethealth_streams_failed", ()): 2.0}


def test_an_apply_is_announced_after_its_results_and_says_they_went_ahead(tmp_path: Path) -> None:
    """The child's side: a watched stream's results are sent first, and its applied mark then
    carries ``"r": 1`` so that ``serve`` does not read them back; others' marks do not."""
    db = Database(f"sqlite:///{tmp_path / 'a.db'}")
    sent: list[tuple[str, Any]] = []
    processor = Processor(
        db, Settings(database_url=db.url), origin="child",
        announce=lambda payloads: sent.extend(("A", orjson.loads(p)) for p in payloads),
        push_results=lambda res: res.actuator_pk == 7 and not sent.append(("R", res.actuator_pk)),
    )
    for pk in (7, 8):
        processor._meta[pk] = StreamMeta(1, "T", f"a{pk}")  # owners known: no read
    try:
        processor._announce([ApplyResult(1, 1, 3, actuator_pk=7), ApplyResult(1, 1, 5, actuator_pk=8)])
    finally:
        db.dispose()
    assert [(kind, body if kind == "R" else (body["pk"], body["seq"], body.get("r"))) for kind, body in sent] == [
        ("R", 7), ("A", (7, 3, 1)), ("A", (8, 5, None))]


def test_serve_wakes_a_streams_connections_only_when_its_results_did_not_come() -> None:
    heard: list[tuple[Any, ...]] = []

    def applied(pk: int, seq: int, events: list[Any], wake: bool) -> None:
        heard.append(("applied", pk, seq, wake))

    def failed(pk: int, reason: str) -> None:
        heard.append(("failed", pk, reason))

    for payload in (
        {"o": "child", "pk": 7, "seq": 3, "ev": [], "r": 1},
        {"o": "child", "pk": 8, "seq": 5, "ev": []},
        {"o": "child", "pk": 9, "failure": "broken"},
        {"o": "serve", "pk": 10, "seq": 1, "ev": []},  # its own: ignored
    ):
        wakeups.dispatch_applied(orjson.dumps(payload), "serve", applied, failed)
    assert heard == [("applied", 7, 3, False), ("applied", 8, 5, True), ("failed", 9, "broken")]


def test_the_hub_says_when_a_stream_gets_its_first_and_loses_its_last_connection() -> None:
    hub = Hub()
    calls: list[tuple[int, bool]] = []
    hub.on_watch = lambda pk, watched: calls.append((pk, watched))

    async def scenario() -> None:
        a = hub.subscribe_stream(7, 4)
        b = hub.subscribe_stream(7, 4)
        assert calls == [(7, True)]
        hub.unsubscribe(a)
        assert calls == [(7, True)]
        hub.unsubscribe(b)
        assert hub.streams() == []

    asyncio.run(scenario())
    assert calls == [(7, True), (7, False)]
