"""CPU of one apply and of one log commit, in-process, one thread, no contention.

A stream with the bench's default estimators (``ema_voltage``: FAKF) on a fresh SQLite file;
``--n`` one-sample batches are logged one commit each through the log writer, then applied one
batch per apply group by the processor (``PROCESSOR_MAX_BATCHES_PER_TXN=1``), as one sequential
client's POSTs are. Prints the thread CPU (user + system) per log commit and per apply, so the
fixed cost of one round of each can be compared between trees (run it in each checkout).

Usage::

    .venv/bin/python bench/bench_apply.py [--n 300] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from fastapi.testclient import TestClient  # noqa: E402
from sqlalchemy import select  # noqa: E402

from app.config import Settings  # noqa: E402
from app.db import Database  # noqa: E402
from app.ingest import ParsedBatch  # noqa: E402
from app.main import create_app  # noqa: E402
from app.migrate import upgrade  # noqa: E402
from app.models import Actuator  # noqa: E402
from app.processing.processor import Processor  # noqa: E402
from app.telemetry.writer import LogWriter  # noqa: E402

KEY = "bench-admin-key-abcdefghijklmnop"


def _batch(k: int) -> ParsedBatch:
    return ParsedBatch(f"m{k}", np.array([1.7e9 + k * 0.01]), {"current": np.array([0.3]), "voltage": np.array([-8.0])})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=300)
    parser.add_argument("--profile", action="store_true", help="print a cProfile of the applies")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="fleethealth-bench-apply-") as tmp:
        url = f"sqlite:///{tmp}/apply.db"
        upgrade(url)
        with TestClient(create_app(Settings(database_url=url, bootstrap_admin_key=KEY, processor_enabled=False))) as c:
            h = {"Authorization": f"Bearer {KEY}"}
            assert c.post("/v1/aircraft", json={"tail": "N1"}, headers=h).status_code == 201
            r = c.post("/v1/aircraft/N1/actuators", json={"actuator_id": "a", "kind": "ema_voltage"}, headers=h)
            assert r.status_code == 201, r.text
        db = Database(url)
        with db.read() as s:
            pk = int(s.scalar(select(Actuator.id)))  # type: ignore[arg-type]
        writer = LogWriter(db)
        from app.telemetry.writer import _Append

        t0 = time.thread_time()
        for k in range(args.n):
            writer._write([_Append(pk, _batch(k))])  # one group of one append, in this thread
        log_ms = 1e3 * (time.thread_time() - t0) / args.n
        processor = Processor(db, Settings(database_url=url, processor_max_batches_per_txn=1))
        assert processor._apply_group([pk], {})[1] == 1  # the first apply parses the state
        prof = cProfile.Profile() if args.profile else None
        t0 = time.thread_time()
        if prof:
            prof.enable()
        for _ in range(args.n - 1):
            assert processor._apply_group([pk], {})[1] == 1
        if prof:
            prof.disable()
        apply_ms = 1e3 * (time.thread_time() - t0) / (args.n - 1)
        db.dispose()
    print(f"log commit of one one-sample append: {log_ms:.3f} ms CPU")
    print(f"apply of one one-sample batch:       {apply_ms:.3f} ms CPU")
    if prof:
        pstats.Stats(prof).sort_stats("tottime").print_stats(30)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
