"""Cross-process wake-ups: PostgreSQL LISTEN/NOTIFY against NATS, as fleethealth would use them.

Measured on loopback, one notification per committed transaction (what the log writer and the
processor send):

* ``notify``: a transaction that updates a row and calls ``pg_notify`` in it, committed; the clock
  runs from just before the commit until a listener on another connection has the notification;
* ``commit only``: the same transaction without the notification (what NOTIFY adds to a commit);
* ``nats``: the same transaction committed, then a NATS publish; the clock runs from just before
  the commit until a NATS subscriber has the message (the dual write a broker would need).

Usage::

    .venv/bin/python bench/bench_wakeups.py [--pg URL] [--nats nats://127.0.0.1:4222] [-n 500]

NATS needs ``pip install nats-py`` (not a dependency of the service). Figures are printed.
"""

from __future__ import annotations

import argparse
import asyncio
import threading
import time

import numpy as np
import psycopg

CHANNEL = "fleethealth_bench_wakeups"


def _setup(url: str) -> None:
    with psycopg.connect(url, autocommit=True) as c:
        c.execute("CREATE TABLE IF NOT EXISTS bench_wakeups (id int PRIMARY KEY, n bigint)")
        c.execute("INSERT INTO bench_wakeups VALUES (1, 0) ON CONFLICT DO NOTHING")


def pg_notify(url: str, n: int, with_notify: bool) -> np.ndarray:
    got = threading.Event()
    stop = threading.Event()
    listening = threading.Event()

    def listen() -> None:
        with psycopg.connect(url, autocommit=True) as c:
            c.execute(f"LISTEN {CHANNEL}")
            listening.set()
            while not stop.is_set():
                for _ in c.notifies(timeout=0.2):
                    got.set()

    th = threading.Thread(target=listen, daemon=True)
    th.start()
    listening.wait(10)
    lat = []
    with psycopg.connect(url) as c:
        for k in range(n):
            got.clear()
            c.execute("UPDATE bench_wakeups SET n = n + 1 WHERE id = 1")
            if with_notify:
                c.execute("SELECT pg_notify(%s, %s)", (CHANNEL, f"o {k}"))
            t0 = time.perf_counter()
            c.commit()
            if with_notify:
                got.wait(5)
            lat.append(time.perf_counter() - t0)
    stop.set()
    th.join(2)
    return np.asarray(lat)


def nats_after_commit(url: str, nats_url: str, n: int) -> np.ndarray:
    import nats

    async def run() -> list[float]:
        nc = await nats.connect(nats_url)
        got = asyncio.Event()

        async def on_msg(_msg: object) -> None:
            got.set()

        await nc.subscribe("fleethealth.bench.wakeups", cb=on_msg)
        await nc.flush()
        lat = []
        with psycopg.connect(url) as c:
            for k in range(n):
                got.clear()
                c.execute("UPDATE bench_wakeups SET n = n + 1 WHERE id = 1")
                t0 = time.perf_counter()
                c.commit()
                await nc.publish("fleethealth.bench.wakeups", f"o {k}".encode())
                await asyncio.wait_for(got.wait(), 5)
                lat.append(time.perf_counter() - t0)
        await nc.close()
        return lat

    return np.asarray(asyncio.run(run()))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pg", default="postgresql://postgres@127.0.0.1:5432/test")
    ap.add_argument("--nats", default="nats://127.0.0.1:4222")
    ap.add_argument("-n", type=int, default=500)
    args = ap.parse_args()
    _setup(args.pg)
    rows = [
        ("commit only", pg_notify(args.pg, args.n, with_notify=False)),
        ("commit + NOTIFY, until heard", pg_notify(args.pg, args.n, with_notify=True)),
    ]
    try:
        rows.append(("commit, NATS publish, until heard", nats_after_commit(args.pg, args.nats, args.n)))
    except Exception as exc:  # no nats-py or no server: say so
        print(f"NATS not measured: {type(exc).__name__}: {exc}")
    print(f"\n{'case':<38}{'median ms':>12}{'p99 ms':>10}")
    for name, lat in rows:
        print(f"{name:<38}{np.median(lat) * 1e3:>12.3f}{np.percentile(lat, 99) * 1e3:>10.3f}")
    with psycopg.connect(args.pg, autocommit=True) as c:
        c.execute("DROP TABLE bench_wakeups")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
