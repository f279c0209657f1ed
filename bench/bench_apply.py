"""CPU of one apply and of one log commit, in-process, one thread, no contention.

``--streams`` streams (default 1) with the bench's default estimators (``ema_voltage``: FAKF) on
a fresh SQLite file; ``--n`` rounds, each logging one one-sample batch per stream in one commit
of the log writer, then applying them in one apply group of the processor
(``PROCESSOR_MAX_BATCHES_PER_TXN=1``): one stream is one sequential client's POSTs, 32 streams
the rounds of 32 concurrent clients. Prints the thread CPU (user + system) per appended batch
and per applied batch, so the fixed cost of each can be compared between trees.

``--baseline TREE`` runs the same rounds with another source tree's ``app`` (e.g. ``git archive
main | tar -x -C /tmp/base``) in a child process, alternating with this checkout ``--rounds``
times, and prints both side by side (the median of the rounds, with their ratio).

Usage::

    .venv/bin/python bench/bench_apply.py [--n 300] [--streams 1] [--profile] [--baseline TREE --rounds 3]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# --tree (a child measuring another source tree): that tree's packages, not this checkout's.
sys.path.insert(0, sys.argv[sys.argv.index("--tree") + 1] if "--tree" in sys.argv else str(ROOT))

from fastapi.testclient import TestClient  # noqa: E402
from sqlalchemy import select  # noqa: E402

from app.config import Settings  # noqa: E402
from app.db import Database  # noqa: E402
from app.ingest import ParsedBatch  # noqa: E402
from app.main import create_app  # noqa: E402
from app.migrate import upgrade  # noqa: E402
from app.models import Actuator  # noqa: E402
from app.processing.processor import Processor  # noqa: E402
from app.telemetry.writer import LogWriter, _Append  # noqa: E402

KEY = "bench-admin-key-abcdefghijklmnop"


def _batch(k: int, samples: int) -> ParsedBatch:
    t = 1.7e9 + (k * samples + np.arange(samples)) * 0.01
    rng = np.random.default_rng(k)
    return ParsedBatch(f"m{k}", t, {"current": 0.3 + 0.01 * rng.standard_normal(samples),
                                    "voltage": -8.0 + 0.1 * rng.standard_normal(samples)})


def measure(n: int, streams: int, profile: bool, profile_sort: str = "tottime", samples: int = 1,
            apply_process: bool = False) -> tuple[float, float]:
    """CPU ms per appended batch and per applied batch over ``n`` rounds of ``streams`` streams
    of ``samples``-sample batches (``apply_process``: the processor as the SQLite apply process
    runs it: the batches read from the log, computed outside the write lock)."""
    with tempfile.TemporaryDirectory(prefix="fleethealth-bench-apply-") as tmp:
        url = f"sqlite:///{tmp}/apply.db"
        upgrade(url)
        with TestClient(create_app(Settings(database_url=url, bootstrap_admin_key=KEY, processor_enabled=False))) as c:
            h = {"Authorization": f"Bearer {KEY}"}
            assert c.post("/v1/aircraft", json={"tail": "N1"}, headers=h).status_code == 201
            for i in range(streams):
                r = c.post("/v1/aircraft/N1/actuators", json={"actuator_id": f"a{i}", "kind": "ema_voltage"},
                           headers=h)
                assert r.status_code == 201, r.text
        db = Database(url)
        with db.read() as s:
            pks = [int(pk) for pk in s.scalars(select(Actuator.id).order_by(Actuator.id))]
        processor = Processor(db, Settings(database_url=url, processor_max_batches_per_txn=1),
                              in_lock_applies=not apply_process)
        # As in the server: the processor finds the batches its process logged decoded (not the
        # apply process, a process of its own).
        writer = LogWriter(db, recent=None if apply_process else processor.recent)

        def log_round(k: int) -> None:
            writer._write([_Append(pk, _batch(k, samples)) for pk in pks])  # one group, in this thread

        def apply_round() -> None:
            assert processor.apply_streams(pks) == streams

        for k in range(2):  # the first applies parse the states and size the streams
            log_round(k)
            apply_round()
        log_cpu = apply_cpu = 0.0
        prof = cProfile.Profile() if profile else None
        for k in range(2, n + 2):
            t0 = time.thread_time()
            log_round(k)
            t1 = time.thread_time()
            if prof:
                prof.enable()
            apply_round()
            if prof:
                prof.disable()
            log_cpu += t1 - t0
            apply_cpu += time.thread_time() - t1
        db.dispose()
    if prof:
        pstats.Stats(prof).sort_stats(profile_sort).print_stats(40)
    return 1e3 * log_cpu / (n * streams), 1e3 * apply_cpu / (n * streams)


def _child(tree: str, n: int, streams: int, extra: list[str]) -> tuple[float, float]:
    env = {**os.environ, "PYTHONPATH": tree}
    out = subprocess.run([sys.executable, __file__, "--n", str(n), "--streams", str(streams), *extra, "--json",
                          "--tree", tree],
                         env=env, cwd=tree, capture_output=True, text=True, check=True).stdout
    figures = json.loads(out.strip().splitlines()[-1])
    return figures["log_ms"], figures["apply_ms"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=300, help="rounds")
    parser.add_argument("--streams", type=int, default=1)
    parser.add_argument("--samples", type=int, default=1, help="samples per batch")
    parser.add_argument("--apply-process", action="store_true",
                        help="the processor as SQLite's apply process runs it (batches read from the log, "
                             "computed outside the write lock)")
    parser.add_argument("--profile", nargs="?", const="tottime", help="print a cProfile of the applies, "
                        "sorted by this column (tottime, cumulative)")
    parser.add_argument("--baseline", help="another source tree, measured side by side")
    parser.add_argument("--rounds", type=int, default=3, help="alternations with --baseline")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--tree", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.json:
        log_ms, apply_ms = measure(args.n, args.streams, False, samples=args.samples,
                                   apply_process=args.apply_process)
        print(json.dumps({"log_ms": log_ms, "apply_ms": apply_ms}))
        return 0
    if not args.baseline:
        log_ms, apply_ms = measure(args.n, args.streams, bool(args.profile), args.profile or "tottime",
                                   args.samples, args.apply_process)
        print(f"{args.streams} stream(s), {args.samples}-sample batches, {args.n} rounds"
              + (", as the apply process" if args.apply_process else ""))
        print(f"log commit, per appended batch: {log_ms:.3f} ms CPU")
        print(f"apply, per applied batch:       {apply_ms:.3f} ms CPU")
        return 0
    base: list[tuple[float, float]] = []
    new: list[tuple[float, float]] = []
    extra = ["--samples", str(args.samples)] + (["--apply-process"] if args.apply_process else [])
    for _ in range(args.rounds):
        base.append(_child(str(Path(args.baseline).resolve()), args.n, args.streams, extra))
        new.append(_child(str(ROOT), args.n, args.streams, extra))
    print(f"{args.streams} stream(s), {args.samples}-sample batches, {args.n} rounds"
          + (", as the apply process" if args.apply_process else "")
          + f"; median of {args.rounds} alternations")
    print(f"{'ms CPU':34s} {'baseline':>9s} {'this tree':>9s} {'ratio':>6s}")
    for i, name in enumerate(("log commit, per appended batch", "apply, per applied batch")):
        b = statistics.median(f[i] for f in base)
        m = statistics.median(f[i] for f in new)
        print(f"{name:34s} {b:9.3f} {m:9.3f} {m / b:6.2f}")
        print(f"{'  (each round)':34s} {' '.join(f'{f[i]:.3f}' for f in base)} | {' '.join(f'{f[i]:.3f}' for f in new)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
