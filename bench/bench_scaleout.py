"""Scale-out on PostgreSQL: one-sample POSTs through N API processes with M ``fleethealth worker``
processes, against one ``fleethealth serve`` that applies in-process, on the same machine.

For each topology ``AxW`` (A API processes, W workers; ``1x0`` is one server with its own
processor) a fresh PostgreSQL schema is migrated, the processes are started on 127.0.0.1,
``--clients`` actuators are registered, and every client sends ``--per-client`` one-sample POSTs
over its own kept-alive connection (the lean load client, ``bench/http_load.py``), the clients
dealt round-robin over the API processes. The clock runs from the first request until the last
answer (requests/s, latency) and on until every sample is applied (``applied/s``: polled through
the first API process, whose reads reach every worker's commits).

CPU (user + system, ``/proc``) is summed per role over the load and apply: the API processes, the
workers, and PostgreSQL's own processes (every process named ``postgres`` on this machine: run it
where nothing else uses that server). Transactions are PostgreSQL's ``xact_commit`` count of the
database over the same span (``pg_stat_database``, which the statistics collector updates about
every half second: read after a pause, so it counts every commit of the case).

Usage::

    .venv/bin/python bench/bench_scaleout.py --pg postgresql+psycopg://postgres@127.0.0.1:5432/test \\
        [--topologies 1x0 1x1 2x2] [--clients 32] [--per-client 100]

Figures are printed; nothing is asserted. All processes share this machine's cores with the load
clients and PostgreSQL, so what a topology gains is bounded by the cores it is given.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from sqlalchemy import create_engine, text

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import http_load  # noqa: E402
from bench_ingest import (  # noqa: E402
    Server,
    _one_sample,
    _post,
    fleethealth_exe,
    running_server,
    tree_cpu_s,
)
from fleethealth_client import FleetHealthClient  # noqa: E402

TAIL = "SCALE"
WARM_UP_POSTS = 20


@contextmanager
def fresh_schema(pg_url: str) -> Iterator[str]:
    """A new schema in the PostgreSQL database (dropped afterwards); the URL that uses it."""
    schema = "bench_" + uuid.uuid4().hex[:10]
    engine = create_engine(pg_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as c:
        c.execute(text(f'CREATE SCHEMA "{schema}"'))
    sep = "&" if "?" in pg_url else "?"
    try:
        yield f"{pg_url}{sep}options=-csearch_path%3D{schema}"
    finally:
        with engine.connect() as c:
            c.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        engine.dispose()


@contextmanager
def running_worker(db_url: str, log_path: Path, timeout_s: float) -> Iterator[subprocess.Popen[bytes]]:
    env = {**os.environ, "FLEETHEALTH_DATABASE_URL": db_url}
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([fleethealth_exe(), "worker"], env=env, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            deadline = time.monotonic() + timeout_s
            while b"fleethealth worker" not in log_path.read_bytes():
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit(f"worker not ready; log:\n{log_path.read_text(errors='replace')[-3000:]}")
                time.sleep(0.2)
            yield proc
        finally:
            proc.terminate()
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


def postgres_cpu_s() -> float:
    """CPU seconds used so far by every process named ``postgres`` on this machine."""
    total = 0.0
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        with contextlib.suppress(OSError):
            if Path(f"/proc/{pid}/comm").read_text().strip() == "postgres":
                total += tree_cpu_s(int(pid))
    return total


def commits(pg_url: str) -> int:
    engine = create_engine(pg_url)
    try:
        with engine.connect() as c:
            return int(c.execute(text(
                "SELECT xact_commit FROM pg_stat_database WHERE datname = current_database()")).scalar_one())
    finally:
        engine.dispose()


def _load_all(apis: list[Server], per_api: list[list[list[bytes]]], processes: int) -> http_load.LoadResult:
    """Each API process's connections at once (one load run per API process, in threads)."""
    results: list[http_load.LoadResult | BaseException] = [http_load.LoadResult() for _ in apis]

    def run(i: int) -> None:
        host, port = apis[i].url.removeprefix("http://").split(":")
        try:
            results[i] = http_load.run_load(host, int(port), per_api[i], processes)
        except BaseException as exc:  # noqa: BLE001 - reported below
            results[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(apis)) if per_api[i]]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    merged = http_load.LoadResult()
    for r in results:
        if isinstance(r, BaseException):
            raise r
        merged.latencies_s += r.latencies_s
        merged.statuses.update(r.statuses)
        merged.resent += r.resent
        merged.client_cpu_s += r.client_cpu_s
        merged.elapsed_s = max(merged.elapsed_s, r.elapsed_s)
    return merged


def run_topology(pg_url: str, n_api: int, n_workers: int, args: argparse.Namespace, workdir: Path) -> dict[str, float]:
    with fresh_schema(pg_url) as url, ExitStack() as stack:
        api_env = {"FLEETHEALTH_PROCESSOR_ENABLED": "false"} if n_workers else {}
        first = stack.enter_context(running_server(url, workdir, args.ready_timeout_s, extra_env=api_env))
        workers = [stack.enter_context(running_worker(url, workdir / f"worker{k}.log", args.ready_timeout_s))
                   for k in range(n_workers)]
        apis = [first]
        for _ in range(n_api - 1):
            # The same bootstrap key: the first process created it, the others find it.
            env = {**api_env, "FLEETHEALTH_BOOTSTRAP_ADMIN_KEY": first.api_key}
            apis.append(stack.enter_context(running_server(url, workdir, args.ready_timeout_s, extra_env=env)))
        for a in apis[1:]:
            a.api_key = first.api_key
        acts = [f"c{i:03d}" for i in range(args.clients)]
        with FleetHealthClient(first.url, first.api_key) as client:
            client.create_aircraft(TAIL)
            for act in acts:
                client.create_actuator(TAIL, act, kind="ema_voltage")

        def plan(ks: range) -> list[list[list[bytes]]]:
            per_api: list[list[list[bytes]]] = [[] for _ in apis]
            for i, act in enumerate(acts):
                api = apis[i % len(apis)]
                per_api[i % len(apis)].append(
                    [_post(api, f"/v1/aircraft/{TAIL}/actuators/{act}/telemetry", _one_sample(k)) for k in ks])
            return per_api

        def wait_all(n: int) -> None:
            with FleetHealthClient(first.url, first.api_key) as client:
                for act in acts:
                    client.wait_applied(TAIL, act, n, timeout_s=args.timeout_s, poll_s=0.05)

        _load_all(apis, plan(range(WARM_UP_POSTS)), args.load_processes)  # warm-up: every process, every stream
        wait_all(WARM_UP_POSTS)
        per_api = plan(range(WARM_UP_POSTS, WARM_UP_POSTS + args.per_client))
        time.sleep(1.0)
        pids = {"api": [a.process.pid for a in apis], "worker": [w.pid for w in workers]}
        cpu0 = {role: sum(tree_cpu_s(p) for p in ps) for role, ps in pids.items()}
        pg0, tx0 = postgres_cpu_s(), commits(url)
        start = time.perf_counter()
        load = _load_all(apis, per_api, args.load_processes)
        wrong = {s: n for s, n in load.statuses.items() if s != 202}
        if wrong:
            raise SystemExit(f"answered {wrong}: {load.samples}")
        wait_all(WARM_UP_POSTS + args.per_client)
        applied_s = time.perf_counter() - start
        cpu1 = {role: sum(tree_cpu_s(p) for p in ps) for role, ps in pids.items()}
        pg1 = postgres_cpu_s()
        time.sleep(1.0)  # the statistics collector's last report
        tx1 = commits(url)
    n = len(load.latencies_s)
    lat = sorted(load.latencies_s)
    return {
        "requests_per_s": n / load.elapsed_s,
        "median_ms": 1e3 * statistics.median(lat),
        "p99_ms": 1e3 * lat[min(n - 1, int(0.99 * n))],
        "applied_per_s": n / applied_s,
        "api_cpu_ms": 1e3 * (cpu1["api"] - cpu0["api"]) / n,
        "worker_cpu_ms": 1e3 * (cpu1["worker"] - cpu0["worker"]) / n,
        "postgres_cpu_ms": 1e3 * (pg1 - pg0) / n,
        "client_cpu_ms": 1e3 * load.client_cpu_s / n,
        "transactions_per_request": (tx1 - tx0) / n,
        "transactions_per_s": (tx1 - tx0) / applied_s,
        "resent": float(load.resent),
    }


ROWS = (
    ("one-sample POSTs answered per second", "requests_per_s", "{:,.0f}"),
    ("median latency, ms", "median_ms", "{:.2f}"),
    ("p99 latency, ms", "p99_ms", "{:.2f}"),
    ("samples applied per second (to the last apply)", "applied_per_s", "{:,.0f}"),
    ("API processes' CPU per request, ms", "api_cpu_ms", "{:.3f}"),
    ("workers' CPU per request, ms", "worker_cpu_ms", "{:.3f}"),
    ("PostgreSQL's CPU per request, ms", "postgres_cpu_ms", "{:.3f}"),
    ("load clients' CPU per request, ms", "client_cpu_ms", "{:.3f}"),
    ("PostgreSQL commits per request", "transactions_per_request", "{:.3f}"),
    ("PostgreSQL commits per second", "transactions_per_s", "{:,.0f}"),
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pg", required=True, help="PostgreSQL URL (a schema is created and dropped per topology)")
    parser.add_argument("--topologies", nargs="+", default=["1x0", "1x1", "2x2"],
                        help="AxW: A API processes, W workers (W=0: the API process applies)")
    parser.add_argument("--clients", type=int, default=32)
    parser.add_argument("--per-client", type=int, default=100)
    parser.add_argument("--load-processes", type=int, default=1, help="load client processes per API process")
    parser.add_argument("--timeout-s", type=float, default=600.0)
    parser.add_argument("--ready-timeout-s", type=float, default=600.0)
    args = parser.parse_args(argv)
    results: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="fleethealth-scaleout-") as tmp:
        for topo in args.topologies:
            n_api, n_workers = (int(x) for x in topo.lower().split("x"))
            print(f"[{topo}] {n_api} API process(es), {n_workers} worker(s)", flush=True)
            results[topo] = run_topology(args.pg, n_api, n_workers, args, Path(tmp))
            print(f"[{topo}] " + ", ".join(f"{k} {v:.3g}" for k, v in results[topo].items()), flush=True)
    print(f"\nScale-out on PostgreSQL: {args.clients} clients x {args.per_client} one-sample POSTs, FAKF attached; "
          f"topology AxW = A API processes, W workers (x0: the API process applies)")
    print(f"{'':50s}" + "".join(f"{t:>12s}" for t in results))
    for label, key, fmt in ROWS:
        print(f"{label:50s}" + "".join(f"{fmt.format(r[key]):>12s}" for r in results.values()))
    print(f"machine: {os.cpu_count()} cores shared by every process above, the load clients and PostgreSQL")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
