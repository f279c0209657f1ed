"""The parts of SQLite's apply process that a live server does not single out: the write lock
across processes and the merge of the child's metrics (the process itself:
tests/e2e/test_apply_process.py)."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

from prometheus_client.metrics_core import Metric
from prometheus_client.samples import Sample
from sqlalchemy import text

from app.db import Database
from app.processing.apply_process import merged_families

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
